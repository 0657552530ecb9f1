//! The service commands, run as an operator would: the real binary against the embedded
//! emulated drives (default config, `inproc` bus).

use std::process::Command;

struct Out {
    code: i32,
    stdout: String,
    stderr: String,
}

fn cncgw(args: &[&str]) -> Out {
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw")).args(args).output().expect("run cncgw");
    Out {
        code: o.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
    }
}

#[test]
fn scan_table_lists_every_configured_node() {
    let o = cncgw(&["scan"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let lines: Vec<&str> = o.stdout.lines().collect();
    assert!(lines[0].contains("inproc") && lines[0].contains("3 node(s)"), "{}", o.stdout);
    assert!(lines[1].contains("vendor") && lines[1].contains("NMT state") && lines[1].contains("heartbeat"));
    // Sorted by node id; identity as the emulator's config gives it.
    assert!(lines[2].trim_start().starts_with("1 x"), "{}", o.stdout);
    assert!(lines[2].contains("SIM-SERVO X") && lines[2].contains("0x00000CA7") && lines[2].contains("0x51000001"));
    assert!(lines[2].contains("0x00020192"), "device type 0x1000 shown: {}", lines[2]);
    assert!(lines[2].contains("pre-operational") && lines[2].trim_end().ends_with("off"), "{}", lines[2]);
    assert!(lines[3].trim_start().starts_with("2 z") && lines[3].contains("SIM-SERVO Z"));
    assert!(lines[4].trim_start().starts_with("3 s1") && lines[4].contains("SIM-SPINDLE S1"));
}

#[test]
fn scan_json() {
    let o = cncgw(&["scan", "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).expect("one JSON document");
    assert_eq!(v["bus"], "inproc");
    let nodes = v["nodes"].as_array().unwrap();
    assert_eq!(nodes.len(), 3);
    let n1 = &nodes[0];
    assert_eq!(n1["node"], 1);
    assert_eq!(n1["axis"], "x");
    assert_eq!(n1["vendor"], 0xCA7);
    assert_eq!(n1["serial"], 0x5100_0001u32);
    assert_eq!(n1["device_type"], 0x20192);
    assert_eq!(n1["name"], "SIM-SERVO X");
    assert_eq!(n1["nmt_state"], "pre-operational");
    assert_eq!(n1["nmt_heard"], "boot-up");
    assert_eq!(n1["heartbeat_ms"], 0);
    assert!(n1["error"].is_null());
}

#[test]
fn scan_names_a_bus_that_cannot_be_opened() {
    let o = cncgw(&["scan", "--bus", "nosuchcan9"]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("nosuchcan9") && o.stderr.contains("--bus inproc"), "{}", o.stderr);
}
