//! Friction feed-forward for a feed axis in CSP, through the drive's torque offset 0x60B2
//! (`axes.NAME.friction_compensation`).
//!
//! Why: a drive in CSP holds its dry friction with the velocity loop's integrator. Where the
//! axis starts from rest, or reverses, that integrator must swing through twice the friction
//! before the slide moves, and for those cycles the slide sticks while its set-point runs on —
//! at the start of a rigid tap the feed axis then trails the spindle by the whole stiction
//! (4× the default friction: Z stuck for 9 cycles, 12 µm). A production CNC feeds the friction
//! forward (Fanuc's static friction compensation, SINUMERIK's friction compensation in the
//! drive); a CSP master does it through 0x60B2, which the drive adds to its torque command
//! with the set-point it comes with.
//!
//! How much: learnt online from the drive's torque actual 0x6077 (both per mille of the rated
//! torque 0x6076, so no unit is needed) while the axis moves, by least squares with forgetting
//! over `T = c₊·[v > 0] + c₋·[v < 0] + J·a` — the torque the axis needs moving up and down,
//! inertia apart. Each direction keeps its own figure (a vertical axis' weight makes them
//! differ); a direction not yet travelled is taken as the mirror of the other (a soft prior,
//! outweighed by the first few samples of its own). Nothing is sent before the fit has
//! enough samples; no friction above [`MAX_PERMILLE`] is fed forward.
//!
//! When: where the command starts from rest or reverses — that is where the integrator is
//! late — in the direction of the commanded speed, ramped over the first [`BAND_COUNTS`]
//! counts per cycle (a set-point that barely moves does not kick the slide). What the drive's
//! integrator holds at that moment is taken out (measured from 0x6077 where the slide stood —
//! a slide stuck against its set-point, or creeping in, holds up to its friction either way;
//! at a reversal, what it has taken over of the last offset), so that drive and offset together
//! give the friction: the slide breaks away at once, neither sticking nor jumping. Once the
//! slide moves in the new direction the offset hands over to the integrator (some 100 ms), and
//! where the command comes to rest what is left fades in ten cycles: stops, and the slide
//! settling onto its count, are the drive's own, as without the offset (an offset that
//! followed the slide into its stop made it hunt, and stop short or past).
//!
//! Not on a compliant axis: behind a belt (or a long screw's lost motion) the motor is not
//! held by the friction — the slide is, and the belt winds up to it as the motor turns. A kick
//! there throws the motor ahead of its set-point by the belt's whole wind-up (a belt with
//! 2.7 times the default friction: 7.3 µm of sync error at the rigid tap's start, 4.7 µm
//! without the offset), and the torque the drive holds at rest is the belt's, not
//! friction's. Which one the axis is shows at its first start, before anything is fed
//! forward: a rigid slide does not move until the drive's torque has risen to its friction;
//! the motor behind a belt moves at once, with a fraction of it. [`FrictionComp::compliant`]
//! says what was found; a compliant axis gets no offset.

use nalgebra::{Matrix3, Vector3};

/// Commanded speed (counts per cycle) over which the offset ramps to its full value.
pub const BAND_COUNTS: f64 = 1.0;
/// Largest friction fed forward, per mille of the rated torque: box ways under a heavy table
/// can take a third of it (eight times the emulator's friction, 380 ‰, is fed forward whole);
/// more than half is a mechanical fault, not something to feed forward.
pub const MAX_PERMILLE: f64 = 500.0;
/// Actual speed (counts per cycle) below which a torque sample says nothing about friction
/// (stiction and the velocity loop's settling dominate there).
const MIN_SAMPLE_SPEED: f64 = 4.0;
/// Samples (in weight) before the fit is used.
const MIN_SAMPLES: f64 = 8.0;
/// Forgetting factor per sample: the fit follows friction that changes as the slide warms
/// (a memory of a few hundred samples).
const FORGET: f64 = 0.995;
/// Weight of the prior "the unseen direction mirrors the seen one" (samples).
const MIRROR_PRIOR: f64 = 1.0;
/// Motion of the motor (counts) that shows it has started at its first start.
const PROBE_MOVED_COUNTS: f64 = 2.0;
/// Share of the friction the drive's torque has risen by when a rigid slide moves (all of
/// it, less what one cycle's sampling misses); a motor behind a belt moves with far less.
const PROBE_RIGID_SHARE: f64 = 0.5;
/// Friction (per mille) below which the first start cannot tell (nothing to feed forward).
const PROBE_MIN_PERMILLE: f64 = 5.0;

