//! Whether the spindle manages the acceleration it is commanded: a spindle whose torque
//! cannot give it (a heavier chuck than the motor was sized for) falls behind by ½·Δa·t²
//! and faults its following-error window within half a second of a tap (load 0.12 kg·m² on
//! 70 N·m: alarm 2010 in a S3000 tap, the window 180°).
//!
//! Any stable loop follows a constant acceleration with a lag that settles (delays, gains and
//! feed-forward only set how far behind): the *speed* it lags by settles too. A spindle out of
//! torque lags in speed by more every cycle. So the governor compares the commanded speed
//! (of the set-points the feedback answers) with the measured one, over a window of
//! [`WINDOW`] cycles: where the speed lag grows by more than [`DEFICIT_SHARE`] of the
//! commanded acceleration for [`CONFIRM`] windows in a row, with the spindle behind in the
//! direction it is accelerated (ahead while braking) by more than a share of its window, it
//! is out of torque, and what it managed over the window is its acceleration. O(1), no
//! allocation.

/// Cycles over which speeds and accelerations are measured.
pub const WINDOW: usize = 10;
/// Growth of the speed lag (share of the commanded acceleration) that counts as falling
/// behind. A spindle of 0.12 kg·m² on 70 N·m managed 94 % of 5000 rpm/s and faulted all the
/// same, its lag growing for half a second; the settling of a loop without feed-forward
/// (which this must not take for it) is kept out by [`CONFIRM`] and the lag gate.
const DEFICIT_SHARE: f64 = 0.04;
/// Windows in a row it must be seen.
const CONFIRM: u32 = 3;
/// A smaller growth, seen for longer: a spindle of 0.135 kg·m² on 81 N·m managed 98 % and was
/// never found at [`DEFICIT_SHARE`] — 175° behind after 0.55 s of the S3000 tap's ramp, it
/// overshot past its window where the tap braked. A loop's settling decays (a loop without
/// feed-forward of τ 33 ms is past 2 % within 130 ms); a spindle out of torque stays behind
/// (sp_j135: 1.14 µm at five windows, 2.56 at six, 9.68 at nine, found ever later).
/// No other model of the matrix, its variants or 90 random ones is governed by it that was
/// not before (air, cut, 0.3 ms jitter, 2026-11-30).
const DEFICIT_SHARE_LONG: f64 = 0.02;
/// Windows in a row the smaller growth must be seen.
const CONFIRM_LONG: u32 = 5;

/// The spindle's speed lag, tracked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpindleGovernor {
    /// Commanded and measured speed (deg/s) of the last WINDOW fresh samples (ring).
    cmd: [f64; WINDOW],
    act: [f64; WINDOW],
    k: usize,
    filled: usize,
    /// The set-point and the actual angle of the last fresh sample.
    last: Option<(f64, f64)>,
    /// Samples in a row that fell behind by [`DEFICIT_SHARE`], and by [`DEFICIT_SHARE_LONG`].
    behind: u32,
    behind_long: u32,
}

impl Default for SpindleGovernor {
    fn default() -> Self {
        SpindleGovernor { cmd: [0.0; WINDOW], act: [0.0; WINDOW], k: 0, filled: 0, last: None, behind: 0, behind_long: 0 }
    }
}

impl SpindleGovernor {
    /// One fresh sample: `sent` the set-point this feedback answers, `actual` the measured
    /// angle (degrees), `dt` the cycle (s), `lag_ok` the lag (degrees) below which nothing is
    /// judged. Returns the acceleration the spindle managed over the window (deg/s², > 0)
    /// when it is out of torque, else None.
    pub fn update(&mut self, sent: f64, actual: f64, dt: f64, lag_ok: f64) -> Option<f64> {
        if !(sent.is_finite() && actual.is_finite() && dt > 0.0) {
            self.restart();
            return None;
        }
        let (s0, a0) = self.last.replace((sent, actual))?;
        let (wc, wa) = ((sent - s0) / dt, (actual - a0) / dt);
        let (wc0, wa0) = (self.cmd[self.k], self.act[self.k]);
        self.cmd[self.k] = wc;
        self.act[self.k] = wa;
        self.k = (self.k + 1) % WINDOW;
        self.filled = (self.filled + 1).min(WINDOW + 1);
        if self.filled <= WINDOW {
            return None;
        }
        let span = WINDOW as f64 * dt;
        let (ac, aa) = ((wc - wc0) / span, (wa - wa0) / span);
        // Behind in the direction it is accelerated (ahead while braking), by a lag worth
        // judging.
        let lagging = (sent - actual) * ac.signum() > lag_ok;
        let deficit = (ac - aa) * ac.signum();
        let falling = lagging && ac != 0.0 && aa * ac >= 0.0;
        let count = |n: &mut u32, share: f64| *n = if falling && deficit > share * ac.abs() { *n + 1 } else { 0 };
        count(&mut self.behind, DEFICIT_SHARE);
        count(&mut self.behind_long, DEFICIT_SHARE_LONG);
        let found = self.behind >= CONFIRM * WINDOW as u32 || self.behind_long >= CONFIRM_LONG * WINDOW as u32;
        found.then_some(aa.abs()).filter(|a| *a > 0.0)
    }

    /// Forget the samples (a stale or missing feedback, a new start).
    pub fn restart(&mut self) {
        *self = SpindleGovernor::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spindle commanded at 36 000 °/s² (6000 rpm/s) that manages 27 000: found within
    /// 60 cycles, with what it managed.
    #[test]
    fn a_spindle_out_of_torque_is_found_with_its_acceleration() {
        let mut g = SpindleGovernor::default();
        let dt = 0.002;
        let mut found = None;
        for k in 0..200 {
            let t = k as f64 * dt;
            let sent = 0.5 * 36000.0 * t * t;
            let actual = 0.5 * 27000.0 * t * t;
            if let Some(a) = g.update(sent, actual, dt, 45.0) {
                found = Some((k, a));
                break;
            }
        }
        let (k, a) = found.expect("found");
        assert!(k < 100, "found after {k} cycles");
        assert!((a - 27000.0).abs() < 100.0, "{a}");
    }

    /// A loop without feed-forward (lag τ·v, τ = 33 ms) and a transport delay of two cycles
    /// follow the same ramp with a lag that grows with the speed: not out of torque.
    #[test]
    fn a_lag_that_settles_is_not_falling_behind() {
        let dt = 0.002;
        for (tau, delay) in [(0.033, 0.0), (0.0, 2.0 * dt)] {
            let mut g = SpindleGovernor::default();
            let mut y = 0.0f64;
            for k in 0..1000 {
                let t = k as f64 * dt;
                let sent = 0.5 * 36000.0 * t * t;
                let td = (t - delay).max(0.0);
                let u = 0.5 * 36000.0 * td * td;
                y = if tau > 0.0 { y + dt / tau * (u - y) } else { u };
                assert_eq!(g.update(sent, y, dt, 45.0), None, "tau {tau} delay {delay} at {k}");
            }
        }
    }
}
