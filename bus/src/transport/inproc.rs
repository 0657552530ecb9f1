//! The in-process bus: any number of endpoints; every frame one endpoint sends is seen by
//! every other endpoint, in send order, as on a real CAN bus. Used with a simulated clock the
//! bus has no latency of its own: the simulated world decides when frames are processed.
//!
//! Fault injection (`WireFaults`: frames dropped, delayed or corrupted at random from a
//! seeded generator, so a run is reproducible; bus-off on command) lives here because it
//! is a property of the wire, not of a node. Delays need the bus's time: the simulated
//! world sets it (`set_time_ns`); otherwise it is the wall clock since the bus was made.

use super::{BusError, CanBus};
use crate::frame::CanFrame;
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Frames an endpoint can hold before it overflows (a CAN controller's FIFO, generously).
const QUEUE_CAP: usize = 4096;

/// Random faults of the wire. Each frame (whose COB-ID is in `ids`, if given) is lost with
/// probability `drop`, else delayed by `delay_ns` with probability `delay`, and arrives with
/// one data bit flipped with probability `corrupt` (what a broken gateway or a CRC that
/// failed to catch an error delivers; CANopen itself cannot tell, except the CRC of SDO
/// block transfers). Draws come from a xorshift generator seeded with `seed`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WireFaults {
    pub seed: u64,
    pub ids: Option<(u16, u16)>,
    pub drop: f64,
    pub delay: f64,
    pub delay_ns: u64,
    pub corrupt: f64,
}

/// Frames affected so far by `WireFaults`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultCounts {
    pub dropped: u64,
    pub delayed: u64,
    pub corrupted: u64,
}

struct Faults {
    cfg: WireFaults,
    rng: u64,
    counts: FaultCounts,
}

impl Faults {
    /// Uniform in [0, 1).
    fn draw(&mut self) -> f64 {
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.rng = x;
        (x >> 11) as f64 / (1u64 << 53) as f64
    }
}

struct Queue {
    /// (due time, frame), ordered by due time.
    frames: VecDeque<(u64, CanFrame)>,
    dropped: u64,
}

impl Queue {
    fn push(&mut self, due: u64, f: CanFrame) {
        // A frame sent later but due earlier (a delayed one is in the way) goes before it.
        let mut at = self.frames.len();
        while at > 0 && self.frames[at - 1].0 > due {
            at -= 1;
        }
        self.frames.insert(at, (due, f));
    }

    fn pop(&mut self, now: u64) -> Option<CanFrame> {
        if self.frames.front().is_some_and(|(due, _)| *due <= now) {
            self.frames.pop_front().map(|(_, f)| f)
        } else {
            None
        }
    }
}

struct Shared {
    queues: Vec<Queue>,
    bus_off: bool,
    /// Frames sent over the bus in total (for bus statistics).
    sent: u64,
    faults: Option<Faults>,
    /// Bus time set by a simulated world; None = wall clock since `epoch`.
    time_ns: Option<u64>,
    epoch: Instant,
}

impl Shared {
    fn now(&self) -> u64 {
        self.time_ns.unwrap_or_else(|| self.epoch.elapsed().as_nanos() as u64)
    }
}

/// The wire. Clone it to make more endpoints.
#[derive(Clone)]
pub struct InprocBus {
    inner: Arc<(Mutex<Shared>, Condvar)>,
}

impl Default for InprocBus {
    fn default() -> Self {
        Self::new()
    }
}

impl InprocBus {
    pub fn new() -> Self {
        InprocBus {
            inner: Arc::new((
                Mutex::new(Shared { queues: Vec::new(), bus_off: false, sent: 0, faults: None, time_ns: None, epoch: Instant::now() }),
                Condvar::new(),
            )),
        }
    }

    /// A new node on the bus. It sees frames sent from now on.
    pub fn endpoint(&self) -> InprocEndpoint {
        let mut s = self.inner.0.lock().unwrap_or_else(|e| e.into_inner());
        s.queues.push(Queue { frames: VecDeque::with_capacity(QUEUE_CAP), dropped: 0 });
        InprocEndpoint { bus: self.clone(), idx: s.queues.len() - 1 }
    }

    /// Put the bus into (or out of) bus-off: sends fail with `BusError::BusOff`.
    pub fn set_bus_off(&self, off: bool) {
        self.inner.0.lock().unwrap_or_else(|e| e.into_inner()).bus_off = off;
    }

    /// Frames sent so far.
    pub fn frames_sent(&self) -> u64 {
        self.inner.0.lock().unwrap_or_else(|e| e.into_inner()).sent
    }

