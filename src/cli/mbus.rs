//! Modbus buses in the service commands: `--bus modbus-tcp://HOST:PORT` and
//! `--bus modbus-rtu:///dev/ttyUSB0?baud=115200&parity=none&stop_bits=1` put every axis of
//! the configuration on that one link (unit id = the axis's `node`, register map = its
//! `modbus_profile` / `cia402_map` / `pr_map`). A configuration whose axes are all on Modbus
//! links (`config/lathe-modbus.toml`) is served the same way without `--bus`.
//!
//! `scan`, `drive status` and `monitor` read the drives' holding registers directly, one
//! transaction at a time (read-only); `jog`, `run` and `tap-test` go through the controller's
//! own Modbus master (`drives::modbus`) and cycle loop.

use super::MachineArgs;
use crate::config::{AxisConfig, LinkTransport, MachineConfig, ModbusLink, Parity};
use cncgw_bus::cia402::State;
use cncgw_bus::modbus::{exception_text, pr_status, Cia402Map, PrMap, Profile};
use std::time::{Duration, Instant};
use tokio_modbus::client::{Context, Reader};
use tokio_modbus::prelude::SlaveContext;
use tokio_modbus::Slave;

/// The link name `--bus modbus-…` gets in the configuration.
pub const BUS_LINK: &str = "bus";

/// `modbus-tcp://HOST[:PORT]` (port 502 by default) or
/// `modbus-rtu://DEVICE[?baud=N&parity=none|even|odd&stop_bits=1|2&timeout_ms=N]` as a
/// link; None for any other bus.
pub fn parse_bus_url(bus: &str) -> Option<Result<ModbusLink, String>> {
    let mut t = toml::Table::new();
    if let Some(rest) = bus.strip_prefix("modbus-tcp://") {
        let addr = rest.trim_end_matches('/');
        if addr.is_empty() {
            return Some(Err(format!("{bus}: give the drive's address, e.g. modbus-tcp://192.168.1.10:502")));
        }
        let addr = if addr.rsplit_once(':').is_some_and(|(_, p)| p.parse::<u16>().is_ok()) { addr.to_string() } else { format!("{addr}:502") };
        t.insert("transport".into(), "tcp".into());
        t.insert("address".into(), addr.into());
    } else if let Some(rest) = bus.strip_prefix("modbus-rtu://") {
        let (dev, query) = rest.split_once('?').unwrap_or((rest, ""));
        if dev.is_empty() {
            return Some(Err(format!("{bus}: give the serial device, e.g. modbus-rtu:///dev/ttyUSB0?baud=115200&parity=none")));
        }
        t.insert("transport".into(), "rtu".into());
        t.insert("device".into(), dev.into());
        for kv in query.split('&').filter(|s| !s.is_empty()) {
            let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
            let num = |v: &str| v.parse::<i64>().map_err(|_| format!("{bus}: {k}={v} is not a number"));
            let val: toml::Value = match k {
                "baud" | "stop_bits" | "timeout_ms" => match num(v) {
                    Ok(n) => n.into(),
                    Err(e) => return Some(Err(e)),
                },
                "parity" => v.to_ascii_lowercase().into(),
                _ => return Some(Err(format!("{bus}: unknown parameter `{k}` (baud, parity, stop_bits, timeout_ms)"))),
            };
            t.insert(k.into(), val);
        }
    } else {
        return None;
    }
    Some(toml::Value::Table(t).try_into::<ModbusLink>().map_err(|e| format!("{bus}: {e}")))
}

/// Put every axis of `cfg` on the link of a `modbus-…` bus. Ok(true) if `bus` was one.
pub fn apply_bus(cfg: &mut MachineConfig, bus: Option<&str>) -> Result<bool, String> {
    let Some(link) = bus.and_then(parse_bus_url) else { return Ok(false) };
    let link = link?;
    cfg.modbus.clear();
    cfg.modbus.insert(BUS_LINK.into(), link);
    for a in cfg.axes.values_mut() {
        a.modbus = Some(BUS_LINK.into());
    }
    cfg.bus.interface = "none".into();
    Ok(true)
}

