//! The machine's discrete I/O (`[io]` in the machine config): which device carries which
//! bit, what each M code and the T code switch and wait for, and which inputs stop the
//! machine when they drop.
//!
//! Devices: a CANopen CiA 401 I/O module on the drives' bus (digital inputs 0x6000, outputs
//! 0x6200, exchanged by PDO every SYNC; see `drives::canopen::master`) or a Modbus TCP I/O
//! unit (coils and discrete inputs; see `drives::modbus::io`). Every device has at most
//! [`MAX_BITS`] inputs and as many outputs.
//!
//! The M-code handshake follows a Fanuc 0i-TF (the manuals only list the codes, manual 004
//! §3.1.8 "以标准梯形图为准", as the standard ladder does them): when execution reaches the
//! code its outputs are switched (the ladder's reaction to the MF strobe), and the next item
//! of the program waits for the completion signal FIN — here: every confirmation input of
//! the code in the configured state. The 0i-TF itself waits for FIN for ever; the timeout
//! alarm (2600) is what a machine builder's ladder adds as an operator message, here one
//! `timeout_ms` per code (default `[io] fin_timeout_ms`).
//!
//! This module is only the configuration, checked and resolved to bit positions; the
//! cycle loop's side is `control::io`.

use serde::Deserialize;
use std::collections::BTreeMap;

/// Inputs (and outputs) per device.
pub const MAX_BITS: u8 = 32;
/// Devices per machine.
pub const MAX_DEVICES: usize = 8;
/// Outputs an M code may switch, and inputs it may wait for.
pub const MAX_PER_CODE: usize = 8;

/// `[io]`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct IoConfig {
    /// Default FIN timeout of a code that waits for a confirmation, ms.
    #[serde(default = "default_fin_timeout")]
    pub fin_timeout_ms: u32,
    /// Devices by name.
    #[serde(default)]
    pub devices: BTreeMap<String, IoDevice>,
    /// Named inputs: `name = "device.bit"`.
    #[serde(default)]
    pub inputs: BTreeMap<String, String>,
    /// Named outputs: `name = "device.bit"`.
    #[serde(default)]
    pub outputs: BTreeMap<String, String>,
    /// Inputs that stop the machine when they drop.
    #[serde(default)]
    pub safety: Safety,
    /// M codes by number (`[io.m.8]`).
    #[serde(default)]
    pub m: BTreeMap<String, MCode>,
    /// The turret's index handshake on a T code.
    pub turret: Option<Turret>,
}

impl Default for IoConfig {
    fn default() -> Self {
        IoConfig {
            fin_timeout_ms: default_fin_timeout(),
            devices: BTreeMap::new(),
            inputs: BTreeMap::new(),
            outputs: BTreeMap::new(),
            safety: Safety::default(),
            m: BTreeMap::new(),
            turret: None,
        }
    }
}

fn default_fin_timeout() -> u32 {
    5000
}

/// `[io.devices.NAME]`: exactly one of `canopen_node` and `modbus`.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct IoDevice {
    /// A CiA 401 module on the drives' CANopen bus, this node id.
    pub canopen_node: Option<u8>,
    /// A Modbus TCP I/O unit at `host:port`.
    pub modbus: Option<String>,
    /// Modbus unit id.
    #[serde(default = "default_unit")]
    pub unit: u8,
    /// Modbus: the first discrete input / coil address.
    #[serde(default)]
    pub first_input: u16,
    #[serde(default)]
    pub first_output: u16,
    /// Modbus poll period, ms.
    #[serde(default = "default_poll")]
    pub poll_ms: u32,
    /// Inputs and outputs used (1–32; a CiA 401 module maps them in whole bytes).
    #[serde(default = "default_bits")]
    pub inputs: u8,
    #[serde(default = "default_bits")]
    pub outputs: u8,
    /// How sim-drives emulates this device (cncgw itself ignores it; see sim-drives' README).
    pub emulate: Option<toml::Value>,
}

fn default_unit() -> u8 {
    1
}
fn default_poll() -> u32 {
    10
}
fn default_bits() -> u8 {
    8
}

/// `[io.safety]`: input names. Each must read 1 (closed circuit) while a program runs.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Safety {
    /// Hardware E-stop chain: open → every drive quick stop, alarm 2400 (as the panel's E-stop).
    pub estop: Option<String>,
    /// Door closed: open → controlled stop, alarm 2601.
    pub door: Option<String>,
    /// Chuck clamped: open while the spindle turns or after the clamp code was confirmed →
    /// controlled stop, alarm 2602.
    pub chuck: Option<String>,
}

