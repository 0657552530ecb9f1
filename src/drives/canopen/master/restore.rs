//! A failed start-up leaves every drive as it found it. Application objects (0x6000–0x9FFF)
//! start-up writes are read first and written back; an NMT reset communication of each
//! configured node brings back its communication objects (PDO mapping and COB-IDs valid
//! again, heartbeat and guarding as at power-on); then each node is put back in the NMT
//! state it was heard in before start-up (unknown: pre-operational, where a node boots).

use super::{CanOpenMaster, Sdo};
use crate::drives::DriveBus;
use cncgw_bus::canopen::nmt::{NmtCommand, NmtState};
use cncgw_bus::cia402::cw;
use cncgw_bus::{CanBus, Clock};

/// One object's value before start-up wrote it.
#[derive(Clone, Debug)]
pub(super) struct Undo {
    pub node: usize,
    pub index: u16,
    pub sub: u8,
    pub old: Vec<u8>,
}

/// Objects whose value survives an NMT reset communication (CiA 301: the communication
/// area 0x1000–0x1FFF is reset, the rest is not).
pub(super) fn survives_comm_reset(index: u16) -> bool {
    index >= 0x2000
}

impl<B: CanBus> CanOpenMaster<B> {
    /// Before start-up writes `index:sub` of node `i`: keep its present value (once) to
    /// write back if start-up fails. Objects the drive lacks or will not read are not kept
    /// (the write that follows says what is wrong with them).
    pub(super) fn keep_for_undo(&mut self, clock: &mut dyn Clock, i: usize, index: u16, sub: u8) {
        if !survives_comm_reset(index) || self.undo.as_ref().is_none_or(|u| u.iter().any(|e| e.node == i && e.index == index && e.sub == sub)) {
            return;
        }
        if let Ok(old) = self.sdo(clock, i, Sdo::Up(index, sub)) {
            if let Some(u) = self.undo.as_mut() {
                u.push(Undo { node: i, index, sub, old });
            }
        }
    }

    /// Five cycles under our SYNC with the control words as set (shutdown): enough for a
    /// drive to see them and switch off before the master stops talking or reconfigures.
    pub(super) fn power_off_cycles(&mut self, clock: &mut dyn Clock) {
        for _ in 0..5 {
            let t = clock.now_ns() + self.cycle_ns;
            clock.wait_until(t);
            let now = clock.now_ns();
            let _ = self.receive(now);
            let _ = self.transmit(now);
        }
    }

    /// Leave every drive as start-up found it (see the module doc). `found`: the NMT state
    /// each node was heard in before start-up. Best effort: failures are logged, the alarm
    /// that caused this is what the operator sees.
    pub(super) fn restore(&mut self, clock: &mut dyn Clock, found: &[Option<NmtState>]) {
        let enabled = self.nodes.iter().any(|n| n.enabled || n.controlword != 0);
        self.running = false;
        if enabled {
            // Power off under our SYNC (a few cycles) before anything else.
            for n in &mut self.nodes {
                n.controlword = cw::SHUTDOWN;
                n.target = n.unwrapped;
            }
            self.power_off_cycles(clock);
        }
        for u in self.undo.take().unwrap_or_default().into_iter().rev() {
            if let Err(e) = self.sdo(clock, u.node, Sdo::Down(u.index, u.sub, &u.old)) {
                tracing::warn!(node = self.nodes[u.node].spec.node, "restoring 0x{:04X}:{:02X} failed: {e}", u.index, u.sub);
            }
        }
        // Out of operational first: a reset straight from operational is a lost connection
        // to some drives (0x6007).
        // Only nodes that are there answer a reset with a boot-up.
        let order: Vec<usize> = self.by_node_id().into_iter().filter(|&i| self.nodes[i].booted).collect();
        for &i in &order {
            let node = self.nodes[i].spec.node;
            let _ = self.send(&NmtCommand::EnterPreOperational.frame(node));
            let _ = self.send(&NmtCommand::ResetCommunication.frame(node));
            self.nodes[i].booted = false;
            self.nodes[i].guarding = None;
        }
        self.hb_started = false;
        let end = clock.now_ns() + self.boot_timeout_ms as u64 * 1_000_000;
        while !order.iter().all(|&i| self.nodes[i].booted) && clock.now_ns() < end {
            self.settle(clock, 1);
        }
        for &i in &order {
            let node = self.nodes[i].spec.node;
            let cmd = match found.get(i).copied().flatten() {
                Some(NmtState::Operational) => Some(NmtCommand::Start),
                Some(NmtState::Stopped) => Some(NmtCommand::Stop),
                _ => None,
            };
            if let Some(c) = cmd {
                let _ = self.send(&c.frame(node));
            }
        }
        self.settle(clock, 1);
        tracing::info!("start-up failed: the drives were left as found (objects written back, communication reset, NMT state restored)");
    }
}
