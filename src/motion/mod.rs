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
//! - A segment with `exact_stop` (G61/G09/rapids), or followed by anything but a motion, ends
//!   at rest: the last moving cycle lands on the end point bit for bit, and the following cycle
//!   holds it before the next item starts.
//! - Look-ahead (G64): a segment pushed without `exact_stop` is linked to the next one when it
//!   arrives. The junction is crossed within one cycle at a speed limited by the corner angle
//!   (each axis' velocity jump `v·|Δu_i| ≤ ½·amax_i·dt`, plus `v²·dt/2r` for each arc at the
//!   junction: the chord's turn from its tangent; where junctions are closer than a cycle's
//!   travel the jumps of one cycle add up, `× v·dt/h`: the centripetal limit of a chord
//!   chain, see `corner_speed`), by both segments' speed limits, and by
//!   [`MAX_JUNCTIONS`] × the next segment's length per cycle: a cycle crosses as many
//!   junctions as its travel spans, at most [`MAX_JUNCTIONS`], so `step` stays bounded and a
//!   CAM contour of 0.02 mm blocks runs at its feed. A backward pass (`relax`, once per cycle
//!   over what was pushed since) makes sure every later stop can still be braked for: each
//!   block may count on the whole queued room after it, in distance, down to a stop at rest
//!   on the last queued block — a queue shorter than the braking distance lowers the speed.
//!   Segments next to a blended junction ramp with half the acceleration, the other half is
//!   the corner's; a chain of short blocks ramps with one acceleration (`accel_chain`).
//! - Events (aux codes, M00/M01, M30) and spindle commands are taken in program order, one item
//!   per cycle.
//!
//! Limits per segment: the path speed is at most `min_i vmax_i/|u_i|` and the path
//! acceleration `min_i amax_i/|u_i|` (u = unit direction), so no axis exceeds its own limit;
//! rapids run at exactly that speed, which is Fanuc's linear-interpolation rapid (every axis
//! as fast as the slowest axis' share allows). On an arc half of the smaller axis acceleration
//! goes to the tangential ramp and 45 % to the centripetal `v²/r`; the speed is further limited
//! so that the chord between two setpoints deviates from the circle by at most
//! `chord_tol`: sagitta `(v·dt)²/(8r) ≤ chord_tol` ⇒ `v ≤ √(8·r·chord_tol)/dt`.

//! # Contract with the cycle loop
//!
//! - Every cycle: read the drives' feedback, call `step` once, send the setpoint. `step` never
//!   allocates, never panics, does a bounded amount of work (at most [`MAX_JUNCTIONS`]
//!   crossings and one look-ahead pass over the queue), and is deterministic (same
//!   pushes, feedback and operator calls give bit-identical setpoints).
//! - `Feedback::pos[AX_S]` is the measured spindle angle in continuous degrees whose multiples
//!   of 360 are the one-revolution reference; `Feedback::spindle_rpm` the measured speed.
//!   Per-revolution feed and threading use them; the sync-error monitor also reads the
//!   actual X/Y/Z in synchronised moves.
//! - Push moves whenever `has_room()`; `push` refuses a move with an alarm and queues
//!   nothing. After M00 (and M01 with the optional stop switch on), feed hold and single
//!   block, `is_held()` is true until `cycle_start()`. In drilling and tapping cycles
//!   (moves tagged with their action) single block and feed hold follow the manuals'
//!   action rules (`single_block_stop`, `hold_now`); a single-block stop there is decided
//!   when the next item is queued.
//! - After `stop()` wait for `is_idle()`; the rest of the program is dropped and the next
//!   push plans from where the axes stopped. Check `take_alarm()` after each cycle (outside
//!   the time-critical part): a fault found by `step` (thread too fast) already triggered a
//!   controlled stop.
//! - G02/G03 sense: `cw` is clockwise seen from the positive third axis (G18: from +Y, Z to
//!   the right, X up). The interpreter maps the lathe's tool-post convention onto this.
//! - Under G96 the spindle speed follows the *commanded* X of the previous cycle.
//!
//! # Spindle synchronisation
//!
//! - Threads (`MoveKind::Thread`) lock the path position to the spindle angle predicted to
//!   when the axes get there (measured angle + measured speed × (feedback delay + the long
//!   axis' learnt lag)), see [`crate::sync::thread`] and `step_thread`. A
//!   segment with `continuous` that is queued when the one before it reaches its end is
//!   crossed into within that cycle with the same lock (no wait for the one-revolution
//!   signal, no stop, no phase jump; the path speed changes in the ratio of the path leads, so
//!   e.g. X of a run-out chamfer starts at its synchronous speed at once, as on Fanuc). One
//!   pushed only after the previous ended still continues that lock and catches up. Push a
//!   pass's segments back to back.
//! - G34 (`lead_inc`): z = z0 + L0·n + K·n²/2 after n revolutions; refused (PS0014) when the
//!   lead would reach 0 before the end, and (2306) when the largest lead × S is too fast.
//! - G92.1 (`RigidThread`) and rigid taps: the spindle is braked, then driven in position
//!   with the feed axes on one profile (matched acceleration: No.5261, No.5271 on the way
//!   out); rpm × lead is checked against the feed axes and the spindle at `push`. With
//!   `Limits::sync_correction` the feed axes are sent after the spindle's *actual* angle
//!   (`sync_corr`). `Feedback` must then be paired as `Limits::feedback_delay` says.
//! - A controlled stop during a thread keeps the axes on the thread while the spindle brakes.
//! - The sync error ([`Motion::sync_error`]) is measured every cycle from the feedback;
//!   beyond `Limits::sync_err_limit_um` it is alarm 2307 and a controlled stop of spindle and
//!   axes together. So `Feedback` must carry the drives' *actual* X/Y/Z too.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN, which must be refused.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// Axis loops index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

mod fault;
pub mod geom;
mod polar;
pub mod polygon;
pub mod profile;
#[cfg(test)]
mod tests;

use crate::canon::{Feed, Move, MoveKind, Plane, Pos, SpindleCmd, SpindleDir};
use crate::config::{AxisKind, MachineConfig};
use crate::sync::angle_filter::AngleFilter;
use crate::sync::correction::SyncCorrection;
use crate::sync::governor::SpindleGovernor;
use crate::sync::lag::settle_lead;
use crate::sync::monitor::{Sample, SyncMonitor};
use crate::sync::overload::SpindleOverload;
use crate::sync::torque_margin::TorqueMargin;
use crate::sync::ThreadSync;
use crate::Alarm;
use geom::Geom;
use std::f64::consts::TAU;

pub const AX_X: usize = 0;
pub const AX_Y: usize = 1;
pub const AX_Z: usize = 2;
/// Spindle angle, degrees, continuous (not wrapped).
pub const AX_S: usize = 3;
pub const N_AXES: usize = 4;

/// The actual positions in `Feedback` answer the setpoint returned this many cycles before
/// (CANopen: the target sent after SYNC k−1 is the demand from SYNC k, whose actual arrives
/// with the TPDOs of SYNC k+1; see `cycle.rs`).
pub const FEEDBACK_DELAY: usize = 2;
/// Setpoint history kept for the sync correction (≥ the largest feedback delay + 3).
const HIST: usize = 6;
/// In-position width before a rigid tap (Z, and the spindle times the lead), mm.
pub const INPOS_MM: f64 = 0.001;
/// Largest motion between two cycles of a slide taken as in position, mm (a quarter of the
/// window: creeping onto its count is still, running through the window is not).
const INPOS_STILL_MM: f64 = INPOS_MM / 4.0;
/// Longest wait for the in-position check, cycles (then the tap starts anyway).
const INPOS_MAX_CYCLES: u32 = 150;
/// Memory of the feed axes' lag models (see `sync_corr`), s.
const LAG_MEMORY_S: f64 = 2.0;
/// The rigid tap's bell-shaped acceleration when No.5365 is not set, cycles (see
/// `Limits::from_config`).
const TAP_BELL_CYCLES: f64 = 10.0;
/// A thread's lead-in acceleration rises and falls over this time when No.1626 is not set, s.
/// A step in acceleration where the lead-in meets the synchronous line sets a compliant feed
/// axis ringing (a belt: 20–60 Hz) and its lag settling over its position loop's time
/// constant (1/kv: 40 ms at kv 25), and the phase is measured and learnt while it does. A
/// moving average of this length nulls 25 Hz and attenuates every mode above it by
/// 1/(π·f·T); it costs v·T/2 of lead-in path (0.75 mm at 37.5 mm/s). Belt-driven Z, thread
/// phase spread S500–1500: 0.166° with a step, 0.142° at 20 ms, 0.088° at 30 ms, 0.033° at
/// 40 ms, 0.024° at 50 ms (drive matrix, air, 2026-11-28). A second average of 1.5 × this
/// follows it (`sync::thread::SECOND_SMOOTH`: a null at 16.7 Hz for softer belts).
const THREAD_LEADIN_SMOOTH_S: f64 = 0.04;
/// Share of the spindle's following-error window (0x6065) its lag must reach before the
/// governor judges it (`sync::governor`): below it a lag is the loop's own. 9° of 180°: at a
/// quarter of the window the spindle of 0.12 kg·m² was found too late — 130° behind by then,
/// it overshot by 180° where the tap braked.
const SP_LAG_JUDGE_SHARE: f64 = 0.05;
/// Share of what a spindle out of torque was seen to manage that is planned with from then
/// on (`Motion::govern_spindle`). The rest is what it has to catch up the lag it built up
/// before it was found: at 0.9 a 0.15 kg·m² spindle on 70 N·m (3860 of 5000 rpm/s) was still
/// falling behind and faulted its 180° window in the S3000 tap; at 0.8 it runs it (1.35 µm),
/// every other model as before (drive matrix, air and cut, 2026-11-30).
const SP_ACCEL_MARGIN: f64 = 0.8;
/// Peak speed of a thread's take-up (`Motion::thread_take_up`), mm/s. Slow enough that a slide
/// behind a belt breaks away with next to no speed for the belt to ring with: the same take-up
/// approached at 0.5, 2 and 5 mm/s left a lightly damped belt's thread phase spread 0.120,
/// 0.069 and 0.159° (an undamped one 0.060, 0.048, 0.103°; scratch harness, 2026-11-30).
const TAKE_UP_SPEED: f64 = 2.0;
/// Gain with which a thread's measured phase error corrects the long axis' lag, per cycle.
const THREAD_TRIM_GAIN: f64 = 0.1;
/// Most junctions of a blended chain crossed within one cycle. Keeps `step` bounded: a
/// chain of tiny segments (CAM contours) runs at up to `MAX_JUNCTIONS` segment lengths per
/// cycle (64 × 0.01 mm per 2 ms = 19 m/min), where one crossing per cycle capped the path
/// speed at one segment per cycle. Fanuc's AI contour control likewise processes several
/// blocks per interpolation period.
pub const MAX_JUNCTIONS: usize = 64;

/// Largest C (spindle angle) a move may ask for, degrees: beyond it an angle no longer
/// resolves a count of the spindle's encoder in f64 (a C of 1e300 from a macro made the
/// spindle's command run away).
const C_MAX_DEG: f64 = 1e9;

const AXIS_NAMES: [char; N_AXES] = ['X', 'Y', 'Z', 'S'];

/// A G22-style box (machine coordinates, X as a radius); `outside`: No.1002#0 = 1, the
/// outside is forbidden. The cycle's guard (`control::guard`) checks each
/// set-point against it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StrokeArea {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    pub outside: bool,
}

/// Alarm numbers raised by the motion layer (2300–2399: sync and motion; Fanuc numbers where
/// Fanuc has one).
pub mod alarms {
    /// PS0011: feed zero (a feed move without a positive F).
    pub const FEED_ZERO: u32 = crate::alarm::FEED_ZERO;
    /// PS0020: arc radius out of tolerance (start and end radii differ).
    pub const ARC_RADIUS: u32 = crate::alarm::ARC_RADIUS;
    /// The look-ahead queue is full (caller must check `has_room`).
    pub const QUEUE_FULL: u32 = crate::alarm::QUEUE_FULL;
    /// End point outside the software travel limits, or on an axis that is not configured.
    pub const TRAVEL: u32 = crate::alarm::TRAVEL;
    /// Feed per revolution (G99) while the spindle is stopped.
    pub const PER_REV_SPINDLE_STOPPED: u32 = crate::alarm::PER_REV_SPINDLE_STOPPED;
    /// A value that is not a finite number, a negative dwell or speed, a degenerate arc.
    pub const BAD_VALUE: u32 = crate::alarm::BAD_VALUE;
    /// A move kind this motion layer does not execute yet.
    pub const UNSUPPORTED: u32 = crate::alarm::UNSUPPORTED;
    /// A move pushed while a controlled stop is in progress.
    pub const STOPPING: u32 = crate::alarm::STOPPING;
    /// Thread lead × spindle speed is faster than the feed axes can go.
    pub const THREAD_TOO_FAST: u32 = crate::alarm::THREAD_TOO_FAST;
    /// The measured spindle–axis sync error exceeded `machine.sync_error_limit_um`.
    pub const SYNC_ERROR: u32 = crate::alarm::SYNC_ERROR;
    /// PS0014: G34 lead change makes the lead ≤ 0 before the end of the thread.
    pub const ILLEGAL_LEAD: u32 = crate::alarm::ILLEGAL_LEAD;
    /// G51.2/G50.2 on a machine without a tool spindle (see `polygon.rs`).
    pub const NO_TOOL_SPINDLE: u32 = crate::alarm::NO_TOOL_SPINDLE;
}

/// Actual values from the drives (X radius).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Feedback {
    pub pos: [f64; N_AXES],
    pub spindle_rpm: f64,
    /// Cycles since each drive's position was sampled (0: at this cycle's SYNC). The sync
    /// monitor and correction pair a spindle angle only with a feed-axis position of the same
    /// age, that is, from one SYNC: a late TPDO must not be read as a sync error.
    pub age: [u32; N_AXES],
    /// How late after its slot the SYNC these positions were latched at went out, s (the
    /// cycle's own SYNC, woken late by the PC; 0 on an external SYNC or a bus that samples on
    /// its own). Each position is where its axis was that much after the nominal instant
    /// the set-points are timed for: the spindle's lag measured against them must be taken
    /// back to that instant, or the PC's wake-up jitter reads as lag (`Motion::sync_corr`).
    pub late_s: f64,
    /// With `late_s`: the spindle's angle taken back to the slot by its speed over the
    /// interval that ends at that SYNC, degrees (`CycleLoop::spindle_to_slot`).
    pub spindle_at_slot: f64,
    /// The spindle drive's torque as last read (torque actual 0x6077), in units of its rated
    /// torque; NaN when it gives none (`sync::overload`).
    pub spindle_torque: f64,
    /// Its torque limit (max torque 0x6072) in the same unit; NaN or 0 when not known
    /// (`sync::torque_margin`).
    pub spindle_torque_max: f64,
}

/// `fb.late_s` where it applies (fresh spindle feedback), within a cycle, s.
fn sample_late(fb: &Feedback, cycle_s: f64) -> f64 {
    if fb.age[AX_S] == 0 && fb.late_s.is_finite() {
        fb.late_s.clamp(0.0, cycle_s)
    } else {
        0.0
    }
}

