//! The spindle's measured lag as the sync correction may use it: tracked by an α-β filter
//! whose gain follows the noise it measures, and with the noise it measures.
//!
//! Why: the spindle's lag is measured as its actual angle (sampled by the drive at a SYNC)
//! minus the set-point the master sent for that cycle. On a real-time PC the SYNC leaves
//! 0.05–0.5 ms late now and then (wake-up jitter; far more on a loaded or virtualised host),
//! and at S3000 each 0.1 ms of it moves the sampled angle by 1.8° — noise of tens of µm once
//! multiplied by the lead. Extrapolating that sample across the feedback delay and adding the
//! axis' acceleration lead amplified it until the correction itself oscillated (alarm 2307 at
//! 0.3 ms of uniform jitter on every drive model; see `docs/ARCHITECTURE.md`, sync).
//!
//! The noise is told from the lag's real motion by the second difference d of the raw
//! samples: white measurement noise gives d a lag-1 autocorrelation of −2/3, a smooth lag one
//! near +1, so with ρ the measured autocorrelation the noise's share of E[d²] is
//! (1 − ρ)·3/5 and the measurement's own variance a sixth of that. The filter's gain follows
//! Kalata's tracking index λ = σ_process/σ_noise (α = 1 − r², r = (4 + λ − √(8λ + λ²))/4,
//! β = α²/(2 − α), Benedict–Bordner): without noise α = β = 1, which is exactly the plain
//! two-sample extrapolation the correction used before. Statistics are kept across the holes
//! of a program (the noise is the machine's, not the hole's). O(1), no allocation.

/// Weight of one sample in the noise statistics (≈ 64 cycles of memory).
const STAT_W: f64 = 1.0 / 64.0;

/// How fast the gain in use follows its estimate, per cycle.
const ALPHA_W: f64 = 1.0 / 32.0;
/// The least gain: the lag must still be followed through a tap's acceleration.
const ALPHA_MIN: f64 = 0.2;

/// The tracker's state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LagTracker {
    x: f64,
    v: f64,
    /// Samples since the lock began (0: none).
    n: u32,
    /// The two raw samples before, and the last second difference.
    l1: f64,
    l2: f64,
    d1: f64,
    /// Running means of d² and of d·d₋₁.
    dd: f64,
    dd1: f64,
    /// The measurement noise's standard deviation, in the samples' unit.
    noise: f64,
    /// The gain in use: follows Kalata's α slowly (its estimate scatters with the
    /// correlation's; switching the gain abruptly costs more than a gain a little off).
    alpha: f64,
}

impl LagTracker {
    /// A new lock: the filter restarts from the next sample, the noise statistics stay.
    pub fn restart(&mut self) {
        self.n = 0;
    }

    /// The measurement noise's standard deviation (the samples' unit).
    pub fn noise(&self) -> f64 {
        self.noise
    }

    /// One sample `l`; `exact_below`: a noise at or below which the sample is taken as it is
    /// (α = 1). Returns the filtered value and its change per cycle.
    pub fn update(&mut self, l: f64, exact_below: f64) -> (f64, f64) {
        self.n = self.n.saturating_add(1);
        self.learn_noise(l);
        if self.n == 1 {
            (self.x, self.v) = (l, 0.0);
            return (l, 0.0);
        }
        let target = if self.noise <= exact_below { 1.0 } else { self.kalata_alpha() };
        self.alpha = if self.n == 2 && self.alpha == 0.0 { target } else { self.alpha + ALPHA_W * (target - self.alpha) };
        let a = if self.noise <= exact_below { 1.0 } else { self.alpha };
        let b = a * a / (2.0 - a);
        let xp = self.x + self.v;
        let r = l - xp;
        self.x = xp + a * r;
        self.v += b * r;
        (self.x, self.v)
    }

    /// A cycle without a sample (a late TPDO): the lag moves on at its tracked rate; the
    /// noise statistics skip it. Before the first sample there is nothing to coast on: 0.
    pub fn coast(&mut self) -> (f64, f64) {
        if self.n == 0 {
            return (0.0, 0.0);
        }
        self.x += self.v;
        (self.l2, self.l1) = (self.l1, self.x);
        (self.x, self.v)
    }

    fn learn_noise(&mut self, l: f64) {
        if self.n >= 3 {
            let d = l - 2.0 * self.l1 + self.l2;
            // Running means from zero: one step of the lag (a spindle starting) weighs 1/64,
            // only noise that lasts counts (the noise is the machine's: a new lock keeps them).
            // Both means over the same samples (else their ratio, the correlation, is biased
            // while they fill).
            if d.is_finite() {
                if self.n >= 4 {
                    self.dd1 += STAT_W * (d * self.d1 - self.dd1);
                    self.dd += STAT_W * (d * d - self.dd);
                }
                self.d1 = d;
            }
        }
        (self.l2, self.l1) = (self.l1, l);
        // No correlation measured yet: no evidence of noise.
        let rho = if self.dd > 0.0 && self.dd1 != 0.0 { (self.dd1 / self.dd).clamp(-2.0 / 3.0, 1.0) } else { 1.0 };
        self.noise = ((1.0 - rho) * 0.6 * self.dd / 6.0).max(0.0).sqrt();
    }

    /// Kalata's steady-state α for the measured process and noise.
    fn kalata_alpha(&self) -> f64 {
        let process = (self.dd - 6.0 * self.noise * self.noise).max(0.0);
        let lam = process.sqrt() / self.noise.max(1e-300);
        let r = (4.0 + lam - (8.0 * lam + lam * lam).sqrt()) / 4.0;
        (1.0 - r * r).clamp(ALPHA_MIN, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic uniform noise in [−1, 1).
    fn noise(state: &mut u64) -> f64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state % 2_000_001) as f64 / 1_000_000.0 - 1.0
    }

    #[test]
    fn a_clean_ramp_is_tracked_exactly_as_the_two_sample_extrapolation() {
        let mut t = LagTracker::default();
        let mut prev = 0.0;
        for k in 0..300 {
            let l = -0.05 * k as f64 - 1e-4 * (k * k) as f64;
            let (x, v) = t.update(l, 1e-9);
            assert!((x - l).abs() < 1e-9, "cycle {k}: {x} vs {l}");
            if k > 0 {
                assert!((v - (l - prev)).abs() < 1e-9, "cycle {k}: slope {v} vs {}", l - prev);
            }
            prev = l;
        }
        assert!(t.noise() < 1e-6, "a smooth lag read as noise: {}", t.noise());
    }

    #[test]
    fn white_noise_is_measured_and_filtered_out_of_a_ramp() {
        let mut t = LagTracker::default();
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        // Uniform in [−1, 1): σ = 1/√3.
        let sigma = 1.0 / 3f64.sqrt();
        let (mut raw_err, mut filt_err) = (0.0, 0.0);
        for k in 0..2000 {
            let truth = -0.3 * k as f64;
            let (x, _) = t.update(truth + noise(&mut s), 0.0);
            if k > 200 {
                filt_err += (x - truth).powi(2);
                raw_err += sigma * sigma;
            }
        }
        let n = t.noise();
        assert!((n / sigma - 1.0).abs() < 0.3, "noise measured {n}, true {sigma}");
        assert!(filt_err < 0.4 * raw_err, "filtered {filt_err} vs raw {raw_err}");
    }
}
