//! The OPC UA server of `cncgw run` (`[opcua]`), observed by the peer we did not write:
//! python asyncua (tests/python/opcua_client.py) in the project venv. A run of the embedded
//! machine, paced to the wall clock, whose X drive has no torque to spare:
//! the client sees the Z axis move and the state change during the run, and receives the
//! drive's fault (alarm 2010) as an event and as an alarm condition (its number, active,
//! unacknowledged; ConditionRefresh for a client that comes later; no acknowledging; the
//! condition a node it browses to); an unsigned connection, an untrusted client certificate, a
//! wrong password and an unknown X.509 user certificate are refused, the configured one signs
//! in. Without `[opcua]` no port is opened.
//!
//! Needs build/venv with asyncua (`scripts/install-test-deps.sh --python`): without the venv
//! the test FAILS naming that command (as tests/cli/python_drives.rs); a venv without asyncua
//! skips it and says so; CNCGW_SKIP_PYTHON=1 skips it deliberately.
#![cfg(feature = "opcua")]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The venv's python with asyncua, or None (the test is skipped, said why).
fn python() -> Option<PathBuf> {
    if std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") && std::env::var("CI").is_err() {
        eprintln!("CNCGW_SKIP_PYTHON=1: OPC UA client test skipped on request");
        return None;
    }
    let python = root().join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python`, or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );
    let ok = Command::new(&python).args(["-c", "import asyncua"]).stderr(Stdio::null()).status().is_ok_and(|s| s.success());
    if !ok {
        eprintln!(
            "SKIPPED: {} has no asyncua: run `scripts/install-test-deps.sh --python` (or build/venv/bin/pip install asyncua)",
            python.display()
        );
        return None;
    }
    Some(python)
}

/// A free TCP port on loopback (bound and released: good enough for a test).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The embedded machine's emulated drives with an X motor that has almost no torque left over
/// its friction: an X rapid ends in the drive's following-error fault.
const STUCK_X: &str = r#"
[[drive]]
node = 1
kind = "linear"
axis = "x"
counts_per_unit = 10000.0
counts_per_rev = 100000
[drive.physics]
torque_limit = 0.2
coulomb_friction = 0.19

[[drive]]
node = 2
kind = "linear"
axis = "z"
counts_per_unit = 10000.0
counts_per_rev = 100000

[[drive]]
node = 3
kind = "spindle"
axis = "s1"
counts_per_unit = 1000.0
counts_per_rev = 360000
"#;

/// A dwell for the client to connect, a spindle, a Z feed it watches, then an X rapid the
/// stuck drive faults on.
const PROGRAM: &str =
    "%\nO0026 (OPC UA TEST)\nN10 G21 G99 G97\nN20 G04 X15.0\nN30 M03 S600\nN40 G00 Z2\nN50 G01 Z-15 F0.5\nN60 G00 X40\nN70 M30\n%\n";

fn cncgw_hash(password: &str) -> String {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cncgw")).arg("opcua-hash").stdin(Stdio::piped()).stdout(Stdio::piped()).spawn().unwrap();
    use std::io::Write;
    writeln!(c.stdin.take().unwrap(), "{password}").unwrap();
    let o = c.wait_with_output().unwrap();
    assert!(o.status.success());
    String::from_utf8(o.stdout).unwrap().trim().to_string()
}

fn write_setup(dir: &Path, opcua: &str) -> (PathBuf, PathBuf, PathBuf) {
    std::fs::create_dir_all(dir).unwrap();
    let cfg = dir.join("machine.toml");
    std::fs::write(&cfg, format!("{}\n{opcua}", cncgw::config::EMBEDDED_LATHE)).unwrap();
    let sim = dir.join("drives.toml");
    std::fs::write(&sim, STUCK_X).unwrap();
    let prog = dir.join("opcua_test.nc");
    std::fs::write(&prog, PROGRAM).unwrap();
    (cfg, sim, prog)
}

#[test]
fn a_python_client_watches_a_run_and_receives_the_drive_fault_as_an_event() {
    let Some(python) = python() else { return };
    let dir = testkit::tmp!("opcua_server", "watched");
    let port = free_port();
    let hash = cncgw_hash("s3cret-spindle");
    // The X.509 user "cell": its certificate (made by the client script, asyncua's generator)
    // named relative to the configuration file.
    std::fs::create_dir_all(&dir).unwrap();
    let made = Command::new(&python).arg(root().join("tests/python/opcua_client.py")).arg("--user-certs").arg(&dir).output().unwrap();
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let opcua = format!(
        "[opcua]\nenabled = true\nhost = \"127.0.0.1\"\nport = {port}\nlinger_ms = 8000\n[[opcua.users]]\nname = \"mes\"\npassword_hash = \"{hash}\"\n[[opcua.users]]\nname = \"cell\"\ncertificate = \"cell_user.der\"\n"
    );
    let (cfg, sim, prog) = write_setup(&dir, &opcua);
    let state = dir.join("state");
    let run = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--realtime", "--config"])
        .arg(&cfg)
        .arg("--sim-config")
        .arg(&sim)
        .arg(&prog)
        .env("CNCGW_STATE_DIR", &state)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // (It ends by itself: the program stops on the drive's fault.)
    let client = Command::new(&python)
        .arg(root().join("tests/python/opcua_client.py"))
        .args([
            &format!("opc.tcp://127.0.0.1:{port}/"),
            state.join("opcua/pki").to_str().unwrap(),
            dir.to_str().unwrap(),
            "mes",
            "s3cret-spindle",
            "cncgw default lathe (X/Z + Cs spindle)",
        ])
        .output()
        .unwrap();
    let o = run.wait_with_output().unwrap();
    let out = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    let client_err = String::from_utf8_lossy(&client.stderr);
    assert!(client.status.success(), "client failed:\n{client_err}\ncncgw:\n{out}");
    let v: serde_json::Value = serde_json::from_slice(&client.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&client.stdout)));
    eprintln!("{}", serde_json::to_string_pretty(&v).unwrap());
    // Security: what must be refused is.
    assert!(v["none_refused"].is_string(), "an unsigned connection was accepted: {v}");
    assert!(v["untrusted_refused"].is_string(), "an unknown client certificate was accepted: {v}");
    assert_eq!(v["rejected_files"], 1, "the refused certificate was not kept in pki/rejected: {v}");
    assert!(v["wrong_password_refused"].is_string(), "a wrong password was accepted: {v}");
    assert!(v["write_refused"].is_string(), "a write was accepted: {v}");
    // X.509 user identities: the configured certificate signs in, another is refused.
    assert!(v["unknown_user_cert_refused"].as_str().is_some_and(|e| e.contains("BadIdentityTokenRejected")), "{v}");
    assert!(v["cert_user_state"].is_string(), "the configured user certificate was refused: {v}");
    // The address space.
    for child in ["Identification", "Monitoring", "Production", "Axes", "Notification"] {
        assert!(v["machine_children"].as_array().unwrap().iter().any(|c| c == child), "no {child}: {v}");
    }
    assert_eq!(v["axes"], serde_json::json!(["S1", "X", "Z"]));
    assert_eq!(v["identification"]["SoftwareRevision"], env!("CARGO_PKG_VERSION"));
    assert!(v["program"].as_str().unwrap().ends_with("opcua_test.nc"), "{v}");
    // Values change during the run: Z moves through many positions, the state runs then alarms.
    let changes = v["changes"].as_array().unwrap();
    let z: Vec<f64> =
        changes.iter().filter(|c| c["node"].as_str().unwrap().contains("Axes.Z.ActualPosition")).filter_map(|c| c["value"].as_f64()).collect();
    let states: Vec<&str> = changes.iter().filter_map(|c| c["value"].as_str()).collect();
    assert!(z.len() >= 10 && z.iter().any(|p| *p < -10.0), "Z seen at {z:?}");
    assert!(states.contains(&"Running") && states.last() == Some(&"Alarm"), "states seen: {states:?}");
    // The spindle's load: its drive's torque actual 0x6077 (read by SDO), percent of rated.
    let load: Vec<f64> =
        changes.iter().filter(|c| c["node"].as_str().unwrap().contains("Spindle1.Load")).filter_map(|c| c["value"].as_f64()).collect();
    assert!(load.iter().any(|l| *l != 0.0) && load.iter().all(|l| l.abs() <= 300.0), "spindle load seen: {load:?}");
    // The drive's fault arrives as an event with its number and text.
    let ev = v["events"].as_array().unwrap();
    assert_eq!(ev.len(), 1, "{ev:?}");
    assert!(ev[0]["Message"].as_str().unwrap().starts_with("alarm 2010: node 1 (axis x): drive fault"), "{ev:?}");
    assert_eq!((ev[0]["Severity"].as_u64(), ev[0]["SourceName"].as_str()), (Some(800), Some("cncgw default lathe (X/Z + Cs spindle)")), "{ev:?}");
    // Filtered on our condition type, its own field and the condition's state arrive too.
    let typed = v["typed_events"].as_array().unwrap();
    assert_eq!(typed.len(), 1, "{typed:?}");
    let t = &typed[0];
    assert_eq!(t["AlarmNumber"], 2010, "{t}");
    assert!(t["Message"].as_str().unwrap().starts_with("alarm 2010: node 1 (axis x): drive fault"), "{t}");
    assert_eq!(
        (&t["Severity"], &t["ActiveState"], &t["ActiveState/Id"], &t["AckedState/Id"], &t["Retain"]),
        (&800.into(), &"Active".into(), &true.into(), &false.into(), &true.into()),
        "{t}"
    );
    assert_eq!((&t["ConditionName"], &t["NodeId"]), (&"Alarm2010".into(), &"ns=2;s=Machine.Alarm.2010".into()), "{t}");
    // A client that comes after the alarm gets it by ConditionRefresh; acknowledging is refused.
    let late = &v["late"];
    assert_eq!(late["before_refresh"], serde_json::json!([]), "{late}");
    let refreshed = late["refreshed"].as_array().unwrap();
    assert_eq!(refreshed.len(), 1, "{late}");
    assert_eq!(
        (&refreshed[0]["AlarmNumber"], &refreshed[0]["ActiveState/Id"], &refreshed[0]["Retain"]),
        (&2010.into(), &true.into(), &true.into()),
        "{late}"
    );
    assert_ne!(refreshed[0]["EventId"], t["EventId"], "a refresh's event has its own EventId: {late}");
    assert!(late["refresh_bad_subscription"].as_str().is_some_and(|e| e.contains("BadSubscriptionIdInvalid")), "{late}");
    assert!(late["ack_refused"].is_string(), "an acknowledgement was accepted: {late}");
    // The condition is a node: in Notification/Messages, HasCondition from the machine, its
    // state readable.
    let node = &late["condition_node"];
    let cid = "ns=2;s=Machine.Alarm.2010";
    assert_eq!((&node["in_messages"], &node["has_condition"]), (&serde_json::json!([cid]), &serde_json::json!([cid])), "{node}");
    assert_eq!((&node["browse_name"], &node["type"]), (&"2:Alarm2010".into(), &"ns=2;s=CncAlarmConditionType".into()), "{node}");
    assert_eq!(
        (&node["ActiveState"], &node["ActiveState/Id"], &node["AlarmNumber"], &node["Retain"]),
        (&"Active".into(), &true.into(), &2010.into(), &true.into()),
        "{node}"
    );
    assert!(node["Message"].as_str().is_some_and(|m| m.starts_with("alarm 2010: node 1 (axis x): drive fault")), "{node}");
    assert!(out.contains("alarm 2010"), "{out}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Without `[opcua]` (or with `enabled = false`) `cncgw run` opens no listening socket.
#[test]
fn without_the_section_no_port_is_opened() {
    let dir = testkit::tmp!("opcua_server", "closed");
    let (cfg, _, _) = write_setup(&dir, "");
    let prog = dir.join("dwell.nc");
    std::fs::write(&prog, "%\nO0001\nG04 X1.5\nM30\n%\n").unwrap();
    let mut run = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--realtime", "--config"])
        .arg(&cfg)
        .arg(&prog)
        .env("CNCGW_STATE_DIR", dir.join("state"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let pid = run.id();
    let mut listening = Vec::new();
    let mut looked = 0;
    while run.try_wait().unwrap().is_none() {
        listening.extend(listening_sockets(pid));
        looked += 1;
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    assert!(run.wait().unwrap().success());
    assert!(looked >= 5, "the run ended before it could be looked at");
    assert!(listening.is_empty(), "cncgw listened on {listening:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The local addresses `pid` listens on (TCP, v4 and v6): its socket inodes in /proc/PID/fd
/// matched with /proc/net/tcp{,6} rows in state 0A (LISTEN).
fn listening_sockets(pid: u32) -> Vec<String> {
    let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) else { return Vec::new() };
    let inodes: Vec<String> = fds
        .filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter_map(|l| l.to_str()?.strip_prefix("socket:[")?.strip_suffix(']').map(str::to_string))
        .collect();
    let mut found = Vec::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        for row in std::fs::read_to_string(table).unwrap_or_default().lines().skip(1) {
            let f: Vec<&str> = row.split_whitespace().collect();
            if f.len() > 9 && f[3] == "0A" && inodes.iter().any(|i| i == f[9]) {
                found.push(f[1].to_string());
            }
        }
    }
    found
}
