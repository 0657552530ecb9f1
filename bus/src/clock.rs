//! Injected time. The cycle loop and the SDO/NMT start-up take a `Clock`: real time for
//! hardware, simulated time for tests, where waiting advances the simulated world (bus and
//! emulated drives) deterministically and faster than real time. The same code runs in both.

use std::time::Duration;
#[cfg(not(target_os = "linux"))]
use std::time::Instant;

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
    /// A clock paced by received SYNCs (`bus.sync = "external"`, [`crate::sync_source`]):
    /// take in what has arrived, without waiting, and return the time now — one period on
    /// for every SYNC that came since the wake-up. The cycle asks just before it sends its
    /// set-points: a SYNC that came meanwhile was not waited for, and the set-points would be
    /// taken a SYNC later than computed. `None`: a timer clock (its SYNC is sent by the cycle
    /// itself, after the set-points).
    fn poll_sync(&mut self) -> Option<u64> {
        None
    }
}

/// A clock behind a box or a mutable reference is that clock (written once for both).
macro_rules! forward_clock {
    ($($ptr:ty),*) => {$(
        impl<C: Clock + ?Sized> Clock for $ptr {
            fn now_ns(&self) -> u64 {
                (**self).now_ns()
            }
            fn wait_until(&mut self, t_ns: u64) {
                (**self).wait_until(t_ns)
            }
            fn is_simulated(&self) -> bool {
                (**self).is_simulated()
            }
            fn poll_sync(&mut self) -> Option<u64> {
                (**self).poll_sync()
            }
        }
    )*};
}

forward_clock!(Box<C>, &mut C);

/// How [`RealClock`] waits for a deadline: sleep, in steps of at most `max_sleep_ns`, until
/// `spin_ns` before it, then busy-wait. The default (both 0) is one sleep to the deadline.
///
/// Why steps: on a virtual machine without a cpuidle driver an idle vCPU halts and the host
/// deschedules it; a long sleep then wakes late by the host's reschedule latency (hundreds of
/// µs measured on the Firecracker VM of this project), while short sleeps keep the vCPU in the
/// host's halt polling. Each step is a wake-up and costs a little CPU (see
/// `examples/wake_latency.rs`). Spinning gives µs accuracy but burns the core for `spin_ns`
/// every cycle: only where the cycle thread has a core to itself.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WakeStrategy {
    /// Longest single sleep in ns; 0 = no limit.
    pub max_sleep_ns: u64,
    /// Busy-wait this long before the deadline, in ns; 0 = never spin.
    pub spin_ns: u64,
}

/// The next thing a wait does (see [`WakeStrategy::step`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WakeStep {
    /// The deadline has passed: return.
    Done,
    /// Sleep until this absolute time (ns on the clock's scale); it is never after the deadline.
    SleepUntil(u64),
    /// Busy-wait (inside the spin margin).
    Spin,
}

impl WakeStrategy {
    /// At `now`, waiting for `deadline`: return, sleep until when, or spin. A sleep ends no
    /// later than `deadline - spin_ns` and lasts at most `max_sleep_ns`.
    pub fn step(&self, now: u64, deadline: u64) -> WakeStep {
        if now >= deadline {
            return WakeStep::Done;
        }
        let sleep_end = deadline.saturating_sub(self.spin_ns);
        if now >= sleep_end {
            return WakeStep::Spin;
        }
        if self.max_sleep_ns > 0 {
            WakeStep::SleepUntil(sleep_end.min(now.saturating_add(self.max_sleep_ns)))
        } else {
            WakeStep::SleepUntil(sleep_end)
        }
    }
}

/// Wall-clock time (CLOCK_MONOTONIC on Linux, `Instant` elsewhere).
///
/// By default `wait_until` sleeps to the deadline (on Linux an absolute `clock_nanosleep`, so
/// a late wake-up is not followed by a late re-sleep); hrtimer lateness is typically 50–100 µs
/// on a PC. [`RealClock::with_wake`] sleeps in steps and/or spins the last part, see
/// [`WakeStrategy`] — spinning only where the cycle thread has a core to itself (CPU affinity,
/// SCHED_FIFO); on a shared or single core it starves the other processes, including emulated
/// drives on the same machine.
pub struct RealClock {
    #[cfg(not(target_os = "linux"))]
    start: Instant,
    #[cfg(target_os = "linux")]
    start_mono: u64,
    wake: WakeStrategy,
}

#[cfg(target_os = "linux")]
fn mono_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes only the timespec we own; CLOCK_MONOTONIC always exists.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    (ts.tv_sec as u64).saturating_mul(1_000_000_000).saturating_add(ts.tv_nsec as u64)
}

impl RealClock {
    pub fn new() -> Self {
        Self::with_wake(WakeStrategy::default())
    }

    /// Busy-wait the last `spin` of every wait.
    pub fn with_spin(spin: Duration) -> Self {
        Self::with_wake(WakeStrategy { max_sleep_ns: 0, spin_ns: spin.as_nanos().min(u64::MAX as u128) as u64 })
    }

    /// Wait as `wake` says.
    pub fn with_wake(wake: WakeStrategy) -> Self {
        RealClock {
            #[cfg(not(target_os = "linux"))]
            start: Instant::now(),
            #[cfg(target_os = "linux")]
            start_mono: mono_ns(),
            wake,
        }
    }

    pub fn wake(&self) -> WakeStrategy {
        self.wake
    }

