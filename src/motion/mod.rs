//! Planner, interpolator and cycle loop.
//!
//! [`Motion`] takes canonical moves ([`crate::canon::Move`], machine coordinates, X as a
//! radius) through [`Motion::push`] into a fixed-size queue, and every bus cycle
//! [`Motion::step`] returns the position setpoint of X, Y, Z and the spindle angle.
//!
//! How a cycle is computed:
//! - The path speed is decided online, once per cycle, by [`profile::next_speed`]: it moves
//!   towards the commanded speed by at most `a·dt`, and never above the speed from which the
//!   rest of the segment can still be braked to rest with the same step (a discrete
//!   trapezoid). Being online, a per-revolution feed follows the measured spindle speed, and
//!   overrides, feed hold and stop take effect in the next cycle.
//! - Each segment ends with an exact stop (milestone 1): the last moving cycle lands on the end
//!   point bit for bit, and the following cycle holds it at rest before the next item starts.
//! - Events (aux codes, M00/M01, M30) and spindle commands are taken in program order, one item
//!   per cycle, so `step` is O(1).
//!
//! Limits per segment: the path speed is at most `min_i vmax_i/|u_i|` and the path
//! acceleration `min_i amax_i/|u_i|` (u = unit direction), so no axis exceeds its own limit;
//! rapids run at exactly that speed, which is Fanuc's linear-interpolation rapid (every axis
//! as fast as the slowest axis' share allows). On an arc half of the smaller axis acceleration
//! goes to the tangential ramp and 45 % to the centripetal `v²/r`; the speed is further limited
//! so that the chord between two setpoints deviates from the circle by at most
//! `chord_tol`: sagitta `(v·dt)²/(8r) ≤ chord_tol` ⇒ `v ≤ √(8·r·chord_tol)/dt`.

pub mod cycle;
pub mod geom;
pub mod profile;
#[cfg(test)]
mod tests;

use crate::canon::{Feed, Move, MoveKind, Plane, Pos, SpindleCmd, SpindleDir};
use crate::config::{AxisKind, MachineConfig};
use crate::Alarm;
use geom::Geom;

pub const AX_X: usize = 0;
pub const AX_Y: usize = 1;
pub const AX_Z: usize = 2;
/// Spindle angle, degrees, continuous (not wrapped).
pub const AX_S: usize = 3;
pub const N_AXES: usize = 4;

const AXIS_NAMES: [char; N_AXES] = ['X', 'Y', 'Z', 'S'];

/// Alarm numbers raised by the motion layer (2300–2399: sync and motion; Fanuc numbers where
/// Fanuc has one).
pub mod alarms {
    /// PS0011: feed zero (a feed move without a positive F).
    pub const FEED_ZERO: u32 = 11;
    /// PS0020: arc radius out of tolerance (start and end radii differ).
    pub const ARC_RADIUS: u32 = 20;
    /// The look-ahead queue is full (caller must check `has_room`).
    pub const QUEUE_FULL: u32 = 2300;
    /// End point outside the software travel limits, or on an axis that is not configured.
    pub const TRAVEL: u32 = 2301;
    /// Feed per revolution (G99) while the spindle is stopped.
    pub const PER_REV_SPINDLE_STOPPED: u32 = 2302;
    /// A value that is not a finite number, a negative dwell or speed, a degenerate arc.
    pub const BAD_VALUE: u32 = 2303;
    /// A move kind this motion layer does not execute yet.
    pub const UNSUPPORTED: u32 = 2304;
    /// A move pushed while a controlled stop is in progress.
    pub const STOPPING: u32 = 2305;
}

/// Actual values from the drives (X radius).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Feedback {
    pub pos: [f64; N_AXES],
    pub spindle_rpm: f64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    None,
    Stop { optional: bool },
    End,
    Aux { letter: char, value: f64 },
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Setpoint {
    /// Commanded positions this cycle.
    pub pos: [f64; N_AXES],
    /// Commanded velocities (units/s) — feed-forward / CSV.
    pub vel: [f64; N_AXES],
    /// Commanded spindle speed (signed: + = M03).
    pub spindle_rpm: f64,
    /// Actual path speed, mm/min.
    pub path_feed: f64,
    /// Source line of the move being executed (0 before the first).
    pub line: u32,
    /// Reached this cycle (M00/M01 stops, M30 end, aux codes).
    pub event: Event,
}

