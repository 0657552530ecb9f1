//! The rigid-tap state kept on disk while a tap runs (manual 000, "刚性攻丝返回"), so that
//! `G30 P99` can bring the tool out along the thread after any interruption — reset, E-stop,
//! a feed hold abort, or the controller process dying.
//!
//! Three parts, so that the cycle thread neither blocks nor allocates:
//! - [`TapWatch`] runs on the cycle thread. It learns each tap hole from the `Tap` strokes as
//!   they are pushed into motion (axis, R plane = where the hole's first stroke starts,
//!   direction, lead, speed in, pull-out override = speed out / speed in) into a ring
//!   allocated once, and every cycle works out from the set-point (its line and position)
//!   and the actual positions whether the tool is inside the hole being tapped. It publishes
//!   the state into a [`TapSlot`].
//! - [`TapSlot`]: a seqlock of atomics — one writer (the cycle), any readers; a write is a
//!   dozen atomic stores, a read retries while a write is in progress.
//! - [`TapPersister`]: a thread that reads the slot every `period` (and at once when the
//!   cycle wakes it: the tool entered the hole, or is back at R) and, when the state changed,
//!   replaces the file atomically (`persist::atomic_write`: temporary file, fsync, rename,
//!   fsync of the directory).
//!
//! "In the hole": the tool's commanded position is past the R plane into the hole (by any
//! amount), or its actual position is by more than [`IN_HOLE_MM`]. The state is written at
//! the entry, every `period` while the tool moves in the hole, and "not in a hole" once both
//! are back at R.
//!
//! The entry is on disk before the tool leaves R: motion holds a hole's first stroke at R
//! (spindle at rest, like a dwell; [`crate::motion::Motion::gate_taps`]) while
//! [`TapWatch::gate`] publishes the "in hole" state with the hole's R, lead, axis and the
//! spindle angle at R, and opens it once the writer acknowledges that state durable
//! ([`TapSlot::acked`]: the slot sequence of the last state the writer has on disk). A write
//! is two fsyncs: on an SSD about a millisecond; on this project's loaded build VM 22 ms
//! median and ~1 s at p90. Past [`ACK_TIMEOUT`] without the acknowledgement: alarm
//! [`TAP_ACK_TIMEOUT`], no stroke starts (a Fanuc has no such state file; a controller that
//! cannot record where the tool is must not put it into the hole).
//!
//! At start-up a state that says "in the hole" refuses any program whose first motion is not
//! `G30 P99` (alarm [`TAP_IN_HOLE`]): a Fanuc 0i-TF likewise raises an alarm and asks for
//! the rigid-tap return before anything else moves.

