//! An emulated CiA 401 digital I/O module (and the input behaviour a Modbus I/O unit
//! shares): NMT slave with boot-up, an expedited SDO server for 0x1000 (device type 401),
//! the CiA 301 mandatory error register 0x1001 and identity 0x1018, the heartbeat producer
//! 0x1017, the PDO parameters (0x1400/0x1600 RPDO1, 0x1800/0x1A00 TPDO1) and the digital
//! inputs 0x6000 / outputs 0x6200; RPDO1 sets the outputs, TPDO1 goes out on every SYNC
//! (transmission type 1–240) or on an input change (254/255). tests/python/io401.eds
//! describes it; python `canopen` drives it in tests/realtime/io_python.rs.
//!
//! The inputs are what a machine's wiring would make them ([`IoEmulation`]): bits that
//! are on from the start (an E-stop chain, a closed door), inputs that follow an output after
//! a delay (chuck clamped follows the clamp valve), and timed changes (the E-stop chain
//! opens at 1.5 s) — or forced from a test (`SimWorld::set_io_input`).
//!
//! In a cncgw machine config the module is `[io.devices.NAME]` with `canopen_node`, and its
//! emulation `[io.devices.NAME.emulate]`:
//!
//! ```toml
//! [io.devices.io1.emulate]
//! inputs_on = [0, 1]                                     # closed from the start
//! follow = [{ input = 2, output = 1, delay_ms = 150 }]   # in2 = out1, 150 ms later
//! events = [{ input = 0, at_ms = 1500, value = false }]  # in0 opens at 1.5 s
//! ```

use cncgw_bus::canopen::cob;
use cncgw_bus::canopen::nmt::{heartbeat_frame, NmtCommand, NmtState};
use cncgw_bus::canopen::sdo::{abort, SdoRequest, SdoResponse};
use cncgw_bus::CanFrame;
use serde::Deserialize;
use std::collections::BTreeMap;

/// An input that follows an output.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Follow {
    pub input: u8,
    pub output: u8,
    #[serde(default)]
    pub delay_ms: u64,
    /// The input is the output inverted (an "unclamped" switch).
    #[serde(default)]
    pub invert: bool,
}

/// An input forced to `value` from `at_ms` on (simulated time from the start).
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct InputEvent {
    pub input: u8,
    pub at_ms: u64,
    pub value: bool,
}

/// How the inputs behave.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct IoEmulation {
    #[serde(default)]
    pub inputs_on: Vec<u8>,
    #[serde(default)]
    pub follow: Vec<Follow>,
    #[serde(default)]
    pub events: Vec<InputEvent>,
}

/// The inputs of a unit as its wiring makes them, from its outputs' history. Shared by the
/// CiA 401 module and the Modbus I/O unit.
#[derive(Clone, Debug, Default)]
pub struct Wiring {
    pub emu: IoEmulation,
    outputs: u32,
    /// Per output bit: its value before the last change, and when it changed (ns).
    prev: [bool; 32],
    changed: [u64; 32],
    forced: [Option<bool>; 32],
}

impl Wiring {
    pub fn new(emu: IoEmulation) -> Wiring {
        Wiring { emu, ..Wiring::default() }
    }

    pub fn outputs(&self) -> u32 {
        self.outputs
    }

    pub fn set_outputs(&mut self, v: u32, now: u64) {
        for b in 0..32 {
            let (old, new) = (self.outputs >> b & 1 == 1, v >> b & 1 == 1);
            if old != new {
                self.prev[b] = old;
                self.changed[b] = now;
            }
        }
        self.outputs = v;
    }

    /// Force input `bit` (None: back to the wiring).
    pub fn force(&mut self, bit: u8, v: Option<bool>) {
        if let Some(f) = self.forced.get_mut(bit as usize) {
            *f = v;
        }
    }

    /// The inputs at `now`.
    pub fn inputs(&self, now: u64) -> u32 {
        let mut v = 0u32;
        for &b in &self.emu.inputs_on {
            v |= 1 << (b & 31);
        }
        for f in &self.emu.follow {
            let o = (f.output & 31) as usize;
            let cur = self.outputs >> o & 1 == 1;
            let seen = if now >= self.changed[o] + f.delay_ms * 1_000_000 { cur } else { self.prev[o] };
            let bit = 1 << (f.input & 31);
            v = if seen != f.invert { v | bit } else { v & !bit };
        }
        for e in self.emu.events.iter().filter(|e| now >= e.at_ms * 1_000_000) {
            let bit = 1 << (e.input & 31);
            v = if e.value { v | bit } else { v & !bit };
        }
        for (b, f) in self.forced.iter().enumerate() {
            if let Some(on) = f {
                v = if *on { v | 1 << b } else { v & !(1 << b) };
            }
        }
        v
    }
}

