//! When a drive's reported position was taken: at the instant its SYNC arrived (a servo whose
//! loop runs on its own clock — the position latched is where the motor physically was then),
//! or at the slot the SYNC stands for (a drive that steps its interpolation once per SYNC,
//! whatever the time between them: python `canopen` LocalNodes in `tests/python/`).
//!
//! The cycle loop sends its own SYNC δ after the slot (it woke late). If the drives latch in
//! time, the spindle's angle is ω·δ on — noise that must be taken out (`Feedback::late_s`);
//! if they step per SYNC, taking it out *adds* that noise (a python tap_s15 at S3000: 4 → 75–115
//! µm, alarm 2307). Which kind they are shows in their positions: the second difference of a
//! position, Δ²p = a·Δt² + k·v·Δ²δ, carries the lateness' second difference with k = 1 for a
//! drive that latches in time, 0 for one that steps per SYNC; the acceleration term is smooth
//! and the wake-up jitter random, so k is their regression — a least-squares slope over every
//! drive of the bus, in counts (the rapid to a tap's R point teaches it before the spindle
//! turns), with a long memory, from k = 0 (nothing taken out) until the data say otherwise;
//! a slope past ½ by two standard errors is drives that latch in time
//! (`SampleTiming::latches_in_time`).
//! O(1), no allocation.

/// Drives followed (the cycle loop's trace and snapshot hold as many).
pub const MAX_DRIVES: usize = 8;
/// Memory of the regression, per fresh sample (≈ 2000 cycles: 4 s at 2 ms).
const FORGET: f64 = 0.9995;
/// Weight of the prior k = 0, counts²: 10 counts of lateness-borne motion.
const PRIOR_W: f64 = 100.0;

/// The share `k` (0…1) of a SYNC's lateness that shows in the drives' reported positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SampleTiming {
    /// Per drive the last two raw positions (counts), newest first, and how many are valid.
    pos: [[f64; 2]; MAX_DRIVES],
    n: [u8; MAX_DRIVES],
    /// The last three latenesses, s, newest first (common to the bus).
    late: [f64; 3],
    /// Σx·y, Σx², Σy² (x = v·Δ²δ, y = Δ²p, counts²) and the samples' weight, with forgetting.
    sxy: f64,
    sxx: f64,
    syy: f64,
    sw: f64,
}

impl Default for SampleTiming {
    fn default() -> Self {
        SampleTiming { pos: [[0.0; 2]; MAX_DRIVES], n: [0; MAX_DRIVES], late: [0.0; 3], sxy: 0.0, sxx: 0.0, syy: 0.0, sw: 0.0 }
    }
}

impl SampleTiming {
    /// This cycle's SYNC went out `late_s` after its slot (call once per cycle, before
    /// `sample`; the latenesses of the samples that follow).
    pub fn lateness(&mut self, late_s: f64) {
        self.late = [if late_s.is_finite() { late_s } else { 0.0 }, self.late[0], self.late[1]];
    }

    /// Drive `d`'s raw position `counts`, fresh at this cycle's SYNC, moving at `v` counts/s
    /// (`None`: stale or not latched at the SYNC — its differences start again).
    pub fn sample(&mut self, d: usize, counts: Option<f64>, v: f64) {
        let Some(n) = self.n.get_mut(d) else { return };
        let Some(p) = counts.filter(|p| p.is_finite() && v.is_finite()) else {
            *n = 0;
            return;
        };
        let q = &mut self.pos[d];
        if *n == 2 {
            let y = p - 2.0 * q[0] + q[1];
            let x = v * (self.late[0] - 2.0 * self.late[1] + self.late[2]);
            self.sxy = FORGET * self.sxy + x * y;
            self.sxx = FORGET * self.sxx + x * x;
            self.syy = FORGET * self.syy + y * y;
            self.sw = FORGET * self.sw + 1.0;
        }
        *q = [p, q[0]];
        *n = (*n + 1).min(2);
    }

