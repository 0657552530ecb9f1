//! Service commands: `scan`, `sdo read|write`, `nmt`, `drive status`. Read-only unless the
//! command itself is a write; nothing here enables a drive.

use super::OrSetup;
use super::{exit, open_or_exit, open_service_bus, MachineArgs, ServiceBus};
use crate::drives::access::{read_status, DriveAccess, DriveStatus};
use crate::drives::canopen::master::{mode_short, supported_modes_text, DriveProbe};
use crate::drives::canopen::sdo_client::SdoError;
use cncgw_bus::canopen::emcy::error_text;
use cncgw_bus::canopen::nmt::{NmtCommand, NmtState};
use cncgw_bus::cia402::{mode, State};
use serde_json::json;

/// Parse a number written in decimal or as 0x… hex (an optional leading '-' for decimal).
pub fn parse_int(s: &str) -> Result<i64, String> {
    let t = s.trim().replace('_', "");
    let (neg, body) = match t.strip_prefix('-') {
        Some(b) => (true, b.to_string()),
        None => (false, t.clone()),
    };
    let v = if let Some(h) = body.strip_prefix("0x").or_else(|| body.strip_prefix("0X")) { i64::from_str_radix(h, 16) } else { body.parse::<i64>() }
        .map_err(|_| format!("`{s}` is not a number (write decimal, or hex as 0x…)"))?;
    Ok(if neg { -v } else { v })
}

fn parse_ranged(s: &str, what: &str, lo: i64, hi: i64) -> Result<i64, String> {
    let v = parse_int(s)?;
    if v < lo || v > hi {
        return Err(format!("{what} {s} is out of range {lo}…{hi} (0x{hi:X})"));
    }
    Ok(v)
}

pub fn parse_node(s: &str) -> Result<u8, String> {
    parse_ranged(s, "node id", 1, 127).map(|v| v as u8)
}
pub fn parse_index(s: &str) -> Result<u16, String> {
    parse_ranged(s, "index", 0, 0xFFFF).map(|v| v as u16)
}
pub fn parse_sub(s: &str) -> Result<u8, String> {
    parse_ranged(s, "sub-index", 0, 0xFF).map(|v| v as u8)
}

/// The CANopen data types the `sdo` commands understand.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SdoType {
    U8,
    U16,
    U32,
    I8,
    I16,
    I32,
    F32,
    /// VISIBLE_STRING
    Str,
    /// DOMAIN: raw bytes, to or from a file
    Domain,
}

impl SdoType {
    fn size(self) -> Option<usize> {
        Some(match self {
            SdoType::U8 | SdoType::I8 => 1,
            SdoType::U16 | SdoType::I16 => 2,
            SdoType::U32 | SdoType::I32 | SdoType::F32 => 4,
            SdoType::Str | SdoType::Domain => return None,
        })
    }
    fn name(self) -> &'static str {
        match self {
            SdoType::U8 => "u8",
            SdoType::U16 => "u16",
            SdoType::U32 => "u32",
            SdoType::I8 => "i8",
            SdoType::I16 => "i16",
            SdoType::I32 => "i32",
            SdoType::F32 => "f32",
            SdoType::Str => "str",
            SdoType::Domain => "domain",
        }
    }
}

/// Encode `value` as `ty` (little-endian). Domain values are file names.
pub fn encode_value(ty: SdoType, value: &str) -> Result<Vec<u8>, String> {
    let int = |lo: i64, hi: i64| -> Result<i64, String> {
        let v = parse_int(value)?;
        if v < lo || v > hi {
            Err(format!("{value} does not fit in {}: range {lo}…{hi}", ty.name()))
        } else {
            Ok(v)
        }
    };
    Ok(match ty {
        SdoType::U8 => vec![int(0, u8::MAX as i64)? as u8],
        SdoType::U16 => (int(0, u16::MAX as i64)? as u16).to_le_bytes().to_vec(),
        SdoType::U32 => (int(0, u32::MAX as i64)? as u32).to_le_bytes().to_vec(),
        SdoType::I8 => vec![int(i8::MIN as i64, i8::MAX as i64)? as i8 as u8],
        SdoType::I16 => (int(i16::MIN as i64, i16::MAX as i64)? as i16).to_le_bytes().to_vec(),
        SdoType::I32 => (int(i32::MIN as i64, i32::MAX as i64)? as i32).to_le_bytes().to_vec(),
        SdoType::F32 => {
            let f: f32 = value.trim().parse().map_err(|_| format!("`{value}` is not a number (f32)"))?;
            if !f.is_finite() {
                return Err(format!("`{value}` is not a finite number"));
            }
            f.to_le_bytes().to_vec()
        }
        SdoType::Str => value.as_bytes().to_vec(),
        SdoType::Domain => std::fs::read(value).map_err(|e| format!("{value}: cannot read the domain file: {e}"))?,
    })
}

