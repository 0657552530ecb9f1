//! The service commands, run as an operator would: the real binary against the embedded
//! emulated drives (default config, `inproc` bus).

use testkit::Out;

fn cncgw(args: &[&str]) -> Out {
    testkit::cli!().run(args)
}

#[test]
fn scan_table_lists_every_configured_node() {
    let o = cncgw(&["scan"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let all: Vec<&str> = o.stdout.lines().collect();
    assert!(all[0].contains("inproc") && all[0].contains("3 node(s)"), "{}", o.stdout);
    assert!(all[1].contains("vendor") && all[1].contains("NMT state") && all[1].contains("heartbeat"));
    // One line per node, then its modes, SYNC, units and error control indented below it.
    let lines: Vec<&str> = all.iter().copied().filter(|l| l.trim_start().starts_with(|c: char| c.is_ascii_digit())).collect();
    // Sorted by node id; identity as the emulator's config gives it.
    assert!(lines[0].trim_start().starts_with("1 x"), "{}", o.stdout);
    assert!(lines[0].contains("SIM-SERVO X") && lines[0].contains("0x00000CA7") && lines[0].contains("0x51000001"));
    assert!(lines[0].contains("0x00020192"), "device type 0x1000 shown: {}", lines[0]);
    assert!(lines[0].contains("pre-operational") && lines[0].trim_end().ends_with("off"), "{}", lines[0]);
    assert!(lines[1].trim_start().starts_with("2 z") && lines[1].contains("SIM-SERVO Z"));
    assert!(lines[2].trim_start().starts_with("3 s1") && lines[2].contains("SIM-SPINDLE S1"));
    let x: Vec<&str> = all[3..7].iter().map(|l| l.trim()).collect();
    assert_eq!(x[0], "modes: PP, HM, CSP, CSV (0x6502 = 0x000001A1); active: no mode (0)", "{}", o.stdout);
    assert_eq!(x[1], "SYNC: consumer (0x1005 = 0x00000080)");
    assert_eq!(x[2], "units: encoder increments (0x608F 100000 inc / 1 rev, 0x6091 gear 1:1, 0x6092 feed 100000 / 1 rev, 0x607E 0x00)");
    assert_eq!(x[3], "error control: heartbeat off; consumes heartbeat (0x1016): none set; node guarding (0x100C/0x100D): off");
}

/// A sim-drives config in a temp file, for `--sim-config`: three drives (X, Z, S1)
/// with `shape` (TOML lines of `[drive.shape]`) on each.
fn shaped(name: &str, shape: &str) -> std::path::PathBuf {
    let mut t = String::new();
    for (node, kind, axis, cpu) in [(1, "linear", "x", 10000.0), (2, "linear", "z", 10000.0), (3, "spindle", "s1", 1000.0)] {
        t.push_str(&format!("[[drive]]\nnode = {node}\nkind = \"{kind}\"\naxis = \"{axis}\"\ncounts_per_unit = {cpu:?}\n[drive.shape]\n{shape}\n"));
    }
    let p = std::env::temp_dir().join(format!("cncgw_cli_diag_{name}_{}.toml", std::process::id()));
    std::fs::write(&p, t).unwrap();
    p
}

#[test]
fn scan_shows_what_start_up_will_check_and_an_unreadable_vendor_as_unreadable() {
    let f = shaped("scan", "boot_mode = 1\nsupported_modes_object = false\nfeed_constant = 10000\nsync_producer = true\nheartbeat_consumer = false\nidentity_subs = 0\npolarity = 0x80");
    let o = cncgw(&["scan", "--sim-config", f.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let all: Vec<&str> = o.stdout.lines().map(|l| l.trim()).collect();
    assert!(all[2].starts_with("1 x     unreadable unreadable unreadable unreadable 0x00020192"), "{}", o.stdout);
    assert_eq!(all[3], "modes: absent; active: PP (profile position)");
    assert_eq!(all[4], "SYNC: PRODUCER (0x1005 = 0x40000080): it sends SYNC itself");
    assert_eq!(all[5], "units: 1 unit = 10 increments (0x608F 100000 inc / 1 rev, 0x6091 gear 1:1, 0x6092 feed 10000 / 1 rev, 0x607E 0x80)");
    assert_eq!(all[6], "error control: heartbeat off; consumes heartbeat (0x1016): absent; node guarding (0x100C/0x100D): off");
    let o = cncgw(&["scan", "--json", "--sim-config", f.to_str().unwrap()]);
    let _ = std::fs::remove_file(&f);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).expect("one JSON document");
    let n1 = &v["nodes"][0];
    assert!(n1["vendor"].is_null() && n1["serial"].is_null(), "unreadable, not 0: {n1}");
    assert!(n1["modes"]["supported"].is_null());
    assert_eq!(n1["modes"]["active"], 1);
    assert_eq!(n1["sync"]["producer"], true);
    assert_eq!(n1["units"]["increments_per_unit"], 10.0);
    assert_eq!(n1["units"]["polarity"], 0x80);
    assert!(n1["error_control"]["consumer_heartbeat"].is_null());
    assert_eq!(n1["error_control"]["guard_time_ms"], 0);
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
    assert_eq!(n1["modes"]["supported"], 0x1A1);
    assert_eq!(n1["modes"]["supported_names"], "PP, HM, CSP, CSV");
    assert_eq!(n1["modes"]["active"], 0);
    assert_eq!(n1["sync"]["producer"], false);
    assert_eq!(n1["units"]["text"], "encoder increments");
    assert_eq!(n1["units"]["encoder"]["increments"], 100_000);
    assert_eq!(n1["error_control"]["consumer_heartbeat"], serde_json::json!([]));
}

#[test]
fn scan_names_a_bus_that_cannot_be_opened() {
    let o = cncgw(&["scan", "--bus", "nosuchcan9"]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("nosuchcan9") && o.stderr.contains("--bus inproc"), "{}", o.stderr);
}

#[test]
fn sdo_read_is_type_aware() {
    let o = cncgw(&["sdo", "read", "1", "0x6041", "0", "--type", "u16"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.stdout.trim(), "node 1 0x6041:00 = 592 (0x0250) [u16]");
    let o = cncgw(&["sdo", "read", "2", "0x1008", "0", "-t", "str"]);
    assert_eq!(o.stdout.trim(), "node 2 0x1008:00 = \"SIM-SERVO Z\" [str]");
    // Without a type: by length.
    let o = cncgw(&["sdo", "read", "0x03", "0x1018", "0x04"]);
    assert_eq!(o.stdout.trim(), "node 3 0x1018:04 = 1358954499 (0x51000003) [u32]");
    // Signed, and JSON.
    let o = cncgw(&["sdo", "read", "1", "0x6064", "0", "--type", "i32", "--json"]);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap();
    assert_eq!(v["value"], 0);
    assert_eq!(v["raw"], "00 00 00 00");
    assert_eq!(v["index"], "0x6064");
    // Wrong type for the object's length: told, not guessed.
    let o = cncgw(&["sdo", "read", "1", "0x1018", "0", "-t", "u16"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("answered 1 byte(s)") && o.stderr.contains("try another --type"), "{}", o.stderr);
}

#[test]
fn sdo_domain_read_to_a_file() {
    let dir = std::env::temp_dir().join(format!("cncgw_cli_diag_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("name.bin");
    let o = cncgw(&["sdo", "read", "1", "0x1008", "0", "--type", "domain", "-o", f.to_str().unwrap()]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(std::fs::read(&f).unwrap(), b"SIM-SERVO X");
    assert!(o.stdout.contains("11 byte(s): 53 49 4D"), "{}", o.stdout);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn sdo_aborts_in_words_with_nonzero_exit() {
    let o = cncgw(&["sdo", "read", "1", "0x1234", "0"]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("0x06020000 object does not exist in the object dictionary"), "{}", o.stderr);
    let o = cncgw(&["sdo", "write", "1", "0x1000", "0", "u32", "5"]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("0x06010002 attempt to write a read only object"), "{}", o.stderr);
}

#[test]
fn sdo_write_parses_and_checks_values() {
    let o = cncgw(&["sdo", "write", "1", "0x1017", "0", "u16", "0x64"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.stdout.trim(), "node 1 0x1017:00 ← 0x64 [u16]: ok");
    let o = cncgw(&["sdo", "write", "1", "0x6065", "0", "u8", "300"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("300 does not fit in u8: range 0…255"), "{}", o.stderr);
    let o = cncgw(&["sdo", "write", "1", "0x607D", "1", "i32", "-5"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    // Motion objects on a real bus need --yes, refused before the bus is opened.
    let o = cncgw(&["sdo", "write", "1", "0x6040", "0", "u16", "0x0F", "--bus", "can7"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("--yes") && o.stderr.contains("can7"), "{}", o.stderr);
    let o = cncgw(&["sdo", "read", "200", "0x1000", "0"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("node id 200 is out of range 1…127"), "{}", o.stderr);
}

#[test]
fn nmt_reset_is_confirmed_by_boot_up() {
    let o = cncgw(&["nmt", "reset-comm", "all"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.starts_with("NMT reset communication → all nodes on inproc"), "{}", o.stdout);
    for n in 1..=3 {
        assert!(o.stdout.contains(&format!("node {n}: now pre-operational")), "{}", o.stdout);
    }
    let o = cncgw(&["nmt", "reset", "2", "--json"]);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap();
    assert_eq!(v["nodes"].as_array().unwrap().len(), 1);
    assert_eq!(v["nodes"][0]["node"], 2);
    assert_eq!(v["nodes"][0]["confirmed"], true);
}

#[test]
fn nmt_reset_of_an_absent_node_fails_with_advice() {
    let o = cncgw(&["nmt", "reset", "9"]);
    assert_eq!(o.code, 1);
    assert!(o.stdout.contains("node 9: no boot-up") && o.stdout.contains("check power and the node id"), "{}", o.stdout);
}

#[test]
fn nmt_start_without_heartbeat_is_reported_unconfirmed() {
    let o = cncgw(&["nmt", "start", "1"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("NMT start → node 1"), "{}", o.stdout);
    assert!(o.stdout.contains("not confirmed: no heartbeat heard"), "{}", o.stdout);
    let o = cncgw(&["nmt", "jump", "1"]);
    assert_eq!(o.code, 2);
}

#[test]
fn drive_status_decodes_the_statusword() {
    let o = cncgw(&["drive", "status", "1"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let s = &o.stdout;
    assert!(s.starts_with("node 1 (axis x): Switch On Disabled"), "{s}");
    assert!(s.contains("statusword 0x6041 = 0x0250"), "{s}");
    assert!(s.contains("bit  4 1 voltage enabled") && s.contains("bit  6 1 switch on disabled") && s.contains("bit  9 1 remote"), "{s}");
    assert!(s.contains("bit  2 0 operation enabled") && s.contains("bit  3 0 fault"), "{s}");
    assert!(s.contains("mode 0x6061 = 0 (no mode)"), "{s}");
    assert!(s.contains("position 0x6064 = 0 counts = 0.0000 mm"), "{s}");
    assert!(s.contains("velocity 0x606C = 0 counts/s"), "{s}");
    assert!(s.contains("following error 0x60F4 = 0 counts"), "{s}");
    assert!(s.contains("error code 0x603F = 0x0000 error reset or no error"), "{s}");
    assert!(s.contains("last EMCY: none heard"), "{s}");
}

#[test]
fn drive_status_json_for_the_spindle() {
    let o = cncgw(&["drive", "status", "3", "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap();
    assert_eq!(v["axis"], "s1");
    assert_eq!(v["state"], "Switch On Disabled");
    assert_eq!(v["statusword"], "0x0250");
    assert_eq!(v["unit"], "deg");
    let bits = v["bits"].as_array().unwrap();
    assert_eq!(bits.len(), 16);
    assert_eq!(bits[6]["name"], "switch on disabled");
    assert_eq!(bits[6]["set"], true);
    assert_eq!(bits[2]["set"], false);
    assert_eq!(v["error_code"], "0x0000");
    assert!(v["last_emcy"].is_null());
}

#[test]
fn completions_and_man_page() {
    let o = cncgw(&["completions", "bash"]);
    assert_eq!(o.code, 0);
    assert!(o.stdout.contains("_cncgw()") && o.stdout.contains("scan") && o.stdout.contains("reset-comm"), "bash script");
    let o = cncgw(&["completions", "zsh"]);
    assert!(o.stdout.starts_with("#compdef cncgw"), "{}", &o.stdout[..o.stdout.len().min(80)]);
    let o = cncgw(&["man"]);
    assert_eq!(o.code, 0);
    assert!(o.stdout.contains(".TH cncgw 1") && o.stdout.contains("scan") && o.stdout.contains("drive"), "man page");
}

#[test]
fn every_service_command_has_an_example_in_its_help() {
    for args in [
        &["scan", "--help"][..],
        &["sdo", "read", "--help"],
        &["sdo", "write", "--help"],
        &["nmt", "--help"],
        &["drive", "status", "--help"],
        &["completions", "--help"],
        &["man", "--help"],
    ] {
        let o = cncgw(args);
        assert_eq!(o.code, 0, "{args:?}");
        assert!(o.stdout.contains("Example: `cncgw"), "{args:?}: {}", o.stdout);
        if args[0] != "completions" && args[0] != "man" {
            assert!(o.stdout.contains("--config") && o.stdout.contains("--bus"), "{args:?}");
        }
    }
}

#[test]
fn od_check_against_an_eds() {
    let eds = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds");
    let o = cncgw(&["od", "check", "2", "--eds", eds]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("node 2 agrees with") && o.stdout.contains("sim_drive.eds"), "{}", o.stdout);
    // A vendor file with an object the drive lacks.
    let bad = std::env::temp_dir().join(format!("cncgw_od_check_{}.eds", std::process::id()));
    let text = std::fs::read_to_string(eds).unwrap() + "\n[2345]\nParameterName=Vendor thing\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\n";
    let line = text.lines().count() - 4;
    std::fs::write(&bad, &text).unwrap();
    let o = cncgw(&["od", "check", "2", "--eds", bad.to_str().unwrap()]);
    let _ = std::fs::remove_file(&bad);
    assert_eq!(o.code, 1, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains(&format!(".eds:{line} [2345] \"Vendor thing\": node 2 does not have 0x2345:00")), "{}", o.stdout);
    assert!(o.stdout.contains("1 disagreement(s)"), "{}", o.stdout);
}
