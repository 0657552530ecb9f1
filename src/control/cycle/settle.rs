//! The program's end: every drive settled onto its last set-point before the run hands the
//! machine to the stop (`rest`), bounded by the caller.
//!
//! A drive counts as settled on two *distinct* readings in a row within a count of its
//! target and of each other. Distinct matters on a bus that reads at its own rate (Modbus):
//! a loaded link reads a drive every third cycle, and the same reading seen on two cycles
//! is one sample — a spindle passing through its C angle at 2 rpm read 179.999° twice, the
//! run ended there and torque went off with the spindle creeping 0.05° short.
//!
//! A drive that does not settle is described (`SettleMiss`): how often it crossed its
//! target, how far it swung, whether it was still moving. A drive that hunts on its own
//! about a set-point that stands still (a belt with lost motion behind a slow speed filter:
//! ±28 µm, through the target on nearly every 2 ms cycle) is named as such — no set-point of ours fixes it, its own loops must be
//! tuned. The manuals are silent; a Fanuc 0i-TF raises SV0410 (excess error at stop, No.1829)
//! where the deviation at rest passes a limit; here the run already ends "not at the end
//! point", and the message says why.

use crate::drives::AxisFeedback;

/// How far (counts) a settled reading may be from the target and from the one before.
const SETTLED_COUNTS: i64 = 1;

/// Crossings of the target (by more than `SETTLED_COUNTS` each way) that make a hunt: one is
/// an overshoot, two a ring that may still die away, three a swing that goes on.
const HUNT_CROSSINGS: u32 = 3;

/// Cycles per half-period of a swing whose frequency the crossings tell.
const RESOLVED_READINGS: f64 = 4.0;

/// How a drive that had not settled moved about its target while the run waited.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SettleMiss {
    /// Counts from the target at the last reading (actual − target).
    pub off_counts: i64,
    /// The last reading's change from the one before, counts (0: standing).
    pub step_counts: i64,
    /// Times it crossed its target by more than a count each way.
    pub crossings: u32,
    /// Largest |actual − target| since the first crossing (throughout, where none), counts.
    pub peak_counts: i64,
    /// The hunt's frequency from the crossings (two per period), Hz; 0 with fewer than two.
    pub hunt_hz: f64,
    /// At least `RESOLVED_READINGS` cycles per half-period: `hunt_hz` is the swing's own
    /// frequency, not an alias of one faster than the cycle resolves (a velocity loop that
    /// oscillates at hundreds of Hz crosses the target on almost every reading).
    pub resolved: bool,
    /// Time the run waited, s.
    pub waited_s: f64,
}

impl SettleMiss {
    /// It swung through its target, again and again, on a set-point that stood still.
    pub fn hunts(&self) -> bool {
        self.crossings >= HUNT_CROSSINGS
    }
}

/// One drive's readings while settling.
#[derive(Clone, Copy, Default)]
struct Track {
    /// The last distinct reading's instant (`sampled_ns`), on a bus that gives one.
    sample: Option<u64>,
    /// The last reading's counts while it was on target; `None`: it was not.
    on: Option<i64>,
    settled: bool,
    /// The last reading, its distance from the target and its change from the one before.
    last: Option<i64>,
    off: i64,
    step: i64,
    /// Which side of the target it was last seen on beyond a count (−1, 0 not yet, +1).
    side: i8,
    crossings: u32,
    peak: i64,
    /// The settle cycles of the first and the last crossing.
    first: u32,
    at: u32,
}

/// Each drive's readings against its target, cycle by cycle.
pub(super) struct EndSettle {
    tracks: Vec<Track>,
    /// Cycles waited so far.
    cycles: u32,
}

impl EndSettle {
    /// Allocated once, before the run's first cycle.
    pub(super) fn new(n: usize) -> EndSettle {
        EndSettle { tracks: vec![Track::default(); n], cycles: 0 }
    }

    /// Drive `d`'s reading this cycle against its target; true once it has settled. A
    /// reading seen before (no new sample) changes nothing.
    pub(super) fn update(&mut self, d: usize, f: &AxisFeedback, target: i64) -> bool {
        let t = &mut self.tracks[d];
        t.read(f, target, self.cycles);
        t.settled
    }

    /// One more cycle waited (after every drive's `update`).
    pub(super) fn tick(&mut self) {
        self.cycles += 1;
    }

    pub(super) fn cycles(&self) -> u32 {
        self.cycles
    }

    /// How drive `d` missed, where it had not settled; `dt` the cycle, s.
    pub(super) fn miss(&self, d: usize, dt: f64) -> Option<SettleMiss> {
        let t = self.tracks.get(d)?;
        if t.settled || t.last.is_none() {
            return None;
        }
        Some(t.miss(self.cycles, dt))
    }
}

/// A set-point that stood this long (s) is one a drive had to settle on: mid-program, a drive
/// still swinging through it by then hunts, and one whose overshoot rang out within it does
/// not. The manuals are silent; a Fanuc 0i-TF arms its stop check (SV0410) once the command
/// has stood and the drive has had its in-position time — this is that time, generous.
const HUNT_MIN_S: f64 = 0.3;