/// Decode `data` as `ty`: (text, JSON value). Err when the length does not match the type.
pub fn decode_value(ty: SdoType, data: &[u8]) -> Result<(String, serde_json::Value), String> {
    if let Some(n) = ty.size() {
        if data.len() != n {
            return Err(format!(
                "the node answered {} byte(s) ({}), but {} is {n} byte(s); try another --type, or none to see the raw bytes",
                data.len(),
                hex(data),
                ty.name()
            ));
        }
    }
    let le = |n: usize| -> u64 {
        let mut b = [0u8; 8];
        b[..n].copy_from_slice(&data[..n]);
        u64::from_le_bytes(b)
    };
    Ok(match ty {
        SdoType::U8 | SdoType::U16 | SdoType::U32 => {
            let n = data.len();
            let v = le(n);
            (format!("{v} (0x{v:0w$X})", w = n * 2), json!(v))
        }
        SdoType::I8 | SdoType::I16 | SdoType::I32 => {
            let n = data.len();
            let u = le(n);
            let shift = 64 - 8 * n as u32;
            let v = ((u << shift) as i64) >> shift;
            (format!("{v} (0x{u:0w$X})", w = n * 2), json!(v))
        }
        SdoType::F32 => {
            let v = f32::from_le_bytes([data[0], data[1], data[2], data[3]]);
            (format!("{v}"), json!(v))
        }
        SdoType::Str => {
            let s = String::from_utf8_lossy(data).trim_end_matches('\0').to_string();
            (format!("{s:?}"), json!(s))
        }
        SdoType::Domain => (format!("{} byte(s): {}", data.len(), hex(data)), json!(hex(data))),
    })
}

fn hex(data: &[u8]) -> String {
    data.iter().map(|b| format!("{b:02X}")).collect::<Vec<_>>().join(" ")
}

/// Without `--type`: numbers for 1, 2 and 4 bytes, text when it is printable, else bytes.
fn guess(data: &[u8]) -> (String, serde_json::Value, &'static str) {
    let ty = match data.len() {
        1 => Some(SdoType::U8),
        2 => Some(SdoType::U16),
        4 => Some(SdoType::U32),
        _ => None,
    };
    if let Some(ty) = ty {
        if let Ok((t, j)) = decode_value(ty, data) {
            return (t, j, ty.name());
        }
    }
    if !data.is_empty() && data.iter().all(|&b| (0x20..0x7F).contains(&b) || b == 0) {
        if let Ok((t, j)) = decode_value(SdoType::Str, data) {
            return (t, j, "str");
        }
    }
    let (t, j) = decode_value(SdoType::Domain, data).unwrap_or_else(|_| (hex(data), json!(hex(data))));
    (t, j, "domain")
}

/// An SDO failure in words, with what to do next.
pub fn sdo_error_text(e: &SdoError) -> String {
    match e {
        SdoError::Abort { code } => format!("SDO abort 0x{code:08X} {}", cncgw_bus::canopen::sdo::abort_text(*code)),
        SdoError::Timeout { .. } => format!("{e}; `cncgw scan` lists the nodes that answer"),
        SdoError::Protocol(_) => e.to_string(),
    }
}

fn nmt_name(st: Option<NmtState>) -> &'static str {
    match st {
        // A boot-up message means the node is now pre-operational (CiA 301).
        Some(NmtState::BootUp) => "pre-operational",
        Some(s) => s.name(),
        None => "unknown",
    }
}

// ---------------------------------------------------------------- scan

