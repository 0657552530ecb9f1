//! `cncgw monitor`'s machine I/O (`[io]`): every device's inputs and outputs as they stand,
//! each named input and output, and the safety inputs as the panel shows them. Read only:
//! a CiA 401 module by SDO (0x6000 / 0x6200, one sub-index per 8 bits), a Modbus TCP unit
//! by FC02 (discrete inputs) and FC01 (coils) — the monitor never writes an output, so it
//! can watch a machine that a run drives.

use crate::config::MachineConfig;
use crate::control::panel::SafetyInputs;
use crate::io::{Bit, DeviceKind, Resolved};
use std::time::Duration;
use tokio_modbus::client::Reader;
use tokio_modbus::prelude::SlaveContext;

/// How long a Modbus unit may take to connect or answer one read.
const MODBUS_TIMEOUT: Duration = Duration::from_millis(500);

/// A Modbus unit's connection, made again after a failure.
struct ModbusReader {
    ctx: Option<tokio_modbus::client::Context>,
}

/// The I/O of a machine config, and how to read it.
pub struct IoMonitor {
    cfg: Resolved,
    rt: Option<tokio::runtime::Runtime>,
    modbus: Vec<ModbusReader>,
}

/// One reading: per device (in `Resolved::devices` order) its (inputs, outputs) or why not.
pub struct IoRead(Vec<Result<(u32, u32), String>>);

/// Reads one byte of a CANopen object (node, index, sub) by SDO.
pub type SdoByte<'a> = &'a mut dyn FnMut(u8, u16, u8) -> Result<u8, String>;

impl IoMonitor {
    /// The machine's I/O, or None when it has no `[io]` devices. Err: `[io]` does not resolve.
    pub fn new(cfg: &MachineConfig) -> Result<Option<IoMonitor>, String> {
        let r = cfg.io.resolve().map_err(|e| e.join("; "))?;
        if r.is_empty() {
            return Ok(None);
        }
        let rt = if r.devices.iter().any(|d| matches!(d.1, DeviceKind::ModbusTcp { .. })) {
            Some(tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| format!("cannot start the I/O runtime: {e}"))?)
        } else {
            None
        };
        let modbus = r.devices.iter().map(|_| ModbusReader { ctx: None }).collect();
        Ok(Some(IoMonitor { cfg: r, rt, modbus }))
    }

    /// Read every device. `sdo`: the CANopen bus's SDO client (None: no CANopen bus open, as
    /// in the Modbus monitor — a CiA 401 module is then not read).
    pub fn read(&mut self, mut sdo: Option<SdoByte>) -> IoRead {
        let mut out = Vec::with_capacity(self.cfg.devices.len());
        for (k, (_, kind, ins, outs)) in self.cfg.devices.iter().enumerate() {
            out.push(match kind {
                DeviceKind::Cia401 { node } => match sdo.as_mut() {
                    Some(f) => read_cia401(&mut **f, *node, *ins, *outs),
                    None => Err("a CiA 401 module on the CANopen bus, which this monitor of Modbus drives does not open".into()),
                },
                DeviceKind::ModbusTcp { address, unit, first_input, first_output, .. } => match &self.rt {
                    Some(rt) => {
                        let m = &mut self.modbus[k];
                        let r = rt.block_on(read_modbus(&mut m.ctx, address, *unit, (*first_input, *ins), (*first_output, *outs)));
                        if r.is_err() {
                            m.ctx = None;
                        }
                        r
                    }
                    None => Err("no runtime".into()),
                },
            });
        }
        IoRead(out)
    }

    /// A bit as read (None: its device did not answer).
    fn bit(&self, r: &IoRead, b: Bit, input: bool) -> Option<bool> {
        let (i, o) = r.0.get(b.dev as usize)?.as_ref().ok()?;
        Some((if input { i } else { o }) >> b.bit & 1 == 1)
    }

    /// The safety inputs as the panel shows them; one not read counts as open, as in the
    /// cycle loop (a safety input must be seen closed).
    pub fn safety(&self, r: &IoRead) -> SafetyInputs {
        let get = |x: &Option<(Bit, String)>| x.as_ref().map(|(b, _)| self.bit(r, *b, true).unwrap_or(false));
        SafetyInputs { estop: get(&self.cfg.estop), door: get(&self.cfg.door), chuck: get(&self.cfg.chuck) }
    }

    /// The monitor's text: the safety line, a line per device, the named inputs and outputs.
    pub fn lines(&self, r: &IoRead) -> Vec<String> {
        let labels: Vec<&str> = self.safety(r).labels().collect();
        let mut v = vec![format!("I/O: {}", if labels.is_empty() { "no safety inputs configured".to_string() } else { labels.join("  ") })];
        for ((name, kind, _, _), got) in self.cfg.devices.iter().zip(&r.0) {
            let what = match got {
                Ok((i, o)) => format!("in 0x{i:08X}  out 0x{o:08X}"),
                Err(e) => format!("no answer: {e}"),
            };
            v.push(format!("  {name:<10} {:<34} {what}", device_text(kind)));
        }
        let named = |names: &[(Bit, String)], input: bool| -> String {
            let f = |b| self.bit(r, b, input).map_or("?", |x| if x { "1" } else { "0" });
            names.iter().map(|(b, n)| format!("{n} {}", f(*b))).collect::<Vec<_>>().join("  ")
        };
        v.push(format!("  inputs:  {}", named(&self.cfg.input_names, true)));
        v.push(format!("  outputs: {}", named(&self.cfg.output_names, false)));
        v
    }

    /// The monitor's JSON: `devices` (raw words), `inputs` / `outputs` by name (null: not
    /// read), `safety` (null: not configured).
    pub fn json(&self, r: &IoRead) -> serde_json::Value {
        let devices: Vec<serde_json::Value> = self
            .cfg
            .devices
            .iter()
            .zip(&r.0)
            .map(|((name, kind, _, _), got)| {
                let mut d = match kind {
                    DeviceKind::Cia401 { node } => serde_json::json!({"name": name, "kind": "cia401", "node": node}),
                    DeviceKind::ModbusTcp { address, unit, .. } => {
                        serde_json::json!({"name": name, "kind": "modbus_tcp", "address": address, "unit": unit})
                    }
                };
                let (i, o, e) = match got {
                    Ok((i, o)) => (Some(*i), Some(*o), None),
                    Err(e) => (None, None, Some(e.clone())),
                };
                d["inputs"] = serde_json::json!(i);
                d["outputs"] = serde_json::json!(o);
                d["error"] = serde_json::json!(e);
                d
            })
            .collect();
        let named = |names: &[(Bit, String)], input: bool| -> serde_json::Map<String, serde_json::Value> {
            names.iter().map(|(b, n)| (n.clone(), serde_json::json!(self.bit(r, *b, input)))).collect()
        };
        let s = self.safety(r);
        serde_json::json!({
            "devices": devices,
            "inputs": named(&self.cfg.input_names, true),
            "outputs": named(&self.cfg.output_names, false),
            "safety": {"estop": s.estop, "door": s.door, "chuck": s.chuck},
        })
    }
}

