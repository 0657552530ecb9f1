//! The socketcand daemon's TCP protocol (raw mode), as spoken by socketcand itself and by
//! python-can: `< hi >`, `< open can0 >` → `< ok >`, `< rawmode >` → `< ok >`, then
//! `< send ID DLC B0 B1 … >` from the client and `< frame ID SEC.USEC DATA >` from the server.
//! Used by the cncgw client transport and by sim-drives' server, so both agree.
//!
//! Strictness (measured with python-can 4.6): standard ids are exactly 3 hex digits (any
//! other length reads as extended, 8 digits); data is one uppercase hex string; a
//! zero-length frame keeps its empty data field (`< frame 080 1700000000.000000  >`).

use crate::CanFrame;

#[derive(Clone, Debug, PartialEq)]
pub enum Msg {
    Hi,
    Ok,
    Open(String),
    RawMode,
    Echo,
    Send(CanFrame),
    /// A received frame with its timestamp in microseconds.
    Frame(CanFrame, u64),
    Error(String),
    /// Anything else (other modes, commands we do not implement).
    Other(String),
}

fn parse_id(s: &str) -> Option<(u32, bool)> {
    let id = u32::from_str_radix(s, 16).ok()?;
    if s.len() == 3 {
        (id <= 0x7FF).then_some((id, false))
    } else {
        (id <= 0x1FFF_FFFF).then_some((id, true))
    }
}

fn fmt_id(f: &CanFrame) -> String {
    if f.extended {
        format!("{:08X}", f.id)
    } else {
        format!("{:03X}", f.id)
    }
}

/// Parse the inside of one `< … >` message.
pub fn parse(body: &str) -> Msg {
    let mut w = body.split_whitespace();
    let cmd = w.next().unwrap_or("");
    match cmd {
        "hi" => Msg::Hi,
        "ok" => Msg::Ok,
        "rawmode" => Msg::RawMode,
        "echo" => Msg::Echo,
        "open" => Msg::Open(w.next().unwrap_or("").to_string()),
        "error" => Msg::Error(w.collect::<Vec<_>>().join(" ")),
        "send" => {
            let parsed = (|| {
                let (id, extended) = parse_id(w.next()?)?;
                let dlc: usize = w.next()?.parse().ok()?;
                if dlc > 8 {
                    return None;
                }
                let mut data = [0u8; 8];
                for b in data.iter_mut().take(dlc) {
                    *b = u8::from_str_radix(w.next()?, 16).ok()?;
                }
                if w.next().is_some() {
                    return None;
                }
                Some(CanFrame { id, extended, rtr: false, len: dlc as u8, data })
            })();
            parsed.map(Msg::Send).unwrap_or_else(|| Msg::Other(body.trim().to_string()))
        }
        "frame" => {
            let parsed = (|| {
                let (id, extended) = parse_id(w.next()?)?;
                let ts = w.next()?;
                // Byte slicing below: anything but ASCII is no timestamp or hex (and would
                // split a character: a peer's garbage must not panic us).
                if !ts.is_ascii() {
                    return None;
                }
                let (sec, usec) = ts.split_once('.').unwrap_or((ts, "0"));
                // A fraction of other than 6 digits is still a fraction of a second.
                let frac = &usec[..usec.len().min(6)];
                let scale = 10u64.pow(6 - frac.len() as u32);
                let us = if frac.is_empty() { 0 } else { frac.parse::<u64>().ok()? * scale };
                let t = sec.parse::<u64>().ok()?.checked_mul(1_000_000)?.checked_add(us)?;
                let hex = w.next().unwrap_or("");
                if !hex.is_ascii() || hex.len() % 2 != 0 || hex.len() > 16 || w.next().is_some() {
                    return None;
                }
                let mut data = [0u8; 8];
                for (i, b) in data.iter_mut().take(hex.len() / 2).enumerate() {
                    *b = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok()?;
                }
                Some((CanFrame { id, extended, rtr: false, len: (hex.len() / 2) as u8, data }, t))
            })();
            parsed.map(|(f, t)| Msg::Frame(f, t)).unwrap_or_else(|| Msg::Other(body.trim().to_string()))
        }
        _ => Msg::Other(body.trim().to_string()),
    }
}

/// An error frame as socketcand's raw mode forwards it: `< error CLASS SEC.USEC >` (the
/// error class of the CAN ID in hex; the data bytes — controller status, error counters —
/// are not carried). Stock socketcand never subscribes to error frames (no
/// CAN_RAW_ERR_FILTER on its raw socket), so only a daemon that does sends these. Other
/// `< error … >` messages are the server's own complaints: None.
pub fn error_frame_class(error_body: &str) -> Option<u32> {
    let mut w = error_body.split_whitespace();
    let class = w.next().filter(|c| c.len() >= 3 && c.bytes().all(|b| b.is_ascii_hexdigit()))?;
    let ts = w.next().filter(|t| t.contains('.') && t.bytes().all(|b| b.is_ascii_digit() || b == b'.'))?;
    (w.next().is_none() && !ts.is_empty()).then(|| u32::from_str_radix(class, 16).ok()).flatten()
}

