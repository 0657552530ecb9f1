//! Profile position (mode 1) and homing (mode 6): the drive's own trajectory generator.
//!
//! Profile position: a rising edge of controlword bit 4 (new set-point) takes 0x607A
//! (absolute, or relative to the last target with bit 6) and moves there on a trapezoid of
//! 0x6081 / 0x6083 / 0x6084. Bit 5 (change set immediately) replaces a move under way; without
//! it one set-point is buffered and started when the present move ends. Statusword bit 12
//! acknowledges the set-point (and stays set while the buffer is full), bit 10 says the
//! target is reached (within 0x6067). Halt (bit 8) stops on 0x6084 and cancels the move.
//!
//! Homing: a rising edge of bit 4 starts method 0x6098; a falling edge interrupts it.
//! 35 and 37: the present position becomes the home offset 0x607C. 17 / 18: search the
//! negative / positive limit switch at 0x6099:1, leave it at 0x6099:2, and the point where
//! it releases becomes 0x607C; ramps on 0x609A. Bits 13/12/10 = error / attained / reached
//! as CiA 402 tabulates them. The limit switches are emulated at the positions of 0x2101
//! (physical counts, i.e. before any homing shift) and show in 0x60FD bits 0/1.
//!
//! Approximately the other CiA 402 methods: 19–30 the home switch (0x2101:3, active at and
//! above that position: its edge is home, reached from below whichever side the axis
//! starts), 1–14 the same switches followed by the next index pulse (one every 0x2101:4
//! counts of physical position, the encoder's once-per-revolution mark) in the direction
//! the switch was left, 33 / 34 the next index pulse moving negative / positive. The
//! coordinate a homing sets is lost with an NMT reset node (the application restarts; an
//! incremental encoder counts afresh from where it stands).

use super::SimDrive;
use crate::servo::Command;
use cncgw_bus::canopen::od as ix;
use cncgw_bus::cia402::{cw, mode, sw};

pub(super) const HOME_OFFSET: u16 = 0x607C;
pub(super) const PROFILE_VELOCITY: u16 = 0x6081;
pub(super) const PROFILE_ACCEL: u16 = 0x6083;
pub(super) const DIGITAL_INPUTS: u16 = 0x60FD;
/// Manufacturer record: emulated limit switches (hardware: they survive an NMT reset).
/// Sub 1: negative limit switch, active at or below this position; sub 2: positive, at or
/// above; sub 3: home switch, active at or above. Physical counts (the power-on
/// coordinate); i32::MIN / i32::MAX = not fitted. Sub 4: index pulse period, counts.
pub const SIM_SWITCHES: u16 = 0x2101;
/// Homing methods this drive implements.
pub fn homing_method_supported(m: i64) -> bool {
    matches!(m, 0..=14 | 17..=30 | 33..=35 | 37)
}

#[derive(Clone, Copy, Debug)]
enum Goal {
    Position(f64),
    Velocity(f64),
}

#[derive(Clone, Copy, Debug)]
struct Traj {
    pos: f64,
    v: f64,
    goal: Goal,
}

impl Traj {
    /// One step of `dt` s; true when a position goal is reached.
    fn step(&mut self, vmax: f64, acc: f64, dec: f64, dt: f64) -> bool {
        match self.goal {
            Goal::Position(t) => {
                let dist = t - self.pos;
                // The fastest speed from which `dec` still stops at the target.
                let vdes = dist.signum() * vmax.min((2.0 * dec * dist.abs()).sqrt());
                let speeding_up = vdes.abs() > self.v.abs() && vdes * self.v >= 0.0;
                self.v = approach(self.v, vdes, if speeding_up { acc } else { dec } * dt);
                let next = self.pos + self.v * dt;
                let crossed = (t - next) * dist <= 0.0;
                if crossed && self.v.abs() <= 4.0 * dec * dt + 1.0 {
                    self.pos = t;
                    self.v = 0.0;
                    return true;
                }
                self.pos = next;
                false
            }
            Goal::Velocity(vt) => {
                self.v = approach(self.v, vt, acc * dt);
                self.pos += self.v * dt;
                false
            }
        }
    }
}

