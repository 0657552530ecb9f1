//! Modbus drive register maps and link timing, shared by the cncgw master and sim-drives.
//!
//! The Modbus frame codec itself is tokio-modbus's (client in cncgw, server in sim-drives):
//! one implementation on both sides. What is ours is how a drive's process data sit in its
//! holding registers — two profiles, every address configurable — and what a link can carry
//! per cycle.

use serde::{Deserialize, Deserializer};

/// How the master reads the registers it needs every cycle (statusword / status, actual
/// position, error / alarm code): a drive answers a read with exception 0x02 if any register
/// in it does not exist, and many maps have holes between those three.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReadBlocks {
    /// One read over all of them when they lie within 16 registers (every register between
    /// them must be readable), else one read per value.
    #[default]
    Auto,
    /// One read from the lowest to the highest, holes included.
    Span,
    /// One read per run of adjacent registers the master needs: no register it does not
    /// need is read.
    Contiguous,
    /// One read per value (a 32-bit value is still one read of its two registers).
    Single,
}

impl ReadBlocks {
    /// Its name in a configuration file.
    pub fn name(self) -> &'static str {
        match self {
            ReadBlocks::Auto => "auto",
            ReadBlocks::Span => "span",
            ReadBlocks::Contiguous => "contiguous",
            ReadBlocks::Single => "single",
        }
    }

    /// The reads covering `regs` (each `(addr, len)`).
    pub fn blocks(self, regs: &[(u16, u16)]) -> Vec<(u16, u16)> {
        let (a, l) = span(regs);
        match self {
            ReadBlocks::Span => vec![(a, l)],
            ReadBlocks::Auto if l <= 16 => vec![(a, l)],
            ReadBlocks::Auto | ReadBlocks::Single => {
                let mut v = regs.to_vec();
                v.sort();
                v
            }
            ReadBlocks::Contiguous => {
                let mut v = regs.to_vec();
                v.sort();
                let mut out: Vec<(u16, u16)> = Vec::new();
                for (a, l) in v {
                    match out.last_mut() {
                        Some(last) if last.0 as u32 + last.1 as u32 >= a as u32 => {
                            let end = (last.0 as u32 + last.1 as u32).max(a as u32 + l as u32);
                            last.1 = (end - last.0 as u32) as u16;
                        }
                        _ => out.push((a, l)),
                    }
                }
                out
            }
        }
    }
}

/// An optional register of a map: its address, or `"none"` where the drive has no such
/// register (the master then skips it, with a warning where something is lost).
fn optional_register<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u16>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum R {
        Addr(u16),
        Word(String),
    }
    match R::deserialize(d)? {
        R::Addr(a) => Ok(Some(a)),
        R::Word(w) if w == "none" => Ok(None),
        R::Word(w) => Err(serde::de::Error::custom(format!("a register address (0…65535) or \"none\", got \"{w}\""))),
    }
}

/// Order of the two 16-bit registers of a 32-bit value.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WordOrder {
    /// High word at the lower address (Modbus' big-endian habit; most drives).
    #[default]
    HighFirst,
    /// Low word at the lower address (some Delta and Inovance maps).
    LowFirst,
}

impl WordOrder {
    pub fn split_i32(self, v: i32) -> [u16; 2] {
        let (hi, lo) = ((v as u32 >> 16) as u16, v as u32 as u16);
        match self {
            WordOrder::HighFirst => [hi, lo],
            WordOrder::LowFirst => [lo, hi],
        }
    }
    pub fn join_i32(self, r: [u16; 2]) -> i32 {
        let (hi, lo) = match self {
            WordOrder::HighFirst => (r[0], r[1]),
            WordOrder::LowFirst => (r[1], r[0]),
        };
        ((hi as u32) << 16 | lo as u32) as i32
    }
}

/// Which register map a drive speaks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Profile {
    /// CiA 402 objects in holding registers: the CiA 402 state machine, cyclic synchronous
    /// position with the drive interpolating over one link cycle.
    #[default]
    Cia402,
    /// Position-register block: mode, position, speed, acceleration, deceleration, dwell,
    /// then a trigger register; status and actual position polled.
    Pr,
}