/// Format a message, including the angle brackets.
pub fn format(m: &Msg) -> String {
    match m {
        Msg::Hi => "< hi >".into(),
        Msg::Ok => "< ok >".into(),
        Msg::RawMode => "< rawmode >".into(),
        Msg::Echo => "< echo >".into(),
        Msg::Open(bus) => format!("< open {bus} >"),
        Msg::Error(e) => format!("< error {e} >"),
        Msg::Other(s) => format!("< {s} >"),
        Msg::Send(f) => {
            let mut s = format!("< send {} {}", fmt_id(f), f.len);
            for b in f.data() {
                s.push_str(&format!(" {b:02X}"));
            }
            s.push_str(" >");
            s
        }
        Msg::Frame(f, t) => {
            let mut hex = String::with_capacity(16);
            for b in f.data() {
                hex.push_str(&format!("{b:02X}"));
            }
            format!("< frame {} {}.{:06} {} >", fmt_id(f), t / 1_000_000, t % 1_000_000, hex)
        }
    }
}

/// Splits a byte stream into `< … >` messages.
#[derive(Default)]
pub struct Splitter {
    buf: Vec<u8>,
}

impl Splitter {
    pub fn push(&mut self, data: &[u8]) {
        self.buf.extend_from_slice(data);
    }

    /// The next complete message, if any. Garbage before a `<` is skipped; a message longer
    /// than 1 KiB without its `>` is dropped (no valid message is that long).
    pub fn next_msg(&mut self) -> Option<Msg> {
        let start = self.buf.iter().position(|&b| b == b'<')?;
        if start > 0 {
            self.buf.drain(..start);
        }
        match self.buf.iter().position(|&b| b == b'>') {
            Some(end) => {
                let body = String::from_utf8_lossy(&self.buf[1..end]).into_owned();
                self.buf.drain(..=end);
                Some(parse(&body))
            }
            None => {
                if self.buf.len() > 1024 {
                    self.buf.clear();
                }
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_frames_as_socketcand_forwards_them_are_told_from_its_complaints() {
        // state_raw.c: sprintf("< error %03X %ld.%06ld >", can_id & CAN_EFF_MASK, …)
        match parse("error 040 1700000000.123456") {
            Msg::Error(e) => assert_eq!(error_frame_class(&e), Some(0x040)),
            m => panic!("{m:?}"),
        }
        assert_eq!(error_frame_class("20000004 1.000001"), Some(0x2000_0004));
        assert_eq!(error_frame_class("unknown command"), None);
        assert_eq!(error_frame_class("040"), None);
        assert_eq!(error_frame_class("040 12.5 x"), None);
    }

    #[test]
    fn frames_format_exactly_like_socketcand() {
        let sync = CanFrame::new(0x80, &[]);
        assert_eq!(format(&Msg::Frame(sync, 1_700_000_000_000_000)), "< frame 080 1700000000.000000  >");
        let tpdo = CanFrame::new(0x181, &[0x27, 0x00, 0xE8, 0x03, 0x00, 0x00]);
        assert_eq!(format(&Msg::Frame(tpdo, 1_700_000_000_123_456)), "< frame 181 1700000000.123456 2700E8030000 >");
        assert_eq!(format(&Msg::Send(tpdo)), "< send 181 6 27 00 E8 03 00 00 >");
        let ext = CanFrame { id: 0x1234567, extended: true, rtr: false, len: 1, data: [0xAB, 0, 0, 0, 0, 0, 0, 0] };
        assert_eq!(format(&Msg::Frame(ext, 5)), "< frame 01234567 0.000005 AB >");
    }

    #[test]
    fn parse_round_trips_and_id_length_decides_extended() {
        let f = CanFrame::new(0x601, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
        assert_eq!(parse("send 601 8 40 00 10 00 00 00 00 00"), Msg::Send(f));
        assert_eq!(parse(" frame 080 1700000000.000000  "), Msg::Frame(CanFrame::new(0x80, &[]), 1_700_000_000_000_000));
        match parse("send 00000601 0") {
            Msg::Send(f) => assert!(f.extended),
            m => panic!("{m:?}"),
        }
        assert!(matches!(parse("send 601 9 00"), Msg::Other(_)));
        // Timestamps with a fraction of other than 6 digits (python-can prints floats).
        assert_eq!(parse("frame 080 12.5 "), Msg::Frame(CanFrame::new(0x80, &[]), 12_500_000));
        assert_eq!(parse("frame 080 12.1234567 "), Msg::Frame(CanFrame::new(0x80, &[]), 12_123_456));
        assert_eq!(parse("frame 080 12 "), Msg::Frame(CanFrame::new(0x80, &[]), 12_000_000));
        assert!(matches!(parse("send 601 2 00"), Msg::Other(_)));
        // Non-ASCII where hex or a timestamp belongs (found by fuzzing: it panicked).
        assert!(matches!(parse("frame 181 12.5 2700E80300\u{FFFD}"), Msg::Other(_)));
        assert!(matches!(parse("frame 181 12.\u{FFFD}12345 00"), Msg::Other(_)));
    }

    #[test]
    fn splitter_handles_partial_and_joined_messages() {
        let mut s = Splitter::default();
        s.push(b"< hi >< ok");
        assert_eq!(s.next_msg(), Some(Msg::Hi));
        assert_eq!(s.next_msg(), None);
        s.push(b" >< open can0 >");
        assert_eq!(s.next_msg(), Some(Msg::Ok));
        assert_eq!(s.next_msg(), Some(Msg::Open("can0".into())));
    }
}