pub fn scan(machine: &MachineArgs, json_out: bool) -> i32 {
    let mut s = match open_service_bus(machine) {
        Ok(ServiceBus::Modbus(cfg)) => return super::mbus::scan(&cfg, json_out),
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let mut nodes = s.master.node_ids();
    nodes.sort_unstable();
    let mut rows = Vec::new();
    let mut failed = 0;
    for &node in &nodes {
        let axis = s.master.node_spec(node).map(|n| n.axis.clone()).unwrap_or_else(|| "-".into());
        match s.master.read_identity(&mut *s.clock, node) {
            Ok(info) => {
                let probe = s.master.probe(&mut *s.clock, node);
                rows.push((node, axis, Some((info, probe)), None::<String>));
            }
            Err(e) => {
                failed += 1;
                rows.push((node, axis, None, Some(sdo_error_text(&e))));
            }
        }
    }
    // A node whose state is still unknown but that produces a heartbeat: wait for one.
    let longest = rows
        .iter()
        .filter(|r| s.master.nmt_state(r.0).is_none())
        .filter_map(|r| r.2.as_ref().and_then(|(_, p)| p.producer_heartbeat_ms.as_ref().and_then(|h| h.as_ref().ok().copied())))
        .max()
        .unwrap_or(0);
    if longest > 0 {
        s.master.listen(&mut *s.clock, (longest as u64 * 3 / 2).min(5000));
    }
    if json_out {
        let arr: Vec<_> = rows
            .iter()
            .map(|(node, axis, got, err)| {
                let st = s.master.nmt_state(*node);
                let info = got.as_ref().map(|g| &g.0);
                let probe = got.as_ref().map(|g| probe_json(&g.1));
                json!({
                    "node": node,
                    "axis": axis,
                    "vendor": info.and_then(|i| i.vendor),
                    "product": info.and_then(|i| i.product),
                    "revision": info.and_then(|i| i.revision),
                    "serial": info.and_then(|i| i.serial),
                    "device_type": info.map(|i| i.device_type),
                    "name": info.map(|i| i.name.clone()),
                    "nmt_state": st.map(|_| nmt_name(st)),
                    "nmt_heard": st.map(|s| if s == NmtState::BootUp { "boot-up" } else { "heartbeat" }),
                    "heartbeat_ms": got.as_ref().and_then(|g| g.1.producer_heartbeat_ms.clone().and_then(|r| r.ok())),
                    "modes": probe.as_ref().map(|p| p["modes"].clone()),
                    "sync": probe.as_ref().map(|p| p["sync"].clone()),
                    "units": probe.as_ref().map(|p| p["units"].clone()),
                    "error_control": probe.as_ref().map(|p| p["error_control"].clone()),
                    "error": err,
                })
            })
            .collect();
        println!("{}", json!({ "bus": s.bus, "simulated": s.simulated, "nodes": arr }));
    } else {
        println!("bus {} — {} node(s) in the configuration", s.what, nodes.len());
        println!(
            "{:>4} {:<5} {:<10} {:<10} {:<10} {:<10} {:<11} {:<20} {:<16} heartbeat",
            "node", "axis", "vendor", "product", "revision", "serial", "device type", "name", "NMT state"
        );
        for (node, axis, got, err) in &rows {
            match got {
                Some((i, p)) => {
                    let st = s.master.nmt_state(*node);
                    let hb = match &p.producer_heartbeat_ms {
                        Some(Ok(0)) => "off".to_string(),
                        Some(Ok(ms)) => format!("{ms} ms"),
                        Some(Err(_)) => "unreadable".to_string(),
                        None => "none".to_string(),
                    };
                    let id = |v: Option<u32>| v.map_or_else(|| format!("{:<10}", "unreadable"), |v| format!("0x{v:08X}"));
                    println!(
                        "{node:>4} {axis:<5} {} {} {} {} 0x{:08X}  {:<20} {:<16} {hb}",
                        id(i.vendor),
                        id(i.product),
                        id(i.revision),
                        id(i.serial),
                        i.device_type,
                        i.name,
                        nmt_name(st)
                    );
                    for line in probe_lines(p) {
                        println!("           {line}");
                    }
                }
                None => println!("{node:>4} {axis:<5} no answer: {}", err.as_deref().unwrap_or("")),
            }
        }
        if failed > 0 {
            eprintln!("{failed} node(s) did not answer: check power, wiring, bitrate and node ids (`--bus`, `--config`)");
        }
    }
    if failed > 0 {
        exit::NOT_MET
    } else {
        exit::OK
    }
}

/// A probed value in words: its text, "absent" where the drive lacks the object, or the
/// failure.
fn probed<T>(v: &Option<Result<T, String>>, f: impl Fn(&T) -> String) -> String {
    match v {
        None => "absent".into(),
        Some(Ok(x)) => f(x),
        Some(Err(e)) => format!("unreadable ({e})"),
    }
}

/// Modes, SYNC, units and error control of one node, one line each (`scan`).
fn probe_lines(p: &DriveProbe) -> Vec<String> {
    let modes = probed(&p.supported_modes, |b| format!("{} (0x6502 = 0x{b:08X})", supported_modes_text(*b)));
    let active = probed(&p.mode_display, |m| mode_short(*m));
    let sync = probed(&p.sync_cob, |c| {
        if c & 0x4000_0000 != 0 {
            format!("PRODUCER (0x1005 = 0x{c:08X}): it sends SYNC itself")
        } else {
            format!("consumer (0x1005 = 0x{c:08X})")
        }
    });
    vec![
        format!("modes: {modes}; active: {active}"),
        format!("SYNC: {sync}"),
        format!("units: {} ({})", p.scaling.unit_text(), p.scaling.describe()),
        format!("error control: {}", error_control_text(p)),
    ]
}

fn error_control_text(p: &DriveProbe) -> String {
    let hb = probed(&p.producer_heartbeat_ms, |ms| if *ms == 0 { "off".into() } else { format!("{ms} ms") });
    let consumer = probed(&p.consumer_heartbeat, |v| {
        if v.is_empty() {
            "none set".into()
        } else {
            v.iter().map(|(n, ms)| format!("node {n} within {ms} ms")).collect::<Vec<_>>().join(", ")
        }
    });
    let guard = match (&p.guard_time_ms, &p.life_time_factor) {
        (None, _) | (_, None) => "absent".to_string(),
        (Some(Ok(0)), _) | (_, Some(Ok(0))) => "off".to_string(),
        (Some(Ok(g)), Some(Ok(f))) => format!("{g} ms × {f}"),
        _ => "unreadable".to_string(),
    };
    format!("heartbeat {hb}; consumes heartbeat (0x1016): {consumer}; node guarding (0x100C/0x100D): {guard}")
}

fn probe_json(p: &DriveProbe) -> serde_json::Value {
    let res = |v: &Option<Result<serde_json::Value, String>>| match v {
        None => json!(null),
        Some(Ok(x)) => x.clone(),
        Some(Err(e)) => json!({ "error": e }),
    };
    let map = |v: &Option<Result<u32, String>>, f: &dyn Fn(u32) -> serde_json::Value| v.clone().map(|r| r.map(f));
    let s = &p.scaling;
    json!({
        "modes": {
            "supported": res(&map(&p.supported_modes, &|b| json!(b))),
            "supported_names": res(&map(&p.supported_modes, &|b| json!(supported_modes_text(b)))),
            "active": res(&p.mode_display.clone().map(|r| r.map(|m| json!(m)))),
            "active_name": res(&p.mode_display.clone().map(|r| r.map(|m| json!(mode_short(m))))),
        },
        "sync": {
            "cob_id": res(&map(&p.sync_cob, &|c| json!(c))),
            "producer": res(&map(&p.sync_cob, &|c| json!(c & 0x4000_0000 != 0))),
        },
        "units": {
            "encoder": s.encoder.map(|(i, r)| json!({ "increments": i, "revolutions": r })),
            "gear_ratio": s.gear.map(|(m, r)| json!({ "motor_revolutions": m, "shaft_revolutions": r })),
            "feed_constant": s.feed.map(|(f, r)| json!({ "feed": f, "shaft_revolutions": r })),
            "polarity": s.polarity,
            "increments_per_unit": s.increments_per_unit(),
            "units_per_motor_rev": s.units_per_rev(),
            "text": s.unit_text(),
        },
        "error_control": {
            "heartbeat_ms": res(&p.producer_heartbeat_ms.clone().map(|r| r.map(|v| json!(v)))),
            "consumer_heartbeat": res(&p.consumer_heartbeat.clone().map(|r| r.map(|v| json!(v.iter().map(|(n, ms)| json!({ "node": n, "ms": ms })).collect::<Vec<_>>())))),
            "guard_time_ms": res(&p.guard_time_ms.clone().map(|r| r.map(|v| json!(v)))),
            "life_time_factor": res(&p.life_time_factor.clone().map(|r| r.map(|v| json!(v)))),
        },
    })
}

// ---------------------------------------------------------------- sdo

pub fn sdo_read(machine: &MachineArgs, node: u8, index: u16, sub: u8, ty: Option<SdoType>, out: Option<&std::path::Path>, json_out: bool) -> i32 {
    let mut s = match open_or_exit(machine) {
        Ok(s) => s,
        Err(c) => return c,
    };
    s.master.ensure_node(node);
    let data = match s.master.sdo_upload(&mut *s.clock, node, index, sub) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: node {node} 0x{index:04X}:{sub:02X}: {}", sdo_error_text(&e));
            return exit::NOT_MET;
        }
    };
    if let Some(path) = out {
        if let Err(e) = std::fs::write(path, &data) {
            eprintln!("error: {}: cannot write: {e}", path.display());
            return exit::SETUP;
        }
    }
    let (text, val, tname) = match ty {
        Some(t) => match decode_value(t, &data) {
            Ok((a, b)) => (a, b, t.name()),
            Err(e) => {
                eprintln!("error: node {node} 0x{index:04X}:{sub:02X}: {e}");
                return exit::INPUT;
            }
        },
        None => guess(&data),
    };
    if json_out {
        println!("{}", json!({"node": node, "index": format!("0x{index:04X}"), "sub": sub, "type": tname, "value": val, "raw": hex(&data)}));
    } else {
        let saved = out.map(|p| format!(" → {}", p.display())).unwrap_or_default();
        println!("node {node} 0x{index:04X}:{sub:02X} = {text} [{tname}]{saved}");
    }
    exit::OK
}