use crate::canon::{Move, MoveKind};
use crate::motion::{TapEntry, AX_S, N_AXES};
use crate::persist::{TapState, TapStateFile};
use crate::Alarm;
use std::sync::atomic::{fence, AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Our alarm: the tool is in a tapped hole (stored state) and the program does not start with
/// `G30 P99`.
pub const TAP_IN_HOLE: u32 = crate::alarm::TAP_IN_HOLE;

/// Our alarm: the tap-state writer did not acknowledge a hole's entry state within
/// [`ACK_TIMEOUT`]; the tap did not start.
pub const TAP_ACK_TIMEOUT: u32 = crate::alarm::TAP_ACK_TIMEOUT;

/// How long a hole's first stroke waits at R for the entry state to be on disk.
pub const ACK_TIMEOUT: Duration = Duration::from_secs(2);

/// The actual position counts as inside the hole past this depth (mm): a drive at rest on R
/// jitters by a count or two.
pub const IN_HOLE_MM: f64 = 0.002;

/// Holes remembered between being pushed and being tapped (motion's queue holds at most
/// `Limits::queue_len` items, 1024 by default, and a hole takes two strokes at least).
const HOLES: usize = 1024;

const WORDS: usize = 8;

/// The published state: a seqlock over atomics (no torn reads, no locks, no allocation).
pub struct TapSlot {
    seq: AtomicU64,
    w: [AtomicU64; WORDS],
    /// The sequence (of `store`) of the last state the writer has on disk.
    ack: AtomicU64,
}

impl TapSlot {
    pub fn new(init: Option<TapState>) -> Arc<TapSlot> {
        let s = TapSlot { seq: AtomicU64::new(0), w: Default::default(), ack: AtomicU64::new(0) };
        s.store(&init);
        Arc::new(s)
    }

    /// The sequence of the last state the writer acknowledged as on disk (0: none).
    pub fn acked(&self) -> u64 {
        self.ack.load(Ordering::Acquire)
    }

    /// The writer: the state of sequence `seq` (from `load_seq`) is on disk.
    pub fn acknowledge(&self, seq: u64) {
        self.ack.fetch_max(seq, Ordering::AcqRel);
    }

    fn encode(st: &Option<TapState>) -> [u64; WORDS] {
        let Some(t) = st else { return [0; WORDS] };
        let flags = 1 | (t.in_hole as u64) << 1 | (t.axis as u64 & 0xFF) << 8 | (t.line as u64) << 32;
        let dir_lead = if t.direction_in < 0.0 { 1u64 << 2 } else { 0 };
        [
            flags | dir_lead,
            t.r_plane.to_bits(),
            t.lead.to_bits(),
            t.rpm.to_bits(),
            t.override_pct.to_bits(),
            t.position.to_bits(),
            t.spindle_deg.to_bits(),
            0,
        ]
    }

    fn decode(w: &[u64; WORDS]) -> Option<TapState> {
        let f = w[0];
        if f & 1 == 0 {
            return None;
        }
        Some(TapState {
            in_hole: f & 2 != 0,
            axis: char::from((f >> 8) as u8),
            r_plane: f64::from_bits(w[1]),
            direction_in: if f & 4 != 0 { -1.0 } else { 1.0 },
            lead: f64::from_bits(w[2]),
            rpm: f64::from_bits(w[3]),
            override_pct: f64::from_bits(w[4]),
            position: f64::from_bits(w[5]),
            spindle_deg: f64::from_bits(w[6]),
            line: (f >> 32) as u32,
        })
    }

    /// Publish `st`; returns its sequence (see `acked`). One writer at a time (the cycle
    /// thread).
    pub fn store(&self, st: &Option<TapState>) -> u64 {
        let v = Self::encode(st);
        let s = self.seq.load(Ordering::Relaxed);
        self.seq.store(s.wrapping_add(1), Ordering::Relaxed);
        fence(Ordering::Release);
        for (a, x) in self.w.iter().zip(v) {
            a.store(x, Ordering::Relaxed);
        }
        self.seq.store(s.wrapping_add(2), Ordering::Release);
        s.wrapping_add(2)
    }

    /// The last published state (retries while a write is in progress).
    pub fn load(&self) -> Option<TapState> {
        self.load_seq().1
    }

    /// The last published state and its sequence.
    pub fn load_seq(&self) -> (u64, Option<TapState>) {
        loop {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 & 1 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let mut v = [0u64; WORDS];
            for (x, a) in v.iter_mut().zip(&self.w) {
                *x = a.load(Ordering::Relaxed);
            }
            fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) == s1 {
                return (s1, Self::decode(&v));
            }
        }
    }
}

/// One excursion of a tap from its R plane into the hole and back, as pushed.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Hole {
    line: u32,
    axis: usize,
    r: f64,
    dir: f64,
    lead: f64,
    rpm: f64,
    ovr: f64,
    /// Its return to R has not been pushed yet.
    open: bool,
}

