//! Programs that could never finish are refused before anything moves (issue 19.7): a feed
//! that rounds to zero, G96 with S0 under a per-revolution cut, a C target beyond what the
//! spindle axis resolves, a program that ends without M02/M30 (Fanuc's "end of record",
//! PS5010), an empty file. Each used to run (or hang in a batch run) or exit 0.

use std::process::Command;

fn run(name: &str, text: &str) -> (i32, String, String) {
    let dir = testkit::tmp!("before_motion", "");
    let f = dir.join(format!("{name}.nc"));
    std::fs::write(&f, text).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", dir.join("state"))
        .args(["run", "--batch", "--json"])
        .arg(&f)
        .output()
        .unwrap();
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

fn refused(name: &str, text: &str, alarm: u32, line: Option<u32>) {
    let (code, out, err) = run(name, text);
    assert_eq!(code, 3, "{name}: {err}");
    assert!(err.contains(&format!("alarm {alarm:04}")) && err.contains("nothing was moved"), "{name}: {err}");
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{name}: {e}: {out}"));
    assert_eq!(v["alarm"]["number"], alarm, "{name}: {v}");
    assert_eq!(v["alarm"]["line"].as_u64().map(|l| l as u32), line, "{name}: {v}");
    assert_eq!(v["cycles"], 0, "{name}: nothing ran: {v}");
}

#[test]
fn a_feed_that_rounds_to_zero() {
    refused("feed", "G21\nG98\nG0 X40 Z2\nG1 Z0 F0.0001\nM30\n", 11, Some(4));
    refused("feed-rev", "G21\nG99\nM03 S500\nG0 X40 Z2\nG1 Z0 F0.00001\nM30\n", 11, Some(5));
}

#[test]
fn constant_surface_speed_zero_under_a_per_revolution_cut() {
    refused("css", "G21\nG99\nG96 S0 M03\nG0 X40 Z2\nG1 Z0 F0.2\nM30\n", 2302, Some(5));
}

#[test]
fn a_c_target_beyond_the_axis_resolution() {
    refused("c", "G21\n#1=1000000\n#2=#1*#1*#1\nG0 C#2\nM30\n", 2303, Some(4));
}

#[test]
fn a_program_without_an_end_and_an_empty_one() {
    refused("noend", "G21\nG98\nG0 X40 Z2\n", 5010, Some(3));
    refused("empty", "", 5010, None);
    refused("percent", "%\n", 5010, None);
    // A program that does end runs.
    let (code, _, err) = run("ends", "G21\nG0 X40 Z2\nM30\n");
    assert_eq!(code, 0, "{err}");
}

/// A program that will stop with an alarm at a block — here the Fanuc user alarm
/// `#3000 = k (MESSAGE)` (alarm 3000 + k) — is refused before any motion: the pre-motion pass
/// runs it from the same start and variables, so the run would stop there after moving.
#[test]
fn a_user_alarm_ahead_is_refused_before_motion() {
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("ua.nc");
    std::fs::write(&prog, "G0 X10 Z5\n#1=5\nIF[#1GT3]THEN#3000=12(TOOL 5 IS BROKEN)\nG0 X20\nM30\n").unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", dir.path().join("state"))
        .args(["run", "--batch", "--json"])
        .arg(&prog)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("ua.nc:3:1: alarm 3012: TOOL 5 IS BROKEN") && err.contains("nothing was moved"), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((v["moves"].as_u64(), v["alarm"]["number"].as_u64()), (Some(0), Some(3012)), "{v}");
    // In `plan` the listing stops there with the same alarm.
    // (`plan` reads the stored offsets: never the user's.)
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", dir.path().join("state"))
        .arg("plan")
        .arg(&prog)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("alarm 3012"));
}
