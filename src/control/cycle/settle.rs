//! The program's end: every drive settled onto its last set-point before the run hands the
//! machine to the stop (`rest`), bounded by the caller.
//!
//! A drive counts as settled on two *distinct* readings in a row within a count of its
//! target and of each other. Distinct matters on a bus that reads at its own rate (Modbus):
//! a loaded link reads a drive every third cycle, and the same reading seen on two cycles
//! is one sample — a spindle passing through its C angle at 2 rpm read 179.999° twice, the
//! run ended there and torque went off with the spindle creeping 0.05° short.

use crate::drives::AxisFeedback;

/// How far (counts) a settled reading may be from the target and from the one before.
const SETTLED_COUNTS: i64 = 1;

/// Each drive's last reading and whether it and the one before were on target.
pub(super) struct EndSettle {
    /// The last distinct reading's instant (`sampled_ns`), on a bus that gives one.
    sample: Vec<Option<u64>>,
    /// The last reading's counts while it was on target; `None`: it was not.
    on: Vec<Option<i64>>,
    settled: Vec<bool>,
}

impl EndSettle {
    /// Allocated once, before the run's first cycle.
    pub(super) fn new(n: usize) -> EndSettle {
        EndSettle { sample: vec![None; n], on: vec![None; n], settled: vec![false; n] }
    }

    /// Drive `d`'s reading this cycle against its target; true once it has settled. A
    /// reading seen before (no new sample) changes nothing.
    pub(super) fn update(&mut self, d: usize, f: &AxisFeedback, target: i64) -> bool {
        let new = match f.sampled_ns {
            Some(t) => self.sample[d].replace(t) != Some(t),
            None => f.age_cycles == 0,
        };
        if new {
            let on = (f.counts - target).abs() <= SETTLED_COUNTS;
            let prev = std::mem::replace(&mut self.on[d], on.then_some(f.counts));
            self.settled[d] = on && prev.is_some_and(|p| (f.counts - p).abs() <= SETTLED_COUNTS);
        }
        self.settled[d]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(counts: i64, sampled_ns: Option<u64>, age_cycles: u32) -> AxisFeedback {
        AxisFeedback { counts, sampled_ns, age_cycles, ..Default::default() }
    }

    #[test]
    fn one_sample_seen_twice_is_not_a_drive_at_rest() {
        let mut s = EndSettle::new(1);
        assert!(!s.update(0, &at(179_999, Some(10), 0), 180_000));
        assert!(!s.update(0, &at(179_999, Some(10), 1), 180_000), "the same sample again");
        assert!(!s.update(0, &at(179_960, Some(16), 0), 180_000), "it was passing through");
        assert!(!s.update(0, &at(180_000, Some(22), 0), 180_000));
        assert!(s.update(0, &at(180_001, Some(28), 0), 180_000), "two samples on target");
        assert!(s.update(0, &at(180_001, Some(28), 2), 180_000), "and it stays settled");
    }

    #[test]
    fn a_drive_read_at_the_cycle_settles_on_two_fresh_readings() {
        let mut s = EndSettle::new(2);
        assert!(!s.update(1, &at(5, None, 0), 5));
        assert!(!s.update(1, &at(5, None, 1), 5), "not fresh");
        assert!(s.update(1, &at(4, None, 0), 5));
        assert!(!s.update(1, &at(2, None, 0), 5), "moved off");
        assert!(!s.update(1, &at(6, None, 0), 5), "on, but three counts from the reading before");
        assert!(!s.update(0, &at(0, None, 0), 5), "the other drive is its own");
    }
}
