//! An online model of how far a drive's actual position lags its command: lag ≈ τ₁·v + τ₂·a
//! (v, a: the command's speed and acceleration at the instant the feedback answers), fitted
//! by recursive least squares with forgetting. Regressors are per-cycle increments
//! (v·dt, a·dt²), so the parameters are in cycles and cycles² and the fit is well
//! conditioned whatever the units. O(1), no allocation.
//!
//! Why these two terms: a CSP drive's response to its set-point is, at the frequencies a
//! path contains, 1 − τ₁·s + τ₂'·s² … (any stable loop with unit gain at rest: position
//! gain, velocity feed-forward, transport delay, inner loops). The first moment τ₁ is the
//! lag at constant speed (with a transport delay of n cycles it includes n); the second
//! captures the acceleration phases, where a first-moment model alone leaves an error that
//! grows with the acceleration.

/// RLS estimate of (τ₁, τ₂) in cycles / cycles².
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LagModel {
    theta: [f64; 2],
    p: [[f64; 2]; 2],
    lambda: f64,
    /// Samples taken.
    pub samples: u32,
}

impl LagModel {
    /// `memory_cycles`: the forgetting horizon (λ = 1 − 1/memory).
    pub fn new(memory_cycles: f64) -> LagModel {
        LagModel { theta: [0.0; 2], p: [[1e2, 0.0], [0.0, 1e2]], lambda: 1.0 - 1.0 / memory_cycles.max(2.0), samples: 0 }
    }

    /// One sample: the lag (command − actual) and the command's increments `dv` (this cycle's
    /// travel, units) and `da` (change of travel per cycle) at the instant the actual answers.
    pub fn update(&mut self, dv: f64, da: f64, lag: f64) {
        if !(dv.is_finite() && da.is_finite() && lag.is_finite()) {
            return;
        }
        let phi = [dv, da];
        let pphi = [self.p[0][0] * phi[0] + self.p[0][1] * phi[1], self.p[1][0] * phi[0] + self.p[1][1] * phi[1]];
        let den = self.lambda + phi[0] * pphi[0] + phi[1] * pphi[1];
        if !(den > 1e-12) {
            return;
        }
        let k = [pphi[0] / den, pphi[1] / den];
        let e = lag - (phi[0] * self.theta[0] + phi[1] * self.theta[1]);
        self.theta[0] += k[0] * e;
        self.theta[1] += k[1] * e;
        for i in 0..2 {
            for j in 0..2 {
                self.p[i][j] = (self.p[i][j] - k[i] * pphi[j]) / self.lambda;
            }
        }
        // Keep P bounded when there is no excitation (covariance wind-up).
        let tr = self.p[0][0] + self.p[1][1];
        if tr > 1e4 {
            let s = 1e4 / tr;
            for r in &mut self.p {
                for x in r {
                    *x *= s;
                }
            }
        }
        self.samples = self.samples.saturating_add(1);
    }

    /// (τ₁ cycles, τ₂ cycles²), clamped to what a drive can plausibly have.
    pub fn params(&self) -> (f64, f64) {
        (self.theta[0].clamp(0.0, 50.0), self.theta[1].clamp(-200.0, 200.0))
    }

    /// The command that makes the actual follow `d` (this cycle's desired position) given
    /// the desired trajectory's per-cycle increments: d + τ₁·Δd + (τ₁² + τ₂)·Δ²d.
    pub fn lead(&self, dv: f64, da: f64) -> f64 {
        let (t1, t2) = self.params();
        t1 * dv + (t1 * t1 + t2) * da
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A first-order drive with feed-forward (kv, ff) sampled at dt: the fitted τ₁ is the
    /// velocity lag (1 − ff)/kv in cycles.
    #[test]
    fn fits_the_velocity_lag_of_a_first_order_drive() {
        let (kv, ff, dt) = (25.0, 0.95, 0.002);
        let mut m = LagModel::new(500.0);
        let (mut y, mut u_prev, mut v_prev) = (0.0f64, 0.0f64, 0.0f64);
        let sub = 20;
        for k in 0..3000 {
            let t = k as f64 * dt;
            let u = 10.0 * (1.0 - (t * 3.0).cos()) + 2.0 * t;
            let v = (u - u_prev) / dt;
            // The drive interpolates the set-point linearly over the cycle.
            let h = dt / sub as f64;
            for i in 0..sub {
                let us = u_prev + v * h * (i + 1) as f64;
                y += h * (ff * v + kv * (us - y));
            }
            let dv = u - u_prev;
            let da = dv - v_prev * dt;
            if k > 2 {
                m.update(dv, da, u - y);
            }
            v_prev = v;
            u_prev = u;
        }
        let (t1, _) = m.params();
        let want = (1.0 - ff) / kv / dt;
        assert!((t1 - want).abs() < 0.1 * want, "τ1 {t1} cycles, want {want}");
    }
}
