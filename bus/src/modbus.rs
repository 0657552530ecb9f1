//! Modbus drive register maps and link timing, shared by the cncgw master and sim-drives.
//!
//! The Modbus frame codec itself is tokio-modbus's (client in cncgw, server in sim-drives):
//! one implementation on both sides. What is ours is how a drive's process data sit in its
//! holding registers — two profiles, every address configurable — and what a link can carry
//! per cycle.

use serde::Deserialize;

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
    /// 0x603F error code.
    pub error_code: u16,
    /// 0x60C2 interpolation period in ms (the link cycle; the drive interpolates over it).
    pub interpolation_ms: u16,
    /// 0x6065 following-error window, counts (2 registers).
    pub following_error_window: u16,
    /// Communication timeout, ms (the Modbus analogue of 0x1016/0x6007: no write for this
    /// long and the drive faults and stops by itself; 0 = off).
    pub comm_timeout_ms: u16,
    pub word_order: WordOrder,
}

impl Default for Cia402Map {
    /// The map sim-drives serves: the cyclic write (controlword + target) and the cyclic
    /// read (statusword … error code) are each one contiguous block.
    fn default() -> Self {
        Cia402Map {
            controlword: 0,
            target_position: 1,
            target_velocity: 3,
            mode: 5,
            statusword: 10,
            mode_display: 11,
            position_actual: 12,
            velocity_actual: 14,
            error_code: 16,
            interpolation_ms: 20,
            following_error_window: 21,
            comm_timeout_ms: 23,
            word_order: WordOrder::HighFirst,
        }
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
    /// Alarm code (0 = none).
    pub alarm_code: u16,
    /// Write 1 to clear a latched alarm.
    pub alarm_reset: u16,
    /// Communication timeout, ms (0 = off).
    pub comm_timeout_ms: u16,
    pub word_order: WordOrder,
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
            alarm_code: 0x2203,
            alarm_reset: 0x0033,
            comm_timeout_ms: 0x0050,
            word_order: WordOrder::HighFirst,
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
        assert_eq!(span(&[(m.statusword, 1), (m.position_actual, 2), (m.error_code, 1)]), (10, 7));
    }

    #[test]
    fn pr_block_layout() {
        let b = pr_block(-100_000, 1500, 50, 60, 0, WordOrder::HighFirst);
        assert_eq!(b[0], PR_MODE_ABSOLUTE);
        assert_eq!(WordOrder::HighFirst.join_i32([b[1], b[2]]), -100_000);
        assert_eq!(&b[3..], &[1500, 50, 60, 0]);
    }
}
