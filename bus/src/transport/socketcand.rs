//! A socketcand client: the bus is a CAN interface served over TCP by a socketcand daemon
//! (or by `sim-drives --socketcand`), e.g. `socketcand://10.0.0.5:29536/can0`.
//!
//! A reader thread turns `< frame … >` messages into frames behind a bounded channel; sends
//! are formatted into a stack buffer and written directly, so the cycle loop allocates
//! nothing. TCP_NODELAY is set: without it a 2 ms SYNC/RPDO stream arrives in bursts.

use super::{BusError, CanBus};
use crate::can_error::{ControllerStatus, ErrorFrame};
use crate::socketcand::{Msg, Splitter};
use crate::CanFrame;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::mpsc;
use std::time::Duration;

pub struct Socketcand {
    name: String,
    stream: TcpStream,
    rx: mpsc::Receiver<Result<CanFrame, BusError>>,
    /// Error frames forwarded by the server (`< error CLASS TIME >`): class only, and only a
    /// daemon subscribed to error frames sends them (stock socketcand is not).
    status: std::sync::Arc<std::sync::Mutex<Option<ControllerStatus>>>,
}

/// Parse `socketcand://HOST:PORT/IFACE` into (`HOST:PORT`, `IFACE`).
pub fn parse_url(url: &str) -> Option<(String, String)> {
    let rest = url.strip_prefix("socketcand://")?;
    let (addr, iface) = rest.split_once('/')?;
    if addr.is_empty() || iface.is_empty() || !addr.contains(':') {
        return None;
    }
    Some((addr.to_string(), iface.to_string()))
}

fn expect(stream: &mut TcpStream, sp: &mut Splitter, what: &str, bus: &str) -> Result<Msg, BusError> {
    let mut buf = [0u8; 512];
    loop {
        if let Some(m) = sp.next_msg() {
            return Ok(m);
        }
        let n = stream.read(&mut buf).map_err(|e| BusError::Open { bus: bus.into(), reason: format!("waiting for {what}: {e}") })?;
        if n == 0 {
            return Err(BusError::Open { bus: bus.into(), reason: format!("server closed the connection waiting for {what}") });
        }
        sp.push(&buf[..n]);
    }
}

/// Format `< send ID DLC B… >` into `out` without allocating; returns the length.
fn format_send(f: &CanFrame, out: &mut [u8; 64]) -> usize {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    let mut n = 0;
    let mut put = |b: u8, n: &mut usize| {
        out[*n] = b;
        *n += 1;
    };
    for &b in b"< send " {
        put(b, &mut n);
    }
    let digits = if f.extended { 8 } else { 3 };
    for i in (0..digits).rev() {
        put(HEX[((f.id >> (4 * i)) & 0xF) as usize], &mut n);
    }
    put(b' ', &mut n);
    put(b'0' + f.len.min(8), &mut n);
    for &b in f.data() {
        put(b' ', &mut n);
        put(HEX[(b >> 4) as usize], &mut n);
        put(HEX[(b & 0xF) as usize], &mut n);
    }
    for &b in b" >" {
        put(b, &mut n);
    }
    n
}

