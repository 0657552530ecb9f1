//! Which Modbus transactions each drive needs, at start-up and every link cycle, from its
//! profile and register map. Pure: no I/O, so the cycle computation and the tests use it.

use super::link::{Command, Reading};
use cncgw_bus::modbus::{pr_block, pr_status, rtu_size, Cia402Map, PrMap, Profile, PR_BLOCK_LEN};

/// One Modbus transaction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Exchange {
    /// Function 3.
    Read { addr: u16, len: u16 },
    /// Function 16.
    Write { addr: u16, len: u16 },
    /// Function 6.
    WriteSingle { addr: u16 },
    /// Function 23.
    ReadWrite { read_addr: u16, read_len: u16, write_addr: u16, write_len: u16 },
}

impl Exchange {
    /// RTU request and response sizes in bytes.
    pub fn rtu_bytes(&self) -> (usize, usize) {
        match *self {
            Exchange::Read { len, .. } => rtu_size::read(len as usize),
            Exchange::Write { len, .. } => rtu_size::write(len as usize),
            Exchange::WriteSingle { .. } => rtu_size::write_single(),
            Exchange::ReadWrite { read_len, write_len, .. } => rtu_size::read_write(read_len as usize, write_len as usize),
        }
    }

    pub fn reads(&self) -> bool {
        matches!(self, Exchange::Read { .. } | Exchange::ReadWrite { .. })
    }

    /// In words, for errors: function, register, count.
    pub fn describe(&self) -> String {
        match *self {
            Exchange::Read { addr, len } => format!("function 03 (read holding registers) at register {addr} (0x{addr:04X}), {len} registers"),
            Exchange::Write { addr, len } => format!("function 16 (write multiple registers) at register {addr} (0x{addr:04X}), {len} registers"),
            Exchange::WriteSingle { addr } => format!("function 06 (write single register) at register {addr} (0x{addr:04X})"),
            Exchange::ReadWrite { read_addr, read_len, write_addr, write_len } => format!(
                "function 23 (read/write multiple registers) reading {read_len} at {read_addr} (0x{read_addr:04X}), writing {write_len} at {write_addr} (0x{write_addr:04X})"
            ),
        }
    }
}

/// One drive on a link.
#[derive(Clone, Debug)]
pub struct DrivePlan {
    pub axis: String,
    pub unit: u8,
    pub profile: Profile,
    pub cia: Cia402Map,
    pub pr: PrMap,
    pub fc23: bool,
    /// Following-error window, counts.
    pub ferr_window: u32,
    /// Configuration written at start-up (before the cycle is known).
    pub setup: Vec<(Exchange, Vec<u16>)>,
    /// The exchanges of one link cycle while streaming (for the cycle computation).
    pub cyclic: Vec<Exchange>,
    /// Target last written (counts, wire value).
    pub last_target: i32,
    /// PR: what was last written to servo-on and the alarm reset.
    written_servo_on: Option<bool>,
    written_reset_seq: u32,
    /// The link cycle, ms (PR speed computation).
    cycle_ms: f64,
    /// PR: the position last read (counts, wire value), for the speed that closes what the
    /// drive has left of earlier blocks.
    pub last_actual: Option<i32>,
    /// PR: the axis's maximum speed in motor rpm (the block's speed never asks for more).
    pub max_rpm: f64,
    /// CiA 402 spindle: may run in speed (cyclic synchronous velocity, `Command::speed_mode`).
    pub speed_capable: bool,
    /// CiA 402: the mode (speed?) and following-error window last written; `None`: write it
    /// again (a cycle failed part-way).
    written_speed: Option<bool>,
    written_window: Option<u32>,
}