/// `[io.m.N]`: outputs switched when execution reaches MN, inputs that confirm it (FIN).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MCode {
    #[serde(default)]
    pub set: Vec<String>,
    #[serde(default)]
    pub clear: Vec<String>,
    /// Inputs that must read 1 …
    #[serde(default)]
    pub wait_on: Vec<String>,
    /// … and 0 before the program goes on.
    #[serde(default)]
    pub wait_off: Vec<String>,
    pub timeout_ms: Option<u32>,
}

/// `[io.turret]`: on a T code, the station number (T□□△△: □□) binary on `code` (bit 0
/// first), then `strobe` on; FIN when `in_position` reads 1; then `strobe` off.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Turret {
    #[serde(default)]
    pub code: Vec<String>,
    pub strobe: String,
    pub in_position: String,
    pub timeout_ms: Option<u32>,
}

/// A device as the run uses it.
#[derive(Clone, Debug, PartialEq)]
pub enum DeviceKind {
    Cia401 { node: u8 },
    ModbusTcp { address: String, unit: u8, first_input: u16, first_output: u16, poll_ms: u32 },
}

/// One bit: device index (into [`Resolved::devices`]) and bit number.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bit {
    pub dev: u8,
    pub bit: u8,
}

/// Up to [`MAX_PER_CODE`] bits, no allocation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bits {
    pub n: u8,
    pub at: [Bit; MAX_PER_CODE],
}

impl Bits {
    pub fn iter(&self) -> impl Iterator<Item = &Bit> {
        self.at[..self.n as usize].iter()
    }
}

/// What a code does, resolved to bits.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Action {
    pub set: Bits,
    pub clear: Bits,
    pub wait_on: Bits,
    pub wait_off: Bits,
    pub timeout_ms: u32,
}

impl Action {
    pub fn waits(&self) -> bool {
        self.wait_on.n + self.wait_off.n > 0
    }
}

/// The turret resolved to bits.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TurretBits {
    pub code: Bits,
    pub strobe: Bit,
    pub in_position: Bit,
    pub timeout_ms: u32,
}

/// `[io]` resolved: devices in name order, codes by number.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Resolved {
    pub devices: Vec<(String, DeviceKind, u8, u8)>,
    /// (M number, action), ascending.
    pub m: Vec<(u16, Action)>,
    pub turret: Option<TurretBits>,
    /// E-stop, door, chuck: the bit and its name.
    pub estop: Option<(Bit, String)>,
    pub door: Option<(Bit, String)>,
    pub chuck: Option<(Bit, String)>,
    /// Every named input and output, for messages: (bit, name).
    pub input_names: Vec<(Bit, String)>,
    pub output_names: Vec<(Bit, String)>,
}

impl Resolved {
    pub fn is_empty(&self) -> bool {
        self.devices.is_empty()
    }
    pub fn input_name(&self, b: Bit) -> &str {
        self.input_names.iter().find(|(x, _)| *x == b).map_or("?", |(_, n)| n)
    }
    /// The CiA 401 modules: (node id, inputs, outputs).
    pub fn canopen_modules(&self) -> Vec<(u8, u8, u8)> {
        self.devices.iter().filter_map(|(_, k, i, o)| if let DeviceKind::Cia401 { node } = k { Some((*node, *i, *o)) } else { None }).collect()
    }
}

/// M codes the interpreter and motion execute themselves: they cannot be mapped to I/O.
const OWN_M_CODES: &[u16] = &[0, 1, 2, 3, 4, 5, 29, 30, 91, 92, 98, 99];