/// The cycle thread's side: see the module doc. Allocates only in `new`.
pub struct TapWatch {
    slot: Arc<TapSlot>,
    wake: Option<std::thread::Thread>,
    holes: Vec<Hole>,
    /// Holes pushed, and the index of the one being tapped or next to be.
    pushed: u64,
    cursor: u64,
    /// The tool is inside hole `cursor`.
    inside: bool,
    /// Where the last pushed motion ends (X radius, Y, Z).
    last_end: [f64; 3],
    /// The state loaded at start (an interrupted tap that `G30 P99` returns from).
    seed: Option<TapState>,
    /// The entry published for the hole waiting at R: its sequence, when, the state before.
    pending: Option<(u64, Instant, Option<TapState>)>,
    ack_timeout: Duration,
    /// The longest wait at R so far for an acknowledgement.
    max_wait: Duration,
}

const AXIS_CHARS: [char; 3] = ['X', 'Y', 'Z'];

impl TapWatch {
    /// `start`: the machine position the program starts from; `seed`: the state loaded from
    /// disk (its R plane, speed and override are those of a `G30 P99` return).
    pub fn new(slot: Arc<TapSlot>, wake: Option<std::thread::Thread>, start: &[f64; N_AXES], seed: Option<TapState>) -> TapWatch {
        TapWatch {
            slot,
            wake,
            holes: vec![Hole::default(); HOLES],
            pushed: 0,
            cursor: 0,
            inside: false,
            last_end: [start[0], start[1], start[2]],
            seed,
            pending: None,
            ack_timeout: ACK_TIMEOUT,
            max_wait: Duration::ZERO,
        }
    }

    /// Replace [`ACK_TIMEOUT`] (tests).
    pub fn set_ack_timeout(&mut self, t: Duration) {
        self.ack_timeout = t;
    }

    /// The longest a hole's first stroke waited at R for the writer so far.
    pub fn max_ack_wait(&self) -> Duration {
        self.max_wait
    }

    /// Every cycle after `on_cycle`, with motion's hole waiting at R (`Motion::tap_waiting`):
    /// publish its "in hole" entry state once, wake the writer, and say whether the stroke may
    /// start (`Ok(true)`: the writer has it on disk). `Err`: no acknowledgement within the
    /// timeout (the published entry is withdrawn; the caller stops). No allocation, no
    /// blocking (but for the alarm).
    pub fn gate(&mut self, waiting: Option<TapEntry>) -> Result<bool, Alarm> {
        let Some(e) = waiting else {
            self.pending = None;
            return Ok(false);
        };
        let (seq, t0, _) = match self.pending {
            Some(p) => p,
            None => {
                let before = self.slot.load();
                // The hole's own data from motion; the pull-out override from the hole as
                // learnt at push (its return stroke's speed), where that is the same hole.
                let h = (self.cursor < self.pushed).then(|| self.holes[(self.cursor % HOLES as u64) as usize]);
                let ovr = h.filter(|h| h.line == e.line && h.axis == e.axis && h.lead == e.lead).map_or(100.0, |h| h.ovr);
                let st = TapState {
                    in_hole: true,
                    axis: AXIS_CHARS[e.axis.min(2)],
                    r_plane: e.r,
                    direction_in: e.dir,
                    lead: e.lead,
                    rpm: e.rpm,
                    override_pct: ovr,
                    position: e.r,
                    spindle_deg: e.spindle_deg,
                    line: e.line,
                };
                let seq = self.slot.store(&Some(st));
                if let Some(w) = &self.wake {
                    w.unpark();
                }
                let p = (seq, Instant::now(), before);
                self.pending = Some(p);
                p
            }
        };
        let waited = t0.elapsed();
        if self.slot.acked() >= seq {
            self.max_wait = self.max_wait.max(waited);
            return Ok(true);
        }
        if waited < self.ack_timeout {
            return Ok(false);
        }
        // The tool stays at R: withdraw the entry (a late write then says "not in a hole").
        if let Some((_, _, before)) = self.pending.take() {
            self.slot.store(&before);
            if let Some(w) = &self.wake {
                w.unpark();
            }
        }
        Err(Alarm::new(
            TAP_ACK_TIMEOUT,
            format!(
                "rigid tap of line {}: the tap-state file was not written within {} ms, so the tap did not start (the tool is at R, {} {:.3}); the disk of the state directory is too slow or failing: check it (free space, errors in the system log) or move --state-dir to a working disk, then start the program again",
                e.line,
                self.ack_timeout.as_millis(),
                AXIS_CHARS[e.axis.min(2)],
                e.r
            ),
        ))
    }

