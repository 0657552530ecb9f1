//! The emulated drives behind the Modbus server: the same `Core` (physics, 402 state
//! machine, timers) as the CANopen emulator, with each drive's process data in holding
//! registers per its profile (`cncgw_bus::modbus::Cia402Map` or `PrMap`).

use super::pr::Gen;
use crate::{Core, FaultAt, ModbusQuirks, SimConfig, SimDrive};
use cncgw_bus::canopen::od as ix;
use cncgw_bus::canopen::sdo::abort;
use cncgw_bus::cia402::{cw, mode, State};
use cncgw_bus::modbus::{pr_status, Profile, WordOrder, PR_BLOCK_LEN, PR_MODE_ABSOLUTE};
use tokio_modbus::{ExceptionCode, Request, Response};

const MS: u64 = 1_000_000;
/// Most registers one FC03/FC04 reads (Modbus Application Protocol V1.1b3 §6.3).
pub const MAX_READ: u16 = 125;
/// Most registers one FC16 writes (§6.12).
pub const MAX_WRITE: u16 = 123;
/// Most registers the write part of one FC23 carries (§6.17).
pub const MAX_RW_WRITE: u16 = 121;
/// Error code of the Modbus watchdog (no write within the comm timeout): CiA 301's
/// "heartbeat / life guard error", as the CANopen drive raises on a lost master.
pub const COMM_TIMEOUT_CODE: u16 = 0x8130;
/// 0x6067 position window: the PR profile's in-position window.
const POSITION_WINDOW: u16 = 0x6067;
/// 0x607C home offset.
const HOME_OFFSET: u16 = 0x607C;
/// The PR profile's internal profile generator period.
const PR_PERIOD: u64 = MS;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Reg {
    Controlword,
    TargetPosition,
    TargetVelocity,
    Mode,
    Statusword,
    ModeDisplay,
    PositionActual,
    VelocityActual,
    ErrorCode,
    InterpolationMs,
    FerrWindow,
    Block,
    Trigger,
    ServoOn,
    Status,
    AlarmCode,
    AlarmReset,
    CommTimeout,
    HomingMethod,
    HomeOffset,
    HomingSwitchSpeed,
    HomingZeroSpeed,
    HomingAccel,
    DigitalInputs,
}

impl Reg {
    fn of(profile: Profile, name: &str) -> Option<Reg> {
        use Reg::*;
        Some(match (profile, name) {
            (Profile::Cia402, "controlword") => Controlword,
            (Profile::Cia402, "target_position") => TargetPosition,
            (Profile::Cia402, "target_velocity") => TargetVelocity,
            (Profile::Cia402, "mode") => Mode,
            (Profile::Cia402, "statusword") => Statusword,
            (Profile::Cia402, "mode_display") => ModeDisplay,
            (_, "position_actual") => PositionActual,
            (Profile::Cia402, "velocity_actual") => VelocityActual,
            (Profile::Cia402, "error_code") => ErrorCode,
            (Profile::Cia402, "interpolation_ms") => InterpolationMs,
            (Profile::Cia402, "following_error_window") => FerrWindow,
            (Profile::Pr, "block") => Block,
            (Profile::Pr, "trigger") => Trigger,
            (Profile::Pr, "servo_on") => ServoOn,
            (Profile::Pr, "status") => Status,
            (Profile::Pr, "alarm_code") => AlarmCode,
            (Profile::Pr, "alarm_reset") => AlarmReset,
            (_, "comm_timeout_ms") => CommTimeout,
            (Profile::Cia402, "homing_method") => HomingMethod,
            (Profile::Cia402, "home_offset") => HomeOffset,
            (Profile::Cia402, "homing_switch_speed") => HomingSwitchSpeed,
            (Profile::Cia402, "homing_zero_speed") => HomingZeroSpeed,
            (Profile::Cia402, "homing_accel") => HomingAccel,
            (Profile::Cia402, "digital_inputs") => DigitalInputs,
            _ => return None,
        })
    }

    fn writable(self) -> bool {
        use Reg::*;
        !matches!(self, Statusword | ModeDisplay | PositionActual | VelocityActual | ErrorCode | Status | AlarmCode | DigitalInputs)
    }

