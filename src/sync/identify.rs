//! Identification of a drive's response to its cyclic set-points (commissioning): from the
//! set-points sent and the actual positions received every cycle, the model
//!
//! ```text
//!   Δy(k) = ff·v(k) + (1 − ff)·z(k),   z(k) = α·z(k−1) + (1 − α)·v(k),   α = e^(−dt/τ)
//!   v(k) = (1 − f)·Δu(k−d) + f·Δu(k−d−1)
//! ```
//!
//! — a pure delay of `d + f` cycles (transport, the drive's interpolation over a period, the
//! feedback's own cycle, as the controller sees them; the fraction `f` because a drive that
//! interpolates its set-point over the period shifts it by part of a cycle), a share `ff` that follows at once (velocity feed-forward) and the
//! rest through a first-order lag `τ` (the position loop, 1/Kv). It fits what a CiA 402 drive
//! in CSP does at the frequencies a path has. For each delay and each τ of a logarithmic grid
//! (refined by golden-section search) `ff` is the least-squares solution (nalgebra), and the
//! best triple wins. Fit quality: the variance of Δy the model accounts for (VAF).
//!
//! Derived: the velocity lag (actual ≈ command delayed by `d·dt + (1 − ff)·τ` at constant
//! speed), what a following-error window must at least allow at the axis' maximum speed.

use nalgebra::{DMatrix, DVector};

/// A drive's identified response.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Response {
    /// Cycles between a set-point and the first change of the actual position the controller
    /// reads (whole cycles; the fraction is in `delay_fraction`).
    pub delay_cycles: u32,
    /// The part of a cycle beyond `delay_cycles`, 0 … 0.9.
    pub delay_fraction: f64,
    /// The share of a speed change that follows at once (velocity feed-forward).
    pub feed_forward: f64,
    /// Time constant of the rest, s.
    pub time_constant_s: f64,
    /// Variance of the position increments the model accounts for, 0 … 1.
    pub vaf: f64,
    /// Lag of the actual position behind the command at constant speed, s: regressed on
    /// the data directly (lag = T·v + A·a), so that it holds where the first-order model is
    /// only an approximation (a velocity loop that overshoots, a compliance).
    pub velocity_lag: f64,
    /// Samples used.
    pub samples: usize,
}

impl Response {
    /// Lag of the actual position behind the command at constant speed, s (the regressed
    /// one; the model's own is `(d + f)·dt + (1 − ff)·τ`).
    pub fn velocity_lag_s(&self, _dt: f64) -> f64 {
        self.velocity_lag
    }

    /// The model's own lag at constant speed, s.
    pub fn velocity_lag_model(&self, dt: f64) -> f64 {
        (self.delay_cycles as f64 + self.delay_fraction) * dt + (1.0 - self.feed_forward) * self.time_constant_s
    }
}

/// The command increments delayed by `d` whole cycles and the fraction `f`.
fn delayed(du: &[f64], d: usize, f: f64) -> Vec<f64> {
    let at = |k: usize, back: usize| if k >= back { du[k - back] } else { 0.0 };
    (0..du.len()).map(|k| (1.0 - f) * at(k, d) + f * at(k, d + 1)).collect()
}

/// The model's position increments for the delayed command increments `v` (per cycle).
fn simulate(v: &[f64], ff: f64, alpha: f64) -> Vec<f64> {
    let mut z = 0.0;
    v.iter()
        .map(|u| {
            z = alpha * z + (1.0 - alpha) * u;
            ff * u + (1.0 - ff) * z
        })
        .collect()
}

/// For the delayed increments `v` and lag factor `alpha`: the least-squares `ff` and the
/// residual sum.
fn fit_ff(v: &[f64], dy: &[f64], alpha: f64) -> (f64, f64) {
    // dy = z + ff·(v − z): one regressor, solved as a least-squares system.
    let zonly = simulate(v, 0.0, alpha);
    let n = v.len();
    let phi = DMatrix::from_fn(n, 1, |k, _| v[k] - zonly[k]);
    let rhs = DVector::from_fn(n, |k, _| dy[k] - zonly[k]);
    let ff = phi.svd(true, true).solve(&rhs, 1e-12).map(|x| x[0]).unwrap_or(0.0).clamp(0.0, 1.5);
    let model = simulate(v, ff, alpha);
    let sse = dy.iter().zip(&model).map(|(a, b)| (a - b) * (a - b)).sum();
    (ff, sse)
}

