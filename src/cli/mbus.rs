//! Modbus buses in the service commands: `--bus modbus-tcp://HOST:PORT` and
//! `--bus modbus-rtu:///dev/ttyUSB0?baud=115200&parity=none&stop_bits=1` put every axis of
//! the configuration on that one link (unit id = the axis's `node`, register map = its
//! `modbus_profile` / `cia402_map` / `pr_map`). A configuration whose axes are all on Modbus
//! links (`config/lathe-modbus.toml`) is served the same way without `--bus`.
//!
//! `scan`, `drive status` and `monitor` read the drives' holding registers directly, one
//! transaction at a time (read-only); `jog`, `run` and `tap-test` go through the controller's
//! own Modbus master (`drives::modbus`) and cycle loop.

use super::exit;
use super::MachineArgs;
use super::OrSetup;
use crate::config::{AxisConfig, LinkTransport, MachineConfig, ModbusLink, Parity};
use crate::drives::access::{self, DriveAccess, ObjType};
use crate::drives::modbus::link::exception_words;
use cncgw_bus::cia402::State;
use cncgw_bus::modbus::{Profile, WordOrder};
use std::time::{Duration, Instant};
use tokio_modbus::client::{Context, Reader, Writer};
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

/// Put every axis of `cfg` on the link of a `modbus-…` bus. True if `bus` was one.
/// The URL says where the drives are; how to talk to them (timeout, function 23, link
/// cycle, turnaround, and the line settings the URL does not give) stays the
/// configuration's first Modbus link's. Without one, the timeout is held to what rides
/// through one lost answer within `bus.feedback_timeout_ms`.
pub fn apply_bus(cfg: &mut MachineConfig, bus: Option<&super::BusKind>) -> bool {
    let Some(super::BusKind::Modbus(b)) = bus else { return false };
    let mut link = b.link.clone();
    let given: Vec<&str> = b.given.iter().map(String::as_str).collect();
    let base = cfg.modbus.iter().find(|(n, _)| cfg.axes.values().any(|a| a.modbus.as_deref() == Some(n.as_str()))).map(|(_, l)| l.clone());
    match base {
        Some(b) => {
            link.fc23 = b.fc23;
            link.cycle_ms = b.cycle_ms;
            link.turnaround_ms = b.turnaround_ms;
            if !given.contains(&"timeout_ms") {
                link.timeout_ms = b.timeout_ms;
            }
            if link.transport == LinkTransport::Rtu && b.transport == LinkTransport::Rtu {
                if !given.contains(&"baud") {
                    link.baud = b.baud;
                }
                if !given.contains(&"parity") {
                    link.parity = b.parity;
                }
                if !given.contains(&"stop_bits") {
                    link.stop_bits = b.stop_bits;
                }
            }
        }
        None if !given.contains(&"timeout_ms") => {
            if let Some(most) = link.most_timeout_ms(cfg.bus.feedback_timeout_ms, cfg.machine.cycle_ms) {
                link.timeout_ms = link.timeout_ms.min(most as u32);
            }
        }
        None => {}
    }
    cfg.modbus.clear();
    cfg.modbus.insert(BUS_LINK.into(), link);
    for a in cfg.axes.values_mut() {
        a.modbus = Some(BUS_LINK.into());
    }
    cfg.bus.interface = "none".into();
    true
}

