//! SocketCAN error frames (linux/can/error.h): what the CAN controller itself reports —
//! error-warning, error-passive, bus-off, restarted, missing ACK, controller RX overflow —
//! decoded into a [`ControllerStatus`] that keeps the state, the error counters and how
//! often each event happened (as `ip -details -statistics link show can0` shows them).
//!
//! Sans-I/O: the transport hands over the frame's CAN ID word and data as the kernel sends
//! them (`CAN_RAW_ERR_FILTER` subscribed, see `transport::socketcan`); nothing here reads a
//! socket. [`ErrorFrame::encode`] builds the same bytes for tests and for injecting error
//! frames on a vcan interface.

use std::fmt;

/// CAN ID flag of an error frame (linux/can.h CAN_ERR_FLAG).
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// The error class bits of the CAN ID (CAN_ERR_MASK).
pub const CAN_ERR_MASK: u32 = 0x1FFF_FFFF;

/// Error classes in the CAN ID (linux/can/error.h).
pub mod class {
    pub const TX_TIMEOUT: u32 = 0x001;
    pub const LOSTARB: u32 = 0x002;
    /// Controller problems, data[1].
    pub const CRTL: u32 = 0x004;
    /// Protocol violations, data[2] (type) and data[3] (location).
    pub const PROT: u32 = 0x008;
    /// Transceiver status, data[4].
    pub const TRX: u32 = 0x010;
    /// No ACK on transmission.
    pub const ACK: u32 = 0x020;
    pub const BUSOFF: u32 = 0x040;
    pub const BUSERROR: u32 = 0x080;
    pub const RESTARTED: u32 = 0x100;
    /// TX / RX error counters valid in data[6] / data[7].
    pub const CNT: u32 = 0x200;
}

/// data[1]: the controller's status (CAN_ERR_CRTL_*).
pub mod crtl {
    pub const RX_OVERFLOW: u8 = 0x01;
    pub const TX_OVERFLOW: u8 = 0x02;
    pub const RX_WARNING: u8 = 0x04;
    pub const TX_WARNING: u8 = 0x08;
    pub const RX_PASSIVE: u8 = 0x10;
    pub const TX_PASSIVE: u8 = 0x20;
    /// Recovered to error-active.
    pub const ACTIVE: u8 = 0x40;
}

/// One error frame as the kernel sends it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ErrorFrame {
    /// Error class bits (CAN ID & CAN_ERR_MASK).
    pub class: u32,
    pub data: [u8; 8],
}

impl ErrorFrame {
    /// From the CAN ID word (with or without CAN_ERR_FLAG) and the data bytes.
    pub fn decode(id: u32, data: &[u8]) -> ErrorFrame {
        let mut d = [0u8; 8];
        let n = data.len().min(8);
        d[..n].copy_from_slice(&data[..n]);
        ErrorFrame { class: id & CAN_ERR_MASK, data: d }
    }

    /// CAN ID word (CAN_ERR_FLAG set) and the 8 data bytes, as the kernel sends them.
    pub fn encode(&self) -> (u32, [u8; 8]) {
        ((self.class & CAN_ERR_MASK) | CAN_ERR_FLAG, self.data)
    }

    /// An error frame of `class` with the controller status byte `ctrl` and, if given, the
    /// TX/RX error counters.
    pub fn new(class: u32, ctrl: u8, counters: Option<(u8, u8)>) -> ErrorFrame {
        let mut data = [0u8; 8];
        data[1] = ctrl;
        let mut class = class;
        if let Some((tx, rx)) = counters {
            class |= self::class::CNT;
            data[6] = tx;
            data[7] = rx;
        }
        if ctrl != 0 {
            class |= self::class::CRTL;
        }
        ErrorFrame { class, data }
    }

    fn has(&self, c: u32) -> bool {
        self.class & c != 0
    }

    fn ctrl(&self, bits: u8) -> bool {
        self.has(class::CRTL) && self.data[1] & bits != 0
    }
}

/// The controller's fault confinement state (ISO 11898-1).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CanState {
    #[default]
    ErrorActive,
    ErrorWarning,
    ErrorPassive,
    BusOff,
}

