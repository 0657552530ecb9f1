//! Modbus figures: transactions per second and the link cycle achieved by cncgw's Modbus
//! layer against sim-drives' Modbus server, for 1 and 3 drives, over TCP (loopback) and RTU
//! at 115200 baud 8N1 (through a socat pseudo-terminal pair when socat is installed).
//!
//!     cargo bench --bench modbus
//!
//! For RTU two figures matter and both are printed: the cycle cncgw computes for a real
//! 115200-baud line (frame bytes, 3.5-character silences, 1 ms drive turnaround) — which it
//! runs at —, and what the software alone could do (a pty carries bytes without a baud rate).

use cncgw::config::MachineConfig;
use cncgw::drives::modbus::ModbusDrives;
use cncgw::drives::DriveBus;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

const AXES: [&str; 3] = [
    "[axes.x]\nkind = \"linear\"\nnode = 1\nmodbus = \"m\"\ncounts_per_unit = 10000.0\nmin = -2.0\nmax = 150.0\nmax_speed = 10000.0\nmax_accel = 2000.0\n",
    "[axes.z]\nkind = \"linear\"\nnode = 2\nmodbus = \"m\"\ncounts_per_unit = 10000.0\nmin = -400.0\nmax = 5.0\nmax_speed = 12000.0\nmax_accel = 2000.0\n",
    "[axes.s1]\nkind = \"spindle\"\nnode = 3\nmodbus = \"m\"\ncounts_per_unit = 1000.0\nmax_speed = 6000.0\nmax_accel = 6000.0\nfollowing_error = 30.0\n",
];

fn machine(n: usize, link: &str) -> String {
    format!(
        "[machine]\nname = \"bench\"\ncycle_ms = 1.0\n[bus]\ninterface = \"none\"\nfeedback_timeout_ms = 500\n[modbus.m]\n{link}\ntimeout_ms = 200\n{}",
        AXES[..n].concat()
    )
}

/// Enable the drives and hold them for `secs`; the link's statistics.
fn run(text: &str, secs: f64) -> Result<cncgw::drives::modbus::LinkStats, String> {
    let cfg = MachineConfig::from_toml("bench.toml", text).map_err(|e| e.to_string())?;
    let mut d = ModbusDrives::new(&cfg);
    let mut clock = cncgw::bus::RealClock::new();
    d.startup(&mut clock).map_err(|a| a.to_string())?;
    let t0 = Instant::now();
    let mut enabled = false;
    while t0.elapsed().as_secs_f64() < secs + 2.0 {
        std::thread::sleep(Duration::from_millis(1));
        d.receive(0).map_err(|a| a.to_string())?;
        if !enabled {
            enabled = d.enable_step().map_err(|a| a.to_string())?;
        }
        d.transmit(0).map_err(|a| a.to_string())?;
        if enabled && t0.elapsed().as_secs_f64() > 2.0 {
            break;
        }
    }
    let before = d.link_stats().remove(0);
    let t1 = Instant::now();
    while t1.elapsed().as_secs_f64() < secs {
        std::thread::sleep(Duration::from_millis(1));
        d.receive(0).map_err(|a| a.to_string())?;
        d.transmit(0).map_err(|a| a.to_string())?;
    }
    let mut after = d.link_stats().remove(0);
    let dt = t1.elapsed().as_secs_f64();
    d.shutdown(&mut clock);
    after.transactions -= before.transactions;
    after.cycles -= before.cycles;
    after.failures -= before.failures;
    after.overruns -= before.overruns;
    // Per second.
    after.transactions = (after.transactions as f64 / dt).round() as u64;
    after.cycles = (after.cycles as f64 / dt).round() as u64;
    Ok(after)
}

/// Back-to-back FC03 reads of the feedback block with tokio-modbus: the raw rate.
fn raw_rate(ctx: &mut tokio_modbus::client::Context, rt: &tokio::runtime::Runtime, units: u8, secs: f64) -> f64 {
    use tokio_modbus::prelude::*;
    let t0 = Instant::now();
    let mut n = 0u64;
    while t0.elapsed().as_secs_f64() < secs {
        for u in 1..=units {
            ctx.set_slave(Slave(u));
            if rt.block_on(ctx.read_holding_registers(10, 7)).is_ok() {
                n += 1;
            }
        }
    }
    n as f64 / t0.elapsed().as_secs_f64()
}

