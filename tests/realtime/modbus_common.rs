//! What the Modbus drive tests (modbus_run, modbus_maps, modbus_vendor) share: the shipped
//! Modbus machine, scratch files and a state directory of the test binary's own, `cncgw`
//! run there, and sim-drives' Modbus server.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::Output;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

pub const MODBUS_LATHE: &str = include_str!("../../config/lathe-modbus.toml");

/// `name` in the scratch directory of the test binary (named after it, as before).
pub fn tmp(name: &str) -> PathBuf {
    testkit::tmp!(env!("CARGO_CRATE_NAME"), name)
}

/// `s` written to the scratch file `name`; its path.
pub fn write(name: &str, s: &str) -> String {
    let p = tmp(name);
    std::fs::write(&p, s).unwrap();
    p.display().to_string()
}

/// `cncgw args` with the power-off state in the scratch directory.
pub fn cncgw(args: &[&str]) -> Output {
    testkit::cli!().state(tmp("state")).output(args)
}

/// stdout, then stderr.
pub fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// The JSON summary `cncgw run --json` prints.
pub fn summary(o: &Output) -> serde_json::Value {
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", text(o)))
}

/// `machine` with its Modbus link on `addr` instead of the shipped 127.0.0.1:5020.
pub fn on(machine: &str, addr: SocketAddr) -> String {
    machine.replace("address = \"127.0.0.1:5020\"", &format!("address = \"{addr}\""))
}

/// The drives of `machine` with `quirks(node)` on each, served over TCP on 127.0.0.1.
pub fn tcp_server(machine: &str, quirks: impl Fn(u8) -> sim_drives::ModbusQuirks, stop: &Arc<AtomicBool>) -> sim_drives::modbus::ModbusServer {
    let mut cfg = sim_drives::SimConfig::from_machine_toml_bus(machine, Some(true)).unwrap();
    for d in &mut cfg.drives {
        d.modbus_quirks = quirks(d.node);
    }
    sim_drives::modbus::serve_tcp("127.0.0.1:0".parse().unwrap(), cfg, stop.clone()).unwrap()
}