/// One axis' friction feed-forward. Allocation-free; all inputs are counts and per mille.
#[derive(Clone, Debug, Default)]
pub struct FrictionComp {
    /// Normal equations of the fit (φ = [s₊, s₋, a]).
    s: Matrix3<f64>,
    r: Vector3<f64>,
    /// Sample weight seen (with forgetting).
    n: f64,
    /// The torque the axis needs moving in + and − (per mille), when the fit has enough.
    c: Option<(f64, f64)>,
    /// The last two actual positions (counts) and the speed between them.
    act: Option<i64>,
    v_act: Option<f64>,
    a_act: f64,
    /// The previous set-point (counts, unrounded).
    prev_cmd: Option<f64>,
    /// The last offset sent; the drive's torque where the slide last stood (filtered).
    sent: i16,
    t_rest: f64,
    /// The direction of the command's motion (0 at rest), the cycles it has stood still.
    dir: f64,
    still: u32,
    /// Since the last start or reversal: what the drive's integrator held then, the friction
    /// to overcome now (per mille) and the share of it the offset still carries.
    i0: f64,
    f: f64,
    env: f64,
    /// The first start, watched unkicked: the drive's torque where the motor stood and the
    /// position and direction it started from; then the rise of torque (in the direction of
    /// motion) by the time the motor had moved; then the verdict.
    probe: Probe,
}

/// What the first start showed (see the module doc).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
enum Probe {
    #[default]
    Waiting,
    Started {
        from: i64,
        dir: f64,
        t0: f64,
    },
    Moved {
        dir: f64,
        t0: f64,
        rise: f64,
    },
    Found {
        compliant: bool,
    },
}

/// Where the command has come to rest, what is left of the offset fades by this per cycle
/// (towards 0, never past it): the slide comes in on the drive's own loops.
const FADE: f64 = 0.85;
/// While the command moves on in one direction the offset hands over to the drive's
/// integrator by this per cycle (some 100 ms): the offset breaks the slide away where it
/// starts or reverses, the integrator carries the friction of the motion, so that where the
/// command stops the slide comes in exactly as without the offset.
const DECAY: f64 = 0.98;

impl FrictionComp {
    /// A fresh position feedback (counts, once per cycle).
    pub fn observe_actual(&mut self, counts: i64) {
        if let Some(p) = self.act {
            let v = (counts - p) as f64;
            if let Some(v0) = self.v_act {
                self.a_act = v - v0;
            }
            self.v_act = Some(v);
        }
        self.act = Some(counts);
    }

    /// A torque actual value 0x6077 read from the drive (per mille of the rated torque).
    pub fn torque_sample(&mut self, permille: i16) {
        // The drive's own torque (ours taken out), averaged over a few cycles (a belt rings).
        self.t_rest += (f64::from(permille) - f64::from(self.sent) - self.t_rest) * 0.25;
        if let (Probe::Started { from, dir, t0 }, Some(p)) = (self.probe, self.act) {
            if (p - from) as f64 * dir >= PROBE_MOVED_COUNTS {
                self.probe = Probe::Moved { dir, t0, rise: (f64::from(permille) - t0) * dir };
            }
        }
        let Some(v) = self.v_act.filter(|v| v.abs() >= MIN_SAMPLE_SPEED) else { return };
        let phi = Vector3::new(f64::from(u8::from(v > 0.0)), f64::from(u8::from(v < 0.0)), self.a_act);
        self.s = self.s * FORGET + phi * phi.transpose();
        self.r = self.r * FORGET + phi * f64::from(permille);
        self.n = self.n * FORGET + 1.0;
        self.c = self.solve();
    }

