//! The sync correction of rigid taps and G92.1: the feed axes sent after the spindle's
//! *actual* angle, with their own lag pre-compensated, and what the models leave trimmed
//! from the measured sync error.
//!
//! One profile drives the spindle angle θ and the feed axes. Commanding both from the same θ
//! holds the relation on the *commands*; on the drives' actual positions it opens wherever
//! the spindle and a feed axis respond differently — at entry, reversal and exit, and
//! growing with the speed (a spindle is heavy with a soft position loop; a belt-driven axis
//! lags its command by milliseconds). So every cycle, for each feed axis locked to the
//! spindle (g = mm per spindle degree):
//!
//! 1. **Where it must actually be:** the nominal plus g × the spindle's measured lag
//!    (actual − sent, paired over the feedback delay from one SYNC, extrapolated to the
//!    cycle this set-point takes effect) — the axis follows the spindle's actual angle.
//! 2. **What to send so that it gets there:** that target plus the axis' own predicted lag,
//!    τ₁·v + (τ₁² + τ₂)·a of the target's speed and acceleration ([`LagModel`], learnt online
//!    from all the axis' motion — the rapid to R teaches it before the tap).
//! 3. **Trim:** the measured sync error (actual axis against actual spindle) integrated,
//!    with a gain bounded by the loop's delay (feedback delay + the axis' lag), so whatever
//!    the models miss (friction, load, a model still learning) is removed within a few
//!    cycles without ringing.
//!
//! The spindle's measured lag reaches step 1 through [`LagTracker`]: on a real-time PC the
//! SYNC's jitter puts noise into the sampled angle, which the tracker measures and filters;
//! the part of the lag fed forward fades out as that noise (in µm of the axis) rises from
//! [`FF_NOISE_FULL_UM`] to [`FF_NOISE_OFF_UM`] — past it the trim alone holds the relation,
//! which measures actual against actual at one SYNC and so sees no jitter. (Measured in
//! simulated time with the SYNC sent 0–0.3 ms late at random: every model of the matrix
//! stopped by alarm 2307 before, none after; `drive_matrix --jitter-us 300`.)
//!
//! The correction's change per cycle is bounded by the axis' acceleration (implausible
//! feedback must not kick it), its size by [`CORR_MAX`]; the bound brakes in time (the step
//! never exceeds what can still stop at the target), so a target that jumps back and forth
//! does not wind the offset up into an oscillation. It stays on through the strokes
//! and dwells of one hole and fades out afterwards. This is the Yaskawa Σ-V-SD scheme
//! (host-interpolated tapping: the feed axis follows the spindle's actual position) with
//! Siemens' idea of matched dynamics (the feed axis commanded ahead by its own lag). O(1),
//! no allocation.

use super::lag::{settle_lead, LagModel, LagSplit};
use super::lag_tracker::LagTracker;
use super::ring_guard::RingGuard;

