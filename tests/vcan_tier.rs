//! The vcan tier: `sim-drives --bus vcan0` and `cncgw run --bus vcan0` as two processes
//! talking CANopen over the kernel's SocketCAN. These tests need a `vcan0` interface, so they
//! are `#[ignore]`d in the plain host run; `scripts/test.sh` runs them with `--ignored`
//! through `scripts/run-vcan-tier.sh`, natively where the kernel has vcan and otherwise in a
//! User-Mode Linux guest. With CNCGW_VCAN_REQUIRED=1 a missing vcan0 fails instead of
//! skipping.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod profiles_common;
use profiles_common::{assert_json_at_end_point, machine_for, mixed, relaxed, MIXED_SETS};

fn bin(name: &str) -> PathBuf {
    // sim-drives is another package of the workspace; its binary lands beside ours.
    let cncgw = PathBuf::from(env!("CARGO_BIN_EXE_cncgw"));
    if name == "cncgw" {
        return cncgw;
    }
    cncgw.parent().unwrap().join(name)
}

fn vcan0_present() -> bool {
    Path::new("/sys/class/net/vcan0").exists()
}

fn require_vcan() -> bool {
    if vcan0_present() {
        return true;
    }
    if std::env::var("CNCGW_VCAN_REQUIRED").as_deref() == Ok("1") {
        panic!("CNCGW_VCAN_REQUIRED=1 but there is no vcan0 interface");
    }
    eprintln!("SKIPPED: no vcan0 here; run through scripts/run-vcan-tier.sh");
    false
}