/// CiA 402 objects in holding registers (addresses are 0-based PDU addresses). 32-bit
/// objects take two registers in `word_order`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Cia402Map {
    /// 0x6040 controlword.
    pub controlword: u16,
    /// 0x607A target position (2 registers).
    pub target_position: u16,
    /// 0x60FF target velocity (2 registers), counts/s.
    pub target_velocity: u16,
    /// 0x6060 modes of operation.
    pub mode: u16,
    /// 0x6041 statusword.
    pub statusword: u16,
    /// 0x6061 modes of operation display.
    pub mode_display: u16,
    /// 0x6064 position actual (2 registers).
    pub position_actual: u16,
    /// 0x606C velocity actual (2 registers), counts/s.
    pub velocity_actual: u16,
    /// 0x603F error code; `"none"`: the drive has none (alarms then name no error code).
    #[serde(deserialize_with = "optional_register")]
    pub error_code: Option<u16>,
    /// 0x60C2 interpolation period in ms (the link cycle; the drive interpolates over it);
    /// `"none"`: the drive has a fixed one or takes it from elsewhere (the master warns).
    #[serde(deserialize_with = "optional_register")]
    pub interpolation_ms: Option<u16>,
    /// 0x6065 following-error window, counts (2 registers).
    pub following_error_window: u16,
    /// Communication timeout, ms (the Modbus analogue of 0x1016/0x6007: no write for this
    /// long and the drive faults and stops by itself; 0 = off); `"none"`: the drive has
    /// none (the master warns: a dead controller is not noticed by the drive).
    #[serde(deserialize_with = "optional_register")]
    pub comm_timeout_ms: Option<u16>,
    // The homing registers and the digital inputs came after the first maps: a map table
    // written for a drive (any `cia402_map` in a config) that does not name them means the
    // drive has none (`#[serde(default)]` on the field: absent = None) — else cncgw would write
    // the homing into whatever registers 24–32 are on that drive. Only the built-in map (no
    // table: `Cia402Map::default()`, what sim-drives serves) has them.
    /// 0x6098 homing method (INTEGER8 in one register); `"none"` or absent from a map
    /// table: the drive homes with the method of its own parameters (`cncgw home` then
    /// refuses any method but 35).
    #[serde(default, deserialize_with = "optional_register")]
    pub homing_method: Option<u16>,
    /// 0x607C home offset, counts (2 registers); optional, absent = none.
    #[serde(default, deserialize_with = "optional_register")]
    pub home_offset: Option<u16>,
    /// 0x6099:1 homing speed searching the switch, counts/s (2 registers); optional, absent = none.
    #[serde(default, deserialize_with = "optional_register")]
    pub homing_switch_speed: Option<u16>,
    /// 0x6099:2 homing speed searching zero, counts/s (2 registers); optional, absent = none.
    #[serde(default, deserialize_with = "optional_register")]
    pub homing_zero_speed: Option<u16>,
    /// 0x609A homing acceleration, counts/s² (2 registers); optional, absent = none.
    #[serde(default, deserialize_with = "optional_register")]
    pub homing_accel: Option<u16>,
    /// 0x60FD digital inputs (2 registers, read): bit 0 negative limit switch, bit 1
    /// positive, bit 2 home switch (CiA 402); optional, absent = none. `cncgw monitor` shows it.
    #[serde(default, deserialize_with = "optional_register")]
    pub digital_inputs: Option<u16>,
    pub word_order: WordOrder,
    /// How the cyclic read is split (`ReadBlocks`).
    pub reads: ReadBlocks,
}

/// One register (or 32-bit pair) of a map: `config check --bus` tries each on a live drive,
/// sim-drives serves them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapRegister {
    /// Its key in the map.
    pub name: &'static str,
    pub addr: u16,
    pub len: u16,
    /// The master writes it (else it only reads it).
    pub writable: bool,
    /// May be `"none"` in the map.
    pub optional: bool,
}

fn reg(name: &'static str, addr: Option<u16>, len: u16, writable: bool, optional: bool) -> Option<MapRegister> {
    addr.map(|addr| MapRegister { name, addr, len, writable, optional })
}