/// Largest sync correction, mm (beyond it the sync monitor stops the machine anyway).
pub const CORR_MAX: f64 = 5.0;
/// Integral gain of the trim on the measured sync error, per cycle (at most; see `trim`).
const TRIM_GAIN: f64 = 0.3;
/// The trim's gain around a loop of d cycles is at most this over (d + 1) (`trim`).
const TRIM_DELAY_GAIN: f64 = 1.2;
/// Noise of the fed-forward spindle lag (µm at the axis) up to which it is fed forward whole
/// and taken as measured (no filtering): quantisation of a fine encoder, an ideal bus.
pub const FF_NOISE_FULL_UM: f64 = 0.4;
/// Noise at which none of it is fed forward any more: beyond ≈ 2 µm the noise, amplified by
/// the extrapolation over the feedback delay and the axis' lead, costs more than the lag it
/// removes (measured across the drive matrix with 0.3 and 0.8 ms of SYNC jitter).
pub const FF_NOISE_OFF_UM: f64 = 2.0;
/// Speed (mm/s) from which on a sample counts whole in the axes' lag fits (`LagModel::new`):
/// the rapids. Below it a sample weighs with its speed squared as before, but (floor)⁻²
/// more, so the slow approach to a first tap teaches the lag. A trade measured across the
/// drive matrix and 60 more models (25, 150, 300, 500 mm/s tried, in the air and with the SYNC
/// 0–0.3 ms late): faster learning took a Z with 85 % feed-forward at Kv 30/s from 4.1 to
/// 2.5 µm but fitted the jitter's noise too (default model, cut, jittered: 7.4 → 10.1 µm at
/// 25 mm/s, 8.4 at 300, where the low-feed-forward Z keeps 2.7 µm).
const LAG_FIT_FLOOR_MM_S: f64 = 300.0;
/// Share per cycle by which the lead's acceleration follows the second difference of the
/// spindle's measured lag (the nominal's is exact). The measured angle carries the encoder's
/// quantisation — a 4096-count spindle encoder: 0.088°, 0.37 µm of Z at a 1.5 mm pitch — and
/// the delay lead's D(D − 1)/2 multiplies that second difference by 6 where the axis has two
/// cycles of transport delay (D = 4): ±5 µm of set-point noise, and the rigid tap at S3000
/// lagged the spindle by up to 9.08 µm (2.61 with one cycle, 0.90 with none). Smoothed, the
/// count that alternates cycle by cycle averages out while the lag's change of rate (where a
/// ramp starts or ends) passes: 3.78 µm. Measured across 617 models in the air (simulated
/// time, `drive_matrix --air`): mean 2.13 → 2.09 µm, 123 better, 60 worse (by at most
/// 0.38 µm), none newly beyond a bound. Without the lag's share at all (0): 2.45 µm on that
/// model but the delay models 0.3–1.2 µm worse; the rigid tap under cutting load moved by
/// ≤ 1.1 µm either way (mean 5.11 → 5.24 µm at this value).
const LAG_ACCEL_SMOOTHING: f64 = 0.5;
/// After a tapped hole or G92.1 stroke the correction fades out by at most this per cycle, mm.
const CORR_FADE: f64 = 0.0005;

/// The sync correction's state: per feed axis (X, Y, Z).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SyncCorrection {
    /// Cycle, s; feedback delay, cycles; each axis' acceleration limit, mm/s².
    dt: f64,
    fd: usize,
    amax: [f64; 3],
    /// Each feed axis' lag model.
    lag: [LagModel; 3],
    /// mm per spindle degree of the locked stroke (0 = not locked).
    gain: [f64; 3],
    /// The offset sent this cycle and in the two before.
    corr: [f64; 3],
    prev: [f64; 3],
    prev2: [f64; 3],
    /// The spindle's measured lag, filtered, with its noise.
    tracker: LagTracker,
    /// The axes' target (actual position wanted) of the last two cycles.
    want_prev: [[f64; 3]; 2],
    /// The axes' nominal set-point of the last two cycles, and the smoothed second
    /// difference of the rest of the target (the spindle's lag, the trim's share apart): the
    /// lead's acceleration (see `axis`).
    nominal_prev: [[f64; 3]; 2],
    lag_accel: [f64; 3],
    /// The trim's integral, mm.
    trim: [f64; 3],
    /// The sync error measured this cycle (mm per axis; + = the axis ahead).
    err: [f64; 3],
    /// Each axis' lead through its lag's own settling, the delay's share apart
    /// (`LagModel::split`), mm.
    lead: [f64; 3],
    /// The delay share of each axis' lag the lead last split off (`LagModel::split`).
    delay: [f64; 3],
    /// The locked axes stand at rest in the hole (`rest`).
    resting: bool,
    /// Each axis' guard on its trim's loop.
    guard: [RingGuard; 3],
}

impl SyncCorrection {
    /// `dt` cycle (s), `fd` feedback delay (cycles), `amax` the axes' acceleration limits
    /// (mm/s²), `memory_s` the lag models' memory, `start` where the axes are.
    pub fn new(dt: f64, fd: usize, amax: [f64; 3], memory_s: f64, start: [f64; 3]) -> SyncCorrection {
        SyncCorrection {
            dt,
            fd: fd.max(1),
            amax,
            lag: [LagModel::new(memory_s / dt.max(1e-4), LAG_FIT_FLOOR_MM_S * dt); 3],
            gain: [0.0; 3],
            corr: [0.0; 3],
            prev: [0.0; 3],
            prev2: [0.0; 3],
            tracker: LagTracker::default(),
            want_prev: [start; 2],
            nominal_prev: [start; 2],
            lag_accel: [0.0; 3],
            trim: [0.0; 3],
            err: [0.0; 3],
            lead: [0.0; 3],
            delay: [0.0; 3],
            resting: false,
            guard: [RingGuard::default(); 3],
        }
    }