/// Objects whose write can set a motor in motion: they need `--yes` on a real bus.
fn moves_iron(index: u16) -> bool {
    matches!(index, 0x6040 | 0x6060 | 0x607A | 0x60FF | 0x6071 | 0x60B0..=0x60B2 | 0x6081 | 0x6098..=0x609A)
}

#[allow(clippy::too_many_arguments)]
pub fn sdo_write(machine: &MachineArgs, node: u8, index: u16, sub: u8, ty: SdoType, value: &str, yes: bool) -> i32 {
    let _bus_lock = match super::lock::for_writing(machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    let data = match encode_value(ty, value) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: {e}");
            return exit::INPUT;
        }
    };
    // Refuse before touching the bus: the effective bus is --bus, else the config's.
    let (bus, embedded) = match super::load_config(machine.config.as_deref()) {
        Ok((c, _)) => (machine.bus.clone().unwrap_or_else(|| c.bus.interface.clone()), machine.on_embedded_bus(&c)),
        Err(e) => {
            eprintln!("error: {e}");
            return exit::SETUP;
        }
    };
    if moves_iron(index) && !embedded && !yes {
        eprintln!("error: writing 0x{index:04X} can set a motor in motion on {bus}; make sure the axis is free to move, then repeat with --yes");
        return exit::INPUT;
    }
    let mut s = match open_or_exit(machine) {
        Ok(s) => s,
        Err(c) => return c,
    };
    s.master.ensure_node(node);
    match s.master.sdo_download(&mut *s.clock, node, index, sub, &data) {
        Ok(()) => {
            let shown = if ty == SdoType::Domain { format!("{} byte(s) from {value}", data.len()) } else { value.to_string() };
            println!("node {node} 0x{index:04X}:{sub:02X} ← {shown} [{}]: ok", ty.name());
            exit::OK
        }
        Err(e) => {
            eprintln!("error: node {node} 0x{index:04X}:{sub:02X}: {}", sdo_error_text(&e));
            exit::NOT_MET
        }
    }
}