/// The configuration for the service commands' Modbus path: Some when `--bus` is a Modbus
/// bus or every axis of the configuration is on a Modbus link.
pub fn modbus_machine(m: &MachineArgs) -> Result<Option<MachineConfig>, String> {
    let (mut cfg, _) = super::load_config(m.config.as_deref())?;
    let bus_given = apply_bus(&mut cfg, m.bus.as_deref())?;
    Ok((bus_given || (!cfg.has_canopen() && !cfg.modbus.is_empty() && m.bus.is_none())).then_some(cfg))
}

/// A plain synchronous Modbus client for the service commands (the controller's own master
/// runs a link thread with a cycle; these commands ask one question at a time).
pub struct Client {
    rt: tokio::runtime::Runtime,
    ctx: Context,
    link: ModbusLink,
    pub what: String,
    last_end: Option<Instant>,
}

impl Client {
    pub fn connect(link: &ModbusLink) -> Result<Client, String> {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| format!("cannot start the I/O runtime: {e}"))?;
        let timeout = Duration::from_millis(link.timeout_ms.max(100) as u64);
        let (ctx, what) = match link.transport {
            LinkTransport::Tcp => {
                let addr = link.address.clone().unwrap_or_default();
                let ctx = rt.block_on(async {
                    let sa = tokio::net::lookup_host(&addr).await.map_err(|e| format!("{addr}: {e}"))?.next().ok_or_else(|| format!("{addr}: no address"))?;
                    let s = tokio::time::timeout(timeout.max(Duration::from_millis(500)), tokio::net::TcpStream::connect(sa))
                        .await
                        .map_err(|_| format!("{addr}: connection timed out"))?
                        .map_err(|e| format!("{addr}: {e}; is the drive (or `sim-drives --modbus-tcp {addr}`) there?"))?;
                    let _ = s.set_nodelay(true);
                    Ok::<_, String>(tokio_modbus::client::tcp::attach(s))
                })?;
                (ctx, format!("Modbus TCP {addr}"))
            }
            LinkTransport::Rtu => {
                let dev = link.device.clone().unwrap_or_default();
                let parity = match link.parity {
                    Parity::None => tokio_serial::Parity::None,
                    Parity::Even => tokio_serial::Parity::Even,
                    Parity::Odd => tokio_serial::Parity::Odd,
                };
                let stop = if link.stop_bits == 2 { tokio_serial::StopBits::Two } else { tokio_serial::StopBits::One };
                let b = tokio_serial::new(&dev, link.baud).parity(parity).stop_bits(stop).data_bits(tokio_serial::DataBits::Eight);
                let port = rt.block_on(async { tokio_serial::SerialStream::open(&b) }).map_err(|e| format!("{dev}: {e}; check the device and its permissions (dialout group)"))?;
                (tokio_modbus::client::rtu::attach(port), format!("Modbus RTU {dev} {} baud", link.baud))
            }
        };
        Ok(Client { rt, ctx, link: link.clone(), what, last_end: None })
    }

    /// Read `len` holding registers of `unit` from `addr`.
    pub fn read(&mut self, unit: u8, addr: u16, len: u16) -> Result<Vec<u16>, String> {
        if self.link.transport == LinkTransport::Rtu {
            // The 3.5-character silence between frames (generous: 4 ms covers 9600 baud).
            if let Some(end) = self.last_end {
                let due = end + Duration::from_millis(4);
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                }
            }
        }
        let timeout = Duration::from_millis(self.link.timeout_ms.max(100) as u64);
        self.ctx.set_slave(Slave(unit));
        let ctx = &mut self.ctx;
        let r = self.rt.block_on(async { tokio::time::timeout(timeout, ctx.read_holding_registers(addr, len)).await });
        self.last_end = Some(Instant::now());
        match r {
            Err(_) => Err(format!("unit {unit}: no answer within {} ms", timeout.as_millis())),
            Ok(Err(e)) => Err(format!("unit {unit}: {e}")),
            Ok(Ok(Err(code))) => {
                let c: u8 = code.into();
                Err(format!("unit {unit}: exception 0x{c:02X} {} reading register {addr} ({len})", exception_text(c)))
            }
            Ok(Ok(Ok(v))) if v.len() == len as usize => Ok(v),
            Ok(Ok(Ok(v))) => Err(format!("unit {unit}: {} registers in the answer, {len} asked", v.len())),
        }
    }
}

