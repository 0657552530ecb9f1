//! Interpolated position (CiA 402 mode 7) for drives without CSP (`axes.NAME.mode = "ip"`).
//!
//! Set up as CiA 402 §12 describes it, in pre-operational: sub-mode 0x60C0 = 0 (linear
//! interpolation, the only one the standard defines), the interpolation period 0x60C2 = the
//! cycle (written with CSP's), the buffer 0x60C4:6 cleared (0) and enabled (1) where the
//! drive has one, set-points into 0x60C1:1 by RPDO1. Once the drive is Operation Enabled the
//! master sets controlword bit 4 ("enable ip mode") in every RPDO1 and waits for statusword
//! bit 12 ("ip mode active") before it calls the drive enabled; bit 12 dropping while
//! running is alarm 2005, as a mode left behind the master's back. The set-points are the
//! same as CSP's (one per SYNC, the position at the end of the period): the drive
//! interpolates linearly over 0x60C2.

use super::explain::is_absent;
use super::CanOpenMaster;
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::od;
use cncgw_bus::cia402::{cw, sw, State};
use cncgw_bus::{CanBus, Clock};

/// Consecutive TPDO1s in Operation Enabled without "ip mode active" before alarm 2005 (one
/// frame is a glitch the stale-feedback logic covers).
pub(super) const IP_INACTIVE_ALARM: u32 = 3;

impl<B: CanBus> CanOpenMaster<B> {
    /// Start-up, IP axes: sub-mode linear, buffer cleared and enabled (each where present).
    pub(super) fn configure_ip(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let node = self.nodes[i].spec.node;
        let sub_mode = 0i16.to_le_bytes();
        match self.try_write(clock, i, od::INTERPOLATION_SUB_MODE, 0, &sub_mode) {
            Ok(()) => {}
            Err(SdoError::Abort { code }) if is_absent(code) => {
                tracing::info!(node, "no 0x60C0 (interpolation sub-mode): the drive interpolates linearly, the only sub-mode CiA 402 defines")
            }
            Err(e) => return Err(self.write_alarm(i, od::INTERPOLATION_SUB_MODE, 0, &sub_mode, &e)),
        }
        // 0 clears the buffer and disables access, 1 enables it (CiA 402 0x60C4:6).
        for v in [0u8, 1] {
            match self.try_write(clock, i, od::INTERPOLATION_BUFFER, 6, &[v]) {
                Ok(()) => {}
                Err(SdoError::Abort { code }) if is_absent(code) => {
                    tracing::info!(node, "no 0x60C4 (interpolation buffer): one set-point per SYNC, nothing to clear");
                    break;
                }
                Err(e) => return Err(self.write_alarm(i, od::INTERPOLATION_BUFFER, 6, &[v], &e)),
            }
        }
        Ok(())
    }

    /// The controlword node `i` gets in RPDO1: in IP, bit 4 (enable ip mode) on top of
    /// Enable Operation once the drive is enabled in IP.
    pub(super) fn cyclic_controlword(&self, i: usize) -> u16 {
        let n = &self.nodes[i];
        let c = n.controlword;
        if n.spec.ip && n.enabled && c == cw::ENABLE_OPERATION_CMD && n.mode.want == n.spec.position_mode() && n.mode.ok() {
            c | cw::OMS4
        } else {
            c
        }
    }

    /// In `enable_step`: an enabled IP drive shows "ip mode active" (statusword bit 12).
    pub(super) fn ip_active(&self, i: usize) -> bool {
        let n = &self.nodes[i];
        !n.spec.ip || n.mode.want != n.spec.position_mode() || n.status & sw::OMS12 != 0
    }

    /// Per TPDO1 of an IP drive: count frames in Operation Enabled without bit 12.
    pub(super) fn note_ip_status(&mut self, i: usize) {
        let n = &mut self.nodes[i];
        // Only once bit 4 has been out long enough to show in a statusword (after a profile
        // move or homing the drive comes back to IP with bit 4 sent anew).
        let watch = n.spec.ip && n.ip_sent > super::FRESH_STATUS_CYCLES && n.mode.want == n.spec.position_mode() && n.mode.ok();
        let inactive = watch && State::from_statusword(n.status) == State::OperationEnabled && n.status & sw::OMS12 == 0;
        n.ip_inactive = if inactive { n.ip_inactive.saturating_add(1) } else { 0 };
    }
}
