//! Bus log in candump's log-file format (`candump -l`, replayable with `canplayer`):
//! `(1700000000.123456) vcan0 181#2700E8030000`, one frame a line, both directions.

use crate::socketcand::unix_us;
use cncgw_bus::{BusError, CanBus, CanFrame};
use std::io::Write;
use std::time::{Duration, Instant};

/// Buffered output is flushed at least this often (and when the bus is idle, and on drop).
const FLUSH_EVERY: Duration = Duration::from_millis(100);

/// One candump log line (without the newline).
pub fn candump_line(t_us: u64, iface: &str, f: &CanFrame) -> String {
    format!("({}.{:06}) {iface} {f:?}", t_us / 1_000_000, t_us % 1_000_000)
}

/// A `CanBus` that writes every frame it sends or receives to a candump log.
pub struct LoggedBus {
    inner: Box<dyn CanBus>,
    iface: String,
    out: Box<dyn Write + Send>,
    last_flush: Instant,
    failed: bool,
}

impl LoggedBus {
    /// `iface` is the interface name written on each line (candump's second column).
    pub fn new(inner: Box<dyn CanBus>, iface: &str, out: Box<dyn Write + Send>) -> LoggedBus {
        LoggedBus { inner, iface: iface.to_string(), out, last_flush: Instant::now(), failed: false }
    }

    fn log(&mut self, f: &CanFrame) {
        if self.failed {
            return;
        }
        let line = candump_line(unix_us(), &self.iface, f);
        let r = writeln!(self.out, "{line}").and_then(|_| {
            if self.last_flush.elapsed() >= FLUSH_EVERY {
                self.last_flush = Instant::now();
                self.out.flush()
            } else {
                Ok(())
            }
        });
        if let Err(e) = r {
            // The drives keep running; the log stops (disk full, …) and says so once.
            tracing::error!("bus log: {e}; logging stopped");
            self.failed = true;
        }
    }
}

impl CanBus for LoggedBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let r = self.inner.send(frame);
        if r.is_ok() {
            self.log(frame);
        }
        r
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let r = self.inner.try_recv();
        if let Ok(Some(f)) = &r {
            self.log(f);
        }
        r
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        let r = self.inner.recv_timeout(timeout);
        match &r {
            Ok(Some(f)) => self.log(f),
            Ok(None) if !self.failed => {
                let _ = self.out.flush();
                self.last_flush = Instant::now();
            }
            _ => {}
        }
        r
    }

    fn name(&self) -> &str {
        self.inner.name()
    }
}

impl Drop for LoggedBus {
    fn drop(&mut self) {
        let _ = self.out.flush();
    }
}