impl Socketcand {
    pub fn connect(addr: &str, iface: &str) -> Result<Self, BusError> {
        let name = format!("socketcand://{addr}/{iface}");
        let open_err = |reason: String| BusError::Open { bus: name.clone(), reason };
        let mut stream = TcpStream::connect(addr).map_err(|e| open_err(format!("cannot connect to {addr}: {e}")))?;
        stream.set_nodelay(true).map_err(|e| open_err(e.to_string()))?;
        stream.set_read_timeout(Some(Duration::from_secs(3))).map_err(|e| open_err(e.to_string()))?;
        let mut sp = Splitter::default();
        match expect(&mut stream, &mut sp, "< hi >", &name)? {
            Msg::Hi => {}
            m => return Err(open_err(format!("expected < hi >, got {m:?}"))),
        }
        stream.write_all(format!("< open {iface} >").as_bytes()).map_err(|e| open_err(e.to_string()))?;
        match expect(&mut stream, &mut sp, "< ok > to open", &name)? {
            Msg::Ok => {}
            m => return Err(open_err(format!("the server refused to open {iface}: {m:?}"))),
        }
        stream.write_all(b"< rawmode >").map_err(|e| open_err(e.to_string()))?;
        match expect(&mut stream, &mut sp, "< ok > to rawmode", &name)? {
            Msg::Ok => {}
            m => return Err(open_err(format!("the server refused raw mode: {m:?}"))),
        }
        stream.set_read_timeout(None).map_err(|e| open_err(e.to_string()))?;
        let mut reader = stream.try_clone().map_err(|e| open_err(e.to_string()))?;
        let (tx, rx) = mpsc::sync_channel(4096);
        let bus = name.clone();
        let status = std::sync::Arc::new(std::sync::Mutex::new(None));
        let seen = status.clone();
        std::thread::Builder::new()
            .name("socketcand-rx".into())
            .spawn(move || {
                let mut buf = [0u8; 4096];
                // Frames that arrived with the handshake's last read.
                while let Some(m) = sp.next_msg() {
                    if let Msg::Frame(f, _) = m {
                        if tx.send(Ok(f)).is_err() {
                            return;
                        }
                    }
                }
                loop {
                    let n = match reader.read(&mut buf) {
                        Ok(0) => {
                            let _ = tx.send(Err(BusError::Closed { bus: bus.clone() }));
                            return;
                        }
                        Ok(n) => n,
                        Err(e) => {
                            let _ = tx.send(Err(BusError::Io { bus: bus.clone(), reason: e.to_string() }));
                            return;
                        }
                    };
                    sp.push(&buf[..n]);
                    while let Some(m) = sp.next_msg() {
                        let item = match m {
                            Msg::Frame(f, _) => Ok(f),
                            Msg::Error(e) if crate::socketcand::error_frame_class(&e).is_some() => {
                                let class = crate::socketcand::error_frame_class(&e).unwrap_or(0);
                                let mut g = seen.lock().unwrap_or_else(|p| p.into_inner());
                                g.get_or_insert_with(ControllerStatus::default).apply(&ErrorFrame::decode(class, &[]));
                                continue;
                            }
                            Msg::Error(e) => Err(BusError::Io { bus: bus.clone(), reason: format!("server error: {e}") }),
                            _ => continue,
                        };
                        if tx.send(item).is_err() {
                            return;
                        }
                    }
                }
            })
            .map_err(|e| open_err(e.to_string()))?;
        Ok(Socketcand { name, stream, rx, status })
    }
}