/// The configuration for the service commands' Modbus path: Some when `--bus` is a Modbus
/// bus or every axis of the configuration is on a Modbus link.
pub fn modbus_machine(m: &MachineArgs) -> Result<Option<MachineConfig>, String> {
    let (mut cfg, _) = super::load_config(m.config.as_deref())?;
    let bus_given = apply_bus(&mut cfg, m.bus_kind()?.as_ref());
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
                    let sa = tokio::net::lookup_host(&addr)
                        .await
                        .map_err(|e| format!("{addr}: {e}"))?
                        .next()
                        .ok_or_else(|| format!("{addr}: no address"))?;
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
                let port = rt
                    .block_on(async { tokio_serial::SerialStream::open(&b) })
                    .map_err(|e| format!("{dev}: {e}; check the device and its permissions (dialout group)"))?;
                (tokio_modbus::client::rtu::attach(port), format!("Modbus RTU {dev} {} baud", link.baud))
            }
        };
        Ok(Client { rt, ctx, link: link.clone(), what, last_end: None })
    }

    /// The 3.5-character silence between RTU frames, for this line's baud rate and framing
    /// (a fixed 4 ms was below it at 9600 baud with parity).
    fn rtu_gap(&self) {
        if self.link.transport == LinkTransport::Rtu {
            if let Some(end) = self.last_end {
                let due = end + rtu_silence(&self.link);
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                }
            }
        }
    }

    /// Write `words` to the holding registers of `unit` from `addr` (FC06 for one register,
    /// FC16 for more).
    pub fn write(&mut self, unit: u8, addr: u16, words: &[u16]) -> Result<(), String> {
        self.rtu_gap();
        let timeout = Duration::from_millis(self.link.timeout_ms.max(100) as u64);
        self.ctx.set_slave(Slave(unit));
        let ctx = &mut self.ctx;
        let r = self.rt.block_on(async {
            tokio::time::timeout(timeout, async {
                match words {
                    [w] => ctx.write_single_register(addr, *w).await,
                    _ => ctx.write_multiple_registers(addr, words).await,
                }
            })
            .await
        });
        self.last_end = Some(Instant::now());
        match r {
            Err(_) => Err(format!("unit {unit}: no answer within {} ms", timeout.as_millis())),
            Ok(Err(e)) => Err(format!("unit {unit}: {e}")),
            Ok(Ok(Err(code))) => Err(format!("unit {unit}: {} writing register {addr} = {words:?}", exception_words(code))),
            Ok(Ok(Ok(()))) => Ok(()),
        }
    }

    /// Read `len` holding registers of `unit` from `addr`.
    pub fn read(&mut self, unit: u8, addr: u16, len: u16) -> Result<Vec<u16>, String> {
        self.rtu_gap();
        let timeout = Duration::from_millis(self.link.timeout_ms.max(100) as u64);
        self.ctx.set_slave(Slave(unit));
        let ctx = &mut self.ctx;
        let r = self.rt.block_on(async { tokio::time::timeout(timeout, ctx.read_holding_registers(addr, len)).await });
        self.last_end = Some(Instant::now());
        match r {
            Err(_) => Err(format!("unit {unit}: no answer within {} ms", timeout.as_millis())),
            Ok(Err(e)) => Err(format!("unit {unit}: {e}")),
            Ok(Ok(Err(code))) => Err(format!("unit {unit}: {} reading register {addr} ({len})", exception_words(code))),
            Ok(Ok(Ok(v))) if v.len() == len as usize => Ok(v),
            Ok(Ok(Ok(v))) => Err(format!("unit {unit}: {} registers in the answer, {len} asked", v.len())),
        }
    }
}

/// The silence an RTU frame must be preceded by on `link`'s line (Modbus over serial line
/// V1.02 §2.5.1.1: 3.5 characters, 1.75 ms above 19 200 baud), as the link thread keeps it.
pub fn rtu_silence(link: &ModbusLink) -> Duration {
    let t = cncgw_bus::modbus::SerialTiming { baud: link.baud, parity: link.parity != Parity::None, stop_bits: link.stop_bits };
    Duration::from_secs_f64(t.t35_s())
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
    /// 0x60FD digital inputs (bit 0 negative, bit 1 positive limit switch, bit 2 home switch),
    /// where the map has the register.
    pub digital_inputs: Option<u32>,
    pub round_trip_ms: f64,
}

/// Read one drive's state (read-only).
pub fn read_drive(c: &mut Client, axis: &str, a: &AxisConfig) -> Result<DriveRead, String> {
    let t0 = Instant::now();
    let mut d = DriveRead { axis: axis.into(), unit: a.node, ..DriveRead::default() };
    match a.modbus_profile {
        Profile::Cia402 => {
            let m = a.cia402_map.unwrap_or_default();
            d.profile = "cia402";
            d.statusword = c.read(a.node, m.statusword, 1)?[0];
            d.mode = Some(c.read(a.node, m.mode_display, 1)?[0] as i16 as i8);
            let p = c.read(a.node, m.position_actual, 2)?;
            d.position_counts = m.word_order.join_i32([p[0], p[1]]) as i64;
            let v = c.read(a.node, m.velocity_actual, 2)?;
            d.velocity_per_s = Some(m.word_order.join_i32([v[0], v[1]]) as f64 / a.counts_per_unit);
            if let Some(e) = m.error_code {
                d.error_code = c.read(a.node, e, 1)?[0];
            }
            // Shown, never needed: a drive that lacks it still answers the rest.
            if let Some(r) = m.digital_inputs {
                d.digital_inputs = c.read(a.node, r, 2).ok().map(|w| m.word_order.join_i32([w[0], w[1]]) as u32);
            }
        }
        Profile::Pr => {
            let m = a.pr_map.unwrap_or_default();
            d.profile = "pr";
            let st = c.read(a.node, m.status, 1)?[0];
            d.pr_status = Some(st);
            d.statusword = crate::drives::modbus::plan::pr_statusword(st);
            let p = c.read(a.node, m.position_actual, 2)?;
            d.position_counts = m.word_order.join_i32([p[0], p[1]]) as i64;
            if let Some(e) = m.alarm_code {
                d.error_code = c.read(a.node, e, 1)?[0];
            }
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
        "digital_inputs": d.digital_inputs,
        "round_trip_ms": d.round_trip_ms,
    })
}

