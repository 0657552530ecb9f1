//! The end of every run: spindle and axes brought to rest under control before torque goes
//! off, whatever ended the run.
//!
//! Causes and what the drives do (docs/ARCHITECTURE.md, "Every stop"): the program's end and
//! every controlled stop (a program alarm, reset, a signal, the watchdog, one drive's fault
//! with the others under control) keep sending set-points — the path decelerates, the spindle
//! ramps down on its acceleration (a Fanuc 0i-TF's reset at M02/M30 likewise stops the
//! spindle) — until every drive reports the same position for [`STILL_CYCLES`] cycles and the
//! ones under control stand on their set-point. E-stop, a bus error or a second fault
//! quick-stop every drive: each brakes on its own quick-stop ramp (0x605A, 0x6085) and the
//! loop watches until they stand still. A controlled stop that has not come to rest after
//! [`REST_TIMEOUT_NS`] falls back to quick stop; one that still has not after another
//! [`QUICK_TIMEOUT_NS`] is reported as not at rest. Only then does the caller's `finish`
//! switch the drives off.

use super::{CycleLoop, SpindleMeter};
use crate::motion::Motion;
use crate::Alarm;

/// A drive counts as standing still after this many cycles of fresh feedback within
/// [`STILL_COUNTS`] of the cycle before.
pub const STILL_CYCLES: u32 = 10;
/// Counts a drive at rest may jitter from one cycle to the next.
const STILL_COUNTS: i64 = 2;
/// A drive under control that stands still but off its set-point (friction holding it short)
/// counts as at rest after this many still cycles.
const STILL_OFF_TARGET_CYCLES: u32 = 100;
/// A drive without fresh feedback for this many of its feedback periods cannot be seen coming
/// to rest.
const SILENT_CYCLES: u32 = 10;
/// Longest controlled stop before falling back to quick stop, ns of clock time (a spindle
/// at 6000 rpm braking at 1000 rpm/s takes 6 s).
pub const REST_TIMEOUT_NS: u64 = 10_000_000_000;
/// Longest wait for quick-stopped drives to stand still, ns.
pub const QUICK_TIMEOUT_NS: u64 = 5_000_000_000;

/// How the machine came to rest at the end of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rest {
    /// Every drive stood still (the ones under control on their set-point) before torque was
    /// removed.
    pub at_rest: bool,
    /// Every drive was sent quick stop (E-stop, a bus error, a second fault, a limit, or the
    /// controlled stop timed out).
    pub quick_stop: bool,
    /// The controlled stop did not come to rest within its time and quick stop was sent.
    pub timed_out: bool,
    /// From the end of the program or the stop's start (the alarm, reset or drive fault that
    /// began it) to standstill, s of clock time.
    pub time_s: f64,
    /// A faulted drive braked on its own fault reaction (the others under control).
    pub fault_reaction: bool,
    /// The spindle's measured speed when the run handed the drives back for torque off, rpm.
    pub spindle_rpm_at_off: f64,
    /// Drives that sent no feedback while stopping (a silent node, a lost bus): not seen at
    /// rest; they stop by themselves when they miss the controller's heartbeat.
    pub unobserved: u32,
}

impl Rest {
    /// The machine's state in words, for the run's message.
    pub fn describe(&self) -> String {
        match (self.at_rest, self.quick_stop, self.timed_out) {
            (true, false, _) if self.fault_reaction => format!(
                "the faulted drive braked on its own fault reaction, the others under control; all stood still {:.2} s after the stop began; torque was removed at standstill",
                self.time_s
            ),
            (true, false, _) => format!(
                "spindle and axes came to rest under control in {:.2} s; torque was removed at standstill",
                self.time_s
            ),
            (true, true, false) => format!(
                "every drive was sent quick stop and braked on its own ramp to standstill in {:.2} s; torque was removed at standstill",
                self.time_s
            ),
            (true, true, true) => format!(
                "the controlled stop did not come to rest in time: every drive was sent quick stop and stood still after {:.2} s",
                self.time_s
            ),
            (false, _, _) if self.unobserved > 0 => format!(
                "{} drive(s) sent no feedback and could not be seen coming to rest (the others did in {:.2} s); a drive that misses the controller's heartbeat stops by itself",
                self.unobserved, self.time_s
            ),
            (false, _, _) => format!(
                "the drives were NOT seen at rest ({:.0} rpm measured on the spindle when the run ended): check the machine before you touch it; drives that lost the controller's heartbeat stop by themselves",
                self.spindle_rpm_at_off
            ),
        }
    }
}