impl CanState {
    pub fn name(self) -> &'static str {
        match self {
            CanState::ErrorActive => "error-active",
            CanState::ErrorWarning => "error-warning",
            CanState::ErrorPassive => "error-passive",
            CanState::BusOff => "bus-off",
        }
    }
}

impl fmt::Display for CanState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// What one error frame reported (bits, so that one frame's several events fit a `u16`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Events(pub u16);

impl Events {
    pub const WARNING: u16 = 1;
    pub const PASSIVE: u16 = 2;
    pub const BUS_OFF: u16 = 4;
    pub const RESTARTED: u16 = 8;
    pub const BACK_TO_ACTIVE: u16 = 16;
    pub const NO_ACK: u16 = 32;
    pub const RX_OVERFLOW: u16 = 64;
    pub const TX_OVERFLOW: u16 = 128;
    pub const TX_TIMEOUT: u16 = 256;
    pub const PROTOCOL: u16 = 512;
    pub const LOST_ARBITRATION: u16 = 1024;
    pub const TRANSCEIVER: u16 = 2048;

    const TEXT: [(u16, &'static str); 12] = [
        (Self::BUS_OFF, "bus-off (the controller stopped sending: too many errors)"),
        (Self::PASSIVE, "error-passive (an error counter over 127)"),
        (Self::WARNING, "error-warning (an error counter over 95)"),
        (Self::RESTARTED, "controller restarted after bus-off"),
        (Self::BACK_TO_ACTIVE, "back to error-active"),
        (Self::NO_ACK, "no ACK (no other node acknowledged a frame: drives off, cable or termination?)"),
        (Self::RX_OVERFLOW, "controller RX overflow (frames lost)"),
        (Self::TX_OVERFLOW, "controller TX overflow"),
        (Self::TX_TIMEOUT, "TX timeout"),
        (Self::PROTOCOL, "protocol error (bit, stuff, form or CRC)"),
        (Self::LOST_ARBITRATION, "lost arbitration"),
        (Self::TRANSCEIVER, "transceiver error"),
    ];

    pub fn has(self, e: u16) -> bool {
        self.0 & e != 0
    }

    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// Each event in words, most serious first.
    pub fn texts(self) -> impl Iterator<Item = &'static str> {
        Self::TEXT.into_iter().filter(move |(b, _)| self.has(*b)).map(|(_, t)| t)
    }

    /// Worth a warning to the operator (not the flood of single bus errors).
    pub fn warn(self) -> bool {
        self.0 & !(Self::PROTOCOL | Self::LOST_ARBITRATION) != 0
    }
}

/// The controller as its error frames tell it: state, last error counters, and how often
/// each event came (counted since the bus was opened).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct ControllerStatus {
    pub state: CanState,
    /// Last TX / RX error counters reported (CAN_ERR_CNT), if any frame carried them.
    pub tx_errors: Option<u8>,
    pub rx_errors: Option<u8>,
    pub error_frames: u64,
    pub warnings: u64,
    pub passives: u64,
    pub bus_offs: u64,
    pub restarts: u64,
    pub no_ack: u64,
    pub rx_overflows: u64,
    pub protocol_errors: u64,
    /// CAN_ERR_TX_TIMEOUT: a frame the controller could not send in time.
    pub tx_timeouts: u64,
    /// CAN_ERR_LOSTARB: arbitration lost (another node sent a lower ID at once).
    pub lost_arbitrations: u64,
    /// CAN_ERR_TRX: the transceiver reported a wire fault (CAN-H/CAN-L open or shorted).
    pub transceiver_errors: u64,
    /// CAN_ERR_CRTL_TX_OVERFLOW: the controller's TX buffer overflowed.
    pub tx_overflows: u64,
    /// CAN_ERR_CRTL without a status byte: "a controller problem", which one unknown (socketcand
    /// forwards the class, not the data).
    pub controller_unspecified: u64,
}

