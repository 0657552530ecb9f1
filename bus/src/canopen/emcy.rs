//! EMCY messages (0x80 + node): error code, error register, 5 manufacturer bytes; and the
//! CiA 301 / CiA 402 error codes in words.

use super::cob;
use crate::CanFrame;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Emcy {
    pub code: u16,
    pub register: u8,
    pub vendor: [u8; 5],
}

impl Emcy {
    pub fn frame(&self, node: u8) -> CanFrame {
        let c = self.code.to_le_bytes();
        let v = self.vendor;
        CanFrame::new(cob::EMCY_BASE + node as u16, &[c[0], c[1], self.register, v[0], v[1], v[2], v[3], v[4]])
    }

    /// Decode (node, emcy). The SYNC frame shares function code 0x080 but has node 0.
    pub fn decode(f: &CanFrame) -> Option<(u8, Emcy)> {
        let (func, node) = cob::split(f.cob_id());
        if func != cob::EMCY_BASE || node == 0 || f.len != 8 || f.rtr {
            return None;
        }
        let d = &f.data;
        Some((node, Emcy { code: u16::from_le_bytes([d[0], d[1]]), register: d[2], vendor: [d[3], d[4], d[5], d[6], d[7]] }))
    }
}

/// CiA 301 and CiA 402 error codes (0x603F / EMCY) in words. Exact codes first, then the
/// code's class (high byte / high nibble) as CiA 301 Table 21 defines it.
pub fn error_text(code: u16) -> String {
    let exact = match code {
        0x0000 => Some("error reset or no error"),
        0x1000 => Some("generic error"),
        0x2310 => Some("continuous overcurrent"),
        0x2311 => Some("overcurrent, device input side"),
        0x2320 => Some("short circuit / earth leakage"),
        0x2330 => Some("earth leakage"),
        0x2340 => Some("short circuit"),
        0x3110 => Some("mains overvoltage"),
        0x3120 => Some("mains undervoltage"),
        0x3130 => Some("phase failure"),
        0x3210 => Some("DC-link overvoltage"),
        0x3220 => Some("DC-link undervoltage"),
        0x4210 => Some("excess temperature device"),
        0x4310 => Some("excess temperature drive"),
        0x5114 => Some("supply voltage, motor / power stage"),
        0x5530 => Some("data storage (EEPROM) error"),
        0x6010 => Some("software reset (watchdog)"),
        0x6320 => Some("parameter error"),
        0x7121 => Some("motor blocked"),
        0x7300 => Some("sensor error"),
        0x7305 => Some("incremental encoder 1 broken"),
        0x7306 => Some("incremental encoder 2 broken"),
        0x7310 => Some("speed (tachometer) error"),
        0x7320 => Some("position sensor error"),
        0x8110 => Some("CAN overrun (objects lost)"),
        0x8120 => Some("CAN in error passive mode"),
        0x8130 => Some("life guard error or heartbeat error"),
        0x8140 => Some("recovered from bus off"),
        0x8141 => Some("CAN-ID collision"),
        0x8210 => Some("PDO not processed due to length error"),
        0x8220 => Some("PDO length exceeded"),
        0x8250 => Some("RPDO timeout"),
        0x8400 => Some("velocity speed controller (speed deviation)"),
        0x8500 => Some("position controller"),
        0x8611 => Some("following error"),
        0x8612 => Some("reference limit"),
        0xFF00 => Some("manufacturer specific"),
        _ => None,
    };
    if let Some(t) = exact {
        return t.to_string();
    }
    let class = match code >> 8 {
        0x10 => "generic error",
        0x20..=0x23 => "current",
        0x30..=0x33 => "voltage",
        0x40..=0x43 => "temperature",
        0x50 => "device hardware",
        0x60..=0x63 => "device software",
        0x70 => "additional modules",
        0x71..=0x73 => "motor / sensor",
        0x80..=0x82 => "monitoring / communication",
        0x84..=0x86 => "control / following",
        0x90 => "external error",
        0xF0 => "additional functions",
        0xFF => "manufacturer specific",
        _ => "unknown error class",
    };
    format!("{class} (0x{code:04X})")
}

/// The error register 0x1001 (CiA 301 §7.5.2.2) in words: the set bits, comma-separated;
/// "no error" for 0.
pub fn error_register_text(reg: u8) -> String {
    const BITS: [&str; 8] = [
        "generic error",
        "current",
        "voltage",
        "temperature",
        "communication error (overrun, error state)",
        "device profile specific",
        "reserved (bit 6)",
        "manufacturer specific",
    ];
    if reg == 0 {
        return "no error".into();
    }
    BITS.iter().enumerate().filter(|(i, _)| reg & (1 << i) != 0).map(|(_, t)| *t).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn emcy_round_trip_and_words() {
        let e = Emcy { code: 0x8611, register: 0x20, vendor: [0; 5] };
        assert_eq!(format!("{:?}", e.frame(2)), "082#1186200000000000");
        assert_eq!(Emcy::decode(&e.frame(2)), Some((2, e)));
        assert_eq!(Emcy::decode(&crate::canopen::sync_frame(None)), None);
        assert_eq!(error_text(0x2310), "continuous overcurrent");
        assert_eq!(error_text(0x3210), "DC-link overvoltage");
        assert_eq!(error_text(0x7305), "incremental encoder 1 broken");
        assert_eq!(error_text(0x8611), "following error");
        assert_eq!(error_text(0x2399), "current (0x2399)");
        assert_eq!(error_register_text(0), "no error");
        assert_eq!(error_register_text(0x03), "generic error, current");
        assert_eq!(error_register_text(0x21), "generic error, device profile specific");
    }
}
