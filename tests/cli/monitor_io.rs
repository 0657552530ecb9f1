//! Issue 24: `cncgw monitor` shows the machine's I/O — the safety inputs as the panel shows
//! them, every device's inputs and outputs, each named input and output — in its table and
//! its JSON. The CiA 401 module of config/lathe-io.toml on the embedded bus (E-stop chain and
//! door closed from the start, the chuck not clamped), and sim-drives' emulated Modbus TCP
//! I/O unit (in this process) as a second device; then the same unit beside Modbus drives.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use testkit::Out;

fn tmp(name: &str) -> std::path::PathBuf {
    testkit::tmp!("monitor_io", name)
}

/// A Modbus I/O unit whose discrete input 1 is on from the start.
fn io_unit(stop: &Arc<AtomicBool>) -> sim_drives::modbus_io::IoServer {
    let emu = sim_drives::io401::IoEmulation { inputs_on: vec![1], ..Default::default() };
    sim_drives::modbus_io::serve("127.0.0.1:0", emu, stop.clone()).unwrap()
}

/// `machine` with the Modbus unit `unit2` at `addr`: input 1 `spare_in`, output 0 `spare_out`.
fn with_unit(machine: &str, addr: std::net::SocketAddr, io_names: bool) -> String {
    let dev = format!("\n[io.devices.unit2]\nmodbus = \"{addr}\"\ninputs = 4\noutputs = 4\n");
    if io_names {
        machine
            .replace("turret_in_position = \"io1.3\"\n", "turret_in_position = \"io1.3\"\nspare_in = \"unit2.1\"\n")
            .replace("coolant = \"io1.0\"\n", "coolant = \"io1.0\"\nspare_out = \"unit2.0\"\n")
            + &dev
    } else {
        format!("{machine}\n[io]\n[io.inputs]\nspare_in = \"unit2.1\"\n[io.outputs]\nspare_out = \"unit2.0\"\n{dev}")
    }
}

fn monitor(cfg: &std::path::Path, json: bool) -> Out {
    let c = cfg.to_str().unwrap();
    let mut args = vec!["monitor", "--once", "--config", c];
    if json {
        args.push("--json");
    }
    testkit::cli!().state(tmp("state")).run(&args)
}

#[test]
fn monitor_shows_the_cia401_module_and_a_modbus_unit() {
    let stop = Arc::new(AtomicBool::new(false));
    let unit = io_unit(&stop);
    let cfg = tmp("lathe-io.toml");
    std::fs::write(&cfg, with_unit(include_str!("../../config/lathe-io.toml"), unit.addr, true)).unwrap();

    let o = monitor(&cfg, false);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let t = &o.stdout;
    // The drives' table is still there, then the I/O.
    assert!(t.contains("follow. error") && t.contains("bus inproc load"), "{t}");
    assert!(t.contains("I/O: E-stop ok  door shut  CHUCK OPEN"), "{t}");
    assert!(t.contains("io1        CiA 401 node 10") && t.contains("in 0x00000003  out 0x00000000"), "{t}");
    assert!(t.contains(&format!("unit2      Modbus TCP {} unit 1", unit.addr)) && t.contains("in 0x00000002  out 0x00000000"), "{t}");
    assert!(t.contains("inputs:  chuck_clamped 0  door_closed 1  estop_ok 1  spare_in 1  turret_in_position 0"), "{t}");
    assert!(t.contains("outputs: chuck_clamp 0  coolant 0  spare_out 0  turret_index 0"), "{t}");

    let o = monitor(&cfg, true);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap_or_else(|e| panic!("{e}: {}", o.stdout));
    let io = &v["io"];
    assert_eq!(io["safety"], serde_json::json!({"estop": true, "door": true, "chuck": false}), "{io}");
    assert_eq!(io["inputs"]["estop_ok"], true);
    assert_eq!(io["inputs"]["chuck_clamped"], false);
    assert_eq!(io["inputs"]["spare_in"], true);
    assert_eq!(io["outputs"]["coolant"], false);
    let devs = io["devices"].as_array().unwrap();
    assert_eq!(devs[0], serde_json::json!({"name": "io1", "kind": "cia401", "node": 10, "inputs": 3, "outputs": 0, "error": null}));
    assert_eq!((devs[1]["name"].as_str(), devs[1]["kind"].as_str(), devs[1]["inputs"].as_u64()), (Some("unit2"), Some("modbus_tcp"), Some(2)));
    assert_eq!(v["drives"].as_array().unwrap().len(), 3, "the module is I/O, not a drive: {v}");

    // The unit gone: its bits are unknown (null), the module's still read, and a safety
    // input on it would count as open (as in the cycle loop).
    stop.store(true, Ordering::Relaxed);
    drop(unit);
    std::thread::sleep(std::time::Duration::from_millis(300));
    let o = monitor(&cfg, true);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap_or_else(|e| panic!("{e}: {}", o.stdout));
    assert!(v["io"]["devices"][1]["error"].as_str().is_some_and(|e| !e.is_empty()), "{v}");
    assert_eq!(v["io"]["inputs"]["spare_in"], serde_json::Value::Null, "{v}");
    assert_eq!(v["io"]["inputs"]["estop_ok"], true, "{v}");
}

/// A machine without `[io]`: no I/O lines, `"io": null`.
#[test]
fn monitor_without_io_says_nothing_of_it() {
    let o = testkit::cli!().state(tmp("state")).run(&["monitor", "--once"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(!o.stdout.contains("I/O"), "{}", o.stdout);
    let o = testkit::cli!().state(tmp("state")).run(&["monitor", "--once", "--json"]);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap();
    assert!(v["io"].is_null(), "{v}");
}

/// Modbus drives (the monitor of Modbus drives) with a Modbus I/O unit.
#[test]
fn the_modbus_monitor_shows_a_modbus_unit() {
    let stop = Arc::new(AtomicBool::new(false));
    let unit = io_unit(&stop);
    let lathe = include_str!("../../config/lathe-modbus.toml");
    let drives = sim_drives::SimConfig::from_machine_toml_bus(lathe, Some(true)).unwrap();
    let srv = sim_drives::modbus::serve_tcp("127.0.0.1:0".parse().unwrap(), drives, stop.clone()).unwrap();
    let machine = lathe.replace("address = \"127.0.0.1:5020\"", &format!("address = \"{}\"", srv.local_addr().unwrap()));
    let cfg = tmp("lathe-modbus-io.toml");
    std::fs::write(&cfg, with_unit(&machine, unit.addr, false)).unwrap();
    let o = monitor(&cfg, false);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("I/O: no safety inputs configured") && o.stdout.contains("inputs:  spare_in 1"), "{}", o.stdout);
    let o = monitor(&cfg, true);
    let v: serde_json::Value = serde_json::from_str(o.stdout.trim()).unwrap_or_else(|e| panic!("{e}: {}", o.stdout));
    assert_eq!(v["bus"], "modbus");
    assert_eq!(v["io"]["inputs"]["spare_in"], true, "{v}");
    assert_eq!(v["io"]["outputs"]["spare_out"], false, "{v}");
    stop.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}
