//! The controller process dies on a Modbus machine: the drives stop by themselves.
//!
//! `sim-drives --modbus-tcp` runs as its own process; `cncgw run` (config/lathe-modbus.toml)
//! feeds Z with the spindle turning and is killed with SIGKILL. cncgw's start-up set each
//! drive's communication timeout (register 23, the Modbus analogue of 0x1016/0x6007): with no
//! write for that long an enabled drive faults (error code 0x8130) and stops. A second Modbus
//! client (this test) reads statusword, position and error code of every unit and times it.
//! (The CANopen case, heartbeat consumer, is in tests/realtime/tap_return_kill.rs.) Real time: runs
//! alone (.config/nextest.toml).

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::{bin, Kill};
use tokio_modbus::prelude::*;

const CYCLE_MS: f64 = 2.0;
/// sim-drives' Cia402 register map (cncgw_bus::modbus::Cia402Map::default()).
const STATUSWORD: u16 = 10;
const COMM_TIMEOUT: u16 = 23;

fn tmp(name: &str) -> PathBuf {
    testkit::tmp!("controller_death", name)
}

/// One reading of a unit: (time, unit, statusword, position counts, error code).
type Reading = (Instant, u8, u16, i64, u16);

#[test]
fn realtime_modbus_drives_stop_when_the_controller_is_killed() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let lathe = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe-modbus.toml")).unwrap();
    // A shared 2-core machine: feedback age and transaction timeout with room for the
    // scheduler (as tests/realtime/modbus_run.rs).
    let machine = lathe
        .replace("address = \"127.0.0.1:5020\"", &format!("address = \"{addr}\""))
        .replace("feedback_timeout_ms = 50", "feedback_timeout_ms = 300")
        .replace("timeout_ms = 20 ", "timeout_ms = 100 ");
    let cfg = tmp("modbus.toml");
    std::fs::write(&cfg, &machine).unwrap();
    let cfg_s = cfg.display().to_string();
    let log = tmp("sim.log");
    let _sim = Kill(
        Command::new(bin!("sim-drives"))
            .args(["--config", &cfg_s, "--modbus-tcp", &addr])
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    let t0 = Instant::now();
    while std::net::TcpStream::connect(&addr).is_err() {
        assert!(t0.elapsed().as_secs() < 10, "sim-drives --modbus-tcp did not start: {}", std::fs::read_to_string(&log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(20));
    }
    let mut sc = sim_drives::report::Scenario::new("survive/sigkill_controller_modbus");
    sc.faults_injected = 1;

    // The observer: a second Modbus client reading every unit in turn.
    let readings: Arc<Mutex<Vec<Reading>>> = Arc::default();
    let timeouts: Arc<Mutex<[u16; 4]>> = Arc::default();
    let stop = Arc::new(AtomicBool::new(false));
    let (r2, t2, s2, a2) = (readings.clone(), timeouts.clone(), stop.clone(), addr.clone());
    let obs = std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async move {
            let mut c = tokio_modbus::client::tcp::connect_slave(a2.parse().unwrap(), Slave(1)).await.expect("connect");
            while !s2.load(Ordering::Relaxed) {
                for unit in 1..=3u8 {
                    c.set_slave(Slave(unit));
                    let Ok(Ok(v)) = c.read_holding_registers(STATUSWORD, 7).await else { continue };
                    let pos = (((v[2] as u32) << 16) | v[3] as u32) as i32 as i64;
                    r2.lock().unwrap().push((Instant::now(), unit, v[0], pos, v[6]));
                    if let Ok(Ok(t)) = c.read_holding_registers(COMM_TIMEOUT, 1).await {
                        t2.lock().unwrap()[unit as usize] = t[0];
                    }
                }
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        });
    });

    let prog = tmp("feed.nc");
    std::fs::write(&prog, "O1\nG21\nG98 G97\nM03 S120\nG00 X20 Z2\nG01 Z-150 F1500\nM05\nM30\n").unwrap();
    let run_log = tmp("run.log");
    let mut cnc = Kill(
        Command::new(bin!("cncgw"))
            .args(["run", "--config", &cfg_s, "--state-dir", &tmp("state").display().to_string()])
            .arg(&prog)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&run_log).unwrap())
            .spawn()
            .unwrap(),
    );
    // Kill once Z is 5 mm into the feed (unit 2 below −50 000 counts).
    let t0 = Instant::now();
    loop {
        if readings.lock().unwrap().iter().any(|r| r.1 == 2 && r.3 < -50_000) {
            break;
        }
        if let Ok(Some(st)) = cnc.0.try_wait() {
            panic!("cncgw ended before the kill ({st}): {}", std::fs::read_to_string(&run_log).unwrap_or_default());
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "Z never moved: {}", std::fs::read_to_string(&run_log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(2));
    }
    let t_kill = Instant::now();
    cnc.0.kill().unwrap();
    let status = cnc.0.wait().unwrap();
    assert_eq!(status.code(), None, "{status}");
    std::thread::sleep(Duration::from_millis(1500));
    stop.store(true, Ordering::Relaxed);
    obs.join().unwrap();
    let readings = std::mem::take(&mut *readings.lock().unwrap());
    let timeouts = *timeouts.lock().unwrap();
    let ms = |t: Instant| t.saturating_duration_since(t_kill).as_secs_f64() * 1e3;
    let mut worst = 0.0f64;
    let mut bound_ms = 0.0f64;
    for unit in 1..=3u8 {
        let wd = timeouts[unit as usize] as f64;
        assert!(wd >= 200.0, "unit {unit}: comm timeout {wd} ms (cncgw's start-up sets ≥ 200)");
        let bound = wd + 200.0;
        bound_ms = bound_ms.max(bound);
        let after: Vec<_> = readings.iter().filter(|r| r.1 == unit && r.0 >= t_kill).collect();
        assert!(after.len() >= 10, "unit {unit}: {} readings after the kill", after.len());
        let fault =
            after.iter().find(|r| r.4 == 0x8130).map(|r| ms(r.0)).unwrap_or_else(|| panic!("unit {unit}: no comm-timeout fault: {:?}", after.last()));
        let left_oe = after.iter().find(|r| r.2 & 0x6F != 0x27).map(|r| ms(r.0)).unwrap_or(f64::INFINITY);
        let last = after.last().unwrap().3;
        // At rest: within 1 µm (X, Z) or 0.1° (the spindle) of where it ends.
        let tol = if unit == 3 { 100 } else { 10 };
        let moving_until = after.iter().rev().find(|r| (r.3 - last).abs() > tol).map_or(0.0, |r| ms(r.0));
        let at_rest = after.iter().find(|r| ms(r.0) > moving_until).map_or(f64::INFINITY, |r| ms(r.0));
        eprintln!("unit {unit}: comm timeout {wd} ms; fault 0x8130 after {fault:.0} ms, statusword out of Operation Enabled by {left_oe:.0} ms, at rest by {at_rest:.0} ms of the kill");
        assert!(fault <= bound && left_oe <= bound && at_rest <= bound, "unit {unit}: bound {bound} ms");
        worst = worst.max(fault).max(left_oe).max(at_rest);
    }
    sc.stop_cycles = Some((worst / CYCLE_MS).ceil() as u64);
    sc.bound_cycles = Some((bound_ms / CYCLE_MS) as u64);
    sc.record();
}