/// `cncgw scan` on Modbus: every configured unit, whether it answers, its state.
pub fn scan(cfg: &MachineConfig, json: bool) -> i32 {
    let mut cl = match clients(cfg).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
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
        exit::NOT_MET
    } else {
        exit::OK
    }
}

/// `cncgw monitor` on Modbus: the same table from the registers, refreshed in place.
pub fn monitor(cfg: &MachineConfig, seconds: Option<f64>, once: bool, interval_ms: u64, json: bool) -> i32 {
    let links = match clients(cfg).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    let io = match super::service::io_monitor(cfg) {
        Ok(m) => m,
        Err(code) => return code,
    };
    let mut bus = ModbusMonitor { axes: axes(cfg), links, epoch: Instant::now() };
    super::service::monitor_loop(&mut bus, io, seconds, once, interval_ms, json)
}

/// The Modbus links of the monitor: each unit's row read through its `ModbusDrive`.
struct ModbusMonitor {
    axes: Vec<(String, AxisConfig, String)>,
    links: std::collections::BTreeMap<String, Client>,
    epoch: Instant,
}

impl super::service::MonitorBus for ModbusMonitor {
    fn noun(&self) -> &'static str {
        "unit"
    }
    fn now_ns(&mut self) -> u64 {
        self.epoch.elapsed().as_nanos() as u64
    }
    fn rows(&mut self) -> Vec<super::service::MonitorRow> {
        let mut rows = Vec::new();
        for (name, a, link) in &self.axes {
            // The link's one client lent to the unit's drive for its row (an RTU line opens once).
            let Some(c) = self.links.remove(link) else { continue };
            let mut d = ModbusDrive { c, a: a.clone(), name: name.clone(), epoch: self.epoch };
            rows.push(super::service::monitor_read(&mut d));
            self.links.insert(link.clone(), d.c);
        }
        rows
    }
    fn read_io(&mut self, m: &mut super::iomon::IoMonitor) -> super::iomon::IoRead {
        m.read(None)
    }
    fn status(&mut self, tick: u64, rows_done: u64, _: u64, n_rows: usize) -> (Vec<String>, serde_json::Map<String, serde_json::Value>) {
        let rtt = rows_done.saturating_sub(tick) as f64 * 1e-6;
        let line = format!("Modbus: the register reads of {n_rows} unit(s) took {rtt:.1} ms");
        let fields = serde_json::json!({"bus": "modbus", "poll_ms": rtt});
        (vec![line], fields.as_object().cloned().unwrap_or_default())
    }
    fn wait(&mut self, tick: u64, interval: u64, _: bool) {
        let now = self.now_ns();
        if tick + interval > now {
            std::thread::sleep(Duration::from_nanos(tick + interval - now));
        }
    }
}

// ---------------------------------------------------------------- drive enable/disable/home

/// The axis with Modbus unit id `unit` and a client on its link. Err = the exit code
/// (message printed).
fn open_unit(cfg: &MachineConfig, unit: u8) -> Result<(String, AxisConfig, Client), i32> {
    let Some((name, a, link)) = axes(cfg).into_iter().find(|(_, a, _)| a.node == unit) else {
        eprintln!("error: no axis of the configuration has Modbus unit id {unit} (`cncgw config check` lists them); Modbus registers are addressed through an axis's map");
        return Err(exit::INPUT);
    };
    match cfg.modbus.get(&link).ok_or_else(|| format!("no link {link}")).and_then(Client::connect) {
        Ok(c) => Ok((name, a, c)),
        Err(e) => {
            eprintln!("error: Modbus link {link}: {e}");
            Err(exit::SETUP)
        }
    }
}