/// One drive as read over Modbus.
#[derive(Clone, Debug, Default)]
pub struct DriveRead {
    pub axis: String,
    pub unit: u8,
    pub profile: &'static str,
    /// CiA 402 statusword (a PR drive's status as the equivalent statusword).
    pub statusword: u16,
    /// The PR status register as read (PR profile).
    pub pr_status: Option<u16>,
    pub mode: Option<i8>,
    pub position_counts: i64,
    pub position: f64,
    pub velocity_per_s: Option<f64>,
    /// 0x603F (CiA 402) or the alarm code (PR).
    pub error_code: u16,
    pub round_trip_ms: f64,
}

/// Read one drive's state (read-only).
pub fn read_drive(c: &mut Client, axis: &str, a: &AxisConfig) -> Result<DriveRead, String> {
    let t0 = Instant::now();
    let mut d = DriveRead { axis: axis.into(), unit: a.node, ..DriveRead::default() };
    match a.modbus_profile {
        Profile::Cia402 => {
            let m = a.cia402_map.unwrap_or_else(Cia402Map::default);
            d.profile = "cia402";
            d.statusword = c.read(a.node, m.statusword, 1)?[0];
            d.mode = Some(c.read(a.node, m.mode_display, 1)?[0] as i16 as i8);
            let p = c.read(a.node, m.position_actual, 2)?;
            d.position_counts = m.word_order.join_i32([p[0], p[1]]) as i64;
            let v = c.read(a.node, m.velocity_actual, 2)?;
            d.velocity_per_s = Some(m.word_order.join_i32([v[0], v[1]]) as f64 / a.counts_per_unit);
            d.error_code = c.read(a.node, m.error_code, 1)?[0];
        }
        Profile::Pr => {
            let m = a.pr_map.unwrap_or_else(PrMap::default);
            d.profile = "pr";
            let st = c.read(a.node, m.status, 1)?[0];
            d.pr_status = Some(st);
            d.statusword = crate::drives::modbus::plan::pr_statusword(st);
            let p = c.read(a.node, m.position_actual, 2)?;
            d.position_counts = m.word_order.join_i32([p[0], p[1]]) as i64;
            d.error_code = c.read(a.node, m.alarm_code, 1)?[0];
        }
    }
    d.position = d.position_counts as f64 / a.counts_per_unit;
    d.round_trip_ms = t0.elapsed().as_secs_f64() * 1e3;
    Ok(d)
}

/// Clients for every link of `cfg` that carries an axis, by link name.
fn clients(cfg: &MachineConfig) -> Result<std::collections::BTreeMap<String, Client>, String> {
    let mut out = std::collections::BTreeMap::new();
    for (name, l) in &cfg.modbus {
        if cfg.axes.values().any(|a| a.modbus.as_deref() == Some(name.as_str())) {
            out.insert(name.clone(), Client::connect(l).map_err(|e| format!("Modbus link {name}: {e}"))?);
        }
    }
    Ok(out)
}

/// Axes of `cfg` in unit order: (name, axis, link).
fn axes(cfg: &MachineConfig) -> Vec<(String, AxisConfig, String)> {
    let mut v: Vec<_> = cfg.axes.iter().filter_map(|(n, a)| a.modbus.clone().map(|l| (n.clone(), a.clone(), l))).collect();
    v.sort_by_key(|(_, a, l)| (l.clone(), a.node));
    v
}