    fn push_hole(&mut self, h: Hole) {
        self.holes[(self.pushed % HOLES as u64) as usize] = h;
        self.pushed += 1;
        // Never reached: motion holds fewer items than the ring.
        if self.pushed - self.cursor > HOLES as u64 {
            self.cursor = self.pushed - HOLES as u64;
            self.inside = false;
        }
    }

    fn last_hole(&mut self) -> Option<&mut Hole> {
        (self.pushed > self.cursor).then(|| &mut self.holes[((self.pushed - 1) % HOLES as u64) as usize])
    }

    /// A move was accepted by motion (call in push order).
    pub fn on_push(&mut self, m: &Move) {
        let Some(end) = m.kind.end() else { return };
        let e = [end.x, end.y, end.z];
        if let MoveKind::Tap { lead, rpm, .. } = m.kind {
            if let Some(a) = (0..3).find(|&i| e[i] != self.last_end[i]) {
                let d = (e[a] - self.last_end[a]).signum();
                let line = m.src.line;
                let is_return = m.tag.as_ref().is_some_and(|t| &*t.cycle == "G30 P99");
                let seed = self.seed.filter(|s| s.in_hole);
                match self.last_hole() {
                    // The return of a hole of this program (K198 left it open).
                    Some(h) if h.open && h.axis == a && (is_return || (h.line == line && h.lead == lead)) => {
                        if d == -h.dir {
                            h.ovr = rpm / h.rpm * 100.0;
                        }
                        if (e[a] - h.r) * h.dir <= 1e-9 {
                            h.open = false;
                        }
                    }
                    _ if is_return => {
                        // The return from an interrupted tap: the hole is the stored one.
                        let (r, rpm_in, ovr) = seed.map_or((e[a], rpm, 100.0), |s| (s.r_plane, s.rpm, s.override_pct));
                        self.push_hole(Hole { line, axis: a, r, dir: -d, lead, rpm: rpm_in, ovr, open: false });
                    }
                    _ => self.push_hole(Hole { line, axis: a, r: self.last_end[a], dir: d, lead, rpm, ovr: 100.0, open: true }),
                }
            }
        }
        self.last_end = e;
    }

    fn depth(h: &Hole, p: f64) -> f64 {
        (p - h.r) * h.dir
    }

    /// Every cycle, after the set-point: `line` and `cmd` of the set-point, `act` the actual
    /// positions (motion axes). No allocation, no blocking.
    pub fn on_cycle(&mut self, line: u32, cmd: &[f64; N_AXES], act: &[f64; N_AXES]) {
        if self.cursor >= self.pushed {
            return;
        }
        let h = self.holes[(self.cursor % HOLES as u64) as usize];
        let commanded_in = Self::depth(&h, cmd[h.axis]) > 1e-6;
        let inside = commanded_in || Self::depth(&h, act[h.axis]) > IN_HOLE_MM;
        let entered = !self.inside;
        if entered {
            // Only the command leaving R enters the hole: an actual position still settling
            // from the rapid to R (past it by a few µm) is not a tap.
            if !(commanded_in && line == h.line) {
                return;
            }
            self.inside = true;
        }
        let st = TapState {
            in_hole: inside,
            axis: AXIS_CHARS[h.axis],
            r_plane: h.r,
            direction_in: h.dir,
            lead: h.lead,
            rpm: h.rpm,
            override_pct: h.ovr,
            position: act[h.axis],
            spindle_deg: act[AX_S],
            line: h.line,
        };
        self.slot.store(&Some(st));
        if !inside {
            // Back at R: this excursion is done.
            self.inside = false;
            self.cursor += 1;
        }
        // Entry and exit are written at once (the writer otherwise wakes every period).
        if entered || !inside {
            if let Some(w) = &self.wake {
                w.unpark();
            }
        }
    }
}