/// The spindle's measured angle at the instant its set-points are timed for
/// (`Feedback::late_s`), degrees. At S3000 a SYNC 0.3 ms late puts the angle 5.4° on: read as
/// lag it stopped heavy spindles' taps by alarm 2307, and read as speed it kept the governor
/// from seeing a spindle out of torque (alarm 2010).
fn spindle_at_slot(fb: &Feedback, cycle_s: f64) -> f64 {
    if sample_late(fb, cycle_s) > 0.0 && fb.spindle_at_slot.is_finite() {
        fb.spindle_at_slot
    } else {
        fb.pos[AX_S]
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    None,
    Stop {
        optional: bool,
    },
    End,
    Aux {
        letter: char,
        value: f64,
    },
    /// G22 (`Some`, the area, X a radius) or G23 (`None`) reached: the cycle loop switches its
    /// per-set-point guard (`control::guard::Guard::set_stroke2`) before it checks this set-point.
    Stroke2(Option<StrokeArea>),
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
    /// Tool spindle angle setpoint, degrees (G51.2 polygon turning; see `polygon.rs`).
    pub tool_spindle: f64,
}

/// Machine limits as the interpolator uses them (SI-ish: units/s, units/s²).
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    /// Per-axis maximum speed, units/s (mm/s; spindle deg/s). 0 for an axis not configured.
    pub vmax: [f64; N_AXES],
    /// Per-axis maximum acceleration, units/s² (spindle deg/s²).
    pub amax: [f64; N_AXES],
    /// Per-axis jerk limit of the path-speed profile, units/s³; 0 = not limited. A segment
    /// whose axes are all unlimited keeps the discrete trapezoid (see [`profile`]).
    pub jmax: [f64; N_AXES],
    /// Software travel limits (min, max) of X (radius), Y, Z in mm.
    pub travel: [(f64, f64); 3],
    /// Per-axis in-position width (`axes.NAME.in_position`), units; 0 where not configured.
    pub in_position: [f64; N_AXES],
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
    /// Spindle acceleration in rigid tapping, deg/s² (No.5261: ms to reach 1000 rpm);
    /// infinity when not set (the spindle's max_accel then applies).
    pub tap_accel: f64,
    /// No.5200#6: feed hold and single block act within a rigid tap (1), or only once the
    /// tool is back at the R point (0).
    pub tap_hold_in_hole: bool,
    /// Alarm limit of the measured sync error, µm (`machine.sync_error_limit_um`).
    pub sync_err_limit_um: f64,
    /// Spindle acceleration of a rigid-tap retract stroke (out of the hole), deg/s² (No.5271:
    /// ms to 1000 rpm); infinity when not set (then `tap_accel` applies).
    pub tap_retract_accel: f64,
    /// Bell-shaped acceleration of rigid taps: the time over which the acceleration ramps
    /// (jerk = acceleration / this), s; 0 = linear (the manual's No.5261/5271 alone). The
    /// manual is silent; Fanuc 0i-TF has it as No.5365 (T2 of bell-shaped acceleration/
    /// deceleration for rigid tapping). An acceleration step makes every drive's lag turn
    /// within one cycle, and the spindle's and the feed axis' lags turn differently; ramped,
    /// both follow their set-points smoothly and the sync holds on drives with other delays,
    /// compliance or friction.
    pub tap_bell_s: f64,
    /// Time over which a thread's lead-in acceleration rises and falls, s (0 = a step; see
    /// `ThreadSync::arm_smooth`). No.1626 in ms when set (Fanuc: the threading cycles' acc/dec
    /// time constant; here a moving average that keeps the phase exact), else
    /// THREAD_LEADIN_SMOOTH_S.
    pub thread_leadin_s: f64,
    /// Spindle lag (degrees) from which on the governor judges whether it falls behind
    /// (`SP_LAG_JUDGE_SHARE` of its following-error window); ∞ = never.
    pub sp_lag_judge: f64,
    /// The spindle amplifier's overload rating: % of rated torque, for seconds
    /// (`axes.NAME.overload_pct`, `overload_s`).
    pub sp_overload: (f64, f64),
    /// In rigid taps and G92.1, add the spindle's measured lag (times the lead) to the feed
    /// axes' setpoint, so that they follow the spindle's *actual* angle (see `sync_corr`).
    /// Needs `Feedback` as `CycleLoop` delivers it: the answer to the setpoint of
    /// [`FEEDBACK_DELAY`] cycles before.
    pub sync_correction: bool,
    /// The actual positions in `Feedback` answer the setpoint returned this many cycles
    /// before ([`FEEDBACK_DELAY`] under `CycleLoop`; 1 for an ideal drive that is where the
    /// last setpoint put it). Threads predict the spindle angle this far ahead, the sync
    /// correction pairs feedback with setpoints by it. 1 ..= 3.
    pub feedback_delay: usize,
    /// No.5275: cycles by which a flexible tap's axis lags the spindle encoder (compensated).
    pub flex_lag_cycles: f64,
    /// No.5276 (0.1 rpm units, here rpm): a flexible tap's retract starts once the encoder
    /// shows the reversed spindle at this speed; 0 = at once.
    pub flex_retract_rpm: f64,
    /// No.1421: the rapid rate at rapid override F0, mm/s (Fanuc's F0 is this rate, not a
    /// percentage); 0 (unset) = rapids stand at F0.
    pub rapid_f0: f64,
    /// A thread pass's take-up, mm along the thread (`machine.thread_take_up_mm`; 0 = none):
    /// see `Motion::thread_take_up`.
    pub thread_take_up: f64,
}

impl Limits {
    /// Limits of the configured machine: axes named `x`, `y`, `z` (linear) and the first
    /// spindle. mm/min → mm/s, rpm → deg/s (×6), rpm/s → deg/s² (×6).
    pub fn from_config(cfg: &MachineConfig) -> Limits {
        let mut l = Limits {
            vmax: [0.0; N_AXES],
            amax: [0.0; N_AXES],
            jmax: [0.0; N_AXES],
            travel: [(0.0, 0.0); 3],
            in_position: [0.0; N_AXES],
            present: [false; N_AXES],
            cycle_s: cfg.cycle_s(),
            feed_clamp: f64::INFINITY,
            chord_tol: 0.001,
            arc_radius_tol: 0.01,
            queue_len: 1024,
            tap_accel: f64::INFINITY,
            tap_hold_in_hole: cfg.param_bit(5200, 6),
            sync_err_limit_um: cfg.machine.sync_error_limit_um,
            tap_retract_accel: f64::INFINITY,
            tap_bell_s: 0.0,
            thread_leadin_s: 0.0,
            sp_lag_judge: f64::INFINITY,
            sp_overload: (f64::INFINITY, 0.0),
            sync_correction: true,
            feedback_delay: FEEDBACK_DELAY,
            flex_lag_cycles: cfg.param(5275).filter(|n| n.is_finite() && *n > 0.0).unwrap_or(0.0),
            flex_retract_rpm: cfg.param(5276).filter(|n| n.is_finite() && *n > 0.0).map_or(0.0, |n| n * 0.1),
            rapid_f0: cfg.param(1421).filter(|n| n.is_finite() && *n > 0.0).map_or(0.0, |n| n / 60.0),
            thread_take_up: cfg.machine.thread_take_up_mm,
        };
        for (name, a) in &cfg.axes {
            if a.role == Some(crate::config::AxisRole::ToolSpindle) {
                continue; // polygon turning's tool spindle: see polygon::ToolSpindle
            }
            let i = match (a.kind, name.to_ascii_lowercase().as_str()) {
                (AxisKind::Linear, "x") => AX_X,
                (AxisKind::Linear, "y") => AX_Y,
                (AxisKind::Linear, "z") => AX_Z,
                (AxisKind::Spindle, _) if !l.present[AX_S] => AX_S,
                _ => continue,
            };
            l.present[i] = true;
            if i == AX_S {
                l.vmax[i] = a.max_speed_units_s();
                l.amax[i] = a.max_accel_units_s2();
                l.sp_lag_judge = SP_LAG_JUDGE_SHARE * a.following_error;
                l.sp_overload = (a.overload_pct, a.overload_s);
            } else {
                l.vmax[i] = a.max_speed_units_s();
                l.amax[i] = a.max_accel;
                l.jmax[i] = a.jerk_limit(cfg.param(1772));
                l.travel[i] = (a.min.unwrap_or(0.0), a.max.unwrap_or(0.0));
                l.in_position[i] = a.in_position;
            }
        }
        if let Some(f) = cfg.param(6023).filter(|f| f.is_finite() && *f > 0.0) {
            l.feed_clamp = f / 60.0;
        }
        if let Some(ms) = cfg.param(5261).filter(|t| t.is_finite() && *t > 0.0) {
            l.tap_accel = 1000.0 / (ms / 1000.0) * 6.0;
        }
        if let Some(ms) = cfg.param(5271).filter(|t| t.is_finite() && *t > 0.0) {
            l.tap_retract_accel = 1000.0 / (ms / 1000.0) * 6.0;
        }
        // No.5365 = 0 is linear on Fanuc, whose servos are matched to its CNC. Here the
        // spindle and the feed axes are anyone's drives: an acceleration step turns their lags
        // differently within a cycle, and across a transport delay the correction learns of
        // it cycles late. So unset, the acceleration ramps over TAP_BELL_CYCLES (drive matrix,
        // no load: 7.9 → 3.2 µm with 2 cycles of delay, all others ≤ 4.1 µm); an explicit
        // value is kept (0: linear, as on Fanuc).
        l.tap_bell_s = match cfg.param(5365).filter(|t| t.is_finite() && *t >= 0.0) {
            Some(ms) => ms / 1000.0,
            None => TAP_BELL_CYCLES * l.cycle_s,
        };
        l.thread_leadin_s = cfg.param(1626).filter(|t| t.is_finite() && *t >= 0.0).map_or(THREAD_LEADIN_SMOOTH_S, |ms| ms / 1000.0);
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
    /// Path jerk, mm/s³ (`min_i jmax_i/|u_i|`); 0 = the discrete trapezoid, no jerk limit.
    jlim: f64,
    /// Unit tangents at start and end.
    t0: [f64; 3],
    t1: [f64; 3],
    /// The previous segment may blend into this one (it was pushed without exact stop).
    blend_in: bool,
    /// Speed limit at the junction with the next segment (corner, axis limits, lengths);
    /// 0 while no next segment is linked: the segment ends with an exact stop.
    vj: f64,
    /// Look-ahead: distance beyond the end at which braking to rest may be assumed
    /// (see `relax`). 0 = exact stop at the end. Only ever grows while the segment is queued
    /// or running, which keeps the braking invariant of `profile` valid.
    ext: f64,
}

/// A spindle-synchronised thread pass (a straight line, taper allowed).
#[derive(Clone, Copy, Debug, PartialEq)]
struct ThreadSeg {
    geom: Geom,
    /// Path length per spindle revolution (lead along the long axis / its direction share).
    lead_path: f64,
    /// G34: change of `lead_path` per revolution (lead_inc / the long axis' share).
    k_path: f64,
    /// The long axis' share of the path (long-axis mm per path mm).
    u_long: f64,
    /// The long axis (X, Y or Z).
    long_axis: usize,
    /// Largest path lead over the segment (the start's or, under G34, the end's).
    lead_path_max: f64,
    /// Starts without waiting for the one-revolution signal, continuing the lock of the
    /// thread segment before it (see `ThreadSync::continue_with`).
    continuous: bool,
    start_angle: f64,
    vlim: f64,
    alim: f64,
}

/// A rigid-tap stroke along one feed axis (`axis`: Z for G84, X for G88 — a radius, Y):
/// the spindle angle is `360·(p − p0)/lead`, p the position on that axis.
#[derive(Clone, Copy, Debug, PartialEq)]
struct TapSeg {
    axis: usize,
    p0: f64,
    p1: f64,
    lead: f64,
    /// Commanded speed along the tapping axis (rpm × |lead|), mm/s.
    v: f64,
    vlim: f64,
    alim: f64,
    /// Jerk limit along the tapping axis (bell-shaped acceleration, `Limits::tap_bell_s`),
    /// mm/s³; 0 = linear acceleration.
    jlim: f64,
    /// Out of the hole (No.5271's time constant).
    retract: bool,
}

/// A G92.1 rigid thread stroke, or a rapid that positions the spindle (Cs): a line of the
/// feed axes and a spindle turn of `dc` degrees on one profile, the spindle in position mode:
/// angle = θ_ref + dc·s/plen.
#[derive(Clone, Copy, Debug, PartialEq)]
struct RigidSeg {
    geom: Geom,
    /// Spindle travel, degrees (signed).
    dc: f64,
    /// Length of the profile: the path length in mm, or |dc| in degrees when only the
    /// spindle moves.
    plen: f64,
    /// Commanded path speed (from the rpm), mm/s.
    v: f64,
    vlim: f64,
    alim: f64,
    /// The long axis' share of the path (long-axis mm per path mm).
    u_long: f64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Item {
    Move(Seg),
    Thread(ThreadSeg),
    Tap(TapSeg),
    Rigid(RigidSeg),
    /// G12.1 polar coordinate interpolation (see `polar.rs`).
    Polar(polar::PolarSeg),
    /// G51.2 (Some) / G50.2 (None): the tool spindle's synchronisation (see `polygon.rs`).
    Polygon(Option<crate::canon::PolygonCmd>),
    Dwell(u64),
    Spindle(SpindleCmd),
    Event(Event),
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Entry {
    item: Item,
    line: u32,
    /// The drilling/tapping cycle action this item belongs to.
    cyc: CycStep,
}

/// Where an item stands in a drilling or tapping canned cycle (from [`crate::canon::CycleTag`]),
/// for single block and feed hold by the manuals' actions: 1 positioning, 2 to R, 3 cutting
/// or tapping in (pecks), 4 dwell at the bottom, 5 back to R, 6 back to the initial plane.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct CycStep {
    /// Which cycle (index in [`DRILL_CYCLES`] + 1); 0 = not a drilling/tapping cycle.
    code: u8,
    step: u8,
    /// A hole tapped rigidly (manual 000's rules apply instead of 004 §2.21's).
    rigid: bool,
}

/// The drilling and tapping cycles whose actions are numbered 1–6 (004 §2.21–2.22, 000, and
/// the SINUMERIK drilling cycles, which the interpreter tags the same way).
const DRILL_CYCLES: [&str; 13] =
    ["G83", "G84", "G85", "G87", "G88", "G89", "CYCLE81", "CYCLE82", "CYCLE83", "CYCLE84", "CYCLE840", "CYCLE85", "CYCLE86"];
/// Of those, the tapping cycles (a flexible tap must not stop in the hole either).
const TAP_CYCLES: [&str; 4] = ["G84", "G88", "CYCLE84", "CYCLE840"];

impl CycStep {
    fn of(m: &Move) -> CycStep {
        match &m.tag {
            Some(t) => match DRILL_CYCLES.iter().position(|c| **c == *t.cycle) {
                Some(i) => CycStep { code: i as u8 + 1, step: t.step, rigid: false },
                None => CycStep::default(),
            },
            None => CycStep::default(),
        }
    }

    /// Actions 3–5 of a flexible (not rigid) tapping cycle: the tap is in the hole, cut by
    /// the turning spindle.
    fn flex_tap_in_hole(self) -> bool {
        self.code > 0
            && !self.rigid
            && (3..=5).contains(&self.step)
            && DRILL_CYCLES.get((self.code - 1) as usize).is_some_and(|c| TAP_CYCLES.contains(c))
    }

    /// Actions 1, 2 and 3–6 (cutting in to back on the initial plane) are the three single
    /// blocks of a hole (004 §2.21 note 2, §2.22 note 4).
    fn group(self) -> u8 {
        self.step.min(3)
    }

    /// `next` continues this item's action of the same hole.
    fn same_action(self, next: CycStep) -> bool {
        next.code == self.code && next.group() == self.group() && next.step >= self.step
    }
}

/// What is executing now.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Run {
    None,
    /// `s` arc length done, `v` path speed of the last cycle; `landed` once on the end point
    /// (the next cycle holds it at rest, then the segment is done).
    Move {
        seg: Seg,
        s: f64,
        v: f64,
        landed: bool,
    },
    Dwell {
        left: u64,
    },
    /// Waiting for the spindle (`sync` None) or cutting, locked to the measured angle.
    Thread {
        seg: ThreadSeg,
        sync: Option<ThreadSync>,
        s: f64,
        v: f64,
        landed: bool,
    },
    /// Waiting for the spindle to stop (`theta0` None), then the stroke; `theta0` is the tap
    /// reference (p_ref, θ_ref) on the tapping axis: spindle angle = θ_ref + 360·(p − p_ref)/lead.
    Tap {
        seg: TapSeg,
        theta0: Option<(f64, f64)>,
        s: f64,
        v: f64,
        landed: bool,
    },
    /// G92.1: waiting for the spindle to stop (`theta0` None), then the stroke from the
    /// spindle angle `theta0`.
    Rigid {
        seg: RigidSeg,
        theta0: Option<f64>,
        s: f64,
        v: f64,
        landed: bool,
    },
    /// G12.1: braking the spindle, aligning C, then on the virtual path (see `polar.rs`).
    Polar(polar::PolarRun),
}

/// A fault found while executing (reported by [`Motion::take_alarm`]; `step` cannot return
/// an error and must not allocate).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    ThreadTooFast { v: f64, vlim: f64, line: u32 },
    SyncError { err_um: f64, limit_um: f64, line: u32 },
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
    /// Planned spindle speed (rpm, G97), for checks at push; None under css or stopped.
    plan_rpm: Option<f64>,
    /// The last pushed item is a motion without exact stop: the next one may blend into it.
    last_blendable: bool,
    // Spindle execution state (rpm).
    sp_dir: f64,
    sp_rpm: f64,
    sp_css: Option<f64>,
    sp_max: f64,
    sp_cur: f64,
    /// Whether the spindle manages its acceleration (`sync::governor`), and the acceleration
    /// it was found to manage (deg/s², ∞ until it fell behind once).
    sp_gov: SpindleGovernor,
    sp_accel_cap: f64,
    /// Whether the spindle has torque to spare (`sync::torque_margin`); whether that set
    /// `sp_accel_cap` last (it gave the acceleration, at its torque limit).
    sp_margin: TorqueMargin,
    sp_cap_by_torque: bool,
    /// The spindle amplifier's overload (`sync::overload`) and the acceleration it allows
    /// (deg/s², ∞ until its load passed its share).
    sp_overload: SpindleOverload,
    sp_heat_cap: f64,
    /// The same, found during a stroke: taken when the next one starts.
    sp_heat_next: f64,
    /// The speed the ramp is heading for this cycle (rpm, signed).
    sp_target: f64,
    // Operator controls.
    feed_ovr: f64,
    rapid_ovr: f64,
    spindle_ovr: f64,
    held: bool,
    paused: bool,
    /// An M/T code's completion (FIN) is awaited: no next item (see [`Motion::wait_fin`]).
    fin_wait: bool,
    optional_stop: bool,
    single_block: bool,
    stopping: bool,
    fault: Option<Fault>,
    /// The sync-error monitor's state (see `sync_error`).
    monitor: SyncMonitor,
    /// Each feed axis' effective lag on a thread's synchronous line, s, learnt from the
    /// threads' own measured phase error (None: not yet threaded; the lag model's τ₁ then).
    thread_tau: [Option<f64>; 3],
    /// A thread's ideal path step per cycle through the settling lead's filter (see
    /// `thread_shortfall`), mm.
    thread_vf: f64,
    /// The spindle angle a thread follows, smoothed (see `crate::sync::angle_filter`).
    thread_angle: AngleFilter,
    /// The long axis' settling (`SyncCorrection::settling`) as it was when the pass armed.
    thread_settle: Option<(f64, f64)>,
    /// Each feed axis' last direction of motion (−1, 0, +1), for the thread's take-up.
    last_dir: [f64; 3],
    /// The take-up before a thread pass (`thread_take_up`): (cycles run, its length mm), set
    /// where the pass starts (`take_up_len`).
    takeup: Option<(u32, f64)>,
    /// The lock of the thread segment that ended last and its length, for a continuous
    /// segment that follows it (cleared by any other item).
    thread_chain: Option<(ThreadSync, f64)>,
    /// Rigid tapping reference (axis, position on it, spindle angle, lead) of the last stroke,
    /// so that the strokes of one hole share one axis–angle relation and the return ends on
    /// the start angle exactly.
    tap_ref: Option<(usize, f64, f64, f64)>,
    /// The tool is inside a tapped hole (a tap stroke ended away from the hole's R point).
    in_hole: bool,
    /// Direction (±1) of the tap stroke that landed last: the sign of the sync error at rest
    /// in the hole.
    hole_dir: f64,
    /// Planning: the hole the last pushed tap strokes are in (tapping axis, R point on it,
    /// direction into it).
    plan_tap: Option<(usize, f64, f64)>,
    /// Setpoints sent in the last HIST cycles (ring, index `hist_k` = the newest).
    hist: [[f64; N_AXES]; HIST],
    hist_k: usize,
    /// The sync correction of rigid taps and G92.1 (`crate::sync::correction`).
    corr: SyncCorrection,
    /// Cycles waited for the in-position check before a rigid tap.
    inpos_wait: u32,
    /// The feedback at the last in-position check: in position means still there too.
    inpos_prev: [f64; N_AXES],
    /// The cycle action of the item running or last taken from the queue.
    cur_cyc: CycStep,
    /// The cycle action of the last pushed item (planning).
    plan_cyc: CycStep,
    /// Single block: a drilling-cycle item ended; whether to stop is decided against the next
    /// item (see `single_block_stop`).
    sb_pending: bool,
    /// The measured spindle speed of the last cycle (flexible tapping's lag compensation).
    fb_rpm_prev: f64,
    /// A drive of the running synchronised pair faulted: the survivor follows it (`fault.rs`).
    follow: Option<fault::Follow>,
    /// The tool spindle of polygon turning (absent unless `set_tool_spindle`).
    tool: polygon::ToolSync,
    /// S-curve: path acceleration at the end of the last cycle of a `Run::Move`, mm/s² (its
    /// speed is the `v` there). 0 with the trapezoid.
    path_a: f64,
    /// Rigid-tap entry gate (`tapstate`): None = a hole's first stroke starts at once;
    /// Some(open) = it starts only once opened (the "in hole" state is on disk).
    tap_gate: Option<bool>,
    /// A hole's first stroke is ready at R and waits for the gate.
    tap_wait: Option<TapEntry>,
    /// Items pushed since the last look-ahead pass (`relax`, at the start of `step`).
    relax_pending: usize,
}

