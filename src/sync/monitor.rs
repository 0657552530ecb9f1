//! The spindle–axis sync-error monitor's state: which cycles are compared, what was measured,
//! and which were skipped because their feedback was not from one SYNC.
//!
//! The relation itself (thread line, tap stroke, G92.1 stroke) is the motion's: it hands the
//! error it computed to [`SyncMonitor::record`]. What lives here is the part every relation
//! shares: a cycle is compared only after a set-point locked to the spindle was sent
//! ([`SyncMonitor::watch`]), and only when the spindle's angle and the feed axes' positions
//! were sampled at the same SYNC — a late TPDO pairs an angle with positions of another SYNC
//! and would read as a sync error of lead × speed × period. Such cycles, and the cycle after
//! one (the late frame may arrive then, as fresh as the others by its arrival but answering the
//! SYNC before theirs), hold the last value and are counted. O(1), no allocation.

/// What the monitor does with this cycle's feedback (see [`SyncMonitor::begin`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sample {
    /// Nothing locked was sent last cycle: no error (0).
    Off,
    /// Locked, but the feedback is not from one SYNC: the last value is held, the cycle counted.
    Held,
    /// Locked and paired: compute the error and [`SyncMonitor::record`] it.
    Measure,
}

/// The monitor's state (one per `Motion`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SyncMonitor {
    /// The last measured error, µm along the relation (+ = the axis ahead of the spindle).
    err_um: f64,
    /// The same as a vector of the feed axes, mm (NaN over a held cycle: the trim skips it).
    err_vec: [f64; 3],
    /// A thread's phase error measured this cycle, path mm (+ = the axes ahead).
    thread_err: Option<f64>,
    /// Locked cycles whose feedback could not be paired from one SYNC.
    unpaired: u32,
    /// This cycle's feedback is not from one SYNC, or the last cycle's was not.
    suspect: bool,
    late_before: bool,
    /// The last cycle sent a set-point locked to the spindle.
    watch: bool,
}

impl SyncMonitor {
    /// Whether the set-point sent this cycle is locked to the spindle (compare it next cycle).
    pub fn watch(&mut self, locked: bool) {
        self.watch = locked;
    }

    /// Start of a cycle: `paired` = the spindle's angle and every feed axis' position come
    /// from one SYNC. Says whether to measure.
    pub fn begin(&mut self, paired: bool) -> Sample {
        let watch = std::mem::take(&mut self.watch);
        self.thread_err = None;
        self.suspect = !paired || self.late_before;
        self.late_before = !paired;
        if watch && self.suspect {
            self.unpaired = self.unpaired.saturating_add(1);
            self.err_vec = [f64::NAN; 3];
            return Sample::Held;
        }
        self.err_um = 0.0;
        self.err_vec = [0.0; 3];
        if watch {
            Sample::Measure
        } else {
            Sample::Off
        }
    }

    /// The error of a [`Sample::Measure`] cycle: `err_mm` along the relation, `vec` per feed
    /// axis (mm), `thread` a thread's phase error (path mm). Non-finite feedback counts as an
    /// infinite error. True when it exceeds `limit_um`.
    pub fn record(&mut self, err_mm: f64, vec: [f64; 3], thread: Option<f64>, limit_um: f64) -> bool {
        let um = err_mm * 1000.0;
        self.err_um = if um.is_finite() { um } else { f64::INFINITY };
        self.err_vec = vec;
        self.thread_err = thread;
        !(self.err_um.abs() <= limit_um)
    }

    /// The last measured error, µm (held over unpaired cycles, 0 when nothing is locked).
    pub fn error_um(&self) -> f64 {
        self.err_um
    }

    /// This cycle's error per feed axis, mm (NaN over a held cycle).
    pub fn error_vec(&self) -> [f64; 3] {
        self.err_vec
    }

    /// A thread's phase error of this cycle, once.
    pub fn take_thread_err(&mut self) -> Option<f64> {
        self.thread_err.take()
    }

    /// Locked cycles not compared because their feedback was not from one SYNC.
    pub fn unpaired(&self) -> u32 {
        self.unpaired
    }

    /// This cycle's feedback, or the last cycle's, was not from one SYNC: learn nothing from it.
    pub fn suspect(&self) -> bool {
        self.suspect
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cycle_is_measured_only_after_a_locked_setpoint() {
        let mut m = SyncMonitor::default();
        assert_eq!(m.begin(true), Sample::Off);
        m.watch(true);
        assert_eq!(m.begin(true), Sample::Measure);
        assert!(!m.record(0.002, [0.0, 0.0, 0.002], None, 5.0));
        assert!((m.error_um() - 2.0).abs() < 1e-12);
        // Not re-armed: the next cycle is not compared and reads 0.
        assert_eq!(m.begin(true), Sample::Off);
        assert_eq!(m.error_um(), 0.0);
    }

    #[test]
    fn a_late_tpdo_and_the_cycle_after_it_hold_and_are_counted() {
        let mut m = SyncMonitor::default();
        m.watch(true);
        assert_eq!(m.begin(true), Sample::Measure);
        m.record(0.003, [0.0, 0.0, 0.003], None, 50.0);
        for paired in [false, true] {
            m.watch(true);
            assert_eq!(m.begin(paired), Sample::Held);
            assert!((m.error_um() - 3.0).abs() < 1e-12, "held");
            assert!(m.error_vec()[2].is_nan(), "the trim skips a held cycle");
            assert!(m.suspect());
        }
        assert_eq!(m.unpaired(), 2);
        m.watch(true);
        assert_eq!(m.begin(true), Sample::Measure);
        assert!(!m.suspect());
    }

    #[test]
    fn non_finite_feedback_exceeds_any_limit() {
        let mut m = SyncMonitor::default();
        m.watch(true);
        m.begin(true);
        assert!(m.record(f64::NAN, [f64::NAN; 3], None, 1e9));
        assert_eq!(m.error_um(), f64::INFINITY);
    }
}