    #[cfg(target_os = "linux")]
    fn sleep_until(&self, t_ns: u64) {
        let abs = self.start_mono.saturating_add(t_ns);
        let ts = libc::timespec { tv_sec: (abs / 1_000_000_000) as libc::time_t, tv_nsec: (abs % 1_000_000_000) as libc::c_long };
        // SAFETY: ts lives across the call; with TIMER_ABSTIME the remainder pointer is unused.
        // EINTR or any error just returns: the caller's loop re-checks the time.
        unsafe { libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &ts, std::ptr::null_mut()) };
    }

    #[cfg(not(target_os = "linux"))]
    fn sleep_until(&self, t_ns: u64) {
        let now = self.now_ns();
        if t_ns > now {
            std::thread::sleep(Duration::from_nanos(t_ns - now));
        }
    }
}

impl Default for RealClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for RealClock {
    #[cfg(target_os = "linux")]
    fn now_ns(&self) -> u64 {
        mono_ns().saturating_sub(self.start_mono)
    }

    #[cfg(not(target_os = "linux"))]
    fn now_ns(&self) -> u64 {
        self.start.elapsed().as_nanos() as u64
    }

    fn wait_until(&mut self, t_ns: u64) {
        loop {
            match self.wake.step(self.now_ns(), t_ns) {
                WakeStep::Done => return,
                WakeStep::SleepUntil(t) => self.sleep_until(t),
                WakeStep::Spin => std::hint::spin_loop(),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;
    const US: u64 = 1_000;

    #[test]
    fn real_clock_waits_at_least_until_the_deadline() {
        let strategies = [
            WakeStrategy::default(),
            WakeStrategy { max_sleep_ns: 0, spin_ns: 100 * US },
            WakeStrategy { max_sleep_ns: 300 * US, spin_ns: 0 },
            WakeStrategy { max_sleep_ns: 300 * US, spin_ns: 50 * US },
            // A spin margin longer than the wait: all spin.
            WakeStrategy { max_sleep_ns: 0, spin_ns: 10 * MS },
        ];
        for w in strategies {
            let mut c = RealClock::with_wake(w);
            for _ in 0..3 {
                let t = c.now_ns() + 2 * MS;
                c.wait_until(t);
                assert!(c.now_ns() >= t, "{w:?} returned early");
            }
            // A deadline in the past returns at once, without sleeping.
            let now = c.now_ns();
            c.wait_until(now.saturating_sub(MS));
        }
        let mut c = RealClock::with_spin(Duration::from_micros(100));
        assert_eq!(c.wake().spin_ns, 100 * US);
        let t = c.now_ns() + MS;
        c.wait_until(t);
        assert!(c.now_ns() >= t);
    }

    #[test]
    fn the_clock_is_monotonic_and_starts_near_zero() {
        let c = RealClock::new();
        let a = c.now_ns();
        assert!(a < 1_000 * MS, "{a}");
        let b = c.now_ns();
        assert!(b >= a);
    }

    #[test]
    fn default_strategy_sleeps_to_the_deadline_in_one_step() {
        let w = WakeStrategy::default();
        assert_eq!(w.step(0, 2 * MS), WakeStep::SleepUntil(2 * MS));
        assert_eq!(w.step(2 * MS - 1, 2 * MS), WakeStep::SleepUntil(2 * MS));
        assert_eq!(w.step(2 * MS, 2 * MS), WakeStep::Done);
        assert_eq!(w.step(3 * MS, 2 * MS), WakeStep::Done);
    }

    #[test]
    fn chunked_sleeps_are_at_most_the_chunk_and_end_at_the_deadline() {
        let w = WakeStrategy { max_sleep_ns: 500 * US, spin_ns: 0 };
        // Walk a 2 ms wait as the clock would, each sleep ending exactly on time.
        let (mut now, deadline, mut steps) = (0, 2 * MS, Vec::new());
        loop {
            match w.step(now, deadline) {
                WakeStep::SleepUntil(t) => {
                    assert!(t > now && t - now <= 500 * US && t <= deadline);
                    steps.push(t);
                    now = t;
                }
                WakeStep::Done => break,
                WakeStep::Spin => panic!("spun without a spin margin"),
            }
        }
        assert_eq!(steps, vec![500 * US, MS, 1500 * US, 2 * MS]);
        // A late wake-up: the next step is measured from the actual time, still capped.
        assert_eq!(w.step(1_700 * US, deadline), WakeStep::SleepUntil(2 * MS));
        assert_eq!(w.step(100 * US, deadline), WakeStep::SleepUntil(600 * US));
    }

    #[test]
    fn spin_margin_ends_the_sleep_early_and_then_spins() {
        let w = WakeStrategy { max_sleep_ns: 0, spin_ns: 150 * US };
        assert_eq!(w.step(0, 2 * MS), WakeStep::SleepUntil(1_850 * US));
        assert_eq!(w.step(1_850 * US, 2 * MS), WakeStep::Spin);
        assert_eq!(w.step(1_999_999, 2 * MS), WakeStep::Spin);
        assert_eq!(w.step(2 * MS, 2 * MS), WakeStep::Done);
        // Chunks and spin together: the last chunk ends at the spin margin.
        let w = WakeStrategy { max_sleep_ns: 800 * US, spin_ns: 50 * US };
        assert_eq!(w.step(0, 2 * MS), WakeStep::SleepUntil(800 * US));
        assert_eq!(w.step(1_600 * US, 2 * MS), WakeStep::SleepUntil(1_950 * US));
        assert_eq!(w.step(1_950 * US, 2 * MS), WakeStep::Spin);
        // A margin longer than the whole wait: spin from the start, never underflow.
        let w = WakeStrategy { max_sleep_ns: 0, spin_ns: 5 * MS };
        assert_eq!(w.step(0, 2 * MS), WakeStep::Spin);
        // Huge values do not overflow.
        let w = WakeStrategy { max_sleep_ns: u64::MAX, spin_ns: 0 };
        assert_eq!(w.step(u64::MAX - 10, u64::MAX), WakeStep::SleepUntil(u64::MAX));
    }
}