/// A rigid tap's first stroke of a hole, ready at its R point (see [`Motion::tap_waiting`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TapEntry {
    pub line: u32,
    /// Tapping axis (`AX_X`, `AX_Y`, `AX_Z`).
    pub axis: usize,
    /// The R point on it (where the stroke starts) and the direction into the hole (±1).
    pub r: f64,
    pub dir: f64,
    /// The spindle angle at R, degrees (the thread's reference for the hole).
    pub spindle_deg: f64,
    /// The stroke's signed lead (mm per revolution) and spindle speed going in (rpm).
    pub lead: f64,
    pub rpm: f64,
}

fn xyz3(p: &[f64; N_AXES]) -> [f64; 3] {
    [p[AX_X], p[AX_Y], p[AX_Z]]
}

fn xyz(p: &Pos) -> [f64; 3] {
    [p.x, p.y, p.z]
}

impl Motion {
    pub fn new(limits: Limits, start: [f64; N_AXES]) -> Motion {
        let cap = limits.queue_len.max(1);
        let dummy = Entry { item: Item::Event(Event::None), line: 0, cyc: CycStep { code: 0, step: 0, rigid: false } };
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
            plan_rpm: None,
            last_blendable: false,
            fault: None,
            monitor: SyncMonitor::default(),
            thread_tau: [None; 3],
            thread_vf: 0.0,
            thread_angle: AngleFilter::default(),
            thread_settle: None,
            last_dir: [0.0; 3],
            takeup: None,
            thread_chain: None,
            tap_ref: None,
            in_hole: false,
            hole_dir: 1.0,
            plan_tap: None,
            hist: [start; HIST],
            hist_k: 0,
            corr: SyncCorrection::new(
                limits.cycle_s,
                limits.feedback_delay.clamp(1, HIST - 3),
                [limits.amax[AX_X], limits.amax[AX_Y], limits.amax[AX_Z]],
                LAG_MEMORY_S,
                [start[AX_X], start[AX_Y], start[AX_Z]],
            ),

            inpos_wait: 0,
            inpos_prev: [f64::NAN; N_AXES],
            cur_cyc: CycStep::default(),
            plan_cyc: CycStep::default(),
            sb_pending: false,
            fb_rpm_prev: 0.0,
            follow: None,
            tool: polygon::ToolSync::none(),
            path_a: 0.0,
            tap_gate: None,
            tap_wait: None,
            relax_pending: 0,
            sp_dir: 0.0,
            sp_rpm: 0.0,
            sp_css: None,
            sp_max: f64::INFINITY,
            sp_cur: 0.0,
            sp_gov: SpindleGovernor::default(),
            sp_accel_cap: f64::INFINITY,
            sp_margin: TorqueMargin::default(),
            sp_cap_by_torque: false,
            sp_overload: SpindleOverload::new(limits.sp_overload.0, limits.sp_overload.1),
            sp_heat_cap: f64::INFINITY,
            sp_heat_next: f64::INFINITY,
            sp_target: 0.0,
            feed_ovr: 1.0,
            rapid_ovr: 1.0,
            spindle_ovr: 1.0,
            held: false,
            paused: false,
            fin_wait: false,
            optional_stop: false,
            single_block: false,
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
            return Err(at(Alarm::new(alarms::STOPPING, "controlled stop in progress: wait until the motion is idle, then restart the program")));
        }
        if !self.has_room() {
            return Err(at(Alarm::new(alarms::QUEUE_FULL, "motion queue full: the caller must wait for has_room() before pushing")));
        }
        let blend_in = self.last_blendable;
        let blended = blend_in || !m.exact_stop;
        let item = match &m.kind {
            MoveKind::Rapid { end: e } if end_c_moves(self.plan_c, e) => Item::Rigid(self.c_rapid_seg(e, self.plan_c.unwrap_or(e.c)).map_err(at)?),
            MoveKind::Rapid { end } => {
                let end = self.check_end(end).map_err(at)?;
                let g = geom::line(self.plan_end, end);
                Item::Move(self.line_seg(g, Speed::Rapid, blended))
            }
            MoveKind::Feed { end, feed } => {
                let speed = self.check_feed(feed).map_err(at)?;
                let end = self.check_end(end).map_err(at)?;
                let g = geom::line(self.plan_end, end);
                Item::Move(self.line_seg(g, speed, blended))
            }
            MoveKind::Arc { end, center, cw, plane, feed } => {
                let speed = self.check_feed(feed).map_err(at)?;
                let end = self.check_end(end).map_err(at)?;
                Item::Move(self.arc_seg(end, xyz(center), *cw, *plane, speed, blended).map_err(at)?)
            }
            MoveKind::Thread { end, lead, start_angle, continuous, lead_inc } => {
                Item::Thread(self.thread_seg(end, *lead, *start_angle, *lead_inc, *continuous).map_err(at)?)
            }
            MoveKind::RigidThread { end, lead, rpm } => Item::Rigid(self.rigid_seg(end, *lead, *rpm).map_err(at)?),
            // One spindle is driven (the first configured): a tap on another (E2–E4, M25–M27)
            // is refused before anything moves.
            MoveKind::Tap { spindle, .. } if *spindle != 1 => {
                return Err(at(Alarm::new(
                    alarms::UNSUPPORTED,
                    format!(
                    "rigid tap on spindle {spindle}: this machine drives one spindle (spindle 1); select it with E1 (or M24), or remove E / M25–M27"
                ),
                )))
            }
            MoveKind::Tap { end, lead, rpm, .. } => {
                let mut t = self.tap_seg(end, *lead, *rpm).map_err(at)?;
                // G30 P99, the return from an interrupted tap, pulls out from where the tool is.
                t.retract |= m.tag.as_ref().is_some_and(|g| &*g.cycle == "G30 P99");
                Item::Tap(t)
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
            MoveKind::StrokeCheck { area } => Item::Event(Event::Stroke2(area.map(|a| StrokeArea {
                lo: [a.lo.x, a.lo.y, a.lo.z],
                hi: [a.hi.x, a.hi.y, a.hi.z],
                outside: a.outside,
            }))),
            MoveKind::Polar { end, from, to, center, cw, c_zero, feed } => {
                Item::Polar(self.polar_seg(end, *from, *to, *center, *cw, *c_zero, feed, m.work_offset.x, m.exact_stop).map_err(at)?)
            }
            MoveKind::Polygon(cmd) => Item::Polygon(self.check_polygon(cmd).map_err(at)?),
        };
        let mut item = item;
        // Accepted: commit the planning state.
        match &mut item {
            Item::Move(s) => {
                s.blend_in = blend_in;
                self.plan_tap = None;
                self.plan_end = s.geom.end();
                if let Some(e) = m.kind.end() {
                    self.plan_c = Some(e.c);
                }
            }
            Item::Spindle(c) => {
                self.plan_spindle_on = c.dir != SpindleDir::Stop && (c.rpm > 0.0 || c.css.is_some_and(|v| v > 0.0));
                self.plan_rpm = (self.plan_spindle_on && c.css.is_none()).then_some(c.rpm);
            }
            Item::Thread(t) => {
                self.plan_tap = None;
                self.plan_end = t.geom.end();
                if let Some(e) = m.kind.end() {
                    self.plan_c = Some(e.c);
                }
            }
            Item::Rigid(r) => {
                self.plan_tap = None;
                self.plan_end = r.geom.end();
                if let Some(e) = m.kind.end() {
                    self.plan_c = Some(e.c);
                }
                // Like rigid tapping, G92.1 leaves the spindle stopped, in position control.
                self.plan_spindle_on = false;
                self.plan_rpm = None;
            }
            Item::Polar(_) => {
                self.plan_tap = None;
                if let Some(e) = m.kind.end() {
                    self.plan_end = xyz(&e);
                    self.plan_c = Some(e.c);
                }
                // The spindle is the C axis: stopped, in position control, until M03/M04.
                self.plan_spindle_on = false;
                self.plan_rpm = None;
            }
            Item::Polygon(Some(c)) => {
                self.plan_spindle_on = true;
                self.plan_rpm = Some(c.rpm);
            }
            Item::Tap(t) => {
                self.plan_tap = match self.plan_tap {
                    Some((a, r, d)) if a == t.axis => {
                        // Back at the R point: the hole is done.
                        (t.p1 != r).then_some((a, r, d))
                    }
                    _ => Some((t.axis, t.p0, (t.p1 - t.p0).signum())),
                };
                self.plan_end[t.axis] = t.p1;
                // Rigid tapping leaves the spindle stopped, in position control.
                self.plan_spindle_on = false;
                self.plan_rpm = None;
            }
            _ => {}
        }
        let is_move = matches!(item, Item::Move(_));
        let cyc = self.plan_cycle_step(m, &item);
        let i = (self.head + self.len) % self.queue.len();
        self.queue[i] = Entry { item, line: m.src.line, cyc };
        self.len += 1;
        self.relax_pending = self.relax_pending.saturating_add(1);
        if is_move && blend_in {
            self.link_last();
        }
        self.last_blendable = is_move && !m.exact_stop;
        Ok(())
    }

    /// The cycle action of a move being pushed. A rigid tap stroke marks its hole rigid: the
    /// items of actions 1–2 before it (still queued or running) and every later item of the
    /// hole's actions 3–6.
    fn plan_cycle_step(&mut self, m: &Move, item: &Item) -> CycStep {
        let mut c = CycStep::of(m);
        if c.code == 0 {
            self.plan_cyc = c;
            return c;
        }
        let p = self.plan_cyc;
        if matches!(item, Item::Tap(_)) {
            c.rigid = true;
            if !(p.rigid && p.code == c.code) {
                let cap = self.queue.len();
                let mut k = self.len;
                let mut all = true;
                while k > 0 {
                    let e = &mut self.queue[(self.head + k - 1) % cap].cyc;
                    if e.code != c.code || e.step >= 3 {
                        all = false;
                        break;
                    }
                    e.rigid = true;
                    k -= 1;
                }
                if all && self.cur_cyc.code == c.code && self.cur_cyc.step < 3 {
                    self.cur_cyc.rigid = true;
                }
            }
        } else if p.rigid && p.code == c.code && p.step >= 3 && c.step >= p.step {
            c.rigid = true;
        }
        self.plan_cyc = c;
        c
    }

    /// Single block between the item that ended (`cur_cyc`) and the next one, in a drilling or
    /// tapping cycle. 004 §2.21 note 2 / §2.22 note 4: stop at the ends of actions 1, 2 and 6
    /// (3–6 are one block). Rigid tapping, 000 "暂停与单段": never within actions 1–6 of a
    /// hole; after a hole only with No.5200#6, and after the cycle's last hole always (its
    /// table: `G84 …; C180;` do not stop with #6 = 0, `C270;` before `G80` does).
    /// False while the next item is not queued yet (decided when it arrives).
    fn single_block_stop(&self, next: Option<Entry>) -> bool {
        let a = self.cur_cyc;
        let Some(n) = next.map(|e| e.cyc) else { return false };
        if n.code != a.code {
            return true;
        }
        if a.same_action(n) {
            return false;
        }
        if a.rigid {
            // A new hole of the same cycle (anything else is inside the hole).
            a.step >= 3 && self.lim.tap_hold_in_hole
        } else {
            true
        }
    }

    /// An item that single block stops after ended.
    fn block_end(&mut self) {
        if !self.single_block {
            return;
        }
        if self.cur_cyc.code == 0 {
            self.paused = true;
        } else {
            self.sb_pending = true;
        }
    }

    /// The segment before the newest queued one, if it has not finished yet: the previous
    /// queue entry, or the running segment when the new one is the only one queued.
    fn prev_seg_mut(&mut self, back: usize) -> Option<&mut Seg> {
        let cap = self.queue.len();
        if back < self.len {
            match &mut self.queue[(self.head + self.len - 1 - back) % cap].item {
                Item::Move(s) => Some(s),
                _ => None,
            }
        } else if back == self.len {
            match &mut self.run {
                Run::Move { seg, landed: false, .. } => Some(seg),
                _ => None,
            }
        } else {
            None
        }
    }

    /// Link the newest segment to its predecessor (G64): the junction speed limit from the
    /// corner angle and the axis limits, then the backward pass.
    fn link_last(&mut self) {
        let dt = self.lim.cycle_s;
        let Some(Item::Move(new)) = self.len.checked_sub(1).map(|k| self.queue[(self.head + k) % self.queue.len()].item) else {
            return;
        };
        let amax = self.lim.amax;
        if !self.jerk_chain(new) {
            return;
        }
        self.accel_chain(new);
        let Some(prev) = self.prev_seg_mut(1) else { return };
        // The junction is crossed within one cycle: the velocity vector turns from t1 to t0
        // there, so each axis' speed jumps by v·|Δu_i|; allow half its acceleration for that
        // (the other half is the tangential ramp, see line_seg/arc_seg). One crossing per
        // cycle at most: v ≤ len/dt of the next segment.
        // The setpoints move along chords, not tangents: the chord of a cycle that ends on (or
        // starts from) an arc at the junction is turned from the arc's end tangent by up to
        // half the angle swept in the cycle, `v·dt/2r`. The cycle on the other side of the
        // junction ramps with the other segment's share (a line has no centripetal half), so
        // this turn is not covered there: count `v·(v·dt/2r)` per arc in the corner's half,
        // on that arc's plane axes: `v·|Δu_i| + v²·k_i ≤ c_i`.
        let mut k = [0.0; 3];
        for g in [prev.geom, new.geom] {
            if let Geom::Arc { ia, ib, r0, dr, .. } = g {
                let r = r0.min(r0 + dr);
                if r > 0.0 {
                    k[ia] += dt / (2.0 * r);
                    k[ib] += dt / (2.0 * r);
                }
            }
        }
        // At most MAX_JUNCTIONS crossings per cycle: every junction crossed in a cycle is
        // crossed at a speed ≤ its `vj` (see `relax`), so with `vj ≤ M·len/dt` of the segment
        // after it, n crossings in one cycle need `v·dt > (n−1)·min len ≥ (n−1)·v·dt/M`: n ≤ M.
        let h = prev.geom.len().min(new.geom.len());
        let mut v = prev.vlim.min(new.vlim).min(MAX_JUNCTIONS as f64 * new.geom.len() / dt);
        for i in 0..3 {
            let du = (new.t0[i] - prev.t1[i]).abs();
            let du = if du > 1e-12 { du } else { 0.0 };
            if du > 0.0 || k[i] > 0.0 {
                v = v.min(corner_speed(du, k[i], h, 0.5 * amax[i] * dt, dt));
            }
        }
        prev.vj = finite_or_zero(v);
    }