/// A hunt mid-program: how a drive swung about a set-point that stood still, at which line,
/// and whether it was still at it when an alarm stopped the run (then it is the likely cause).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hunt {
    pub miss: SettleMiss,
    pub line: u32,
    pub at_alarm: bool,
}

/// One drive on its current set-point.
#[derive(Clone, Copy, Default)]
struct Stand {
    target: Option<i64>,
    line: u32,
    cycles: u32,
    track: Track,
}

/// Mid-program: each feed axis on a set-point that stands still (a dwell, an exact stop, the
/// wait for the spindle), watched for a hunt; each drive's largest is kept.
pub(super) struct HuntWatch {
    stands: Vec<Stand>,
    worst: Vec<Option<Hunt>>,
    dt: f64,
    /// `HUNT_MIN_S` in cycles.
    min_cycles: u32,
}

impl HuntWatch {
    /// Allocated once, before the run's first cycle.
    pub(super) fn new(n: usize, dt: f64) -> HuntWatch {
        HuntWatch { stands: vec![Stand::default(); n], worst: vec![None; n], dt, min_cycles: (HUNT_MIN_S / dt) as u32 }
    }

    /// Drive `d`'s reading this cycle against the set-point it answers, in block `line`.
    pub(super) fn update(&mut self, d: usize, f: &AxisFeedback, target: i64, line: u32) {
        if self.stands[d].target != Some(target) {
            self.close(d, self.min_cycles, false);
            self.stands[d] = Stand { target: Some(target), ..Stand::default() };
        }
        let s = &mut self.stands[d];
        s.cycles += 1;
        s.line = line;
        s.track.read(f, target, s.cycles);
    }

    /// The run stopped at an alarm: every drive still swinging counts, however short its
    /// stand — a hunt that tripped its drive (0x8611) is the alarm's cause.
    pub(super) fn at_alarm(&mut self) {
        for d in 0..self.stands.len() {
            self.close(d, 0, true);
        }
    }

    /// Drive `d`'s hunt: the one at the alarm, else the largest.
    pub(super) fn hunt(&self, d: usize) -> Option<Hunt> {
        self.worst.get(d).copied().flatten()
    }

    /// Drive `d`'s stand ends (it lasted at least `min` cycles): kept if it was a hunt.
    fn close(&mut self, d: usize, min: u32, at_alarm: bool) {
        let s = &self.stands[d];
        if s.target.is_none() || s.cycles < min || !s.track.swinging(s.cycles) {
            return;
        }
        let h = Hunt { miss: s.track.miss(s.cycles, self.dt), line: s.line, at_alarm };
        let w = &mut self.worst[d];
        if at_alarm || w.is_none_or(|w| !w.at_alarm && w.miss.peak_counts < h.miss.peak_counts) {
            *w = Some(h);
        }
    }
}

impl Track {
    /// The reading `f` against `target` in settle cycle `cycle`. A reading seen before (no
    /// new sample) changes nothing.
    fn read(&mut self, f: &AxisFeedback, target: i64, cycle: u32) {
        let new = match f.sampled_ns {
            Some(s) => self.sample.replace(s) != Some(s),
            None => f.age_cycles == 0,
        };
        if !new {
            return;
        }
        let off = f.counts - target;
        let on = off.abs() <= SETTLED_COUNTS;
        let prev = std::mem::replace(&mut self.on, on.then_some(f.counts));
        self.settled = on && prev.is_some_and(|p| (f.counts - p).abs() <= SETTLED_COUNTS);
        self.step = self.last.map_or(0, |l| f.counts - l);
        self.last = Some(f.counts);
        self.off = off;
        self.swing(off, cycle);
    }

    /// The description after `cycles` cycles of `dt` s.
    fn miss(&self, cycles: u32, dt: f64) -> SettleMiss {
        let span = self.at.saturating_sub(self.first) as f64 * dt;
        let hunt_hz = if self.crossings >= 2 && span > 0.0 { (self.crossings - 1) as f64 / (2.0 * span) } else { 0.0 };
        SettleMiss {
            off_counts: self.off,
            step_counts: self.step,
            crossings: self.crossings,
            peak_counts: self.peak,
            hunt_hz,
            resolved: hunt_hz * 2.0 * RESOLVED_READINGS * dt <= 1.0,
            waited_s: cycles as f64 * dt,
        }
    }

    /// Still swinging after `cycles`: its last crossing no longer ago than two of its
    /// half-periods (one where the cycle does not resolve them).
    fn swinging(&self, cycles: u32) -> bool {
        if self.crossings < HUNT_CROSSINGS {
            return false;
        }
        let half = (self.at - self.first) / (self.crossings - 1);
        cycles.saturating_sub(self.at) <= 2 * half.max(1)
    }