/// Machine limits as the interpolator uses them (SI-ish: units/s, units/s²).
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Per-axis maximum speed, units/s (mm/s; spindle deg/s). 0 for an axis not configured.
    pub vmax: [f64; N_AXES],
    /// Per-axis maximum acceleration, units/s² (spindle deg/s²).
    pub amax: [f64; N_AXES],
    /// Software travel limits (min, max) of X (radius), Y, Z in mm.
    pub travel: [(f64, f64); 3],
    /// Whether each axis is configured.
    pub present: [bool; N_AXES],
    /// Cycle (interpolation) period, s.
    pub cycle_s: f64,
    /// Cutting feed clamp (No.6023), mm/s; infinity when not set.
    pub feed_clamp: f64,
    /// Largest allowed sagitta between two setpoints on an arc, mm.
    pub chord_tol: f64,
    /// Largest allowed difference between an arc's start and end radius, mm.
    pub arc_radius_tol: f64,
    /// Look-ahead queue capacity (moves).
    pub queue_len: usize,
}

impl Limits {
    /// Limits of the configured machine: axes named `x`, `y`, `z` (linear) and the first
    /// spindle. mm/min → mm/s, rpm → deg/s (×6), rpm/s → deg/s² (×6).
    pub fn from_config(cfg: &MachineConfig) -> Limits {
        let mut l = Limits {
            vmax: [0.0; N_AXES],
            amax: [0.0; N_AXES],
            travel: [(0.0, 0.0); 3],
            present: [false; N_AXES],
            cycle_s: cfg.cycle_s(),
            feed_clamp: f64::INFINITY,
            chord_tol: 0.001,
            arc_radius_tol: 0.01,
            queue_len: 256,
        };
        for (name, a) in &cfg.axes {
            let i = match (a.kind, name.to_ascii_lowercase().as_str()) {
                (AxisKind::Linear, "x") => AX_X,
                (AxisKind::Linear, "y") => AX_Y,
                (AxisKind::Linear, "z") => AX_Z,
                (AxisKind::Spindle, _) if !l.present[AX_S] => AX_S,
                _ => continue,
            };
            l.present[i] = true;
            if i == AX_S {
                l.vmax[i] = a.max_speed * 6.0;
                l.amax[i] = a.max_accel * 6.0;
            } else {
                l.vmax[i] = a.max_speed / 60.0;
                l.amax[i] = a.max_accel;
                l.travel[i] = (a.min.unwrap_or(0.0), a.max.unwrap_or(0.0));
            }
        }
        if let Some(f) = cfg.param(6023).filter(|f| f.is_finite() && *f > 0.0) {
            l.feed_clamp = f / 60.0;
        }
        // No.3410: arc radius error limit (here in mm).
        if let Some(t) = cfg.param(3410).filter(|t| t.is_finite() && *t > 0.0) {
            l.arc_radius_tol = t;
        }
        l
    }
}

/// How the path speed of a segment is commanded.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Speed {
    /// The segment's axis-limited speed (linear rapid).
    Rapid,
    /// mm/s.
    PerMin(f64),
    /// mm per spindle revolution, times the measured spindle speed.
    PerRev(f64),
}

/// A planned motion segment.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Seg {
    geom: Geom,
    speed: Speed,
    /// Highest path speed the axes and the geometry allow, mm/s.
    vlim: f64,
    /// Path acceleration, mm/s².
    alim: f64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Item {
    Move(Seg),
    Dwell(u64),
    Spindle(SpindleCmd),
    Event(Event),
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Entry {
    item: Item,
    line: u32,
}

/// What is executing now.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Run {
    None,
    /// `s` arc length done, `v` path speed of the last cycle; `landed` once on the end point
    /// (the next cycle holds it at rest, then the segment is done).
    Move { seg: Seg, s: f64, v: f64, landed: bool },
    Dwell { left: u64 },
}

/// Planner + interpolator.
pub struct Motion {
    lim: Limits,
    queue: Vec<Entry>,
    head: usize,
    len: usize,
    run: Run,
    /// Current setpoint.
    pos: [f64; N_AXES],
    line: u32,
    // Planning state: where the last pushed move ends.
    plan_end: [f64; 3],
    plan_c: Option<f64>,
    plan_spindle_on: bool,
    // Spindle execution state (rpm).
    sp_dir: f64,
    sp_rpm: f64,
    sp_css: Option<f64>,
    sp_max: f64,
    sp_cur: f64,
    // Operator controls.
    feed_ovr: f64,
    rapid_ovr: f64,
    held: bool,
    paused: bool,
    optional_stop: bool,
    stopping: bool,
}

