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
pub struct RealClock {
    start: Instant,
}

impl RealClock {
    pub fn new() -> Self {
        RealClock { start: Instant::now() }
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
        // Sleep most of the way, then spin the last 150 µs: Linux timer slack plus wake-up
        // latency would otherwise add ~60–100 µs of jitter to every cycle.
        const SPIN_NS: u64 = 150_000;
        loop {
            let now = self.now_ns();
            if now >= t_ns {
                return;
            }
            let left = t_ns - now;
            if left > SPIN_NS {
                std::thread::sleep(Duration::from_nanos(left - SPIN_NS));
            } else {
                std::hint::spin_loop();
            }
        }
    }
}