    /// A missed cycle: every drive's differences would span more than one period.
    pub fn restart(&mut self) {
        self.n = [0; MAX_DRIVES];
    }

    /// The regression's slope, 0…1: the share of the lateness in the reported positions.
    pub fn share(&self) -> f64 {
        (self.sxy / (self.sxx + PRIOR_W)).clamp(0.0, 1.0)
    }

    /// The drives latch their positions when the SYNC arrives (k = 1), not at its slot (k = 0):
    /// the slope lies above ½ by two standard errors. A vote, not a gain: the regressor takes
    /// the *commanded* speed, which leads the actual one through a drive's lag, so the slope of
    /// a drive that latches in time comes out 0.9–0.97 while the spindle accelerates behind 2
    /// cycles of transport delay (taking out 90 % of the lateness left delay2's tap at 9.2 µm
    /// where all of it gives 5.3); and the standard error, because a profile's own
    /// acceleration in y can outweigh a small jitter in x (a python drive read as latching in
    /// time by chance: tap_s40 at 54 µm).
    pub fn latches_in_time(&self) -> bool {
        let k = self.share();
        let resid = (self.syy - k * self.sxy).max(0.0) / (self.sw - 1.0).max(1.0);
        let se = (resid / (self.sxx + PRIOR_W)).sqrt();
        k - 2.0 * se >= 0.5
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// xorshift lateness 0–0.3 ms, reproducible.
    fn lateness(n: usize) -> Vec<f64> {
        let mut x = 0x1234_5678_9ABC_DEF1u64;
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x % 300_000) as f64 * 1e-9
            })
            .collect()
    }

    /// A spindle (1000 counts/°) accelerating at 36 000 °/s² to S3000 and a Z (10 000
    /// counts/mm) at 100 mm/s, sampled every 2 ms at their SYNC (late by δ) by drives that
    /// latch in time, and by drives that step per SYNC: k found 1 and 0.
    #[test]
    fn drives_that_latch_in_time_and_drives_that_step_per_sync_are_told_apart() {
        let (dt, a, wmax) = (0.002, 36_000.0, 18_000.0);
        let theta = |t: f64| if t < wmax / a { 0.5 * a * t * t } else { wmax * wmax / (2.0 * a) + wmax * (t - wmax / a) };
        let late = lateness(600);
        let (mut in_time, mut per_sync) = (SampleTiming::default(), SampleTiming::default());
        for (i, d) in late.iter().enumerate() {
            let t = i as f64 * dt;
            let w = (a * t).min(wmax) * 1000.0;
            for (m, off) in [(&mut in_time, *d), (&mut per_sync, 0.0)] {
                m.lateness(*d);
                m.sample(0, Some(theta(t + off) * 1000.0), w);
                m.sample(1, Some(1e6 * (t + off)), 1e6);
            }
        }
        assert!((in_time.share() - 1.0).abs() < 0.02, "latches in time: k {}", in_time.share());
        assert!(per_sync.share() < 0.02, "steps per SYNC: k {}", per_sync.share());
        assert!(in_time.latches_in_time() && !per_sync.latches_in_time());
        // Z alone (the rapid before a tap, the spindle still) already tells.
        let mut z_only = SampleTiming::default();
        for (i, d) in late.iter().take(100).enumerate() {
            z_only.lateness(*d);
            z_only.sample(1, Some(1e6 * (i as f64 * dt + d)), 1e6);
        }
        assert!(z_only.share() > 0.95, "{}", z_only.share());
        // No lateness (an on-time SYNC, simulated time): no evidence, nothing taken out.
        let mut on_time = SampleTiming::default();
        for i in 0..600 {
            on_time.lateness(0.0);
            on_time.sample(0, Some(theta(i as f64 * dt) * 1000.0), 1.8e7);
        }
        assert_eq!(on_time.share(), 0.0);
        assert!(!on_time.latches_in_time());
    }
}
