//! An external SYNC as the cycle's time base (`bus.sync = "external"`): another device (a
//! drive with 0x1005 bit 30, a separate SYNC producer) produces SYNC and the master's cycle
//! runs on it instead of on its own timer.
//!
//! [`external_sync`] splits a bus and a clock into a [`SyncBus`] (what the master reads and
//! writes: every frame, SYNCs included, in order) and a [`SyncClock`] whose time is locked to
//! the SYNCs received: while SYNC comes, the clock's time advances by one period per SYNC
//! (drift-free against the producer's crystal), and a wait for the next period's slot returns
//! when its SYNC arrives. So every `wait_until` of the cycle loop — start-up, the program, the
//! controlled stops — wakes on the SYNC without knowing it. Waits inside a period (SDO polls)
//! are plain timer waits. A SYNC overdue by half a period unlocks the clock: it runs free on
//! the timer (the master raises its alarm on the missing SYNC, see `bus.sync_loss_cycles`),
//! and the next SYNC locks it again without a jump — unless that SYNC is one whose slot the
//! timer already served (it came late, or in a burst after the path it came by stalled): its
//! cycle has run and sent its set-points, so it moves nothing (see [`SyncTrack::on_sync`]).
//!
//! The time keeping is [`SyncTrack`], sans-I/O (times in, times out) and unit-tested.

use crate::canopen::cob;
use crate::{BusError, CanBus, CanFrame, Clock};
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Frames the clock may hold for the bus while it waits (a few cycles of a full bus).
const QUEUE: usize = 1024;

/// A SYNC whose slot the free-running clock passed at most this many periods ago is taken as
/// that slot's, late; one further behind is a SYNC that stopped and came back (start-up's NMT
/// reset reboots a producing drive): it locks the clock where it stands.
const SERVED_PERIODS: u64 = 8;

/// Whether `f` is a SYNC (COB-ID 0x080, no data or the 1-byte counter).
pub fn is_sync(f: &CanFrame) -> bool {
    !f.extended && !f.rtr && f.cob_id() == cob::SYNC && f.len <= 1
}

/// The clock's time (virtual) from the inner clock's (inner) and the SYNCs seen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SyncTrack {
    period: u64,
    /// Virtual and inner time of the last SYNC (or of the unlock).
    anchor_v: u64,
    anchor_inner: u64,
    /// SYNC comes: virtual time moves one period per SYNC.
    locked: bool,
    syncs: u64,
    unlocks: u64,
    /// Virtual time of the slot the last SYNC stood for, and its inner arrival time.
    sync_v: u64,
    sync_inner: u64,
    /// No SYNC since the clock unlocked.
    since_unlock: bool,
    /// SYNCs that came for slots the timer had already served.
    served_late: u64,
}

impl SyncTrack {
    pub fn new(period_ns: u64) -> Self {
        SyncTrack {
            period: period_ns.max(2),
            anchor_v: 0,
            anchor_inner: 0,
            locked: false,
            syncs: 0,
            unlocks: 0,
            sync_v: 0,
            sync_inner: 0,
            since_unlock: false,
            served_late: 0,
        }
    }

    /// Virtual time at inner time `inner`. Locked, it stops one ns short of the next slot:
    /// the slot is reached by its SYNC.
    pub fn now(&self, inner: u64) -> u64 {
        let e = inner.saturating_sub(self.anchor_inner);
        self.anchor_v + if self.locked { e.min(self.period - 1) } else { e }
    }

