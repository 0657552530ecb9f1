//! The last line of defence against a drive whose position feedback is scaled differently
//! from its set-points (a factor group start-up cannot see, a feedback mapped from another
//! encoder, a polarity applied to one side only): while running, each axis' actual
//! displacement is compared with its commanded displacement over a window, once the command
//! has moved far enough that an honest drive's lag cannot matter.
//!
//! Over a window of commanded travel D the actual travel is D − (e₁ − e₀), e the following
//! error at either end, |e| ≤ the following-error window W the drive enforces (0x6065). With
//! D ≥ `SPAN_WINDOWS` × W an honest drive's ratio is within 1 ± 2/`SPAN_WINDOWS` (±0.2);
//! outside `[MIN_RATIO, MAX_RATIO]` the feedback disagrees with the command by a factor — 10×,
//! 0.1× or sign-flipped — and that is alarm 2019, not "ok". A ratio between, say 1.3, is not
//! flagged: that is not a constant factor one can tell from lag. Allocation-free, two
//! integers of state per axis.

/// Alarm: position feedback disagrees with the commanded motion by a constant factor.
pub const ALARM: u32 = crate::alarm::FEEDBACK_SCALE;
/// Commanded travel per comparison, in following-error windows.
pub const SPAN_WINDOWS: f64 = 10.0;
pub const MIN_RATIO: f64 = 0.5;
pub const MAX_RATIO: f64 = 2.0;

#[derive(Clone, Copy, Debug)]
pub struct ScaleWatch {
    /// Commanded travel per comparison, counts (0: not watched).
    span: i64,
    /// Command and actual at the start of the present window: the median (by following
    /// error) of three consecutive samples, so that one corrupted frame cannot be the start.
    start: Option<(i64, i64)>,
    candidates: [(i64, i64); 3],
    n_candidates: u8,
    /// Consecutive window ends outside the bounds (one corrupted frame is one).
    bad: u8,
}

impl ScaleWatch {
    /// A watch for an axis with this following-error window (counts); `None` or a window
    /// under one count: not watched.
    pub fn new(window_counts: Option<f64>) -> ScaleWatch {
        let span = window_counts.filter(|w| w.is_finite() && *w >= 1.0).map_or(0, |w| (w * SPAN_WINDOWS).ceil().min(i64::MAX as f64 / 4.0) as i64);
        ScaleWatch { span, start: None, candidates: [(0, 0); 3], n_candidates: 0, bad: 0 }
    }

    /// Forget the window.
    pub fn reset(&mut self) {
        self.start = None;
        self.n_candidates = 0;
        self.bad = 0;
    }

    /// A commanded position and the actual position that answers it (same instant, counts,
    /// unwrapped), from consecutive cycles. Some(ratio of actual to commanded travel) when
    /// two window ends in a row are outside the bounds.
    pub fn observe(&mut self, cmd: i64, act: i64) -> Option<f64> {
        if self.span == 0 {
            return None;
        }
        let Some((c0, a0)) = self.start else {
            self.candidates[self.n_candidates as usize] = (cmd, act);
            self.n_candidates += 1;
            if self.n_candidates == 3 {
                let mut c = self.candidates;
                c.sort_unstable_by_key(|&(c, a)| a.saturating_sub(c));
                self.start = Some(c[1]);
                self.n_candidates = 0;
            }
            return None;
        };
        let dc = cmd.saturating_sub(c0);
        if dc.unsigned_abs() < self.span as u64 {
            return None;
        }
        let r = act.saturating_sub(a0) as f64 / dc as f64;
        if (MIN_RATIO..=MAX_RATIO).contains(&r) {
            // A new window from here.
            self.bad = 0;
            self.start = None;
            self.candidates[0] = (cmd, act);
            self.n_candidates = 1;
            return None;
        }
        self.bad = self.bad.saturating_add(1);
        (self.bad >= 2).then_some(r)
    }

    /// The alarm text for `axis` with the ratio found.
    pub fn message(axis: &str, ratio: f64, counts_per_unit: f64) -> String {
        let what = if ratio < 0.0 && (ratio + 1.0).abs() < 0.2 {
            "against the commanded motion (sign-flipped)".to_string()
        } else {
            format!("{ratio:.3}× the commanded motion")
        };
        format!(
            "axis {axis}: the position feedback moves {what}: the drive's position scaling or polarity differs between its set-point (0x607A) and its feedback (0x6064). Stopped; check the drive's factor group, polarity and feedback encoder against axes.{axis}.counts_per_unit = {counts_per_unit}"
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An honest drive lagging by up to its window, and drives off by a factor.
    #[test]
    fn lag_passes_factors_do_not() {
        let w = 10_000.0; // 1 mm at 10000 counts/mm
        let mut honest = ScaleWatch::new(Some(w));
        let mut ten = ScaleWatch::new(Some(w));
        let mut flipped = ScaleWatch::new(Some(w));
        let mut alarms = (0, 0, 0);
        for k in 0..20_000i64 {
            // A back-and-forth command, 2 mm/ms… with a lag of up to the whole window.
            let cmd = ((k as f64 * 0.01).sin() * 500_000.0) as i64;
            let lag = ((k as f64 * 0.037).cos() * w) as i64;
            alarms.0 += honest.observe(cmd, cmd - lag).is_some() as u32;
            alarms.1 += ten.observe(cmd, (cmd - lag / 10) * 10).is_some() as u32;
            alarms.2 += flipped.observe(cmd, -(cmd - lag)).is_some() as u32;
        }
        assert_eq!(alarms.0, 0);
        assert!(alarms.1 > 0 && alarms.2 > 0, "{alarms:?}");
        // Not watched without a window.
        assert_eq!(ScaleWatch::new(None).observe(0, 0), None);
        assert!(ScaleWatch::message("x", -1.0, 10000.0).contains("moves against the commanded motion (sign-flipped)"));
        assert!(ScaleWatch::message("x", 10.0, 10000.0).contains("moves 10.000× the commanded motion"));
    }

    /// The first window that ends tells (confirmed by the next sample): after
    /// `SPAN_WINDOWS` windows of commanded travel from the third sample.
    #[test]
    fn found_after_one_span() {
        let mut s = ScaleWatch::new(Some(100.0));
        let mut at = None;
        for k in 0..10_000i64 {
            if s.observe(k, 10 * k).is_some() {
                at = Some(k);
                break;
            }
        }
        assert_eq!(at, Some(1002));
    }

    /// One corrupted feedback sample — at a window's start, at its end, anywhere — is not a
    /// scaling error.
    #[test]
    fn single_corrupted_samples_are_not_a_factor() {
        for glitch_at in [0, 1, 2, 3, 500, 1001, 1002, 1003, 1004, 2005] {
            let mut s = ScaleWatch::new(Some(100.0));
            for k in 0..5000i64 {
                let a = if k == glitch_at { k + (1 << 20) } else { k };
                assert_eq!(s.observe(k, a), None, "glitch at {glitch_at}, sample {k}");
            }
        }
    }
}
