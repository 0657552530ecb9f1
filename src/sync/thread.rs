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
    /// Path length per spindle revolution, mm.
    lead_path: f64,
}

impl ThreadSync {
    /// Arm a pass at measured angle `theta` (deg) and speed `rpm` (signed). `start_angle`
    /// (deg) is measured from the one-revolution reference in the direction of rotation;
    /// `lead_path` is mm of path per revolution, `a` the lead-in acceleration (mm/s²).
    /// `None` when the spindle is (nearly) stopped or an argument is not usable.
    pub fn arm(theta: f64, rpm: f64, start_angle: f64, lead_path: f64, a: f64) -> Option<ThreadSync> {
        if !(theta.is_finite() && rpm.is_finite() && start_angle.is_finite()) {
            return None;
        }
        if !(rpm.abs() >= 1.0 && lead_path > 0.0 && lead_path.is_finite() && a > 0.0 && a.is_finite()) {
            return None;
        }
        let dir = rpm.signum();
        let omega = rpm.abs() * 6.0;
        let v = lead_path * rpm.abs() / 60.0;
        let dtheta = omega * v / (2.0 * a);
        // The first θ0 ≡ dir·start_angle (mod 360) at least Δθ ahead in the direction of
        // rotation, so the ramp starts in the future. In "forward" coordinates q = dir·θ.
        let q = dir * theta + dtheta;
        let q0 = start_angle + 360.0 * ((q - start_angle) / 360.0).ceil();
        let theta0 = dir * q0;
        Some(ThreadSync { dir, theta_start: theta0 - dir * dtheta, theta0, omega, a, v, lead_path })
    }

    /// Synchronous path speed (mm/s) at the speed the pass was armed with.
    pub fn sync_speed(&self) -> f64 {
        self.v
    }

    /// The angle at which the synchronous line passes the thread's start, degrees.
    pub fn theta0(&self) -> f64 {
        self.theta0
    }

    /// Path position (mm from the thread's start) where the axes belong at measured angle
    /// `theta`: 0 before the start angle, the ramp, then the synchronous line.
    pub fn target(&self, theta: f64) -> f64 {
        let p = self.dir * (theta - self.theta_start);
        if !(p > 0.0) {
            return 0.0;
        }
        let tau = p / self.omega;
        let t_ramp = self.v / self.a;
        if tau <= t_ramp {
            0.5 * self.a * tau * tau
        } else {
            self.lead_path * self.dir * (theta - self.theta0) / 360.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_angle_is_congruent_and_ahead() {
        for (theta, rpm, sa) in [(0.0, 500.0, 0.0), (1234.5, 800.0, 90.0), (-77.0, -600.0, 180.0), (359.0, 300.0, 0.0)] {
            let t = ThreadSync::arm(theta, rpm, sa, 2.0, 1000.0).unwrap();
            let dir: f64 = if rpm > 0.0 { 1.0 } else { -1.0 };
            let q0 = dir * t.theta0();
            assert!(((q0 - sa).rem_euclid(360.0)).min(360.0 - (q0 - sa).rem_euclid(360.0)) < 1e-9, "θ0 {q0} ≢ {sa}");
            assert!(dir * (t.theta_start - theta) >= 0.0, "ramp must start in the future");
            assert_eq!(t.target(theta), 0.0);
        }
    }

    #[test]
    fn ramp_meets_the_synchronous_line_continuously() {
        let t = ThreadSync::arm(10.0, 1000.0, 45.0, 1.5, 800.0).unwrap();
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
        let t = ThreadSync::arm(0.0, -1000.0, 30.0, 2.0, 1000.0).unwrap();
        assert!(t.theta0() < 0.0);
        assert!((t.target(t.theta0() - 720.0) - 4.0).abs() < 1e-9);
    }

    #[test]
    fn stopped_spindle_does_not_arm() {
        assert!(ThreadSync::arm(0.0, 0.2, 0.0, 2.0, 1000.0).is_none());
        assert!(ThreadSync::arm(f64::NAN, 500.0, 0.0, 2.0, 1000.0).is_none());
    }
}