impl DrivePlan {
    pub fn new(axis: &str, unit: u8, profile: Profile, cia: Cia402Map, pr: PrMap, fc23: bool, ferr_window: u32) -> DrivePlan {
        let mut d = DrivePlan {
            axis: axis.to_string(),
            unit,
            profile,
            cia,
            pr,
            fc23,
            ferr_window,
            setup: Vec::new(),
            cyclic: Vec::new(),
            last_target: 0,
            written_servo_on: None,
            written_reset_seq: 0,
            cycle_ms: 1.0,
            last_actual: None,
            max_rpm: u16::MAX as f64,
            speed_capable: false,
            // Start-up writes mode 8 and the window.
            written_speed: Some(false),
            written_window: Some(ferr_window),
        };
        d.setup = match profile {
            Profile::Cia402 => vec![
                (Exchange::WriteSingle { addr: cia.mode }, vec![cncgw_bus::cia402::mode::CYCLIC_SYNC_POSITION as u16]),
                (Exchange::Write { addr: cia.following_error_window, len: 2 }, cia.word_order.split_i32(ferr_window as i32).to_vec()),
            ],
            // The PR drive is told nothing up front: it starts with servo off, and the
            // cycle thread turns it on.
            Profile::Pr => Vec::new(),
        };
        d.cyclic = d.steady_cycle();
        d
    }

    /// The exchanges of one link cycle while streaming, in the steady state (the second
    /// cycle: the first also writes the PR servo-on or a change of mode, once). A spindle
    /// that may run in speed counts its longer write (controlword, target position and
    /// target velocity), so that the link cycle holds in either mode.
    fn steady_cycle(&self) -> Vec<Exchange> {
        let probe = Command { stream: true, servo_on: true, speed_mode: self.speed_capable, ..Command::default() };
        let mut tmp = self.clone();
        tmp.cyclic_writes(&probe);
        tmp.cyclic_writes(&probe).into_iter().map(|x| x.0).collect()
    }

    /// Let this CiA 402 drive (a spindle) run in speed when asked (`Command::speed_mode`).
    pub fn allow_speed_mode(&mut self) {
        if self.profile == Profile::Cia402 {
            self.speed_capable = true;
            self.cyclic = self.steady_cycle();
        }
    }

    /// Controlword, target position and target velocity in one write (the default map).
    fn cia_speed_write_contiguous(&self) -> bool {
        self.cia_write_contiguous() && self.cia.target_velocity == self.cia.controlword.wrapping_add(3)
    }

    fn cia_write_contiguous(&self) -> bool {
        self.cia.target_position == self.cia.controlword.wrapping_add(1)
    }

    /// The cyclic reads: one per block of the map (`ReadBlocks`).
    fn read_blocks(&self) -> Vec<Exchange> {
        let blocks = match self.profile {
            Profile::Cia402 => self.cia.cyclic_reads(),
            Profile::Pr => self.pr.cyclic_reads(),
        };
        blocks.into_iter().map(|(addr, len)| Exchange::Read { addr, len }).collect()
    }