    /// A SYNC arrived at inner time `inner`, while a wait for `deadline` (virtual) may be
    /// pending. Locked, the SYNC is the next slot; unlocked, it locks the clock where it
    /// stands. A pending deadline from half a period before the SYNC's slot to a period after
    /// it becomes the slot: the waiter's grid and the SYNCs line up (the shift is never
    /// observed, it happens inside the wait). A deadline up to a period *after* the slot is
    /// this SYNC's too: were it left where it is, the cycle would wake on the timer that far
    /// after every SYNC from then on (its deadlines falling inside the period), not on the
    /// SYNC — and with its set-points sent late in the period, every bit of lateness would
    /// make a drive take them a SYNC late.
    ///
    /// Unlocked, a SYNC whose slot (one period after the last SYNC's) the clock has already
    /// passed on its timer, the first since the unlock or one of a burst (less than half a
    /// period after the one before), is that slot's, late: the cycle it stood for ran on the
    /// timer and sent its set-points, and the drives take them at this SYNC. It moves
    /// nothing. Counted as a new slot, it would run the next cycle at once — a second
    /// set-point before the drives' next SYNC, which they take instead: a double step (a
    /// burst of n such SYNCs: an n-fold one).
    pub fn on_sync(&mut self, inner: u64, deadline: Option<u64>) {
        if self.served(inner) {
            self.sync_v += self.period;
            self.sync_inner = inner;
            self.since_unlock = false;
            self.syncs += 1;
            self.served_late += 1;
            return;
        }
        let v = if self.locked { self.anchor_v + self.period } else { self.now(inner) };
        self.anchor_v = match deadline {
            Some(t) if t + self.period / 2 > v && t < v + self.period => t,
            _ => v,
        };
        self.anchor_inner = inner;
        self.locked = true;
        self.syncs += 1;
        self.sync_v = self.anchor_v;
        self.sync_inner = inner;
        self.since_unlock = false;
    }

    /// Whether a SYNC arriving at `inner` stands for a slot the unlocked clock has served.
    fn served(&self, inner: u64) -> bool {
        if self.locked || self.syncs == 0 {
            return false;
        }
        let slot = self.sync_v + self.period;
        let now = self.now(inner);
        let burst = inner.saturating_sub(self.sync_inner) < self.period / 2;
        slot <= now && now - slot < SERVED_PERIODS * self.period && (self.since_unlock || burst)
    }

    /// At inner time `inner` with no SYNC: unlock when it is half a period overdue. True when
    /// this call unlocked it.
    pub fn check(&mut self, inner: u64) -> bool {
        if self.locked && inner.saturating_sub(self.anchor_inner) >= self.period + self.period / 2 {
            self.anchor_v = self.now(inner);
            self.anchor_inner = inner;
            self.locked = false;
            self.unlocks += 1;
            self.since_unlock = true;
            return true;
        }
        false
    }

    /// Inner time at which virtual time reaches `t` without a SYNC, if it can.
    pub fn inner_at(&self, t: u64) -> Option<u64> {
        let d = t.saturating_sub(self.anchor_v);
        (!self.locked || d < self.period).then_some(self.anchor_inner + d)
    }

    /// Inner time by which the next SYNC is overdue (locked only).
    pub fn overdue_at(&self) -> Option<u64> {
        self.locked.then_some(self.anchor_inner + self.period + self.period / 2)
    }

    pub fn locked(&self) -> bool {
        self.locked
    }

    pub fn syncs(&self) -> u64 {
        self.syncs
    }

    /// How often SYNC went missing long enough to unlock the clock.
    pub fn unlocks(&self) -> u64 {
        self.unlocks
    }

    /// SYNCs that came for a slot the unlocked clock had already served (late, or in a burst).
    pub fn served_late(&self) -> u64 {
        self.served_late
    }
}

struct Shared {
    bus: Box<dyn CanBus>,
    queue: VecDeque<CanFrame>,
    dropped: u64,
    track: SyncTrack,
    /// Inner time last read by the clock: the arrival time of a SYNC the bus side reads.
    inner_hint: u64,
    deadline: Option<u64>,
    name: String,
}

impl Shared {
    fn push(&mut self, f: CanFrame, inner: u64) {
        if is_sync(&f) {
            self.track.on_sync(inner, self.deadline);
        }
        if self.queue.len() < QUEUE {
            self.queue.push_back(f);
        } else {
            self.dropped += 1;
        }
    }

    /// Everything waiting on the bus into the queue.
    fn pump(&mut self, inner: u64) -> Result<(), BusError> {
        while let Some(f) = self.bus.try_recv()? {
            self.push(f, inner);
        }
        Ok(())
    }