/// A module as the machine config describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct IoModuleConfig {
    pub node: u8,
    pub emu: IoEmulation,
}

/// A Modbus I/O unit of a machine config: address, unit id, wiring.
pub type ModbusUnit = (String, u8, IoEmulation);

/// The CiA 401 modules (and Modbus units) of a cncgw machine config.
pub fn from_machine_toml(text: &str) -> Result<(Vec<IoModuleConfig>, Vec<ModbusUnit>), String> {
    #[derive(Deserialize)]
    struct Dev {
        canopen_node: Option<u8>,
        modbus: Option<String>,
        #[serde(default)]
        unit: Option<u8>,
        emulate: Option<IoEmulation>,
    }
    #[derive(Deserialize, Default)]
    struct Io {
        #[serde(default)]
        devices: BTreeMap<String, Dev>,
    }
    #[derive(Deserialize)]
    struct Machine {
        #[serde(default)]
        io: Option<toml::Value>,
    }
    let m: Machine = toml::from_str(text).map_err(|e| format!("machine config: {e}"))?;
    let Some(io) = m.io else { return Ok((Vec::new(), Vec::new())) };
    // Only the devices table: the rest of [io] is the controller's.
    let devices = io.get("devices").cloned().unwrap_or(toml::Value::Table(Default::default()));
    let io = Io { devices: devices.try_into().map_err(|e| format!("io.devices: {e}"))? };
    let mut can = Vec::new();
    let mut modbus = Vec::new();
    for d in io.devices.into_values() {
        let emu = d.emulate.unwrap_or_default();
        match (d.canopen_node, d.modbus) {
            (Some(node), _) => can.push(IoModuleConfig { node, emu }),
            (None, Some(addr)) => modbus.push((addr, d.unit.unwrap_or(1), emu)),
            _ => {}
        }
    }
    Ok((can, modbus))
}

/// The emulated module on the bus.
pub struct SimIo {
    node: u8,
    nmt: NmtState,
    od: BTreeMap<(u16, u8), u32>,
    pub wiring: Wiring,
    last_sent: Option<u32>,
    /// When the next heartbeat is due (ns), while 0x1017 is not 0.
    next_heartbeat: u64,
    out: Vec<CanFrame>,
}

impl SimIo {
    pub fn new(cfg: IoModuleConfig) -> SimIo {
        let mut m = SimIo {
            node: cfg.node,
            nmt: NmtState::BootUp,
            od: BTreeMap::new(),
            wiring: Wiring::new(cfg.emu),
            last_sent: None,
            next_heartbeat: 0,
            out: Vec::new(),
        };
        m.reset_comm();
        // Powered up: boot-up message.
        m.boot();
        m
    }

    pub fn node(&self) -> u8 {
        self.node
    }

    pub fn nmt_state(&self) -> NmtState {
        self.nmt
    }

    /// CiA 401 defaults: RPDO1 0x6200:01, TPDO1 0x6000:01 on change (255).
    fn reset_comm(&mut self) {
        let n = self.node as u32;
        self.od.insert((0x1000, 0), 0x000F_0191);
        // CiA 301 mandatory: error register, identity (vendor as sim-drives' drives).
        self.od.insert((0x1001, 0), 0);
        self.od.insert((0x1017, 0), 0);
        for (s, v) in [4, 0x0000_0CA7, 0x0401_0001, 0x0001_0000, 0x5200_0000 + n].into_iter().enumerate() {
            self.od.insert((0x1018, s as u8), v);
        }
        // Highest sub-index of the PDO communication records (no inhibit time, event timer).
        self.od.insert((0x1400, 0), 2);
        self.od.insert((0x1800, 0), 2);
        self.od.insert((0x1400, 1), 0x200 + n);
        self.od.insert((0x1400, 2), 255);
        self.od.insert((0x1600, 0), 1);
        self.od.insert((0x1600, 1), 0x6200_0108);
        self.od.insert((0x1800, 1), 0x180 + n);
        self.od.insert((0x1800, 2), 255);
        self.od.insert((0x1A00, 0), 1);
        self.od.insert((0x1A00, 1), 0x6000_0108);
        for s in 2..=4 {
            self.od.insert((0x1600, s), 0);
            self.od.insert((0x1A00, s), 0);
        }
        for s in 0..=4u8 {
            self.od.insert((0x6000, s), if s == 0 { 4 } else { 0 });
            self.od.insert((0x6200, s), if s == 0 { 4 } else { 0 });
        }
        self.last_sent = None;
    }