fn pty_pair() -> Option<(std::process::Child, String, String)> {
    let mut c =
        Command::new("socat").args(["-d", "-d", "pty,raw,echo=0", "pty,raw,echo=0"]).stdout(Stdio::null()).stderr(Stdio::piped()).spawn().ok()?;
    let err = c.stderr.take()?;
    let mut lines = BufReader::new(err).lines();
    let mut p = Vec::new();
    while p.len() < 2 {
        let l = lines.next()?.ok()?;
        if let Some(x) = l.split("PTY is ").nth(1) {
            p.push(x.trim().to_string());
        }
    }
    std::thread::spawn(move || for _ in lines.by_ref() {});
    Some((c, p[0].clone(), p[1].clone()))
}

fn main() {
    let secs = 3.0;
    println!("Modbus: cncgw ModbusDrives ↔ sim-drives' server, {secs} s each (machine cycle 1 ms)");
    println!(
        "{:<6} {:>6} {:>6} {:>14} {:>12} {:>14} {:>10} {:>9}",
        "link", "drives", "fc", "link cycle ms", "cycles/s", "transactions/s", "failures", "overruns"
    );
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
    for n in [1usize, 3] {
        let stop = Arc::new(AtomicBool::new(false));
        let sim_cfg = sim_drives::SimConfig::from_machine_toml_bus(&machine(n, ""), Some(true)).expect("sim config");
        let srv = sim_drives::modbus::serve_tcp("127.0.0.1:0".parse().unwrap(), sim_cfg, stop.clone()).expect("server");
        let addr = srv.local_addr().unwrap();
        for fc23 in [false, true] {
            let link = format!("transport = \"tcp\"\naddress = \"{addr}\"\nfc23 = {fc23}");
            match run(&machine(n, &link), secs) {
                Ok(s) => println!(
                    "{:<6} {:>6} {:>6} {:>14.0} {:>12} {:>14} {:>10} {:>9}",
                    "tcp",
                    n,
                    if fc23 { "23" } else { "16+03" },
                    s.cycle.as_secs_f64() * 1e3,
                    s.cycles,
                    s.transactions,
                    s.failures,
                    s.overruns
                ),
                Err(e) => println!("tcp {n} drives: {e}"),
            }
        }
        let mut ctx = rt.block_on(tokio_modbus::client::tcp::connect(addr)).expect("connect");
        println!("  raw tokio-modbus FC03 back to back, {n} drive(s): {:.0} transactions/s", raw_rate(&mut ctx, &rt, n as u8, 2.0));
        stop.store(true, Ordering::Relaxed);
        let _ = srv.join();
    }
    let Some(_) = Command::new("socat").arg("-V").stdout(Stdio::null()).status().ok() else {
        println!("rtu: socat is not installed (scripts/install-test-deps.sh): no RTU figures");
        return;
    };
    for n in [1usize, 3] {
        let Some((mut socat, a, b)) = pty_pair() else {
            println!("rtu: no pty pair from socat");
            return;
        };
        let stop = Arc::new(AtomicBool::new(false));
        let sim_cfg = sim_drives::SimConfig::from_machine_toml_bus(&machine(n, ""), Some(true)).expect("sim config");
        let srv = sim_drives::modbus::serve_rtu(&a, sim_drives::modbus::RtuLine::default(), sim_cfg, stop.clone()).expect("rtu server");
        for fc23 in [false, true] {
            let link = format!("transport = \"rtu\"\ndevice = \"{b}\"\nbaud = 115200\nfc23 = {fc23}");
            let text = machine(n, &link);
            let computed =
                MachineConfig::from_toml("b", &text).ok().map(|c| ModbusDrives::new(&c).planned_links()[0].rtu.map_or(0.0, |r| r.0)).unwrap_or(0.0);
            match run(&text, secs) {
                Ok(s) => println!(
                    "{:<6} {:>6} {:>6} {:>14.0} {:>12} {:>14} {:>10} {:>9}   (115200 8N1 line: {:.2} ms of frames, silences and turnarounds per cycle)",
                    "rtu",
                    n,
                    if fc23 { "23" } else { "16+03" },
                    s.cycle.as_secs_f64() * 1e3,
                    s.cycles,
                    s.transactions,
                    s.failures,
                    s.overruns,
                    computed * 1e3
                ),
                Err(e) => println!("rtu {n} drives: {e}"),
            }
        }
        let port = rt.block_on(async { tokio_serial::SerialStream::open(&tokio_serial::new(&b, 115_200)) }).expect("pty");
        let mut ctx = tokio_modbus::client::rtu::attach(port);
        println!(
            "  raw tokio-modbus FC03 back to back over the pty (no baud limit), {n} drive(s): {:.0} transactions/s",
            raw_rate(&mut ctx, &rt, n as u8, 2.0)
        );
        stop.store(true, Ordering::Relaxed);
        let _ = srv.join();
        let _ = socat.kill();
        let _ = socat.wait();
    }
}