    /// The order writes of one request take effect: state first, then parameters, then the
    /// targets (latched last, with the state and parameters of the same request).
    fn apply_rank(self) -> u8 {
        use Reg::*;
        match self {
            AlarmReset => 0,
            Controlword | ServoOn => 1,
            Mode => 2,
            InterpolationMs | FerrWindow | CommTimeout | HomingMethod | HomeOffset | HomingSwitchSpeed | HomingZeroSpeed | HomingAccel => 3,
            Block => 4,
            TargetVelocity => 5,
            TargetPosition | Trigger => 6,
            _ => 7,
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Field {
    reg: Reg,
    addr: u16,
    len: u16,
}

/// PR profile state of one drive.
#[derive(Clone, Debug)]
struct Pr {
    trigger_value: u16,
    block: [u16; PR_BLOCK_LEN as usize],
    trigger: u16,
    servo_on: bool,
    /// The profile generator while the power stage is on.
    gen: Option<Gen>,
    /// Rated (= maximum) motor speed, rpm, and counts per revolution.
    rated_rpm: f64,
    counts_per_rev: f64,
    last_step: Option<u64>,
}

/// One drive as a Modbus unit.
struct Unit {
    node: u8,
    fields: Vec<Field>,
    order: WordOrder,
    comm_timeout_ms: u16,
    last_write: u64,
    /// When to latch the present target again (after a CSP segment that started from a
    /// hold, see `SimDrive::modbus_latch`).
    relatch_at: Option<u64>,
    pr: Option<Pr>,
    quirks: ModbusQuirks,
    /// Requests addressed to this unit so far (the quirks count them).
    requests: u64,
    /// Whether the drive was in Operation Enabled at the last look (`latch_any_time`).
    was_enabled: bool,
}

impl Unit {
    fn field_at(&self, addr: u16) -> Option<Field> {
        self.fields.iter().copied().find(|f| f.addr <= addr && (addr as u32) < f.addr as u32 + f.len as u32)
    }
}

/// The drives and their registers. Time in ns from the start.
pub(crate) struct World {
    core: Core,
    units: Vec<Unit>,
}

fn abort_to_exception(code: u32) -> ExceptionCode {
    match code {
        abort::READ_ONLY | abort::NO_OBJECT | abort::NO_SUBINDEX => ExceptionCode::IllegalDataAddress,
        abort::INVALID_VALUE | abort::VALUE_TOO_HIGH | abort::VALUE_TOO_LOW | abort::MAX_LESS_THAN_MIN | abort::PARAM_INCOMPATIBLE => {
            ExceptionCode::IllegalDataValue
        }
        _ => ExceptionCode::ServerDeviceFailure,
    }
}

impl World {
    pub fn new(cfg: SimConfig, faults: Vec<FaultAt>) -> Result<World, String> {
        cfg.validate()?;
        let mut units = Vec::new();
        for d in &cfg.drives {
            let p = d.modbus_profile;
            let mut fields: Vec<Field> =
                d.modbus_registers().into_iter().filter_map(|(name, addr, len)| Reg::of(p, name).map(|reg| Field { reg, addr, len })).collect();
            fields.sort_by_key(|f| f.addr);
            let order = match p {
                Profile::Cia402 => d.cia402_map.word_order,
                Profile::Pr => d.pr_map.word_order,
            };
            if p == Profile::Pr && d.pr_map.counts_per_rev != d.counts_per_rev {
                // The master turns counts into the block's rpm with the map's figure; the
                // drive turns rpm back into counts with its own.
                tracing::warn!(
                    node = d.node,
                    "pr_map.counts_per_rev = {} but the drive has {} counts/rev: PR speeds will be off by {:.3}×",
                    d.pr_map.counts_per_rev,
                    d.counts_per_rev,
                    d.counts_per_rev as f64 / d.pr_map.counts_per_rev.max(1) as f64
                );
            }
            let pr = (p == Profile::Pr).then_some(Pr {
                trigger_value: d.pr_map.trigger_value,
                block: [PR_MODE_ABSOLUTE, 0, 0, 60, 100, 100, 0],
                trigger: 0,
                servo_on: false,
                gen: None,
                rated_rpm: d.physics.max_speed_rpm,
                counts_per_rev: d.counts_per_rev as f64,
                last_step: None,
            });
            // The watchdog is off until the master sets its timeout.
            units.push(Unit {
                node: d.node,
                fields,
                order,
                comm_timeout_ms: 0,
                last_write: 0,
                relatch_at: None,
                pr,
                quirks: d.modbus_quirks.clone(),
                requests: 0,
                was_enabled: false,
            });
        }
        let mut core = Core::new(cfg);
        core.schedule(faults);
        let mut w = World { core, units };
        for i in 0..w.units.len() {
            let node = w.units[i].node;
            let is_pr = w.units[i].pr.is_some();
            let power_up = w.units[i].quirks.power_up_counts;
            if let Some(d) = w.core.drive_mut(node) {
                if power_up != 0 {
                    d.set_position(power_up as f64);
                }
                // 0x60C2 in ms: the interpolation period register is the index (:1) with
                // the exponent (:2) fixed at 10⁻³ s.
                let mut r = d.modbus_write(ix::INTERPOLATION_PERIOD, 2, -3, 0);
                if is_pr {
                    // The PR generator feeds the CSP interpolator every millisecond.
                    r = r
                        .and_then(|_| d.modbus_write(ix::INTERPOLATION_PERIOD, 1, (PR_PERIOD / MS) as i64, 0))
                        .and_then(|_| d.modbus_write(ix::MODES_OF_OPERATION, 0, mode::CYCLIC_SYNC_POSITION as i64, 0));
                } else {
                    // The drive's own homing method until the master writes one (a map
                    // without `homing_method` keeps it): 35, the present position is home.
                    r = r.and_then(|_| d.modbus_write(ix::HOMING_METHOD, 0, 35, 0));
                }
                r.map_err(|c| format!("drive node {node}: setting up its Modbus profile failed (SDO abort 0x{c:08X})"))?;
            }
        }
        Ok(w)
    }

    pub fn nodes(&self) -> Vec<u8> {
        self.units.iter().map(|u| u.node).collect()
    }

    pub fn drive(&self, node: u8) -> Option<&SimDrive> {
        self.core.drive(node)
    }

    /// Integrate to `t` (ns), firing the watchdogs at their deadlines and the PR profile
    /// generators on their 1 ms grid.
    pub fn advance(&mut self, t: u64) {
        let any_pr = self.units.iter().any(|u| u.pr.is_some());
        loop {
            self.events();
            let now = self.core.now;
            if now >= t {
                return;
            }
            let mut next = t;
            if any_pr {
                next = next.min((now / PR_PERIOD + 1) * PR_PERIOD);
            }
            for u in &self.units {
                for dl in [self.watchdog_deadline(u), u.relatch_at].into_iter().flatten() {
                    if dl > now {
                        next = next.min(dl);
                    }
                }
            }
            // Nothing listens to CAN frames here (boot-up, EMCY): drop them.
            self.core.advance_to(next, |out, _| out.clear());
        }
    }

    fn watchdog_deadline(&self, u: &Unit) -> Option<u64> {
        let d = self.core.drive(u.node)?;
        (u.comm_timeout_ms > 0 && d.state() == State::OperationEnabled).then(|| u.last_write + u.comm_timeout_ms as u64 * MS)
    }

    fn events(&mut self) {
        let now = self.core.now;
        for i in 0..self.units.len() {
            if self.watchdog_deadline(&self.units[i]).is_some_and(|dl| dl <= now) {
                let u = &self.units[i];
                tracing::warn!(node = u.node, "Modbus comm timeout: no write for {} ms while enabled", u.comm_timeout_ms);
                if let Some(d) = self.core.drive_mut(u.node) {
                    d.inject_fault(COMM_TIMEOUT_CODE, now);
                }
                self.pr_sync(i, now);
            }
            if self.units[i].relatch_at.is_some_and(|t| t <= now) {
                let node = self.units[i].node;
                self.units[i].relatch_at = self.core.drive_mut(node).and_then(|d| d.modbus_latch(now));
            }
            if self.enable_edge(i) && self.units[i].quirks.latch_any_time {
                self.latch_held_target(i, now);
            }
            if now % PR_PERIOD == 0 {
                self.pr_step(i, now);
            }
        }
        self.core.collect();
        self.core.out.clear();
    }

    /// Whether unit `i`'s drive has just entered Operation Enabled (since the last look).
    fn enable_edge(&mut self, i: usize) -> bool {
        let node = self.units[i].node;
        let en = self.core.drive(node).is_some_and(|d| d.state() == State::OperationEnabled);
        let edge = en && !self.units[i].was_enabled;
        self.units[i].was_enabled = en;
        edge
    }

    /// `latch_any_time`: on enabling, the drive takes 0x607A as it stands, however old.
    fn latch_held_target(&mut self, i: usize, now: u64) {
        if self.units[i].pr.is_some() {
            return;
        }
        let node = self.units[i].node;
        if let Some(d) = self.core.drive_mut(node) {
            tracing::debug!(node, target = d.object(ix::TARGET_POSITION, 0).unwrap_or(0), "enabled: latching the target register as it stands");
            self.units[i].relatch_at = d.modbus_latch(now);
        }
    }

    /// How late unit `ui`'s answer to the request just counted leaves, and the exception
    /// it gets instead of being executed, if any (the quirks).
    fn quirk_of_request(&mut self, ui: usize) -> (std::time::Duration, Option<ExceptionCode>) {
        let u = &mut self.units[ui];
        u.requests += 1;
        let q = &u.quirks;
        let n = u.requests;
        let busy = if q.refuse_after > 0 && n > q.refuse_after as u64 {
            Some(ExceptionCode::ServerDeviceFailure)
        } else if q.busy_every > 0 && n % q.busy_every as u64 == 0 {
            Some(ExceptionCode::ServerDeviceBusy)
        } else {
            None
        };
        let mut late_ms = 0;
        if n <= q.slow_first as u64 {
            late_ms = q.slow_first_ms;
        }
        if (q.late_every > 0 && n % q.late_every as u64 == 0) || (q.late_after > 0 && n > q.late_after as u64) {
            late_ms = late_ms.max(q.late_ms);
        }
        (std::time::Duration::from_millis(late_ms as u64), busy)
    }

    /// The PR drive's servo-on level walks the 402 machine, as a servo-on input does: an
    /// alarm stops the profile; after the alarm reset a servo-on still 1 enables again.
    fn pr_sync(&mut self, i: usize, now: u64) {
        let u = &mut self.units[i];
        let (Some(pr), Some(d)) = (u.pr.as_mut(), self.core.drives.iter_mut().find(|d| d.node() == u.node)) else {
            return;
        };
        let st = d.state();
        if matches!(st, State::Fault | State::FaultReactionActive) {
            pr.gen = None;
            return;
        }
        // The internal controlwords go through the drive's rules; they cannot be refused.
        let mut cw_write = |c: u16| {
            if let Err(code) = d.modbus_write(ix::CONTROLWORD, 0, c as i64, now) {
                tracing::error!(node = d.node(), "internal controlword 0x{c:04X} refused: 0x{code:08X}");
            }
        };
        if pr.servo_on {
            match st {
                State::SwitchOnDisabled => {
                    cw_write(cw::SHUTDOWN);
                    cw_write(cw::ENABLE_OPERATION_CMD);
                }
                State::ReadyToSwitchOn | State::SwitchedOn => cw_write(cw::ENABLE_OPERATION_CMD),
                State::QuickStopActive => cw_write(cw::DISABLE_VOLTAGE),
                _ => {}
            }
        } else if !matches!(st, State::SwitchOnDisabled | State::NotReadyToSwitchOn) {
            cw_write(cw::DISABLE_VOLTAGE);
        }
        if d.state() == State::OperationEnabled && d.mode_display() == mode::CYCLIC_SYNC_POSITION {
            if pr.gen.is_none() {
                pr.gen = Some(Gen::hold(d.position_actual() as f64));
            }
        } else {
            pr.gen = None;
        }
    }

    /// One period of the PR profile generator: the next profile point goes to the CSP
    /// interpolator, which reaches it one period later.
    fn pr_step(&mut self, i: usize, now: u64) {
        if self.units[i].pr.as_ref().is_none_or(|p| p.last_step == Some(now)) {
            return;
        }
        self.pr_sync(i, now);
        let u = &mut self.units[i];
        let Some(pr) = u.pr.as_mut() else { return };
        pr.last_step = Some(now);
        let Some(g) = pr.gen.as_mut() else { return };
        g.step(PR_PERIOD as f64 * 1e-9, now + PR_PERIOD);
        let target = g.p.round().clamp(i32::MIN as f64, i32::MAX as f64) as i64;
        if let Some(d) = self.core.drives.iter_mut().find(|d| d.node() == u.node) {
            // Latched every period: never late, nothing to re-latch.
            if d.modbus_write(ix::TARGET_POSITION, 0, target, now).is_ok() {
                let _ = d.modbus_latch(now);
            }
        }
    }

    /// Answer one request addressed to `unit`, and how long after now the answer leaves (the
    /// quirks). `None`: no answer (an unknown unit on RTU — nobody on the line has that
    /// address).
    pub fn request(&mut self, unit: u8, req: &Request<'_>, rtu: bool) -> (Result<Option<Response>, ExceptionCode>, std::time::Duration) {
        let Some(ui) = self.units.iter().position(|u| u.node == unit) else {
            // A TCP server for several units is a gateway: the target did not answer.
            let r = if rtu { Ok(None) } else { Err(ExceptionCode::GatewayTargetDevice) };
            return (r, std::time::Duration::ZERO);
        };
        let (delay, refused) = self.quirk_of_request(ui);
        if let Some(e) = refused {
            tracing::debug!(unit, "{req:?} → {e} (quirk)");
            return (Err(e), delay);
        }
        (self.execute(ui, req), delay)
    }

    fn execute(&mut self, ui: usize, req: &Request<'_>) -> Result<Option<Response>, ExceptionCode> {
        let unit = self.units[ui].node;
        let now = self.core.now;
        tracing::trace!(unit, t_ms = now as f64 * 1e-6, "{req:?}");
        let r = match req {
            Request::ReadHoldingRegisters(a, n) => self.read(ui, *a, *n, MAX_READ).map(Response::ReadHoldingRegisters),
            Request::ReadInputRegisters(a, n) => self.read(ui, *a, *n, MAX_READ).map(Response::ReadInputRegisters),
            Request::WriteSingleRegister(a, v) => self.write(ui, *a, &[*v], MAX_WRITE, now).map(|()| Response::WriteSingleRegister(*a, *v)),
            Request::WriteMultipleRegisters(a, ws) => {
                self.write(ui, *a, ws, MAX_WRITE, now).map(|()| Response::WriteMultipleRegisters(*a, ws.len() as u16))
            }
            Request::ReadWriteMultipleRegisters(ra, rn, wa, ws) => {
                // Both parts are checked before the write; the write happens before the read.
                self.check_read(ui, *ra, *rn, MAX_READ)
                    .and_then(|()| self.write(ui, *wa, ws, MAX_RW_WRITE, now))
                    .and_then(|()| self.read(ui, *ra, *rn, MAX_READ))
                    .map(Response::ReadWriteMultipleRegisters)
            }
            _ => Err(ExceptionCode::IllegalFunction),
        };
        self.core.collect();
        self.core.out.clear();
        if let Err(e) = &r {
            tracing::debug!(unit, "{req:?} → exception {e:?}");
        }
        r.map(Some)
    }

    /// Quantity, then addresses (the order of the Modbus spec's request checks).
    fn check_read(&self, ui: usize, addr: u16, n: u16, max: u16) -> Result<(), ExceptionCode> {
        if n == 0 || n > max {
            return Err(ExceptionCode::IllegalDataValue);
        }
        let u = &self.units[ui];
        if addr as u32 + n as u32 > 0x1_0000 {
            return Err(ExceptionCode::IllegalDataAddress);
        }
        if (addr..=addr + (n - 1)).all(|a| u.field_at(a).is_some()) {
            Ok(())
        } else {
            Err(ExceptionCode::IllegalDataAddress)
        }
    }

    fn read(&self, ui: usize, addr: u16, n: u16, max: u16) -> Result<Vec<u16>, ExceptionCode> {
        self.check_read(ui, addr, n, max)?;
        let u = &self.units[ui];
        let mut out = Vec::with_capacity(n as usize);
        let mut a = addr as u32;
        let end = addr as u32 + n as u32;
        while a < end {
            let f = u.field_at(a as u16).ok_or(ExceptionCode::IllegalDataAddress)?;
            let words = self.field_words(u, f.reg);
            let from = (a - f.addr as u32) as usize;
            let to = ((f.addr as u32 + f.len as u32).min(end) - f.addr as u32) as usize;
            out.extend_from_slice(words.get(from..to).ok_or(ExceptionCode::ServerDeviceFailure)?);
            a = f.addr as u32 + to as u32;
        }
        Ok(out)
    }

    /// The present value of a field, as registers.
    fn field_words(&self, u: &Unit, reg: Reg) -> Vec<u16> {
        let Some(d) = self.core.drive(u.node) else { return Vec::new() };
        let obj = |i: u16, s: u8| d.object(i, s).unwrap_or(0);
        let two = |v: i64| u.order.split_i32(v as i32).to_vec();
        let now = self.core.now;
        match reg {
            Reg::Controlword => vec![obj(ix::CONTROLWORD, 0) as u16],
            Reg::TargetPosition => two(obj(ix::TARGET_POSITION, 0)),
            Reg::TargetVelocity => two(obj(ix::TARGET_VELOCITY, 0)),
            Reg::Mode => vec![obj(ix::MODES_OF_OPERATION, 0) as i16 as u16],
            Reg::Statusword => vec![d.statusword()],
            Reg::ModeDisplay => vec![d.mode_display() as i16 as u16],
            Reg::PositionActual => two(d.position_actual() as i64),
            Reg::VelocityActual => two(d.velocity_actual() as i64),
            Reg::ErrorCode | Reg::AlarmCode => vec![d.error_code()],
            Reg::InterpolationMs => vec![obj(ix::INTERPOLATION_PERIOD, 1) as u16],
            Reg::FerrWindow => two(obj(ix::FOLLOWING_ERROR_WINDOW, 0)),
            Reg::CommTimeout => vec![u.comm_timeout_ms],
            Reg::HomingMethod => vec![obj(ix::HOMING_METHOD, 0) as i16 as u16],
            Reg::HomeOffset => two(obj(HOME_OFFSET, 0)),
            Reg::HomingSwitchSpeed => two(obj(ix::HOMING_SPEEDS, 1)),
            Reg::HomingZeroSpeed => two(obj(ix::HOMING_SPEEDS, 2)),
            Reg::HomingAccel => two(obj(ix::HOMING_ACCEL, 0)),
            // The emulated limit switches (`DriveConfig::switches`), as on CANopen.
            // (Computed now: the object dictionary's copy is refreshed only for CANopen.)
            Reg::DigitalInputs => two(d.digital_inputs()),
            Reg::Block => u.pr.as_ref().map(|p| p.block.to_vec()).unwrap_or_default(),
            Reg::Trigger => vec![u.pr.as_ref().map_or(0, |p| p.trigger)],
            Reg::ServoOn => vec![u.pr.as_ref().map_or(0, |p| p.servo_on as u16)],
            Reg::AlarmReset => vec![0],
            Reg::Status => {
                let st = d.state();
                let mut s = 0;
                if matches!(st, State::Fault | State::FaultReactionActive) {
                    s |= pr_status::FAULT;
                }
                if st == State::OperationEnabled {
                    s |= pr_status::ENABLED;
                    if let Some(g) = u.pr.as_ref().and_then(|p| p.gen.as_ref()) {
                        if g.running(now) {
                            s |= pr_status::RUNNING;
                        } else {
                            let window = obj(POSITION_WINDOW, 0) as f64;
                            if (d.position_actual() as f64 - g.target).abs() <= window {
                                s |= pr_status::IN_POSITION;
                            }
                        }
                    }
                }
                vec![s]
            }
        }
    }

    /// A write of `words` from `addr`: every register must be a writable register of the
    /// map (else 0x02) and every value valid (else 0x03) before anything takes effect.
    fn write(&mut self, ui: usize, addr: u16, words: &[u16], max: u16, now: u64) -> Result<(), ExceptionCode> {
        let n = words.len();
        if n == 0 || n > max as usize {
            return Err(ExceptionCode::IllegalDataValue);
        }
        if addr as usize + n > 0x1_0000 {
            return Err(ExceptionCode::IllegalDataAddress);
        }
        // The touched fields with their new words (a partly written 32-bit value keeps its
        // other half).
        let mut touched: Vec<(Field, Vec<u16>)> = Vec::new();
        {
            let u = &self.units[ui];
            for (k, &w) in words.iter().enumerate() {
                let a = addr + k as u16;
                let f = u.field_at(a).filter(|f| f.reg.writable()).ok_or(ExceptionCode::IllegalDataAddress)?;
                let i = match touched.iter().position(|t| t.0.addr == f.addr) {
                    Some(i) => i,
                    None => {
                        touched.push((f, self.field_words(u, f.reg)));
                        touched.len() - 1
                    }
                };
                if let Some(slot) = touched[i].1.get_mut((a - f.addr) as usize) {
                    *slot = w;
                }
            }
            for (f, v) in &touched {
                self.check_value(u, f.reg, v)?;
            }
        }
        touched.sort_by_key(|t| t.0.reg.apply_rank());
        self.units[ui].last_write = now;
        let mut latch = false;
        for (f, v) in &touched {
            latch |= matches!(f.reg, Reg::TargetPosition | Reg::TargetVelocity);
            self.apply(ui, f.reg, v, now)?;
        }
        // A controlword that enabled the drive: a drive that latches at any time takes the
        // target register as it stands (after this request's own target, if any).
        let edge = self.enable_edge(ui);
        latch |= edge && self.units[ui].quirks.latch_any_time && self.units[ui].pr.is_none();
        if latch {
            let node = self.units[ui].node;
            if let Some(d) = self.core.drive_mut(node) {
                self.units[ui].relatch_at = d.modbus_latch(now);
            }
        }
        Ok(())
    }

    fn check_value(&self, u: &Unit, reg: Reg, v: &[u16]) -> Result<(), ExceptionCode> {
        let first = v.first().copied().unwrap_or(0);
        let ok = match reg {
            Reg::Mode => {
                [mode::PROFILE_POSITION, mode::HOMING, mode::CYCLIC_SYNC_POSITION, mode::CYCLIC_SYNC_VELOCITY].iter().any(|&m| m as u16 == first)
            }
            // 0x60C2:1 is one byte of ms.
            Reg::InterpolationMs => first <= u8::MAX as u16,
            Reg::ServoOn | Reg::AlarmReset => first <= 1,
            Reg::Trigger => first == 0 || u.pr.as_ref().is_some_and(|p| p.trigger_value == first),
            Reg::Block => {
                let rated = u.pr.as_ref().map_or(0.0, |p| p.rated_rpm);
                v.len() == PR_BLOCK_LEN as usize && v[0] == PR_MODE_ABSOLUTE && v[3] >= 1 && v[3] as f64 <= rated
            }
            _ => true,
        };
        if ok {
            Ok(())
        } else {
            Err(ExceptionCode::IllegalDataValue)
        }
    }

    fn apply(&mut self, ui: usize, reg: Reg, v: &[u16], now: u64) -> Result<(), ExceptionCode> {
        let u = &self.units[ui];
        let node = u.node;
        let val32 = || match v {
            [a, b] => u.order.join_i32([*a, *b]) as i64,
            _ => 0,
        };
        let first = v.first().copied().unwrap_or(0);
        let obj_write = match reg {
            Reg::Controlword => Some((ix::CONTROLWORD, 0, first as i64)),
            Reg::Mode => Some((ix::MODES_OF_OPERATION, 0, first as i16 as i64)),
            Reg::InterpolationMs => {
                // A drive with a coarser grid rounds the period up to it (a quirk).
                let grid = u.quirks.interpolation_grid_ms.max(1);
                Some((ix::INTERPOLATION_PERIOD, 1, first.div_ceil(grid).saturating_mul(grid) as i64))
            }
            Reg::FerrWindow => Some((ix::FOLLOWING_ERROR_WINDOW, 0, val32() as u32 as i64)),
            Reg::TargetPosition => Some((ix::TARGET_POSITION, 0, val32())),
            Reg::TargetVelocity => Some((ix::TARGET_VELOCITY, 0, val32())),
            // INTEGER8 in a register: a value outside -128…127 is refused (0x03), not cut.
            Reg::HomingMethod => {
                let m = first as i16;
                if i8::try_from(m).is_err() {
                    return Err(ExceptionCode::IllegalDataValue);
                }
                Some((ix::HOMING_METHOD, 0, m as i64))
            }
            Reg::HomeOffset => Some((HOME_OFFSET, 0, val32())),
            Reg::HomingSwitchSpeed => Some((ix::HOMING_SPEEDS, 1, val32() as u32 as i64)),
            Reg::HomingZeroSpeed => Some((ix::HOMING_SPEEDS, 2, val32() as u32 as i64)),
            Reg::HomingAccel => Some((ix::HOMING_ACCEL, 0, val32() as u32 as i64)),
            _ => None,
        };
        if let Some((index, sub, x)) = obj_write {
            let d = self.core.drive_mut(node).ok_or(ExceptionCode::ServerDeviceFailure)?;
            return d.modbus_write(index, sub, x, now).map_err(abort_to_exception);
        }
        match reg {
            Reg::CommTimeout => self.units[ui].comm_timeout_ms = first,
            Reg::Block => {
                if let Some(pr) = self.units[ui].pr.as_mut() {
                    for (s, w) in pr.block.iter_mut().zip(v) {
                        *s = *w;
                    }
                }
            }
            Reg::ServoOn => {
                if let Some(pr) = self.units[ui].pr.as_mut() {
                    pr.servo_on = first == 1;
                }
                self.pr_sync(ui, now);
            }
            Reg::AlarmReset if first == 1 => {
                let d = self.core.drive_mut(node).ok_or(ExceptionCode::ServerDeviceFailure)?;
                if d.state() == State::Fault {
                    // A rising edge of the fault-reset bit, as the 402 machine wants it.
                    d.modbus_write(ix::CONTROLWORD, 0, 0, now).map_err(abort_to_exception)?;
                    d.modbus_write(ix::CONTROLWORD, 0, cw::FAULT_RESET_CMD as i64, now).map_err(abort_to_exception)?;
                }
                self.pr_sync(ui, now);
            }
            Reg::Trigger => {
                let u = &mut self.units[ui];
                let order = u.order;
                if let Some(pr) = u.pr.as_mut() {
                    pr.trigger = first;
                    if first == pr.trigger_value {
                        let b = pr.block;
                        let rated = pr.rated_rpm / 60.0 * pr.counts_per_rev;
                        let vmax = b[3] as f64 / 60.0 * pr.counts_per_rev;
                        // Acceleration and deceleration are times from 0 to rated speed.
                        let acc = rated / (b[4].max(1) as f64 * 1e-3);
                        let dec = rated / (b[5].max(1) as f64 * 1e-3);
                        let target = order.join_i32([b[1], b[2]]) as f64;
                        match pr.gen.as_mut() {
                            Some(g) => g.start(target, vmax, acc, dec, b[6] as u64 * MS),
                            // Servo off or in alarm: a real drive ignores the trigger too.
                            None => tracing::debug!(node = u.node, "PR trigger while not enabled: ignored"),
                        }
                    }
                }
            }
            _ => {}
        }
        Ok(())
    }
}
