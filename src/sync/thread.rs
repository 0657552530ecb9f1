//! Spindle-synchronised thread cutting: where along the thread the feed axes must be, as a
//! function of the *measured* spindle angle.
//!
//! The cut is locked to the spindle: after the lead-in, the path position is
//! `s = lead_path · (θ − θ0) / 360` (θ measured, continuous degrees, in the direction of
//! rotation), where `θ0 ≡ start_angle (mod 360)` after the one-revolution reference (angle 0).
//! So every pass of a multi-pass thread, and every start of a multi-start thread, lands in the
//! same groove, whatever the spindle angle was when the pass began.
//!
//! Lead-in: the axis cannot jump to the synchronous speed `v`. Instead of starting at θ0 and
//! lagging behind by `v²/2a` for the whole cut (Fanuc's exponential lead-in does that), it starts
//! early, at `θ0 − Δθ` with `Δθ = ω·v/(2a)`, and ramps at `a`: a constant-acceleration ramp
//! from rest meets the synchronous line `lead_path·(θ − θ0)/360` exactly when it reaches `v`. The
//! lead is short only within the ramp (the programmer's δ1 zone), and the phase is exact.
//! With [`ThreadSync::arm_smooth`] the ramp's acceleration rises and falls over `tj` and
//! `1.5·tj` (the constant-acceleration ramp averaged over `tj`, then over `1.5·tj`,
//! [`SECOND_SMOOTH`]): a symmetric profile meets the line at its centroid, so it starts
//! `ω·2.5·tj/2` earlier still and the line is the same.
//!
//! G34 variable lead: the lead grows by `k` per revolution, so after `n` revolutions from θ0
//! the path position is `L0·n + k·n²/2` (the sum of the leads, in closed form). The quadratic
//! term is added to the ramp as well, from θ0 on: it is zero with zero slope there, so the
//! target stays continuous in position and speed.
//!
//! Continuous segments (consecutive G32 blocks, the run-out of G92/G76/G78): a segment that
//! follows a thread segment directly keeps its spindle lock. [`ThreadSync::continue_with`]
//! counts the revolutions the previous segment takes on the synchronous line and starts the
//! next one's line there, so the axes go on without waiting, without a stop, and without a
//! phase jump.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN, which must be refused.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// Axis loops index several per-axis arrays at once.
#![allow(clippy::needless_range_loop)]

/// One armed thread pass.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThreadSync {
    /// +1 (M03) or −1 (M04): the direction the measured angle runs.
    dir: f64,
    /// Measured angle at which the axis starts moving, degrees.
    theta_start: f64,
    /// Angle at which the synchronous line passes the start of the thread, degrees.
    theta0: f64,
    /// Spindle speed when armed, deg/s (> 0).
    omega: f64,
    /// Lead-in ramp acceleration, mm/s² (> 0).
    a: f64,
    /// Synchronous path speed at `omega`, mm/s.
    v: f64,
    /// Path length per spindle revolution at the segment's start, mm.
    lead_path: f64,
    /// G34: change of `lead_path` per revolution, mm/rev (0 = constant lead).
    k: f64,
    /// Revolutions from θ0 (along the synchronous line) at which this segment starts.
    n_start: f64,
    /// This segment was armed (has the lead-in ramp); false for a continuation.
    ramp: bool,
    /// Time over which the lead-in's acceleration rises and falls (moving average of the
    /// constant-acceleration ramp), s; 0 = a step in acceleration.
    tj: f64,
    /// A second moving average after the first, [`SECOND_SMOOTH`] times as long (0 with `tj`).
    tj2: f64,
    /// Path already travelled before the lead-in (the take-up, `arm_after`), mm: the target
    /// stands there until the ramp starts, and the ramp starts from it.
    pre: f64,
}

/// Length of the lead-in's second moving average, in units of the first. One average of
/// length T nulls T⁻¹, 2T⁻¹ … and lets through half of what lies at 0.6/T: a belt that rings
/// at 14–18 Hz behind 40 ms (its damping 2–3 %) moved the thread's phase 0.47–0.78° between
/// S500 and S1500. A second one of 1.5 T nulls (1.5 T)⁻¹ — 16.7 Hz for T = 40 ms — and the
/// product attenuates all between; it costs v·0.75 T more of lead-in path (1.1 mm at
/// 37.5 mm/s).
pub const SECOND_SMOOTH: f64 = 1.5;