    /// S-curve look-ahead: all segments of a blended chain brake with one path acceleration
    /// and jerk, the chain's smallest, so that the speed and acceleration carried across any
    /// junction can always be braked within the next segment (its braking distance is the
    /// one the previous segment planned for). Lowers them on the newest segment and back
    /// along the chain; returns false, leaving everything as it was, when that would change
    /// the running segment's (its profile was planned with them): then the junction is an
    /// exact stop. Segments without a jerk limit on either side of the junction: nothing to do.
    fn jerk_chain(&mut self, new: Seg) -> bool {
        let Some(prev) = self.prev_seg_mut(1).copied() else { return true };
        let minpos = |x: f64, y: f64| if x > 0.0 && y > 0.0 { x.min(y) } else { x.max(y) };
        let (mut a, mut j) = (prev.alim.min(new.alim), minpos(prev.jlim, new.jlim));
        if !(j > 0.0) {
            return true;
        }
        let dt = self.lim.cycle_s;
        let short = |p: &Seg| p.geom.len() <= speed_cap(p).min(p.vlim) * dt;
        if short(&prev) || short(&new) {
            // A chain of short blocks (a CAM contour) brakes with the least a blended line
            // can have on this machine from its first junction on: the blocks of a contour
            // whose direction keeps turning then never lower the chain later (that would
            // reach the running block and stop at the junction).
            let l = &self.lim;
            for i in (0..3).filter(|&i| l.present[i]) {
                a = a.min(0.5 * l.amax[i]);
                j = minpos(j, l.jmax[i]);
            }
        }
        if a == new.alim && j == new.jlim && a == prev.alim && j == prev.jlim {
            return true;
        }
        // Lowering the chain's limits must not reach the running segment (back == len).
        if a != prev.alim || j != prev.jlim {
            let mut back = 1;
            loop {
                if back == self.len {
                    return false;
                }
                match self.prev_seg_mut(back + 1) {
                    Some(p) if p.vj > 0.0 => back += 1,
                    _ => break,
                }
            }
        }
        let cap = self.queue.len();
        if let Some(k) = self.len.checked_sub(1) {
            if let Item::Move(n) = &mut self.queue[(self.head + k) % cap].item {
                n.alim = a;
                n.jlim = j;
            }
        }
        let mut back = 1;
        while let Some(p) = self.prev_seg_mut(back) {
            if back > 1 && !(p.vj > 0.0) {
                break;
            }
            p.alim = a;
            p.jlim = j;
            back += 1;
        }
        true
    }

    /// Trapezoid look-ahead: in a chain of short blocks, every block brakes at least as hard
    /// as the one before it, so that `relax` can hand each block the whole room after it
    /// (see `relaxed_ext`). When the newest block's acceleration is lower, the linked blocks
    /// before it that are shorter than a cycle's travel at their speed are lowered —
    /// all or none: not if that would reach a long block, or the running block whose state
    /// could not brake for its room with the lower acceleration; the junction then keeps the
    /// rule that loses a cycle's travel, which a long block does not notice. Lowering a
    /// block's acceleration keeps its own `ext` valid (see `relaxed_ext`). Stops at the
    /// first block already as low. They are lowered to the least a blended line can have on
    /// this machine (or the new block's, if less), so that the next blocks of a contour whose
    /// direction keeps turning do not lower them again: each block is lowered at most twice,
    /// and `push` stays O(1) amortised.
    fn accel_chain(&mut self, new: Seg) {
        let dt = self.lim.cycle_s;
        let a = new.alim;
        if new.jlim > 0.0 || !(a > 0.0) {
            return;
        }
        let lowers = |p: &Seg| p.alim > a && p.jlim == 0.0;
        let floor = self.blend_floor().min(a);
        let short = |p: &Seg| p.geom.len() <= speed_cap(p).min(p.vlim) * dt;
        let len = self.len;
        let mut back = 1;
        // Block 1 is being linked to `new`; older ones only along the linked chain.
        while let Some(p) = self.prev_seg_mut(back) {
            if !lowers(p) || (back > 1 && !(p.vj > 0.0)) {
                break;
            }
            if !short(p) {
                return;
            }
            if back == len {
                // The running block, lowered only if its state can still brake for its room
                // with the lower acceleration (`profile::next_speed` then stays within a·dt).
                let Run::Move { seg, s, v, .. } = self.run else { return };
                let dv = floor * dt;
                if !(dt * profile::g(v - dv, dv) <= seg.geom.len() - s + seg.ext) {
                    return;
                }
            }
            back += 1;
        }
        for b in 1..back {
            if let Some(p) = self.prev_seg_mut(b) {
                p.alim = floor;
            }
        }
        self.relax_pending = self.relax_pending.max(back);
    }

    /// Backward pass over the linked chains, from the newest segment: the speed at which each
    /// junction may be crossed (≤ its corner limit, and low enough that the rest of the chain
    /// can still be braked within the acceleration), expressed as the segment's `ext`.
    ///
    /// Run once per cycle (at the start of `step`) over what was pushed since, not once per
    /// push: a chain of tiny blocks within braking distance of the end of the queue is
    /// hundreds of blocks long, and every push grows the `ext` of all of them (at 0.01 mm and
    /// F6000, 20 pushes a cycle would each walk 500 blocks). It walks every block pushed since
    /// the last pass, then back while an `ext` grows — far enough in DISTANCE: the room of the
    /// whole queued chain, ending at rest on the last queued block, whatever their number.
    /// At most the queue's length, no allocation.
    fn relax(&mut self) {
        let pending = std::mem::take(&mut self.relax_pending);
        if pending == 0 {
            return;
        }
        let dt = self.lim.cycle_s;
        // (length, ext, dv, feed) of the segment after the one looked at; None: not a move.
        let mut next: Option<(f64, f64, f64, f64)> = None;
        for back in 0..=self.len {
            let Some(prev) = self.prev_seg_mut(back) else {
                if back >= pending {
                    break;
                }
                next = None;
                continue;
            };
            let mut grew = false;
            if let (Some((nlen, next_ext, ndv, next_cap)), true) = (next, prev.vj > 0.0) {
                let ext = relaxed_ext(prev, nlen + next_ext, ndv, next_cap, dt);
                if ext > prev.ext {
                    prev.ext = ext;
                    grew = true;
                }
            }
            if !grew && back >= pending {
                break;
            }
            next = Some((prev.geom.len(), prev.ext, prev.alim * dt, speed_cap(prev)));
        }
    }

