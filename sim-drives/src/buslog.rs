//! Bus log in candump's log-file format (`candump -l`, replayable with `canplayer`):
//! `(1700000000.123456) vcan0 181#2700E8030000`, one frame a line, both directions.

use crate::socketcand::unix_us;
use cncgw_bus::{BusError, CanBus, CanFrame};
use std::io::Write;
use std::time::{Duration, Instant};

/// Buffered output is flushed at least this often (and when the bus is idle, and on drop).
const FLUSH_EVERY: Duration = Duration::from_millis(100);

pub use cncgw_bus::frame::candump_line;

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
    fn remote_frames(&self) -> bool {
        self.inner.remote_frames()
    }
}

impl Drop for LoggedBus {
    fn drop(&mut self) {
        let _ = self.out.flush();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cncgw_bus::transport::inproc::InprocBus;
    use std::sync::{Arc, Mutex};

    #[derive(Clone, Default)]
    struct Shared(Arc<Mutex<Vec<u8>>>);
    impl Write for Shared {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn lines_are_candump_log_format() {
        assert_eq!(
            candump_line(1_700_000_000_123_456, "vcan0", &CanFrame::new(0x181, &[0x27, 0, 0xE8, 3, 0, 0])),
            "(1700000000.123456) vcan0 181#2700E8030000"
        );
        assert_eq!(candump_line(1_700_000_000_000_001, "can0", &CanFrame::new(0x80, &[])), "(1700000000.000001) can0 080#");
        let ext = CanFrame { id: 0x18FF_0001, extended: true, rtr: false, len: 1, data: [0xAB, 0, 0, 0, 0, 0, 0, 0] };
        assert_eq!(candump_line(5, "can0", &ext), "(0.000005) can0 18FF0001#AB");
    }

    #[test]
    fn both_directions_are_logged_in_order() {
        let bus = InprocBus::new();
        let mut peer = bus.endpoint();
        let out = Shared::default();
        let mut lb = LoggedBus::new(Box::new(bus.endpoint()), "vcan0", Box::new(out.clone()));
        peer.send(&CanFrame::new(0x601, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0])).unwrap();
        assert!(lb.recv_timeout(Duration::from_millis(100)).unwrap().is_some());
        lb.send(&CanFrame::new(0x581, &[0x43, 0x00, 0x10, 0, 0x92, 0x01, 0x02, 0x00])).unwrap();
        drop(lb);
        let text = String::from_utf8(out.0.lock().unwrap().clone()).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2, "{text}");
        for (l, want) in lines.iter().zip([" vcan0 601#4000100000000000", " vcan0 581#4300100092010200"]) {
            let (ts, rest) = l.split_once(')').unwrap();
            assert_eq!(rest, want);
            let ts = ts.strip_prefix('(').unwrap();
            let (s, us) = ts.split_once('.').unwrap();
            assert!(s.len() >= 10 && us.len() == 6 && ts.chars().all(|c| c.is_ascii_digit() || c == '.'), "{l}");
        }
    }
}