struct Killer(Child);
impl Drop for Killer {
    fn drop(&mut self) {
        // SIGTERM first so that sim-drives can log its shutdown, then make sure.
        unsafe_kill(self.0.id());
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(2) {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn unsafe_kill(pid: u32) {
    let _ = Command::new("kill").arg("-TERM").arg(pid.to_string()).status();
}

fn start_sim() -> Killer {
    start_sim_with(None)
}

/// sim-drives on vcan0 with the drives of `config` (a sim-drives config file), else the
/// default lathe's.
fn start_sim_with(config: Option<&Path>) -> Killer {
    let sim = bin("sim-drives");
    assert!(sim.exists(), "{} is missing: run `cargo build --workspace --bins` first", sim.display());
    let mut cmd = Command::new(&sim);
    if let Some(c) = config {
        cmd.arg("--config").arg(c);
    }
    let child = cmd.args(["--bus", "vcan0"]).stdout(Stdio::inherit()).stderr(Stdio::inherit()).spawn().expect("start sim-drives");
    // Give it time to open the socket; the master resets communication anyway.
    std::thread::sleep(Duration::from_millis(300));
    Killer(child)
}

/// The default machine with the timing tolerances of a kernel that is not real-time
/// (profiles_common::relaxed), as a file.
fn relaxed_config() -> PathBuf {
    let text = std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("config/lathe.toml")).unwrap();
    write_temp("lathe.toml", &relaxed(&text, false))
}

/// `text` in a file of this process's in the temp dir.
fn write_temp(name: &str, text: &str) -> PathBuf {
    let p = std::env::temp_dir().join(format!("cncgw-vcan-{}-{name}", std::process::id()));
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn first_part_runs_over_vcan_against_sim_drives_process() {
    if !require_vcan() {
        return;
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let cfg = relaxed_config();
    let _sim = start_sim();
    let t = Instant::now();
    let out = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["run", "--bus", "vcan0", "--json", "--config"])
        .arg(&cfg)
        .arg(root.join("examples/first_part.nc"))
        .output()
        .expect("run cncgw");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("cncgw run --bus vcan0 took {:.1} s\nstdout: {stdout}\nstderr: {stderr}", t.elapsed().as_secs_f64());
    assert!(out.status.success(), "cncgw run failed: {:?}", out.status);
    assert_json_at_end_point(&stdout);
}

// Issue 21's "done means" in this tier: first_part against every emulated drive profile
// (IP only, fixed mapping, no 0x1016, boots into PP, user units, external SYNC), in two sim-drives
// processes of mixed profiles (profiles_common::MIXED_SETS, also run in simulated time by
// tests/sim/drive_profiles.rs) rather than five: a first_part is ~35 s.

/// first_part with `cncgw -v run --bus vcan0 --json` against sim-drives of `profiles`
/// (X, Z, S1), node 1 producing the SYNC if `external`; the start-up log.
fn first_part_against(profiles: [&str; 3], external: bool) -> String {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let tag = if external { "b" } else { "a" };
    // An external SYNC every 4 ms: the relaxed cycle.
    let sim = write_temp(&format!("sim-{tag}.toml"), &mixed(profiles, external.then_some(4000)).to_commented_toml());
    let base = std::fs::read_to_string(root.join("config/lathe.toml")).unwrap();
    let cfg = write_temp(&format!("lathe-{tag}.toml"), &machine_for(&relaxed(&base, external), profiles));
    let _sim = start_sim_with(Some(&sim));
    let t = Instant::now();
    let out = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .env_remove("RUST_LOG")
        .args(["-v", "run", "--bus", "vcan0", "--json", "--config"])
        .arg(&cfg)
        .arg(root.join("examples/first_part.nc"))
        .output()
        .expect("run cncgw");
    let _ = (std::fs::remove_file(&sim), std::fs::remove_file(&cfg));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    eprintln!(
        "{profiles:?} external SYNC {external}: cncgw run --bus vcan0 took {:.1} s\nstdout: {stdout}\nstderr: {stderr}",
        t.elapsed().as_secs_f64()
    );
    assert!(out.status.success(), "{profiles:?}: cncgw run failed: {:?}", out.status);
    assert_json_at_end_point(&stdout);
    stderr
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn first_part_over_vcan_against_ip_only_fixed_pdo_and_pp_boot_drives() {
    if !require_vcan() {
        return;
    }
    let (profiles, external) = MIXED_SETS[0];
    let err = first_part_against(profiles, external);
    assert!(err.contains("start-up: mode IP (interpolated position) (axes.x.mode = \"ip\")"), "{err}");
    assert!(err.contains("fixed RPDO1 0x202 = [0x6040:00 (16 bit), 0x607A:00 (32 bit)]"), "{err}");
    assert!(err.contains("booted in profile position (1) and switched by 0x6060"), "{err}");
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn first_part_over_vcan_against_drives_without_0x1016_and_one_in_user_units() {
    if !require_vcan() {
        return;
    }
    let (profiles, external) = MIXED_SETS[1];
    let err = first_part_against(profiles, external);
    assert!(err.contains("node guarding (no 0x1016 heartbeat consumer)"), "{err}");
    assert!(err.contains("units: 1 unit = 10 increments"), "{err}");
}

// The external SYNC profile (`bus.sync = "external"`): the second set's drives again, node 1
// producing the SYNC every 4 ms and the master's cycle running on it (as tests/sim/drive_profiles.rs
// does in simulated time). A cycle held up past the next SYNC is caught up, not sent stale
// (tests/sim/late_external_sync.rs); before that it failed here 4 runs of 4 on the spindle's
// following error.
#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn first_part_over_vcan_on_the_sync_drive_1_produces() {
    if !require_vcan() {
        return;
    }
    let (profiles, _) = MIXED_SETS[1];
    let err = first_part_against(profiles, true);
    assert!(err.contains("cycle on the external SYNC") && err.contains("external SYNC heard"), "{err}");
    assert!(err.contains("the drive produces the SYNC the cycle runs on"), "{err}");
    assert!(err.contains("node guarding (no 0x1016 heartbeat consumer)"), "{err}");
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn missing_drive_is_an_alarm_not_a_hang() {
    if !require_vcan() {
        return;
    }
    // No sim-drives on the bus: start-up must fail with the boot-up alarm, quickly.
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let t = Instant::now();
    let out = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["run", "--bus", "vcan0"])
        .arg(root.join("examples/first_part.nc"))
        .output()
        .expect("run cncgw");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("alarm 2001"), "{stderr}");
    assert!(stderr.contains("no boot-up message"), "{stderr}");
    assert!(t.elapsed() < Duration::from_secs(10));
}

// Issue 21 item 8: the CAN controller's error frames, injected on vcan0 as a controller's
// driver sends them (linux/can/error.h), reach the master through CAN_RAW_ERR_FILTER.

fn inject(frames: &[cncgw_bus::can_error::ErrorFrame]) {
    let mut s = cncgw_bus::transport::socketcan::SocketCan::open("vcan0").expect("open vcan0");
    for f in frames {
        s.inject_error(f).expect("inject an error frame on vcan0");
    }
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn monitor_shows_the_controller_state_and_counters_from_error_frames() {
    use cncgw_bus::can_error::{class, crtl, ErrorFrame};
    use std::io::BufRead;
    if !require_vcan() {
        return;
    }
    let _sim = start_sim();
    let mut child = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["monitor", "--bus", "vcan0", "--json", "--seconds", "20", "--interval-ms", "300", "--config"])
        .arg(relaxed_config())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start cncgw monitor");
    let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
    let first: serde_json::Value = serde_json::from_str(&lines.next().expect("a first refresh").unwrap()).unwrap();
    assert_eq!(first["controller"]["state"], "error-active", "{first}");
    assert_eq!(first["controller"]["error_frames"], 0, "{first}");
    inject(&[
        ErrorFrame::new(0, crtl::TX_WARNING, Some((97, 3))),
        ErrorFrame::new(0, crtl::RX_PASSIVE, Some((97, 128))),
        ErrorFrame::new(class::ACK, 0, None),
        ErrorFrame::new(0, crtl::RX_OVERFLOW, None),
    ]);
    let mut last = serde_json::Value::Null;
    for l in lines.by_ref().take(20) {
        last = serde_json::from_str(&l.unwrap()).unwrap();
        if last["controller"]["error_frames"] == 4 {
            break;
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    let c = &last["controller"];
    assert_eq!(c["state"], "error-passive", "{last}");
    assert_eq!((c["tx_errors"].as_u64(), c["rx_errors"].as_u64()), (Some(97), Some(128)), "{last}");
    assert_eq!(
        (c["warnings"].as_u64(), c["passives"].as_u64(), c["no_ack"].as_u64(), c["rx_overflows"].as_u64()),
        (Some(1), Some(1), Some(1), Some(1))
    );
}

#[test]
#[ignore = "needs vcan0: run through scripts/run-vcan-tier.sh (scripts/test.sh does)"]
fn a_controller_going_bus_off_while_running_is_alarm_2023() {
    use cncgw_bus::can_error::{class, crtl, ErrorFrame};
    use std::io::BufRead;
    if !require_vcan() {
        return;
    }
    // A slow feed (5 mm/s) is moving when the bus goes off: a stall of the guest cannot
    // push an axis out of its 1 mm window first (at first_part's 55 mm/s rapid, 40 ms did:
    // alarm 2010 before the bus-off).
    let prog = write_temp("bus-off.nc", "O1\nG21 G98\nG01 X20 F300\nX0\nM30\n");
    let _sim = start_sim();
    let mut child = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["-v", "run", "--bus", "vcan0", "--config"])
        .arg(relaxed_config())
        .arg(prog)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start cncgw run");
    let (tx, rx) = std::sync::mpsc::channel();
    let err = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut all = String::new();
        for l in std::io::BufReader::new(err).lines().map_while(Result::ok) {
            let _ = tx.send(l.clone());
            all.push_str(&l);
            all.push('\n');
        }
        all
    });
    // Once the three drives are configured the cycle runs: then the controller reports trouble.
    let (t, mut configured) = (Instant::now(), 0);
    while t.elapsed() < Duration::from_secs(60) && configured < 3 {
        if let Ok(l) = rx.recv_timeout(Duration::from_secs(1)) {
            configured += l.contains("start-up: mode") as u32;
        }
    }
    std::thread::sleep(Duration::from_millis(1000));
    inject(&[ErrorFrame::new(0, crtl::TX_PASSIVE, Some((130, 0))), ErrorFrame::new(class::BUSOFF, 0, Some((255, 0)))]);
    let status = child.wait().unwrap();
    let stderr = reader.join().unwrap();
    eprintln!("{stderr}");
    assert!(!status.success());
    assert!(stderr.contains("error-passive"), "{stderr}");
    assert!(stderr.contains("alarm 2023") && stderr.contains("went bus-off"), "{stderr}");
}