impl ThreadSync {
    /// Arm a pass at measured angle `theta` (deg) and speed `rpm` (signed). `start_angle`
    /// (deg) is measured from the one-revolution reference in the direction of rotation;
    /// `lead_path` is mm of path per revolution, `k` its change per revolution (G34, else 0),
    /// `a` the lead-in acceleration (mm/s²).
    /// `None` when the spindle is (nearly) stopped or an argument is not usable.
    pub fn arm(theta: f64, rpm: f64, start_angle: f64, lead_path: f64, k: f64, a: f64) -> Option<ThreadSync> {
        ThreadSync::arm_smooth(theta, rpm, start_angle, lead_path, k, a, 0.0)
    }

    /// `arm` with a lead-in whose acceleration rises and falls over `tj` seconds (the
    /// constant-acceleration ramp averaged over `tj`; 0 = a step). A step in acceleration
    /// where the ramp meets the synchronous line sets a compliant axis ringing and its lag
    /// settling; the phase is measured, and learnt from, while it does.
    pub fn arm_smooth(theta: f64, rpm: f64, start_angle: f64, lead_path: f64, k: f64, a: f64, tj: f64) -> Option<ThreadSync> {
        ThreadSync::arm_after(theta, rpm, start_angle, lead_path, k, a, tj, 0.0)
    }

    /// `arm_smooth` for axes that already stand `pre` mm along the path (a take-up before the
    /// pass): the ramp starts from there, `pre / v` later, and meets the same synchronous line.
    #[allow(clippy::too_many_arguments)]
    pub fn arm_after(theta: f64, rpm: f64, start_angle: f64, lead_path: f64, k: f64, a: f64, tj: f64, pre: f64) -> Option<ThreadSync> {
        if !(theta.is_finite() && rpm.is_finite() && start_angle.is_finite() && k.is_finite() && pre.is_finite() && pre >= 0.0) {
            return None;
        }
        if !(rpm.abs() >= 1.0 && lead_path > 0.0 && lead_path.is_finite() && a > 0.0 && a.is_finite()) {
            return None;
        }
        let dir = rpm.signum();
        let omega = rpm.abs() * 6.0;
        let v = lead_path * rpm.abs() / 60.0;
        let tj = if tj.is_finite() { tj.max(0.0) } else { 0.0 };
        let tj2 = SECOND_SMOOTH * tj;
        // A symmetric acceleration profile meets the line at its centroid: half its length;
        // from `pre` along the path it starts `pre / v` later.
        let dtheta = omega * ((v / a + tj + tj2) / 2.0 - pre / v);
        // The first θ0 ≡ dir·start_angle (mod 360) at least Δθ ahead in the direction of
        // rotation, so the ramp starts in the future. In "forward" coordinates q = dir·θ.
        let q = dir * theta + dtheta;
        let q0 = start_angle + 360.0 * ((q - start_angle) / 360.0).ceil();
        let theta0 = dir * q0;
        Some(ThreadSync { dir, theta_start: theta0 - dir * dtheta, theta0, omega, a, v, lead_path, k, n_start: 0.0, ramp: true, tj, tj2, pre })
    }

    /// The lock for the segment that directly follows this one (which is `len` mm long):
    /// its synchronous line starts where this one's reaches `len`. `lead_path`/`k` are the new
    /// segment's. `None` when this segment never reaches `len` (the lead shrinks to zero first)
    /// or an argument is not usable.
    pub fn continue_with(&self, len: f64, lead_path: f64, k: f64) -> Option<ThreadSync> {
        let n = self.revs_to(len)?;
        if !(lead_path > 0.0 && lead_path.is_finite() && k.is_finite()) {
            return None;
        }
        Some(ThreadSync { n_start: self.n_start + n, lead_path, k, ramp: false, v: lead_path * self.omega / 360.0, ..*self })
    }