impl Cia402Map {
    /// Every register of the map the drive has (optional ones set to `"none"` left out).
    pub fn registers(&self) -> Vec<MapRegister> {
        [
            reg("controlword", Some(self.controlword), 1, true, false),
            reg("target_position", Some(self.target_position), 2, true, false),
            reg("target_velocity", Some(self.target_velocity), 2, true, false),
            reg("mode", Some(self.mode), 1, true, false),
            reg("statusword", Some(self.statusword), 1, false, false),
            reg("mode_display", Some(self.mode_display), 1, false, false),
            reg("position_actual", Some(self.position_actual), 2, false, false),
            reg("velocity_actual", Some(self.velocity_actual), 2, false, false),
            reg("error_code", self.error_code, 1, false, true),
            reg("interpolation_ms", self.interpolation_ms, 1, true, true),
            reg("following_error_window", Some(self.following_error_window), 2, true, false),
            reg("comm_timeout_ms", self.comm_timeout_ms, 1, true, true),
            reg("homing_method", self.homing_method, 1, true, true),
            reg("home_offset", self.home_offset, 2, true, true),
            reg("homing_switch_speed", self.homing_switch_speed, 2, true, true),
            reg("homing_zero_speed", self.homing_zero_speed, 2, true, true),
            reg("homing_accel", self.homing_accel, 2, true, true),
            reg("digital_inputs", self.digital_inputs, 2, false, true),
        ]
        .into_iter()
        .flatten()
        .collect()
    }

    /// The register that carries CiA 402 object `index`:`sub` on this map, if the map has
    /// one: how the service commands read and write a drive's objects over Modbus as they
    /// do over SDO (`drives::access`). 0x6065 and the homing objects take 2 registers, the
    /// rest as their type.
    pub fn register(&self, index: u16, sub: u8) -> Option<u16> {
        match (index, sub) {
            (0x6040, 0) => Some(self.controlword),
            (0x6041, 0) => Some(self.statusword),
            (0x6060, 0) => Some(self.mode),
            (0x6061, 0) => Some(self.mode_display),
            (0x6064, 0) => Some(self.position_actual),
            (0x606C, 0) => Some(self.velocity_actual),
            (0x607A, 0) => Some(self.target_position),
            (0x60FF, 0) => Some(self.target_velocity),
            (0x6065, 0) => Some(self.following_error_window),
            (0x603F, 0) => self.error_code,
            (0x60C2, 1) => self.interpolation_ms,
            (0x6098, 0) => self.homing_method,
            (0x607C, 0) => self.home_offset,
            (0x6099, 1) => self.homing_switch_speed,
            (0x6099, 2) => self.homing_zero_speed,
            (0x609A, 0) => self.homing_accel,
            (0x60FD, 0) => self.digital_inputs,
            _ => None,
        }
    }

    /// The registers of the cyclic read: statusword, position actual, error code.
    pub fn cyclic_reads(&self) -> Vec<(u16, u16)> {
        let mut v = vec![(self.statusword, 1), (self.position_actual, 2)];
        v.extend(self.error_code.map(|a| (a, 1)));
        self.reads.blocks(&v)
    }
}

impl PrMap {
    /// Every register of the map the drive has (optional ones set to `"none"` left out).
    pub fn registers(&self) -> Vec<MapRegister> {
        [
            reg("block", Some(self.block), PR_BLOCK_LEN, true, false),
            reg("trigger", Some(self.trigger), 1, true, false),
            reg("servo_on", Some(self.servo_on), 1, true, false),
            reg("status", Some(self.status), 1, false, false),
            reg("position_actual", Some(self.position_actual), 2, false, false),
            reg("alarm_code", self.alarm_code, 1, false, true),
            reg("alarm_reset", Some(self.alarm_reset), 1, true, false),
            reg("comm_timeout_ms", self.comm_timeout_ms, 1, true, true),
        ]
        .into_iter()
        .flatten()
        .collect()
    }

    /// The registers of the cyclic read: status, position actual, alarm code.
    pub fn cyclic_reads(&self) -> Vec<(u16, u16)> {
        let mut v = vec![(self.status, 1), (self.position_actual, 2)];
        v.extend(self.alarm_code.map(|a| (a, 1)));
        self.reads.blocks(&v)
    }
}