    /// The fit: the prior row (c₊ + c₋ = 0, weight `MIRROR_PRIOR`) keeps an untravelled
    /// direction determined; a little ridge keeps the inertia term determined at constant speed.
    fn solve(&self) -> Option<(f64, f64)> {
        if self.n < MIN_SAMPLES {
            return None;
        }
        let prior = Vector3::new(1.0, 1.0, 0.0);
        let m = self.s + prior * prior.transpose() * MIRROR_PRIOR + Matrix3::from_diagonal(&Vector3::new(1e-6, 1e-6, 1e-3));
        let x = m.cholesky()?.solve(&self.r);
        let clamp = |c: f64| c.clamp(-MAX_PERMILLE, MAX_PERMILLE);
        (x[0].is_finite() && x[1].is_finite()).then(|| (clamp(x[0]), clamp(x[1])))
    }

    /// The learnt torque moving + and − (per mille), once the fit has enough samples.
    pub fn learnt(&self) -> Option<(f64, f64)> {
        self.c
    }

    /// Whether the first start showed a compliant axis (None: not yet known).
    pub fn compliant(&self) -> Option<bool> {
        match self.probe {
            Probe::Found { compliant } => Some(compliant),
            _ => None,
        }
    }

    /// Watch the first start (before anything is fed forward): `v` the command's step, with
    /// the fit `c` once it is learnt to judge what was seen.
    fn watch_first_start(&mut self, v: f64) {
        match self.probe {
            Probe::Waiting if v != 0.0 && self.dir == 0.0 => {
                if let Some(from) = self.act {
                    self.probe = Probe::Started { from, dir: v.signum(), t0: self.t_rest };
                }
            }
            // Reversed or stopped before the motor moved: watch the next start.
            Probe::Started { dir, .. } if v.signum() != dir => self.probe = Probe::Waiting,
            // Judged against the friction's size (the first move's fit, through a rapid's
            // acceleration and braking, may still have its signs wrong).
            Probe::Moved { dir, t0, rise } => {
                let Some((up, down)) = self.c else { return };
                let need = up.abs().max(down.abs()) - t0 * dir;
                if need >= PROBE_MIN_PERMILLE {
                    self.probe = Probe::Found { compliant: rise < PROBE_RIGID_SHARE * need };
                }
            }
            _ => {}
        }
    }