impl ControllerStatus {
    /// Take one error frame; what it reported.
    pub fn apply(&mut self, f: &ErrorFrame) -> Events {
        let mut ev = 0u16;
        self.error_frames += 1;
        if f.has(class::CNT) {
            self.tx_errors = Some(f.data[6]);
            self.rx_errors = Some(f.data[7]);
        }
        if f.has(class::BUSOFF) {
            ev |= Events::BUS_OFF;
            self.bus_offs += 1;
            self.state = CanState::BusOff;
        }
        if f.has(class::RESTARTED) {
            ev |= Events::RESTARTED;
            self.restarts += 1;
            self.state = CanState::ErrorActive;
        }
        if f.ctrl(crtl::RX_PASSIVE | crtl::TX_PASSIVE) {
            ev |= Events::PASSIVE;
            self.passives += 1;
            if self.state != CanState::BusOff {
                self.state = CanState::ErrorPassive;
            }
        } else if f.ctrl(crtl::RX_WARNING | crtl::TX_WARNING) {
            ev |= Events::WARNING;
            self.warnings += 1;
            if matches!(self.state, CanState::ErrorActive) {
                self.state = CanState::ErrorWarning;
            }
        }
        if f.ctrl(crtl::ACTIVE) {
            ev |= Events::BACK_TO_ACTIVE;
            self.state = CanState::ErrorActive;
        }
        if f.ctrl(crtl::RX_OVERFLOW) {
            ev |= Events::RX_OVERFLOW;
            self.rx_overflows += 1;
        }
        if f.ctrl(crtl::TX_OVERFLOW) {
            ev |= Events::TX_OVERFLOW;
            self.tx_overflows += 1;
        }
        if f.has(class::CRTL) && f.data[1] == 0 {
            self.controller_unspecified += 1;
        }
        if f.has(class::ACK) {
            ev |= Events::NO_ACK;
            self.no_ack += 1;
        }
        if f.has(class::TX_TIMEOUT) {
            ev |= Events::TX_TIMEOUT;
            self.tx_timeouts += 1;
        }
        if f.has(class::PROT | class::BUSERROR) {
            ev |= Events::PROTOCOL;
            self.protocol_errors += 1;
        }
        if f.has(class::LOSTARB) {
            ev |= Events::LOST_ARBITRATION;
            self.lost_arbitrations += 1;
        }
        if f.has(class::TRX) {
            ev |= Events::TRANSCEIVER;
            self.transceiver_errors += 1;
        }
        Events(ev)
    }