    /// Axis `i` (X/Y/Z) may be commanded to `v`: finite, configured, inside its travel.
    /// `what` names the point in the message ("end point", "arc").
    fn check_axis(&self, i: usize, v: f64, what: &str) -> Result<(), Alarm> {
        let name = AXIS_NAMES[i];
        if !v.is_finite() {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("{name} {what} is not a finite number ({v})")));
        }
        if !self.lim.present[i] {
            if (v - self.plan_end[i]).abs() > 1e-9 {
                return Err(Alarm::new(alarms::TRAVEL, format!("axis {name} is not configured on this machine; remove {name} from the program")));
            }
            return Ok(());
        }
        let (lo, hi) = self.lim.travel[i];
        if v < lo || v > hi {
            let radius = if i == AX_X { " (radius)" } else { "" };
            return Err(Alarm::new(
                alarms::TRAVEL,
                format!("{name} {what} {v:.4} mm{radius} is beyond the travel limits [{lo}, {hi}]; correct the program or the work offset"),
            ));
        }
        Ok(())
    }

    fn check_end(&self, end: &Pos) -> Result<[f64; 3], Alarm> {
        let e = xyz(end);
        for (i, v) in e.iter().enumerate() {
            self.check_axis(i, *v, "end point")?;
        }
        check_c(end.c)?;
        if self.plan_c.is_some_and(|c| c != end.c) {
            return Err(Alarm::new(
                alarms::UNSUPPORTED,
                "C-axis (Cs contour) positioning is not supported by this motion layer yet; remove the C word",
            ));
        }
        Ok(e)
    }

    fn check_feed(&self, f: &Feed) -> Result<Speed, Alarm> {
        // An F below the least input increment (0.001 mm/min, 0.0001 mm/rev, as Fanuc's IS-B)
        // is zero: it would run for ever (F0.0001 mm/min: 18 minutes a micrometre).
        let f = match *f {
            Feed::PerMin(v) if v.abs() < 0.001 => Feed::PerMin(0.0),
            Feed::PerRev(v) if v.abs() < 0.0001 => Feed::PerRev(0.0),
            f => f,
        };
        match f {
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
                format!("feed rate must be > 0 (at least F0.001 mm/min or F0.0001 mm/rev), got F{v}; program an F word before the cutting move"),
            )),
        }
    }

    fn thread_seg(&self, end: &Pos, lead: f64, start_angle: f64, lead_inc: f64, continuous: bool) -> Result<ThreadSeg, Alarm> {
        if !(lead.is_finite() && lead > 0.0) {
            return Err(Alarm::new(alarms::FEED_ZERO, format!("thread lead must be > 0, got F{lead}; correct the F/I word")));
        }
        if !start_angle.is_finite() {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("thread start angle is not a finite number ({start_angle})")));
        }
        if !lead_inc.is_finite() {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("G34 lead change is not a finite number ({lead_inc})")));
        }
        if !self.plan_spindle_on {
            return Err(Alarm::new(
                alarms::PER_REV_SPINDLE_STOPPED,
                "thread cutting with the spindle stopped: start the spindle (M03/M04 S…) before the thread",
            ));
        }
        let end = self.check_end(end)?;
        let g = geom::line(self.plan_end, end);
        let delta = [end[0] - self.plan_end[0], end[1] - self.plan_end[1], end[2] - self.plan_end[2]];
        let len = g.len();
        if !(len > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, "thread of zero length: correct the end point"));
        }
        // The lead is along the long axis (Fanuc: Z unless the taper is steeper than 45°).
        let u_long = delta.iter().fold(0.0f64, |m, d| m.max(d.abs())) / len;
        let lead_path = lead / u_long;
        // G34: after n revolutions the long axis has gone L·n + K·n²/2 and the lead is L + K·n,
        // so at the end (long distance D) the lead is √(L² + 2·K·D).
        let disc = lead * lead + 2.0 * lead_inc * len * u_long;
        let lead_end = disc.max(0.0).sqrt();
        if lead_inc != 0.0 && !(disc > 0.0 && lead_end > 1e-6) {
            return Err(Alarm::new(
                alarms::ILLEGAL_LEAD,
                format!(
                    "G34 lead F{lead} changing by K{lead_inc} per revolution reaches 0 before the end of the thread; shorten the thread or reduce the decrement K"
                ),
            ));
        }
        let lead_path_max = lead.max(lead_end) / u_long;
        let s = self.line_seg(g, Speed::Rapid, false);
        if let Some(rpm) = self.plan_rpm {
            let v = lead_path_max * rpm / 60.0;
            if v > s.vlim {
                return Err(Alarm::new(
                    alarms::THREAD_TOO_FAST,
                    format!(
                        "thread lead {:.4} mm × S{rpm} needs {:.0} mm/min, more than the axes' {:.0} mm/min; lower the spindle speed",
                        lead_path_max * u_long,
                        v * 60.0,
                        s.vlim * 60.0
                    ),
                ));
            }
        }
        Ok(ThreadSeg {
            geom: g,
            lead_path,
            k_path: lead_inc / u_long,
            u_long,
            long_axis: (0..3).fold(AX_Z, |b, i| if delta[i].abs() > delta[b].abs() { i } else { b }),
            lead_path_max,
            continuous,
            start_angle,
            vlim: s.vlim,
            alim: s.alim,
        })
    }

    fn tap_seg(&self, end: &Pos, lead: f64, rpm: f64) -> Result<TapSeg, Alarm> {
        if !(lead.is_finite() && lead != 0.0) {
            return Err(Alarm::new(alarms::FEED_ZERO, format!("tap lead must be non-zero, got F{lead}; correct the F word")));
        }
        if !(rpm.is_finite() && rpm > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("tapping spindle speed must be > 0, got S{rpm}")));
        }
        if !self.lim.present[AX_S] {
            return Err(Alarm::new(alarms::UNSUPPORTED, "rigid tapping needs a spindle axis in the config"));
        }
        let e = self.check_end(end)?;
        // The tapping axis is the one axis that moves (G84: Z, G88: X; X is a radius and the
        // lead is along it). A zero-length stroke stays on the hole's axis.
        let mut moved = (0..3).filter(|&i| e[i] != self.plan_end[i]);
        let axis = match (moved.next(), moved.next()) {
            (Some(a), None) => a,
            (None, _) => self.plan_tap.map_or(AX_Z, |(a, _, _)| a),
            _ => {
                return Err(Alarm::new(
                    alarms::BAD_VALUE,
                    "a rigid tap stroke moves the tapping axis only (Z for G84, X for G88): position the other axes before the tap",
                ))
            }
        };
        let name = AXIS_NAMES[axis];
        let l = &self.lim;
        let p0 = self.plan_end[axis];
        // Out of the hole: the stroke runs against the direction of the hole's first stroke.
        let retract = self.plan_tap.is_some_and(|(a, _, din)| a == axis && (e[axis] - p0) * din < 0.0);
        let per_deg = lead.abs() / 360.0; // mm of the tapping axis per spindle degree
                                          // Feasibility before anything moves: the axis must be able to follow the spindle at S.
        let v = rpm * lead.abs() / 60.0;
        if !(v <= l.vmax[axis] * (1.0 + 1e-9)) {
            return Err(Alarm::new(
                alarms::THREAD_TOO_FAST,
                format!(
                    "rigid tap lead {:.4} mm × S{rpm} needs {:.0} mm/min of {name}, more than {name}'s {:.0} mm/min; lower S",
                    lead.abs(),
                    v * 60.0,
                    l.vmax[axis] * 60.0
                ),
            ));
        }
        if !(rpm * 6.0 <= l.vmax[AX_S] * (1.0 + 1e-9)) {
            return Err(Alarm::new(
                alarms::THREAD_TOO_FAST,
                format!("rigid tap S{rpm} is above the spindle's {:.0} rpm; lower S", l.vmax[AX_S] / 6.0),
            ));
        }
        // Matched acceleration: spindle (its limit, No.5261 or on the way out No.5271) and the
        // tapping axis on one profile, the lower of the two.
        let sp_acc = if retract && l.tap_retract_accel.is_finite() { l.tap_retract_accel } else { l.tap_accel };
        let alim = l.amax[axis].min(l.amax[AX_S].min(sp_acc) * per_deg);
        if !(alim > 0.0 && alim.is_finite()) {
            return Err(Alarm::new(
                alarms::BAD_VALUE,
                format!("rigid tap: no usable acceleration for {name} and the spindle; set max_accel of both (and No.5261)"),
            ));
        }
        let vlim = l.vmax[axis].min(l.vmax[AX_S] * per_deg);
        let jlim = if l.tap_bell_s > 0.0 { alim / l.tap_bell_s } else { 0.0 };
        Ok(TapSeg { axis, p0, p1: e[axis], lead, v: v.min(vlim), vlim, alim, jlim, retract })
    }

    /// G92.1: the feed axes to `end` and the spindle through `end.c − c_start` on one profile.
    /// Feasibility before motion: the commanded rpm × lead must be within the feed axes' and
    /// the spindle's speed limits, and the spindle travel must match the lead.
    fn rigid_seg(&self, end: &Pos, lead: f64, rpm: f64) -> Result<RigidSeg, Alarm> {
        if !(lead.is_finite() && lead != 0.0) {
            return Err(Alarm::new(alarms::FEED_ZERO, format!("G92.1 lead must be non-zero, got F{lead}; correct the F word")));
        }
        if !(rpm.is_finite() && rpm > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("G92.1 spindle speed must be > 0, got S{rpm}")));
        }
        if !self.lim.present[AX_S] {
            return Err(Alarm::new(alarms::UNSUPPORTED, "G92.1 needs a spindle axis (Cs) in the config"));
        }
        let e = xyz(end);
        for (i, v) in e.iter().enumerate() {
            self.check_axis(i, *v, "end point")?;
        }
        if !end.c.is_finite() {
            return Err(Alarm::new(alarms::BAD_VALUE, format!("G92.1 spindle end angle is not a finite number ({})", end.c)));
        }
        let g = geom::line(self.plan_end, e);
        let len = g.len();
        if !(len > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, "G92.1 stroke of zero length: correct the end point"));
        }
        let delta = [e[0] - self.plan_end[0], e[1] - self.plan_end[1], e[2] - self.plan_end[2]];
        let long = delta.iter().fold(0.0f64, |m, d| m.max(d.abs()));
        // The turn the lead asks for; when the start angle is known it must agree with end.c.
        let turn = lead.signum() * 360.0 * long / lead.abs();
        let dc = match self.plan_c {
            Some(c0) => {
                let dc = end.c - c0;
                if (dc - turn).abs() > 1e-6 * turn.abs().max(1.0) {
                    return Err(Alarm::new(
                        alarms::BAD_VALUE,
                        format!("G92.1 spindle travel {dc:.3}° does not match the lead ({turn:.3}° for {long:.4} mm at F{lead})"),
                    ));
                }
                dc
            }
            None => turn,
        };
        let l = &self.lim;
        let line = self.line_seg(g, Speed::Rapid, false);
        let per_deg = len / dc.abs(); // path mm per spindle degree
        let vlim = line.vlim.min(l.vmax[AX_S] * per_deg);
        let alim = line.alim.min(l.amax[AX_S].min(l.tap_accel) * per_deg);
        let v = rpm * 6.0 * per_deg;
        if !(v <= vlim * (1.0 + 1e-9)) {
            return Err(Alarm::new(
                alarms::THREAD_TOO_FAST,
                format!(
                    "G92.1 lead {lead} mm × S{rpm} needs {:.0} mm/min of path, more than the axes and spindle allow ({:.0} mm/min); lower S",
                    v * 60.0,
                    vlim * 60.0
                ),
            ));
        }
        Ok(RigidSeg { geom: g, dc, plen: len, v, vlim, alim, u_long: long / len })
    }

    /// A rapid that also turns the spindle to `end.c` (Cs positioning, e.g. G92.1's start
    /// angle): the spindle is braked, then moved in position with the feed axes on one linear
    /// profile, every axis within its limits.
    fn c_rapid_seg(&self, end: &Pos, c0: f64) -> Result<RigidSeg, Alarm> {
        if !self.lim.present[AX_S] {
            return Err(Alarm::new(alarms::UNSUPPORTED, "C positioning needs a spindle axis (Cs) in the config; remove the C word"));
        }
        let e = xyz(end);
        for (i, v) in e.iter().enumerate() {
            self.check_axis(i, *v, "end point")?;
        }
        check_c(end.c)?;
        let dc = end.c - c0;
        let g = geom::line(self.plan_end, e);
        let line = self.line_seg(g, Speed::Rapid, false);
        let l = &self.lim;
        let len = g.len();
        let (plen, vlim, alim) = if len > 0.0 {
            let per_deg = len / dc.abs();
            (len, line.vlim.min(l.vmax[AX_S] * per_deg), line.alim.min(l.amax[AX_S] * per_deg))
        } else {
            (dc.abs(), l.vmax[AX_S], l.amax[AX_S])
        };
        let vlim = finite_or_zero(vlim);
        Ok(RigidSeg { geom: g, dc, plen, v: vlim, vlim, alim: finite_or_zero(alim), u_long: 0.0 })
    }

    fn check_spindle(&self, c: &SpindleCmd) -> Result<SpindleCmd, Alarm> {
        let bad = |what: &str, v: f64| Alarm::new(alarms::BAD_VALUE, format!("spindle {what} must be a finite number ≥ 0, got {v}"));
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

    /// A line segment. `blended`: a junction at either end may be passed without stopping, so
    /// half of each axis' acceleration is kept for the velocity change at the corner.
    fn line_seg(&self, g: Geom, speed: Speed, blended: bool) -> Seg {
        let (mut v, mut a, mut j) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
        if let Geom::Line { delta, len, .. } = g {
            if len > 0.0 {
                for i in 0..3 {
                    let u = delta[i].abs() / len;
                    if u > 0.0 {
                        v = v.min(self.lim.vmax[i] / u);
                        a = a.min(self.lim.amax[i] / u);
                        if self.lim.jmax[i] > 0.0 {
                            j = j.min(self.lim.jmax[i] / u);
                        }
                    }
                }
            }
        }
        let a = if blended { (0.5 * a).min(self.blend_floor()) } else { a };
        let mut s = seg(g, speed, v, a);
        s.jlim = finite_or_zero(j);
        s
    }

    /// Path acceleration of a blended segment, at most: half the least axis acceleration of
    /// the machine, whatever the segment's direction. A cycle that crosses junctions moves
    /// along a mix of the segments' directions (its mean direction `ū`, `|ū_i| ≤ 1`), while
    /// its speed step is the segment's where it started: only a bound that holds for every
    /// direction keeps each axis' share of that step `Δv·|ū_i|` within the half of its
    /// acceleration left by the corner rule. (Per direction, `amax_i/|u_i|`, a diagonal line
    /// ramped 41 % harder and a cycle crossing from it onto an axis-parallel block exceeded
    /// that axis' limit.)
    fn blend_floor(&self) -> f64 {
        (0..3).filter(|&i| self.lim.present[i]).map(|i| 0.5 * self.lim.amax[i]).fold(f64::INFINITY, f64::min)
    }

    /// An arc segment: tangential and centripetal acceleration share each plane axis' limit
    /// (0.5 + 0.45 with exact stops; 0.25 + 0.25 when blended, leaving 0.5 for the corner).
    fn arc_seg(&self, end: [f64; 3], center: [f64; 3], cw: bool, plane: Plane, speed: Speed, blended: bool) -> Result<Seg, Alarm> {
        let axes = match plane {
            Plane::Xy => (AX_X, AX_Y, AX_Z),
            Plane::Zx => (AX_Z, AX_X, AX_Y),
            Plane::Yz => (AX_Y, AX_Z, AX_X),
        };
        if center.iter().any(|c| !c.is_finite()) {
            return Err(Alarm::new(alarms::BAD_VALUE, "arc centre is not a finite number"));
        }
        let Some((g, r0, r1)) = geom::arc(self.plan_end, end, center, axes, cw) else {
            return Err(Alarm::new(alarms::BAD_VALUE, "arc with zero radius: the start or end point is the centre; correct R or I/J/K"));
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
        // Not only the end point: the arc's outermost points (where it crosses the plane axes'
        // directions from the centre) must stay inside the travel too.
        if let Geom::Arc { ca, cb, r0, dr, th0, sweep, .. } = g {
            let r = r0.max(r0 + dr);
            for k in 0..4 {
                let ang = k as f64 * std::f64::consts::FRAC_PI_2;
                let rel = if sweep >= 0.0 { (ang - th0).rem_euclid(TAU) } else { (th0 - ang).rem_euclid(TAU) };
                if rel <= sweep.abs() {
                    match k {
                        0 => self.check_axis(ia, ca + r, "arc")?,
                        1 => self.check_axis(ib, cb + r, "arc")?,
                        2 => self.check_axis(ia, ca - r, "arc")?,
                        _ => self.check_axis(ib, cb - r, "arc")?,
                    }
                }
            }
        }
        let l = &self.lim;
        let a_plane = l.amax[ia].min(l.amax[ib]);
        let rmin = r0.min(r1);
        let len = g.len();
        let uc = if let Geom::Arc { dc, .. } = g { dc.abs() / len.max(1e-300) } else { 0.0 };
        let (tangential, centripetal) = if blended { (0.25, 0.25) } else { (0.5, 0.45) };
        let mut v = l.vmax[ia].min(l.vmax[ib]);
        v = v.min((centripetal * a_plane * rmin).sqrt());
        v = v.min((8.0 * rmin * l.chord_tol).sqrt() / l.cycle_s);
        let mut a = tangential * a_plane;
        if uc > 0.0 {
            v = v.min(l.vmax[ic] / uc);
            a = a.min(tangential * l.amax[ic] / uc);
        }
        if blended {
            a = a.min(self.blend_floor());
        }
        // S-curve: the plane axes' jerk is shared like their acceleration: half for the
        // tangential profile, half for the centripetal acceleration turning with the tool
        // (v³/r² at constant speed, which limits v).
        let j_plane = match (l.jmax[ia] > 0.0, l.jmax[ib] > 0.0) {
            (true, true) => l.jmax[ia].min(l.jmax[ib]),
            (true, false) => l.jmax[ia],
            (false, true) => l.jmax[ib],
            (false, false) => 0.0,
        };
        let mut j = if j_plane > 0.0 { 0.5 * j_plane } else { f64::INFINITY };
        if j_plane > 0.0 {
            v = v.min((0.5 * j_plane * rmin * rmin).cbrt());
        }
        if uc > 0.0 && l.jmax[ic] > 0.0 {
            j = j.min(0.5 * l.jmax[ic] / uc);
        }
        let mut s = seg(g, speed, v, a);
        s.jlim = finite_or_zero(j);
        Ok(s)
    }

    fn peek(&self) -> Option<Entry> {
        (self.len > 0).then(|| self.queue[self.head])
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
                let n = if r > 1e-9 { 1000.0 * css / (TAU * r) } else { f64::INFINITY };
                // The G50 clamp holds after the override.
                (n * self.spindle_ovr).min(self.sp_max)
            }
            None => self.sp_rpm * self.spindle_ovr,
        };
        let target = if self.stopping { 0.0 } else { self.sp_dir * mag.min(machine_max) };
        self.sp_target = target;
        // In polygon turning the tool spindle must keep up with the ratio (polygon.rs).
        let step = self.lim.amax[AX_S].min(self.tool.work_accel_cap()).min(self.sp_cap()) / 6.0 * dt;
        let d = target - self.sp_cur;
        self.sp_cur = if d.abs() <= step { target } else { self.sp_cur + step.copysign(d) };
        self.pos[AX_S] += self.sp_cur * 6.0 * dt;
    }

    /// Feed hold in force now. With No.5200#6 = 0 it waits while the tool is in a tapped hole
    /// (the tap would break): the strokes and the dwell at the bottom run on to the R point.
    fn hold_now(&self) -> bool {
        self.held && (!self.in_hole || self.lim.tap_hold_in_hole) && !self.flex_tap_defers_hold()
    }

    /// 004 §2.22 note 4: feed hold in actions 3–5 of a (flexible) G84/G88 does not stop the
    /// tap; it takes effect when the tool is back at R (the end of action 5).
    fn flex_tap_defers_hold(&self) -> bool {
        let c = self.cur_cyc;
        c.flex_tap_in_hole()
            && (self.run != Run::None || self.peek().is_some_and(|e| e.cyc.flex_tap_in_hole() && e.cyc.code == c.code && e.cyc.step >= c.step))
    }

    /// The commanded path speed (mm/s) of a segment this cycle.
    fn v_cmd(&self, seg: &Seg, fb: &Feedback) -> f64 {
        if (self.held && !self.flex_tap_defers_hold()) || self.stopping {
            return 0.0;
        }
        let v = match seg.speed {
            // F0 (override 0) is No.1421's rate, as on a Fanuc; the other steps a share.
            Speed::Rapid if self.rapid_ovr == 0.0 => self.lim.rapid_f0.min(seg.vlim),
            Speed::Rapid => seg.vlim * self.rapid_ovr,
            Speed::PerMin(f) => (f * self.feed_ovr).min(self.lim.feed_clamp),
            Speed::PerRev(r) if self.cur_cyc.flex_tap_in_hole() => self.flex_tap_v(r, fb),
            Speed::PerRev(r) => {
                let rpm = if fb.spindle_rpm.is_finite() { fb.spindle_rpm.abs() } else { 0.0 };
                (r * rpm / 60.0 * self.feed_ovr).min(self.lim.feed_clamp)
            }
        };
        v.min(seg.vlim)
    }

    /// A flexible tap stroke (004 §2.22.3, manual 000 No.5275/5276): the tapping axis follows
    /// the spindle encoder, one lead per revolution, whatever the feed override (note 3).
    /// No.5275: the axis lags the encoder by that many cycles; compensated by following the
    /// speed the encoder will read that many cycles on (extrapolated from the last change).
    /// No.5276: the stroke out of the hole (action 5) waits until the encoder reads the
    /// reversed spindle at that speed.
    fn flex_tap_v(&self, lead: f64, fb: &Feedback) -> f64 {
        let now = if fb.spindle_rpm.is_finite() { fb.spindle_rpm } else { 0.0 };
        if self.cur_cyc.step == 5 && self.lim.flex_retract_rpm > 0.0 && now * self.sp_dir < self.lim.flex_retract_rpm {
            return 0.0;
        }
        let ahead = now + self.lim.flex_lag_cycles * (now - self.fb_rpm_prev);
        (lead * ahead.abs() / 60.0).min(self.lim.feed_clamp)
    }

    /// Advance one cycle. Never allocates; never panics; bounded (see the module doc).
    ///
    /// Order: relax and watch the sync error, run the spindle's own ramp (unless a stroke
    /// drives it as a position axis), take the next queued item when nothing runs
    /// ([`Motion::take_next`]), advance what runs ([`Motion::advance`]), drop the rest of the
    /// program once a controlled stop is at rest, then the sync correction and the set-point.
    pub fn step(&mut self, fb: &Feedback) -> Setpoint {
        let prev = self.pos;
        self.relax();
        self.monitor_sync(fb);
        self.govern_spindle(fb);
        // In a rigid-tap stroke the spindle is a position axis driven by the tap profile.
        if !self.in_sync_stroke() && !matches!(self.run, Run::Polar(r) if r.holds_spindle()) {
            self.step_spindle(self.lim.cycle_s);
        }
        let event = self.take_next();
        let path_v = self.advance(fb, &prev);
        // At rest in the hole: measured too (`monitor_sync`). A stroke's first cycle stays
        // unmeasured as before — trimmed on, the return's start was worse cut (delay1 5.2 → 7.4 µm).
        let resting = matches!(self.run, Run::None | Run::Dwell { .. } | Run::Tap { theta0: None, .. });
        if self.in_hole && resting && self.tap_ref.is_some() {
            self.monitor.watch(true);
        }
        if self.stopping && self.run == Run::None {
            self.stopped_at_rest();
        }
        self.setpoint(fb, &prev, path_v, event)
    }

    /// A spindle out of torque (`sync::governor`): from then on every ramp, tap and G92.1
    /// stroke plans with 80 % of what it managed — the running stroke too, where it can still
    /// brake at that rate. The manual is silent; a SINUMERIK 828D plans a rigid tap within
    /// the spindle's acceleration characteristic (MD35200), which is found here at run time; a
    /// Fanuc 0i-TF would stop with SV0411 (excess error in motion).
    fn govern_spindle(&mut self, fb: &Feedback) {
        let sent = self.answered(0)[AX_S];
        // Every cycle: it takes the commanded acceleration from consecutive set-points.
        if let Some(a) = self.sp_margin.update(sent, fb.spindle_torque, fb.spindle_torque_max, self.lim.cycle_s) {
            self.cap_spindle_accel(a, true);
        }
        if fb.age[AX_S] != 0 {
            return;
        }
        let actual = spindle_at_slot(fb, self.lim.cycle_s);
        if let Some(a) = self.sp_gov.update(sent, actual, self.lim.cycle_s, self.lim.sp_lag_judge) {
            self.cap_spindle_accel(a, false);
        }
        if let Some(a) = self.sp_overload.update(sent, fb.spindle_torque, self.lim.cycle_s) {
            self.sp_heat_next = self.sp_heat_next.min(a);
            // A tap or G92.1 stroke under way keeps its plan (a change of acceleration within
            // it turns the spindle's and the axis' lags differently) unless the amplifier is
            // near its trip; the next stroke plans with it.
            if self.sp_overload.urgent() || !self.in_sync_stroke() {
                self.sp_heat_cap = self.sp_heat_next;
            }
        }
    }

    /// Plan the spindle with `SP_ACCEL_MARGIN` of `a` (deg/s²) from now on, where that is
    /// lower than before; `by_torque`: it gave `a` at its torque limit (else: it managed `a`).
    fn cap_spindle_accel(&mut self, a: f64, by_torque: bool) {
        if SP_ACCEL_MARGIN * a < self.sp_accel_cap {
            self.sp_accel_cap = SP_ACCEL_MARGIN * a;
            self.sp_cap_by_torque = by_torque;
        }
    }

    /// A rigid tap or G92.1 stroke drives the spindle as a position axis.
    fn in_sync_stroke(&self) -> bool {
        matches!(self.run, Run::Tap { theta0: Some(_), .. } | Run::Rigid { theta0: Some(_), .. })
    }

    /// The spindle acceleration every ramp, tap and G92.1 stroke plans within (deg/s²): what
    /// its torque managed and what its amplifier's overload allows.
    fn sp_cap(&self) -> f64 {
        self.sp_accel_cap.min(self.sp_heat_cap)
    }

    /// The set-point this cycle's feedback answers (paired over the feedback delay), or the
    /// one `back` cycles before it.
    fn answered(&self, back: usize) -> [f64; N_AXES] {
        let fd = self.lim.feedback_delay.clamp(1, HIST - 3);
        self.hist[(self.hist_k + HIST - (fd - 1) - back) % HIST]
    }

    /// A stroke's path acceleration `alim` (and jerk `jlim`) within what the spindle was found
    /// to manage, `per_deg` path units per spindle degree — where it can still brake at the
    /// lower rate from speed `v` and acceleration `a0` within `d` (else it keeps its plan).
    /// With a jerk limit the braking takes its jerk phases too: judged on v²/2a alone, a cap
    /// found while still accelerating (S3000, a 0.24 kg·m² spindle, the SYNC 0.3 ms late)
    /// left the stroke unable to stop and it reached the bottom at 750 rpm.
    fn capped_accel(&self, alim: f64, jlim: f64, per_deg: f64, v: f64, a0: f64, d: f64) -> (f64, f64) {
        let a = alim.min(self.sp_cap() * per_deg);
        if !(a < alim && a > 0.0) {
            return (alim, jlim);
        }
        let j = jlim * a / alim;
        let brake = if j > 0.0 { profile::stop_dist(v, a0, a, j) } else { v * v / (2.0 * a) };
        if brake <= d {
            (a, j)
        } else {
            (alim, jlim)
        }
    }

    /// When nothing runs: the single-block stop, then the next queued item started (its
    /// event, if it is one, returned for the set-point).
    fn take_next(&mut self) -> Event {
        let mut event = Event::None;
        if self.run == Run::None && self.sb_pending && !self.stopping && self.single_block_stop(self.peek()) {
            self.sb_pending = false;
            self.paused |= self.single_block;
        }
        if self.run == Run::None && !self.stopping && !self.hold_now() && !self.paused && !self.fin_wait {
            if let Some(e) = self.pop() {
                self.line = e.line;
                self.cur_cyc = e.cyc;
                // A spindle command or code inside an action (a clamp M code, M05 at the
                // bottom) is part of it: the single-block decision waits for the next block.
                self.sb_pending &= matches!(e.item, Item::Spindle(_) | Item::Event(Event::Aux { .. } | Event::None));
                let chain = self.thread_chain.take();
                self.thread_chain = chain.filter(|_| matches!(e.item, Item::Thread(_)));
                match e.item {
                    Item::Move(seg) => {
                        self.in_hole = false;
                        self.path_a = 0.0;
                        self.run = Run::Move { seg, s: 0.0, v: 0.0, landed: false };
                    }
                    Item::Dwell(n) => self.run = Run::Dwell { left: n },
                    Item::Thread(seg) => {
                        self.in_hole = false;
                        // A continuous segment pushed too late to be crossed into on the fly
                        // still keeps the lock of the thread that just ended.
                        let sync = match self.thread_chain {
                            Some((t, len)) if seg.continuous => t.continue_with(len, seg.lead_path, seg.k_path),
                            _ => None,
                        };
                        self.takeup = if sync.is_none() && !seg.continuous { self.take_up_len(&seg).map(|d| (0, d)) } else { None };
                        if sync.is_none() {
                            self.thread_angle.restart();
                        }
                        self.run = Run::Thread { seg, sync, s: 0.0, v: 0.0, landed: false };
                    }
                    Item::Tap(seg) => self.run = Run::Tap { seg, theta0: None, s: 0.0, v: 0.0, landed: false },
                    Item::Rigid(seg) => {
                        self.in_hole = false;
                        self.run = Run::Rigid { seg, theta0: None, s: 0.0, v: 0.0, landed: false };
                    }
                    Item::Spindle(c) => self.apply_spindle(c),
                    Item::Polar(seg) => {
                        self.in_hole = false;
                        self.run = Run::Polar(polar::PolarRun::new(seg));
                    }
                    Item::Polygon(c) => self.apply_polygon(c),
                    Item::Event(ev) => {
                        event = ev;
                        match ev {
                            Event::Stop { optional: false } => self.paused = true,
                            Event::Stop { optional: true } => self.paused = self.optional_stop,
                            // M30/M02 reset polygon turning (G50.2 is the reset state) and
                            // stop the spindle, as a Fanuc 0i-TF's standard ladder does at
                            // the program's end (manual 004 §2.19 example: "M30; 程序结束,
                            // 关主轴、冷却液"); the coolant is the cycle loop's (`control::io`).
                            Event::End => {
                                self.tool.unlock();
                                self.sp_dir = 0.0;
                            }
                            _ => {}
                        }
                    }
                }
            }
        }
        event
    }

    /// Advance what runs by one cycle; the path speed of the cycle, mm/s.
    fn advance(&mut self, fb: &Feedback, prev: &[f64; N_AXES]) -> f64 {
        match self.run {
            _ if self.follow.is_some() => self.step_follow(fb, prev),
            Run::None => 0.0,
            Run::Move { landed: true, .. } => {
                // Exact stop: one cycle at rest on the end point.
                self.run = Run::None;
                self.block_end();
                0.0
            }
            Run::Move { seg, s, v, landed: false } => self.step_move(seg, s, v, fb),
            Run::Dwell { left } => {
                self.step_dwell(left);
                0.0
            }
            Run::Thread { landed: true, .. } => {
                self.run = Run::None;
                self.block_end();
                0.0
            }
            Run::Thread { seg, sync, s, v, landed: false } => self.step_thread(fb, seg, sync, s, v),
            Run::Rigid { landed: true, .. } => {
                // At rest on the end, spindle stopped in position (no run-out).
                self.sp_cur = 0.0;
                self.run = Run::None;
                self.block_end();
                0.0
            }
            Run::Rigid { seg, theta0: None, .. } => {
                self.rigid_entry(seg, fb);
                0.0
            }
            Run::Rigid { seg, theta0: Some(th0), s, v, landed: false } => self.step_rigid(seg, th0, (s, v), prev),
            Run::Polar(r) => self.step_polar(r),
            Run::Tap { seg, theta0, landed: true, .. } => {
                self.tap_landed(&seg, theta0);
                0.0
            }
            Run::Tap { seg, theta0: None, .. } => {
                self.tap_entry(seg, fb);
                0.0
            }
            Run::Tap { seg, theta0: Some(r), s, v, landed: false } => self.step_tap(seg, r, (s, v), prev),
        }
    }

    /// A feed or rapid move: one cycle of its speed profile (S-curve or trapezoid), across
    /// junctions where the look-ahead blends.
    fn step_move(&mut self, mut seg: Seg, s: f64, v: f64, fb: &Feedback) -> f64 {
        let len = seg.geom.len();
        let d = len - s;
        let dt = self.lim.cycle_s;
        let dv = seg.alim * dt;
        let jerk = seg.jlim > 0.0 && seg.alim > 0.0;
        // Single block: end this block at rest if it can still brake for its end point
        // from here (dropping the look-ahead extension is safe only then); otherwise
        // blend on and stop at the end of a later block.
        let can_stop = if jerk { profile::stop_dist(v, self.path_a, seg.alim, seg.jlim) <= d } else { profile::v_allowed(d, dv, dt) >= v - dv };
        if self.single_block && seg.ext > 0.0 && can_stop {
            seg.ext = 0.0;
        }
        // `adv`: the distance of this cycle (the trapezoid's `nv·dt`; the S-curve's
        // integral of its speed over the cycle, `nv` being the speed at its end).
        let (nv, adv) = if jerk {
            let (nv, na, adv) = profile::next_state(v, self.path_a, self.v_cmd(&seg, fb), d + seg.ext, seg.alim, seg.jlim, dt);
            self.path_a = na;
            (nv, adv)
        } else {
            let nv = profile::next_speed(v, self.v_cmd(&seg, fb), d + seg.ext, dv, dt);
            self.path_a = 0.0;
            (nv, nv * dt)
        };
        let reach = d - adv <= 1e-9;
        // The path speed of this cycle (the trapezoid's exactly `nv`).
        let pv = if jerk { adv / dt } else { nv };
        if let Some((next, s2)) = (reach && seg.ext > 0.0).then(|| self.cross(adv - d)).flatten() {
            let p = next.geom.at(s2);
            self.pos[..3].copy_from_slice(&p);

            self.run = Run::Move { seg: next, s: s2, v: nv, landed: false };
            pv
        } else {
            let (s2, landed) = if reach { (len, true) } else { (s + adv, false) };
            let p = seg.geom.at(s2);
            self.pos[..3].copy_from_slice(&p);

            // Stopping and at rest (this cycle did not move): done.
            self.run = if self.stopping && nv == 0.0 && !landed { Run::None } else { Run::Move { seg, s: s2, v: nv, landed } };
            if landed {
                d / dt
            } else {
                pv
            }
        }
    }

    /// A dwell (or a canned cycle's wait): counts down unless held; a stop ends it.
    fn step_dwell(&mut self, left: u64) {
        if self.stopping {
            self.run = Run::None;
        } else if !self.hold_now() {
            let left = left.saturating_sub(1);
            self.run = if left == 0 { Run::None } else { Run::Dwell { left } };
            if left == 0 && self.cur_cyc.code > 0 {
                self.block_end();
            } else {
                self.paused |= self.single_block && left == 0 && !self.in_hole;
            }
        }
    }

    /// Axis `i` in position on its set-point and still: a slide that passes through the
    /// window while it runs in (a drive with more delay overshoots) is not yet in position —
    /// a stroke started then begins with its overshoot as sync error.
    fn settled(&self, fb: &Feedback, sent: &[f64; N_AXES], i: usize) -> bool {
        (fb.pos[i] - sent[i]).abs() <= INPOS_MM && (fb.pos[i] - self.inpos_prev[i]).abs() <= INPOS_STILL_MM
    }

    /// Every feed axis the machine has `settled`.
    fn feed_axes_settled(&self, fb: &Feedback, sent: &[f64; N_AXES]) -> bool {
        (0..3).all(|i| !self.lim.present[i] || self.settled(fb, sent, i))
    }

    /// Before a thread arms (not a continuation): the feed axes in position on their
    /// set-points and still, bounded. The manual is silent; a Fanuc 0i-TF checks in position at
    /// the end of the positioning G00 (No.1601#5 NCI = 0) before G32 waits for the one-turn
    /// signal. A slow or compliant Z that still runs in from the rapid (Kv 15 behind a belt:
    /// 0.16 mm) otherwise begins the thread with that error, and the sync monitor stops it.
    fn thread_in_position(&mut self, fb: &Feedback) -> bool {
        let sent = self.hist[self.hist_k];
        let ok = self.inpos_wait >= INPOS_MAX_CYCLES || self.feed_axes_settled(fb, &sent);
        self.inpos_prev = fb.pos;
        self.inpos_wait = if ok { 0 } else { self.inpos_wait.saturating_add(1) };
        ok
    }

    /// G92.1 before its stroke: brake the spindle and wait in position.
    fn rigid_entry(&mut self, seg: RigidSeg, fb: &Feedback) {
        // Like rigid tapping: brake the spindle, then take its angle as the origin.
        self.sp_dir = 0.0;
        self.sp_css = None;
        // In position first, as before a rigid tap: a stroke that starts while the axes
        // still settle from the positioning move begins with that error as sync error.
        let sent = self.hist[self.hist_k];
        let in_pos = self.inpos_wait >= INPOS_MAX_CYCLES
            || seg.u_long == 0.0
            || (self.feed_axes_settled(fb, &sent) && (fb.pos[AX_S] - sent[AX_S]).abs() * seg.plen / seg.dc.abs().max(1e-9) <= INPOS_MM);
        self.inpos_prev = fb.pos;
        self.inpos_wait = if self.sp_cur == 0.0 { self.inpos_wait.saturating_add(1) } else { 0 };
        if self.stopping {
            self.run = Run::None;
        } else if self.sp_cur == 0.0 && in_pos {
            self.inpos_wait = 0;
            self.sp_heat_cap = self.sp_heat_next;
            self.run = Run::Rigid { seg, theta0: Some(self.pos[AX_S]), s: 0.0, v: 0.0, landed: false };
        }
    }

    /// A G92.1 stroke: one profile for path and spindle (`sv`: arc length done, speed).
    fn step_rigid(&mut self, mut seg: RigidSeg, th0: f64, sv: (f64, f64), prev: &[f64; N_AXES]) -> f64 {
        // One profile for path and spindle; feed hold and override do not apply (a
        // thread), a controlled stop brakes both together on the same profile.
        let dt = self.lim.cycle_s;
        let (s, v) = sv;
        let len = seg.plen;
        let d = len - s;
        if seg.dc != 0.0 {
            (seg.alim, _) = self.capped_accel(seg.alim, 0.0, len / seg.dc.abs(), v, 0.0, d);
        }
        let v_cmd = if self.stopping { 0.0 } else { seg.v };
        let nv = profile::next_speed(v, v_cmd, d, seg.alim * dt, dt);
        let (s2, landed) = if d - nv * dt <= 1e-9 { (len, true) } else { (s + nv * dt, false) };
        if seg.geom.len() > 0.0 {
            self.pos[..3].copy_from_slice(&seg.geom.at(s2));
        }
        self.pos[AX_S] = if landed { th0 + seg.dc } else { th0 + seg.dc * s2 / len };
        // Only a thread is watched (a positioning rapid has no lead).
        self.monitor.watch(seg.u_long > 0.0);
        self.sp_cur = (self.pos[AX_S] - prev[AX_S]) / dt / 6.0;
        self.run = if self.stopping && nv == 0.0 && !landed {
            self.sp_cur = 0.0;
            Run::None
        } else {
            Run::Rigid { seg, theta0: Some(th0), s: s2, v: nv, landed }
        };
        if landed {
            d / dt
        } else {
            nv
        }
    }

    /// A rigid-tap stroke at its end.
    fn tap_landed(&mut self, seg: &TapSeg, theta0: Option<(f64, f64)>) {
        // At rest on the stroke's end, spindle stopped in position.
        self.sp_cur = 0.0;
        self.run = Run::None;
        // In the hole: landed past the reference point (the hole's R, or where a G30 P99
        // return started) in the direction into the hole; a pull-out that ends on or
        // beyond R (No.5282/No.5382 extra return) is out of it.
        let into = (seg.p1 - seg.p0).signum() * if seg.retract { -1.0 } else { 1.0 };
        self.in_hole = theta0.is_some_and(|(pr, _)| (seg.p1 - pr) * into > 0.0);
        self.hole_dir = (seg.p1 - seg.p0).signum();
        // Single block never stops inside a tap; after the hole only with No.5200#6
        // (in a canned cycle by its actions, see `single_block_stop`).
        if self.cur_cyc.code > 0 {
            self.block_end();
        } else {
            self.paused |= self.single_block && !self.in_hole && self.lim.tap_hold_in_hole;
        }
    }

    /// A rigid-tap stroke before it starts: brake the spindle, wait in position and for the
    /// tap-state gate, take the tap reference.
    fn tap_entry(&mut self, seg: TapSeg, fb: &Feedback) {
        // Rigid tapping starts from a stopped spindle: brake it (step_spindle), then
        // take its angle as the stroke's origin.
        self.sp_dir = 0.0;
        self.sp_css = None;
        // In-position check before a hole's first stroke: the tapping axis and the
        // spindle at rest on their setpoints (a tap that starts while the axis still
        // settles from the rapid to R begins with a sync error). Bounded, so bad
        // feedback cannot hang the program.
        let sent = self.hist[self.hist_k];
        let a = seg.axis;
        let in_pos = self.in_hole
            || self.inpos_wait >= INPOS_MAX_CYCLES
            || (self.settled(fb, &sent, a) && ((fb.pos[AX_S] - sent[AX_S]) * seg.lead / 360.0).abs() <= INPOS_MM);
        self.inpos_prev = fb.pos;
        self.inpos_wait = if self.sp_cur == 0.0 { self.inpos_wait.saturating_add(1) } else { 0 };
        self.tap_wait = None;
        if self.stopping {
            self.run = Run::None;
        } else if self.sp_cur == 0.0 && in_pos && !self.in_hole && !seg.retract && self.tap_gate == Some(false) {
            // Held at R, spindle at rest, until the "in hole" state is durable.
            let dir = (seg.p1 - seg.p0).signum();
            let rpm = seg.v / seg.lead.abs().max(1e-12) * 60.0;
            self.tap_wait = Some(TapEntry { line: self.line, axis: a, r: seg.p0, dir, spindle_deg: self.pos[AX_S], lead: seg.lead, rpm });
        } else if self.sp_cur == 0.0 && in_pos {
            self.inpos_wait = 0;
            // The gate lets one hole in; the next waits again.
            self.tap_gate = self.tap_gate.map(|_| false);
            // Keep the previous stroke's reference if the spindle is still exactly where
            // that relation puts it (same hole, nothing turned it since).
            let r = match self.tap_ref {
                Some((ax, pr, thr, lead)) if ax == a && lead == seg.lead && thr + 360.0 * (seg.p0 - pr) / lead == self.pos[AX_S] => (pr, thr),
                _ => (seg.p0, self.pos[AX_S]),
            };
            self.tap_ref = Some((a, r.0, r.1, seg.lead));
            self.sp_heat_cap = self.sp_heat_next;
            self.run = Run::Tap { seg, theta0: Some(r), s: 0.0, v: 0.0, landed: false };
        }
    }

    /// A rigid-tap stroke: axis and spindle on one profile (`r`: the tap reference, `sv`: done, speed).
    fn step_tap(&mut self, mut seg: TapSeg, r: (f64, f64), sv: (f64, f64), prev: &[f64; N_AXES]) -> f64 {
        // Feed hold acts within the stroke only with No.5200#6 (see hold_now); a hold
        // or a controlled stop brakes the axis and the spindle together on one profile.
        let dt = self.lim.cycle_s;
        let ((pr, thr), (s, v)) = (r, sv);
        let len = (seg.p1 - seg.p0).abs();
        let d = len - s;
        let a0 = if s == 0.0 { 0.0 } else { self.path_a };
        (seg.alim, seg.jlim) = self.capped_accel(seg.alim, seg.jlim, seg.lead.abs() / 360.0, v, a0, d);
        let v_cmd = if self.stopping || (self.held && self.lim.tap_hold_in_hole) { 0.0 } else { seg.v };
        let (nv, adv) = if seg.jlim > 0.0 {
            let (nv, na, adv) = profile::next_state(v, a0, v_cmd, d, seg.alim, seg.jlim, dt);
            self.path_a = na;
            (nv, adv)
        } else {
            let nv = profile::next_speed(v, v_cmd, d, seg.alim * dt, dt);
            (nv, nv * dt)
        };
        let (s2, landed) = if d - adv <= 1e-9 { (len, true) } else { (s + adv, false) };
        let p = if landed { seg.p1 } else { seg.p0 + s2.copysign(seg.p1 - seg.p0) };
        self.pos[seg.axis] = p;
        self.pos[AX_S] = thr + 360.0 * (p - pr) / seg.lead;
        self.monitor.watch(true);
        self.sp_cur = (self.pos[AX_S] - prev[AX_S]) / dt / 6.0;
        let path_v = (p - prev[seg.axis]).abs() / dt;
        self.run = if self.stopping && nv == 0.0 && !landed {
            self.sp_cur = 0.0;
            Run::None
        } else {
            Run::Tap { seg, theta0: Some((pr, thr)), s: s2, v: nv, landed }
        };
        path_v
    }

    /// A controlled stop at rest: drop the rest of the program and plan from here.
    fn stopped_at_rest(&mut self) {
        self.len = 0;
        self.stopping = false;
        self.held = false;
        self.paused = false;
        self.fin_wait = false;
        self.plan_end = [self.pos[AX_X], self.pos[AX_Y], self.pos[AX_Z]];
        self.plan_spindle_on = false;
        self.last_blendable = false;
        self.in_hole = false;
        self.sb_pending = false;
        self.cur_cyc = CycStep::default();
        self.plan_cyc = CycStep::default();
        self.sp_dir = 0.0;
        self.sp_css = None;
    }

    /// The set-point of this cycle: the interpolated position with the sync correction on
    /// top, the velocities, the history the sync laws read.
    fn setpoint(&mut self, fb: &Feedback, prev: &[f64; N_AXES], path_v: f64, event: Event) -> Setpoint {
        let dt = self.lim.cycle_s;
        if !self.follow_corr() {
            self.sync_corr(fb);
        }
        self.step_tool(fb.pos[AX_S], fb.spindle_rpm * 6.0);
        let mut out = self.pos;
        let mut vel = [0.0; N_AXES];
        let (corr, dcorr) = (self.corr.offset(), self.corr.step());
        for i in 0..3 {
            out[i] += corr[i];
            vel[i] = (self.pos[i] - prev[i] + dcorr[i]) / dt;
            if self.pos[i] != prev[i] {
                self.last_dir[i] = (self.pos[i] - prev[i]).signum();
            }
        }
        self.hist_k = (self.hist_k + 1) % HIST;
        self.hist[self.hist_k] = out;
        vel[AX_S] = self.sp_cur * 6.0;
        self.fb_rpm_prev = if fb.spindle_rpm.is_finite() { fb.spindle_rpm } else { 0.0 };
        Setpoint { pos: out, vel, spindle_rpm: self.sp_cur, path_feed: path_v * 60.0, line: self.line, event, tool_spindle: self.tool.pos() }
    }

    /// Blend: cross the junction at the end of the running segment within this cycle, onto
    /// the next queued segment, `over` (≥ 0) beyond the end, and on across the junctions of
    /// the segments that this cycle passes entirely, at most [`MAX_JUNCTIONS`]. Returns the
    /// segment the cycle ends in and the arc length there, or None when no linked segment is
    /// queued (the running one then lands on its end). Bounded, allocation-free.
    ///
    /// Every junction crossed is crossed at a speed its `vj` allows and every segment entered
    /// can still be braked within its length and `ext` (see `relax`): the same reasoning as for
    /// one junction, applied to each in turn. `link_last` keeps the count within the bound;
    /// the bound is only a backstop against rounding.
    fn cross(&mut self, over: f64) -> Option<(Seg, f64)> {
        let mut over = over.max(0.0);
        let mut last = None;
        for _ in 0..MAX_JUNCTIONS {
            let Some(Entry { item: Item::Move(next), line, cyc }) = self.peek() else { break };
            self.pop();
            self.line = line;
            self.cur_cyc = cyc;
            let len = next.geom.len();
            last = Some((next, over.min(len)));
            // Passed entirely, and blended on: cross its end too.
            if !(over - len > 1e-9 && next.ext > 0.0) {
                break;
            }
            over -= len;
        }
        last
    }

    /// One cycle of a thread pass: wait for the spindle, arm at the measured angle, then track
    /// the synchronous position within the axis limits, braking for the end — or, when a
    /// continuous thread segment is queued next, crossing into it within the cycle with the
    /// same lock. Returns the path speed (mm/s).
    ///
    /// The target is computed from the spindle angle predicted to when the axes actually get
    /// there: measured angle plus measured speed × (`feedback_delay` cycles plus the long
    /// axis' learnt velocity lag τ). Otherwise the lock would lag by `ω·(delay + τ)`, which
    /// shifts the phase with the rpm (LinuxCNC issue #3455).
    fn step_thread(&mut self, fb: &Feedback, seg: ThreadSeg, sync: Option<ThreadSync>, s: f64, v: f64) -> f64 {
        let dt = self.lim.cycle_s;
        let rpm = if fb.spindle_rpm.is_finite() { fb.spindle_rpm } else { 0.0 };
        // Predicted to when this setpoint is where the axes actually are: the measured angle
        // is `feedback_delay` cycles old by then.
        // Plus the long axis' own velocity lag (learnt, see `sync_corr`): otherwise the thread
        // phase would move with the rpm by ω·τ.
        let la = seg.long_axis.min(2);
        let mut tau = self.thread_tau[la].unwrap_or_else(|| self.axis_lag(la));
        // Learn the lag from the phase error itself on the synchronous line (the lead-in
        // over): an error e at path speed v is a lag misjudged by e/v.
        if let (Some(e), Some(t)) = (self.monitor.take_thread_err(), sync) {
            let vs = t.sync_speed();
            if e.is_finite() && vs > 1e-3 && t.on_line(fb.pos[AX_S]) {
                tau = (tau - THREAD_TRIM_GAIN * e / vs).clamp(0.0, 0.1);
            }
        }
        if self.lim.sync_correction {
            self.thread_tau[la] = Some(tau);
        } else {
            tau = 0.0;
        }
        // A late spindle TPDO brings an angle `age` cycles older: predict over those too.
        let late = dt * fb.age[AX_S].min(8) as f64;
        // Smoothed (`AngleFilter`): a coarse encoder's counts and the measured speed's noise,
        // multiplied by the prediction's horizon, shook a lightly damped long axis. The lag's
        // lead uses the smoothed speed outside the filter: inside it, the filter's lag sat in
        // the trim's loop (a belt with backlash rang at ±9° of phase).
        // While the spindle's command ramps (a stop, a speed change) it would be off by a·T²
        // (a controlled stop in a thread left Z 0.86 µm off the groove): the measured angle
        // then, as before.
        if self.stopping || self.sp_cur != self.sp_target {
            self.thread_angle.restart();
        }
        let ahead = spindle_at_slot(fb, dt) + rpm * 6.0 * (dt * self.lim.feedback_delay as f64 + late);
        let theta = self.thread_angle.update(ahead, rpm * 6.0, dt) + self.thread_angle.speed() * tau;
        if sync.is_none() {
            if let Some(s2) = self.thread_take_up() {
                self.pos[..3].copy_from_slice(&seg.geom.at(s2));
                self.run = Run::Thread { seg, sync: None, s: s2, v: 0.0, landed: false };
                return (s2 - s) / dt;
            }
        }
        // The lead-in ramp uses 80 % of the path acceleration, leaving the tracker headroom.
        let armed_now = sync.is_none();
        let sync = match sync {
            Some(t) => Some(t),
            None if self.stopping => None,
            // Arm only once the spindle is at its commanded speed (speed arrival).
            None if self.sp_cur != self.sp_target || self.sp_target == 0.0 => None,
            None if !seg.continuous && !self.thread_in_position(fb) => None,
            None => ThreadSync::arm_after(theta, rpm, seg.start_angle, seg.lead_path, seg.k_path, 0.8 * seg.alim, self.lim.thread_leadin_s, s),
        };
        let Some(t) = sync else {
            // Spindle not turning yet (or stopping before the cut began): wait at the start.
            if self.stopping {
                self.run = Run::None;
            }
            return 0.0;
        };
        if armed_now && !seg.continuous && t.sync_speed() * seg.lead_path_max / seg.lead_path > seg.vlim {
            // The measured spindle speed is too fast for the lead: refuse before cutting.
            self.fault = Some(Fault::ThreadTooFast { v: t.sync_speed() * seg.lead_path_max / seg.lead_path, vlim: seg.vlim, line: self.line });
            self.stop();
            self.run = Run::None;
            return 0.0;
        }
        let len = seg.geom.len();
        // The continuation, if it is already queued (O(1): the queue head).
        let next = match self.peek() {
            Some(Entry { item: Item::Thread(n), line, .. }) if n.continuous => Some((n, line)),
            _ => None,
        };
        let dv = seg.alim * dt;
        if armed_now {
            self.thread_vf = 0.0;
            self.thread_settle = self.corr.settling(la);
        }
        let target = t.target(theta);
        let target = target - self.thread_shortfall(&t, target, theta, rpm);
        // Feed hold and override do not apply while threading (Fanuc). A controlled stop keeps
        // the axes on the thread while the spindle brakes (they stop together), so the tool
        // does not leave the groove.
        let want = (target - s) / dt;
        let brake_len = len - s + next.map_or(0.0, |(n, _)| n.geom.len());
        let nv = want.max((v - dv).max(0.0)).min(v + dv).min(seg.vlim).min(profile::v_allowed(brake_len, dv, dt)).max(0.0);
        let d = len - s;
        if let Some((n, line)) = next.filter(|_| d - nv * dt <= 1e-9) {
            if let Some(t2) = t.continue_with(len, n.lead_path, n.k_path) {
                // Cross into the continuation within this cycle: what is left of this cycle's
                // step, at the same angular rate (the path lead may differ).
                self.pop();
                self.line = line;
                let r = n.lead_path / seg.lead_path;
                let len2 = n.geom.len();
                let s2 = ((nv * dt - d) * r).clamp(0.0, len2);
                let landed = len2 - s2 <= 1e-9;
                let s2 = if landed { len2 } else { s2 };
                self.pos[..3].copy_from_slice(&n.geom.at(s2));
                self.run = Run::Thread { seg: n, sync: Some(t2), s: s2, v: nv * r, landed };
                return nv;
            }
        }
        let (s2, landed) = if d - nv * dt <= 1e-9 { (len, true) } else { (s + nv * dt, false) };
        self.pos[..3].copy_from_slice(&seg.geom.at(s2));
        // Watched next cycle while the command is on the lock (lead-in ramp and synchronous
        // line), not while braking for the end.
        self.monitor.watch(nv == want && !landed);
        let spindle_stopped = self.sp_cur == 0.0;
        self.run = if self.stopping && nv == 0.0 && !landed && spindle_stopped {
            Run::None
        } else {
            Run::Thread { seg, sync: Some(t), s: s2, v: nv, landed }
        };
        if landed {
            self.thread_chain = Some((t, len));
            d / dt
        } else {
            nv
        }
    }

    /// The take-up before a thread pass (`Limits::thread_take_up`): where the long axis last
    /// moved against the thread's direction (a G92/G76 pass returns to its start so), the axes
    /// first creep along the thread, at most a quarter of it, at up to [`TAKE_UP_SPEED`] with
    /// a smooth start and stop; the lead-in then starts from there (`ThreadSync::arm_after`),
    /// on the same synchronous line. The path position of this cycle while it runs; None once
    /// it is done or where none is needed. A stop ends it where it stands.
    fn thread_take_up(&mut self) -> Option<f64> {
        let (k, d) = self.takeup?;
        // A cosine profile: its peak speed π·d/(2·T) is TAKE_UP_SPEED.
        let n = (std::f64::consts::PI * d / (2.0 * TAKE_UP_SPEED) / self.lim.cycle_s).ceil().max(1.0);
        let k = k + 1;
        if self.stopping || f64::from(k) > n {
            self.takeup = None;
            return None;
        }
        self.takeup = Some((k, d));
        Some(d * (1.0 - (std::f64::consts::PI * f64::from(k) / n).cos()) / 2.0)
    }

    /// The take-up's length before the pass `seg` (`thread_take_up`): None where the long axis
    /// last moved along the thread already, or the key is 0.
    fn take_up_len(&self, seg: &ThreadSeg) -> Option<f64> {
        let la = seg.long_axis.min(2);
        let dir = (seg.geom.end()[la] - geom_start(&seg.geom)[la]).signum();
        let d = self.lim.thread_take_up.min(0.25 * seg.geom.len());
        (d > 0.0 && self.last_dir[la] != dir).then_some(d)
    }

    /// What of a thread's lead τ·v the long axis' lag has not built up yet, path mm. A loop
    /// with feed-forward lags by c·v/(1 + T·s) beyond its delay (`LagModel::split`): after
    /// the lead-in that share builds up over T (67 ms at Kv 15/s), so the lead τ·v sent at
    /// once ran the axis ahead of the thread (a belt at Kv 20/s with 90 % feed-forward:
    /// alarm 2307 in the lead-in). The exact inverse leads by c·v/(1 + (T − c)·s): the
    /// shortfall is c·(v − that filtered v), with the model as it was when the pass armed
    /// (the fit moves through the lead-in it is excited by). Zero on the line, and where
    /// the lag does not settle on its own (a delay, a stiff loop).
    fn thread_shortfall(&mut self, t: &ThreadSync, target: f64, theta: f64, rpm: f64) -> f64 {
        let step = target - t.target(theta - rpm * 6.0 * self.lim.cycle_s);
        let settling = self.thread_settle.filter(|_| self.lim.sync_correction);
        let Some((c, tf)) = settling.filter(|_| step.is_finite()) else {
            self.thread_vf = if step.is_finite() { step } else { 0.0 };
            return 0.0;
        };
        // The filter is linear: c · (filtered step) is the lead `settle_lead` gives.
        self.thread_vf = settle_lead(self.thread_vf, step, tf);
        c * (step - self.thread_vf)
    }

    /// The sync correction of rigid taps and G92.1 (with `Limits::sync_correction`): the
    /// feed axes follow the spindle's *actual* angle with their own lag pre-compensated and
    /// the measured sync error trimmed out (`crate::sync::correction`). Only the *sent*
    /// set-point carries it; planning, landing and `position()` stay nominal. It stays on
    /// through the strokes and dwells of one hole and fades out afterwards.
    fn sync_corr(&mut self, fb: &Feedback) {
        let gain = match self.run {
            Run::Tap { seg, theta0: Some(_), .. } => {
                let mut g = [0.0; 3];
                g[seg.axis.min(2)] = seg.lead / 360.0;
                Some(g)
            }
            Run::Rigid { seg, theta0: Some(_), .. } if seg.u_long > 0.0 && seg.dc != 0.0 => {
                let e = seg.geom.end();
                let p0 = geom_start(&seg.geom);
                Some([(e[0] - p0[0]) / seg.dc, (e[1] - p0[1]) / seg.dc, (e[2] - p0[2]) / seg.dc])
            }
            // Between the strokes of a hole (reversal, dwell at the bottom): keep the lock.
            _ if self.in_hole => Some(self.corr.gain()),
            _ => None,
        };
        // A dwell in the hole (G84 … P): what the trim integrated in the stroke was a lag that
        // is gone at rest — held, Z stood that far off its set-point when the return began
        // (4.7 µm on a Kv 15/s Z after `G84 … P500`).
        self.corr.rest(self.in_hole && matches!(self.run, Run::Dwell { .. }));
        let (sent, before, before2) = (self.answered(0), self.answered(1), self.answered(2));
        // Every feed axis' lag model learns from all its motion (the rapid to R teaches it
        // before the tap begins).
        // Feedback from a late TPDO answers an older set-point: learn nothing from it, and
        // let the spindle's lag coast on its tracked rate.
        let fresh = fb.age[AX_S] == 0 && !self.monitor.suspect();
        // Positions taken back to the instant their set-points are timed for (`late_s`):
        // the spindle by its measured speed, a feed axis by its commanded step.
        let late = sample_late(fb, self.lim.cycle_s);
        let mut pos = fb.pos;
        for i in 0..3 {
            pos[i] -= (sent[i] - before[i]) / self.lim.cycle_s * late;
        }
        pos[AX_S] = spindle_at_slot(fb, self.lim.cycle_s);
        if fresh {
            self.corr.learn(&xyz3(&sent), &xyz3(&before), &xyz3(&before2), &xyz3(&pos));
        }
        self.corr.set_error(self.monitor.error_vec());
        let gain = gain.filter(|_| self.lim.sync_correction);
        let lag = if fresh { pos[AX_S] - sent[AX_S] } else { f64::NAN };
        self.corr.update(gain, &xyz3(&self.pos), lag);
    }

    /// The learnt velocity lag τ₁ of feed axis `i` (actual ≈ sent − τ₁·v), s.
    fn axis_lag(&self, i: usize) -> f64 {
        self.corr.axis_lag(i)
    }

    /// Measured spindle–axis sync error of the last cycle, µm along the thread's long axis:
    /// from the *actual* positions in `Feedback`, (L_act − L_start) − lead·(θ_act − θ_start)/360
    /// with L the distance along the thread (Z for a straight thread or a tap), lead the
    /// current lead (G34: the sum of the leads), θ the measured spindle angle. Positive = the
    /// axis is ahead of the spindle. Measured in every cycle that follows one whose setpoint
    /// was locked to the spindle (thread lead-in ramp and synchronous line, rigid tap and
    /// G92.1 strokes); 0 otherwise (waiting for the spindle, braking for a thread's end,
    /// other moves). Beyond `Limits::sync_err_limit_um` it raises alarm
    /// [`alarms::SYNC_ERROR`] and a controlled stop in which spindle and axes stop together.
    pub fn sync_error(&self) -> f64 {
        self.monitor.error_um()
    }

    /// Synchronised cycles whose feedback could not be paired from one SYNC (a late TPDO of
    /// the spindle or a feed axis): the monitor held its last value over them.
    pub fn unpaired_cycles(&self) -> u32 {
        self.monitor.unpaired()
    }

    /// The spindle's angle and every configured feed axis' position were sampled at the same
    /// SYNC.
    fn one_sync(&self, fb: &Feedback) -> bool {
        (0..3).all(|i| !self.lim.present[i] || fb.age[i] == fb.age[AX_S])
    }

    /// The sync-error monitor (see `sync_error`), at the start of a cycle, for the setpoint
    /// the last cycle sent: the error of the running relation from the actual positions
    /// (pairing and holding: `crate::sync::monitor`). O(1).
    fn monitor_sync(&mut self, fb: &Feedback) {
        if self.monitor.begin(self.one_sync(fb)) != Sample::Measure {
            return;
        }
        let th = fb.pos[AX_S];
        let mut vec = [0.0; 3];
        let mut thread = None;
        let err_mm = match self.run {
            Run::Thread { seg, sync: Some(t), .. } => {
                let e = line_progress(&seg.geom, &fb.pos) - t.target(th);
                thread = Some(e);
                e * seg.u_long
            }
            Run::Tap { seg, theta0: Some((pr, thr)), .. } => {
                // Along the stroke's direction: + = the tapping axis ahead of the spindle.
                let e = (fb.pos[seg.axis] - pr) - seg.lead * (th - thr) / 360.0;
                vec[seg.axis.min(2)] = e;
                e * (seg.p1 - seg.p0).signum()
            }
            Run::Rigid { seg, theta0: Some(th0), .. } => {
                let len = seg.geom.len();
                let e = line_progress(&seg.geom, &fb.pos) - (th - th0) * len / seg.dc;
                let (p0, p1) = (geom_start(&seg.geom), seg.geom.end());
                for i in 0..3 {
                    vec[i] = e * (p1[i] - p0[i]) / len.max(1e-12);
                }
                e * seg.u_long
            }
            // At rest in the hole (the dwell at the bottom, between the strokes) the tap is
            // engaged all the same: the hole's relation is measured (shown, and held to the
            // limit). Not trimmed on: against a slide's stiction the trim's integral winds the
            // set-point away from a slide that stands on its count (1.1 µm over a 0.5 s dwell on
            // the default Z), and the return then starts from a wound-up drive (NaN: skipped).
            _ if self.in_hole => {
                let Some((ax, pr, thr, lead)) = self.tap_ref else { return };
                vec = [f64::NAN; 3];
                ((fb.pos[ax] - pr) - lead * (th - thr) / 360.0) * self.hole_dir
            }
            _ => return,
        };
        let limit_um = self.lim.sync_err_limit_um;
        if self.monitor.record(err_mm, vec, thread, limit_um) && !self.stopping {
            if self.fault.is_none() {
                self.fault = Some(Fault::SyncError { err_um: self.monitor.error_um(), limit_um, line: self.line });
            }
            self.stop();
        }
    }

    /// A fault found by `step` (which cannot return errors), as an alarm; the motion is already
    /// being brought to a controlled stop. Call outside the real-time path.
    pub fn take_alarm(&mut self) -> Option<Alarm> {
        let f = self.fault.take()?;
        Some(match f {
            Fault::SyncError { err_um, limit_um, line } => Alarm::new(
                alarms::SYNC_ERROR,
                format!(
                    "line {line}: spindle–axis sync error {err_um:.1} µm exceeds the limit {limit_um:.0} µm (machine.sync_error_limit_um); spindle and axes were stopped together: check the drives' tuning and load, or lower S"
                ),
            ),
            Fault::ThreadTooFast { v, vlim, line } => Alarm::new(
                alarms::THREAD_TOO_FAST,
                format!(
                    "line {line}: the measured spindle speed needs {:.0} mm/min for the thread lead, more than the axes' {:.0} mm/min; lower S",
                    v * 60.0,
                    vlim * 60.0
                ),
            ),
        })
    }

    /// True when every pushed move has been executed and the feed axes are at rest. (The
    /// spindle may still turn: see `Setpoint::spindle_rpm`.)
    pub fn is_idle(&self) -> bool {
        // Not while a sync correction is still fading out: what is sent is not the end yet.
        self.len == 0 && self.run == Run::None && !self.stopping && !self.fin_wait && self.corr.is_zero() && self.tool.at_rest()
    }

    /// Hold the next item until the auxiliary code just reached (`Event::Aux`) is complete:
    /// the cycle loop calls `wait_fin(true)` in the cycle the event came out of `step` and
    /// `wait_fin(false)` on FIN (Fanuc: the next block waits for the completion signal of an
    /// M/S/T code). What runs goes on; a controlled stop clears it.
    pub fn wait_fin(&mut self, on: bool) {
        self.fin_wait = on;
    }

    /// True while an auxiliary code's completion is awaited.
    pub fn fin_pending(&self) -> bool {
        self.fin_wait
    }

    /// A spindle-synchronised move is running (a thread pass on its lock, a rigid tap or
    /// G92.1 stroke): its time base cannot be shifted.
    pub fn is_synchronised(&self) -> bool {
        match self.run {
            Run::Thread { sync: Some(_), .. } | Run::Tap { theta0: Some(_), .. } | Run::Rigid { theta0: Some(_), .. } => true,
            _ => self.in_hole,
        }
    }

    /// Forget the queued items, keeping the planning state (where the last push ends, the
    /// spindle, the modes): the pre-motion check plans a whole program through one `Motion`
    /// without executing it (`guard::check_program`).
    pub fn discard_queue(&mut self) {
        self.len = 0;
        self.last_blendable = false;
    }

    /// M03/M04 is in force (M05, M30 or a stop clear it; the speed may still be ramping).
    pub fn spindle_commanded(&self) -> bool {
        self.sp_dir != 0.0
    }

    /// The spindle (and the tool spindle) is commanded to stand still.
    pub fn spindle_at_rest(&self) -> bool {
        self.sp_cur == 0.0 && self.tool.at_rest()
    }

    /// Controlled stop: decelerate along the path within the acceleration limits, ramp the
    /// spindle down, then drop the rest of the queue. New moves are refused until
    /// `is_idle()`; the next move is planned from where the axes came to rest.
    pub fn stop(&mut self) {
        self.stopping = true;
        self.sp_dir = 0.0;
    }

    /// Hold every rigid tap's first stroke of a hole at R until [`Motion::open_tap_gate`]
    /// (the cycle loop opens it once the tap-state writer has the entry on disk).
    pub fn gate_taps(&mut self) {
        self.tap_gate = Some(false);
    }

    /// Open (or keep closed) the gate of [`Motion::gate_taps`]; no effect without it. Opening
    /// lets the waiting hole's first stroke start at the next step.
    pub fn open_tap_gate(&mut self, open: bool) {
        if self.tap_gate.is_some() {
            self.tap_gate = Some(open);
        }
    }

    /// A hole's first stroke waiting at R for the gate (this step).
    pub fn tap_waiting(&self) -> Option<TapEntry> {
        self.tap_wait.filter(|_| matches!(self.run, Run::Tap { theta0: None, .. }))
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

    /// Single block: after each motion block or dwell the program waits for cycle start. With
    /// look-ahead, a block that can no longer brake for its end when the switch goes on runs
    /// on into the next block and stops at the end of that one.
    pub fn set_single_block(&mut self, on: bool) {
        self.single_block = on;
    }

    /// The current position setpoint (what the last `step` returned, or the start).
    pub fn position(&self) -> [f64; N_AXES] {
        self.pos
    }

    /// Optional stop switch: when on, M01 waits for cycle start like M00.
    pub fn set_optional_stop(&mut self, on: bool) {
        self.optional_stop = on;
    }

    /// Feed override, 0–2 (0–200 %), applied to cutting feeds from the next cycle.
    pub fn set_feed_override(&mut self, f: f64) {
        self.feed_ovr = if f.is_finite() { f.clamp(0.0, 2.0) } else { 0.0 };
    }

    /// Spindle speed override, 0.5–1.2 (50–120 %, Fanuc's range), from the next cycle. Under
    /// G96 the G50 clamp still holds; the machine maximum always does.
    pub fn set_spindle_override(&mut self, f: f64) {
        self.spindle_ovr = if f.is_finite() { f.clamp(0.5, 1.2) } else { 1.0 };
    }

    /// The acceleration the spindle was found to manage, rpm/s, where it could not give the
    /// configured one (`govern_spindle`); None while it could.
    pub fn spindle_accel_found(&self) -> Option<f64> {
        self.sp_accel_cap.is_finite().then(|| self.sp_accel_cap / SP_ACCEL_MARGIN / 6.0)
    }

    /// Whether `spindle_accel_found` is the acceleration the spindle gave at its drive's
    /// torque limit (`sync::torque_margin`) rather than all it managed (`sync::governor`).
    pub fn spindle_accel_at_torque_limit(&self) -> bool {
        self.sp_accel_cap.is_finite() && self.sp_cap_by_torque
    }

    /// The spindle acceleration (rpm/s) its amplifier's overload was found to allow
    /// (`sync::overload`); None while it was never near it.
    pub fn spindle_overload_found(&self) -> Option<f64> {
        self.sp_heat_next.is_finite().then(|| self.sp_heat_next / 6.0)
    }

    /// The spindle speed override in effect (0.5–1.2).
    pub fn spindle_override(&self) -> f64 {
        self.spindle_ovr
    }

    /// The feed override in effect (0–2).
    pub fn feed_override(&self) -> f64 {
        self.feed_ovr
    }

    /// Rapid override, 0–1: 0 is F0 (No.1421's rate), else the share of the rapid rate.
    pub fn set_rapid_override(&mut self, f: f64) {
        self.rapid_ovr = if f.is_finite() { f.clamp(0.0, 1.0) } else { 0.0 };
    }
}

