//! NMT commands (COB-ID 0) and heartbeat / boot-up messages (0x700 + node).

use super::cob;
use crate::CanFrame;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NmtCommand {
    Start = 0x01,
    Stop = 0x02,
    EnterPreOperational = 0x80,
    ResetNode = 0x81,
    ResetCommunication = 0x82,
}

impl NmtCommand {
    pub fn from_cs(cs: u8) -> Option<Self> {
        Some(match cs {
            0x01 => Self::Start,
            0x02 => Self::Stop,
            0x80 => Self::EnterPreOperational,
            0x81 => Self::ResetNode,
            0x82 => Self::ResetCommunication,
            _ => return None,
        })
    }

    /// The NMT frame for `node` (0 = all nodes).
    pub fn frame(self, node: u8) -> CanFrame {
        CanFrame::new(cob::NMT, &[self as u8, node])
    }

    /// Decode an NMT frame into (command, addressed node; 0 = broadcast).
    pub fn decode(f: &CanFrame) -> Option<(Self, u8)> {
        if f.cob_id() != cob::NMT || f.len != 2 || f.rtr {
            return None;
        }
        Some((Self::from_cs(f.data[0])?, f.data[1]))
    }
}

/// NMT state as reported in heartbeat messages (CiA 301 §7.2.8.3.2.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NmtState {
    BootUp = 0x00,
    Stopped = 0x04,
    Operational = 0x05,
    PreOperational = 0x7F,
}

impl NmtState {
    pub fn from_byte(b: u8) -> Option<Self> {
        Some(match b & 0x7F {
            0x00 => Self::BootUp,
            0x04 => Self::Stopped,
            0x05 => Self::Operational,
            0x7F => Self::PreOperational,
            _ => return None,
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::BootUp => "boot-up",
            Self::Stopped => "stopped",
            Self::Operational => "operational",
            Self::PreOperational => "pre-operational",
        }
    }
}

/// A heartbeat (or, with `BootUp`, the boot-up message) from `node`.
pub fn heartbeat_frame(node: u8, state: NmtState) -> CanFrame {
    CanFrame::new(cob::HEARTBEAT + node as u16, &[state as u8])
}

/// Decode a heartbeat / boot-up frame into (node, state).
pub fn decode_heartbeat(f: &CanFrame) -> Option<(u8, NmtState)> {
    let (func, node) = cob::split(f.cob_id());
    if func != cob::HEARTBEAT || node == 0 || f.len != 1 || f.rtr {
        return None;
    }
    Some((node, NmtState::from_byte(f.data[0])?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nmt_frames_are_byte_exact() {
        assert_eq!(format!("{:?}", NmtCommand::Start.frame(3)), "000#0103");
        assert_eq!(format!("{:?}", NmtCommand::ResetCommunication.frame(0)), "000#8200");
        assert_eq!(NmtCommand::decode(&NmtCommand::EnterPreOperational.frame(5)), Some((NmtCommand::EnterPreOperational, 5)));
        assert_eq!(NmtCommand::decode(&CanFrame::new(0, &[0x55, 1])), None);
    }

    #[test]
    fn heartbeat_and_boot_up() {
        assert_eq!(format!("{:?}", heartbeat_frame(2, NmtState::BootUp)), "702#00");
        assert_eq!(format!("{:?}", heartbeat_frame(2, NmtState::Operational)), "702#05");
        assert_eq!(decode_heartbeat(&CanFrame::new(0x77F, &[0x7F])), Some((0x7F, NmtState::PreOperational)));
        assert_eq!(decode_heartbeat(&CanFrame::new(0x181, &[0x05])), None);
    }
}