/// The writer thread: see the module doc.
pub struct TapPersister {
    stop: Arc<AtomicBool>,
    handle: std::thread::JoinHandle<PersistStats>,
}

/// What the writer did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PersistStats {
    pub writes: u64,
    pub failures: u64,
    /// The last failure, to report.
    pub last_error: Option<String>,
    /// Times the writer went to sleep (its wake-ups, but the last).
    pub wakeups: u64,
}

impl TapPersister {
    /// Start the writer of `file` from `slot`: at least every `period` while the state
    /// changes, at once when woken (`thread().unpark()`). `written`: the state already on
    /// disk (nothing is rewritten until it changes).
    pub fn spawn(file: TapStateFile, slot: Arc<TapSlot>, period: Duration, written: Option<TapState>) -> std::io::Result<TapPersister> {
        let stop = Arc::new(AtomicBool::new(false));
        let s2 = stop.clone();
        let handle = std::thread::Builder::new().name("tapstate".into()).spawn(move || {
            let mut stats = PersistStats::default();
            let mut last = written;
            let mut last_t = Instant::now();
            loop {
                let stopping = s2.load(Ordering::Acquire);
                let (seq, now) = slot.load_seq();
                // Entry and exit at once; progress in the hole at most every period.
                let due = match (now, last) {
                    (Some(n), Some(l)) => n != l && (n.in_hole != l.in_hole || last_t.elapsed() >= period || stopping),
                    (Some(_), None) => true,
                    (None, _) => false,
                };
                if !due && (now.is_none() || now == last) {
                    // Already on disk (or nothing to keep).
                    slot.acknowledge(seq);
                }
                if due {
                    if let Some(n) = now {
                        match file.save(&n) {
                            Ok(()) => {
                                stats.writes += 1;
                                last = Some(n);
                                last_t = Instant::now();
                                slot.acknowledge(seq);
                            }
                            Err(a) => {
                                if stats.failures == 0 {
                                    eprintln!("{a}");
                                }
                                stats.failures += 1;
                                stats.last_error = Some(a.to_string());
                            }
                        }
                    }
                }
                if stopping {
                    return stats;
                }
                stats.wakeups += 1;
                // Asleep until there is work: progress in a hole at most every period; out
                // of a hole the cycle wakes it at the entry (and `finish` at the end).
                // In a hole the cycle publishes progress without waking it: look every period.
                if now.is_some_and(|n| n.in_hole) {
                    std::thread::park_timeout(period.saturating_sub(last_t.elapsed()).max(Duration::from_micros(500)));
                } else {
                    std::thread::park();
                }
            }
        })?;
        Ok(TapPersister { stop, handle })
    }

    /// The writer's thread handle, to wake it (`unpark`).
    pub fn thread(&self) -> std::thread::Thread {
        self.handle.thread().clone()
    }

    /// Write the last state if it changed, and stop.
    pub fn finish(self) -> PersistStats {
        self.stop.store(true, Ordering::Release);
        self.handle.thread().unpark();
        self.handle.join().unwrap_or_else(|_| PersistStats {
            failures: 1,
            last_error: Some("the tap-state writer panicked".into()),
            ..Default::default()
        })
    }
}