/// Per drive: fresh readings in a row that stood still. Allocated once, before the
/// run's first cycle.
pub(super) struct Still {
    prev: Vec<Option<i64>>,
    cycles: Vec<u32>,
    /// Cycles without fresh feedback after which a drive counts as silent: [`SILENT_CYCLES`]
    /// of its own feedback period (a Modbus link reads a drive every few machine cycles).
    silent_after: Vec<u32>,
}

impl Still {
    /// `period_cycles`: each drive's feedback period in machine cycles (1 at SYNC).
    pub(super) fn new(period_cycles: &[u32]) -> Still {
        let n = period_cycles.len();
        let silent_after = period_cycles.iter().map(|p| SILENT_CYCLES * (*p).max(1)).collect();
        Still { prev: vec![None; n], cycles: vec![0; n], silent_after }
    }

    fn silent_after(&self, d: usize) -> u32 {
        self.silent_after.get(d).copied().unwrap_or(SILENT_CYCLES)
    }

    fn reset(&mut self) {
        self.prev.iter_mut().for_each(|p| *p = None);
        self.cycles.iter_mut().for_each(|c| *c = 0);
    }

    fn update(&mut self, d: usize, counts: i64, fresh: bool) {
        let Some(c) = self.cycles.get_mut(d) else { return };
        if !fresh {
            // Nothing new (a Modbus link slower than the machine cycle reads a drive every
            // few cycles): neither still nor moving. A drive that goes silent is `silent`.
            return;
        }
        let prev = self.prev[d].replace(counts);
        let still = prev.is_some_and(|p| (counts - p).abs() <= STILL_COUNTS);
        *c = if still { c.saturating_add(1) } else { 0 };
    }

    fn cycles(&self, d: usize) -> u32 {
        self.cycles.get(d).copied().unwrap_or(0)
    }
}