/// The drive's error code (0x603F) or alarm code (PR) in words, for messages.
fn error_text(c: &mut Client, a: &AxisConfig) -> String {
    match a.modbus_profile {
        Profile::Cia402 => match a.cia402_map.unwrap_or_default().error_code.map(|r| c.read(a.node, r, 1)) {
            Some(Ok(v)) => format!("error code 0x{:04X} {}", v[0], cncgw_bus::canopen::emcy::error_text(v[0])),
            Some(Err(e)) => format!("error code unreadable ({e})"),
            None => "no error code register in the map".into(),
        },
        Profile::Pr => match a.pr_map.unwrap_or_default().alarm_code.map(|r| c.read(a.node, r, 1)) {
            Some(Ok(v)) => format!("alarm code 0x{:04X} (see the drive's manual)", v[0]),
            Some(Err(e)) => format!("alarm code unreadable ({e})"),
            None => "no alarm code register in the map".into(),
        },
    }
}

/// The drive's communication watchdog off. The controller's Modbus master sets it when it
/// starts and leaves it set; a drive a service command leaves enabled gets no cyclic
/// writes, so the watchdog would fault it (the CANopen side releases the heartbeat the
/// same way).
fn watchdog_off(c: &mut Client, a: &AxisConfig) -> Result<(), String> {
    let addr = match a.modbus_profile {
        Profile::Cia402 => a.cia402_map.unwrap_or_default().comm_timeout_ms,
        Profile::Pr => a.pr_map.unwrap_or_default().comm_timeout_ms,
    };
    // A drive without one has nothing to turn off.
    let Some(addr) = addr else { return Ok(()) };
    c.write(a.node, addr, &[0]).map_err(|e| format!("turning the communication watchdog (register {addr}) off failed: {e}"))
}

/// Step period of the homing's wait.
const STEP: Duration = Duration::from_millis(10);

/// A Modbus drive's CiA 402 objects through its register map: the `cia402_map`'s registers
/// (`Cia402Map::register`; 4-byte objects in two registers, in the map's word order), or a
/// PR drive's status register as a statusword (0x6041), its position (0x6064) and alarm
/// code (0x603F), with the controlword (0x6040) as servo on (voltage enabled and no quick
/// stop: bits 1 and 2) and alarm reset (bit 7).
pub struct ModbusDrive {
    pub c: Client,
    pub a: AxisConfig,
    pub name: String,
    epoch: Instant,
}

impl ModbusDrive {
    /// The axis with unit id `unit` and a client on its link. Err = the exit code (message
    /// printed).
    pub fn open(cfg: &MachineConfig, unit: u8) -> Result<ModbusDrive, i32> {
        let (name, a, c) = open_unit(cfg, unit)?;
        Ok(ModbusDrive { c, a, name, epoch: Instant::now() })
    }

    /// The register and its length in registers that carry `index`:`sub` of type `ty`.
    fn register(&self, index: u16, sub: u8, ty: ObjType) -> Result<(u16, u16, WordOrder), String> {
        let len = if ty.bytes() == 4 { 2 } else { 1 };
        let r = match self.a.modbus_profile {
            Profile::Cia402 => {
                let m = self.a.cia402_map.unwrap_or_default();
                m.register(index, sub).map(|r| (r, m.word_order))
            }
            Profile::Pr => {
                let m = self.a.pr_map.unwrap_or_default();
                match (index, sub) {
                    (0x6041, 0) => Some(m.status),
                    (0x6064, 0) => Some(m.position_actual),
                    (0x603F, 0) => m.alarm_code,
                    _ => None,
                }
                .map(|r| (r, m.word_order))
            }
        };
        r.map(|(r, o)| (r, len, o)).ok_or_else(|| format!("unit {}: the register map has no register for 0x{index:04X}:{sub}", self.a.node))
    }
}