impl Cia402Map {
    /// The map sim-drives serves: the cyclic write (controlword + target) and the cyclic
    /// read (statusword … error code) are each one contiguous block.
    pub const SIM_DRIVES: Cia402Map = Cia402Map {
        controlword: 0,
        target_position: 1,
        target_velocity: 3,
        mode: 5,
        statusword: 10,
        mode_display: 11,
        position_actual: 12,
        velocity_actual: 14,
        error_code: Some(16),
        interpolation_ms: Some(20),
        following_error_window: 21,
        comm_timeout_ms: Some(23),
        homing_method: Some(24),
        home_offset: Some(25),
        homing_switch_speed: Some(27),
        homing_zero_speed: Some(29),
        homing_accel: Some(31),
        digital_inputs: Some(33),
        word_order: WordOrder::HighFirst,
        reads: ReadBlocks::Auto,
    };
}

impl Default for Cia402Map {
    /// [`Cia402Map::SIM_DRIVES`].
    fn default() -> Self {
        Cia402Map::SIM_DRIVES
    }
}

/// Position-register (PR) profile, as many vendors' Modbus servos do it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PrMap {
    /// First register of the block: mode, position (2), speed rpm, acceleration ms,
    /// deceleration ms, dwell ms — written with one multi-register write.
    pub block: u16,
    /// Trigger register and the value that starts the block's move.
    pub trigger: u16,
    pub trigger_value: u16,
    /// Servo on (1) / off (0).
    pub servo_on: u16,
    /// Status bits (see `pr_status`).
    pub status: u16,
    /// Actual position (2 registers).
    pub position_actual: u16,
    /// Alarm code (0 = none); `"none"`: the drive has no such register.
    #[serde(deserialize_with = "optional_register")]
    pub alarm_code: Option<u16>,
    /// Write 1 to clear a latched alarm.
    pub alarm_reset: u16,
    /// Communication timeout, ms (0 = off); `"none"`: the drive has none (the master warns).
    #[serde(deserialize_with = "optional_register")]
    pub comm_timeout_ms: Option<u16>,
    pub word_order: WordOrder,
    /// How the cyclic read is split (`ReadBlocks`).
    pub reads: ReadBlocks,
    /// Encoder counts per motor revolution: the block's speed is in motor rpm, so the master
    /// needs it to turn the streamed counts per cycle into rpm. Set it to the drive's.
    pub counts_per_rev: u32,
}

impl Default for PrMap {
    fn default() -> Self {
        PrMap {
            block: 0x6200,
            trigger: 0x6002,
            trigger_value: 0x0010,
            servo_on: 0x0405,
            status: 0x6003,
            position_actual: 0x602A,
            alarm_code: Some(0x2203),
            alarm_reset: 0x0033,
            comm_timeout_ms: Some(0x0050),
            word_order: WordOrder::HighFirst,
            reads: ReadBlocks::Auto,
            // sim-drives' linear axis: 10 000 counts/mm on a 10 mm lead.
            counts_per_rev: 100_000,
        }
    }
}

/// Length of the PR block in registers.
pub const PR_BLOCK_LEN: u16 = 7;
/// PR block mode word: absolute positioning.
pub const PR_MODE_ABSOLUTE: u16 = 0x0001;

/// Bits of the PR profile's status register.
pub mod pr_status {
    /// A latched alarm (read the alarm code).
    pub const FAULT: u16 = 1 << 0;
    /// Servo on (power stage enabled).
    pub const ENABLED: u16 = 1 << 1;
    /// A PR move is running.
    pub const RUNNING: u16 = 1 << 2;
    /// Position reached (within the in-position window).
    pub const IN_POSITION: u16 = 1 << 3;
}

/// The PR block for an absolute move to `pos` counts.
pub fn pr_block(pos: i32, speed_rpm: u16, accel_ms: u16, decel_ms: u16, dwell_ms: u16, order: WordOrder) -> [u16; PR_BLOCK_LEN as usize] {
    let p = order.split_i32(pos);
    [PR_MODE_ABSOLUTE, p[0], p[1], speed_rpm, accel_ms, decel_ms, dwell_ms]
}

