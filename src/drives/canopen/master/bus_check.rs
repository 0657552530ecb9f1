//! Before the NMT reset: listen to the bus for another master. A second master (a second
//! `cncgw run` on the same bus, a PLC, a service tool on another PC) shows by its SYNC, its
//! heartbeat (0x700 + 0x7F, cncgw's master id), NMT commands, set-points (RPDOs) or SDO
//! requests to the configured drives. Any of them is an alarm naming what was heard, and
//! nothing is reset: resetting would knock the other master's machine out mid-cut. A SYNC
//! alone may come from one of the configured drives (0x1005 bit 30): it is asked which.

use super::drive_check::{fmt_num, ALARM_FOREIGN, SYNC_PRODUCER_BIT};
use super::{CanOpenMaster, MASTER_NODE_ID, POLL_NS};
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::nmt::{NmtCommand, NmtState};
use cncgw_bus::canopen::{cob, od};
use cncgw_bus::{CanBus, CanFrame, Clock};

/// What was heard in the listening window that only a master sends.
#[derive(Debug, Default)]
pub(super) struct Heard {
    pub syncs: u32,
    first_sync_ns: u64,
    last_sync_ns: u64,
    /// The first master-only frame heard, in words.
    pub master: Option<String>,
}

impl Heard {
    /// Note `f` (heard at `now`) if only a master (or a SYNC producer) sends it.
    fn note<B: CanBus>(&mut self, m: &CanOpenMaster<B>, f: &CanFrame, now: u64) {
        if f.extended {
            return;
        }
        let id = f.cob_id();
        let (func, node) = cob::split(id);
        if id == cob::SYNC && !f.rtr && f.len <= 1 {
            if self.syncs == 0 {
                self.first_sync_ns = now;
            }
            self.syncs += 1;
            self.last_sync_ns = now;
            return;
        }
        if self.master.is_some() {
            return;
        }
        self.master = if id == cob::HEARTBEAT + MASTER_NODE_ID as u16 && !f.rtr {
            Some(format!("a master heartbeat (COB-ID 0x{id:03X}, node {MASTER_NODE_ID} — another cncgw?)"))
        } else if id == cob::NMT {
            let what =
                NmtCommand::decode(f).map(|(c, n)| format!("{c:?} for {}", if n == 0 { "every node".to_string() } else { format!("node {n}") }));
            Some(format!("an NMT command ({})", what.unwrap_or_else(|| "undecoded".into())))
        } else if f.rtr && func == cob::HEARTBEAT {
            Some(format!("a node-guarding request to node {node}"))
        } else if let Some(n) = m.nodes.iter().find(|n| n.spec.rpdo_cob == id) {
            Some(format!("set-points for node {} (RPDO COB-ID 0x{id:03X})", n.spec.node))
        } else if func == cob::SDO_RX && m.index_of(node).is_some() {
            Some(format!("SDO requests to node {node} (COB-ID 0x{id:03X})"))
        } else {
            None
        };
    }

    fn sync_period_text(&self) -> String {
        if self.syncs >= 2 {
            let p = (self.last_sync_ns - self.first_sync_ns) as f64 / (self.syncs - 1) as f64 * 1e-6;
            format!(" every ≈ {} ms", fmt_num((p * 10.0).round() / 10.0))
        } else {
            String::new()
        }
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    /// How long start-up listens before its NMT reset: long enough for a SYNC and
    /// set-points at any cycle, and for a master heartbeat of this machine's period.
    pub(super) fn listen_window_ms(&self) -> u64 {
        (self.hb_ms as u64 * 6 / 5).clamp(50, 2000)
    }

    /// Listen for `listen_window_ms` without sending anything; Err: another master (or a
    /// SYNC-producing drive) is on the bus. Ok: the NMT states heard per node (for leaving
    /// the drives as they were if start-up fails).
    pub(super) fn check_bus_free(&mut self, clock: &mut dyn Clock) -> Result<Vec<Option<NmtState>>, Alarm> {
        let ms = self.listen_window_ms();
        let end = clock.now_ns() + ms * 1_000_000;
        let mut heard = Heard::default();
        while clock.now_ns() < end {
            let t = clock.now_ns() + POLL_NS;
            clock.wait_until(t);
            let now = clock.now_ns();
            loop {
                match self.bus.try_recv() {
                    Ok(Some(f)) => {
                        heard.note(self, &f, now);
                        self.on_background(&f, now);
                    }
                    Ok(None) => break,
                    Err(e) => return Err(self.bus_alarm(e)),
                }
            }
        }
        let bus = self.bus.name().to_string();
        if let Some(what) = &heard.master {
            return Err(Alarm::new(
                ALARM_FOREIGN,
                format!(
                    "another CANopen master is active on bus {bus}: heard {what} within {ms} ms before start-up. Nothing was reset; stop the other master (a second cncgw, a PLC, a service tool) before starting this one"
                ),
            ));
        }
        if self.ext_sync.on {
            self.check_external_sync_heard(heard.syncs, heard.first_sync_ns, heard.last_sync_ns, ms)?;
        } else if heard.syncs > 0 {
            return Err(self.foreign_sync_alarm(clock, &heard, ms));
        }
        Ok(self.nodes.iter().map(|n| n.nmt.map(|s| if s == NmtState::BootUp { NmtState::PreOperational } else { s })).collect())
    }

    /// SYNC was heard and nothing else of a master: which configured drive produces it?
    fn foreign_sync_alarm(&mut self, clock: &mut dyn Clock, heard: &Heard, ms: u64) -> Alarm {
        let mut asked = Vec::new();
        for i in self.by_node_id() {
            match self.read_u32(clock, i, od::COB_ID_SYNC, 0) {
                Ok(v) if v & SYNC_PRODUCER_BIT != 0 => {
                    let mut a = self.sync_producer_alarm(clock, i, v);
                    a.message.push_str("; nothing was reset");
                    return a;
                }
                Ok(_) => asked.push(format!("{}", self.nodes[i].spec.node)),
                Err(SdoError::Abort { .. }) => asked.push(format!("{}", self.nodes[i].spec.node)),
                Err(e) => asked.push(format!("{} (no answer: {e})", self.nodes[i].spec.node)),
            }
        }
        Alarm::new(
            ALARM_FOREIGN,
            format!(
                "SYNC (COB-ID 0x080){} is on bus {} from a device that is not one of the configured drives (0x1005 bit 30 clear on nodes {}): another master? Nothing was reset; stop it before starting this one (heard {} SYNCs in {ms} ms)",
                heard.sync_period_text(),
                self.bus.name(),
                asked.join(", "),
                heard.syncs
            ),
        )
    }
}
