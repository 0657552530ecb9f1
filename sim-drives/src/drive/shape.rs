//! The behaviours of `config::Shape`: drives that boot into another mode and switch late,
//! positions in user units (factor group, polarity), a hidden feedback scaling, SYNC
//! produced by the drive itself, node guarding instead of a heartbeat consumer.
//!
//! Position objects (0x607A, 0x6064, 0x6062, 0x60F4, 0x6065, 0x6067, 0x607D) are in the
//! drive's position units; the servo works in encoder increments. Velocity, acceleration and
//! homing objects stay in increments (the velocity factor is not emulated).

use super::{SimDrive, MS};
use cncgw_bus::canopen::nmt::NmtState;
use cncgw_bus::canopen::{cob, od as ix};
use cncgw_bus::cia402::mode;
use cncgw_bus::CanFrame;

/// A mode written to 0x6060 that the drive has not switched to yet.
#[derive(Clone, Copy, Debug)]
pub(super) struct PendingMode {
    pub mode: i8,
    pub due_ns: u64,
    pub syncs_left: u32,
}

/// Node guarding, slave side (CiA 301 §7.2.8.3.1).
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Guarding {
    /// Toggle bit of the next answer.
    pub toggle: bool,
    /// Last guarding request (life guarding runs from the first one).
    pub last_rtr: Option<u64>,
}

/// The factor group's increments per position unit from the dictionary (1 without it).
pub(super) fn increments_per_unit(od: &crate::od::Od) -> f64 {
    let g = |ix: u16, sub: u8| od.get(ix, sub).map(|_| od.int(ix, sub) as f64);
    match (
        g(ix::ENCODER_RESOLUTION, 1),
        g(ix::ENCODER_RESOLUTION, 2),
        g(ix::GEAR_RATIO, 1),
        g(ix::GEAR_RATIO, 2),
        g(ix::FEED_CONSTANT, 1),
        g(ix::FEED_CONSTANT, 2),
    ) {
        (Some(inc), Some(rev), Some(gm), Some(gs), Some(feed), Some(frev)) if rev > 0.0 && gs > 0.0 && feed > 0.0 && frev > 0.0 => {
            let f = inc / rev * gm / gs / (feed / frev);
            if f.is_finite() && f > 0.0 {
                f
            } else {
                1.0
            }
        }
        _ => 1.0,
    }
}

impl SimDrive {
    /// A position (or displacement) in position units → encoder increments.
    pub(super) fn user_to_inc(&self, u: f64) -> f64 {
        u * self.hot.inc_per_unit * self.hot.pos_sign
    }

    /// Encoder increments → position units.
    pub(super) fn inc_to_user(&self, i: f64) -> f64 {
        i / self.hot.inc_per_unit * self.hot.pos_sign
    }

    /// 0x607D in increments (lo, hi), `None` when both are at the type's ends (no limit).
    pub(super) fn software_limits_inc(&self) -> Option<(f64, f64)> {
        let lo = self.od.int(ix::SOFTWARE_LIMIT, 1);
        let hi = self.od.int(ix::SOFTWARE_LIMIT, 2);
        if lo >= hi || (lo == i32::MIN as i64 && hi == i32::MAX as i64) {
            return None;
        }
        let (a, b) = (self.user_to_inc(lo as f64), self.user_to_inc(hi as f64));
        Some((a.min(b), a.max(b)))
    }

    /// 0x6060 written: switch now, or after the shape's delay and SYNCs.
    pub(super) fn request_mode(&mut self, m: i8, now: u64) {
        let sh = &self.cfg.shape;
        if sh.mode_switch_ms <= 0.0 && sh.mode_switch_syncs == 0 {
            self.pending_mode = None;
            self.set_mode(m);
            return;
        }
        if m == self.mode_display() {
            self.pending_mode = None;
            return;
        }
        tracing::info!(
            node = self.cfg.node,
            "mode {} requested: switching in {} ms / {} SYNCs",
            mode::name(m),
            sh.mode_switch_ms,
            sh.mode_switch_syncs
        );
        self.pending_mode =
            Some(PendingMode { mode: m, due_ns: now + (sh.mode_switch_ms * MS as f64).round() as u64, syncs_left: sh.mode_switch_syncs });
    }