    /// The torque offset to send with the set-point `cmd` (counts, unrounded), per mille.
    pub fn offset(&mut self, cmd: f64) -> i16 {
        let v = self.prev_cmd.map_or(0.0, |p| cmd - p);
        self.prev_cmd = Some(cmd);
        self.watch_first_start(v);
        if self.compliant() == Some(true) {
            self.sent = 0;
            return 0;
        }
        let Some((up, down)) = self.c else {
            // Not learnt yet: follow the command's direction only, so that a fit that comes
            // in mid-move does not start there (the drive carries this motion's friction;
            // at its reversal the integrator holds it whole: `f`, with nothing handed over).
            self.dir = if v == 0.0 { 0.0 } else { v.signum() };
            (self.env, self.i0, self.f) = (0.0, 0.0, 0.0);
            return 0;
        };
        if v == 0.0 {
            // The command at rest: the offset fades, the slide comes in as without it.
            self.still = self.still.saturating_add(1);
            if self.still >= 2 {
                self.dir = 0.0;
            }
            self.sent = (f64::from(self.sent) * FADE).trunc() as i16;
            return self.sent;
        }
        let lim = up.abs().max(down.abs());
        if v.signum() != self.dir {
            // A start or a reversal: what the drive's integrator holds now — measured where
            // the slide stood, else what it has taken over of the last motion's offset. Of the
            // last motion's whole friction, not of the last step's ramped share: a command
            // that slows to a creep before it reverses (a sync correction at a tap's bottom)
            // leaves the integrator holding the friction of the motion, and a kick sized on
            // the creep's share left a slide with a slow velocity loop stuck for 8 cycles.
            let last = if self.dir > 0.0 { up } else { down };
            let held = if self.dir == 0.0 { self.t_rest } else { self.i0 + (1.0 - self.env) * (last - self.i0) };
            self.i0 = held.clamp(-lim, lim);
            self.dir = v.signum();
            self.env = 1.0;
        } else if self.v_act.is_some_and(|va| va * self.dir >= 1.0) {
            // Broken away: hand over. (Not before: a command creeping out of its start
            // must find the whole offset when it gets going.)
            self.env *= DECAY;
        }
        self.still = 0;
        let w = (v / BAND_COUNTS).clamp(-1.0, 1.0);
        self.f = if w > 0.0 { up * w } else { -down * w };
        // Bounded by twice the largest friction: with what the drive holds taken out, the
        // torque the two give together is the friction (≤ MAX_PERMILLE).
        self.sent = (self.env * (self.f - self.i0)).clamp(-2.0 * MAX_PERMILLE, 2.0 * MAX_PERMILLE).round() as i16;
        self.sent
    }