fn approach(v: f64, to: f64, dv: f64) -> f64 {
    if (to - v).abs() <= dv {
        to
    } else {
        v + dv * (to - v).signum()
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    SearchSwitch,
    LeaveSwitch,
    /// Moving on (at 0x6099:2, in this direction) to the next index pulse, last seen in
    /// period `k`.
    SeekIndex {
        dir: f64,
        k: i64,
    },
    /// Home found; ramping down.
    Stopping,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Switch {
    Neg,
    Pos,
    Home,
}

#[derive(Clone, Copy, Debug)]
struct Homing {
    switch: Option<Switch>,
    /// The direction searching the switch (the switch is left the other way).
    dir: f64,
    /// Whether an index pulse follows the switch.
    index: bool,
    phase: Phase,
}

#[derive(Clone, Debug, Default)]
pub(super) struct Prof {
    traj: Option<Traj>,
    /// Buffered set-point (unwrapped counts).
    pending: Option<f64>,
    ack: bool,
    /// Last accepted absolute target, for relative moves.
    last_target: Option<f64>,
    homing: Option<Homing>,
    /// Result of the last homing: Some(true) attained, Some(false) error.
    homed: Option<bool>,
    /// Coordinate shift of all homings: physical position = servo position − shift.
    shift: f64,
}

impl Prof {
    /// A new mode of operation: nothing carries over but the homing shift.
    pub(super) fn mode_changed(&mut self) {
        *self = Prof { shift: self.shift, ..Default::default() };
    }

    /// Hold: cancel a move or homing under way (the homing result stays).
    pub(super) fn cancel(&mut self) {
        self.traj = None;
        self.pending = None;
        if self.homing.take().is_some() {
            self.homed = None;
        }
    }
}

impl SimDrive {
    fn physical(&self) -> f64 {
        self.servo.position_counts() as f64 - self.prof.shift
    }

    fn switch_on(&self, w: Switch) -> bool {
        let (n, p) = self.switches();
        match w {
            Switch::Neg => n,
            Switch::Pos => p,
            Switch::Home => {
                let h = self.od.int(SIM_SWITCHES, 3);
                h != i32::MAX as i64 && self.physical() >= h as f64
            }
        }
    }

    fn index_period(&self) -> f64 {
        (self.od.int(SIM_SWITCHES, 4) as f64).max(1.0)
    }

    /// The NMT reset node restarted the application: the coordinate of the last homing is
    /// gone (the position is the physical count again) and so is its result.
    pub(super) fn forget_homing(&mut self) {
        let delta = -self.prof.shift;
        self.shift_coords(delta);
        self.prof = Prof::default();
    }

    /// (negative, positive) limit switch active.
    fn switches(&self) -> (bool, bool) {
        let p = self.physical();
        let neg = self.od.int(SIM_SWITCHES, 1);
        let pos = self.od.int(SIM_SWITCHES, 2);
        (neg != i32::MIN as i64 && p <= neg as f64, pos != i32::MAX as i64 && p >= pos as f64)
    }

    /// 0x60FD: bit 0 negative limit switch, bit 1 positive limit switch.
    pub fn digital_inputs(&self) -> i64 {
        let (n, p) = self.switches();
        n as i64 | (p as i64) << 1
    }

    /// A controlword arrived (after the state machine took it): set-point and homing
    /// handshakes on bit 4.
    pub(super) fn profile_controlword(&mut self, prev: u16, c: u16) {
        if self.state != cncgw_bus::cia402::State::OperationEnabled {
            return;
        }
        let rising = c & cw::OMS4 != 0 && prev & cw::OMS4 == 0;
        match self.mode_display() {
            mode::PROFILE_POSITION => {
                if rising {
                    self.new_setpoint(c);
                } else if c & cw::OMS4 == 0 {
                    self.prof.ack = self.prof.pending.is_some();
                }
            }
            mode::HOMING => {
                if rising {
                    self.start_homing();
                } else if c & cw::OMS4 == 0 && self.prof.homing.is_some() {
                    // Interrupted: ramp down, no result.
                    self.prof.homing = None;
                    self.prof.homed = None;
                    if let Some(t) = self.prof.traj.as_mut() {
                        t.goal = Goal::Velocity(0.0);
                    }
                }
            }
            _ => {}
        }
    }

    fn new_setpoint(&mut self, c: u16) {
        let raw = self.od.int(ix::TARGET_POSITION, 0) as i32;
        let mut t = if c & cw::OMS6 != 0 {
            self.prof.last_target.unwrap_or(self.demand) + self.user_to_inc(raw as f64)
        } else {
            let a = self.servo.position_counts();
            let au = self.inc_to_user(a as f64).round() as i64 as i32;
            a as f64 + self.user_to_inc(raw.wrapping_sub(au) as f64)
        };
        if let Some((lo, hi)) = self.software_limits_inc() {
            t = t.clamp(lo, hi);
        }
        let immediate = c & cw::OMS5 != 0;
        match self.prof.traj.as_mut() {
            Some(tr) if immediate => tr.goal = Goal::Position(t),
            Some(_) if self.prof.pending.is_none() => self.prof.pending = Some(t),
            Some(_) => return, // buffer full: not acknowledged
            None => self.prof.traj = Some(Traj { pos: self.demand, v: 0.0, goal: Goal::Position(t) }),
        }
        self.prof.last_target = Some(t);
        self.prof.ack = true;
    }

    fn start_homing(&mut self) {
        let method = self.od.int(ix::HOMING_METHOD, 0) as i8;
        self.prof.traj = None;
        self.prof.homed = None;
        let (switch, dir, index) = match method {
            35 | 37 => return self.set_home(),
            1 | 17 => (Some(Switch::Neg), -1.0, method == 1),
            2 | 18 => (Some(Switch::Pos), 1.0, method == 2),
            3..=14 | 19..=30 => (Some(Switch::Home), 1.0, method <= 14),
            33 | 34 => (None, if method == 33 { -1.0 } else { 1.0 }, true),
            _ => {
                tracing::warn!(node = self.cfg.node, "homing method {method} not supported");
                self.prof.homed = Some(false);
                return;
            }
        };
        let sub = match switch {
            Some(Switch::Neg) => 1,
            Some(Switch::Pos) => 2,
            Some(Switch::Home) => 3,
            None => 0,
        };
        let unfitted = if sub == 1 { i32::MIN as i64 } else { i32::MAX as i64 };
        if sub != 0 && self.od.int(SIM_SWITCHES, sub) == unfitted {
            // A real axis would run into its hard stop; this one reports it.
            tracing::warn!(node = self.cfg.node, "homing method {method}: no switch fitted (0x2101:{sub})");
            self.prof.homed = Some(false);
            return;
        }
        let phase = match switch {
            None => Phase::SeekIndex { dir, k: (self.physical() / self.index_period()).floor() as i64 },
            Some(w) if w == Switch::Home && self.switch_on(w) => Phase::LeaveSwitch,
            Some(_) => Phase::SearchSwitch,
        };
        self.prof.homing = Some(Homing { switch, dir, index, phase });
        self.prof.traj = Some(Traj { pos: self.demand, v: 0.0, goal: Goal::Velocity(0.0) });
    }

    /// The present position becomes the home offset 0x607C.
    fn set_home(&mut self) {
        let offset = self.od.int(HOME_OFFSET, 0) as f64;
        let here = self.servo.position_counts() as f64;
        self.shift_coords(offset - here);
        self.prof.homed = Some(true);
        tracing::info!(node = self.cfg.node, "homed: position set to {offset} counts");
    }

    /// Move the coordinate system by `delta` counts (the axis stays where it is).
    fn shift_coords(&mut self, delta: f64) {
        self.servo.set_position(self.servo.position_counts() as f64 + delta);
        self.prof.shift += delta;
        self.demand += delta;
        self.seg_start += delta;
        self.seg_end += delta;
        if let Some(t) = self.prof.traj.as_mut() {
            t.pos += delta;
        }
        self.target_ref = None;
        self.prof.last_target = None;
    }

    /// One control tick in mode 1 or 6 (enabled, no stop under way).
    pub(super) fn profile_tick(&mut self, dt: f64) -> Command {
        let homing = self.mode_display() == mode::HOMING;
        let (vmax, acc, dec) = if homing {
            let a = self.od.int(ix::HOMING_ACCEL, 0) as f64;
            (f64::INFINITY, a, a)
        } else {
            (self.od.int(PROFILE_VELOCITY, 0) as f64, self.od.int(PROFILE_ACCEL, 0) as f64, self.od.int(super::PROFILE_DECEL, 0) as f64)
        };
        if let Some(h) = self.prof.homing {
            let on = h.switch.is_some_and(|w| self.switch_on(w));
            let dir = h.dir;
            let fast = self.od.int(ix::HOMING_SPEEDS, 1) as f64;
            let slow = self.od.int(ix::HOMING_SPEEDS, 2) as f64;
            let period = self.index_period();
            let k_now = (self.physical() / period).floor() as i64;
            let phase = match h.phase {
                Phase::SearchSwitch if on => Phase::LeaveSwitch,
                Phase::LeaveSwitch if !on && h.index => Phase::SeekIndex { dir: -dir, k: k_now },
                Phase::LeaveSwitch if !on => {
                    self.set_home();
                    Phase::Stopping
                }
                Phase::SeekIndex { k, .. } if k != k_now => {
                    self.set_home();
                    Phase::Stopping
                }
                p => p,
            };
            let goal = match phase {
                Phase::SearchSwitch => Goal::Velocity(dir * fast),
                Phase::LeaveSwitch => Goal::Velocity(-dir * slow),
                Phase::SeekIndex { dir, .. } => Goal::Velocity(dir * slow),
                Phase::Stopping => Goal::Velocity(0.0),
            };
            if let Some(t) = self.prof.traj.as_mut() {
                t.goal = goal;
            }
            self.prof.homing = Some(Homing { phase, ..h });
            if phase == Phase::Stopping && self.prof.traj.is_some_and(|t| t.v == 0.0) {
                self.prof.homing = None;
                self.prof.traj = None;
                self.prof.homed = Some(true);
            }
        }
        if let Some(t) = self.prof.traj.as_mut() {
            let done = t.step(vmax, acc.max(1.0), dec.max(1.0), dt);
            self.demand = t.pos;
            self.vff = t.v;
            let stopped = matches!(t.goal, Goal::Velocity(v) if v == 0.0) && t.v == 0.0 && self.prof.homing.is_none();
            if done || stopped {
                self.prof.traj = None;
                if let Some(p) = self.prof.pending.take() {
                    self.prof.traj = Some(Traj { pos: self.demand, v: 0.0, goal: Goal::Position(p) });
                    self.prof.ack = self.prev_cw & cw::OMS4 != 0;
                }
            }
        } else {
            self.vff = 0.0;
        }
        Command::Position { demand: self.demand, vff: self.vff }
    }

    /// Statusword bits 10, 12, 13 in modes 1 and 6 while enabled (halt and stops are the
    /// caller's).
    pub(super) fn profile_status(&self) -> u16 {
        let mut s = 0;
        if self.mode_display() == mode::HOMING {
            if self.prof.homing.is_none() {
                match self.prof.homed {
                    Some(true) => s |= sw::OMS12 | sw::TARGET_REACHED,
                    Some(false) if self.servo.at_rest() => s |= sw::OMS13 | sw::TARGET_REACHED,
                    Some(false) => s |= sw::OMS13,
                    None => s |= sw::TARGET_REACHED, // not started or interrupted
                }
            }
        } else {
            if self.prof.ack {
                s |= sw::OMS12;
            }
            let window = self.od.int(super::POSITION_WINDOW, 0) as f64 * self.hot.inc_per_unit;
            if self.prof.traj.is_none() && self.prof.pending.is_none() && (self.demand - self.servo.position_counts() as f64).abs() <= window {
                s |= sw::TARGET_REACHED;
            }
        }
        s
    }
}