fn device_text(kind: &DeviceKind) -> String {
    match kind {
        DeviceKind::Cia401 { node } => format!("CiA 401 node {node}"),
        DeviceKind::ModbusTcp { address, unit, .. } => format!("Modbus TCP {address} unit {unit}"),
    }
}

/// A CiA 401 module's inputs (0x6000) and outputs (0x6200), 8 bits per sub-index.
fn read_cia401(sdo: &mut dyn FnMut(u8, u16, u8) -> Result<u8, String>, node: u8, ins: u8, outs: u8) -> Result<(u32, u32), String> {
    let mut word = |index: u16, bits: u8| -> Result<u32, String> {
        (0..bits.div_ceil(8)).try_fold(0u32, |w, k| {
            let b = sdo(node, index, k + 1).map_err(|e| format!("0x{index:04X}:{}: {e}", k + 1))?;
            Ok(w | (b as u32) << (8 * k))
        })
    };
    let mask = |n: u8| if n >= 32 { u32::MAX } else { (1u32 << n) - 1 };
    Ok((word(0x6000, ins)? & mask(ins), word(0x6200, outs)? & mask(outs)))
}

/// A Modbus unit's discrete inputs and coils ((first address, count) each).
async fn read_modbus(
    ctx: &mut Option<tokio_modbus::client::Context>,
    address: &str,
    unit: u8,
    (first_in, ins): (u16, u8),
    (first_out, outs): (u16, u8),
) -> Result<(u32, u32), String> {
    let t = |what: &str| format!("{what}: no answer within {} ms", MODBUS_TIMEOUT.as_millis());
    if ctx.is_none() {
        let sa =
            tokio::net::lookup_host(address).await.map_err(|e| format!("{address}: {e}"))?.next().ok_or_else(|| format!("{address}: no address"))?;
        let mut c = tokio::time::timeout(MODBUS_TIMEOUT, tokio_modbus::client::tcp::connect(sa))
            .await
            .map_err(|_| t("connect"))?
            .map_err(|e| format!("connect {address}: {e}"))?;
        c.set_slave(tokio_modbus::Slave(unit));
        *ctx = Some(c);
    }
    let c = ctx.as_mut().ok_or("not connected")?;
    let word = |bits: Vec<bool>| bits.iter().take(32).enumerate().fold(0u32, |w, (k, b)| w | (*b as u32) << k);
    let i = tokio::time::timeout(MODBUS_TIMEOUT, c.read_discrete_inputs(first_in, ins as u16))
        .await
        .map_err(|_| t("discrete inputs (FC02)"))?
        .map_err(|e| format!("discrete inputs (FC02): {e}"))?
        .map_err(|e| format!("discrete inputs (FC02): exception {e}"))?;
    let o = tokio::time::timeout(MODBUS_TIMEOUT, c.read_coils(first_out, outs as u16))
        .await
        .map_err(|_| t("coils (FC01)"))?
        .map_err(|e| format!("coils (FC01): {e}"))?
        .map_err(|e| format!("coils (FC01): exception {e}"))?;
    Ok((word(i), word(o)))
}
