//! The alarm history (issue 24.7): every alarm of `cncgw run` is appended to the machine's
//! history in its state directory; `cncgw alarms` shows it, as text or JSON, since a time.

fn cncgw(state: &std::path::Path, args: &[&str]) -> std::process::Output {
    testkit::cli!().state(state).output(args)
}

#[test]
fn run_alarms_are_kept_and_shown() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let prog = dir.path().join("ua.nc");
    std::fs::write(&prog, "G0 X10 Z5\n#3000=7(CHUCK NOT CLAMPED)\nM30\n").unwrap();
    let p = prog.to_str().unwrap();
    let empty = cncgw(&state, &["alarms"]);
    assert!(empty.status.success() && String::from_utf8_lossy(&empty.stdout).contains("no alarms recorded"));
    for _ in 0..2 {
        assert_eq!(cncgw(&state, &["run", "--batch", p]).status.code(), Some(3));
    }
    let o = cncgw(&state, &["alarms", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let recs = v.as_array().unwrap();
    assert_eq!(recs.len(), 2, "{v}");
    assert_eq!((recs[0]["number"].as_u64(), recs[0]["line"].as_u64()), (Some(3007), Some(2)));
    assert!(recs[0]["message"].as_str().unwrap().contains("CHUCK NOT CLAMPED"));
    assert!(humantime::parse_rfc3339(recs[0]["time"].as_str().unwrap()).is_ok());
    let text = String::from_utf8_lossy(&cncgw(&state, &["alarms", "--since", "1h"]).stdout).into_owned();
    assert_eq!(text.lines().filter(|l| l.contains("3007") && l.contains("ua.nc:2")).count(), 2, "{text}");
    let later = String::from_utf8_lossy(&cncgw(&state, &["alarms", "--since", "2100-01-01T00:00:00Z"]).stdout).into_owned();
    assert!(later.contains("no alarms recorded"), "{later}");
    assert_eq!(cncgw(&state, &["alarms", "--since", "yesterday"]).status.code(), Some(2));
    // A torn last line (power cut mid-write) is skipped, the rest still read.
    let file = std::fs::read_dir(&state).unwrap().map(|e| e.unwrap().path()).find(|p| p.to_string_lossy().ends_with(".alarms.jsonl")).unwrap();
    let mut f = std::fs::OpenOptions::new().append(true).open(&file).unwrap();
    std::io::Write::write_all(&mut f, b"{\"time\":\"2026-").unwrap();
    let v: serde_json::Value = serde_json::from_slice(&cncgw(&state, &["alarms", "--json"]).stdout).unwrap();
    assert_eq!(v.as_array().unwrap().len(), 2);
}

/// `cncgw alarms --list`: the catalogue a service engineer looks a number up in, without a
/// machine configuration or state.
#[test]
fn list_prints_the_catalogue() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let o = cncgw(&state, &["alarms", "--list", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let entries = v.as_array().unwrap();
    assert_eq!(entries.len(), cncgw::alarm::CATALOGUE.len());
    let estop = entries.iter().find(|e| e["number"] == 2400).expect("2400 listed");
    assert_eq!(estop["name"], "ESTOP");
    assert!(estop["doc"].as_str().unwrap().contains("E-stop"), "{estop}");
    let text = String::from_utf8_lossy(&cncgw(&state, &["alarms", "--list"]).stdout).into_owned();
    let line = text.lines().find(|l| l.trim_start().starts_with("2015 ")).unwrap_or_else(|| panic!("2015 missing:\n{text}"));
    assert!(
        line.contains("STALE_FEEDBACK")
            && line.contains(cncgw::alarm::CATALOGUE.iter().find(|e| e.number == cncgw::alarm::STALE_FEEDBACK).unwrap().doc),
        "{line}"
    );
    assert!(text.contains("2200–2299 Modbus"), "groups are headed:\n{text}");
    assert!(!state.exists(), "--list touches no state");
    assert_eq!(cncgw(&state, &["alarms", "--list", "--since", "8h"]).status.code(), Some(2));
}

#[test]
fn list_into_a_closed_pipe_ends_quietly() {
    // `cncgw alarms --list | head -1`: the reader is gone before the list is written.
    let mut child =
        testkit::cli!().command(&["alarms", "--list"]).stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
}
