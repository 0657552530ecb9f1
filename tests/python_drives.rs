//! Drives we did not write in Rust: python `canopen` LocalNodes (tests/python/canopen_drive.py)
//! shaped like commercial drives, on a socketcand bus on loopback, driven by `cncgw run
//! examples/first_part.nc` in real time — a second opinion to sim-drives' `[drive.shape]`
//! (tests/startup_shapes.rs). Either the program runs to its end point on the drives' own
//! positions, or it stops before any motion with an alarm that says what the drive is.
//!
//! Needs the project venv (`scripts/install-test-deps.sh --python`); without it this test
//! FAILS naming that command; CNCGW_SKIP_PYTHON=1 skips it deliberately.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A socketcand bus with no emulated drive on it (sim-drives' server as the hub).
fn hub() -> (String, Arc<AtomicBool>, std::thread::JoinHandle<()>) {
    let server = sim_drives::socketcand::SocketcandServer::bind("127.0.0.1:0", "can0").expect("bind");
    let addr = server.local_addr().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let cfg = sim_drives::SimConfig { drives: Vec::new(), step_us: 50 };
    let t = std::thread::spawn(move || {
        let _ = sim_drives::run_realtime(Box::new(server), cfg, s);
    });
    (addr, stop, t)
}

struct Outcome {
    code: i32,
    stdout: String,
    stderr: String,
    /// Per node (1, 2, 3): the python drive's report.
    drives: Vec<serde_json::Value>,
}

/// `cncgw run --batch examples/first_part.nc` against three python drives of `shape`.
fn run(python: &PathBuf, shape: &str) -> Outcome {
    run_cfg(python, shape, |c| c)
}

/// `run` with the machine configuration changed by `edit`.
fn run_cfg(python: &PathBuf, shape: &str, edit: impl Fn(String) -> String) -> Outcome {
    let (addr, stop, hub) = hub();
    let port = addr.rsplit_once(':').unwrap().1.to_string();
    let mut py = Command::new(python)
        .arg(root().join("tests/python/canopen_drive.py"))
        .args(["127.0.0.1", &port, shape])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start python");
    let mut out = BufReader::new(py.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready", "python drives did not start");
    let dir = std::env::temp_dir().join(format!("cncgw_python_drives_{shape}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Python handles every SYNC and PDO in one interpreter: a 5 ms cycle, and feedback may
    // be 100 ms old before it counts as lost.
    let cfg =
        cncgw::config::EMBEDDED_LATHE.replace("cycle_ms = 2.0", "cycle_ms = 5.0").replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 100");
    assert_ne!(cfg, cncgw::config::EMBEDDED_LATHE);
    let cfg = edit(cfg);
    std::fs::write(dir.join("machine.toml"), cfg).unwrap();
    let started = Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--batch", "--bus", &format!("socketcand://{addr}/can0"), "--config"])
        .arg(dir.join("machine.toml"))
        .arg(root().join("examples/first_part.nc"))
        .env("CNCGW_STATE_DIR", &dir)
        .output()
        .expect("run cncgw");
    eprintln!("{shape}: cncgw ran {:.1} s", started.elapsed().as_secs_f64());
    // SAFETY: a signal to our own child process.
    unsafe {
        libc::kill(py.id() as i32, libc::SIGTERM);
    }
    let mut drives = Vec::new();
    for l in out.lines().map_while(Result::ok) {
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&l) {
            drives.push(v);
        }
    }
    let _ = py.wait();
    let mut perr = String::new();
    if let Some(mut e) = py.stderr.take() {
        let _ = std::io::Read::read_to_string(&mut e, &mut perr);
    }
    stop.store(true, Ordering::Relaxed);
    let _ = hub.join();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(drives.len(), 3, "python drives' report missing: {perr}");
    Outcome {
        code: o.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        drives,
    }
}

impl Outcome {
    fn enabled_modes(&self, node: usize) -> Vec<i64> {
        self.drives[node - 1]["enabled_modes"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect()
    }
    fn position(&self, node: usize) -> i64 {
        self.drives[node - 1]["position"].as_i64().unwrap()
    }
    fn nothing_moved(&self) {
        for n in 1..=3 {
            assert!(self.enabled_modes(n).is_empty(), "node {n} was enabled: {:?}", self.drives);
            assert_eq!(self.position(n), 0, "node {n} moved");
        }
    }
}

#[test]
fn realtime_python_drives_shaped_like_commercial_ones() {
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") && !ci {
        eprintln!("CNCGW_SKIP_PYTHON=1: python drives test skipped on request");
        return;
    }
    let python = root().join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python`, or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );

    // Boots in profile position, switches 300 ms and 50 SYNCs after being asked.
    let o = run(&python, "pp_boot");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![8], "node {n} was enabled in another mode than CSP");
    }
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");

    // Positions in µm.
    let o = run(&python, "user_units");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2006: node 1 (axis x): the drive scales positions: 1 position unit = 10 encoder increments"), "{}", o.stderr);
    assert!(o.stderr.contains("Set axes.x.counts_per_unit = 1000"), "{}", o.stderr);
    o.nothing_moved();

    // Produces SYNC itself: named, and nothing reset.
    let o = run(&python, "sync_producer");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2007: node 1 (axis x): the drive produces SYNC itself (0x1005 = 0x40000080"), "{}", o.stderr);
    o.nothing_moved();
    assert!(o.drives.iter().all(|d| d["resets"] == 0), "{:?}", o.drives);

    // No heartbeat consumer, and no remote frames over socketcand for node guarding: runs,
    // and says the drive will not stop by itself if the controller dies.
    let o = run(&python, "no_1016");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("has no heartbeat consumer (0x1016)") && o.stderr.contains("carries no remote frames"), "{}", o.stderr);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000));

    // No 0x6502: the mode is checked in 0x6061.
    let o = run(&python, "no_6502");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000));
}

/// Issue 21: python drives with interpolated position and no CSP, a second opinion to
/// sim-drives' "ip-only" profile: refused in CSP naming the key, run in IP to the end point.
#[test]
fn realtime_python_ip_only_drives() {
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") && !ci {
        eprintln!("CNCGW_SKIP_PYTHON=1: python drives test skipped on request");
        return;
    }
    let python = root().join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python`, or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );
    let o = run(&python, "ip_only");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2005: node 1 (axis x): this drive has no CSP") && o.stderr.contains("set axes.x.mode = \"ip\""), "{}", o.stderr);
    o.nothing_moved();
    let o = run_cfg(&python, "ip_only", |c| {
        let mut c = c;
        for n in 1..=3 {
            c = c.replacen(&format!("\nnode = {n}\n"), &format!("\nnode = {n}\nmode = \"ip\"\n"), 1);
        }
        c
    });
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![7], "node {n} was enabled in another mode than IP");
    }
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");
}