    fn boot(&mut self) {
        self.out.push(heartbeat_frame(self.node, NmtState::BootUp));
        self.nmt = NmtState::PreOperational;
    }

    pub fn take_output(&mut self, out: &mut Vec<CanFrame>) {
        out.append(&mut self.out);
    }

    fn byte_count(&self, map: u16) -> usize {
        self.od.get(&(map, 0)).copied().unwrap_or(0).min(4) as usize
    }

    pub fn handle_frame(&mut self, f: &CanFrame, now: u64) {
        if let Some((cmd, node)) = NmtCommand::decode(f) {
            if node == 0 || node == self.node {
                match cmd {
                    NmtCommand::Start => self.nmt = NmtState::Operational,
                    NmtCommand::Stop => self.nmt = NmtState::Stopped,
                    NmtCommand::EnterPreOperational => self.nmt = NmtState::PreOperational,
                    NmtCommand::ResetNode | NmtCommand::ResetCommunication => {
                        self.reset_comm();
                        self.wiring.set_outputs(0, now);
                        self.boot();
                    }
                }
            }
            return;
        }
        let id = f.cob_id();
        if id == cob::SYNC && f.len <= 1 {
            let tx = self.od.get(&(0x1800, 2)).copied().unwrap_or(255);
            if (1..=240).contains(&tx) {
                self.send_inputs(now);
            }
            return;
        }
        if self.nmt == NmtState::Operational && self.od.get(&(0x1400, 1)).is_some_and(|c| c & 0x8000_0000 == 0 && c & 0x7FF == id as u32) {
            let n = self.byte_count(0x1600).min(f.len as usize);
            let mut b = [0u8; 4];
            b[..n].copy_from_slice(&f.data[..n]);
            self.wiring.set_outputs(u32::from_le_bytes(b), now);
            return;
        }
        if id == cob::SDO_RX + self.node as u16 && self.nmt != NmtState::Stopped {
            if let Some(req) = SdoRequest::decode(f) {
                let resp = self.sdo(req, now);
                self.out.push(resp.encode(self.node));
            }
        }
    }

    /// Event-driven TPDO (254/255): on an input change, checked every control tick; the
    /// heartbeat every 0x1017 ms.
    pub fn tick(&mut self, now: u64) {
        let hb_ms = self.od.get(&(0x1017, 0)).copied().unwrap_or(0) as u64;
        if hb_ms > 0 && now >= self.next_heartbeat {
            self.out.push(heartbeat_frame(self.node, self.nmt));
            self.next_heartbeat = now + hb_ms * 1_000_000;
        }
        let tx = self.od.get(&(0x1800, 2)).copied().unwrap_or(255);
        if tx >= 254 && self.last_sent != Some(self.wiring.inputs(now)) {
            self.send_inputs(now);
        }
    }

    fn send_inputs(&mut self, now: u64) {
        let cob_id = self.od.get(&(0x1800, 1)).copied().unwrap_or(0x8000_0000);
        if self.nmt != NmtState::Operational || cob_id & 0x8000_0000 != 0 {
            return;
        }
        let v = self.wiring.inputs(now);
        let n = self.byte_count(0x1A00);
        self.out.push(CanFrame::new(cob_id as u16 & 0x7FF, &v.to_le_bytes()[..n]));
        self.last_sent = Some(v);
    }

