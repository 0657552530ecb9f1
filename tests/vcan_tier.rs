//! The vcan tier: `sim-drives --bus vcan0` and `cncgw run --bus vcan0` as two processes
//! talking CANopen over the kernel's SocketCAN. These tests need a `vcan0` interface, so they
//! are `#[ignore]`d in the plain host run; `scripts/test.sh` runs them with `--ignored`
//! through `scripts/run-vcan-tier.sh`, natively where the kernel has vcan and otherwise in a
//! User-Mode Linux guest. With CNCGW_VCAN_REQUIRED=1 a missing vcan0 fails instead of
//! skipping.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

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
    let sim = bin("sim-drives");
    assert!(sim.exists(), "{} is missing: run `cargo build --workspace --bins` first", sim.display());
    let child = Command::new(&sim).args(["--bus", "vcan0"]).stdout(Stdio::inherit()).stderr(Stdio::inherit()).spawn().expect("start sim-drives");
    // Give it time to open the socket; the master resets communication anyway.
    std::thread::sleep(Duration::from_millis(300));
    Killer(child)
}

/// The default machine with timing tolerances for a kernel that is not real-time.
///
/// Where this tier runs in a User-Mode Linux (or QEMU) guest, the guest's timers were
/// measured 1–18 ms late at p99 under load (scripts/vmrun, notes/vcan-vm.md): a 2 ms cycle
/// with a 30° spindle window and a 20 ms feedback timeout then faults on the scheduler, not on
/// the bus. This tier proves the SocketCAN path between two processes; the timing figures
/// come from the cycle-timing benchmarks. Only three values change: the cycle (4 ms), the
/// spindle's following-error window (90°) and the feedback timeout (100 ms).
fn relaxed_config() -> PathBuf {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("config/lathe.toml")).unwrap();
    let mut out = String::new();
    let mut changed = 0;
    for line in text.lines() {
        let l = if line.starts_with("cycle_ms = ") {
            changed += 1;
            "cycle_ms = 4.0".to_string()
        } else if line.starts_with("feedback_timeout_ms = ") {
            changed += 1;
            "feedback_timeout_ms = 100".to_string()
        } else if line.starts_with("following_error = ") && line.contains("degrees") {
            changed += 1;
            "following_error = 90.0".to_string()
        } else {
            line.to_string()
        };
        out.push_str(&l);
        out.push('\n');
    }
    assert_eq!(changed, 3, "config/lathe.toml changed shape; update relaxed_config()");
    let p = std::env::temp_dir().join(format!("cncgw-vcan-{}.toml", std::process::id()));
    std::fs::write(&p, out).unwrap();
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
    let v: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap_or("")).expect("JSON summary");
    assert_eq!(v["simulated"], false, "this run must be in real time over SocketCAN");
    assert_eq!(v["at_program_end"], true);
    for a in v["axes"].as_array().unwrap() {
        if let Some(end) = a["program_end_counts"].as_i64() {
            let fin = a["final_actual_counts"].as_i64().unwrap();
            assert!((fin - end).abs() <= 1, "axis {} ended at {fin}, program end {end}", a["axis"]);
        }
    }
    assert!(v["moves"].as_u64().unwrap() > 10);
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

// Issue 21: a drive profile (IP only) and an external SYNC over vcan were tried here and
// fail in the User-Mode Linux guest (under host load) on the spindle's following error (0x8611) — with an
// external SYNC a set-point that misses the next SYNC is not taken, and the guest's timers
// are 1–18 ms late at p99 under load; both run over socketcand on the host
// (tests/drive_profiles.rs).

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
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let _sim = start_sim();
    let mut child = Command::new(bin("cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["-v", "run", "--bus", "vcan0", "--config"])
        .arg(relaxed_config())
        .arg(root.join("examples/first_part.nc"))
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