    /// The drive stopped following set-points (disabled, a stop): the next set-point starts a
    /// new speed, and the position history is stale.
    pub fn reset_motion(&mut self) {
        self.prev_cmd = None;
        if matches!(self.probe, Probe::Started { .. }) {
            self.probe = Probe::Waiting;
        }
        self.sent = 0;
        self.dir = 0.0;
        self.still = 0;
        self.i0 = 0.0;
        self.f = 0.0;
        self.env = 0.0;
        self.act = None;
        self.v_act = None;
        self.a_act = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Drive a simulated axis: speed profile in counts/cycle, torque = friction + inertia.
    fn run(fc: &mut FrictionComp, speeds: &[f64], up: f64, down: f64, j: f64) {
        let mut pos = 0.0;
        let mut v0 = 0.0;
        for &v in speeds {
            pos += v;
            fc.observe_actual(pos as i64);
            let fr = if v > 0.0 {
                up
            } else if v < 0.0 {
                down
            } else {
                0.0
            };
            fc.torque_sample((fr + j * (v - v0)).round() as i16);
            v0 = v;
        }
    }

    fn ramp(vmax: f64, n: usize) -> Vec<f64> {
        let mut s: Vec<f64> = (1..=n).map(|k| vmax * k as f64 / n as f64).collect();
        s.extend((0..n).rev().map(|k| vmax * k as f64 / n as f64));
        s
    }

    #[test]
    fn learns_the_friction_of_a_move_that_only_accelerates_and_brakes() {
        // A short rapid: no constant speed at all, inertia torque larger than the friction.
        let mut fc = FrictionComp::default();
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        let (up, down) = fc.learnt().expect("enough samples");
        assert!((up - 60.0).abs() < 3.0, "up {up}");
        assert!((down + 60.0).abs() < 6.0, "down (mirrored) {down}");
    }

    #[test]
    fn keeps_each_direction_of_a_weighted_axis() {
        // A vertical axis: its weight adds 40 ‰ both ways.
        let mut fc = FrictionComp::default();
        let mut prof = ramp(300.0, 20);
        prof.extend(ramp(-300.0, 20));
        run(&mut fc, &prof, 100.0, -20.0, 2.0);
        let (up, down) = fc.learnt().unwrap();
        assert!((up - 100.0).abs() < 4.0 && (down + 20.0).abs() < 4.0, "{up} {down}");
    }

    /// The slide stands still and the drive holds `t` (per mille): settle the filter.
    fn stand(fc: &mut FrictionComp, t: i16) {
        for _ in 0..60 {
            fc.torque_sample(t);
            fc.offset(fc.prev_cmd.unwrap_or(0.0));
        }
    }

    #[test]
    fn sends_nothing_until_learnt_nothing_at_rest_and_ramps_in() {
        let mut fc = FrictionComp::default();
        assert_eq!(fc.offset(0.0), 0);
        assert_eq!(fc.offset(10.0), 0, "not learnt yet");
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        stand(&mut fc, 0);
        assert_eq!(fc.offset(10.0), 0, "at rest: friction holds");
        let (up, down) = fc.learnt().unwrap();
        assert_eq!(fc.offset(10.5), (up * 0.5).round() as i16, "half the band: half the friction");
        assert_eq!(fc.offset(20.5), up.round() as i16);
        assert_eq!(fc.offset(15.0), down.round() as i16, "reversed");
        assert!((55.0..65.0).contains(&up) && (-65.0..-55.0).contains(&down), "{up} {down}");
    }

    #[test]
    fn where_the_command_stops_the_offset_fades_and_never_turns() {
        let mut fc = FrictionComp::default();
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        stand(&mut fc, 0);
        let up = fc.learnt().unwrap().0;
        assert_eq!(fc.offset(10.0), up.round() as i16);
        // Command at rest: the offset fades to 0, never past it.
        let sent: Vec<i16> = (0..30).map(|_| fc.offset(10.0)).collect();
        assert_eq!(sent[0], (f64::from(up.round() as i16) * FADE).trunc() as i16);
        assert!(sent.windows(2).all(|w| w[1] <= w[0] && w[1] >= 0), "{sent:?}");
        assert_eq!(*sent.last().unwrap(), 0);
    }

    #[test]
    fn a_start_from_rest_takes_out_what_the_drive_holds_and_hands_over_once_moving() {
        let mut fc = FrictionComp::default();
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        let up = fc.learnt().unwrap().0;
        // Stuck with the integrator pushing the other way (−20 ‰): the start sends up + 20.
        stand(&mut fc, -20);
        let first = fc.offset(5.0);
        assert!((f64::from(first) - (up + 20.0)).abs() <= 1.0, "{first} vs {up} + 20");
        // Not moving yet: the whole offset stays.
        fc.observe_actual(1000);
        fc.observe_actual(1000);
        assert_eq!(fc.offset(10.0), first);
        // Broken away: it hands over to the drive, cycle by cycle.
        let mut pos = 1000;
        let mut sent = Vec::new();
        for k in 0..200 {
            pos += 5;
            fc.observe_actual(pos);
            sent.push(fc.offset(15.0 + 5.0 * k as f64));
        }
        assert!(sent.windows(2).all(|w| w[1] <= w[0]), "{sent:?}");
        assert!(sent[0] < first && sent[199].abs() <= 1, "{sent:?}");
    }

    /// A learnt axis moved up long enough that the drive carries the friction (300 cycles at 5
    /// counts): the axis, its learnt (up, down) and where the command stands.
    fn moved_up() -> (FrictionComp, (f64, f64), f64) {
        let mut fc = FrictionComp::default();
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        stand(&mut fc, 0);
        let learnt = fc.learnt().unwrap();
        for k in 1..=300 {
            fc.observe_actual(5 * k);
            fc.offset(5.0 * k as f64);
        }
        (fc, learnt, 1500.0)
    }

    #[test]
    fn a_reversal_swings_the_whole_friction() {
        let (mut fc, (up, down), cmd) = moved_up();
        let back = fc.offset(cmd - 5.0);
        // The offset takes out what the integrator holds (≈ up) and adds the friction down.
        assert!((f64::from(back) - (down - up)).abs() <= 2.0, "{back} vs {down} − {up}");
    }

    #[test]
    fn a_reversal_after_a_creep_still_swings_the_whole_friction() {
        let (mut fc, (up, down), cmd) = moved_up();
        // The command slows to a creep (a twentieth of the band) and turns back at once: the
        // drive's integrator still holds the motion's friction, not the creep's share of it.
        fc.offset(cmd + 0.05);
        let back = fc.offset(cmd - 5.0);
        assert!((f64::from(back) - (down - up)).abs() <= 2.0, "{back} vs {down} − {up}");
    }

    #[test]
    fn a_fit_that_comes_in_mid_move_waits_for_the_next_start() {
        // The first move of a run teaches the fit: nothing is sent within it (the drive
        // carries its friction), the reversal after it swings the whole friction.
        let mut fc = FrictionComp::default();
        let (mut pos, mut cmd) = (0i64, 0.0);
        let mut sent = Vec::new();
        for k in 0..40 {
            let v = if k < 8 { 50.0 * f64::from(k) } else { 400.0 };
            cmd += v;
            sent.push(fc.offset(cmd));
            pos += v as i64;
            fc.observe_actual(pos);
            fc.torque_sample(60);
        }
        let (up, down) = fc.learnt().expect("learnt within the move");
        assert!(sent.iter().all(|&t| t == 0), "{sent:?}");
        let back = fc.offset(cmd - 10.0);
        assert!((f64::from(back) - (down - up)).abs() <= 2.0, "{back} vs {down} − {up}");
    }

    #[test]
    fn never_sends_more_than_the_bound() {
        let mut fc = FrictionComp::default();
        run(&mut fc, &ramp(400.0, 16), 900.0, -900.0, 0.0);
        stand(&mut fc, 0);
        assert_eq!(fc.offset(5.0), MAX_PERMILLE as i16);
        // The drive holding −500 ‰ is taken for −300 at most: together they give the bound.
        stand(&mut fc, -500);
        assert_eq!(fc.offset(10.0), 2 * MAX_PERMILLE as i16, "with what the drive holds taken out");
    }

    /// The first start, unkicked: the command ramps up; for `stick` cycles the motor stands
    /// while the drive's torque rises to the friction (60 ‰), then it follows the command,
    /// the torque rising with its travel over `wind` counts (a belt winding up) before it
    /// carries the friction; then a move that teaches the fit. What the next start sends.
    fn first_start(stick: usize, wind: f64) -> (Option<bool>, i16) {
        let mut fc = FrictionComp::default();
        let (mut cmd, mut pos, mut from) = (0.0, 0i64, 0i64);
        stand(&mut fc, 0);
        for k in 0..40usize {
            cmd += 0.5 * k as f64;
            fc.offset(cmd);
            let t = if k < stick {
                from = cmd as i64;
                60.0 * k as f64 / stick as f64
            } else {
                pos = cmd as i64;
                60.0 * ((pos - from) as f64 / wind).min(1.0)
            };
            fc.observe_actual(pos);
            fc.torque_sample(t as i16);
        }
        run(&mut fc, &ramp(400.0, 16), 60.0, -60.0, 3.0);
        stand(&mut fc, 0);
        let sent = fc.offset(fc.prev_cmd.unwrap_or(0.0) + 5.0);
        (fc.compliant(), sent)
    }

    #[test]
    fn a_rigid_slide_that_sticks_at_its_first_start_gets_the_offset() {
        // The motor stands until the drive has the friction: rigid.
        let (compliant, sent) = first_start(6, 1.0);
        assert_eq!(compliant, Some(false));
        assert!(sent >= 55, "{sent}");
    }

    #[test]
    fn a_motor_that_moves_with_a_fraction_of_the_friction_is_behind_a_belt() {
        // The motor follows at once; the belt takes 200 counts to wind up: no offset, ever.
        let (compliant, sent) = first_start(0, 200.0);
        assert_eq!(compliant, Some(true));
        assert_eq!(sent, 0);
    }

    #[test]
    fn samples_at_creeping_speed_are_ignored() {
        let mut fc = FrictionComp::default();
        run(&mut fc, &[1.0; 50], 500.0, -500.0, 0.0);
        assert!(fc.learnt().is_none());
    }
}
