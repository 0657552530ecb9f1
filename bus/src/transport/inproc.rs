//! The in-process bus: any number of endpoints; every frame one endpoint sends is seen by
//! every other endpoint, in send order, as on a real CAN bus. Used with a simulated clock the
//! bus has no latency of its own: the simulated world decides when frames are processed.
//!
//! Fault injection (drop every n-th frame, bus-off on command) lives here because it is a
//! property of the wire, not of a node.

use super::{BusError, CanBus};
use crate::frame::CanFrame;
use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Frames an endpoint can hold before it overflows (a CAN controller's FIFO, generously).
const QUEUE_CAP: usize = 4096;

struct Queue {
    frames: VecDeque<CanFrame>,
    dropped: u64,
}

struct Shared {
    queues: Vec<Queue>,
    bus_off: bool,
    /// Frames sent over the bus in total (for bus statistics).
    sent: u64,
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
            inner: Arc::new((Mutex::new(Shared { queues: Vec::new(), bus_off: false, sent: 0 }), Condvar::new())),
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
        for (i, q) in s.queues.iter_mut().enumerate() {
            if i == self.idx {
                continue;
            }
            if q.frames.len() >= QUEUE_CAP {
                q.dropped += 1;
            } else {
                q.frames.push_back(*frame);
            }
        }
        cv.notify_all();
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let mut s = self.bus.inner.0.lock().unwrap_or_else(|e| e.into_inner());
        let q = &mut s.queues[self.idx];
        if q.dropped > 0 {
            let dropped = std::mem::take(&mut q.dropped);
            return Err(BusError::Overflow { bus: "inproc".into(), dropped });
        }
        Ok(q.frames.pop_front())
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        let deadline = Instant::now() + timeout;
        let (m, cv) = &*self.bus.inner;
        let mut s = m.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(f) = s.queues[self.idx].frames.pop_front() {
                return Ok(Some(f));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            s = cv.wait_timeout(s, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
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