// ---------------------------------------------------------------- nmt

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum NmtArg {
    /// Start remote node: to operational (PDOs run).
    Start,
    /// Stop remote node: to stopped (only NMT and heartbeat).
    Stop,
    /// Enter pre-operational (SDO, no PDOs).
    Preop,
    /// Reset node (application and communication parameters).
    Reset,
    /// Reset communication parameters only.
    ResetComm,
}

impl NmtArg {
    fn command(self) -> NmtCommand {
        match self {
            NmtArg::Start => NmtCommand::Start,
            NmtArg::Stop => NmtCommand::Stop,
            NmtArg::Preop => NmtCommand::EnterPreOperational,
            NmtArg::Reset => NmtCommand::ResetNode,
            NmtArg::ResetComm => NmtCommand::ResetCommunication,
        }
    }
    fn expected(self) -> NmtState {
        match self {
            NmtArg::Start => NmtState::Operational,
            NmtArg::Stop => NmtState::Stopped,
            _ => NmtState::PreOperational,
        }
    }
}

/// `NODE` or `all` (0 on the wire).
pub fn parse_target(s: &str) -> Result<u8, String> {
    if s.eq_ignore_ascii_case("all") {
        Ok(0)
    } else {
        parse_node(s).map_err(|e| format!("{e}, or `all`"))
    }
}

pub fn nmt(machine: &MachineArgs, cmd: NmtArg, target: u8, json_out: bool) -> i32 {
    let _bus_lock = match super::lock::for_writing(machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    let mut s = match open_or_exit(machine) {
        Ok(s) => s,
        Err(c) => return c,
    };
    if target != 0 {
        s.master.ensure_node(target);
    }
    let mut nodes: Vec<u8> = if target == 0 { s.master.node_ids() } else { vec![target] };
    nodes.sort_unstable();
    if let Err(a) = s.master.nmt_command(target, cmd.command()) {
        eprintln!("{a}");
        return exit::SETUP;
    }
    if matches!(cmd, NmtArg::Reset) {
        // Reset node restarts the drive's application: its position, and the reference.
        super::home::record_reset(machine, target);
    }
    let reset = matches!(cmd, NmtArg::Reset | NmtArg::ResetComm);
    // A reset is confirmed by the boot-up message; other commands by the next heartbeat.
    let window_ms: u64 = if reset { 3000 } else { 1000 };
    let end = s.clock.now_ns() + window_ms * 1_000_000;
    while s.clock.now_ns() < end {
        s.master.listen(&mut *s.clock, 5);
        let done = nodes.iter().all(|&n| if reset { s.master.booted(n) } else { s.master.nmt_state(n).is_some() });
        if done {
            break;
        }
    }
    let mut bad = 0;
    let mut out = Vec::new();
    for &n in &nodes {
        let st = s.master.nmt_state(n);
        let confirmed = match st {
            Some(NmtState::BootUp) => cmd.expected() == NmtState::PreOperational,
            Some(x) => x == cmd.expected(),
            None => false,
        };
        let note = if confirmed {
            format!("now {}", nmt_name(st))
        } else if st.is_some() {
            bad += 1;
            format!("reports {}, expected {}: check the node's NMT handling", nmt_name(st), cmd.expected().name())
        } else if reset {
            bad += 1;
            format!("no boot-up within {window_ms} ms: check power and the node id")
        } else {
            "sent; not confirmed: no heartbeat heard (0x1017 = 0?); `cncgw scan` shows the state".to_string()
        };
        out.push((n, st, confirmed, note));
    }
    if json_out {
        let arr: Vec<_> =
            out.iter().map(|(n, st, c, note)| json!({"node": n, "nmt_state": st.map(|_| nmt_name(*st)), "confirmed": c, "note": note})).collect();
        println!("{}", json!({"command": format!("{cmd:?}").to_lowercase(), "target": target, "nodes": arr}));
    } else {
        let who = if target == 0 { "all nodes".to_string() } else { format!("node {target}") };
        println!("NMT {} → {who} on {}", cmd_name(cmd), s.what);
        for (n, _, _, note) in &out {
            println!("  node {n}: {note}");
        }
        if s.simulated {
            println!("  (embedded emulated drives: they start fresh with every command)");
        }
    }
    if bad > 0 {
        exit::NOT_MET
    } else {
        exit::OK
    }
}

fn cmd_name(c: NmtArg) -> &'static str {
    match c {
        NmtArg::Start => "start",
        NmtArg::Stop => "stop",
        NmtArg::Preop => "enter pre-operational",
        NmtArg::Reset => "reset node",
        NmtArg::ResetComm => "reset communication",
    }
}

// ---------------------------------------------------------------- drive status