impl DriveAccess for ModbusDrive {
    fn noun(&self) -> &'static str {
        "unit"
    }
    fn id(&self) -> u8 {
        self.a.node
    }
    fn label(&self) -> String {
        format!("unit {} (axis {}) on {}", self.a.node, self.name, self.c.what)
    }
    fn axis(&self) -> Option<(String, f64, bool)> {
        Some((self.name.clone(), self.a.counts_per_unit, self.a.kind == crate::config::AxisKind::Spindle))
    }
    fn read(&mut self, index: u16, sub: u8, ty: ObjType) -> Result<i64, String> {
        let (r, len, order) = self.register(index, sub, ty)?;
        let w = self.c.read(self.a.node, r, len)?;
        let raw = if len == 2 { order.join_i32([w[0], w[1]]) as u32 as u64 } else { w[0] as u64 };
        if self.a.modbus_profile == Profile::Pr && index == 0x6041 {
            return Ok(crate::drives::modbus::plan::pr_statusword(raw as u16) as i64);
        }
        Ok(ty.extend(raw))
    }
    fn write(&mut self, index: u16, sub: u8, ty: ObjType, value: i64) -> Result<(), String> {
        if self.a.modbus_profile == Profile::Pr && (index, sub) == (0x6040, 0) {
            let (m, c) = (self.a.pr_map.unwrap_or_default(), value as u16);
            return if c & cncgw_bus::cia402::cw::FAULT_RESET != 0 {
                self.c.write(self.a.node, m.alarm_reset, &[1])
            } else {
                self.c.write(self.a.node, m.servo_on, &[(c & 0x06 == 0x06) as u16])
            };
        }
        let (r, len, order) = self.register(index, sub, ty)?;
        let words = if len == 2 { order.split_i32(value as i32).to_vec() } else { vec![value as u16] };
        self.c.write(self.a.node, r, &words)
    }
    fn error_text(&mut self) -> String {
        error_text(&mut self.c, &self.a)
    }
    fn now_ns(&mut self) -> u64 {
        self.epoch.elapsed().as_nanos() as u64
    }
    fn wait_ns(&mut self, t: u64) {
        let now = self.now_ns();
        if t > now {
            std::thread::sleep(Duration::from_nanos(t - now));
        }
    }
    fn before_enable(&mut self) -> Result<(), String> {
        watchdog_off(&mut self.c, &self.a)
    }
    fn status_register(&mut self) -> Option<(&'static str, u16)> {
        match self.a.modbus_profile {
            Profile::Pr => self.c.read(self.a.node, self.a.pr_map.unwrap_or_default().status, 1).ok().map(|v| ("status register", v[0])),
            Profile::Cia402 => None,
        }
    }
}

/// `cncgw drive home UNIT` on Modbus (confirmation already given). CiA 402 map: homing
/// mode 6 through the mode register and a rising edge of controlword bit 4, with the
/// method, offset and speeds the drive has in its own parameters (the map has no 0x6098,
/// 0x607C, 0x6099 registers); attained (statusword bit 12) with target reached (bit 10)
/// ends it, bit 13 is a homing error. The drive is disabled after it, as on CANopen, and
/// its previous mode restored. The PR map has no homing.
pub fn drive_home(cfg: &MachineConfig, unit: u8, h: &super::service::HomeArgs) -> i32 {
    match home_unit(cfg, unit, h) {
        Ok(_) => exit::OK,
        Err(code) => code,
    }
}

/// One write of the homing: (first register, words, what it is).
type RegisterWrite = (u16, Vec<u16>, &'static str);

/// What the homing `h` (with the axis's `homing.accel`) would set that the map `m` has no
/// register for — each "what (map key; where it is set)". Empty: nothing missing. The
/// speeds, acceleration and a zero offset may be left to the drive's own parameters; the
/// method never is, not even 35 ("the present position is home"):
///
/// - Mode 6 on a drive whose method cncgw cannot write runs whatever method the drive has
///   in its own parameters — a switch or index search (17, 1–14, 33/34) is motion nobody
///   asked for, and the reference would be recorded "method 35" when it is not.
/// - A Fanuc (reference setting without dogs, No.1815 APZ) or an 828D ("set reference
///   point", MD34210) makes "here is home" a controller-side operation when the drive cannot:
///   the control keeps the shift between the encoder and machine coordinates. cncgw keeps
///   none — a machine position is the drive's position over `counts_per_unit`, in one place
///   for the run, jog, the stroke limits and the reference check at start — so a
///   controller-side 35 would leave the drive's coordinates and the machine's apart.
///
/// So a map without `homing_method` refuses every homing with alarm 2017 before anything is
/// written or moved; the operator gives the register, or takes the axis out of the reference
/// requirement (`absolute = true` when the drive keeps its position, else
/// `machine.require_reference = false`).
pub fn homing_missing(m: &cncgw_bus::modbus::Cia402Map, h: &super::service::HomeArgs, accel: Option<f64>) -> Vec<&'static str> {
    [
        (m.homing_method.is_none(), "homing method 0x6098 (homing_method; --method / homing.method)"),
        (h.offset != 0.0 && m.home_offset.is_none(), "home offset 0x607C (home_offset; --offset / homing.offset)"),
        (h.switch_speed.is_some() && m.homing_switch_speed.is_none(), "switch speed 0x6099:1 (homing_switch_speed; --switch-speed / homing.speed)"),
        (h.zero_speed.is_some() && m.homing_zero_speed.is_none(), "zero speed 0x6099:2 (homing_zero_speed; --zero-speed / homing.zero_speed)"),
        (accel.is_some() && m.homing_accel.is_none(), "homing acceleration 0x609A (homing_accel; homing.accel)"),
    ]
    .into_iter()
    .filter_map(|(absent, what)| absent.then_some(what))
    .collect()
}