impl IoConfig {
    /// Check and resolve; every problem as `io.key: what is allowed, got value`.
    pub fn resolve(&self) -> Result<Resolved, Vec<String>> {
        let mut e = Vec::new();
        let mut r = Resolved::default();
        if self.devices.len() > MAX_DEVICES {
            e.push(format!("io.devices: at most {MAX_DEVICES} devices, got {}", self.devices.len()));
        }
        for (name, d) in &self.devices {
            let key = format!("io.devices.{name}");
            for (what, n) in [("inputs", d.inputs), ("outputs", d.outputs)] {
                if n == 0 || n > MAX_BITS {
                    e.push(format!("{key}.{what}: 1–{MAX_BITS}, got {n}"));
                }
            }
            let kind = match (d.canopen_node, &d.modbus) {
                (Some(node), None) if (1..=127).contains(&node) => DeviceKind::Cia401 { node },
                (Some(node), None) => {
                    e.push(format!("{key}.canopen_node: 1–127, got {node}"));
                    continue;
                }
                (None, Some(a)) if a.parse::<std::net::SocketAddr>().is_ok() || a.contains(':') => {
                    if d.poll_ms == 0 {
                        e.push(format!("{key}.poll_ms: must be > 0"));
                    }
                    DeviceKind::ModbusTcp {
                        address: a.clone(),
                        unit: d.unit,
                        first_input: d.first_input,
                        first_output: d.first_output,
                        poll_ms: d.poll_ms,
                    }
                }
                (None, Some(a)) => {
                    e.push(format!("{key}.modbus: host:port of a Modbus TCP I/O unit, got {a:?}"));
                    continue;
                }
                _ => {
                    e.push(format!("{key}: exactly one of canopen_node (a CiA 401 module) and modbus (a Modbus TCP unit, \"host:port\")"));
                    continue;
                }
            };
            r.devices.push((name.clone(), kind, d.inputs.min(MAX_BITS), d.outputs.min(MAX_BITS)));
        }
        let bit = |e: &mut Vec<String>, key: String, spec: &str, input: bool| -> Option<Bit> {
            let Some((dev, b)) = spec.split_once('.') else {
                e.push(format!("{key}: \"device.bit\", e.g. \"io1.0\", got {spec:?}"));
                return None;
            };
            let Some(di) = r.devices.iter().position(|d| d.0 == dev) else {
                e.push(format!("{key}: no device {dev:?} in [io.devices]"));
                return None;
            };
            let max = if input { r.devices[di].2 } else { r.devices[di].3 };
            match b.parse::<u8>() {
                Ok(b) if b < max => Some(Bit { dev: di as u8, bit: b }),
                _ => {
                    e.push(format!("{key}: bit 0–{} of {dev}, got {b:?}", max.saturating_sub(1)));
                    None
                }
            }
        };
        for (n, s) in &self.inputs {
            if let Some(b) = bit(&mut e, format!("io.inputs.{n}"), s, true) {
                r.input_names.push((b, n.clone()));
            }
        }
        for (n, s) in &self.outputs {
            if let Some(b) = bit(&mut e, format!("io.outputs.{n}"), s, false) {
                r.output_names.push((b, n.clone()));
            }
        }
        self.resolve_codes(&mut r, &mut e);
        if e.is_empty() {
            Ok(r)
        } else {
            Err(e)
        }
    }

