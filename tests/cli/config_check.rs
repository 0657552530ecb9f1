//! `cncgw config check` runs every check `run` runs before it touches a drive, and exits
//! non-zero when `run` would refuse the configuration (issue 19.8): the bus load, the EDS
//! files, parameters this controller does not read (a typo is silently ignored otherwise)
//! or with values out of range, a master heartbeat switched off.

use std::process::{Command, Output};

const LATHE: &str = include_str!("../../config/lathe.toml");

fn check(name: &str, toml: &str) -> (Output, serde_json::Value) {
    let dir = testkit::tmp!("config_check", "");
    let f = dir.join(format!("{name}.toml"));
    std::fs::write(&f, toml).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw")).args(["config", "check", "--json"]).arg(&f).output().unwrap();
    let v = serde_json::from_slice(&o.stdout).unwrap_or(serde_json::Value::Null);
    (o, v)
}

fn refused(name: &str, toml: &str, says: &str) {
    let (o, v) = check(name, toml);
    assert_eq!(o.status.code(), Some(1), "{name}: {v} {}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(v["ok"], false, "{name}: {v}");
    assert!(v.to_string().contains(says), "{name}: {v}");
}

#[test]
fn the_shipped_machine_passes() {
    let (o, v) = check("lathe", LATHE);
    assert_eq!(o.status.code(), Some(0), "{v}");
    assert_eq!(v["ok"], true);
}

#[test]
fn a_bus_over_80_percent_is_refused_as_run_refuses_it() {
    refused("busload", &LATHE.replace("bitrate = 1000000", "bitrate = 125000"), "alarm 2021: bus load");
}

#[test]
fn a_master_heartbeat_switched_off_needs_the_unsafe_key() {
    let off = LATHE.replace("heartbeat_ms = 100", "heartbeat_ms = 0");
    refused("hb0", &off, "bus.heartbeat_ms: 0 switches off");
    let allowed = off.replace("heartbeat_ms = 0", "heartbeat_ms = 0\nunsafe_no_heartbeat = true");
    let (o, v) = check("hb0-allowed", &allowed);
    assert_eq!(o.status.code(), Some(0), "{v}");
}

#[test]
fn unknown_parameters_and_values_out_of_range_are_named() {
    refused("typo", &LATHE.replace("5261 = 200", "5621 = 200"), "parameters.5621: not a parameter this controller reads");
    refused("clamp", &LATHE.replace("6023 = 5000", "6023 = -5000"), "parameters.6023");
}

#[test]
fn an_eds_that_does_not_fit_is_refused_before_run_meets_it() {
    let dir = testkit::tmp!("config_check", "");
    let eds = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds")).unwrap();
    // A drive whose EDS has no following-error window (0x6065): start-up writes one.
    let cut = eds.find("[6065]").unwrap();
    let end = cut + eds[cut..].find("\n\n").unwrap() + 2;
    let bad = format!("{}{}", &eds[..cut], &eds[end..]);
    let path = dir.join("no6065.eds");
    std::fs::write(&path, bad).unwrap();
    let cfg = LATHE.replace("[axes.z]\nkind = \"linear\"", &format!("[axes.z]\nkind = \"linear\"\neds = \"{}\"", path.display()));
    assert!(cfg.contains("no6065.eds"));
    refused("eds", &cfg, "axes.z.eds");
}