    /// What the map leaves out, in words, for the start-up log and `config check`: the
    /// optional registers set to `"none"`.
    pub fn map_warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        let (err, ipo, wd) = match self.profile {
            Profile::Cia402 => (self.cia.error_code, self.cia.interpolation_ms, self.cia.comm_timeout_ms),
            Profile::Pr => (self.pr.alarm_code, Some(0), self.pr.comm_timeout_ms),
        };
        let axis = &self.axis;
        if err.is_none() {
            w.push(format!("axis {axis}: the register map has no error code register: a drive fault is alarmed without its code"));
        }
        if ipo.is_none() {
            w.push(format!(
                "axis {axis}: the register map has no interpolation period register: the drive is not told the link cycle; set it on the drive to the link cycle cncgw logs at start-up"
            ));
        }
        if wd.is_none() {
            w.push(format!(
                "axis {axis}: the register map has no communication watchdog register: if cncgw dies the drive is not stopped by its own watchdog; set one on the drive"
            ));
        }
        w
    }

    /// A cycle failed part-way: write servo-on and the alarm reset again next cycle.
    pub fn forget_writes(&mut self) {
        self.written_servo_on = None;
        self.written_speed = None;
        self.written_window = None;
        self.written_reset_seq = self.written_reset_seq.wrapping_sub(1);
    }

    /// The read that returns the feedback (round-trip measurement).
    pub fn feedback_read(&self) -> Exchange {
        match self.profile {
            Profile::Cia402 => self.read_blocks().first().copied().unwrap_or(Exchange::Read { addr: self.cia.statusword, len: 1 }),
            Profile::Pr => Exchange::Read { addr: self.pr.status, len: 1 },
        }
    }

    /// The interpolation period register, if the drive has one (read back after the write).
    pub fn interpolation_register(&self) -> Option<u16> {
        match self.profile {
            Profile::Cia402 => self.cia.interpolation_ms,
            Profile::Pr => None,
        }
    }

    /// Writes that depend on the link cycle: the interpolation period and the watchdog.
    /// `timeout_ms`: the link's transaction timeout (a drive ahead of this one on the line
    /// may take that long to time out before this one's write goes).
    pub fn timing_writes(&mut self, cycle_ms: u16, timeout_ms: u32) -> Vec<(Exchange, Vec<u16>)> {
        self.cycle_ms = cycle_ms as f64;
        // Ten link cycles and two transaction timeouts, at least 200 ms: one drive's missed
        // answer or a scheduling hiccup must not trip it, a dead controller must (the
        // CANopen side uses 3 × the 100 ms heartbeat).
        let watchdog = (cycle_ms as u32 * 10).max(timeout_ms.saturating_mul(2).saturating_add(cycle_ms as u32)).clamp(200, u16::MAX as u32) as u16;
        let (ipo, wd) = match self.profile {
            Profile::Cia402 => (self.cia.interpolation_ms, self.cia.comm_timeout_ms),
            Profile::Pr => (None, self.pr.comm_timeout_ms),
        };
        // Registers the map says the drive does not have are skipped (`map_warnings`).
        let mut v = Vec::new();
        v.extend(ipo.map(|addr| (Exchange::WriteSingle { addr }, vec![cycle_ms])));
        v.extend(wd.map(|addr| (Exchange::WriteSingle { addr }, vec![watchdog])));
        v
    }

    /// The transactions of one link cycle for `cmd`, with the data they write.
    pub fn cyclic_writes(&mut self, cmd: &Command) -> Vec<(Exchange, Vec<u16>)> {
        let mut v = Vec::with_capacity(4);
        match self.profile {
            Profile::Cia402 => {
                let m = self.cia;
                let reads = self.read_blocks();
                let speed = cmd.speed_mode && self.speed_capable;
                // A change of mode (speed ↔ position) or of the window goes first, so that
                // this cycle's targets are taken in the new mode.
                if self.written_speed != Some(speed) {
                    use cncgw_bus::cia402::mode;
                    let mo = if speed { mode::CYCLIC_SYNC_VELOCITY } else { mode::CYCLIC_SYNC_POSITION };
                    v.push((Exchange::WriteSingle { addr: m.mode }, vec![mo as u16]));
                    self.written_speed = Some(speed);
                }
                let window = if cmd.ferr_window > 0 { cmd.ferr_window } else { self.ferr_window };
                if self.written_window != Some(window) {
                    v.push((Exchange::Write { addr: m.following_error_window, len: 2 }, m.word_order.split_i32(window as i32).to_vec()));
                    self.written_window = Some(window);
                }
                let vel = m.word_order.split_i32(cmd.velocity.round().clamp(i32::MIN as f64, i32::MAX as f64) as i32);
                let mut data = vec![cmd.controlword];
                let write = if cmd.stream && speed && self.cia_speed_write_contiguous() {
                    data.extend_from_slice(&m.word_order.split_i32(cmd.target));
                    data.extend_from_slice(&vel);
                    Exchange::Write { addr: m.controlword, len: 5 }
                } else if cmd.stream && speed {
                    v.push((Exchange::Write { addr: m.target_velocity, len: 2 }, vel.to_vec()));
                    Exchange::Write { addr: m.controlword, len: 1 }
                } else if cmd.stream && self.cia_write_contiguous() {
                    data.extend_from_slice(&m.word_order.split_i32(cmd.target));
                    Exchange::Write { addr: m.controlword, len: 3 }
                } else {
                    if cmd.stream {
                        v.push((Exchange::Write { addr: m.target_position, len: 2 }, m.word_order.split_i32(cmd.target).to_vec()));
                    }
                    Exchange::Write { addr: m.controlword, len: 1 }
                };
                let mut rest = reads.as_slice();
                match (self.fc23, write, reads.first()) {
                    (true, Exchange::Write { addr, len }, Some(&Exchange::Read { addr: ra, len: rl })) => {
                        // The first read block rides on the write; the others are read alone.
                        v.push((Exchange::ReadWrite { read_addr: ra, read_len: rl, write_addr: addr, write_len: len }, data));
                        rest = &reads[1..];
                    }
                    (_, Exchange::Write { addr, len: 1 }, _) => v.push((Exchange::WriteSingle { addr }, data)),
                    (_, x, _) => v.push((x, data)),
                }
                v.extend(rest.iter().map(|x| (*x, Vec::new())));
            }
            Profile::Pr => {
                let m = self.pr;
                if self.written_servo_on != Some(cmd.servo_on) {
                    v.push((Exchange::WriteSingle { addr: m.servo_on }, vec![cmd.servo_on as u16]));
                    self.written_servo_on = Some(cmd.servo_on);
                }
                if cmd.alarm_reset_seq != self.written_reset_seq {
                    v.push((Exchange::WriteSingle { addr: m.alarm_reset }, vec![1]));
                    self.written_reset_seq = cmd.alarm_reset_seq;
                }
                if cmd.stream && cmd.servo_on {
                    let rpm = self.pr_speed_rpm(cmd.target);
                    let ramp = self.cycle_ms.round().clamp(1.0, u16::MAX as f64) as u16;
                    let block = pr_block(cmd.target, rpm, ramp, ramp, 0, m.word_order);
                    v.push((Exchange::Write { addr: m.block, len: PR_BLOCK_LEN }, block.to_vec()));
                    v.push((Exchange::WriteSingle { addr: m.trigger }, vec![m.trigger_value]));
                }
                for x in self.read_blocks() {
                    v.push((x, Vec::new()));
                }
            }
        }
        v
    }

    /// PR: the block's speed (motor rpm) for the move to `target`. The drive is retargeted
    /// every link cycle and moves at the block's speed until it is there, so the speed is
    /// the larger of
    /// - the set-point's own step over one link cycle (+1 rpm for the rounding), the speed
    ///   of the path, and
    /// - what the drive has left to go from the position last read, over two link cycles:
    ///   a drive behind its set-points (a link cycle shorter than told, a late write, its
    ///   own ramp) closes the gap within a few cycles. Without it a set-point that stands
    ///   (the end of a move) was sent at 1 rpm and the remainder crawled (issue 22.5:
    ///   first_part ended X 0.3 mm short). Over two cycles because the reading is a cycle
    ///   old: the drive has since moved about one cycle's step toward the last target.
    ///
    /// Bounded by the axis's maximum speed (a drive refuses a block above its own rated
    /// speed with 0x03) and at least 1 rpm (0 is no move on many drives).
    pub fn pr_speed_rpm(&self, target: i32) -> u16 {
        let rpm_per_count_s = 60.0 / self.pr.counts_per_rev.max(1) as f64;
        let cycle_s = self.cycle_ms.max(0.001) * 1e-3;
        let step = (target as i64 - self.last_target as i64).unsigned_abs() as f64 / cycle_s * rpm_per_count_s;
        let left = self.last_actual.map_or(0.0, |p| (target as i64 - p as i64).unsigned_abs() as f64) / (2.0 * cycle_s) * rpm_per_count_s;
        let rpm = if step > 0.0 { step.ceil() + 1.0 } else { 0.0 }.max(left.ceil());
        rpm.min(self.max_rpm.floor()).clamp(1.0, u16::MAX as f64) as u16
    }

    /// Fold the registers `regs` read by `x` into `prev`.
    pub fn decode(&self, x: &Exchange, regs: &[u16], prev: Option<Reading>) -> Option<Reading> {
        let (addr, len) = match *x {
            Exchange::Read { addr, len } => (addr, len),
            Exchange::ReadWrite { read_addr, read_len, .. } => (read_addr, read_len),
            _ => return prev,
        };
        let get = |a: u16| -> Option<u16> {
            let i = a.checked_sub(addr)?;
            if i < len {
                regs.get(i as usize).copied()
            } else {
                None
            }
        };
        let mut r = prev.unwrap_or_default();
        match self.profile {
            Profile::Cia402 => {
                let m = &self.cia;
                if let Some(sw) = get(m.statusword) {
                    r.statusword = sw;
                }
                if let (Some(a), Some(b)) = (get(m.position_actual), get(m.position_actual.wrapping_add(1))) {
                    r.position = m.word_order.join_i32([a, b]);
                }
                if let Some(e) = m.error_code.and_then(get) {
                    r.error_code = e;
                }
            }
            Profile::Pr => {
                let m = &self.pr;
                if let Some(st) = get(m.status) {
                    r.statusword = pr_statusword(st);
                }
                if let (Some(a), Some(b)) = (get(m.position_actual), get(m.position_actual.wrapping_add(1))) {
                    r.position = m.word_order.join_i32([a, b]);
                }
                if let Some(e) = m.alarm_code.and_then(get) {
                    r.error_code = e;
                }
            }
        }
        Some(r)
    }
}

