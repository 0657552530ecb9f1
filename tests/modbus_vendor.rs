//! cncgw against Modbus drives that behave like drives we did not write (issue 22): sim-drives'
//! Modbus server with its `modbus_quirks` switched on — targets latched at any time, a motor
//! that powers up away from 0, "busy" answers, late answers — over TCP and RTU. Real time:
//! serialized in .config/nextest.toml.

mod procs;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

const MODBUS_LATHE: &str = include_str!("../config/lathe-modbus.toml");

fn tmp(name: &str) -> PathBuf {
    procs::tmp("modbus_vendor", name)
}

fn write(name: &str, s: &str) -> String {
    let p = tmp(name);
    std::fs::write(&p, s).unwrap();
    p.display().to_string()
}

fn cncgw(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", tmp("state")).args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn summary(o: &Output) -> serde_json::Value {
    serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {}", text(o)))
}

/// The drives of `machine` with `quirks(node)` on each, served over TCP on 127.0.0.1.
fn tcp_server(machine: &str, quirks: impl Fn(u8) -> sim_drives::ModbusQuirks, stop: &Arc<AtomicBool>) -> sim_drives::modbus::ModbusServer {
    let mut cfg = sim_drives::SimConfig::from_machine_toml_bus(machine, Some(true)).unwrap();
    for d in &mut cfg.drives {
        d.modbus_quirks = quirks(d.node);
    }
    sim_drives::modbus::serve_tcp("127.0.0.1:0".parse().unwrap(), cfg, stop.clone()).unwrap()
}

/// config/lathe-modbus.toml on `addr`: the shipped link settings and windows.
fn tcp_machine(addr: SocketAddr) -> String {
    MODBUS_LATHE.replace("address = \"127.0.0.1:5020\"", &format!("address = \"{addr}\""))
}

/// X powered up 1.6 mm (16 000 counts) from 0, Z 0.8 mm below: both latch at any time.
fn away_from_zero(node: u8) -> sim_drives::ModbusQuirks {
    sim_drives::ModbusQuirks::realistic(match node {
        1 => 16_000,
        2 => -8_000,
        _ => 0,
    })
}

fn stop(srv: sim_drives::modbus::ModbusServer, flag: &Arc<AtomicBool>) {
    flag.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}

/// Issue 22.1: a drive that takes 0x607A as it stands when it enables must not jump to a
/// stale target (0, its power-on value): the master writes the actual position there first.
#[test]
fn run_enables_without_a_jump_on_a_drive_that_latches_targets_any_time() {
    let flag = Arc::new(AtomicBool::new(false));
    let srv = Arc::new(tcp_server(MODBUS_LATHE, away_from_zero, &flag));
    let cfg = write("latch.toml", &tcp_machine(srv.local_addr().unwrap()));
    // Stand still for 0.3 s, then move X and Z further from 0: any step toward 0 is a jump.
    let prog = write("latch.nc", "O1\nG21\nG98\nG04 X0.3\nG01 X5 Z-1.5 F300\nM30\n");
    let (watch, done) = (srv.clone(), Arc::new(AtomicBool::new(false)));
    let d2 = done.clone();
    let sampler = std::thread::spawn(move || {
        let (mut x_min, mut z_max) = (i64::MAX, i64::MIN);
        while !d2.load(Ordering::Relaxed) {
            x_min = x_min.min(watch.with_drive(1, |d| d.position_unwrapped()).unwrap());
            z_max = z_max.max(watch.with_drive(2, |d| d.position_unwrapped()).unwrap());
            std::thread::sleep(std::time::Duration::from_micros(500));
        }
        (x_min, z_max)
    });
    let o = cncgw(&["run", "--json", "--config", &cfg, &prog]);
    done.store(true, Ordering::Relaxed);
    let (x_min, z_max) = sampler.join().unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert_eq!(summary(&o)["at_program_end"], true, "{t}");
    assert!(x_min >= 16_000 - 2, "X stepped toward its stale target 0: down to {x_min} counts from 16000: {t}");
    assert!(z_max <= -8_000 + 2, "Z stepped toward its stale target 0: up to {z_max} counts from -8000: {t}");
    // X5 diameter = 2.5 mm radius, Z-1.5 mm.
    let x = srv.with_drive(1, |d| d.position_unwrapped()).unwrap();
    let z = srv.with_drive(2, |d| d.position_unwrapped()).unwrap();
    assert!((x - 25_000).abs() <= 1, "x at {x} counts: {t}");
    assert!((z + 15_000).abs() <= 1, "z at {z} counts: {t}");
    let srv = Arc::try_unwrap(srv).ok().unwrap();
    stop(srv, &flag);
}

/// The same for `jog`: the axis moves by what was asked from where it stood, nothing else.
#[test]
fn jog_enables_without_a_jump_on_a_drive_that_latches_targets_any_time() {
    let flag = Arc::new(AtomicBool::new(false));
    let srv = tcp_server(MODBUS_LATHE, away_from_zero, &flag);
    let cfg = write("jog.toml", &tcp_machine(srv.local_addr().unwrap()));
    let o = cncgw(&["jog", "z", "--by", "-0.5", "--speed", "300", "--yes", "--config", &cfg]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let z = srv.with_drive(2, |d| d.position_unwrapped()).unwrap();
    assert!((z - (-13_000)).abs() <= 1, "z at {z} counts (from -8000, by -0.5 mm): {t}");
    // X was enabled too (every drive of the machine is) and did not move.
    let x = srv.with_drive(1, |d| d.position_unwrapped()).unwrap();
    assert!((x - 16_000).abs() <= 1, "x at {x} counts: {t}");
    stop(srv, &flag);
}
