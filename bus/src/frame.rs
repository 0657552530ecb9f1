//! A classic CAN 2.0 frame, independent of any transport.

use std::fmt;

#[derive(Clone, Copy, PartialEq, Eq, Default)]
pub struct CanFrame {
    /// 11-bit (standard) or 29-bit (extended) identifier.
    pub id: u32,
    pub extended: bool,
    pub rtr: bool,
    pub len: u8,
    pub data: [u8; 8],
}

impl CanFrame {
    /// A standard-id data frame. Data longer than 8 bytes is truncated (callers build
    /// frames from fixed layouts, so this cannot happen in the codecs).
    pub fn new(id: u16, data: &[u8]) -> Self {
        let len = data.len().min(8);
        let mut d = [0u8; 8];
        d[..len].copy_from_slice(&data[..len]);
        CanFrame { id: id as u32 & 0x7FF, extended: false, rtr: false, len: len as u8, data: d }
    }

    pub fn data(&self) -> &[u8] {
        &self.data[..self.len as usize]
    }

    /// The 11-bit COB-ID of a standard frame.
    pub fn cob_id(&self) -> u16 {
        (self.id & 0x7FF) as u16
    }
}

/// One line of candump's log-file format (`candump -l`, replayable with `canplayer`), without
/// the newline: `(1700000000.123456) vcan0 181#2700E8030000`. `t_us`: µs since the Unix epoch.
pub fn candump_line(t_us: u64, iface: &str, f: &CanFrame) -> String {
    format!("({}.{:06}) {iface} {f:?}", t_us / 1_000_000, t_us % 1_000_000)
}

impl fmt::Debug for CanFrame {
    /// candump style: `181#2700E8030000`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.extended {
            write!(f, "{:08X}#", self.id)?;
        } else {
            write!(f, "{:03X}#", self.id)?;
        }
        if self.rtr {
            return write!(f, "R");
        }
        for b in self.data() {
            write!(f, "{b:02X}")?;
        }
        Ok(())
    }
}

impl fmt::Display for CanFrame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self, f)
    }
}