/// Serial line settings for RTU timing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SerialTiming {
    pub baud: u32,
    /// Parity bit present (even/odd).
    pub parity: bool,
    pub stop_bits: u8,
}

impl SerialTiming {
    /// Bits on the wire per character: start + 8 data + parity + stop.
    pub fn bits_per_char(&self) -> u32 {
        1 + 8 + self.parity as u32 + self.stop_bits as u32
    }
    /// One character, seconds.
    pub fn char_s(&self) -> f64 {
        self.bits_per_char() as f64 / self.baud.max(1) as f64
    }
    /// The inter-frame silence t3.5. Modbus over Serial Line V1.02 §2.5.1.1: above
    /// 19200 baud a fixed 1.750 ms.
    pub fn t35_s(&self) -> f64 {
        if self.baud > 19_200 {
            1.75e-3
        } else {
            3.5 * self.char_s()
        }
    }
    /// One request/response transaction: both frames on the wire, the silence that ends each
    /// frame, and the server's turnaround.
    pub fn transaction_s(&self, req_bytes: usize, resp_bytes: usize, turnaround_s: f64) -> f64 {
        (req_bytes + resp_bytes) as f64 * self.char_s() + 2.0 * self.t35_s() + turnaround_s
    }
}

/// RTU frame sizes (address, function, data, CRC) of the functions the master uses.
pub mod rtu_size {
    /// FC03 read `n` holding registers: (request, response).
    pub fn read(n: usize) -> (usize, usize) {
        (8, 5 + 2 * n)
    }
    /// FC16 write `n` registers.
    pub fn write(n: usize) -> (usize, usize) {
        (9 + 2 * n, 8)
    }
    /// FC06 write one register.
    pub fn write_single() -> (usize, usize) {
        (8, 8)
    }
    /// FC23 read `r` and write `w` registers in one transaction.
    pub fn read_write(r: usize, w: usize) -> (usize, usize) {
        (13 + 2 * w, 5 + 2 * r)
    }
}