    /// Revolutions along this segment's synchronous line from its start to path position `len`:
    /// the root of `L·n + k·n²/2 = len` (written so that it does not cancel for small k).
    pub fn revs_to(&self, len: f64) -> Option<f64> {
        let disc = self.lead_path * self.lead_path + 2.0 * self.k * len;
        let n = 2.0 * len / (self.lead_path + disc.max(0.0).sqrt());
        (disc >= 0.0 && n.is_finite() && n >= 0.0).then_some(n)
    }

    /// Revolutions along the synchronous line since this segment's start at angle `theta`.
    fn revs(&self, theta: f64) -> f64 {
        self.dir * (theta - self.theta0) / 360.0 - self.n_start
    }

    /// Synchronous path speed (mm/s) at the speed the pass was armed with.
    pub fn sync_speed(&self) -> f64 {
        self.v
    }

    /// The angle at which the synchronous line passes the thread's start, degrees.
    pub fn theta0(&self) -> f64 {
        self.theta0
    }

    /// The spindle angle at which the synchronous line reaches path position `s` (mm from the
    /// segment's start): the inverse of `target` past the lead-in ramp. `None` when the lead
    /// shrinks to zero before `s` (G34).
    pub fn angle_at(&self, s: f64) -> Option<f64> {
        let n = self.revs_to(s.max(0.0))?;
        Some(self.theta0 + self.dir * 360.0 * (n + self.n_start))
    }

    /// The lead-in is over at measured angle `theta`: the target is on the synchronous line.
    pub fn on_line(&self, theta: f64) -> bool {
        !self.ramp || self.dir * (theta - self.theta_start) / self.omega >= self.v / self.a + self.tj + self.tj2
    }

    /// ∫₀ᵗ of the constant-acceleration ramp-then-line profile (mm·s).
    fn ramp_integral(&self, t: f64) -> f64 {
        let t1 = self.v / self.a;
        if !(t > 0.0) {
            0.0
        } else if t <= t1 {
            self.a * t * t * t / 6.0
        } else {
            let h = 0.5 * t1;
            self.a * t1 * t1 * t1 / 6.0 + 0.5 * self.v * ((t - h) * (t - h) - h * h)
        }
    }

    /// ∫₀ᵗ `ramp_integral` (mm·s²): the second average takes differences of it.
    fn ramp_integral2(&self, t: f64) -> f64 {
        let t1 = self.v / self.a;
        if !(t > 0.0) {
            0.0
        } else if t <= t1 {
            self.a * t.powi(4) / 24.0
        } else {
            let h = 0.5 * t1;
            let d = t - t1;
            self.a * t1.powi(4) / 24.0 + self.a * t1.powi(3) / 6.0 * d + 0.5 * self.v * (((t - h).powi(3) - h.powi(3)) / 3.0 - h * h * d)
        }
    }

    /// The ramp averaged over `tj`, then over `tj2`, at time `tau` from its start.
    fn smoothed(&self, tau: f64) -> f64 {
        let (t1, t2) = (self.tj, self.tj2);
        if t2 > 0.0 {
            let f = |t: f64| self.ramp_integral2(t);
            (f(tau) - f(tau - t1) - f(tau - t2) + f(tau - t1 - t2)) / (t1 * t2)
        } else {
            (self.ramp_integral(tau) - self.ramp_integral(tau - t1)) / t1
        }
    }