fn xyz(p: &Pos) -> [f64; 3] {
    [p.x, p.y, p.z]
}

impl Motion {
    pub fn new(limits: Limits, start: [f64; N_AXES]) -> Motion {
        let cap = limits.queue_len.max(1);
        let dummy = Entry { item: Item::Event(Event::None), line: 0 };
        Motion {
            queue: vec![dummy; cap],
            head: 0,
            len: 0,
            run: Run::None,
            pos: start,
            line: 0,
            plan_end: [start[AX_X], start[AX_Y], start[AX_Z]],
            plan_c: None,
            plan_spindle_on: false,
            sp_dir: 0.0,
            sp_rpm: 0.0,
            sp_css: None,
            sp_max: f64::INFINITY,
            sp_cur: 0.0,
            feed_ovr: 1.0,
            rapid_ovr: 1.0,
            held: false,
            paused: false,
            optional_stop: false,
            stopping: false,
            lim: limits,
        }
    }

    pub fn limits(&self) -> &Limits {
        &self.lim
    }

    /// Capacity of the look-ahead queue (allocated once in `new`).
    pub fn has_room(&self) -> bool {
        self.len < self.queue.len()
    }

    /// Plan one canonical move. Refuses (alarm, nothing queued) an end point outside the travel
    /// limits or on an unconfigured axis, a per-revolution feed with the spindle stopped, a
    /// zero or non-finite feed, an arc whose radii differ, a full queue.
    pub fn push(&mut self, m: &Move) -> Result<(), Alarm> {
        let at = |a: Alarm| a.at(m.src.clone());
        if self.stopping {
            return Err(at(Alarm::new(
                alarms::STOPPING,
                "controlled stop in progress: wait until the motion is idle, then restart the program",
            )));
        }
        if !self.has_room() {
            return Err(at(Alarm::new(
                alarms::QUEUE_FULL,
                "motion queue full: the caller must wait for has_room() before pushing",
            )));
        }
        let item = match &m.kind {
            MoveKind::Rapid { end } => {
                let end = self.check_end(end).map_err(at)?;
                let g = geom::line(self.plan_end, end);
                Item::Move(self.line_seg(g, Speed::Rapid))
            }
            MoveKind::Feed { end, feed } => {
                let speed = self.check_feed(feed).map_err(at)?;
                let end = self.check_end(end).map_err(at)?;
                let g = geom::line(self.plan_end, end);
                Item::Move(self.line_seg(g, speed))
            }
            MoveKind::Arc { end, center, cw, plane, feed } => {
                let speed = self.check_feed(feed).map_err(at)?;
                let end = self.check_end(end).map_err(at)?;
                Item::Move(self.arc_seg(end, xyz(center), *cw, *plane, speed).map_err(at)?)
            }
            MoveKind::Thread { .. } | MoveKind::Tap { .. } | MoveKind::RigidThread { .. } => {
                return Err(at(Alarm::new(
                    alarms::UNSUPPORTED,
                    format!(
                        "{} moves are not executed by this motion layer yet; remove the block or use a build with spindle sync",
                        m.kind.name()
                    ),
                )))
            }
            MoveKind::Dwell { seconds } => {
                if !(seconds.is_finite() && *seconds >= 0.0) {
                    return Err(at(Alarm::new(
                        alarms::BAD_VALUE,
                        format!("dwell time must be a finite number ≥ 0 s, got {seconds}; correct the G04 word"),
                    )));
                }
                Item::Dwell((seconds / self.lim.cycle_s).round() as u64)
            }
            MoveKind::Spindle(c) => Item::Spindle(self.check_spindle(c).map_err(at)?),
            MoveKind::Aux { letter, value } => Item::Event(Event::Aux { letter: *letter, value: *value }),
            MoveKind::Stop { optional } => Item::Event(Event::Stop { optional: *optional }),
            MoveKind::End { .. } => Item::Event(Event::End),
        };
        // Accepted: commit the planning state.
        match (&item, &m.kind) {
            (Item::Move(s), _) => {
                self.plan_end = s.geom.end();
                if let Some(e) = m.kind.end() {
                    self.plan_c = Some(e.c);
                }
            }
            (Item::Spindle(c), _) => {
                self.plan_spindle_on =
                    c.dir != SpindleDir::Stop && (c.rpm > 0.0 || c.css.is_some_and(|v| v > 0.0));
            }
            _ => {}
        }
        let i = (self.head + self.len) % self.queue.len();
        self.queue[i] = Entry { item, line: m.src.line };
        self.len += 1;
        Ok(())
    }