/// A PR drive's status register as the CiA 402 statusword of the equivalent state, so that
/// the layers above see one kind of drive.
pub fn pr_statusword(st: u16) -> u16 {
    use cncgw_bus::cia402::State;
    let s = if st & pr_status::FAULT != 0 {
        State::Fault
    } else if st & pr_status::ENABLED != 0 {
        State::OperationEnabled
    } else {
        State::SwitchOnDisabled
    };
    let mut w = s.statusword_bits();
    if st & pr_status::IN_POSITION != 0 {
        w |= cncgw_bus::cia402::sw::TARGET_REACHED;
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;
    use cncgw_bus::modbus::WordOrder;

    #[test]
    fn cia402_default_map_needs_two_transactions_or_one_fc23() {
        let d = DrivePlan::new("x", 1, Profile::Cia402, Cia402Map::default(), PrMap::default(), false, 10_000);
        assert_eq!(d.cyclic, vec![Exchange::Write { addr: 0, len: 3 }, Exchange::Read { addr: 10, len: 7 }]);
        let d = DrivePlan::new("x", 1, Profile::Cia402, Cia402Map::default(), PrMap::default(), true, 10_000);
        assert_eq!(d.cyclic, vec![Exchange::ReadWrite { read_addr: 10, read_len: 7, write_addr: 0, write_len: 3 }]);
    }

    #[test]
    fn cia402_scattered_map_writes_target_then_controlword() {
        let m = Cia402Map { target_position: 0x20, ..Cia402Map::default() };
        let mut d = DrivePlan::new("z", 2, Profile::Cia402, m, PrMap::default(), false, 10_000);
        let w = d.cyclic_writes(&Command { controlword: 0x0F, target: -5, stream: true, ..Command::default() });
        assert_eq!(w[0], (Exchange::Write { addr: 0x20, len: 2 }, vec![0xFFFF, 0xFFFB]));
        assert_eq!(w[1], (Exchange::WriteSingle { addr: 0 }, vec![0x0F]));
        // Not streaming (enabling): only the controlword.
        let w = d.cyclic_writes(&Command { controlword: 0x06, ..Command::default() });
        assert_eq!(w[0], (Exchange::WriteSingle { addr: 0 }, vec![0x06]));
        assert!(matches!(w[1].0, Exchange::Read { .. }));
    }

    #[test]
    fn decode_in_both_word_orders() {
        for order in [WordOrder::HighFirst, WordOrder::LowFirst] {
            let m = Cia402Map { word_order: order, ..Cia402Map::default() };
            let d = DrivePlan::new("x", 1, Profile::Cia402, m, PrMap::default(), false, 1);
            let mut regs = vec![0u16; 7];
            regs[0] = 0x0237;
            regs[2..4].copy_from_slice(&order.split_i32(-123_456));
            regs[6] = 0x8611;
            let r = d.decode(&Exchange::Read { addr: 10, len: 7 }, &regs, None).unwrap();
            assert_eq!((r.statusword, r.position, r.error_code), (0x0237, -123_456, 0x8611));
        }
    }

    #[test]
    fn pr_streams_block_and_trigger_with_speed_for_one_cycle() {
        let mut d = DrivePlan::new("w", 4, Profile::Pr, Cia402Map::default(), PrMap::default(), false, 1);
        d.timing_writes(10, 100);
        d.last_target = 0;
        // 1000 counts in 10 ms at 100 000 counts/rev = 60 rpm.
        let w = d.cyclic_writes(&Command { servo_on: true, target: 1000, stream: true, ..Command::default() });
        assert_eq!(w[0], (Exchange::WriteSingle { addr: 0x0405 }, vec![1]));
        let (x, block) = &w[1];
        assert_eq!(*x, Exchange::Write { addr: 0x6200, len: 7 });
        assert_eq!(block[3], 61);
        assert_eq!(w[2], (Exchange::WriteSingle { addr: 0x6002 }, vec![0x0010]));
        // Servo-on is written once.
        let w = d.cyclic_writes(&Command { servo_on: true, target: 1000, stream: true, ..Command::default() });
        assert!(w.iter().all(|(x, _)| *x != Exchange::WriteSingle { addr: 0x0405 }));
    }

    #[test]
    fn pr_speed_closes_what_the_drive_has_left() {
        let mut d = DrivePlan::new("w", 4, Profile::Pr, Cia402Map::default(), PrMap::default(), false, 1);
        d.timing_writes(10, 100);
        d.max_rpm = 1000.0;
        // The set-point stands at 50 000 and the drive was read 3 000 counts short of it:
        // 3 000 counts over two 10 ms cycles = 150 000 counts/s = 90 rpm (was 1 rpm).
        d.last_target = 50_000;
        d.last_actual = Some(47_000);
        assert_eq!(d.pr_speed_rpm(50_000), 90);
        // Moving: the step's speed when the drive keeps up (1 000 counts per cycle = 60 rpm).
        d.last_actual = Some(49_500);
        assert_eq!(d.pr_speed_rpm(51_000), 61);
        // Far behind: never above the axis's maximum speed.
        d.last_actual = Some(0);
        assert_eq!(d.pr_speed_rpm(500_000), 1000);
        // At the target: the slowest speed, not 0.
        d.last_actual = Some(50_000);
        assert_eq!(d.pr_speed_rpm(50_000), 1);
    }

    #[test]
    fn pr_cycle_counts_the_block_trigger_and_reads() {
        let d = DrivePlan::new("w", 4, Profile::Pr, Cia402Map::default(), PrMap::default(), false, 1);
        assert_eq!(
            d.cyclic,
            vec![
                Exchange::Write { addr: 0x6200, len: 7 },
                Exchange::WriteSingle { addr: 0x6002 },
                Exchange::Read { addr: 0x2203, len: 1 },
                Exchange::Read { addr: 0x6003, len: 1 },
                Exchange::Read { addr: 0x602A, len: 2 },
            ]
        );
    }

    #[test]
    fn split_reads_with_fc23_carry_the_first_block() {
        let m = Cia402Map { error_code: Some(18), reads: cncgw_bus::modbus::ReadBlocks::Contiguous, ..Cia402Map::default() };
        let d = DrivePlan::new("z", 2, Profile::Cia402, m, PrMap::default(), true, 1);
        assert_eq!(
            d.cyclic,
            vec![
                Exchange::ReadWrite { read_addr: 10, read_len: 1, write_addr: 0, write_len: 3 },
                Exchange::Read { addr: 12, len: 2 },
                Exchange::Read { addr: 18, len: 1 },
            ]
        );
    }

    #[test]
    fn pr_status_maps_to_cia402_states() {
        use cncgw_bus::cia402::State;
        assert_eq!(State::from_statusword(pr_statusword(pr_status::FAULT)), State::Fault);
        assert_eq!(State::from_statusword(pr_statusword(pr_status::ENABLED)), State::OperationEnabled);
        assert_eq!(State::from_statusword(pr_statusword(0)), State::SwitchOnDisabled);
    }

    /// A spindle in speed: mode 9 once, then controlword, target position and target
    /// velocity in one FC16 every cycle; back in position: mode 8 and the new window first.
    #[test]
    fn cia402_spindle_in_speed_writes_mode_9_and_the_target_velocity() {
        let mut d = DrivePlan::new("s1", 3, Profile::Cia402, Cia402Map::default(), PrMap::default(), false, 30_000);
        d.allow_speed_mode();
        // The cycle is counted with the longer write.
        assert_eq!(d.cyclic, vec![Exchange::Write { addr: 0, len: 5 }, Exchange::Read { addr: 10, len: 7 }]);
        let cmd = Command { controlword: 0x0F, target: 7, velocity: 9.0e6, stream: true, speed_mode: true, ..Command::default() };
        let w = d.cyclic_writes(&cmd);
        assert_eq!(w[0], (Exchange::WriteSingle { addr: 5 }, vec![9]));
        let v = WordOrder::HighFirst.split_i32(9_000_000);
        assert_eq!(w[1], (Exchange::Write { addr: 0, len: 5 }, vec![0x0F, 0, 7, v[0], v[1]]));
        assert_eq!(d.cyclic_writes(&cmd)[0].0, Exchange::Write { addr: 0, len: 5 });
        let cmd = Command { speed_mode: false, ferr_window: 500_000, ..cmd };
        let w = d.cyclic_writes(&cmd);
        assert_eq!(w[0], (Exchange::WriteSingle { addr: 5 }, vec![8]));
        assert_eq!(w[1], (Exchange::Write { addr: 21, len: 2 }, WordOrder::HighFirst.split_i32(500_000).to_vec()));
        assert_eq!(w[2], (Exchange::Write { addr: 0, len: 3 }, vec![0x0F, 0, 7]));
        // A map whose target velocity is elsewhere: its own FC16, then the controlword.
        let m = Cia402Map { target_velocity: 0x30, ..Cia402Map::default() };
        let mut d = DrivePlan::new("s1", 3, Profile::Cia402, m, PrMap::default(), false, 30_000);
        d.allow_speed_mode();
        assert_eq!(d.cyclic, vec![Exchange::Write { addr: 0x30, len: 2 }, Exchange::WriteSingle { addr: 0 }, Exchange::Read { addr: 10, len: 7 }]);
    }

    #[test]
    fn rtu_sizes_of_the_cycle() {
        let d = DrivePlan::new("x", 1, Profile::Cia402, Cia402Map::default(), PrMap::default(), false, 1);
        let bytes: Vec<_> = d.cyclic.iter().map(|x| x.rtu_bytes()).collect();
        assert_eq!(bytes, vec![(15, 8), (8, 19)]);
    }
}