fn state_json(d: &DriveRead) -> serde_json::Value {
    serde_json::json!({
        "unit": d.unit, "axis": d.axis, "profile": d.profile,
        "statusword": format!("0x{:04X}", d.statusword), "state": State::from_statusword(d.statusword).name(),
        "pr_status": d.pr_status.map(|s| format!("0x{s:04X}")),
        "mode": d.mode, "mode_name": d.mode.map(cncgw_bus::cia402::mode::name),
        "position_counts": d.position_counts, "position": d.position, "velocity_per_s": d.velocity_per_s,
        "error_code": format!("0x{:04X}", d.error_code),
        "error_text": if d.profile == "cia402" { Some(cncgw_bus::canopen::emcy::error_text(d.error_code)) } else { None },
        "round_trip_ms": d.round_trip_ms,
    })
}

/// `cncgw scan` on Modbus: every configured unit, whether it answers, its state.
pub fn scan(cfg: &MachineConfig, json: bool) -> i32 {
    let mut cl = match clients(cfg) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return super::diag::EXIT_SETUP;
        }
    };
    let mut failed = 0;
    let mut rows = Vec::new();
    for (name, a, link) in axes(cfg) {
        let Some(c) = cl.get_mut(&link) else { continue };
        let r = read_drive(c, &name, &a);
        if r.is_err() {
            failed += 1;
        }
        rows.push((name, a, link, c.what.clone(), r));
    }
    if json {
        let arr: Vec<_> = rows
            .iter()
            .map(|(n, a, l, w, r)| match r {
                Ok(d) => {
                    let mut v = state_json(d);
                    v["link"] = serde_json::json!(l);
                    v["bus"] = serde_json::json!(w);
                    v["error"] = serde_json::Value::Null;
                    v
                }
                Err(e) => serde_json::json!({"unit": a.node, "axis": n, "link": l, "bus": w, "error": e}),
            })
            .collect();
        println!("{}", serde_json::json!({"bus": "modbus", "simulated": false, "nodes": arr}));
    } else {
        println!("{} Modbus unit(s) in the configuration (Modbus has no identity object: state and position shown)", rows.len());
        println!("{:>4} {:<5} {:<26} {:<7} {:<6} {:<22} {:>12} {:>8}  rtt", "unit", "axis", "link", "profile", "sw", "state", "position", "error");
        for (n, a, _l, w, r) in &rows {
            match r {
                Ok(d) => println!(
                    "{:>4} {n:<5} {w:<26} {:<7} 0x{:04X} {:<22} {:>12.4} {:>8}  {:.1} ms",
                    a.node,
                    d.profile,
                    d.statusword,
                    State::from_statusword(d.statusword).name(),
                    d.position,
                    format!("0x{:04X}", d.error_code),
                    d.round_trip_ms
                ),
                Err(e) => println!("{:>4} {n:<5} {w:<26} no answer: {e}", a.node),
            }
        }
        if failed > 0 {
            eprintln!("{failed} unit(s) did not answer: check power, wiring (A/B), baud rate, parity and unit ids (`--bus`, `--config`)");
        }
    }
    if failed > 0 {
        super::diag::EXIT_NODE
    } else {
        super::diag::EXIT_OK
    }
}