    fn check_end(&self, end: &Pos) -> Result<[f64; 3], Alarm> {
        let e = xyz(end);
        for (i, v) in e.iter().enumerate() {
            let name = AXIS_NAMES[i];
            if !v.is_finite() {
                return Err(Alarm::new(alarms::BAD_VALUE, format!("{name} end point is not a finite number ({v})")));
            }
            if !self.lim.present[i] {
                if *v != self.plan_end[i] {
                    return Err(Alarm::new(
                        alarms::TRAVEL,
                        format!("axis {name} is not configured on this machine; remove {name} from the program"),
                    ));
                }
                continue;
            }
            let (lo, hi) = self.lim.travel[i];
            if *v < lo || *v > hi {
                let what = if i == AX_X { " (radius)" } else { "" };
                return Err(Alarm::new(
                    alarms::TRAVEL,
                    format!(
                        "{name} end point {v:.4} mm{what} is beyond the travel limits [{lo}, {hi}]; correct the program or the work offset"
                    ),
                ));
            }
        }
        if !end.c.is_finite() {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("C end point is not a finite number ({})", end.c)));
        }
        if self.plan_c.is_some_and(|c| c != end.c) {
            return Err(Alarm::new(
                alarms::UNSUPPORTED,
                "C-axis (Cs contour) positioning is not supported by this motion layer yet; remove the C word",
            ));
        }
        Ok(e)
    }

    fn check_feed(&self, f: &Feed) -> Result<Speed, Alarm> {
        match *f {
            Feed::PerMin(v) if v.is_finite() && v > 0.0 => Ok(Speed::PerMin(v / 60.0)),
            Feed::PerRev(v) if v.is_finite() && v > 0.0 => {
                if self.plan_spindle_on {
                    Ok(Speed::PerRev(v))
                } else {
                    Err(Alarm::new(
                        alarms::PER_REV_SPINDLE_STOPPED,
                        "feed per revolution (G99) with the spindle stopped: start the spindle (M03/M04 S…) before the cut, or use G98",
                    ))
                }
            }
            Feed::PerMin(v) | Feed::PerRev(v) => Err(Alarm::new(
                alarms::FEED_ZERO,
                format!("feed rate must be > 0, got F{v}; program an F word before the cutting move"),
            )),
        }
    }

    fn check_spindle(&self, c: &SpindleCmd) -> Result<SpindleCmd, Alarm> {
        let bad = |what: &str, v: f64| {
            Alarm::new(alarms::BAD_VALUE, format!("spindle {what} must be a finite number ≥ 0, got {v}"))
        };
        if !(c.rpm.is_finite() && c.rpm >= 0.0) {
            return Err(bad("speed S", c.rpm));
        }
        if let Some(v) = c.css.filter(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(bad("surface speed (G96 S)", v));
        }
        if let Some(v) = c.max_rpm.filter(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(bad("speed clamp (G50 S)", v));
        }
        if c.dir != SpindleDir::Stop && !self.lim.present[AX_S] {
            return Err(Alarm::new(
                alarms::UNSUPPORTED,
                "no spindle is configured on this machine; add a spindle axis to the config or remove M03/M04",
            ));
        }
        Ok(*c)
    }

    fn line_seg(&self, g: Geom, speed: Speed) -> Seg {
        let (mut v, mut a) = (f64::INFINITY, f64::INFINITY);
        if let Geom::Line { delta, len, .. } = g {
            if len > 0.0 {
                for i in 0..3 {
                    let u = delta[i].abs() / len;
                    if u > 0.0 {
                        v = v.min(self.lim.vmax[i] / u);
                        a = a.min(self.lim.amax[i] / u);
                    }
                }
            }
        }
        Seg { geom: g, speed, vlim: finite_or_zero(v), alim: finite_or_zero(a) }
    }

    fn arc_seg(&self, end: [f64; 3], center: [f64; 3], cw: bool, plane: Plane, speed: Speed) -> Result<Seg, Alarm> {
        let axes = match plane {
            Plane::Xy => (AX_X, AX_Y, AX_Z),
            Plane::Zx => (AX_Z, AX_X, AX_Y),
            Plane::Yz => (AX_Y, AX_Z, AX_X),
        };
        if center.iter().any(|c| !c.is_finite()) {
            return Err(Alarm::new(alarms::BAD_VALUE, "arc centre is not a finite number"));
        }
        let Some((g, r0, r1)) = geom::arc(self.plan_end, end, center, axes, cw) else {
            return Err(Alarm::new(
                alarms::BAD_VALUE,
                "arc with zero radius: the start or end point is the centre; correct R or I/J/K",
            ));
        };
        if (r0 - r1).abs() > self.lim.arc_radius_tol {
            return Err(Alarm::new(
                alarms::ARC_RADIUS,
                format!(
                    "arc radius differs between start ({r0:.4}) and end ({r1:.4}) by more than {} mm; correct I/J/K or the end point",
                    self.lim.arc_radius_tol
                ),
            ));
        }
        let (ia, ib, ic) = axes;
        let l = &self.lim;
        let a_plane = l.amax[ia].min(l.amax[ib]);
        let rmin = r0.min(r1);
        let len = g.len();
        let uc = if let Geom::Arc { dc, .. } = g { dc.abs() / len.max(1e-300) } else { 0.0 };
        let mut v = l.vmax[ia].min(l.vmax[ib]);
        v = v.min((0.45 * a_plane * rmin).sqrt());
        v = v.min((8.0 * rmin * l.chord_tol).sqrt() / l.cycle_s);
        let mut a = 0.5 * a_plane;
        if uc > 0.0 {
            v = v.min(l.vmax[ic] / uc);
            a = a.min(l.amax[ic] / uc);
        }
        Ok(Seg { geom: g, speed, vlim: finite_or_zero(v), alim: finite_or_zero(a) })
    }

    fn pop(&mut self) -> Option<Entry> {
        if self.len == 0 {
            return None;
        }
        let e = self.queue[self.head];
        self.head = (self.head + 1) % self.queue.len();
        self.len -= 1;
        Some(e)
    }

    fn apply_spindle(&mut self, c: SpindleCmd) {
        self.sp_dir = match c.dir {
            SpindleDir::Cw => 1.0,
            SpindleDir::Ccw => -1.0,
            SpindleDir::Stop => 0.0,
        };
        self.sp_rpm = c.rpm;
        self.sp_css = c.css;
        self.sp_max = c.max_rpm.unwrap_or(f64::INFINITY);
    }

    /// Spindle speed ramp at max_accel towards the commanded speed; under css the speed is
    /// computed every cycle from the commanded X (radius): rpm = 1000·css / (2π·|x|).
    fn step_spindle(&mut self, dt: f64) {
        let machine_max = self.lim.vmax[AX_S] / 6.0;
        let mag = match self.sp_css {
            Some(css) => {
                let r = self.pos[AX_X].abs();
                let n = if r > 1e-9 { 1000.0 * css / (std::f64::consts::TAU * r) } else { f64::INFINITY };
                n.min(self.sp_max)
            }
            None => self.sp_rpm,
        };
        let target = if self.stopping { 0.0 } else { self.sp_dir * mag.min(machine_max) };
        let step = self.lim.amax[AX_S] / 6.0 * dt;
        let d = target - self.sp_cur;
        self.sp_cur = if d.abs() <= step { target } else { self.sp_cur + step.copysign(d) };
        self.pos[AX_S] += self.sp_cur * 6.0 * dt;
    }

    /// The commanded path speed (mm/s) of a segment this cycle.
    fn v_cmd(&self, seg: &Seg, fb: &Feedback) -> f64 {
        if self.held || self.stopping {
            return 0.0;
        }
        let v = match seg.speed {
            Speed::Rapid => seg.vlim * self.rapid_ovr,
            Speed::PerMin(f) => (f * self.feed_ovr).min(self.lim.feed_clamp),
            Speed::PerRev(r) => {
                let rpm = if fb.spindle_rpm.is_finite() { fb.spindle_rpm.abs() } else { 0.0 };
                (r * rpm / 60.0 * self.feed_ovr).min(self.lim.feed_clamp)
            }
        };
        v.min(seg.vlim)
    }

    /// Advance one cycle. Never allocates; never panics; O(1).
    pub fn step(&mut self, fb: &Feedback) -> Setpoint {
        let dt = self.lim.cycle_s;
        let prev = self.pos;
        let mut event = Event::None;
        let mut path_v = 0.0;
        self.step_spindle(dt);

        if self.run == Run::None && !self.stopping && !self.held && !self.paused {
            if let Some(e) = self.pop() {
                self.line = e.line;
                match e.item {
                    Item::Move(seg) => self.run = Run::Move { seg, s: 0.0, v: 0.0, landed: false },
                    Item::Dwell(n) => self.run = Run::Dwell { left: n },
                    Item::Spindle(c) => self.apply_spindle(c),
                    Item::Event(ev) => {
                        event = ev;
                        match ev {
                            Event::Stop { optional: false } => self.paused = true,
                            Event::Stop { optional: true } => self.paused = self.optional_stop,
                            _ => {}
                        }
                    }
                }
            }
        }

        match self.run {
            Run::None => {}
            Run::Move { landed: true, .. } => {
                // Exact stop: one cycle at rest on the end point.
                self.run = Run::None;
            }
            Run::Move { seg, s, v, landed: false } => {
                let len = seg.geom.len();
                let d = len - s;
                let nv = profile::next_speed(v, self.v_cmd(&seg, fb), d, seg.alim * dt, dt);
                let (s2, landed) = if d - nv * dt <= 1e-9 { (len, true) } else { (s + nv * dt, false) };
                let p = seg.geom.at(s2);
                self.pos[..3].copy_from_slice(&p);
                path_v = if landed { d / dt } else { nv };
                // Stopping and at rest (this cycle did not move): done.
                self.run = if self.stopping && nv == 0.0 && !landed {
                    Run::None
                } else {
                    Run::Move { seg, s: s2, v: nv, landed }
                };
            }
            Run::Dwell { left } => {
                if self.stopping {
                    self.run = Run::None;
                } else if !self.held {
                    let left = left.saturating_sub(1);
                    self.run = if left == 0 { Run::None } else { Run::Dwell { left } };
                }
            }
        }

        if self.stopping && self.run == Run::None {
            // At rest: drop the rest of the program and plan from here.
            self.len = 0;
            self.stopping = false;
            self.held = false;
            self.paused = false;
            self.plan_end = [self.pos[AX_X], self.pos[AX_Y], self.pos[AX_Z]];
            self.plan_spindle_on = false;
            self.sp_dir = 0.0;
            self.sp_css = None;
        }

        let mut vel = [0.0; N_AXES];
        for i in 0..3 {
            vel[i] = (self.pos[i] - prev[i]) / dt;
        }
        vel[AX_S] = self.sp_cur * 6.0;
        Setpoint {
            pos: self.pos,
            vel,
            spindle_rpm: self.sp_cur,
            path_feed: path_v * 60.0,
            line: self.line,
            event,
        }
    }

    /// True when every pushed move has been executed and the feed axes are at rest. (The
    /// spindle may still turn: see `Setpoint::spindle_rpm`.)
    pub fn is_idle(&self) -> bool {
        self.len == 0 && self.run == Run::None && !self.stopping
    }

    /// Controlled stop: decelerate along the path within the acceleration limits, ramp the
    /// spindle down, then drop the rest of the queue. New moves are refused until
    /// `is_idle()`; the next move is planned from where the axes came to rest.
    pub fn stop(&mut self) {
        self.stopping = true;
        self.sp_dir = 0.0;
    }

    /// Feed hold: decelerate along the path and wait (a dwell stops counting); resume with
    /// [`Motion::cycle_start`].
    pub fn feed_hold(&mut self) {
        self.held = true;
    }

    /// Cycle start: resume after feed hold, M00, or M01 with optional stop on.
    pub fn cycle_start(&mut self) {
        self.held = false;
        self.paused = false;
    }

    /// True while feed hold or a program stop (M00/M01) is waiting for cycle start.
    pub fn is_held(&self) -> bool {
        self.held || self.paused
    }

    /// Optional stop switch: when on, M01 waits for cycle start like M00.
    pub fn set_optional_stop(&mut self, on: bool) {
        self.optional_stop = on;
    }

    /// Feed override, 0–2 (0–200 %), applied to cutting feeds from the next cycle.
    pub fn set_feed_override(&mut self, f: f64) {
        self.feed_ovr = if f.is_finite() { f.clamp(0.0, 2.0) } else { 0.0 };
    }

    /// Rapid override, 0–1 (F0 … 100 %).
    pub fn set_rapid_override(&mut self, f: f64) {
        self.rapid_ovr = if f.is_finite() { f.clamp(0.0, 1.0) } else { 0.0 };
    }
}

fn finite_or_zero(v: f64) -> f64 {
    if v.is_finite() {
        v.max(0.0)
    } else {
        0.0
    }
}