/// Identify from the commanded and the actual positions of the same cycles (`dt` the cycle,
/// s). `None`: too few samples or no motion.
pub fn identify(cmd: &[f64], act: &[f64], dt: f64, max_delay: usize) -> Option<Response> {
    let n = cmd.len().min(act.len());
    if n < 50 || !(dt > 0.0) {
        return None;
    }
    let du: Vec<f64> = (1..n).map(|k| cmd[k] - cmd[k - 1]).collect();
    let dy: Vec<f64> = (1..n).map(|k| act[k] - act[k - 1]).collect();
    let var = {
        let m = dy.iter().sum::<f64>() / dy.len() as f64;
        dy.iter().map(|v| (v - m) * (v - m)).sum::<f64>()
    };
    if !(var > 0.0) || du.iter().all(|v| *v == 0.0) {
        return None;
    }
    let alpha_of = |tau: f64| (-dt / tau).exp();
    let mut best: Option<(f64, usize, f64, f64, f64)> = None; // (sse, d, f, tau, ff)
    for d in 0..=max_delay {
        for fi in 0..10 {
            let f = fi as f64 / 10.0;
            let v = delayed(&du, d, f);
            let (sse, tau, ff) = fit_tau(&v, &dy, dt, &alpha_of);
            if best.is_none_or(|b| sse < b.0) {
                best = Some((sse, d, f, tau, ff));
            }
        }
    }
    let (sse, d, f, tau, ff) = best?;
    let velocity_lag = regress_lag(cmd, act, dt).unwrap_or((d as f64 + f) * dt + (1.0 - ff) * tau);
    Some(Response {
        velocity_lag,
        delay_cycles: d as u32,
        delay_fraction: f,
        feed_forward: ff,
        time_constant_s: tau,
        vaf: (1.0 - sse / var).max(0.0),
        samples: dy.len(),
    })
}

/// The lag at constant speed from the data, s: least squares of (command − actual) on the
/// command's speed over the cycles where that speed has been steady for `STEADY` cycles (the
/// drive's transient after a speed change has died out); where the run has too few of them,
/// over every cycle, with the acceleration as a second regressor.
fn regress_lag(cmd: &[f64], act: &[f64], dt: f64) -> Option<f64> {
    const STEADY: usize = 60;
    let n = cmd.len().min(act.len());
    let v = |k: usize| (cmd[k] - cmd[k - 1]) / dt;
    let steady: Vec<usize> = (STEADY + 1..n).filter(|&k| v(k) != 0.0 && (k - STEADY..k).all(|j| (v(j) - v(k)).abs() <= 1e-6 * v(k).abs())).collect();
    let (rows, cols) = if steady.len() >= 20 { (steady, 1) } else { ((2..n).collect(), 2) };
    let phi = DMatrix::from_fn(rows.len(), cols, |r, c| {
        let k = rows[r];
        if c == 0 {
            v(k)
        } else {
            (v(k) - v(k - 1)) / dt
        }
    });
    let lag = DVector::from_fn(rows.len(), |r, _| cmd[rows[r]] - act[rows[r]]);
    let x = phi.svd(true, true).solve(&lag, 1e-15).ok()?;
    x[0].is_finite().then_some(x[0])
}

/// The best τ for the delayed increments `v`: a logarithmic grid from a tenth of a cycle to
/// 2 s, then golden-section search. (residual sum, τ, ff).
fn fit_tau(v: &[f64], dy: &[f64], dt: f64, alpha_of: &dyn Fn(f64) -> f64) -> (f64, f64, f64) {
    let grid: Vec<f64> = (0..40).map(|i| dt * 0.1 * (2.0 / (dt * 0.1)).powf(i as f64 / 39.0)).collect();
    let (mut bi, mut be) = (0, f64::INFINITY);
    for (i, tau) in grid.iter().enumerate() {
        let (_, sse) = fit_ff(v, dy, alpha_of(*tau));
        if sse < be {
            (bi, be) = (i, sse);
        }
    }
    let (mut lo, mut hi) = (grid[bi.saturating_sub(1)].ln(), grid[(bi + 1).min(grid.len() - 1)].ln());
    let g = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..30 {
        let (a, b) = (hi - g * (hi - lo), lo + g * (hi - lo));
        if fit_ff(v, dy, alpha_of(a.exp())).1 < fit_ff(v, dy, alpha_of(b.exp())).1 {
            hi = b;
        } else {
            lo = a;
        }
    }
    let tau = ((lo + hi) / 2.0).exp();
    let (ff, sse) = fit_ff(v, dy, alpha_of(tau));
    (sse, tau, ff)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A command with speed steps both ways, run through a known model: the fit returns it.
    #[test]
    fn recovers_delay_feed_forward_and_time_constant() {
        let dt = 0.002;
        let mut cmd = vec![0.0];
        for (v, cycles) in [(0.0, 50), (10.0, 300), (0.0, 200), (-20.0, 150), (5.0, 300), (0.0, 300)] {
            for _ in 0..cycles {
                let last = *cmd.last().unwrap();
                cmd.push(last + v * dt);
            }
        }
        for (d, ff, tau) in [(2usize, 0.95, 0.040), (4, 0.8, 0.015), (3, 0.998, 0.05)] {
            let du: Vec<f64> = (1..cmd.len()).map(|k| cmd[k] - cmd[k - 1]).collect();
            let dy = simulate(&delayed(&du, d, 0.3), ff, (-dt / tau).exp());
            let mut act = vec![0.0];
            for v in dy {
                let last = *act.last().unwrap();
                act.push(last + v);
            }
            let r = identify(&cmd, &act, dt, 8).unwrap();
            assert_eq!(r.delay_cycles as usize, d, "{r:?}");
            assert!((r.delay_fraction - 0.3).abs() < 1e-9, "{r:?}");
            assert!((r.feed_forward - ff).abs() < 0.005, "{r:?}");
            if ff < 0.99 {
                assert!((r.time_constant_s / tau - 1.0).abs() < 0.05, "{r:?}");
            }
            assert!(r.vaf > 0.999, "{r:?}");
        }
    }
}