    /// This cycle's offset, to add to the nominal set-point of each feed axis.
    pub fn offset(&self) -> [f64; 3] {
        self.corr
    }

    /// The offset's change since the last cycle (for the velocity feed-forward).
    pub fn step(&self) -> [f64; 3] {
        [self.corr[0] - self.prev[0], self.corr[1] - self.prev[1], self.corr[2] - self.prev[2]]
    }

    /// The gain of the stroke locked last (kept between the strokes of one hole).
    pub fn gain(&self) -> [f64; 3] {
        self.gain
    }

    /// Nothing sent beyond the nominal any more.
    pub fn is_zero(&self) -> bool {
        self.corr == [0.0; 3]
    }

    /// The sync error the monitor measured this cycle, as a vector of the feed axes (mm).
    pub fn set_error(&mut self, e: [f64; 3]) {
        self.err = e;
    }

    /// Feed axis `i`'s learnt lag at constant speed, s.
    pub fn axis_lag(&self, i: usize) -> f64 {
        self.lag[i.min(2)].params().0 * self.dt
    }

    /// Feed axis `i`'s lag where it settles on its own (`LagModel::split`): the settling's
    /// share of its lag and the time constant of the lead that inverts it, both in cycles.
    pub fn settling(&self, i: usize) -> Option<(f64, f64)> {
        let m = &self.lag[i.min(2)];
        Some(m.thread_split()).filter(|s| s.settles()).map(|s| (s.settle, s.tf))
    }

    /// Learn from the feedback: `sent`, `before`, `before2` the set-points the feedback answers
    /// and the two before it, `actual` the feed axes' actual positions.
    pub fn learn(&mut self, sent: &[f64; 3], before: &[f64; 3], before2: &[f64; 3], actual: &[f64; 3]) {
        for i in 0..3 {
            let dv = sent[i] - before[i];
            let da = dv - (before[i] - before2[i]);
            if dv != 0.0 || da != 0.0 {
                self.lag[i].update(dv, da, sent[i] - actual[i]);
            }
        }
    }

    /// One cycle. `gain`: mm per spindle degree of the locked stroke, None when nothing is
    /// locked (the correction fades out); `nominal`: this cycle's nominal set-point;
    /// `spindle_lag`: the spindle's actual − sent, paired over the feedback delay; NaN when
    /// this cycle brought no fresh sample (the lag then coasts on its tracked rate).
    pub fn update(&mut self, gain: Option<[f64; 3]>, nominal: &[f64; 3], spindle_lag: f64) {
        self.prev2 = self.prev;
        self.prev = self.corr;
        let Some(g) = gain else {
            self.release(nominal);
            return;
        };
        self.gain = g;
        let e_s = self.fed_forward(&g, spindle_lag);
        for i in 0..3 {
            if g[i] != 0.0 {
                self.corr[i] = self.axis(i, nominal[i] + g[i] * e_s, nominal[i]);
            }
        }
    }

    /// The spindle lag to follow (degrees): the tracked lag extrapolated by (delay − 1)
    /// cycles — one cycle less than the feedback delay tracks best (the actual is sampled at
    /// the SYNC the demand acts on) — weighted down as its noise rises (module doc).
    fn fed_forward(&mut self, g: &[f64; 3], spindle_lag: f64) -> f64 {
        let mm_per_deg = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let exact_below = if mm_per_deg > 0.0 { FF_NOISE_FULL_UM * 1e-3 / mm_per_deg } else { f64::INFINITY };
        // No fresh sample this cycle (a late TPDO): coast on the tracked rate.
        let (x, v) = if spindle_lag.is_finite() { self.tracker.update(spindle_lag, exact_below) } else { self.tracker.coast() };
        let noise_um = self.tracker.noise() * mm_per_deg * 1e3;
        let w = ((FF_NOISE_OFF_UM - noise_um) / (FF_NOISE_OFF_UM - FF_NOISE_FULL_UM)).clamp(0.0, 1.0);
        w * (x + (self.fd as f64 - 1.0) * v)
    }