    /// One line for a monitor: state, counters, event counts.
    pub fn line(&self) -> String {
        let cnt = |c: Option<u8>| c.map_or("?".to_string(), |c| c.to_string());
        format!(
            "{}, tx errors {}, rx errors {}; error-warning {}, error-passive {}, bus-off {}, restarted {}, no ACK {}, RX overflow {} ({} error frames)",
            self.state,
            cnt(self.tx_errors),
            cnt(self.rx_errors),
            self.warnings,
            self.passives,
            self.bus_offs,
            self.restarts,
            self.no_ack,
            self.rx_overflows,
            self.error_frames
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frames as the kernel's CAN drivers send them (drivers/net/can/dev: can_change_state,
    /// can_bus_off; the SJA1000 / mcp251x patterns), CAN ID word with CAN_ERR_FLAG.
    fn k(id: u32, data: [u8; 8]) -> ErrorFrame {
        assert_ne!(id & CAN_ERR_FLAG, 0);
        ErrorFrame::decode(id, &data)
    }

    #[test]
    fn state_changes_and_counters_as_the_kernel_reports_them() {
        let mut s = ControllerStatus::default();
        // can_change_state to error-warning by TX errors: CRTL | CNT, data[1] TX_WARNING.
        let e = s.apply(&k(0x2000_0204, [0, 0x08, 0, 0, 0, 0, 97, 3]));
        assert!(e.has(Events::WARNING) && e.warn());
        assert_eq!((s.state, s.tx_errors, s.rx_errors), (CanState::ErrorWarning, Some(97), Some(3)));
        // To error-passive by RX errors.
        let e = s.apply(&k(0x2000_0204, [0, 0x10, 0, 0, 0, 0, 97, 128]));
        assert!(e.has(Events::PASSIVE));
        assert_eq!((s.state, s.rx_errors), (CanState::ErrorPassive, Some(128)));
        // Bus-off: CAN_ERR_BUSOFF (can_bus_off), counters as the driver last read them.
        let e = s.apply(&k(0x2000_0240, [0, 0, 0, 0, 0, 0, 255, 0]));
        assert!(e.has(Events::BUS_OFF));
        assert_eq!((s.state, s.tx_errors), (CanState::BusOff, Some(255)));
        // Restarted (can_restart: CAN_ERR_RESTARTED), then back to error-active.
        let e = s.apply(&k(0x2000_0100, [0; 8]));
        assert!(e.has(Events::RESTARTED));
        assert_eq!(s.state, CanState::ErrorActive);
        let e = s.apply(&k(0x2000_0204, [0, 0x40, 0, 0, 0, 0, 0, 0]));
        assert!(e.has(Events::BACK_TO_ACTIVE));
        assert_eq!((s.warnings, s.passives, s.bus_offs, s.restarts, s.error_frames), (1, 1, 1, 1, 5));
    }

    #[test]
    fn missing_ack_overflow_and_bus_errors() {
        let mut s = ControllerStatus::default();
        // No ACK: CAN_ERR_ACK with the protocol location ACK slot (0x19) in data[3].
        let e = s.apply(&k(0x2000_0028, [0, 0, 0, 0x19, 0, 0, 0, 0]));
        assert!(e.has(Events::NO_ACK) && e.warn());
        assert_eq!(s.no_ack, 1);
        // Controller RX overflow.
        let e = s.apply(&k(0x2000_0004, [0, 0x01, 0, 0, 0, 0, 0, 0]));
        assert!(e.has(Events::RX_OVERFLOW));
        assert_eq!(s.rx_overflows, 1);
        // A single stuff error (PROT | BUSERROR): counted, not worth a warning each.
        let e = s.apply(&k(0x2000_0088, [0, 0, 0x04, 0x0A, 0, 0, 0, 0]));
        assert!(e.has(Events::PROTOCOL) && !e.warn());
        assert_eq!(s.state, CanState::ErrorActive);
        // The no-ACK frame above was a protocol error too (location: ACK slot).
        assert_eq!(s.protocol_errors, 2);
        // Counters stay unknown until a frame carries them.
        assert_eq!(s.tx_errors, None);
        assert!(s.line().starts_with("error-active, tx errors ?, rx errors ?;"), "{}", s.line());
    }

    #[test]
    fn tx_timeout_lost_arbitration_transceiver_tx_overflow_and_an_unspecified_controller_problem() {
        let mut s = ControllerStatus::default();
        assert!(s.apply(&k(0x2000_0001, [0; 8])).has(Events::TX_TIMEOUT));
        // Lost arbitration in bit 5 (data[0]).
        assert!(s.apply(&k(0x2000_0002, [5, 0, 0, 0, 0, 0, 0, 0])).has(Events::LOST_ARBITRATION));
        // Transceiver: CAN-H shorted to ground (CAN_ERR_TRX_CANH_SHORT_TO_GND 0x07).
        assert!(s.apply(&k(0x2000_0010, [0, 0, 0, 0, 0x07, 0, 0, 0])).has(Events::TRANSCEIVER));
        assert!(s.apply(&k(0x2000_0004, [0, 0x02, 0, 0, 0, 0, 0, 0])).has(Events::TX_OVERFLOW));
        // CRTL with no status byte (as socketcand forwards it): counted, the state unchanged.
        assert!(s.apply(&k(0x2000_0004, [0; 8])).is_empty());
        assert_eq!(
            (s.tx_timeouts, s.lost_arbitrations, s.transceiver_errors, s.tx_overflows, s.controller_unspecified, s.error_frames),
            (1, 1, 1, 1, 1, 5)
        );
        assert_eq!(s.state, CanState::ErrorActive);
    }

    #[test]
    fn encode_is_what_decode_reads() {
        let f = ErrorFrame::new(class::BUSOFF, 0, Some((255, 4)));
        let (id, data) = f.encode();
        assert_eq!(id, 0x2000_0240);
        assert_eq!(data, [0, 0, 0, 0, 0, 0, 255, 4]);
        assert_eq!(ErrorFrame::decode(id, &data), f);
        let f = ErrorFrame::new(0, crtl::TX_PASSIVE, None);
        assert_eq!(f.encode().0, 0x2000_0004);
        let t: Vec<_> = Events(Events::BUS_OFF | Events::NO_ACK).texts().collect();
        assert_eq!(t.len(), 2);
        assert!(t[0].starts_with("bus-off"));
    }
}