/// `cncgw drive status UNIT` on Modbus.
pub fn drive_status(cfg: &MachineConfig, unit: u8, json: bool) -> i32 {
    use super::diag::{EXIT_NODE, EXIT_OK, EXIT_SETUP, EXIT_USAGE};
    let Some((name, a, link)) = axes(cfg).into_iter().find(|(_, a, _)| a.node == unit) else {
        eprintln!("error: no axis of the configuration has Modbus unit id {unit} (`cncgw config check` lists them); Modbus registers are read through an axis's map");
        return EXIT_USAGE;
    };
    let mut c = match cfg.modbus.get(&link).ok_or_else(|| format!("no link {link}")).and_then(Client::connect) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: Modbus link {link}: {e}");
            return EXIT_SETUP;
        }
    };
    let d = match read_drive(&mut c, &name, &a) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: axis {name}: {e}; `cncgw scan` shows which units answer");
            return EXIT_NODE;
        }
    };
    let state = State::from_statusword(d.statusword);
    let unit_s = if a.kind == crate::config::AxisKind::Spindle { "deg" } else { "mm" };
    let bits = super::diag::statusword_bits(d.statusword, d.mode.unwrap_or(0));
    if json {
        let mut v = state_json(&d);
        v["node"] = serde_json::json!(unit);
        v["bus"] = serde_json::json!(c.what);
        v["unit_of_position"] = serde_json::json!(unit_s);
        v["bits"] = bits.iter().map(|(b, n, s)| serde_json::json!({"bit": b, "name": n, "set": s})).collect();
        println!("{v}");
    } else {
        println!("unit {unit} (axis {name}) on {}: {}", c.what, state.name());
        match d.pr_status {
            Some(st) => {
                println!("status register = 0x{st:04X} (PR profile), as a CiA 402 statusword 0x{:04X}", d.statusword);
                for (bit, n) in [(pr_status::FAULT, "alarm latched"), (pr_status::ENABLED, "servo on"), (pr_status::RUNNING, "PR move running"), (pr_status::IN_POSITION, "in position")] {
                    println!("  {} {n}", if st & bit != 0 { "1" } else { "0" });
                }
            }
            None => {
                println!("statusword = 0x{:04X}", d.statusword);
                for (b, n, set) in &bits {
                    println!("  bit {b:>2} {} {n}", if *set { "1" } else { "0" });
                }
            }
        }
        if let Some(m) = d.mode {
            println!("mode = {m} ({})", cncgw_bus::cia402::mode::name(m));
        }
        println!("position = {} counts = {:.4} {unit_s}", d.position_counts, d.position);
        if let Some(v) = d.velocity_per_s {
            println!("velocity = {v:.4} {unit_s}/s");
        }
        if d.profile == "cia402" {
            println!("error code = 0x{:04X} {}", d.error_code, cncgw_bus::canopen::emcy::error_text(d.error_code));
        } else {
            println!("alarm code = 0x{:04X}{}", d.error_code, if d.error_code == 0 { " (none)" } else { " (see the drive's manual)" });
        }
        println!("round trip {:.1} ms for {} register reads", d.round_trip_ms, if d.profile == "cia402" { 5 } else { 3 });
        if matches!(state, State::Fault | State::FaultReactionActive) {
            println!("the drive is in fault: clear the cause shown above, then reset the fault");
        }
    }
    if matches!(state, State::Fault | State::FaultReactionActive) {
        EXIT_NODE
    } else {
        EXIT_OK
    }
}

