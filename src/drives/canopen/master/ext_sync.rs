//! `bus.sync = "external"` (issue 21 item 6): another device produces SYNC — a drive with
//! 0x1005 bit 30, or a separate SYNC producer — and this master consumes it. The cycle loop
//! wakes on the SYNC received (`cncgw_bus::sync_source`, the clock side); here is the
//! master's side: it sends no SYNC, it counts a drive's unanswered SYNCs from the SYNCs it
//! hears, it checks before start-up that SYNC is there at the cycle's period, and it raises
//! alarm 2022 when SYNC stops for more than `bus.sync_loss_cycles` (the cycle loop then stops
//! the axes under control, on the timer the clock falls back to).

use super::drive_check::SYNC_PRODUCER_BIT;
use super::CanOpenMaster;
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::od;
use cncgw_bus::{CanBus, CanFrame, Clock};

/// What the master knows of the external SYNC.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ExtSync {
    pub on: bool,
    /// No SYNC for longer than this is alarm 2022, ns.
    pub loss_ns: u64,
    pub last_ns: u64,
    pub seen: u64,
    /// Alarm 2022 was raised: once (the stop that follows must not see it again).
    pub reported: bool,
}

impl ExtSync {
    pub fn from_config(cfg: &crate::config::MachineConfig) -> Self {
        ExtSync {
            on: cfg.bus.sync == crate::config::SyncSource::External,
            loss_ns: cfg.cycle_ns().saturating_mul(cfg.bus.sync_loss_cycles as u64),
            last_ns: 0,
            seen: 0,
            reported: false,
        }
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    /// A SYNC heard at `now_ns` (external SYNC: every drive now owes a TPDO).
    pub(super) fn on_sync_heard(&mut self, f: &CanFrame, now_ns: u64) -> bool {
        if !self.ext_sync.on || !cncgw_bus::sync_source::is_sync(f) {
            return false;
        }
        self.ext_sync.last_ns = now_ns;
        self.ext_sync.seen += 1;
        for n in &mut self.nodes {
            n.syncs_unanswered = n.syncs_unanswered.saturating_add(1);
        }
        true
    }

    /// Alarm 2022 when the external SYNC stopped for more than `bus.sync_loss_cycles`.
    pub(super) fn check_sync_loss(&mut self, now_ns: u64) -> Result<(), Alarm> {
        let e = self.ext_sync;
        if !e.on || e.seen == 0 || e.reported {
            return Ok(());
        }
        let gap = now_ns.saturating_sub(e.last_ns);
        if gap <= e.loss_ns {
            return Ok(());
        }
        self.ext_sync.reported = true;
        Err(Alarm::new(
            crate::alarm::SYNC_LOST,
            format!(
                "external SYNC lost on bus {}: none for {:.1} ms (limit {} cycles of {} ms, bus.sync_loss_cycles); the path was stopped under control — without SYNC the drives take no set-point: they hold the last one or stop on their own SYNC watchdog. The SYNC producer (a drive with 0x1005 bit 30, or a separate producer) stopped or is cut off: check it and its cable, then restart",
                self.bus.name(),
                gap as f64 * 1e-6,
                e.loss_ns / self.cycle_ns.max(1),
                self.cycle_ms
            ),
        ))
    }

    /// Before start-up, external SYNC: it must have been heard in the listening window
    /// (`syncs` of them, first and last at the times given), at the cycle's period.
    pub(super) fn check_external_sync_heard(&mut self, syncs: u32, first_ns: u64, last_ns: u64, ms: u64) -> Result<(), Alarm> {
        if syncs == 0 {
            return Err(Alarm::new(
                crate::alarm::SYNC_LOST,
                format!(
                    "bus.sync = \"external\" but no SYNC (COB-ID 0x080) was heard on bus {} within {ms} ms: nothing was reset. Start the SYNC producer (a drive with 0x1005 bit 30 and 0x1006 = {} µs, or a separate producer), or set bus.sync = \"master\"",
                    self.bus.name(),
                    (self.cycle_ms * 1000.0).round()
                ),
            ));
        }
        self.ext_sync.last_ns = last_ns;
        if syncs >= 3 {
            let p = (last_ns - first_ns) as f64 / (syncs - 1) as f64;
            let c = self.cycle_ns as f64;
            if (p - c).abs() > c * 0.1 {
                // A drive producing SYNC gets the cycle's period in 0x1006 during start-up.
                tracing::warn!(
                    "WARNING: external SYNC on bus {} comes every {:.3} ms, the cycle is {} ms (machine.cycle_ms); a SYNC-producing drive gets 0x1006 set to the cycle during start-up, a separate producer must be set to it",
                    self.bus.name(),
                    p * 1e-6,
                    self.cycle_ms
                );
            }
        }
        tracing::info!(bus = self.bus.name(), "external SYNC heard ({syncs} in {ms} ms): the cycle runs on it, this master sends none");
        Ok(())
    }

    /// Start-up of node `i` with an external SYNC: a drive producing SYNC is allowed (it may
    /// be the source) and named.
    pub(super) fn note_sync_producer(&mut self, clock: &mut dyn Clock, i: usize) {
        match self.read_u32(clock, i, od::COB_ID_SYNC, 0) {
            Ok(v) if v & SYNC_PRODUCER_BIT != 0 => tracing::info!(
                node = self.nodes[i].spec.node,
                axis = %self.nodes[i].spec.axis,
                "start-up: the drive produces the SYNC the cycle runs on (0x1005 = 0x{v:08X}); its period 0x1006 is set to the cycle"
            ),
            Ok(_) | Err(SdoError::Abort { .. }) => {}
            Err(e) => tracing::warn!(node = self.nodes[i].spec.node, "reading 0x1005 (COB-ID SYNC) failed: {e}"),
        }
    }
}