/// Statusword bit names (CiA 402-2 Table 29); bits 12/13 by mode of operation.
pub fn statusword_bits(sw: u16, mode_code: i8) -> Vec<(u8, String, bool)> {
    let oms12 = match mode_code {
        mode::CYCLIC_SYNC_POSITION | mode::CYCLIC_SYNC_VELOCITY | mode::CYCLIC_SYNC_TORQUE => "drive follows the command value",
        mode::PROFILE_POSITION => "set-point acknowledge",
        mode::PROFILE_VELOCITY => "speed is zero",
        mode::HOMING => "homing attained",
        _ => "operation mode specific",
    };
    let oms13 = match mode_code {
        mode::CYCLIC_SYNC_POSITION | mode::PROFILE_POSITION => "following error",
        mode::PROFILE_VELOCITY => "max slippage error",
        mode::HOMING => "homing error",
        _ => "operation mode specific",
    };
    let names: [&str; 16] = [
        "ready to switch on",
        "switched on",
        "operation enabled",
        "fault",
        "voltage enabled",
        "quick stop (0 = quick stop active)",
        "switch on disabled",
        "warning",
        "manufacturer specific",
        "remote",
        "target reached",
        "internal limit active",
        oms12,
        oms13,
        "manufacturer specific",
        "manufacturer specific",
    ];
    names.iter().enumerate().map(|(b, n)| (b as u8, n.to_string(), sw & (1 << b) != 0)).collect()
}