    /// Axis `i`'s value `x` of this cycle into `hist` (the last two); its second difference.
    fn push(hist: &mut [[f64; 3]; 2], i: usize, x: f64) -> f64 {
        let da = (x - hist[0][i]) - (hist[0][i] - hist[1][i]);
        hist[1][i] = hist[0][i];
        hist[0][i] = x;
        da
    }

    /// The offset of locked axis `i` whose actual position must be `want`. The lead's
    /// acceleration is the nominal's plus the spindle lag's smoothed (`LAG_ACCEL_SMOOTHING`).
    fn axis(&mut self, i: usize, want: f64, nominal: f64) -> f64 {
        let dv = want - self.want_prev[0][i];
        let da_nominal = Self::push(&mut self.nominal_prev, i, nominal);
        let da_lag = Self::push(&mut self.want_prev, i, want) - da_nominal;
        self.lag_accel[i] += LAG_ACCEL_SMOOTHING * (da_lag - self.lag_accel[i]);
        let da = da_nominal + self.lag_accel[i];
        self.trim(i);
        let c = (want - nominal + self.lead_of(i, dv, da) + self.trim[i]).clamp(-CORR_MAX, CORR_MAX);
        let amax = self.amax[i] * self.dt * self.dt;
        let step_prev = self.prev[i] - self.prev2[i];
        // Toward the target no faster than can still stop there (else a target jumping to and
        // fro winds the offset up), and the step changed by at most the acceleration.
        let d = c - self.prev[i];
        let stoppable = if amax.is_finite() { 0.5 * ((amax * amax + 8.0 * amax * d.abs()).sqrt() - amax) } else { f64::INFINITY };
        let step = (d.signum() * d.abs().min(stoppable)).clamp(step_prev - amax, step_prev + amax);
        self.prev[i] + step
    }

    /// Axis `i`'s lead for the target's increments. Where the lag settles on its own (a soft
    /// loop with low feed-forward, Kv 25 and ff 0.90: over 40 ms) the lead is split
    /// (`LagModel::split`): the delay's share predicts the target's travel over the delay,
    /// the settling's share goes through the lead that inverts the settling — the two-term
    /// lead, exact only where the acceleration changes slowly, missed it by 4–8 µm where the
    /// tap's acceleration ends, in the air; and a settling lead that also filtered the
    /// delay's share missed by as much on a Z with two cycles of transport delay and 85 %
    /// feed-forward (6.7 µm; split 1.9).
    fn lead_of(&mut self, i: usize, dv: f64, da: f64) -> f64 {
        let m = &self.lag[i];
        let s = m.split();
        // The split moved: hand the share that changes side over, so the lead stays whole.
        if s.delay != self.delay[i] {
            let old = LagSplit { delay: self.delay[i], ..s };
            self.lead[i] += old.delay_lead(dv, da) - s.delay_lead(dv, da);
            self.delay[i] = s.delay;
        }
        if !s.settles() {
            // The settling's share tracked all the same: the fit may cross into a settling
            // lag mid-stroke.
            let lead = m.lead(dv, da);
            self.lead[i] = lead - s.delay_lead(dv, da);
            return lead;
        }
        // The settling answers the speed `delay` cycles ahead.
        self.lead[i] = settle_lead(self.lead[i], s.settle * (dv + s.delay * da), s.tf);
        s.delay_lead(dv, da) + self.lead[i]
    }

    /// The locked axes stand at rest (a dwell in the hole): the trim fades out instead of
    /// integrating (`trim`), over the axis' own settling time.
    pub fn rest(&mut self, at_rest: bool) {
        self.resting = at_rest;
    }