impl CanBus for Socketcand {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let mut buf = [0u8; 64];
        let n = format_send(frame, &mut buf);
        self.stream.write_all(&buf[..n]).map_err(|e| BusError::Io { bus: self.name.clone(), reason: e.to_string() })
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        match self.rx.try_recv() {
            Ok(r) => r.map(Some),
            Err(mpsc::TryRecvError::Empty) => Ok(None),
            Err(mpsc::TryRecvError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        match self.rx.recv_timeout(timeout) {
            Ok(r) => r.map(Some),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn remote_frames(&self) -> bool {
        false
    }

    fn controller(&self) -> Option<ControllerStatus> {
        *self.status.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl Drop for Socketcand {
    fn drop(&mut self) {
        let _ = self.stream.shutdown(std::net::Shutdown::Both);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::TcpListener;

    #[test]
    fn send_format_matches_the_codec() {
        for f in [
            CanFrame::new(0x80, &[]),
            CanFrame::new(0x601, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]),
            CanFrame { id: 0x18FF_0001, extended: true, rtr: false, len: 2, data: [1, 2, 0, 0, 0, 0, 0, 0] },
        ] {
            let mut buf = [0u8; 64];
            let n = format_send(&f, &mut buf);
            assert_eq!(std::str::from_utf8(&buf[..n]).unwrap(), crate::socketcand::format(&Msg::Send(f)));
        }
    }

    #[test]
    fn url() {
        assert_eq!(parse_url("socketcand://127.0.0.1:29536/can0"), Some(("127.0.0.1:29536".into(), "can0".into())));
        assert_eq!(parse_url("socketcand://host/can0"), None);
        assert_eq!(parse_url("vcan0"), None);
    }

    #[test]
    fn handshake_then_frames_both_ways_against_a_scripted_server() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        let server = std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            s.write_all(b"< hi >").unwrap();
            let mut sp = Splitter::default();
            let mut got = Vec::new();
            let mut buf = [0u8; 256];
            while got.len() < 3 {
                let n = s.read(&mut buf).unwrap();
                sp.push(&buf[..n]);
                while let Some(m) = sp.next_msg() {
                    match &m {
                        Msg::Open(_) | Msg::RawMode => s.write_all(b"< ok >").unwrap(),
                        _ => {}
                    }
                    got.push(m);
                }
            }
            s.write_all(b"< frame 181 1700000000.000100 2700E8030000 >< frame 080 1700000000.000200  >").unwrap();
            std::thread::sleep(Duration::from_millis(200));
            got
        });
        let mut c = Socketcand::connect(&addr, "can0").unwrap();
        c.send(&CanFrame::new(0x80, &[])).unwrap();
        let f1 = c.recv_timeout(Duration::from_secs(2)).unwrap().unwrap();
        assert_eq!(format!("{f1:?}"), "181#2700E8030000");
        let f2 = c.recv_timeout(Duration::from_secs(2)).unwrap().unwrap();
        assert_eq!(format!("{f2:?}"), "080#");
        let got = server.join().unwrap();
        assert_eq!(got, vec![Msg::Open("can0".into()), Msg::RawMode, Msg::Send(CanFrame::new(0x80, &[]))]);
    }

    #[test]
    fn error_frames_of_every_class_update_the_controller_status() {
        use crate::can_error::CanState;
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        let server = std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            s.write_all(b"< hi >").unwrap();
            let (mut sp, mut oks, mut buf) = (Splitter::default(), 0, [0u8; 256]);
            while oks < 2 {
                let n = s.read(&mut buf).unwrap();
                sp.push(&buf[..n]);
                while let Some(m) = sp.next_msg() {
                    if matches!(m, Msg::Open(_) | Msg::RawMode) {
                        s.write_all(b"< ok >").unwrap();
                        oks += 1;
                    }
                }
            }
            // linux/can/error.h: TX timeout, lost arbitration, controller, protocol,
            // transceiver, no ACK, bus-off, bus error, restarted — then a frame.
            for class in ["001", "002", "004", "008", "010", "020", "040", "080", "100"] {
                s.write_all(format!("< error {class} 1700000000.000100 >").as_bytes()).unwrap();
            }
            s.write_all(b"< frame 181 1700000000.000200 27 >").unwrap();
            std::thread::sleep(Duration::from_millis(200));
        });
        let mut c = Socketcand::connect(&addr, "can0").unwrap();
        assert_eq!(c.controller(), None, "nothing heard yet");
        // Error frames are not frames: the first frame received is the one after them.
        let f = c.recv_timeout(Duration::from_secs(2)).unwrap().unwrap();
        assert_eq!(format!("{f:?}"), "181#27");
        let st = c.controller().expect("error frames seen");
        server.join().unwrap();
        assert_eq!(st.error_frames, 9);
        assert_eq!((st.tx_timeouts, st.lost_arbitrations, st.controller_unspecified, st.transceiver_errors), (1, 1, 1, 1));
        // PROT and BUSERROR are protocol errors, ACK its own count.
        assert_eq!((st.protocol_errors, st.no_ack), (2, 1));
        // Bus-off, then restarted: error-active again.
        assert_eq!((st.bus_offs, st.restarts, st.state), (1, 1, CanState::ErrorActive));
    }
}
