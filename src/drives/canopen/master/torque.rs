//! A spindle drive's torque actual value (0x6077, CiA 402: per mille of the rated torque
//! 0x6076), the spindle's load for observers (the OPC UA server's `Spindle1/Load`).
//!
//! Read by SDO every [`POLL_EVERY_NS`] while running, not mapped: TPDO1 has no room left
//! (statusword, position actual, mode display: 7 of 8 bytes), and a load shown ten times a
//! second needs no PDO of its own. A spindle drive that gives its torque limit (max torque
//! 0x6072, read at start-up) is read every other cycle instead: the torque margin
//! (`sync::torque_margin`) must see a tap's ramp at the limit within its first tens of ms.
//! The poll runs in `receive` as the mode poll does (`mode_track`): expedited answers only,
//! no allocation, never waiting; it yields the SDO channel to the fault diagnosis and to the
//! mode poll. A drive that answers with an abort
//! (no 0x6077) is not asked again.

use super::CanOpenMaster;
use crate::Alarm;
use cncgw_bus::CanBus;

/// How often 0x6077 is read from a spindle drive.
pub(super) const POLL_EVERY_NS: u64 = 100_000_000;

/// Torque actual.
pub const TORQUE_ACTUAL: u16 = cncgw_bus::canopen::od::TORQUE_ACTUAL;

/// The poll of one drive.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct TorquePoll {
    /// The last value read, per mille of the rated torque.
    pub value: Option<i16>,
    pub next_ns: u64,
    /// A read is under way.
    pub polling: bool,
    /// The drive answered with an abort: not asked again.
    pub absent: bool,
    /// Max torque 0x6072 (per mille of the rated torque) as read at start-up, if the drive
    /// has it.
    pub max: Option<u16>,
}

impl<B: CanBus> CanOpenMaster<B> {
    /// In `receive`: read 0x6077 from spindle drives while running, and every cycle from a
    /// feed axis with friction feed-forward (its fit learns from it). Allocation-free.
    pub(super) fn poll_torque(&mut self, now_ns: u64) -> Result<(), Alarm> {
        if !self.running || self.diag.is_some() {
            return Ok(());
        }
        for i in 0..self.nodes.len() {
            let n = &mut self.nodes[i];
            let learn = n.friction.is_some();
            if !(n.spec.spindle || learn) || n.torque.absent || n.mode.polling {
                continue;
            }
            if n.torque.polling {
                let out = n.sdo.poll(now_ns);
                if let Some(r) = n.sdo.take_expedited() {
                    n.torque.polling = false;
                    match r {
                        Ok(v) => {
                            n.torque.value = Some(v as u16 as i16);
                            if let Some(f) = n.friction.as_mut() {
                                f.torque_sample(v as u16 as i16);
                            }
                        }
                        Err(super::SdoError::Abort { .. }) => {
                            n.torque.absent = true;
                            if learn {
                                tracing::warn!(
                                    node = n.spec.node,
                                    "the drive has no torque actual 0x6077: friction feed-forward cannot learn and stays 0"
                                );
                            }
                        }
                        Err(_) => {}
                    }
                }
                if let Some(f) = out {
                    self.send(&f)?;
                }
            } else if now_ns >= n.torque.next_ns && !n.sdo.busy() {
                n.torque.polling = true;
                n.torque.next_ns = if learn || n.torque.max.is_some() { now_ns } else { now_ns + POLL_EVERY_NS };
                let f = n.sdo.start_upload_small(TORQUE_ACTUAL, 0, now_ns);
                self.send(&f)?;
            }
        }
        Ok(())
    }
}
