//! A master we did not write: python `canopen` (with python-can's socketcand interface)
//! drives `sim-drives --socketcand` as a separate process (tests/python/canopen_peer.py).
//!
//! Needs the project venv: `scripts/install-test-deps.sh --python` (scripts/test.sh runs it).
//! Without it this test FAILS, naming that command; set CNCGW_SKIP_PYTHON=1 to skip it
//! deliberately.

use std::io::Read;
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[test]
fn python_canopen_master_drives_sim_drives_over_socketcand() {
    if std::env::var("CI").as_deref() != Ok("true") && std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") {
        eprintln!("CNCGW_SKIP_PYTHON=1: python peer test skipped on request");
        return;
    }
    let python = root().join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python` (makes the venv with python-can and canopen), \
         or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );
    let script = root().join("tests/python/canopen_peer.py");

    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    // Its log goes to a file (a pipe nobody reads would fill and stall it).
    let log = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("python_peer_sim_{port}.log"));
    let sim = Command::new(env!("CARGO_BIN_EXE_sim-drives"))
        .args(["--socketcand", &addr])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("sim-drives log file"))
        .spawn()
        .expect("start sim-drives");
    let mut sim = Kill(sim);
    let deadline = Instant::now() + Duration::from_secs(10);
    while TcpStream::connect(&addr).is_err() {
        if let Ok(Some(st)) = sim.0.try_wait() {
            let err = std::fs::read_to_string(&log).unwrap_or_default();
            panic!("sim-drives exited ({st}) before listening on {addr}: {err}");
        }
        assert!(Instant::now() < deadline, "sim-drives does not listen on {addr} after 10 s");
        std::thread::sleep(Duration::from_millis(20));
    }

    let mut py = Command::new(&python)
        .arg(&script)
        .args(["127.0.0.1", &port.to_string()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start python");
    let deadline = Instant::now() + Duration::from_secs(90);
    let status = loop {
        if let Some(st) = py.try_wait().unwrap() {
            break Some(st);
        }
        if Instant::now() > deadline {
            let _ = py.kill();
            let _ = py.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let (mut out, mut err) = (String::new(), String::new());
    if let Some(mut o) = py.stdout.take() {
        let _ = o.read_to_string(&mut out);
    }
    if let Some(mut e) = py.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    println!("{out}");
    let ok = status.is_some_and(|s| s.success());
    let sim_log = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(ok, "python canopen peer failed ({status:?}):\n{out}\n{err}\nsim-drives log ({}):\n{sim_log}", log.display());
    assert!(out.contains("all checks passed"), "{out}");
}