    /// The reading `off` counts from the target in settle cycle `cycle`: crossings and swing.
    fn swing(&mut self, off: i64, cycle: u32) {
        let side = if off > SETTLED_COUNTS {
            1
        } else if off < -SETTLED_COUNTS {
            -1
        } else {
            self.side
        };
        if side != self.side && self.side != 0 {
            if self.crossings == 0 {
                self.first = cycle;
                self.peak = 0;
            }
            self.crossings += 1;
            self.at = cycle;
        }
        self.side = side;
        self.peak = self.peak.max(off.abs());
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

    /// Readings `offs` (from a target of 0), one a cycle; the miss after them.
    fn settle(offs: &[i64]) -> Option<SettleMiss> {
        let mut s = EndSettle::new(1);
        for o in offs {
            s.update(0, &at(*o, None, 0), 0);
            s.tick();
        }
        s.miss(0, 0.001)
    }

    #[test]
    fn a_drive_that_swings_through_its_target_again_and_again_hunts() {
        // ±28 counts, a period of 40 cycles (25 Hz at 1 ms), for 200 cycles.
        let offs: Vec<i64> = (0..200).map(|k| (28.0 * (k as f64 * std::f64::consts::TAU / 40.0).sin()).round() as i64).collect();
        let m = settle(&offs).expect("it never settled");
        assert!(m.hunts(), "{m:?}");
        assert_eq!(m.peak_counts, 28);
        assert!((m.hunt_hz - 25.0).abs() < 1.5 && m.resolved, "{m:?}");
        assert!((m.waited_s - 0.2).abs() < 1e-9, "{m:?}");
        // Through the target on every other reading: faster than the cycle resolves.
        let m = settle(&[30, -30, 30, -30, 30, -30, 30, -30]).unwrap();
        assert!(m.hunts() && m.crossings == 7 && !m.resolved, "{m:?}");
    }

    #[test]
    fn an_overshoot_that_dies_away_is_no_hunt_nor_a_miss() {
        let m = settle(&[-40, -10, 5, 9, 4, 1, 0, 0]);
        assert_eq!(m, None, "settled");
        let m = settle(&[-40, -10, 5, 9, 4, 2]).expect("not yet settled");
        assert!(!m.hunts() && m.crossings == 1 && m.peak_counts == 9 && m.step_counts == -2, "{m:?}");
    }

    #[test]
    fn a_drive_short_of_its_target_is_moving_or_standing() {
        let moving = settle(&[-9, -8, -7, -6]).unwrap();
        assert_eq!((moving.off_counts, moving.step_counts, moving.crossings, moving.peak_counts), (-6, 1, 0, 9));
        let standing = settle(&[-9, -5, -5, -5]).unwrap();
        assert_eq!((standing.off_counts, standing.step_counts), (-5, 0));
        // Noise of a count about the target is no crossing.
        assert_eq!(settle(&[1, -1, 1, -1, 2, -2]).unwrap().crossings, 1);
    }

    /// Readings `offs` from a set-point of 0 that stands, one a cycle of 2 ms, after a move
    /// (targets 100, 50); then `after` (None: an alarm stops the run there).
    fn stand(offs: &[i64], after: Option<i64>) -> Option<Hunt> {
        let mut w = HuntWatch::new(1, 0.002);
        w.update(0, &at(120, None, 0), 100, 4);
        w.update(0, &at(70, None, 0), 50, 4);
        for o in offs {
            w.update(0, &at(*o, None, 0), 0, 5);
        }
        match after {
            Some(t) => w.update(0, &at(t, None, 0), t, 6),
            None => w.at_alarm(),
        }
        w.hunt(0)
    }

    #[test]
    fn a_swing_that_goes_on_through_a_dwell_is_a_hunt_at_its_line() {
        // ±28 counts at 25 Hz through a 0.4 s dwell (line 5), then the next move.
        let offs: Vec<i64> = (0..200).map(|k| (28.0 * (k as f64 * std::f64::consts::TAU / 20.0).sin()).round() as i64).collect();
        let h = stand(&offs, Some(40)).expect("a hunt");
        assert_eq!((h.line, h.at_alarm, h.miss.peak_counts), (5, false, 28), "{h:?}");
        assert!((h.miss.hunt_hz - 25.0).abs() < 1.0 && h.miss.resolved, "{h:?}");
        assert!((h.miss.waited_s - 0.4).abs() < 0.01, "{h:?}");
        // Too short a stand to tell, unless an alarm stops it there.
        assert_eq!(stand(&offs[..100], Some(40)), None);
        assert!(stand(&offs[..100], None).is_some_and(|h| h.at_alarm));
    }

    #[test]
    fn an_overshoot_that_rings_out_within_the_stand_is_no_hunt() {
        // Three crossings in the first 30 ms, then on target for the rest of 0.4 s.
        let mut offs = vec![-40, -10, 12, 9, -6, -3, 4, 2, 1];
        offs.resize(200, 0);
        assert_eq!(stand(&offs, Some(40)), None);
        assert_eq!(stand(&offs, None), None, "nor at an alarm");
    }
}