    /// A SYNC or a timer: switch to the pending mode once both conditions are met.
    pub(super) fn step_pending_mode(&mut self, now: u64, sync: bool) {
        let Some(p) = self.pending_mode.as_mut() else {
            return;
        };
        if sync {
            p.syncs_left = p.syncs_left.saturating_sub(1);
        }
        if p.syncs_left == 0 && now >= p.due_ns {
            let m = p.mode;
            self.pending_mode = None;
            self.set_mode(m);
        }
    }

    /// When the pending mode's delay ends (a timer), if it is waiting for time.
    pub(super) fn pending_mode_due(&self) -> Option<u64> {
        self.pending_mode.filter(|p| p.syncs_left == 0).map(|p| p.due_ns)
    }

    /// SYNC producer (0x1005 bit 30 and a period in 0x1006): when the next SYNC is due.
    pub(super) fn next_own_sync(&self) -> Option<u64> {
        self.own_sync_next.filter(|_| self.produces_sync())
    }

    pub(super) fn produces_sync(&self) -> bool {
        let c = self.od.int(ix::COB_ID_SYNC, 0) as u32;
        c & 0x4000_0000 != 0
            && self.od.int(ix::COMM_CYCLE_PERIOD, 0) > 0
            && self.od.int(super::SIM_FAULTS, super::fault_sub::SYNC_MUTED) == 0
            && matches!(self.nmt, NmtState::PreOperational | NmtState::Operational)
    }

    /// Produce a SYNC when due (and act on it, as every SYNC consumer on the bus does).
    pub(super) fn own_sync(&mut self, now: u64) {
        if !self.produces_sync() {
            self.own_sync_next = None;
            return;
        }
        let period = self.od.int(ix::COMM_CYCLE_PERIOD, 0) as u64 * 1000;
        match self.own_sync_next {
            None => self.own_sync_next = Some(now + period),
            Some(t) if now >= t => {
                self.out.push(CanFrame::new((self.od.int(ix::COB_ID_SYNC, 0) & 0x7FF) as u16, &[]));
                self.on_sync(now);
                self.own_sync_next = Some(t + period * ((now - t) / period + 1));
            }
            Some(_) => {}
        }
    }

    /// A remote frame: a node-guarding request on 0x700 + node is answered with the NMT state
    /// and the toggle bit.
    pub(super) fn remote_frame(&mut self, f: &CanFrame, now: u64) {
        if !self.cfg.shape.node_guarding || f.cob_id() != cob::HEARTBEAT + self.cfg.node as u16 || self.nmt == NmtState::BootUp {
            return;
        }
        let b = self.nmt as u8 | (self.guarding.toggle as u8) << 7;
        self.guarding.toggle = !self.guarding.toggle;
        self.guarding.last_rtr = Some(now);
        self.out.push(CanFrame::new(f.cob_id(), &[b]));
    }

    /// Life time: 0x100C guard time × 0x100D life time factor (0 = no life guarding).
    fn life_time_ns(&self) -> u64 {
        if !self.cfg.shape.node_guarding {
            return 0;
        }
        self.od.int(ix::GUARD_TIME, 0) as u64 * self.od.int(ix::LIFE_TIME_FACTOR, 0) as u64 * MS
    }

    /// When life guarding fires if no request comes.
    pub(super) fn life_guard_due(&self) -> Option<u64> {
        let life = self.life_time_ns();
        (life > 0).then_some(()).and(self.guarding.last_rtr).map(|t| t + life)
    }

    /// Life guarding event: the master stopped guarding (CiA 301: the 0x6007 action, as a
    /// heartbeat timeout). Monitoring stops until the next request.
    pub(super) fn check_life_guarding(&mut self, now: u64) {
        if let Some(due) = self.life_guard_due() {
            if now >= due && self.nmt != NmtState::BootUp {
                self.guarding.last_rtr = None;
                tracing::warn!(node = self.cfg.node, "life guarding: no guarding request within the life time");
                self.communication_error(0x8130, now);
            }
        }
    }

    /// Whether 0x6060 may take `m`.
    pub(super) fn mode_allowed(&self, m: i64) -> bool {
        m == 0 || self.cfg.shape.modes.iter().any(|&x| x as i64 == m)
    }
}