/// `cncgw monitor` on Modbus: the same table from the registers, refreshed in place.
pub fn monitor(cfg: &MachineConfig, seconds: Option<f64>, once: bool, interval_ms: u64, json: bool) -> i32 {
    use std::io::{IsTerminal, Write};
    let mut cl = match clients(cfg) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return super::diag::EXIT_SETUP;
        }
    };
    let tty = std::io::stdout().is_terminal() && !json;
    let t0 = Instant::now();
    let interval = Duration::from_millis(interval_ms.max(50));
    let mut shown = 0usize;
    let mut out = std::io::stdout();
    loop {
        let tick = Instant::now();
        let mut lines = vec![format!("{:>4} {:<5} {:<6} {:<22} {:<26} {:>12} {:>12} {:>8}", "unit", "axis", "sw", "state", "mode", "position", "velocity/s", "error")];
        let mut arr = Vec::new();
        for (name, a, link) in axes(cfg) {
            let Some(c) = cl.get_mut(&link) else { continue };
            match read_drive(c, &name, &a) {
                Ok(d) => {
                    let mode = d.mode.map(|m| format!("{m} {}", cncgw_bus::cia402::mode::name(m))).unwrap_or_else(|| "-".into());
                    let vel = d.velocity_per_s.map(|v| format!("{v:.4}")).unwrap_or_else(|| "-".into());
                    lines.push(format!(
                        "{:>4} {name:<5} 0x{:04X} {:<22} {mode:<26} {:>12.4} {vel:>12} {:>8}",
                        a.node,
                        d.statusword,
                        State::from_statusword(d.statusword).name(),
                        d.position,
                        format!("0x{:04X}", d.error_code)
                    ));
                    arr.push(state_json(&d));
                }
                Err(e) => {
                    lines.push(format!("{:>4} {name:<5} no answer: {e}", a.node));
                    arr.push(serde_json::json!({"unit": a.node, "axis": name, "error": e}));
                }
            }
        }
        let rtt = tick.elapsed().as_secs_f64() * 1e3;
        lines.push(format!("Modbus: {} register reads took {rtt:.1} ms", arr.len() * 5));
        let text = if json {
            format!("{}\n", serde_json::json!({"t_s": t0.elapsed().as_secs_f64(), "bus": "modbus", "drives": arr, "poll_ms": rtt}))
        } else {
            let mut t = String::new();
            if tty && shown > 0 {
                t.push_str(&format!("\x1b[{shown}A"));
            }
            for l in &lines {
                if tty {
                    t.push_str("\x1b[2K");
                }
                t.push_str(l);
                t.push('\n');
            }
            if !tty && !once {
                t.push('\n');
            }
            t
        };
        if out.write_all(text.as_bytes()).and_then(|_| out.flush()).is_err() {
            return 0;
        }
        shown = lines.len();
        if once || seconds.is_some_and(|s| (t0.elapsed() + interval).as_secs_f64() > s) {
            return 0;
        }
        let next = tick + interval;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bus_urls() {
        let l = parse_bus_url("modbus-tcp://127.0.0.1:5020").unwrap().unwrap();
        assert_eq!((l.transport, l.address.as_deref()), (LinkTransport::Tcp, Some("127.0.0.1:5020")));
        let l = parse_bus_url("modbus-tcp://drive.local").unwrap().unwrap();
        assert_eq!(l.address.as_deref(), Some("drive.local:502"));
        let l = parse_bus_url("modbus-rtu:///dev/ttyUSB0?baud=57600&parity=even&stop_bits=2").unwrap().unwrap();
        assert_eq!((l.transport, l.device.as_deref(), l.baud, l.parity, l.stop_bits), (LinkTransport::Rtu, Some("/dev/ttyUSB0"), 57600, Parity::Even, 2));
        let l = parse_bus_url("modbus-rtu:///dev/ttyUSB0").unwrap().unwrap();
        assert_eq!((l.baud, l.parity), (115_200, Parity::None));
        assert!(parse_bus_url("modbus-rtu:///dev/ttyUSB0?baud=fast").unwrap().unwrap_err().contains("not a number"));
        assert!(parse_bus_url("modbus-rtu:///dev/ttyUSB0?speed=1").unwrap().unwrap_err().contains("unknown parameter `speed`"));
        assert!(parse_bus_url("modbus-rtu:///dev/x?parity=mark").unwrap().is_err());
        assert!(parse_bus_url("can0").is_none() && parse_bus_url("inproc").is_none());
        let mut cfg = MachineConfig::embedded();
        assert!(apply_bus(&mut cfg, Some("modbus-tcp://127.0.0.1:5020")).unwrap());
        assert!(!cfg.has_canopen());
        assert!(cfg.axes.values().all(|a| a.modbus.as_deref() == Some(BUS_LINK)));
    }
}
