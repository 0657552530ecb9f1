//! The master's side of error control (CiA 301 §7.2.8.3): its heartbeat, which the drives
//! consume (0x1016), and node guarding for drives without a heartbeat consumer (the
//! Technosoft iPOS has no 0x1016): a remote frame on 0x700 + node every guard time
//! (0x100C), answered by the node; the node faults by itself (life guarding, 0x6007) when
//! the requests stop for guard time × life time factor (0x100D). The answers count as that
//! node's heartbeat for the master's own monitoring (alarm 2011).

use super::{CanOpenMaster, MASTER_NODE_ID};
use crate::Alarm;
use cncgw_bus::canopen::cob;
use cncgw_bus::canopen::nmt::{heartbeat_frame, NmtState};
use cncgw_bus::{CanBus, CanFrame};

/// Node guarding of one node by the master.
#[derive(Clone, Copy, Debug)]
pub(super) struct Guarding {
    pub period_ns: u64,
    pub next_ns: u64,
}

/// The next instant of a periodic event due at `due` with `period`, after it fired at `now`:
/// on the grid of `due`, so that firing from late cycles does not stretch the period (a
/// 100 ms heartbeat sent from 2 ms cycles ran at 101.9 ms when measured from each late send).
pub(super) fn next_on_grid(due: u64, period: u64, now: u64) -> u64 {
    let next = due.saturating_add(period);
    if next > now {
        next
    } else {
        // More than a period late (a stalled process): pick up the grid after now.
        now + period - (now - due) % period.max(1)
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    /// Send the master heartbeat and the guarding requests that are due. Called from every
    /// wait, not only from the cyclic phase: a drive configured early in start-up consumes
    /// them while the others are still being configured. Allocation-free.
    pub(super) fn tick_life(&mut self, now_ns: u64) -> Result<(), Alarm> {
        if self.hb_ms > 0 && self.hb_started && now_ns >= self.next_hb_ns {
            self.send(&heartbeat_frame(MASTER_NODE_ID, NmtState::Operational))?;
            self.next_hb_ns = next_on_grid(self.next_hb_ns, self.hb_ms as u64 * 1_000_000, now_ns);
        }
        for i in 0..self.nodes.len() {
            let Some(g) = self.nodes[i].guarding else {
                continue;
            };
            if now_ns >= g.next_ns {
                let f = CanFrame { id: (cob::HEARTBEAT + self.nodes[i].spec.node as u16) as u32, extended: false, rtr: true, len: 1, data: [0; 8] };
                self.send(&f)?;
                if let Some(g) = self.nodes[i].guarding.as_mut() {
                    g.next_ns = next_on_grid(g.next_ns, g.period_ns, now_ns);
                }
            }
        }
        Ok(())
    }

    /// At exit: guarded drives stop expecting guarding requests (0x100C = 0: no life
    /// guarding) before the master goes silent, as heartbeat consumers get 0x1016 cleared.
    pub(super) fn stop_guarding(&mut self, clock: &mut dyn cncgw_bus::Clock) {
        for i in 0..self.nodes.len() {
            if self.nodes[i].guarding.take().is_some() {
                if let Err(e) = self.sdo(clock, i, super::Sdo::Down(cncgw_bus::canopen::od::GUARD_TIME, 0, &0u16.to_le_bytes())) {
                    tracing::warn!(node = self.nodes[i].spec.node, "switching life guarding off (0x100C = 0) failed: {e}");
                }
            }
        }
    }

    /// Start guarding node `i` every `period_ms` (after 0x100C / 0x100D were written).
    pub(super) fn start_guarding(&mut self, i: usize, period_ms: u16, now_ns: u64) {
        self.nodes[i].guarding = Some(Guarding { period_ns: period_ms as u64 * 1_000_000, next_ns: now_ns });
        // Its answers are its heartbeat from now on.
        self.nodes[i].last_hb_ns = now_ns.max(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_events_stay_on_their_grid() {
        const MS: u64 = 1_000_000;
        // Due at 100, seen at 102 (a 3 ms cycle): next due at 200, not 202.
        assert_eq!(next_on_grid(100 * MS, 100 * MS, 102 * MS), 200 * MS);
        // Stalled for 250 ms: the next point of the grid after now.
        assert_eq!(next_on_grid(100 * MS, 100 * MS, 350 * MS), 400 * MS);
        assert_eq!(next_on_grid(100 * MS, 100 * MS, 300 * MS), 400 * MS);
    }
}
