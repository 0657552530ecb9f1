//! The CAN controller's own state (issue 21 item 8): SocketCAN reports error-warning,
//! error-passive, bus-off, restarts, missing ACK and controller overflows as error frames
//! (decoded in `cncgw_bus::can_error`). Each is a warning as it happens; bus-off is alarm
//! 2023 (nothing can be sent: the drives stop by themselves when the master's heartbeat stops).

use super::CanOpenMaster;
use crate::Alarm;
use cncgw_bus::can_error::{CanState, ControllerStatus};
use cncgw_bus::CanBus;

/// Missing ACKs come once per transmit attempt: warn on the first and then every this many.
const NO_ACK_EVERY: u64 = 1000;

impl<B: CanBus> CanOpenMaster<B> {
    /// The controller's state and counters, where the transport reports them.
    pub fn controller(&self) -> Option<ControllerStatus> {
        self.bus.controller()
    }

    /// Report what the controller's error frames said since the last call.
    pub(super) fn watch_controller(&mut self) -> Result<(), Alarm> {
        let Some(c) = self.bus.controller() else { return Ok(()) };
        let last = std::mem::replace(&mut self.ctrl_seen, c);
        if c.error_frames == last.error_frames {
            return Ok(());
        }
        let bus = self.bus.name();
        let warn = |what: &str| tracing::warn!("WARNING: CAN controller on bus {bus}: {what} — {}", c.line());
        if c.warnings > last.warnings {
            warn("error-warning (an error counter passed 96: errors on the bus)");
        }
        if c.passives > last.passives {
            warn("error-passive (an error counter passed 127: it may no longer signal errors; check wiring, termination and bitrate)");
        }
        if c.restarts > last.restarts {
            warn("restarted after bus-off");
        }
        if c.no_ack > last.no_ack && (last.no_ack == 0 || c.no_ack / NO_ACK_EVERY > last.no_ack / NO_ACK_EVERY) {
            warn("no ACK for a frame it sent (no other node on the bus acknowledging: drives powered? cable? termination?)");
        }
        if c.rx_overflows > last.rx_overflows {
            warn("controller RX overflow (received frames were lost)");
        }
        if c.bus_offs > last.bus_offs || (c.state == CanState::BusOff && last.state != CanState::BusOff) {
            return Err(Alarm::new(
                crate::alarm::CAN_BUS_OFF,
                format!(
                    "bus {bus}: the CAN controller went bus-off ({}); nothing can be sent, the drives stop by themselves when the controller's heartbeat stops. Check wiring, termination and bitrate, then restart (a controller without automatic restart: `ip link set {bus} type can restart-ms 100`)",
                    c.line()
                ),
            ));
        }
        Ok(())
    }
}
