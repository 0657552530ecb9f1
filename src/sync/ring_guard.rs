//! A guard on the sync trim's own loop: the trim integrates the measured sync error around a
//! loop of the drive's delay and dynamics, and its gain is set from a model of them
//! (`SyncCorrection`). A drive whose response the model reads short (a slow velocity loop
//! behind a high feed-forward reads as almost no lag) puts that loop past its stability
//! limit, and the error then swings with a growing amplitude at the loop's period until the
//! sync monitor stops the machine (alarm 2307). The guard watches the error's half-waves:
//! three in a row, each short (the loop's own period, not a motion's) and none smaller than
//! the one before by more than a tenth, halve the gain. A transient (a reversal, a
//! breakaway) decays and is left alone. O(1), no allocation.

/// Half-waves below this size (mm) are not counted (encoder quantisation, noise).
const AMPLITUDE_MIN: f64 = 0.003;
/// The error must cross zero by this much (mm) to start a new half-wave.
const HYSTERESIS: f64 = 0.0005;
/// The longest half-wave (cycles) the trim's loop rings with: its period is about twice its
/// delay, 3–10 cycles on the drives measured; slower swings are the motion's.
const HALF_WAVE_MAX: u32 = 25;
/// A half-wave at least this share of the one before counts as not decaying.
const NOT_DECAYING: f64 = 0.9;
/// Half-waves in a row that did not decay before the gain is halved.
const RINGING: u32 = 3;
/// The gain is never cut below this share.
const SCALE_MIN: f64 = 0.125;

/// The guard of one axis' trim.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RingGuard {
    sign: f64,
    peak: f64,
    prev_peak: f64,
    len: u32,
    rising: u32,
    scale: f64,
}

impl Default for RingGuard {
    fn default() -> RingGuard {
        RingGuard { sign: 0.0, peak: 0.0, prev_peak: 0.0, len: 0, rising: 0, scale: 1.0 }
    }
}

impl RingGuard {
    /// The share of the trim's gain left (1 until the loop has rung).
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// Times the gain was cut.
    pub fn cuts(&self) -> u32 {
        (1.0 / self.scale).log2().round() as u32
    }

    /// One cycle's sync error `e` (mm) of the locked axis.
    pub fn update(&mut self, e: f64) {
        if !e.is_finite() {
            return;
        }
        self.len = self.len.saturating_add(1);
        if e.abs() < HYSTERESIS || e.signum() == self.sign {
            self.peak = self.peak.max(e.abs());
            return;
        }
        // A half-wave ended: did it ring?
        let short = self.len <= HALF_WAVE_MAX;
        let ringing = short && self.peak >= AMPLITUDE_MIN && self.peak >= NOT_DECAYING * self.prev_peak;
        self.rising = if ringing { self.rising + 1 } else { 0 };
        if self.rising >= RINGING {
            self.scale = (self.scale * 0.5).max(SCALE_MIN);
            self.rising = 0;
        }
        self.prev_peak = if short { self.peak } else { 0.0 };
        self.peak = e.abs();
        self.sign = e.signum();
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An integrator of gain `k` around a pure delay of `d` cycles, a step disturbance of 10
    /// µm; the guard's scale on the gain. Returns the largest |error| over the last 100 cycles.
    fn loop_of(k: f64, d: usize, guard: bool) -> (f64, RingGuard) {
        let mut g = RingGuard::default();
        let mut sent = vec![0.0f64; d + 1];
        let mut trim = 0.0;
        let mut tail = 0.0f64;
        for n in 0..600 {
            let e = sent[0] + 0.010;
            if guard {
                g.update(e);
            }
            trim -= k * g.scale() * e;
            sent.rotate_left(1);
            sent[d] = trim;
            if n >= 500 {
                tail = tail.max(e.abs());
            }
        }
        (tail, g)
    }

    #[test]
    fn a_trim_loop_past_its_limit_is_calmed() {
        // Delay 3: the limit is 0.445 per cycle; 0.6 rings and grows without the guard.
        let (free, _) = loop_of(0.6, 3, false);
        assert!(free > 0.05, "unguarded it should ring up, got {free}");
        let (guarded, g) = loop_of(0.6, 3, true);
        assert!(guarded < 1e-6, "guarded it settles, left {guarded}");
        assert!(g.cuts() >= 1);
    }

    #[test]
    fn a_stable_loop_and_a_decaying_transient_keep_their_gain() {
        let (left, g) = loop_of(0.25, 3, true);
        assert!(left < 1e-6, "settles: {left}");
        assert_eq!(g.scale(), 1.0, "a well damped step is no ringing");
    }
}
