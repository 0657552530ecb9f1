//! Every stop is a controlled stop, against sim-drives as a separate process (issue 19.1 and
//! 19.4), in real time over socketcand on loopback:
//! - a feed-axis fault while the spindle turns (`--fault 1:overcurrent@6000`): the run stops
//!   with the drive's alarm, and half a second after `cncgw run` has exited the spindle stands
//!   still (`cncgw drive status 3 --json` on the same bus) — it used to free-wheel at ≈ 1300 rpm
//!   in Ready to Switch On;
//! - SIGTERM to a batch run: stopped as on reset (alarm 2401 naming SIGTERM), the summary
//!   printed, the trace complete, exit code 3, the spindle at rest.
//!
//! Real time: runs alone (.config/nextest.toml).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use testkit::{bin, Kill};

fn tmp(name: &str) -> PathBuf {
    testkit::tmp!("stop_process", name)
}

/// The default machine with the margins a shared 2-core VM needs in real time (as the other
/// process tests: feedback timeout 300 ms, wider following-error windows).
fn machine() -> PathBuf {
    let lathe = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).unwrap();
    let m = lathe
        .replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 300")
        .replace("following_error = 1.0\n\n[axes.s1]", "following_error = 5.0\n\n[axes.s1]");
    let p = tmp("machine.toml");
    std::fs::write(&p, m).unwrap();
    p
}

fn start_sim(cfg: &Path, faults: &[&str]) -> (Kill, u16) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let log = tmp(&format!("sim-{port}.log"));
    let mut c = Command::new(bin!("sim-drives"));
    c.args(["--config", &cfg.display().to_string(), "--socketcand", &format!("127.0.0.1:{port}")]);
    for f in faults {
        c.args(["--fault", f]);
    }
    let sim = Kill(c.stderr(std::fs::File::create(&log).unwrap()).spawn().unwrap());
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed().as_secs() < 10, "sim-drives did not start: {}", std::fs::read_to_string(&log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(20));
    }
    (sim, port)
}

fn cncgw(args: &[&str], state: &Path) -> Command {
    let mut c = Command::new(bin!("cncgw"));
    c.args(args).env("CNCGW_STATE_DIR", state).env("NO_COLOR", "1");
    c
}

/// The spindle's state and speed as `drive status 3 --json` reads them.
fn spindle_status(cfg: &Path, bus: &str, state: &Path) -> (String, f64) {
    let o = cncgw(&["drive", "status", "3", "--json", "--config", &cfg.display().to_string(), "--bus", bus], state).output().unwrap();
    let t = String::from_utf8_lossy(&o.stdout);
    let v: serde_json::Value = serde_json::from_str(t.trim()).unwrap_or_else(|e| panic!("{e}: {t} {}", String::from_utf8_lossy(&o.stderr)));
    (v["state"].as_str().unwrap_or("").to_string(), v["velocity_per_s"].as_f64().unwrap())
}

#[test]
fn realtime_a_feed_axis_fault_leaves_no_spindle_coasting() {
    let cfg = machine();
    let state = tmp("state-fault");
    let (_sim, port) = start_sim(&cfg, &["1:overcurrent@6000"]);
    let bus = format!("socketcand://127.0.0.1:{port}/can0");
    let program = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc");
    let o = cncgw(&["run", "--batch", "--json", "--config", &cfg.display().to_string(), "--bus", &bus, program], &state).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("alarm 2010") && err.contains("node 1 (axis x)"), "{err}");
    let v: serde_json::Value = serde_json::from_str(String::from_utf8_lossy(&o.stdout).trim()).unwrap();
    assert_eq!(v["rest"]["at_rest"], true, "{v}");
    assert!(v["rest"]["spindle_rpm_at_torque_off"].as_f64().unwrap().abs() < 1.0, "{v}");
    // X braked on its own fault reaction; the spindle and Z came to rest under control.
    assert!(err.contains("the faulted drive braked on its own fault reaction, the others under control"), "{err}");
    assert_eq!(v["rest"]["fault_reaction"], true, "{v}");
    std::thread::sleep(Duration::from_millis(500));
    let (st, vel) = spindle_status(&cfg, &bus, &state);
    eprintln!("spindle 0.5 s after the run: {st}, {vel:.3}°/s");
    assert!(vel.abs() < 6.0, "the spindle turns at {vel}°/s after the run ({st})");
}

#[test]
fn realtime_sigterm_stops_a_batch_run_as_reset() {
    let cfg = machine();
    let state = tmp("state-term");
    let (_sim, port) = start_sim(&cfg, &[]);
    let bus = format!("socketcand://127.0.0.1:{port}/can0");
    let program = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc");
    let trace = tmp("term.csv");
    let child = cncgw(
        &["run", "--batch", "--json", "--config", &cfg.display().to_string(), "--bus", &bus, "--trace", &trace.display().to_string(), program],
        &state,
    )
    .stdout(Stdio::piped())
    .stderr(Stdio::piped())
    .spawn()
    .unwrap();
    std::thread::sleep(Duration::from_millis(4000));
    // SAFETY: a signal to our own child.
    unsafe {
        libc::kill(child.id() as i32, libc::SIGTERM);
    }
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("alarm 2401") && err.contains("SIGTERM"), "{err}");
    let v: serde_json::Value = serde_json::from_str(String::from_utf8_lossy(&o.stdout).trim()).unwrap_or_else(|e| panic!("{e}: no summary"));
    assert_eq!(v["rest"]["at_rest"], true, "{v}");
    // The report says what happened (issue 19.9): the alarm, the blocks done until the stop
    // (not the 27 read ahead), the time until it, not at the program's end.
    assert_eq!(v["alarm"]["number"], cncgw::alarm::RESET, "{v}");
    let blocks = v["blocks"].as_u64().unwrap();
    assert!(blocks > 0 && blocks < 27, "{v}");
    assert!(v["machining_time_s"].as_f64().unwrap() > 1.0, "{v}");
    assert_eq!(v["at_program_end"], false, "{v}");
    // The trace is complete: every line has the header's number of fields.
    let t = std::fs::read_to_string(&trace).unwrap();
    let n = t.lines().next().unwrap().split(',').count();
    assert!(t.lines().count() > 100 && t.lines().all(|l| l.split(',').count() == n), "trace cut");
    assert!(t.ends_with('\n'));
    let (st, vel) = spindle_status(&cfg, &bus, &state);
    assert!(vel.abs() < 6.0, "the spindle turns at {vel}°/s after SIGTERM ({st})");
}