    fn sdo(&mut self, req: SdoRequest, now: u64) -> SdoResponse {
        match req {
            SdoRequest::InitiateUpload { index, sub } => {
                let v = match index {
                    0x6000 if (1..=4).contains(&sub) => Some(self.wiring.inputs(now) >> (8 * (sub as u32 - 1)) & 0xFF),
                    0x6200 if (1..=4).contains(&sub) => Some(self.wiring.outputs() >> (8 * (sub as u32 - 1)) & 0xFF),
                    _ => self.od.get(&(index, sub)).copied(),
                };
                match v {
                    Some(v) => {
                        let size = if sub == 0 && !matches!(index, 0x1000 | 0x1017)
                            || matches!(index, 0x6000 | 0x6200)
                            || sub == 2 && matches!(index, 0x1400 | 0x1800)
                        {
                            1
                        } else if index == 0x1017 {
                            2
                        } else {
                            4
                        };
                        SdoResponse::InitiateUpload { index, sub, expedited: true, size: Some(size), data: v.to_le_bytes() }
                    }
                    None => SdoResponse::Abort { index, sub, code: self.missing(index) },
                }
            }
            SdoRequest::InitiateDownload { index, sub, expedited: true, data, size } => {
                let n = size.unwrap_or(4).min(4) as usize;
                let mut b = [0u8; 4];
                b[..n].copy_from_slice(&data[..n]);
                let v = u32::from_le_bytes(b);
                let read_only = matches!(index, 0x1000 | 0x1001 | 0x1018 | 0x6000) || sub == 0 && matches!(index, 0x1400 | 0x1800 | 0x6200);
                if !self.od.contains_key(&(index, sub)) || read_only {
                    let code = if self.od.contains_key(&(index, sub)) { abort::READ_ONLY } else { self.missing(index) };
                    return SdoResponse::Abort { index, sub, code };
                }
                if index == 0x1017 {
                    self.next_heartbeat = now;
                }
                if index == 0x6200 && sub > 0 {
                    let sh = 8 * (sub as u32 - 1);
                    let o = (self.wiring.outputs() & !(0xFF << sh)) | (v & 0xFF) << sh;
                    self.wiring.set_outputs(o, now);
                } else {
                    self.od.insert((index, sub), v);
                }
                SdoResponse::InitiateDownload { index, sub }
            }
            SdoRequest::InitiateDownload { index, sub, .. } | SdoRequest::Abort { index, sub, .. } => {
                SdoResponse::Abort { index, sub, code: abort::GENERAL }
            }
            _ => SdoResponse::Abort { index: 0, sub: 0, code: abort::GENERAL },
        }
    }
}

impl SimIo {
    /// The abort for an object that is not there: the sub-index of one that is (CiA 301).
    fn missing(&self, index: u16) -> u32 {
        if self.od.keys().any(|(i, _)| *i == index) {
            abort::NO_SUBINDEX
        } else {
            abort::NO_OBJECT
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_input_follows_its_output_after_the_delay_and_events_force_it() {
        let emu = IoEmulation {
            inputs_on: vec![0],
            follow: vec![Follow { input: 2, output: 1, delay_ms: 100, invert: false }],
            events: vec![InputEvent { input: 0, at_ms: 500, value: false }],
        };
        let mut w = Wiring::new(emu);
        assert_eq!(w.inputs(0), 0b001);
        w.set_outputs(0b10, 10_000_000);
        assert_eq!(w.inputs(50_000_000), 0b001);
        assert_eq!(w.inputs(110_000_000), 0b101);
        assert_eq!(w.inputs(500_000_000), 0b100);
        w.force(2, Some(false));
        assert_eq!(w.inputs(500_000_000), 0);
    }

    /// CiA 301 aborts: a sub-index past 0x6000's four (it once shifted a u32 by 32), a
    /// missing object, the read-only identity; the heartbeat 0x1017 once written.
    #[test]
    fn sdo_aborts_and_heartbeat() {
        let mut m = SimIo::new(IoModuleConfig { node: 10, emu: IoEmulation::default() });
        let abort_of = |r: SdoResponse| match r {
            SdoResponse::Abort { code, .. } => code,
            other => panic!("{other:?}"),
        };
        assert_eq!(abort_of(m.sdo(SdoRequest::InitiateUpload { index: 0x6000, sub: 5 }, 0)), abort::NO_SUBINDEX);
        assert_eq!(abort_of(m.sdo(SdoRequest::InitiateUpload { index: 0x6401, sub: 1 }, 0)), abort::NO_OBJECT);
        let write = |index, sub, v: u32| SdoRequest::InitiateDownload { index, sub, expedited: true, size: Some(4), data: v.to_le_bytes() };
        assert_eq!(abort_of(m.sdo(write(0x1018, 1, 7), 0)), abort::READ_ONLY);
        assert!(
            matches!(m.sdo(SdoRequest::InitiateUpload { index: 0x1018, sub: 1 }, 0), SdoResponse::InitiateUpload { data, .. } if data == 0x0CA7u32.to_le_bytes())
        );
        let mut out = Vec::new();
        m.take_output(&mut out);
        assert_eq!(out.len(), 1, "the boot-up alone: {out:?}");
        m.tick(1_000_000);
        m.take_output(&mut out);
        assert_eq!(out.len(), 1, "no heartbeat while 0x1017 = 0");
        assert!(matches!(m.sdo(write(0x1017, 0, 50), 2_000_000), SdoResponse::InitiateDownload { .. }));
        for t in [2_000_000, 30_000_000, 52_000_000] {
            m.tick(t);
        }
        m.take_output(&mut out);
        assert_eq!(out.len(), 3, "heartbeats at 2 and 52 ms: {out:?}");
        assert_eq!((out[2].cob_id(), out[2].data[0]), (0x70A, NmtState::PreOperational as u8));
    }
}