    /// Start (Some) or stop (None) random wire faults; the generator restarts from the seed.
    pub fn set_faults(&self, faults: Option<WireFaults>) {
        let mut s = self.inner.0.lock().unwrap_or_else(|e| e.into_inner());
        s.faults = faults.map(|cfg| Faults { rng: cfg.seed.max(1), cfg, counts: FaultCounts::default() });
    }

    /// Frames dropped, delayed and corrupted since `set_faults`.
    pub fn fault_counts(&self) -> FaultCounts {
        self.inner.0.lock().unwrap_or_else(|e| e.into_inner()).faults.as_ref().map(|f| f.counts).unwrap_or_default()
    }

    /// Set the bus time (simulated worlds call this as they advance; it never goes back).
    pub fn set_time_ns(&self, t: u64) {
        let mut s = self.inner.0.lock().unwrap_or_else(|e| e.into_inner());
        s.time_ns = Some(s.time_ns.map_or(t, |old| old.max(t)));
        drop(s);
        self.inner.1.notify_all();
    }
}

pub struct InprocEndpoint {
    bus: InprocBus,
    idx: usize,
}

impl CanBus for InprocEndpoint {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let (m, cv) = &*self.bus.inner;
        let mut s = m.lock().unwrap_or_else(|e| e.into_inner());
        if s.bus_off {
            return Err(BusError::BusOff { bus: "inproc".into() });
        }
        s.sent += 1;
        let mut frame = *frame;
        // Due at once (0) unless delayed: then by the bus time, which only delays need.
        let mut due = 0;
        let s_now = s.now();
        if let Some(fl) = s.faults.as_mut() {
            let id = frame.cob_id();
            if fl.cfg.ids.is_none_or(|(lo, hi)| (lo..=hi).contains(&id)) {
                if fl.draw() < fl.cfg.drop {
                    fl.counts.dropped += 1;
                    return Ok(()); // lost on the wire: the sender cannot tell
                }
                if fl.draw() < fl.cfg.delay {
                    fl.counts.delayed += 1;
                    due = s_now + fl.cfg.delay_ns;
                }
                if frame.len > 0 && fl.draw() < fl.cfg.corrupt {
                    fl.counts.corrupted += 1;
                    let bit = (fl.draw() * (frame.len as f64 * 8.0)) as usize;
                    frame.data[bit / 8] ^= 1 << (bit % 8);
                }
            }
        }
        for (i, q) in s.queues.iter_mut().enumerate() {
            if i == self.idx {
                continue;
            }
            if q.frames.len() >= QUEUE_CAP {
                q.dropped += 1;
            } else {
                q.push(due, frame);
            }
        }
        cv.notify_all();
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let mut s = self.bus.inner.0.lock().unwrap_or_else(|e| e.into_inner());
        let now = s.now();
        let q = &mut s.queues[self.idx];
        if q.dropped > 0 {
            let dropped = std::mem::take(&mut q.dropped);
            return Err(BusError::Overflow { bus: "inproc".into(), dropped });
        }
        Ok(q.pop(now))
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        let deadline = Instant::now() + timeout;
        let (m, cv) = &*self.bus.inner;
        let mut s = m.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            let bus_now = s.now();
            if let Some(f) = s.queues[self.idx].pop(bus_now) {
                return Ok(Some(f));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            // A delayed frame falls due without a notification: look again by then.
            let mut wait = deadline - now;
            if let (Some((due, _)), None) = (s.queues[self.idx].frames.front(), s.time_ns) {
                wait = wait.min(Duration::from_nanos(due.saturating_sub(bus_now).max(50_000)));
            }
            s = cv.wait_timeout(s, wait).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    fn name(&self) -> &str {
        "inproc"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_other_endpoint_sees_each_frame_in_order() {
        let bus = InprocBus::new();
        let mut a = bus.endpoint();
        let mut b = bus.endpoint();
        let mut c = bus.endpoint();
        a.send(&CanFrame::new(0x80, &[])).unwrap();
        a.send(&CanFrame::new(0x201, &[1, 2])).unwrap();
        for ep in [&mut b, &mut c] {
            assert_eq!(ep.try_recv().unwrap().unwrap().cob_id(), 0x80);
            assert_eq!(ep.try_recv().unwrap().unwrap().data(), &[1, 2]);
            assert_eq!(ep.try_recv().unwrap(), None);
        }
        assert_eq!(a.try_recv().unwrap(), None, "a sender does not see its own frames");
    }

    #[test]
    fn bus_off_fails_sends() {
        let bus = InprocBus::new();
        let mut a = bus.endpoint();
        bus.set_bus_off(true);
        assert!(matches!(a.send(&CanFrame::new(1, &[])), Err(BusError::BusOff { .. })));
        bus.set_bus_off(false);
        assert!(a.send(&CanFrame::new(1, &[])).is_ok());
    }

    fn faults(drop: f64, delay: f64, corrupt: f64, seed: u64) -> WireFaults {
        WireFaults { seed, ids: Some((0x181, 0x181)), drop, delay, delay_ns: 5_000_000, corrupt }
    }

    /// What endpoint b receives of 1000 frames 0x181 and 1000 frames 0x182 (unaffected).
    fn run(f: WireFaults) -> (Vec<CanFrame>, FaultCounts) {
        let bus = InprocBus::new();
        let mut a = bus.endpoint();
        let mut b = bus.endpoint();
        bus.set_faults(Some(f));
        bus.set_time_ns(0);
        let mut got = Vec::new();
        for k in 0..1000u16 {
            bus.set_time_ns(k as u64 * 1_000_000);
            a.send(&CanFrame::new(0x181, &[0; 8])).unwrap();
            a.send(&CanFrame::new(0x182, &k.to_le_bytes())).unwrap();
            while let Some(f) = b.try_recv().unwrap() {
                got.push(f);
            }
        }
        bus.set_time_ns(u64::MAX / 2);
        while let Some(f) = b.try_recv().unwrap() {
            got.push(f);
        }
        (got, bus.fault_counts())
    }

    #[test]
    fn random_faults_are_reproducible_and_only_hit_the_chosen_ids() {
        let (got, c) = run(faults(0.1, 0.1, 0.1, 42));
        assert_eq!(run(faults(0.1, 0.1, 0.1, 42)), (got.clone(), c), "same seed, same faults");
        assert_ne!(run(faults(0.1, 0.1, 0.1, 43)).0, got, "another seed, other faults");
        assert_eq!(got.iter().filter(|f| f.cob_id() == 0x182).count(), 1000);
        let n181 = got.iter().filter(|f| f.cob_id() == 0x181).count() as u64;
        assert_eq!(n181 + c.dropped, 1000);
        for (n, p) in [(c.dropped, 100.0), (c.delayed, 90.0), (c.corrupted, 90.0)] {
            assert!((n as f64 - p).abs() < 35.0, "{c:?}");
        }
        // 0x181 frames are sent all-zero: a corrupted one has exactly one bit set.
        let ones: Vec<u32> = got.iter().filter(|f| f.cob_id() == 0x181).map(|f| f.data().iter().map(|b| b.count_ones()).sum()).collect();
        assert!(ones.iter().all(|&n| n <= 1));
        assert_eq!(ones.iter().filter(|&&n| n == 1).count() as u64, c.corrupted);
    }

    #[test]
    fn delayed_frames_arrive_late_and_are_overtaken() {
        let bus = InprocBus::new();
        let mut a = bus.endpoint();
        let mut b = bus.endpoint();
        bus.set_time_ns(1_000);
        bus.set_faults(Some(WireFaults { seed: 7, ids: Some((0x181, 0x181)), delay: 1.0, delay_ns: 3_000_000, ..WireFaults::default() }));
        a.send(&CanFrame::new(0x181, &[1])).unwrap();
        a.send(&CanFrame::new(0x182, &[2])).unwrap();
        assert_eq!(b.try_recv().unwrap().map(|f| f.cob_id()), Some(0x182), "the undelayed frame overtakes");
        assert_eq!(b.try_recv().unwrap(), None, "the delayed one is not due yet");
        bus.set_time_ns(3_000_999);
        assert_eq!(b.try_recv().unwrap(), None);
        bus.set_time_ns(3_001_000);
        assert_eq!(b.try_recv().unwrap().map(|f| f.cob_id()), Some(0x181));
        // Time never goes back.
        bus.set_time_ns(5);
        a.send(&CanFrame::new(0x182, &[3])).unwrap();
        assert_eq!(b.try_recv().unwrap().map(|f| f.cob_id()), Some(0x182));
    }

    #[test]
    fn overflow_is_reported_not_silent() {
        let bus = InprocBus::new();
        let mut a = bus.endpoint();
        let mut b = bus.endpoint();
        for _ in 0..QUEUE_CAP + 3 {
            a.send(&CanFrame::new(1, &[])).unwrap();
        }
        assert_eq!(b.try_recv(), Err(BusError::Overflow { bus: "inproc".into(), dropped: 3 }));
    }
}