/// The nominal commanded speed of a segment (mm/s), for junction limits: a feed per minute
/// (clamped by No.6023 later in `v_cmd`), unknown for a feed per revolution.
fn speed_cap(s: &Seg) -> f64 {
    match s.speed {
        Speed::PerMin(f) => f,
        Speed::Rapid | Speed::PerRev(_) => f64::INFINITY,
    }
}

/// The `ext` a blended segment may have (see `Motion::relax`), given the room after its end
/// (`room`: the next segment's length and `ext`), the next segment's speed step `ndv` and feed.
fn relaxed_ext(prev: &Seg, room: f64, ndv: f64, next_cap: f64, dt: f64) -> f64 {
    // Hard limit of the crossing speed: the corner, and the next segment must be brakeable
    // from it (its own staircase).
    let ve = prev.vj.min(profile::v_allowed(room, ndv, dt));
    let pdv = prev.alim * dt;
    // A virtual stop `dt·G(w)` beyond the end: the cycle that crosses the junction then runs
    // slower than `w + dv` (see profile::v_allowed). `w = ve − dv` keeps the hard limit; the
    // next segment's feed (soft: `v_cmd` caps the speed anyway) lowers `w` so that a drop in
    // F is braked before the junction, to within one step. Below one step: exact stop.
    if prev.jlim > 0.0 && prev.alim > 0.0 {
        // S-curve (one acceleration `A` and jerk `J` along the chain, see `jerk_chain`): a
        // virtual stop beyond the end, at most `w²/2A` with `w = vj − A·dt`: any state that
        // can still brake within it moves at most `w` there (braking at ≤ A needs v²/2A),
        // hence at most `vj` within the crossing cycle; at most the next segment's room, so
        // that it can still brake there. The next segment's feed is soft (`v_cmd` caps the
        // speed anyway): the distance a cruise at that feed needs to stop, `v²/2A + v·A/2J`;
        // `v²/2A` alone held a chain of blocks shorter than `v·A/2J` at ≈ 85 % of its feed.
        let a = prev.alim;
        let w = prev.vj - pdv;
        let soft = if next_cap.is_finite() { profile::stop_dist(next_cap, 0.0, a, prev.jlim) } else { f64::INFINITY };
        if w > 0.0 {
            (w * w / (2.0 * a)).min(room).min(soft)
        } else {
            0.0
        }
    } else if prev.vj > pdv && ndv >= pdv {
        // The next segment brakes at least as hard (`accel_chain` makes chains of short blocks
        // so): the room itself. A cycle that crosses the end `o` beyond it at speed `v` has
        // `dt·G(v − pdv) ≤ ext − o` (the profile's bound), hence `dt·G'(v − ndv) ≤ room − o`
        // in the next segment: it can still brake; and `v − pdv < G⁻¹(ext/dt) ≤ vj − pdv`.
        // The room of a chain of tiny blocks adds up; the rule below loses one cycle's
        // travel per junction, which stopped such a chain at every block.
        room.min(dt * profile::g((prev.vj - pdv).min(next_cap), pdv))
    } else if ve > pdv {
        dt * profile::g((ve - pdv).min(next_cap), pdv)
    } else {
        0.0
    }
}

