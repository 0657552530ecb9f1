//! Injected time. The cycle loop and the SDO/NMT start-up take a `Clock`: real time for
//! hardware, simulated time for tests, where waiting advances the simulated world (bus and
//! emulated drives) deterministically and faster than real time. The same code runs in both.

use std::time::{Duration, Instant};

pub trait Clock {
    /// Nanoseconds since this clock started.
    fn now_ns(&self) -> u64;
    /// Return at (or as soon as possible after) `t_ns`. A simulated clock advances its
    /// world to exactly `t_ns`.
    fn wait_until(&mut self, t_ns: u64);
    /// True for a simulated clock (used only for reporting).
    fn is_simulated(&self) -> bool {
        false
    }
}

/// Wall-clock time from `Instant`.
///
/// By default `wait_until` sleeps (hrtimer lateness is typically 50–100 µs on a PC). With
/// `with_spin`, it sleeps until `spin` before the deadline and then busy-waits, which cuts the
/// jitter to a few µs — but only where the cycle thread has a core to itself (CPU affinity,
/// SCHED_FIFO); on a shared or single core spinning starves the other processes, including
/// emulated drives on the same machine.
pub struct RealClock {
    start: Instant,
    spin_ns: u64,
}

impl RealClock {
    pub fn new() -> Self {
        RealClock { start: Instant::now(), spin_ns: 0 }
    }

    /// Busy-wait the last `spin` of every wait.
    pub fn with_spin(spin: Duration) -> Self {
        RealClock { start: Instant::now(), spin_ns: spin.as_nanos() as u64 }
    }
}

impl Default for RealClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for RealClock {
    fn now_ns(&self) -> u64 {
        self.start.elapsed().as_nanos() as u64
    }

    fn wait_until(&mut self, t_ns: u64) {
        loop {
            let now = self.now_ns();
            if now >= t_ns {
                return;
            }
            let left = t_ns - now;
            if left > self.spin_ns {
                std::thread::sleep(Duration::from_nanos(left - self.spin_ns));
            } else {
                std::hint::spin_loop();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn real_clock_waits_at_least_until_the_deadline() {
        for mut c in [RealClock::new(), RealClock::with_spin(Duration::from_micros(100))] {
            let t = c.now_ns() + 2_000_000;
            c.wait_until(t);
            assert!(c.now_ns() >= t);
        }
    }
}