/// With the tool in a tapped hole (`st.in_hole`), the program must bring it out first: its
/// first motion must be the `G30 P99` return (spindle stop, M codes and dwells may come
/// before it). `moves`: the program's moves from an interpreter given the state
/// (`set_tap_return`) and the stored position.
pub fn check_return_first(st: &TapState, moves: impl Iterator<Item = Result<Move, Alarm>>) -> Result<(), Alarm> {
    let refuse = |what: String| {
        Alarm::new(
            TAP_IN_HOLE,
            format!(
                "the tool is in a tapped hole (rigid tap of line {} interrupted at {} {:.3} mm, R plane {:.3}): {what}; run a program that starts with `G30 P99 S…` to bring it out along the thread",
                st.line, st.axis, st.position, st.r_plane
            ),
        )
    };
    for m in moves.take(10_000) {
        let m = match m {
            Ok(m) => m,
            Err(a) => return Err(refuse(format!("the program stops at an alarm before its G30 P99 ({a})"))),
        };
        match &m.kind {
            MoveKind::Tap { .. } if m.tag.as_ref().is_some_and(|t| &*t.cycle == "G30 P99") => return Ok(()),
            MoveKind::Aux { .. } | MoveKind::Dwell { .. } | MoveKind::Stop { .. } => {}
            MoveKind::Spindle(c) if c.dir == crate::canon::SpindleDir::Stop => {}
            k => {
                return Err(refuse(format!("line {} would move first ({}); a program other than G30 P99 must not start", m.src.line, k.name()))
                    .at(m.src.clone()))
            }
        }
    }
    Err(refuse("the program has no G30 P99".into()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canon::{CycleTag, Pos, SrcPos};

    fn tap(line: u32, z: f64, lead: f64, rpm: f64, cycle: &str) -> Move {
        Move {
            src: SrcPos::new("t.nc".into(), line, 1),
            kind: MoveKind::Tap { end: Pos::xz(0.0, z), lead, rpm, spindle: 1 },
            exact_stop: true,
            work_offset: Pos::ZERO,
            tag: Some(CycleTag { cycle: cycle.into(), step: 3 }),
        }
    }

    fn at(z: f64, s: f64) -> [f64; N_AXES] {
        [0.0, 0.0, z, s]
    }

    #[test]
    fn slot_round_trip() {
        let st = TapState {
            in_hole: true,
            axis: 'X',
            r_plane: 12.5,
            direction_in: -1.0,
            lead: 1.25,
            rpm: 800.0,
            override_pct: 150.0,
            position: 10.0,
            spindle_deg: -720.5,
            line: 77,
        };
        let s = TapSlot::new(None);
        assert_eq!(s.load(), None);
        s.store(&Some(st));
        assert_eq!(s.load(), Some(st));
        s.store(&Some(TapState { in_hole: false, direction_in: 1.0, ..st }));
        assert_eq!(s.load(), Some(TapState { in_hole: false, direction_in: 1.0, ..st }));
    }

    #[test]
    fn a_hole_is_in_from_the_entry_until_back_at_r() {
        let slot = TapSlot::new(None);
        let mut w = TapWatch::new(slot.clone(), None, &at(2.0, 0.0), None);
        // G84 Z-20 R… from Z2: in at S500, out at S600 (override 120 %), then a second hole.
        w.on_push(&tap(5, -20.0, -1.5, 500.0, "G84"));
        w.on_push(&tap(5, 2.0, -1.5, 600.0, "G84"));
        w.on_push(&tap(6, -10.0, -1.5, 500.0, "G84"));
        w.on_push(&tap(6, 2.0, -1.5, 500.0, "G84"));
        // At R: not in a hole, nothing published.
        w.on_cycle(5, &at(2.0, 0.0), &at(2.0, 0.0));
        assert_eq!(slot.load(), None);
        // Entry (the command is past R before the drive is).
        w.on_cycle(5, &at(1.999, 0.24), &at(2.0, 0.0));
        let s = slot.load().unwrap();
        assert!(s.in_hole && s.axis == 'Z' && s.r_plane == 2.0 && s.direction_in == -1.0, "{s:?}");
        assert_eq!((s.lead, s.rpm, s.override_pct), (-1.5, 500.0, 120.0));
        w.on_cycle(5, &at(-7.0, 2160.0), &at(-6.99, 2157.6));
        let s = slot.load().unwrap();
        assert!(s.in_hole && s.position == -6.99 && s.spindle_deg == 2157.6, "{s:?}");
        // The command is back at R, the drive 10 µm short: still in.
        w.on_cycle(5, &at(2.0, 0.0), &at(1.99, -2.4));
        assert!(slot.load().unwrap().in_hole);
        w.on_cycle(5, &at(2.0, 0.0), &at(2.0, 0.0));
        assert!(!slot.load().unwrap().in_hole);
        // The second hole (its override 100 %).
        w.on_cycle(6, &at(1.5, 120.0), &at(1.6, 96.0));
        let s = slot.load().unwrap();
        assert!(s.in_hole && s.line == 6 && s.override_pct == 100.0, "{s:?}");
    }

    #[test]
    fn g30_p99_returns_along_the_stored_hole_and_clears_it() {
        let seed = TapState {
            in_hole: true,
            axis: 'Z',
            r_plane: 2.0,
            direction_in: -1.0,
            lead: -1.5,
            rpm: 500.0,
            override_pct: 120.0,
            position: -8.0,
            spindle_deg: 2400.0,
            line: 5,
        };
        let slot = TapSlot::new(Some(seed));
        let mut w = TapWatch::new(slot.clone(), None, &at(-8.01, 2399.0), Some(seed));
        w.on_push(&tap(2, 2.0, -1.5, 720.0, "G30 P99"));
        // Before the return moves the stored state stays as it is.
        w.on_cycle(0, &at(-8.01, 2399.0), &at(-8.01, 2399.0));
        assert_eq!(slot.load(), Some(seed));
        w.on_cycle(2, &at(-8.0, 2398.0), &at(-8.01, 2399.0));
        let s = slot.load().unwrap();
        assert!(s.in_hole && s.r_plane == 2.0 && s.rpm == 500.0 && s.override_pct == 120.0, "{s:?}");
        w.on_cycle(2, &at(2.0, 0.0), &at(2.0, 0.0));
        assert!(!slot.load().unwrap().in_hole);
    }

    /// Motion and the watch, stepped as the cycle loop does (ideal drives: the actual is the
    /// last set-point); `ack_at`: the cycle at which a simulated writer acknowledges what is
    /// published. Returns the set-points and the cycle of the gate's answer `Err`, if any.
    type Gated = (Vec<crate::motion::Setpoint>, Vec<Option<TapState>>, Option<(usize, Alarm)>);

    fn gated_hole(ack_at: Option<usize>, timeout: Duration) -> Gated {
        use crate::motion::{Feedback, Limits, Motion};
        let mut l = Limits::from_config(&crate::config::MachineConfig::embedded());
        l.feedback_delay = 1;
        let start = at(2.0, 0.0);
        let mut m = Motion::new(l, start);
        m.gate_taps();
        let slot = TapSlot::new(None);
        let mut w = TapWatch::new(slot.clone(), None, &start, None);
        w.set_ack_timeout(timeout);
        for t in [tap(5, -20.0, -1.5, 500.0, "G84"), tap(5, 2.0, -1.5, 500.0, "G84")] {
            m.push(&t).unwrap();
            w.on_push(&t);
        }
        let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
        let (mut sps, mut disk) = (Vec::new(), Vec::new());
        for k in 0..20_000 {
            if m.is_idle() {
                break;
            }
            let sp = m.step(&fb);
            fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
            w.on_cycle(sp.line, &sp.pos, &fb.pos);
            if ack_at.is_some_and(|c| k >= c) {
                // The simulated writer: everything published so far is on disk.
                let (seq, st) = slot.load_seq();
                slot.acknowledge(seq);
                disk.push(st);
            } else {
                disk.push(disk.last().copied().flatten());
                // A writer that never answers: let the wall-clock timeout run.
                std::thread::sleep(Duration::from_micros(100));
            }
            sps.push(sp);
            match w.gate(m.tap_waiting()) {
                Ok(open) => m.open_tap_gate(open),
                Err(a) => return (sps, disk, Some((k, a))),
            }
        }
        (sps, disk, None)
    }

    #[test]
    fn a_hole_waits_at_r_until_its_entry_is_on_disk() {
        let (free, _, _) = gated_hole(Some(0), Duration::from_secs(60));
        let (slow, disk, err) = gated_hole(Some(400), Duration::from_secs(60));
        assert!(err.is_none());
        let leaves = |sps: &[crate::motion::Setpoint]| sps.iter().position(|s| s.pos[2] < 2.0).unwrap();
        let (k_free, k_slow) = (leaves(&free), leaves(&slow));
        eprintln!("the first stroke leaves R at cycle {k_free} with an immediate acknowledgement, {k_slow} with one at cycle 400");
        // It waited for the acknowledgement (not before), and no longer than a cycle or two.
        assert!(k_free < 400 && (401..=403).contains(&k_slow), "{k_free} {k_slow}");
        // At R meanwhile, spindle at rest and in position.
        let th = slow[k_slow - 1].pos[3];
        for s in &slow[k_free..k_slow] {
            assert!(s.pos[2] == 2.0 && s.pos[3] == th && s.spindle_rpm == 0.0, "{s:?}");
        }
        // Whenever the tool is past R the disk says "in the hole", with the hole and the
        // spindle angle at R (the thread's reference).
        for (s, d) in slow.iter().zip(&disk) {
            if s.pos[2] < 2.0 {
                let d = d.unwrap_or_else(|| panic!("nothing on disk at z {}", s.pos[2]));
                assert!(d.in_hole && d.r_plane == 2.0 && d.lead == -1.5 && d.axis == 'Z' && d.direction_in == -1.0, "{d:?}");
            }
        }
        let entry = disk[k_slow - 1].unwrap();
        assert!(entry.position == 2.0 && entry.spindle_deg == th, "{entry:?}");
        // The tap itself is the same as without the wait.
        assert_eq!(free.len() + (k_slow - k_free), slow.len());
        assert!(slow.last().unwrap().pos[2] == 2.0 && !disk.last().unwrap().unwrap().in_hole);
    }

    #[test]
    fn no_acknowledgement_alarms_and_the_tool_stays_at_r() {
        let (sps, disk, err) = gated_hole(None, Duration::from_millis(30));
        let (k, a) = err.expect("an alarm");
        assert_eq!(a.number, TAP_ACK_TIMEOUT, "{a}");
        assert!(a.message.contains("disk") && a.message.contains("--state-dir") && a.message.contains("line 5"), "{a}");
        assert!(sps.iter().all(|s| s.pos[2] == 2.0), "the tool never left R");
        assert!(disk.iter().all(|d| d.is_none()));
        eprintln!("alarm after {k} cycles: {a}");
    }

    #[test]
    fn only_a_g30_p99_program_may_start_in_a_hole() {
        let cfg = crate::config::MachineConfig::embedded();
        let st = TapState {
            in_hole: true,
            axis: 'Z',
            r_plane: 2.0,
            direction_in: -1.0,
            lead: -1.5,
            rpm: 500.0,
            override_pct: 100.0,
            position: -8.0,
            spindle_deg: 0.0,
            line: 5,
        };
        let run = |text: &str| {
            let mut it = crate::interp::Interpreter::from_source("p.nc", text, &cfg).unwrap();
            it.set_tap_return(Some(st.tap_return()));
            it.set_start_position(Pos::xz(0.0, -8.0));
            check_return_first(&st, it)
        };
        assert!(run("O1\nM05\nG30 P99 S500\nG00 Z50\nM30\n").is_ok());
        let a = run("O1\nG00 X20 Z50\nM30\n").unwrap_err();
        assert_eq!(a.number, TAP_IN_HOLE, "{a}");
        assert!(a.message.contains("G30 P99") && a.message.contains("line 2 would move first"), "{a}");
        assert_eq!(run("O1\nM03 S500\nG30 P99\nM30\n").unwrap_err().number, TAP_IN_HOLE, "the spindle must not start");
        assert_eq!(run("O1\nM30\n").unwrap_err().number, TAP_IN_HOLE);
    }
}