/// `cncgw drive status NODE`: one drive's state, the same for every bus.
pub fn drive_status(machine: &MachineArgs, node: u8, json_out: bool) -> i32 {
    let mut s = match open_service_bus(machine) {
        Ok(ServiceBus::Modbus(cfg)) => {
            let mut d = match super::mbus::ModbusDrive::open(&cfg, node) {
                Ok(d) => d,
                Err(code) => return code,
            };
            let t0 = std::time::Instant::now();
            let st = read_status(&mut d);
            let rtt = t0.elapsed().as_secs_f64() * 1e3;
            let profile = if st.as_ref().is_ok_and(|s| s.status_register.is_some()) { "pr" } else { "cia402" };
            let extra = json!({"unit": node, "profile": profile, "bus": d.c.what, "round_trip_ms": rtt});
            return status_report(&mut d, st, json_out, extra, vec![format!("round trip {rtt:.1} ms for the register reads")]);
        }
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let mut d = super::service::SdoDrive::new(&mut s, node);
    let st = read_status(&mut d);
    let emcy = d.s.master.last_emcy(node);
    let extra = json!({
        "last_emcy": emcy.map(|e| json!({"code": format!("0x{:04X}", e.code), "text": error_text(e.code), "register": e.register})),
    });
    let line = match emcy {
        Some(e) => format!("last EMCY: 0x{:04X} {} (error register 0x{:02X})", e.code, error_text(e.code), e.register),
        None => "last EMCY: none heard".into(),
    };
    status_report(&mut d, st, json_out, extra, vec![line])
}

/// Print a drive's status (`extra`: the bus's own JSON fields and lines) and return the exit
/// code: `NOT_MET` for a drive that does not answer or is in fault.
fn status_report(d: &mut dyn DriveAccess, st: Result<DriveStatus, String>, json_out: bool, extra: serde_json::Value, lines: Vec<String>) -> i32 {
    let st = match st {
        Ok(st) => st,
        Err(e) => {
            eprintln!("error: {e}");
            return exit::NOT_MET;
        }
    };
    let (sw, state) = (st.statusword, st.state());
    let bits = statusword_bits(sw, st.mode.unwrap_or(0));
    let axis = d.axis();
    let (cpu, unit) = match &axis {
        Some((_, k, spindle)) => (Some(*k), if *spindle { "deg" } else { "mm" }),
        None => (None, ""),
    };
    let units = |c: Option<i64>| c.and_then(|c| cpu.map(|k| c as f64 / k));
    // A PR drive's alarm code is the vendor's, not a CiA 301 error code.
    let cia402 = st.status_register.is_none();
    if json_out {
        let mut v = json!({
            "node": d.id(),
            "axis": axis.as_ref().map(|a| a.0.clone()),
            "statusword": format!("0x{sw:04X}"),
            "state": state.name(),
            "pr_status": st.status_register.map(|(_, r)| format!("0x{r:04X}")),
            "bits": bits.iter().map(|(b, n, set)| json!({"bit": b, "name": n, "set": set})).collect::<Vec<_>>(),
            "mode": st.mode,
            "mode_name": st.mode.map(mode::name),
            "position_counts": st.position,
            "position": units(st.position),
            "velocity_counts_per_s": st.velocity,
            "velocity_per_s": units(st.velocity),
            "following_error_counts": st.following_error,
            "following_error": units(st.following_error),
            "unit": if unit.is_empty() { None } else { Some(unit) },
            "unit_of_position": if unit.is_empty() { None } else { Some(unit) },
            "error_code": st.error_code.map(|e| format!("0x{e:04X}")),
            "error_text": st.error_code.filter(|_| cia402).map(error_text),
            "digital_inputs": st.digital_inputs,
        });
        if let (Some(v), serde_json::Value::Object(extra)) = (v.as_object_mut(), extra) {
            v.extend(extra);
        }
        println!("{v}");
    } else {
        println!("{}: {}", d.label(), state.name());
        match st.status_register {
            Some((what, r)) => println!("{what} = 0x{r:04X}, as a CiA 402 statusword 0x{sw:04X}"),
            None => println!("statusword 0x6041 = 0x{sw:04X}"),
        }
        for (b, n, set) in &bits {
            println!("  bit {b:>2} {} {n}", if *set { "1" } else { "0" });
        }
        let show = |c: Option<i64>, what: &str| match (c, units(c)) {
            (Some(c), Some(u)) => format!("{c} {what} = {u:.4} {unit}"),
            (Some(c), None) => format!("{c} {what}"),
            (None, _) => "- (not readable)".to_string(),
        };
        match st.mode {
            Some(m) => println!("mode 0x6061 = {m} ({})", mode::name(m)),
            None => println!("mode 0x6061 = - (not readable)"),
        }
        println!("position 0x6064 = {}", show(st.position, "counts"));
        println!("velocity 0x606C = {}", show(st.velocity, "counts/s").replace(&format!(" {unit}"), &format!(" {unit}/s")));
        println!("following error 0x60F4 = {}", show(st.following_error, "counts"));
        match (st.error_code, cia402) {
            (Some(e), true) => println!("error code 0x603F = 0x{e:04X} {}", error_text(e)),
            (Some(e), false) => println!("alarm code = 0x{e:04X}{}", if e == 0 { " (none)" } else { " (see the drive's manual)" }),
            (None, _) => println!("error code 0x603F = - (not readable)"),
        }
        if let Some(i) = st.digital_inputs {
            println!("digital inputs 0x60FD = 0x{i:08X}");
        }
        for l in lines {
            println!("{l}");
        }
        if matches!(state, State::Fault | State::FaultReactionActive) {
            println!("the drive is in fault: clear the cause shown above, then reset the fault");
        }
    }
    if matches!(state, State::Fault | State::FaultReactionActive) {
        exit::NOT_MET
    } else {
        exit::OK
    }
}

/// `cncgw od check NODE --eds FILE`.
pub fn od_check(machine: &MachineArgs, node: u8, eds_path: &std::path::Path, json_out: bool) -> i32 {
    let eds = match cncgw_bus::canopen::eds::Eds::load(eds_path).or_setup() {
        Ok(e) => e,
        Err(code) => return code,
    };
    let mut s = match open_or_exit(machine) {
        Ok(s) => s,
        Err(c) => return c,
    };
    let mut msgs = Vec::new();
    if s.master.node_spec(node).is_some() {
        msgs.extend(s.master.check_eds(node, &eds));
    }
    msgs.extend(s.master.check_od(&mut *s.clock, node, &eds));
    if json_out {
        println!(
            "{}",
            json!({"node": node, "eds": eds.file, "objects": eds.entries.len(), "agrees": msgs.is_empty(), "disagreements": msgs.iter().map(|m| m.to_string()).collect::<Vec<_>>()})
        );
        return if msgs.is_empty() { 0 } else { 1 };
    }
    for m in &msgs {
        println!("{m}");
    }
    if msgs.is_empty() {
        println!("node {node} agrees with {} ({} objects)", eds.file, eds.entries.len());
        0
    } else {
        println!("{} disagreement(s) between node {node} and {}", msgs.len(), eds.file);
        1
    }
}

// ---------------------------------------------------------------- od dump

/// The objects `od dump` reads without an EDS: CiA 301 communication and identity objects
/// and the CiA 402 objects a drive of this controller uses.
const STANDARD_OBJECTS: &[(u16, u8, &str, SdoType)] = &[
    (0x1000, 0, "Device type", SdoType::U32),
    (0x1001, 0, "Error register", SdoType::U8),
    (0x1008, 0, "Manufacturer device name", SdoType::Str),
    (0x1009, 0, "Manufacturer hardware version", SdoType::Str),
    (0x100A, 0, "Manufacturer software version", SdoType::Str),
    (0x1016, 1, "Consumer heartbeat time 1", SdoType::U32),
    (0x1017, 0, "Producer heartbeat time", SdoType::U16),
    (0x1018, 1, "Identity: vendor id", SdoType::U32),
    (0x1018, 2, "Identity: product code", SdoType::U32),
    (0x1018, 3, "Identity: revision number", SdoType::U32),
    (0x1018, 4, "Identity: serial number", SdoType::U32),
    (0x603F, 0, "Error code", SdoType::U16),
    (0x6040, 0, "Controlword", SdoType::U16),
    (0x6041, 0, "Statusword", SdoType::U16),
    (0x605A, 0, "Quick stop option code", SdoType::I16),
    (0x6060, 0, "Modes of operation", SdoType::I8),
    (0x6061, 0, "Modes of operation display", SdoType::I8),
    (0x6064, 0, "Position actual value", SdoType::I32),
    (0x6065, 0, "Following error window", SdoType::U32),
    (0x606C, 0, "Velocity actual value", SdoType::I32),
    (0x607A, 0, "Target position", SdoType::I32),
    (0x607C, 0, "Home offset", SdoType::I32),
    (0x6081, 0, "Profile velocity", SdoType::U32),
    (0x6083, 0, "Profile acceleration", SdoType::U32),
    (0x6098, 0, "Homing method", SdoType::I8),
    (0x60C2, 1, "Interpolation time period value", SdoType::U8),
    (0x60F4, 0, "Following error actual value", SdoType::I32),
    (0x6502, 0, "Supported drive modes", SdoType::U32),
];

/// The `sdo` type for a CiA 306 DataType code, where there is one.
fn sdo_type_of(dt: u16) -> Option<SdoType> {
    Some(match dt {
        0x0001 | 0x0005 => SdoType::U8,
        0x0002 => SdoType::I8,
        0x0003 => SdoType::I16,
        0x0004 => SdoType::I32,
        0x0006 => SdoType::U16,
        0x0007 => SdoType::U32,
        0x0008 => SdoType::F32,
        0x0009 => SdoType::Str,
        0x000F => SdoType::Domain,
        _ => return None,
    })
}

/// `cncgw od dump NODE [--eds FILE]`: every object as the drive reports it — the EDS's
/// objects, checked against it (present, size of the type, write-only not readable), or
/// without an EDS the standard objects. Read-only.
pub fn od_dump(machine: &MachineArgs, node: u8, eds_path: Option<&std::path::Path>, json_out: bool) -> i32 {
    let eds = match eds_path.map(cncgw_bus::canopen::eds::Eds::load).transpose().or_setup() {
        Ok(e) => e,
        Err(code) => return code,
    };
    let mut s = match open_or_exit(machine) {
        Ok(s) => s,
        Err(c) => return c,
    };
    s.master.ensure_node(node);
    // (index, sub, name, type, access, where in the EDS)
    type Obj = (u16, u8, String, Option<SdoType>, Option<cncgw_bus::canopen::eds::EdsAccess>, Option<String>);
    let list: Vec<Obj> = match &eds {
        Some(e) => e
            .entries
            .values()
            .map(|x| (x.index, x.sub, x.name.clone(), sdo_type_of(x.data_type), Some(x.access), e.describe(x.index, x.sub)))
            .collect(),
        None => STANDARD_OBJECTS.iter().map(|(i, sub, n, t)| (*i, *sub, n.to_string(), Some(*t), None, None)).collect(),
    };
    let mut rows = Vec::new();
    let mut bad = 0usize;
    for (index, sub, name, ty, access, at) in list {
        let r = s.master.sdo_upload(&mut *s.clock, node, index, sub);
        let wo = access == Some(cncgw_bus::canopen::eds::EdsAccess::Wo);
        let (value, raw, problem) = match r {
            Ok(d) => {
                let shown = match ty {
                    Some(t) => decode_value(t, &d),
                    None => Ok({
                        let (a, b, _) = guess(&d);
                        (a, b)
                    }),
                };
                match shown {
                    Ok((text, val)) => {
                        let p = wo.then(|| "AccessType=wo but it can be read".to_string());
                        (Some((text, val)), Some(hex(&d)), p)
                    }
                    Err(e) => (None, Some(hex(&d)), Some(e)),
                }
            }
            Err(SdoError::Abort { code }) if wo && code == cncgw_bus::canopen::sdo::abort::WRITE_ONLY => (None, None, None),
            Err(e) => {
                let absent = matches!(e, SdoError::Abort { code } if code == cncgw_bus::canopen::sdo::abort::NO_OBJECT || code == cncgw_bus::canopen::sdo::abort::NO_SUBINDEX);
                // Without an EDS an absent optional object is not a fault.
                let p = if absent && eds.is_none() { None } else { Some(sdo_error_text(&e)) };
                (None, None, p)
            }
        };
        if problem.is_some() {
            bad += 1;
        }
        rows.push((index, sub, name, ty, access, at, value, raw, problem));
    }
    if json_out {
        let arr: Vec<_> = rows
            .iter()
            .map(|(i, sub, n, t, a, at, v, raw, p)| {
                json!({
                    "index": format!("0x{i:04X}"), "sub": sub, "name": n, "type": t.map(|t| t.name()),
                    "access": a.map(|a| a.name()), "eds": at, "value": v.as_ref().map(|v| v.1.clone()),
                    "raw": raw, "problem": p,
                })
            })
            .collect();
        println!("{}", json!({"node": node, "eds": eds.as_ref().map(|e| e.file.clone()), "objects": arr, "disagreements": bad}));
    } else {
        println!(
            "node {node}: {} object(s){} on {}",
            rows.len(),
            eds.as_ref().map(|e| format!(" of {}", e.file)).unwrap_or_else(|| " (CiA 301/402 standard set; --eds FILE for all of a device's)".into()),
            s.what
        );
        for (i, sub, n, t, a, _at, v, _raw, p) in &rows {
            let ty = t.map(|t| t.name()).unwrap_or("?");
            let acc = a.map(|a| format!(" {}", a.name())).unwrap_or_default();
            let val = match (v, p) {
                (Some(v), _) => v.0.clone(),
                (None, Some(_)) => "-".into(),
                (None, None) if eds.is_none() => "not present".into(),
                (None, None) => "(write-only)".into(),
            };
            let n: String = n.chars().take(36).collect();
            println!("0x{i:04X}:{sub:02X} {n:<36} {ty:<6}{acc:<5} = {val}");
            if let Some(p) = p {
                println!("           ^ {p}");
            }
        }
        if eds.is_some() {
            if bad == 0 {
                println!("node {node} agrees with the EDS");
            } else {
                println!("{bad} disagreement(s) with the EDS (marked ^)");
            }
        }
    }
    if bad > 0 {
        exit::NOT_MET
    } else {
        exit::OK
    }
}