    fn resolve_codes(&self, r: &mut Resolved, e: &mut Vec<String>) {
        let find = |names: &[(Bit, String)], e: &mut Vec<String>, key: &str, n: &str, what: &str| {
            let b = names.iter().find(|(_, m)| m == n).map(|(b, _)| *b);
            if b.is_none() {
                e.push(format!("{key}: no {what} {n:?} in [io.{what}s]"));
            }
            b
        };
        let list = |names: &[(Bit, String)], e: &mut Vec<String>, key: String, l: &[String], what: &str| {
            let mut bits = Bits::default();
            if l.len() > MAX_PER_CODE {
                e.push(format!("{key}: at most {MAX_PER_CODE} names, got {}", l.len()));
            }
            for n in l.iter().take(MAX_PER_CODE) {
                if let Some(b) = find(names, e, &key, n, what) {
                    bits.at[bits.n as usize] = b;
                    bits.n += 1;
                }
            }
            bits
        };
        let (ins, outs) = (r.input_names.clone(), r.output_names.clone());
        for (code, m) in &self.m {
            let key = format!("io.m.{code}");
            let Ok(num) = code.parse::<u16>() else {
                e.push(format!("{key}: the M code's number, e.g. [io.m.8]"));
                continue;
            };
            if OWN_M_CODES.contains(&num) {
                e.push(format!("{key}: M{num} is executed by the controller itself and cannot be mapped to I/O"));
                continue;
            }
            let a = Action {
                set: list(&outs, e, format!("{key}.set"), &m.set, "output"),
                clear: list(&outs, e, format!("{key}.clear"), &m.clear, "output"),
                wait_on: list(&ins, e, format!("{key}.wait_on"), &m.wait_on, "input"),
                wait_off: list(&ins, e, format!("{key}.wait_off"), &m.wait_off, "input"),
                timeout_ms: m.timeout_ms.unwrap_or(self.fin_timeout_ms),
            };
            r.m.push((num, a));
        }
        r.m.sort_by_key(|(n, _)| *n);
        if let Some(t) = &self.turret {
            let code = list(&outs, e, "io.turret.code".into(), &t.code, "output");
            let strobe = find(&outs, e, "io.turret.strobe", &t.strobe, "output");
            let inpos = find(&ins, e, "io.turret.in_position", &t.in_position, "input");
            if let (Some(strobe), Some(in_position)) = (strobe, inpos) {
                r.turret = Some(TurretBits { code, strobe, in_position, timeout_ms: t.timeout_ms.unwrap_or(self.fin_timeout_ms) });
            }
        }
        let safety =
            |e: &mut Vec<String>, key: &str, n: &Option<String>| n.as_ref().and_then(|n| find(&ins, e, key, n, "input").map(|b| (b, n.clone())));
        r.estop = safety(e, "io.safety.estop", &self.safety.estop);
        r.door = safety(e, "io.safety.door", &self.safety.door);
        r.chuck = safety(e, "io.safety.chuck", &self.safety.chuck);
        let names = [&r.estop, &r.door, &r.chuck].iter().filter(|x| x.is_some()).count();
        if names > 0 && r.devices.is_empty() {
            e.push("io.safety: inputs without a device".into());
        }
        if self.fin_timeout_ms == 0 || r.m.iter().any(|(_, a)| a.timeout_ms == 0) || r.turret.is_some_and(|t| t.timeout_ms == 0) {
            e.push("io: fin_timeout_ms / timeout_ms must be > 0".into());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = r#"
        [devices.io1]
        canopen_node = 10
        [devices.unit]
        modbus = "127.0.0.1:1502"
        inputs = 4
        outputs = 4
        [inputs]
        estop_ok = "io1.0"
        door_closed = "io1.1"
        chuck_clamped = "io1.2"
        in_pos = "unit.3"
        [outputs]
        coolant = "io1.0"
        clamp = "io1.1"
        strobe = "unit.0"
        [safety]
        estop = "estop_ok"
        door = "door_closed"
        [m.8]
        set = ["coolant"]
        [m.10]
        set = ["clamp"]
        wait_on = ["chuck_clamped"]
        timeout_ms = 1500
        [turret]
        strobe = "strobe"
        in_position = "in_pos"
    "#;

    #[test]
    fn an_example_resolves_to_bits() {
        let c: IoConfig = toml::from_str(EXAMPLE).unwrap();
        let r = c.resolve().unwrap();
        assert_eq!(r.devices[0].1, DeviceKind::Cia401 { node: 10 });
        assert_eq!(r.m[1].0, 10);
        assert_eq!(r.m[1].1.wait_on.at[0], Bit { dev: 0, bit: 2 });
        assert_eq!(r.m[1].1.timeout_ms, 1500);
        assert_eq!(r.m[0].1.timeout_ms, 5000);
        assert_eq!(r.turret.unwrap().in_position, Bit { dev: 1, bit: 3 });
        assert_eq!(r.estop.as_ref().unwrap().0, Bit { dev: 0, bit: 0 });
        assert_eq!(r.canopen_modules(), vec![(10, 8, 8)]);
    }

    #[test]
    fn no_io_table_is_no_io() {
        let c: IoConfig = toml::from_str("").unwrap();
        assert_eq!(c, IoConfig::default());
        assert!(c.resolve().unwrap().is_empty());
    }

    #[test]
    fn mistakes_name_the_key() {
        let bad = EXAMPLE.replace("\"io1.2\"", "\"io1.9x\"").replace("[m.8]", "[m.3]").replace("door = \"door_closed\"", "door = \"nope\"");
        let c: IoConfig = toml::from_str(&bad).unwrap();
        let e = c.resolve().unwrap_err().join("\n");
        assert!(e.contains("io.inputs.chuck_clamped: bit 0–7 of io1"), "{e}");
        assert!(e.contains("io.m.3: M3 is executed by the controller itself"), "{e}");
        assert!(e.contains("io.safety.door: no input \"nope\""), "{e}");
        assert!(e.contains("io.m.10.wait_on: no input \"chuck_clamped\""), "{e}");
    }
}