/// Largest speed at which a junction may be crossed, for one axis: `du` the jump of that
/// axis' share of the direction, `k` the arcs' chord turn (see `link_last`), `h` the shorter
/// of the two segments, `c` the axis' velocity change allowed per cycle for corners.
///
/// The axis velocity of a cycle is the setpoints' difference over `dt`; from one cycle to the
/// next it changes by `v·Σ du_j·φ_j` over the junctions `j` within `2·v·dt` of path, with tent
/// weights `φ_j ≤ 1` whose sum is at most 1 while the junctions are `≥ v·dt` apart (the
/// one-junction case: `v·du ≤ c`), and about `v·dt/h` when a chord chain packs them `h`
/// apart. Hence `k·v² + du·v·max(1, v·dt/h) ≤ c`. On a circle of radius `R` cut into chords
/// (`du ≈ h/R`) this is `v²/R ≤ c/dt`: the chain's centripetal acceleration gets the corner's
/// share of the axis' acceleration, independent of the chord length.
fn corner_speed(du: f64, k: f64, h: f64, c: f64, dt: f64) -> f64 {
    // The positive root of k·v² + du·v = c, in the form that is stable for k → 0.
    let v = 2.0 * c / (du + (du * du + 4.0 * k * c).sqrt());
    if v * dt <= h || !(du > 0.0) {
        return v;
    }
    // Junctions closer than a cycle's travel: (k + du·dt/h)·v² = c.
    let kk = k + du * dt / h.max(f64::MIN_POSITIVE);
    (c / kk).sqrt().min(v)
}