impl CycleLoop<'_> {
    /// Quick stop on every drive (each brakes on its own quick-stop ramp).
    pub(super) fn quick_stop_all(&mut self) {
        self.quick = true;
        self.drives.quick_stop();
    }

    /// Bring spindle and axes to rest (see the module doc), and the first alarm the drives
    /// raised while stopping (a drive that faulted after the program's end: the run must say
    /// so, not just that quick stop was sent). Allocates nothing but that alarm. (A verb, not a
    /// conversion: the `to_*` naming lint does not apply.)
    #[allow(clippy::wrong_self_convention)]
    pub(super) fn to_rest(&mut self, motion: &mut Motion, still: &mut Still) -> (Rest, Option<Alarm>) {
        let entry = self.clock.now_ns();
        // The time to standstill counts from the stop's start where a stop loop ran before.
        let t0 = self.stop_t0.unwrap_or(entry).min(entry);
        let dt = self.cycle_ns.max(1);
        let mut rest = Rest { fault_reaction: self.fault_reaction, ..Rest::default() };
        let mut raised = None;
        motion.stop();
        let mut meter = SpindleMeter::new(self.spindle_pos(), self.rpm);
        still.reset();
        let mut deadline = entry + if self.quick { QUICK_TIMEOUT_NS } else { REST_TIMEOUT_NS };
        let mut next = entry;
        loop {
            next += dt;
            self.clock.wait_until(next);
            let now = self.clock.now_ns();
            if let Err(a) = self.drives.receive(now) {
                if !self.quick {
                    // Something new went wrong while stopping: every drive brakes on its own.
                    self.quick_stop_all();
                    deadline = now + QUICK_TIMEOUT_NS;
                }
                raised.get_or_insert(a);
            }
            if !self.quick && self.panel.as_mut().is_some_and(|r| r.poll().estop) {
                self.quick_stop_all();
                deadline = now + QUICK_TIMEOUT_NS;
            }
            let fb = self.read_feedback(&mut meter);
            let sp = self.stop_step(motion, &fb, &mut next, now);
            // A set-point beyond the limits is never sent, while stopping either; quick-
            // stopped drives keep their last target.
            if !self.quick && self.active_guard.as_mut().is_some_and(|g| g.check(&motion.position()).is_err()) {
                self.quick_stop_all();
                deadline = now + QUICK_TIMEOUT_NS;
            }
            if !self.quick {
                self.send(&sp);
            }
            // The outputs as the run left them (M02/M30 switched the coolant off).
            if let Ok(Some(io)) = self.io.as_ref() {
                io.write(&mut *self.drives);
            }
            if self.drives.transmit(now).is_err() {
                // The bus is gone: nothing can be seen any more; the drives stop by themselves
                // when they miss the heartbeat.
                rest.unobserved = self.drives.axis_count() as u32;
                rest.time_s = now.saturating_sub(t0) as f64 * 1e-9;
                self.quick = true;
                break;
            }
            if let Some(w) = self.tap.as_mut() {
                w.on_cycle(sp.line, &sp.pos, &fb.pos);
            }
            let n = self.drives.axis_count();
            for d in 0..n {
                let f = self.drives.feedback(d);
                still.update(d, f.counts, f.age_cycles == 0);
            }
            let silent = |d: usize| self.drives.feedback(d).age_cycles > still.silent_after(d);
            let settled = |d: usize| {
                let c = still.cycles(d);
                let f = self.drives.feedback(d);
                if silent(d) {
                    return true;
                }
                // A drive not in Operation Enabled (its own fault reaction) has no set-point,
                // nor has a spindle driven in speed (at rest is standing still: on a link read
                // every 83 ms, the 100 still readings off target took 8.3 s and the stop fell
                // back to quick stop at its 10 s).
                let under_control = f.state() == cncgw_bus::cia402::State::OperationEnabled && self.drives.holds_position(d);
                let on_target = !under_control || (f.counts - self.drives.target_counts(d)).abs() <= self.in_position_counts(d);
                c >= STILL_CYCLES && (self.quick || on_target || c >= STILL_OFF_TARGET_CYCLES)
            };
            let commanded_rest = self.quick || (motion.is_idle() && motion.spindle_at_rest());
            if commanded_rest && (0..n).all(settled) {
                rest.unobserved = (0..n).filter(|d| silent(*d)).count() as u32;
                rest.at_rest = rest.unobserved == 0;
                rest.time_s = now.saturating_sub(t0) as f64 * 1e-9;
                break;
            }
            if now >= deadline {
                if self.quick {
                    rest.time_s = now.saturating_sub(t0) as f64 * 1e-9;
                    break;
                }
                rest.timed_out = true;
                self.quick_stop_all();
                deadline = now + QUICK_TIMEOUT_NS;
            }
        }
        rest.quick_stop = self.quick;
        rest.spindle_rpm_at_off = meter.rpm;
        (rest, raised)
    }

    /// This cycle's set-points to every drive motion commands.
    pub(super) fn send(&mut self, sp: &crate::motion::Setpoint) {
        for d in 0..self.drives.axis_count() {
            if let Some(a) = super::motion_axis(self.drives.axis_name(d), Some(d) == self.spindle_drive) {
                self.drives.set_target(d, sp.pos[a]);
            } else if self.tool.is_some_and(|t| t.drive == d) {
                self.drives.set_target(d, sp.tool_spindle);
            }
        }
    }

    /// How close to its set-point a drive under control must stand: 1 µm on a feed axis,
    /// 0.05° on a spindle (whose soft position loop creeps the last hundredths of a degree
    /// for half a second at standstill), at least two counts.
    fn in_position_counts(&self, d: usize) -> i64 {
        let unit = if Some(d) == self.spindle_drive || self.tool.is_some_and(|t| t.drive == d) { 0.05 } else { 0.001 };
        ((self.drives.counts_per_unit(d) * unit).round() as i64).max(STILL_COUNTS)
    }

    fn spindle_pos(&self) -> f64 {
        self.spindle_drive.map(|s| self.drives.feedback(s).pos).unwrap_or(0.0)
    }
}
