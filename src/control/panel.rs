//! The operator panel as the cycle loop sees it: buttons (feed hold, cycle start, reset),
//! switches (single block, optional stop, E-stop) and override dials, set from any thread
//! (the terminal's key handler, a test, a future control socket) and read by the cycle loop
//! once per cycle without locking or allocating.
//!
//! Buttons are edge-triggered: each press is counted, and the loop acts once per new count,
//! so a press between two cycles is never lost and a held key does not repeat. Switches and
//! dials are levels.

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering::Relaxed};
use std::sync::Arc;

#[derive(Debug)]
struct Inner {
    feed_hold: AtomicU32,
    cycle_start: AtomicU32,
    reset: AtomicU32,
    single_block: AtomicBool,
    optional_stop: AtomicBool,
    estop: AtomicBool,
    /// Percent.
    feed_ovr: AtomicU32,
    rapid_ovr: AtomicU32,
    spindle_ovr: AtomicU32,
    // What the loop reports back (for the display).
    held: AtomicBool,
    line: AtomicU32,
    /// The safety inputs ([`SafetyInputs::word`]).
    safety: AtomicU32,
}

/// The `[io.safety]` inputs as the cycle loop last read them, for the display: `None` = not
/// configured, `Some(true)` = closed (E-stop chain closed, door shut, chuck clamped).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SafetyInputs {
    pub estop: Option<bool>,
    pub door: Option<bool>,
    pub chuck: Option<bool>,
}

impl SafetyInputs {
    /// Two bits per input (configured, closed), in one word the loop stores without a lock.
    pub fn word(&self) -> u32 {
        [self.estop, self.door, self.chuck].iter().enumerate().fold(0, |w, (k, v)| w | v.map_or(0, |c| (1 | (c as u32) << 1) << (2 * k)))
    }
    pub fn from_word(w: u32) -> SafetyInputs {
        let get = |k: u32| (w >> (2 * k) & 1 == 1).then_some(w >> (2 * k + 1) & 1 == 1);
        SafetyInputs { estop: get(0), door: get(1), chuck: get(2) }
    }
    /// How the operator sees each configured input (the panel's status line, `cncgw monitor`):
    /// an open one in capitals.
    pub fn labels(&self) -> impl Iterator<Item = &'static str> {
        [(self.estop, "E-stop ok", "E-STOP OPEN"), (self.door, "door shut", "DOOR OPEN"), (self.chuck, "chuck clamped", "CHUCK OPEN")]
            .into_iter()
            .filter_map(|(input, ok, open)| input.map(|closed| if closed { ok } else { open }))
    }
}

/// The panel's handle; clones share one panel.
#[derive(Clone, Debug)]
pub struct Panel(Arc<Inner>);

impl Default for Panel {
    fn default() -> Self {
        Panel(Arc::new(Inner {
            feed_hold: AtomicU32::new(0),
            cycle_start: AtomicU32::new(0),
            reset: AtomicU32::new(0),
            single_block: AtomicBool::new(false),
            optional_stop: AtomicBool::new(false),
            estop: AtomicBool::new(false),
            feed_ovr: AtomicU32::new(100),
            rapid_ovr: AtomicU32::new(100),
            spindle_ovr: AtomicU32::new(100),
            held: AtomicBool::new(false),
            line: AtomicU32::new(0),
            safety: AtomicU32::new(0),
        }))
    }
}

impl Panel {
    pub fn new() -> Self {
        Self::default()
    }
    /// Feed hold: the path decelerates and waits (per the cycle step's rules).
    pub fn press_feed_hold(&self) {
        self.0.feed_hold.fetch_add(1, Relaxed);
    }
    /// Cycle start: resume after feed hold, single-block stop, M00/M01.
    pub fn press_cycle_start(&self) {
        self.0.cycle_start.fetch_add(1, Relaxed);
    }
    /// Reset: a controlled stop, then the program ends (alarm 2401).
    pub fn press_reset(&self) {
        self.0.reset.fetch_add(1, Relaxed);
    }
    pub fn set_single_block(&self, on: bool) {
        self.0.single_block.store(on, Relaxed);
    }
    pub fn single_block(&self) -> bool {
        self.0.single_block.load(Relaxed)
    }
    pub fn set_optional_stop(&self, on: bool) {
        self.0.optional_stop.store(on, Relaxed);
    }
    /// E-stop: while pressed, every drive gets quick stop (alarm 2400).
    pub fn set_estop(&self, on: bool) {
        self.0.estop.store(on, Relaxed);
    }
    /// Feed override, percent (0–200).
    pub fn set_feed_override(&self, pct: u32) {
        self.0.feed_ovr.store(pct.min(200), Relaxed);
    }
    /// Rapid override, percent (0–100).
    pub fn set_rapid_override(&self, pct: u32) {
        self.0.rapid_ovr.store(pct.min(100), Relaxed);
    }
    /// Spindle override, percent (50–120).
    pub fn set_spindle_override(&self, pct: u32) {
        self.0.spindle_ovr.store(pct.clamp(50, 120), Relaxed);
    }
    pub fn feed_override(&self) -> u32 {
        self.0.feed_ovr.load(Relaxed)
    }
    pub fn rapid_override(&self) -> u32 {
        self.0.rapid_ovr.load(Relaxed)
    }
    pub fn spindle_override(&self) -> u32 {
        self.0.spindle_ovr.load(Relaxed)
    }
    /// True while the program waits for cycle start (feed hold, single block, M00/M01), as
    /// last reported by the cycle loop.
    pub fn is_held(&self) -> bool {
        self.0.held.load(Relaxed)
    }
    /// The source line of the block in execution, as last reported by the cycle loop.
    pub fn line(&self) -> u32 {
        self.0.line.load(Relaxed)
    }