    /// Integrate the measured error, at a gain set by the loop's delay d: the feedback delay,
    /// the axis' lag at speed (τ₁) and, where its lag grows with the acceleration (τ₂ > 0: a
    /// velocity loop slower than its feed-forward, which reads as almost no τ₁), √τ₂ — the
    /// period of that response. An integrator around a pure delay of D cycles is stable below
    /// ≈ 1.6/(D + 0.5) per cycle; 1.2/(d + 1), at most 0.3, is measured side by side across
    /// 254 drive models in the air (the repo's 62, seeds 20261204 and 20261205 with and without
    /// `--loops`): the tap at S3000 mean 2.05 → 1.64 µm on the repo's, models over 5 µm 11 → 3
    /// (belts on other velocity loops: one rings at rest on its own); 0.15 and 0.6/(d + 1)
    /// before. A cap of 0.4 rang two models up to alarm 2307 (a heavy load and a soft spindle,
    /// each behind a slow velocity loop), so the margin is thin: [`RingGuard`] halves the gain
    /// where the loop rings — at twice these gains it kept all 254 models clear of any alarm.
    fn trim(&mut self, i: usize) {
        let e = self.err[i];
        if self.resting {
            // The lag it made up for settles as the drive's own lag does: fade with that time
            // (over 345 taps with a dwell, 115 models: as fast as after the hole, CORR_FADE,
            // alike within 0.01 µm on the mean, 1.90 µm; 2.02 holding the trim).
            let m = &self.lag[i];
            let s = m.split();
            let t = if s.settles() { s.tf + s.settle } else { m.params().0.max(1.0) };
            self.trim[i] -= self.trim[i] / (1.0 + t);
        } else if e.is_finite() {
            let (t1, t2) = self.lag[i].params();
            let d = self.fd as f64 + t1 + t2.max(0.0).sqrt();
            self.guard[i].update(e);
            self.trim[i] -= self.guard[i].scale() * TRIM_GAIN.min(TRIM_DELAY_GAIN / (d + 1.0)) * e;
        }
    }

    /// Nothing locked: fade the offset out, forget the lock.
    fn release(&mut self, nominal: &[f64; 3]) {
        self.gain = [0.0; 3];
        self.tracker.restart();
        self.trim = [0.0; 3];
        self.lead = [0.0; 3];
        for i in 0..3 {
            let at = nominal[i] + self.corr[i];
            self.want_prev[0][i] = at;
            self.want_prev[1][i] = at;
            self.nominal_prev[0][i] = nominal[i];
            self.nominal_prev[1][i] = nominal[i];
            self.lag_accel[i] = 0.0;
            self.corr[i] -= self.corr[i].clamp(-CORR_FADE, CORR_FADE);
        }
    }

    /// Taken over by a fault follow (`motion::fault`): send the nominal only.
    pub fn clear(&mut self) {
        self.prev2 = self.prev;
        self.prev = self.corr;
        self.corr = [0.0; 3];
        self.gain = [0.0; 3];
        self.tracker.restart();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_locked_axis_follows_the_spindles_lag_and_fades_out_after() {
        let mut c = SyncCorrection::new(0.002, 2, [2000.0; 3], 2.0, [0.0; 3]);
        // The spindle lags 2° (actual − sent = −2) at 1.5 mm/rev: Z must stay 2/360·1.5 back.
        let g = [0.0, 0.0, 1.5 / 360.0];
        for _ in 0..2000 {
            c.update(Some(g), &[0.0; 3], -2.0);
        }
        let want = -2.0 * 1.5 / 360.0;
        assert!((c.offset()[2] - want).abs() < 1e-9, "offset {} want {want}", c.offset()[2]);
        assert_eq!(c.offset()[0], 0.0);
        for _ in 0..100 {
            c.update(None, &[0.0; 3], 0.0);
        }
        assert!(c.is_zero(), "faded out: {:?}", c.offset());
    }

    #[test]
    fn the_trim_removes_a_steady_error_without_ringing() {
        let mut c = SyncCorrection::new(0.002, 2, [2000.0; 3], 2.0, [0.0; 3]);
        let g = [0.0, 0.0, 1.0];
        // A plant whose actual is the set-point of two cycles before, 10 µm off.
        let mut hist = [0.0f64; 2];
        let mut errs = Vec::new();
        for _ in 0..400 {
            let e = hist[0] + 0.010;
            errs.push(e);
            c.set_error([0.0, 0.0, e]);
            c.update(Some(g), &[0.0; 3], 0.0);
            hist = [hist[1], c.offset()[2]];
        }
        let last = *errs.last().unwrap();
        assert!(last.abs() < 1e-9, "error left {last}");
        // Well damped: it never overshoots by more than a tenth of the step.
        let worst = errs.iter().fold(0.0f64, |m, e| m.min(*e));
        assert!(worst > -0.001, "overshoot {worst}");
    }
}