/// The homing parameters as register writes (address, words, what) for the registers the
/// map has — the figures the CANopen homing writes (`service::homing_figures`), in counts.
/// Something asked for
/// that the map has no register for (`homing_missing`): alarm 2017, before anything is
/// written or moved.
fn homing_writes(a: &AxisConfig, m: &cncgw_bus::modbus::Cia402Map, h: &super::service::HomeArgs) -> Result<Vec<RegisterWrite>, crate::Alarm> {
    let accel = a.homing.as_ref().and_then(|c| c.accel);
    let missing = homing_missing(m, h, accel);
    if !missing.is_empty() {
        return Err(crate::Alarm::new(
            crate::alarm::HOMING,
            format!(
                "unit {}: homing method {} refused before any motion: the axis's CiA 402 register map has no register for the {} (\"none\" or not named in its cia402_map table: a map table names every register its drive has). Give the register's address in the map if the drive has it, else leave the value to the drive's own parameters (speeds, acceleration, offset 0). The method cannot be left, not even 35: mode 6 would run whatever method the drive has (its own may search a switch), and cncgw keeps no controller-side shift to make \"here is home\" itself; without a method register, home the drive with its own software and set `absolute = true` on the axis if it keeps its position, else `machine.require_reference = false`",
                a.node,
                h.method,
                missing.join(", ")
            ),
        ));
    }
    let bad = |e: String| crate::Alarm::new(crate::alarm::HOMING, format!("unit {}: {e}", a.node));
    let f = super::service::homing_figures(a, h).map_err(bad)?;
    let counts = |units: f64, what: &str| -> Result<[u16; 2], crate::Alarm> {
        let c = (units * a.counts_per_unit).abs().round();
        if !c.is_finite() || c < 1.0 || c > u32::MAX as f64 {
            return Err(bad(format!("the {what} {units} is out of the drive's range (1 to 2^32-1 counts)")));
        }
        Ok(m.word_order.split_i32(c as u32 as i32))
    };
    let mut w = Vec::new();
    if let Some(r) = m.homing_method {
        w.push((r, vec![h.method as i16 as u16], "homing method 0x6098"));
    }
    if let Some(r) = m.home_offset {
        w.push((r, m.word_order.split_i32(f.offset).to_vec(), "home offset 0x607C"));
    }
    if let Some(r) = m.homing_switch_speed {
        w.push((r, counts(f.switch_speed, "homing switch speed")?.to_vec(), "switch speed 0x6099:1"));
    }
    if let Some(r) = m.homing_zero_speed {
        w.push((r, counts(f.zero_speed, "homing zero speed")?.to_vec(), "zero speed 0x6099:2"));
    }
    if let Some(r) = m.homing_accel {
        w.push((r, counts(f.accel, "homing acceleration")?.to_vec(), "homing acceleration 0x609A"));
    }
    Ok(w)
}