    fn overflow(&mut self) -> Result<(), BusError> {
        if self.dropped > 0 {
            let dropped = std::mem::take(&mut self.dropped);
            return Err(BusError::Overflow { bus: self.name.clone(), dropped });
        }
        Ok(())
    }
}

fn lock(s: &Mutex<Shared>) -> std::sync::MutexGuard<'_, Shared> {
    s.lock().unwrap_or_else(|e| e.into_inner())
}

/// The master's side of [`external_sync`]: frames in order, SYNCs included.
pub struct SyncBus {
    shared: Arc<Mutex<Shared>>,
    name: String,
    remote: bool,
}

/// The cycle's side of [`external_sync`]: time locked to the SYNCs received.
pub struct SyncClock<C: Clock> {
    inner: C,
    shared: Arc<Mutex<Shared>>,
    period: u64,
    simulated: bool,
}

/// Split `bus` and `clock` for a cycle of `period_ns` run on an external SYNC.
pub fn external_sync<C: Clock>(bus: Box<dyn CanBus>, clock: C, period_ns: u64) -> (SyncBus, SyncClock<C>) {
    let name = bus.name().to_string();
    let remote = bus.remote_frames();
    let shared = Arc::new(Mutex::new(Shared {
        bus,
        queue: VecDeque::with_capacity(QUEUE),
        dropped: 0,
        track: SyncTrack::new(period_ns),
        inner_hint: 0,
        deadline: None,
        name: name.clone(),
    }));
    let simulated = clock.is_simulated();
    (SyncBus { shared: shared.clone(), name, remote }, SyncClock { inner: clock, shared, period: period_ns.max(2), simulated })
}

impl CanBus for SyncBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        lock(&self.shared).bus.send(frame)
    }

    /// Only what the clock's waits took off the bus: a SYNC is timed where the clock saw it
    /// (read here, after the wait, it would be timed by the wait's start, a cycle early).
    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let mut s = lock(&self.shared);
        s.overflow()?;
        Ok(s.queue.pop_front())
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        if let Some(f) = self.try_recv()? {
            return Ok(Some(f));
        }
        // Not the cycle's path (it waits on the clock): a blocking read of the bus, timing a
        // SYNC by the clock's last reading.
        let mut s = lock(&self.shared);
        let f = s.bus.recv_timeout(timeout)?;
        if f.as_ref().is_some_and(is_sync) {
            let t = s.inner_hint;
            s.track.on_sync(t, None);
        }
        Ok(f)
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn remote_frames(&self) -> bool {
        self.remote
    }

    fn controller(&self) -> Option<crate::can_error::ControllerStatus> {
        lock(&self.shared).bus.controller()
    }
}

impl<C: Clock> SyncClock<C> {
    pub fn inner(&self) -> &C {
        &self.inner
    }

    pub fn inner_mut(&mut self) -> &mut C {
        &mut self.inner
    }

    /// The time keeping as it stands (SYNCs seen, locked, unlocks).
    pub fn track(&self) -> SyncTrack {
        lock(&self.shared).track
    }

    /// One step of a wait for `t` (virtual): pump the bus, then sleep/block until a frame
    /// can have arrived. True: `t` is reached.
    fn step(&mut self, t: u64) -> bool {
        let inner = self.inner.now_ns();
        let mut s = lock(&self.shared);
        s.inner_hint = inner;
        s.deadline = Some(t);
        // A failing bus is the master's to report (its next read fails too).
        let _ = s.pump(inner);
        s.track.check(inner);
        if s.track.now(inner) >= t {
            s.deadline = None;
            return true;
        }
        let until = match (s.track.inner_at(t), s.track.overdue_at()) {
            (Some(a), Some(b)) => a.min(b),
            (Some(a), None) => a,
            (None, Some(b)) => b,
            (None, None) => inner + self.period,
        };
        if self.simulated {
            drop(s);
            // Simulated time: advance the world in small steps so that a SYNC is seen
            // within 1/20 of a period of its arrival.
            self.inner.wait_until(until.min(inner + (self.period / 20).max(1_000)));
        } else {
            let wait = Duration::from_nanos(until.saturating_sub(inner).max(1_000));
            match s.bus.recv_timeout(wait) {
                Ok(Some(f)) => {
                    let now = self.inner.now_ns();
                    s.push(f, now);
                }
                Ok(None) => {}
                Err(_) => {
                    drop(s);
                    // The bus failed: keep time on the timer; the master reports the bus.
                    self.inner.wait_until(until);
                }
            }
        }
        false
    }
}