fn seg(geom: Geom, speed: Speed, v: f64, a: f64) -> Seg {
    let (t0, t1) = geom.tangents();
    Seg { geom, speed, vlim: finite_or_zero(v), alim: finite_or_zero(a), jlim: 0.0, t0, t1, blend_in: false, vj: 0.0, ext: 0.0 }
}

/// A C end point the spindle axis can resolve: finite and within ±[`C_MAX_DEG`].
fn check_c(c: f64) -> Result<(), Alarm> {
    if !c.is_finite() {
        return Err(Alarm::new(alarms::BAD_VALUE, format!("C end point is not a finite number ({c})")));
    }
    if c.abs() > C_MAX_DEG {
        return Err(Alarm::new(
            alarms::BAD_VALUE,
            format!("C end point {c:e}° is beyond what the spindle axis resolves (±{C_MAX_DEG:e}°, 2.8 million turns); check the macro variable that gives it"),
        ));
    }
    Ok(())
}

/// A rapid whose C differs from where the spindle was last programmed: Cs positioning.
fn end_c_moves(plan_c: Option<f64>, end: &Pos) -> bool {
    plan_c.is_some_and(|c| c != end.c && end.c.is_finite())
}

/// Start point of a segment's geometry.
fn geom_start(g: &Geom) -> [f64; 3] {
    g.at(0.0)
}

/// Distance along a line segment of the projection of `p` (X/Y/Z of an axis vector).
fn line_progress(g: &Geom, p: &[f64; N_AXES]) -> f64 {
    match *g {
        Geom::Line { start, delta, len, .. } if len > 0.0 => {
            ((p[0] - start[0]) * delta[0] + (p[1] - start[1]) * delta[1] + (p[2] - start[2]) * delta[2]) / len
        }
        _ => 0.0,
    }
}

fn finite_or_zero(v: f64) -> f64 {
    if v.is_finite() {
        v.max(0.0)
    } else {
        0.0
    }
}