/// `drive_home`'s work: the position after homing (machine units), or the exit code (the
/// message printed).
pub fn home_unit(cfg: &MachineConfig, unit: u8, h: &super::service::HomeArgs) -> Result<f64, i32> {
    use cncgw_bus::cia402::{cw, mode, HomingProgress};
    let mut d = ModbusDrive::open(cfg, unit)?;
    let (name, a) = (d.name.clone(), d.a.clone());
    if a.modbus_profile == Profile::Pr {
        eprintln!("error: unit {unit} (axis {name}) speaks the PR register map: homing is not supported by this register map (it has no mode or homing registers); home the axis with the drive's own software or panel, or set the position with a G92/G50 in the program");
        return Err(exit::INPUT);
    }
    let m = a.cia402_map.unwrap_or_default();
    let writes = match homing_writes(&a, &m, h) {
        Ok(w) => w,
        Err(alarm) => {
            eprintln!("{alarm}");
            eprintln!("nothing was written or moved");
            return Err(exit::INPUT);
        }
    };
    let timeout = match super::service::home_timeout_ms(h) {
        Ok(ms) => Duration::from_millis(ms.min(3_600_000)),
        Err(e) => {
            eprintln!("error: {e}");
            return Err(exit::INPUT);
        }
    };
    let run = |d: &mut ModbusDrive| -> Result<f64, String> {
        let before = d.c.read(unit, m.mode_display, 1)?[0];
        watchdog_off(&mut d.c, &a)?;
        // The homing parameters before the mode: a drive may take them as homing starts.
        for (addr, words, what) in &writes {
            d.c.write(unit, *addr, words).map_err(|e| format!("{e}: writing the {what} (register {addr})"))?;
        }
        d.c.write(unit, m.mode, &[mode::HOMING as u16])
            .map_err(|e| format!("{e}: the drive refused homing mode 6 in its mode register {}", m.mode))?;
        let homed = (|| {
            access::power_walk(d, access::PowerGoal::Enable, 2000)?;
            let shown = d.c.read(unit, m.mode_display, 1)?[0] as i16 as i8;
            if shown != mode::HOMING {
                return Err(format!(
                    "unit {unit} shows mode {shown} ({}) after mode 6 was written: it has no homing mode over Modbus",
                    mode::name(shown)
                ));
            }
            d.c.write(unit, m.controlword, &[cw::ENABLE_OPERATION_CMD])?;
            d.c.write(unit, m.controlword, &[HomingProgress::START])?;
            let end = Instant::now() + timeout;
            loop {
                let s = d.c.read(unit, m.statusword, 1)?[0];
                match HomingProgress::of(s) {
                    HomingProgress::Error => {
                        return Err(format!(
                            "unit {unit} reports a homing error (statusword 0x{s:04X} bit 13): {}; check the drive's homing method and switches",
                            error_text(&mut d.c, &a)
                        ))
                    }
                    _ if State::from_statusword(s) != State::OperationEnabled => {
                        return Err(format!(
                            "unit {unit} left Operation Enabled while homing ({}): {}",
                            State::from_statusword(s).name(),
                            error_text(&mut d.c, &a)
                        ))
                    }
                    HomingProgress::Attained => return Ok(()),
                    HomingProgress::Homing => {}
                }
                if Instant::now() >= end {
                    return Err(format!(
                        "unit {unit} not homed within {:.1} s (statusword 0x{s:04X}); give more --timeout or check the drive's homing method",
                        timeout.as_secs_f64()
                    ));
                }
                std::thread::sleep(STEP);
            }
        })();
        // Bit 4 down, torque off, the mode it had: whatever happened.
        let _ = d.c.write(unit, m.controlword, &[cw::ENABLE_OPERATION_CMD]);
        let _ = d.c.write(unit, m.controlword, &[cw::DISABLE_VOLTAGE]);
        if before as i16 as i8 != mode::HOMING && before != 0 {
            let _ = d.c.write(unit, m.mode, &[before]);
        }
        homed?;
        let p = d.c.read(unit, m.position_actual, 2)?;
        Ok(m.word_order.join_i32([p[0], p[1]]) as f64 / a.counts_per_unit)
    };
    let unit_s = if a.kind == crate::config::AxisKind::Spindle { "deg" } else { "mm" };
    match run(&mut d) {
        Ok(pos) => {
            println!("unit {unit} (axis {name}) on {}: homed in mode 6 with homing method {}; position now {pos:.4} {unit_s}", d.c.what, h.method);
            Ok(pos)
        }
        Err(e) => {
            eprintln!("error: {e}");
            Err(exit::NOT_MET)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bus(url: &str) -> super::super::BusKind {
        super::super::BusKind::parse(url).unwrap()
    }

    #[test]
    fn bus_urls() {
        let l = parse_bus_url("modbus-tcp://127.0.0.1:5020").unwrap().unwrap();
        assert_eq!((l.transport, l.address.as_deref()), (LinkTransport::Tcp, Some("127.0.0.1:5020")));
        let l = parse_bus_url("modbus-tcp://drive.local").unwrap().unwrap();
        assert_eq!(l.address.as_deref(), Some("drive.local:502"));
        let l = parse_bus_url("modbus-rtu:///dev/ttyUSB0?baud=57600&parity=even&stop_bits=2").unwrap().unwrap();
        assert_eq!(
            (l.transport, l.device.as_deref(), l.baud, l.parity, l.stop_bits),
            (LinkTransport::Rtu, Some("/dev/ttyUSB0"), 57600, Parity::Even, 2)
        );
        let l = parse_bus_url("modbus-rtu:///dev/ttyUSB0").unwrap().unwrap();
        assert_eq!((l.baud, l.parity), (115_200, Parity::None));
        assert!(parse_bus_url("modbus-rtu:///dev/ttyUSB0?baud=fast").unwrap().unwrap_err().contains("not a number"));
        assert!(parse_bus_url("modbus-rtu:///dev/ttyUSB0?speed=1").unwrap().unwrap_err().contains("unknown parameter `speed`"));
        assert!(parse_bus_url("modbus-rtu:///dev/x?parity=mark").unwrap().is_err());
        assert!(parse_bus_url("can0").is_none() && parse_bus_url("inproc").is_none());
        let mut cfg = MachineConfig::embedded();
        assert!(apply_bus(&mut cfg, Some(&bus("modbus-tcp://127.0.0.1:5020"))));
        assert!(!cfg.has_canopen());
        assert!(cfg.axes.values().all(|a| a.modbus.as_deref() == Some(BUS_LINK)));
        // No link in the configuration: the default timeout is held within the feedback
        // timeout (20 ms at a 2 ms cycle → at most 16 ms).
        assert_eq!(cfg.modbus[BUS_LINK].timeout_ms, 16);
    }

    /// Issue 18.5: `--bus` is parsed once; a Modbus URL's link and the parameters it gives
    /// come out of that one parse, with the same errors.
    #[test]
    fn a_modbus_bus_is_parsed_once_with_its_link() {
        use super::super::BusKind;
        let BusKind::Modbus(b) = bus("modbus-rtu:///dev/ttyUSB0?baud=57600&timeout_ms=30") else { panic!("not a Modbus bus") };
        assert_eq!(
            (b.link.device.as_deref(), b.link.baud, b.given.as_slice()),
            (Some("/dev/ttyUSB0"), 57600, &["baud".to_string(), "timeout_ms".to_string()][..])
        );
        assert!(BusKind::parse("modbus-rtu:///dev/x?baud=fast").unwrap_err().contains("not a number"));
        assert!(BusKind::parse("modbus-tcp://").unwrap_err().contains("give the drive's address"));
        let mut cfg = MachineConfig::embedded();
        assert!(!apply_bus(&mut cfg, Some(&bus("can0"))) && !apply_bus(&mut cfg, None) && cfg.has_canopen());
        let m = |b: Option<&str>| MachineArgs { config: None, bus: b.map(str::to_string), sim_config: None };
        assert!(m(None).on_embedded_bus(&cfg) && m(Some("inproc")).on_embedded_bus(&cfg));
        assert!(!m(Some("vcan0")).on_embedded_bus(&cfg) && !m(Some("modbus-tcp://127.0.0.1:5020")).on_embedded_bus(&cfg));
    }

    /// Issue 22: the service commands' RTU silence follows the line (a fixed 4 ms was short
    /// of 3.5 characters at 9600 baud with parity: 11 bits × 3.5 / 9600 = 4.01 ms).
    #[test]
    fn rtu_silence_is_three_and_a_half_characters_of_the_line() {
        let l = parse_bus_url("modbus-rtu:///dev/ttyS0?baud=9600&parity=even").unwrap().unwrap();
        let s = rtu_silence(&l).as_secs_f64() * 1e3;
        assert!((s - 4.0104).abs() < 0.001, "{s} ms");
        let l = parse_bus_url("modbus-rtu:///dev/ttyS0?baud=115200").unwrap().unwrap();
        assert!((rtu_silence(&l).as_secs_f64() * 1e3 - 1.75).abs() < 1e-9);
    }

    /// Issue 22: `--bus modbus-tcp://` keeps the configuration's link settings.
    #[test]
    fn bus_url_keeps_the_configured_link_settings() {
        let text = include_str!("../../config/lathe-modbus.toml").replace("# fc23 = true", "fc23 = true\ncycle_ms = 8");
        let mut cfg: MachineConfig = crate::config::MachineConfig::from_toml("lathe-modbus.toml", &text).unwrap();
        assert!(apply_bus(&mut cfg, Some(&bus("modbus-tcp://10.0.0.9:502"))));
        let l = &cfg.modbus[BUS_LINK];
        assert_eq!((l.address.as_deref(), l.timeout_ms, l.fc23, l.cycle_ms), (Some("10.0.0.9:502"), 20, true, Some(8.0)));
        let mut cfg: MachineConfig = crate::config::MachineConfig::from_toml("lathe-modbus.toml", &text).unwrap();
        assert!(apply_bus(&mut cfg, Some(&bus("modbus-rtu:///dev/ttyS1?timeout_ms=30"))));
        assert_eq!(cfg.modbus[BUS_LINK].timeout_ms, 30);
    }
}