impl<C: Clock> Clock for SyncClock<C> {
    fn now_ns(&self) -> u64 {
        let inner = self.inner.now_ns();
        let mut s = lock(&self.shared);
        s.inner_hint = inner;
        s.track.now(inner)
    }

    fn wait_until(&mut self, t_ns: u64) {
        while !self.step(t_ns) {}
    }

    fn is_simulated(&self) -> bool {
        self.simulated
    }

    /// The SYNCs on the bus now, taken in without waiting (see [`Clock::poll_sync`]).
    fn poll_sync(&mut self) -> Option<u64> {
        let inner = self.inner.now_ns();
        let mut s = lock(&self.shared);
        s.inner_hint = inner;
        // A failing bus is the master's to report (its next read fails too).
        let _ = s.pump(inner);
        Some(s.track.now(inner))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: u64 = 2_000_000;

    #[test]
    fn locked_time_moves_one_period_per_sync_whatever_the_producers_crystal() {
        let mut t = SyncTrack::new(P);
        assert_eq!(t.now(123), 123, "free before the first SYNC");
        t.on_sync(1_000_000, None);
        assert!(t.locked());
        assert_eq!(t.now(1_000_000), 1_000_000);
        // A producer 1 % slow: each SYNC is still exactly one period later.
        let mut inner = 1_000_000;
        for k in 1..=100u64 {
            inner += P + P / 100;
            // Between SYNCs time stops one ns short of the next slot.
            assert_eq!(t.now(inner - 1), 1_000_000 + k * P - 1);
            assert!(!t.check(inner - 1));
            t.on_sync(inner, None);
            assert_eq!(t.now(inner), 1_000_000 + k * P);
        }
        assert_eq!(t.syncs(), 101);
        // Waits inside a period are timer waits; the next slot needs its SYNC.
        assert_eq!(t.inner_at(t.now(inner) + P / 2), Some(inner + P / 2));
        assert_eq!(t.inner_at(t.now(inner) + P), None);
    }

    #[test]
    fn a_pending_deadline_near_the_sync_becomes_its_slot() {
        let mut t = SyncTrack::new(P);
        t.on_sync(0, None);
        // The waiter's grid is 0.3 periods off: the SYNC lands on the waiter's deadline.
        t.on_sync(P, Some(P + 3 * P / 10));
        assert_eq!(t.now(P), P + 3 * P / 10);
        t.on_sync(2 * P, Some(2 * P + 3 * P / 10));
        assert_eq!(t.now(2 * P), 2 * P + 3 * P / 10);
        // A deadline far from the slot (a loop that overran) does not move it.
        t.on_sync(3 * P, Some(10 * P));
        assert_eq!(t.now(3 * P), 3 * P + 3 * P / 10);
    }

    #[test]
    fn a_deadline_late_in_the_period_after_the_slot_is_that_syncs_too() {
        // The cycle's first deadline fell 0.7 periods after a SYNC slot (start-up ended
        // there): the next SYNC takes it, and from then on the cycle wakes on every SYNC,
        // not on a timer 0.7 periods after it.
        let mut t = SyncTrack::new(P);
        t.on_sync(0, None);
        assert_eq!(t.inner_at(7 * P / 10), Some(7 * P / 10), "inside the period: a timer wait");
        t.on_sync(P, Some(P + 7 * P / 10));
        assert_eq!(t.now(P), P + 7 * P / 10);
        assert_eq!(t.inner_at(2 * P + 7 * P / 10), None, "the next deadline is the next SYNC's");
        t.on_sync(2 * P, Some(2 * P + 7 * P / 10));
        assert_eq!(t.now(2 * P), 2 * P + 7 * P / 10);
        // Half a period before the slot still snaps; a whole period after it does not.
        t.on_sync(3 * P, Some(3 * P + 7 * P / 10 - P / 2 + 1));
        assert_eq!(t.now(3 * P), 3 * P + 7 * P / 10 - P / 2 + 1);
        let v = t.now(4 * P - 1) + 1;
        t.on_sync(4 * P, Some(v + P));
        assert_eq!(t.now(4 * P), v);
    }

    #[test]
    fn a_missing_sync_unlocks_after_half_a_period_and_the_next_locks_without_a_jump() {
        let mut t = SyncTrack::new(P);
        t.on_sync(0, None);
        assert_eq!(t.overdue_at(), Some(P + P / 2));
        assert!(!t.check(P + P / 2 - 1));
        assert!(t.check(P + P / 2));
        assert!(!t.locked());
        assert_eq!(t.unlocks(), 1);
        let at_unlock = t.now(P + P / 2);
        assert_eq!(at_unlock, P - 1);
        // Free running on the timer from there.
        assert_eq!(t.now(10 * P), P - 1 + 10 * P - (P + P / 2));
        assert_eq!(t.inner_at(20 * P), Some(P + P / 2 + 20 * P - (P - 1)));
        let before = t.now(10 * P);
        t.on_sync(10 * P, None);
        assert!(t.locked());
        assert_eq!(t.now(10 * P), before, "no jump when SYNC comes back");
    }

    #[test]
    fn a_sync_later_than_half_a_period_is_the_slot_the_timer_served_not_the_next() {
        // SYNC k+1 reaches the master 0.6 periods late: the clock unlocked at 1.5 periods and
        // the cycle of slot P ran on the timer. That SYNC must not start the cycle of slot 2P
        // at once (two set-points before the drives' SYNC at 2P: a double step).
        let mut t = SyncTrack::new(P);
        t.on_sync(0, None);
        assert!(t.check(P + P / 2));
        assert!(t.now(P + P / 2 + 1) >= P, "the cycle of slot P ran on the timer");
        t.on_sync(P + 6 * P / 10, Some(2 * P));
        assert!(!t.locked());
        assert_eq!(t.served_late(), 1);
        assert!(t.now(P + 6 * P / 10) < 2 * P, "the next cycle waits");
        // SYNC k+2 on time: slot 2P, locked there.
        t.on_sync(2 * P, Some(2 * P));
        assert!(t.locked());
        assert_eq!(t.now(2 * P), 2 * P);
        assert_eq!(t.syncs(), 3);
    }

    #[test]
    fn a_burst_of_late_syncs_pays_for_the_slots_the_timer_served_and_locks_on_the_current_one() {
        // The path stalled for 4.2 periods, the clock ran free and its cycles served slots P..4P
        // on the timer: the burst's SYNCs k+1..k+4 are those slots'; k+5 is the one waited for.
        let mut t = SyncTrack::new(P);
        t.on_sync(0, None);
        assert!(t.check(P + P / 2));
        let at = 4 * P + P / 5 + P / 2;
        let before = t.now(at);
        assert!(before > 4 * P && before < 5 * P);
        for k in 0..4 {
            t.on_sync(at + k, Some(5 * P));
        }
        assert!(!t.locked(), "{t:?}");
        assert_eq!(t.now(at + 4), before + 4, "no slot counted twice");
        t.on_sync(at + 5, Some(5 * P));
        assert!(t.locked());
        assert_eq!(t.now(at + 5), 5 * P);
        assert_eq!((t.syncs(), t.served_late()), (6, 4));
    }

    #[test]
    fn sync_frames_are_recognised() {
        assert!(is_sync(&CanFrame::new(0x080, &[])));
        assert!(is_sync(&CanFrame::new(0x080, &[7])));
        assert!(!is_sync(&CanFrame::new(0x081, &[])), "EMCY of node 1");
        assert!(!is_sync(&CanFrame::new(0x080, &[1, 2])));
    }
}