    /// The safety inputs as last reported by the cycle loop.
    pub fn safety(&self) -> SafetyInputs {
        SafetyInputs::from_word(self.0.safety.load(Relaxed))
    }

    /// The loop's reader (remembers which presses it has acted on).
    pub fn reader(&self) -> PanelReader {
        PanelReader {
            panel: self.clone(),
            feed_hold: self.0.feed_hold.load(Relaxed),
            cycle_start: self.0.cycle_start.load(Relaxed),
            reset: self.0.reset.load(Relaxed),
        }
    }
}

/// What changed on the panel since the last poll.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PanelInput {
    pub feed_hold: bool,
    pub cycle_start: bool,
    pub reset: bool,
    pub estop: bool,
    pub single_block: bool,
    pub optional_stop: bool,
    /// Fractions (1.0 = 100 %).
    pub feed_ovr: f64,
    pub rapid_ovr: f64,
    pub spindle_ovr: f64,
}

/// The cycle loop's side of a [`Panel`].
#[derive(Debug)]
pub struct PanelReader {
    panel: Panel,
    feed_hold: u32,
    cycle_start: u32,
    reset: u32,
}

impl PanelReader {
    /// Read the panel: buttons pressed since the last poll, switches, dials. No allocation.
    pub fn poll(&mut self) -> PanelInput {
        let p = &self.panel.0;
        let edge = |seen: &mut u32, now: u32| {
            let pressed = now != *seen;
            *seen = now;
            pressed
        };
        PanelInput {
            feed_hold: edge(&mut self.feed_hold, p.feed_hold.load(Relaxed)),
            cycle_start: edge(&mut self.cycle_start, p.cycle_start.load(Relaxed)),
            reset: edge(&mut self.reset, p.reset.load(Relaxed)),
            estop: p.estop.load(Relaxed),
            single_block: p.single_block.load(Relaxed),
            optional_stop: p.optional_stop.load(Relaxed),
            feed_ovr: p.feed_ovr.load(Relaxed) as f64 / 100.0,
            rapid_ovr: p.rapid_ovr.load(Relaxed) as f64 / 100.0,
            spindle_ovr: p.spindle_ovr.load(Relaxed) as f64 / 100.0,
        }
    }

    /// Report the loop's state back to the panel (for the display).
    pub fn report(&self, held: bool, line: u32) {
        self.panel.0.held.store(held, Relaxed);
        self.panel.0.line.store(line, Relaxed);
    }

    /// Report the safety inputs read this cycle (for the display).
    pub fn report_safety(&self, s: SafetyInputs) {
        self.panel.0.safety.store(s.word(), Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presses_are_edges_and_none_is_lost() {
        let p = Panel::new();
        let mut r = p.reader();
        assert!(!r.poll().feed_hold);
        p.press_feed_hold();
        p.press_feed_hold();
        let i = r.poll();
        assert!(i.feed_hold && !i.cycle_start && !i.reset);
        assert!(!r.poll().feed_hold, "a press acts once");
        p.press_cycle_start();
        assert!(r.poll().cycle_start);
        p.set_estop(true);
        assert!(r.poll().estop && r.poll().estop, "E-stop is a level");
    }

    #[test]
    fn dials_are_clamped() {
        let p = Panel::new();
        let mut r = p.reader();
        p.set_feed_override(500);
        p.set_spindle_override(10);
        p.set_rapid_override(150);
        let i = r.poll();
        assert_eq!((i.feed_ovr, i.spindle_ovr, i.rapid_ovr), (2.0, 0.5, 1.0));
        r.report(true, 42);
        assert!(p.is_held());
        assert_eq!(p.line(), 42);
    }

    #[test]
    fn safety_inputs_round_trip_through_the_word() {
        let p = Panel::new();
        assert_eq!(p.safety(), SafetyInputs::default());
        for s in [
            SafetyInputs { estop: Some(true), door: Some(false), chuck: None },
            SafetyInputs { estop: None, door: Some(true), chuck: Some(false) },
            SafetyInputs { estop: Some(false), door: None, chuck: Some(true) },
        ] {
            p.reader().report_safety(s);
            assert_eq!(p.safety(), s);
        }
    }
}
