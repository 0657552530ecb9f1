//! The spindle angle a thread's axes follow, smoothed without lag at constant speed.
//!
//! Why: the angle a thread's long axis follows is the measured one plus the measured speed
//! times the feedback delay (`Motion::step_thread`). A coarse spindle encoder (4096 counts,
//! 0.088°) reads up to half a count off, and at thread speeds the error changes every cycle
//! (S500 turns 68.3 counts per 2 ms cycle: a 135 Hz pattern); the speed taken from those
//! counts carries it too, multiplied by the horizon. Sent through the lead, it shook a
//! lightly damped long axis by up to ±0.2° of phase (sd 0.11°, 2.5× the set-point's own):
//! the start of the same thread moved by 0.11–0.14° between S500, S1000 and S1500 on such
//! drive models, whose fine-encoder twins kept 0.01–0.03°.
//!
//! The angle goes through a first-order low-pass with time constant [`SMOOTH_S`], and the
//! measured speed times that constant is added back: on a constant-speed spindle (a thread's
//! synchronous line, where the phase is cut) the filter's lag is exactly ω·T, so the sum is
//! the angle itself, without the high frequencies. Under an acceleration a it is off by
//! about a·T² (the low-pass' second-order term): 0.04° at 1200°/s², a 1 % speed dip at S1000
//! over 50 ms; `Motion::step_thread` restarts it every cycle while the spindle's command
//! ramps (a stop, a speed change), so that the angle is then the measured one. The speed is
//! low-passed alike for the long axis' own lag lead. The manuals are silent on how the
//! position coder's angle is conditioned; this is our choice. O(1), no allocation.

/// Time constant of the angle's low-pass, s: a 32 Hz corner, 4× below the quantisation
/// pattern of S500 on 4096 counts, and a lag under acceleration below what the phase
/// tolerates.
pub const SMOOTH_S: f64 = 0.005;

/// The filter's state: the low-passed angle, degrees (None: not started).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AngleFilter {
    y: Option<f64>,
    /// The low-passed speed, degrees per second.
    w: f64,
}

impl AngleFilter {
    /// The speed, low-passed alike, degrees per second.
    pub fn speed(&self) -> f64 {
        self.w
    }

    /// Restart from the next angle (a new thread pass).
    pub fn restart(&mut self) {
        self.y = None;
    }

    /// The smoothed angle for the measured `theta` (degrees, continuous over turns) with the
    /// spindle turning at `deg_s` degrees per second, after a cycle of `dt` s.
    pub fn update(&mut self, theta: f64, deg_s: f64, dt: f64) -> f64 {
        if !(theta.is_finite() && deg_s.is_finite() && dt > 0.0) {
            self.y = None;
            self.w = deg_s;
            return theta;
        }
        let k = dt / (SMOOTH_S + dt);
        let lead = deg_s * SMOOTH_S;
        let y = match self.y {
            // Started on its steady state: no transient at the first sample.
            None => {
                self.w = deg_s;
                theta - lead
            }
            // Backward Euler: its steady-state lag on a ramp is exactly ω·SMOOTH_S.
            Some(y) => {
                self.w += k * (deg_s - self.w);
                y + k * (theta - y)
            }
        };
        self.y = Some(y);
        y + lead
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 0.002;

    #[test]
    fn a_constant_speed_angle_comes_out_unchanged() {
        let mut f = AngleFilter::default();
        let w = 9000.0; // S1500
        for k in 0..500 {
            let th = 12.5 + w * DT * k as f64;
            let out = f.update(th, w, DT);
            assert!((out - th).abs() < 1e-9, "cycle {k}: {out} for {th}");
        }
    }

    #[test]
    fn quantisation_of_a_coarse_encoder_is_smoothed() {
        let (mut f, w, q) = (AngleFilter::default(), 3000.0, 360.0 / 4096.0);
        let (mut raw, mut out) = (0.0f64, 0.0f64);
        for k in 0..2000 {
            let th = 0.3 + w * DT * k as f64;
            let read = (th / q).floor() * q + q / 2.0;
            let y = f.update(read, w, DT);
            if k > 100 {
                raw = raw.max((read - th).abs());
                out = out.max((y - th).abs());
            }
        }
        assert!(raw > 0.4 * q, "the readings are quantised: {raw}");
        assert!(out < 0.5 * raw, "smoothed {out}° vs raw {raw}°");
    }

    #[test]
    fn an_acceleration_is_off_by_about_a_t_squared() {
        let (mut f, a) = (AngleFilter::default(), 1200.0);
        let mut off = 0.0;
        for k in 0..1000 {
            let t = DT * k as f64;
            let (th, w) = (6000.0 * t + a * t * t / 2.0, 6000.0 + a * t);
            off = f.update(th, w, DT) - th;
        }
        let (t2, bound) = (a * SMOOTH_S * SMOOTH_S, a * SMOOTH_S * (SMOOTH_S + DT));
        assert!(off >= t2 && off <= bound, "{off}° off; a·T² = {t2}°, a·T·(T + dt) = {bound}°");
    }

    #[test]
    fn a_bad_reading_restarts_it() {
        let mut f = AngleFilter::default();
        f.update(10.0, 100.0, DT);
        assert!(f.update(f64::NAN, 100.0, DT).is_nan());
        assert_eq!(f.update(50.0, 100.0, DT), 50.0);
    }
}