    /// Path position (mm from the segment's start) where the axes belong at spindle angle
    /// `theta`: 0 before the start angle, the ramp, then the synchronous line (for a
    /// continuation: the synchronous line from its start on).
    pub fn target(&self, theta: f64) -> f64 {
        let n = self.revs(theta);
        let n_pos = n.max(0.0);
        let g34 = 0.5 * self.k * n_pos * n_pos;
        if !self.ramp {
            return self.lead_path * n_pos + g34;
        }
        let p = self.dir * (theta - self.theta_start);
        if !(p > 0.0) {
            return self.pre;
        }
        let tau = p / self.omega;
        let t_ramp = self.v / self.a;
        let base = if tau >= t_ramp + self.tj + self.tj2 {
            self.lead_path * n
        } else if self.tj > 0.0 {
            self.pre + self.smoothed(tau)
        } else {
            self.pre + 0.5 * self.a * tau * tau
        };
        base + g34
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_angle_is_congruent_and_ahead() {
        for (theta, rpm, sa) in [(0.0, 500.0, 0.0), (1234.5, 800.0, 90.0), (-77.0, -600.0, 180.0), (359.0, 300.0, 0.0)] {
            let t = ThreadSync::arm(theta, rpm, sa, 2.0, 0.0, 1000.0).unwrap();
            let dir: f64 = if rpm > 0.0 { 1.0 } else { -1.0 };
            let q0 = dir * t.theta0();
            assert!(((q0 - sa).rem_euclid(360.0)).min(360.0 - (q0 - sa).rem_euclid(360.0)) < 1e-9, "θ0 {q0} ≢ {sa}");
            assert!(dir * (t.theta_start - theta) >= 0.0, "ramp must start in the future");
            assert_eq!(t.target(theta), 0.0);
        }
    }

    #[test]
    fn ramp_meets_the_synchronous_line_continuously() {
        let t = ThreadSync::arm(10.0, 1000.0, 45.0, 1.5, 0.0, 800.0).unwrap();
        let v = t.sync_speed();
        assert!((v - 25.0).abs() < 1e-12);
        // Across the whole pass the target is continuous and its slope never exceeds v.
        let mut prev = t.target(t.theta_start);
        let step = 0.01; // degrees
        let mut theta = t.theta_start;
        for _ in 0..200_000 {
            theta += step;
            let s = t.target(theta);
            let ds_dt = (s - prev) / (step / t.omega);
            assert!(ds_dt <= v + 1e-6 && ds_dt >= -1e-9, "slope {ds_dt} at {theta}");
            prev = s;
        }
        // Well past the ramp: exactly the synchronous line.
        let th = t.theta0() + 3600.0;
        assert!((t.target(th) - 1.5 * 10.0).abs() < 1e-9);
    }

    #[test]
    fn reverse_rotation_runs_the_same_way_along_the_path() {
        let t = ThreadSync::arm(0.0, -1000.0, 30.0, 2.0, 0.0, 1000.0).unwrap();
        assert!(t.theta0() < 0.0);
        assert!((t.target(t.theta0() - 720.0) - 4.0).abs() < 1e-9);
    }

    #[test]
    fn stopped_spindle_does_not_arm() {
        assert!(ThreadSync::arm(0.0, 0.2, 0.0, 2.0, 0.0, 1000.0).is_none());
        assert!(ThreadSync::arm(f64::NAN, 500.0, 0.0, 2.0, 0.0, 1000.0).is_none());
    }

    #[test]
    fn continuation_keeps_the_synchronous_line() {
        let t = ThreadSync::arm(0.0, 600.0, 0.0, 2.0, 0.0, 1000.0).unwrap();
        // First segment 10 mm = 5 revolutions; the next (path lead 2.5) starts there.
        let c = t.continue_with(10.0, 2.5, 0.0).unwrap();
        let th_j = t.theta0() + 5.0 * 360.0;
        assert!((t.target(th_j) - 10.0).abs() < 1e-9);
        assert_eq!(c.target(th_j), 0.0);
        assert!((c.target(th_j + 36.0) - 0.25).abs() < 1e-9);
        // Continuations of continuations add up.
        let d = c.continue_with(2.5, 2.0, 0.0).unwrap();
        assert!((d.target(th_j + 360.0 + 180.0) - 1.0).abs() < 1e-9);
    }

    #[test]
    fn g34_lead_grows_per_revolution_in_closed_form() {
        let t = ThreadSync::arm(0.0, 300.0, 0.0, 2.0, 0.1, 1000.0).unwrap();
        for n in [2.0f64, 5.0, 10.0, 12.5] {
            let want = 2.0 * n + 0.1 * n * n / 2.0;
            assert!((t.target(t.theta0() + 360.0 * n) - want).abs() < 1e-9, "n {n}");
        }
        // The target is continuous through the end of the ramp (no jump from the k term).
        let mut prev = 0.0;
        let mut th = t.theta0() - 720.0;
        while th < t.theta0() + 720.0 {
            let s = t.target(th);
            assert!((s - prev).abs() < 0.01, "jump {prev} → {s} at {th}");
            prev = s;
            th += 0.5;
        }
        // Revolutions to a length invert the sum of the leads.
        let n = t.revs_to(2.0 * 10.0 + 0.05 * 100.0).unwrap();
        assert!((n - 10.0).abs() < 1e-9);
        // A shrinking lead that reaches 0 before the length is never done.
        let s = ThreadSync::arm(0.0, 300.0, 0.0, 2.0, -0.5, 1000.0).unwrap();
        assert!(s.revs_to(4.0).is_some());
        assert!(s.revs_to(4.1).is_none());
    }

    #[test]
    fn a_pass_that_took_up_starts_its_ramp_from_there_onto_the_same_line() {
        // 1000 rpm, lead 1.5 (25 mm/s), 800 mm/s², 40 ms smoothing; 0.3 mm already travelled.
        let (a, tj, pre) = (800.0, 0.04, 0.3);
        let t = ThreadSync::arm_after(10.0, 1000.0, 45.0, 1.5, 0.0, a, tj, pre).unwrap();
        let plain = ThreadSync::arm_smooth(10.0, 1000.0, 45.0, 1.5, 0.0, a, tj).unwrap();
        // Stands where the take-up left it until the ramp, which starts pre/v later.
        assert_eq!(t.target(t.theta_start - 1.0), pre);
        assert_eq!(t.target(t.theta_start), pre);
        let later = (t.theta_start - plain.theta_start).rem_euclid(360.0);
        assert!((later - pre / 25.0 * t.omega).abs() < 1e-9, "{later}°");
        // Continuous, never faster than v, never back; and on the same line past the ramp.
        let mut prev = pre;
        let mut th = t.theta_start;
        while th < t.theta_start + 2000.0 {
            th += 0.05;
            let s = t.target(th);
            let v = (s - prev) / (0.05 / t.omega);
            assert!((-1e-9..=25.0 + 1e-6).contains(&v), "speed {v} at {th}");
            prev = s;
        }
        let th = t.theta0() + 3600.0;
        assert!((t.target(th) - 15.0).abs() < 1e-9 && (t.theta0() - plain.theta0()).rem_euclid(360.0) < 1e-9);
        // A negative or non-finite take-up is refused.
        assert!(ThreadSync::arm_after(10.0, 1000.0, 45.0, 1.5, 0.0, a, tj, -0.1).is_none());
        assert!(ThreadSync::arm_after(10.0, 1000.0, 45.0, 1.5, 0.0, a, tj, f64::NAN).is_none());
    }

    #[test]
    fn a_smoothed_lead_in_ramps_its_acceleration_and_keeps_the_phase() {
        // 1000 rpm, lead 1.5 (25 mm/s), a = 800 mm/s², acceleration rising and falling over 40 ms.
        let (a, tj) = (800.0, 0.04);
        let t = ThreadSync::arm_smooth(10.0, 1000.0, 45.0, 1.5, 0.0, a, tj).unwrap();
        let step_s = 1e-4;
        let dth = step_s * t.omega;
        let at = |k: i32| t.target(t.theta_start + k as f64 * dth);
        let (mut v_prev, mut a_prev) = (0.0, 0.0);
        for k in 1..20_000 {
            let v = (at(k) - at(k - 1)) / step_s;
            let acc = (v - v_prev) / step_s;
            assert!(acc <= a + 1.0 && acc >= -1.0 && v <= 25.0 + 1e-6, "a {acc} v {v} at {k}");
            // Jerk bounded by a over the longer average (no acceleration step).
            assert!(k < 3 || (acc - a_prev).abs() / step_s <= 1.01 * a / (SECOND_SMOOTH * tj), "jerk at {k}");
            (v_prev, a_prev) = (v, acc);
        }
        // Past the ramp: exactly the same synchronous line as the unsmoothed lead-in.
        let plain = ThreadSync::arm(10.0, 1000.0, 45.0, 1.5, 0.0, a).unwrap();
        assert_eq!(t.theta0(), plain.theta0());
        let th = t.theta0() + 3600.0;
        assert!((t.target(th) - plain.target(th)).abs() < 1e-9 && (t.target(th) - 15.0).abs() < 1e-9);
        // It starts earlier, by half the two averages' length.
        assert!((plain.theta_start - t.theta_start - 0.5 * (1.0 + SECOND_SMOOTH) * tj * t.omega).abs() < 1e-9);
    }
}