/// The smallest contiguous span `[start, start+len)` covering `regs` (each `(addr, len)`).
pub fn span(regs: &[(u16, u16)]) -> (u16, u16) {
    let lo = regs.iter().map(|r| r.0).min().unwrap_or(0);
    let hi = regs.iter().map(|r| r.0 as u32 + r.1 as u32).max().unwrap_or(lo as u32);
    (lo, (hi - lo as u32).min(u16::MAX as u32) as u16)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 24: the homing registers and the digital inputs are in the built-in map only; a
    /// map table written for a drive that does not name them means the drive has none (so
    /// that no homing is written into what registers 24–34 are on that drive). The older
    /// registers keep their defaults.
    #[test]
    fn a_map_table_without_the_homing_registers_has_none() {
        let d = Cia402Map::default();
        assert_eq!((d.homing_method, d.home_offset, d.homing_accel, d.digital_inputs), (Some(24), Some(25), Some(31), Some(33)));
        let m: Cia402Map = toml::from_str("error_code = 18").unwrap();
        assert_eq!(
            (m.homing_method, m.home_offset, m.homing_switch_speed, m.homing_zero_speed, m.homing_accel, m.digital_inputs),
            (None, None, None, None, None, None)
        );
        assert_eq!((m.error_code, m.interpolation_ms, m.comm_timeout_ms, m.statusword), (Some(18), Some(20), Some(23), 10));
        let m: Cia402Map = toml::from_str("homing_method = 0x100\nhome_offset = \"none\"\ndigital_inputs = 0x200").unwrap();
        assert_eq!((m.homing_method, m.home_offset, m.digital_inputs), (Some(0x100), None, Some(0x200)));
        assert!(m.registers().iter().any(|r| r.name == "digital_inputs" && r.len == 2 && !r.writable));
    }

    #[test]
    fn word_order_round_trip() {
        for o in [WordOrder::HighFirst, WordOrder::LowFirst] {
            for v in [0, 1, -1, i32::MIN, i32::MAX, 0x1234_5678, -123_456_789] {
                assert_eq!(o.join_i32(o.split_i32(v)), v);
            }
        }
        assert_eq!(WordOrder::HighFirst.split_i32(0x1234_5678), [0x1234, 0x5678]);
        assert_eq!(WordOrder::LowFirst.split_i32(0x1234_5678), [0x5678, 0x1234]);
        assert_eq!(WordOrder::HighFirst.split_i32(-2), [0xFFFF, 0xFFFE]);
    }

    #[test]
    fn rtu_timing_115200_8n1() {
        let t = SerialTiming { baud: 115_200, parity: false, stop_bits: 1 };
        assert_eq!(t.bits_per_char(), 10);
        assert!((t.char_s() - 86.8e-6).abs() < 0.1e-6);
        assert_eq!(t.t35_s(), 1.75e-3);
        // FC16 of 3 registers + FC03 of 7: 15+8 and 8+19 bytes.
        let (rq, rs) = rtu_size::write(3);
        assert_eq!((rq, rs), (15, 8));
        let s = t.transaction_s(rq, rs, 0.0);
        assert!((s - (23.0 * 86.806e-6 + 3.5e-3)).abs() < 1e-6, "{s}");
    }

    #[test]
    fn rtu_timing_9600_8e1() {
        let t = SerialTiming { baud: 9600, parity: true, stop_bits: 1 };
        assert_eq!(t.bits_per_char(), 11);
        // t3.5 = 3.5 × 11 / 9600 = 4.01 ms
        assert!((t.t35_s() - 4.0104e-3).abs() < 1e-6);
    }

    #[test]
    fn default_cia402_cyclic_blocks_are_contiguous() {
        let m = Cia402Map::default();
        assert_eq!(span(&[(m.controlword, 1), (m.target_position, 2)]), (0, 3));
        assert_eq!(m.cyclic_reads(), vec![(10, 7)]);
    }

    #[test]
    fn reads_split_into_blocks() {
        let regs = [(16, 1), (10, 1), (12, 2), (13, 1)];
        assert_eq!(ReadBlocks::Span.blocks(&regs), vec![(10, 7)]);
        assert_eq!(ReadBlocks::Auto.blocks(&regs), vec![(10, 7)]);
        assert_eq!(ReadBlocks::Contiguous.blocks(&regs), vec![(10, 1), (12, 2), (16, 1)]);
        assert_eq!(ReadBlocks::Single.blocks(&[(16, 1), (10, 1), (12, 2)]), vec![(10, 1), (12, 2), (16, 1)]);
        // The PR map's registers lie far apart: one read each.
        assert_eq!(PrMap::default().cyclic_reads(), vec![(0x2203, 1), (0x6003, 1), (0x602A, 2)]);
        // Adjacent ones are merged.
        assert_eq!(ReadBlocks::Contiguous.blocks(&[(10, 1), (11, 2), (13, 1)]), vec![(10, 4)]);
    }

    #[test]
    fn optional_registers_are_an_address_or_none() {
        #[derive(Deserialize)]
        struct W {
            m: Cia402Map,
        }
        let w: W = toml::from_str("[m]\ninterpolation_ms = \"none\"\nerror_code = 30\nreads = \"contiguous\"\n").unwrap();
        assert_eq!((w.m.interpolation_ms, w.m.error_code, w.m.comm_timeout_ms), (None, Some(30), Some(23)));
        assert_eq!(w.m.reads, ReadBlocks::Contiguous);
        assert_eq!(w.m.cyclic_reads(), vec![(10, 1), (12, 2), (30, 1)]);
        let e = toml::from_str::<W>("[m]\ncomm_timeout_ms = \"off\"\n").err().unwrap().to_string();
        assert!(e.contains("a register address (0…65535) or \"none\", got \"off\""), "{e}");
    }

    #[test]
    fn pr_block_layout() {
        let b = pr_block(-100_000, 1500, 50, 60, 0, WordOrder::HighFirst);
        assert_eq!(b[0], PR_MODE_ABSOLUTE);
        assert_eq!(WordOrder::HighFirst.join_i32([b[1], b[2]]), -100_000);
        assert_eq!(&b[3..], &[1500, 50, 60, 0]);
    }
}
