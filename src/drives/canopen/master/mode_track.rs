//! The drive's mode of operation as it reports it (0x6061, modes of operation display), not
//! as the master asked for it (0x6060): no drive is enabled before it shows the mode asked
//! for, and no set-point goes to a drive whose reported mode does not take it.
//!
//! **0x6061 is mapped into TPDO1** (statusword, position actual, mode display: 7 bytes)
//! rather than polled: a mode change while running (the drive's own panel, its fault logic,
//! another tool's SDO) is then seen in the cycle it happens, before the next set-point, and
//! costs one byte per drive per cycle (≈ 0.4 % of a 1 Mbit/s bus at 2 ms for three drives);
//! a poll by SDO would see it only every few cycles and compete with the fault diagnosis for
//! the SDO channel. A drive that cannot map 0x6061 (a restricted mapping) falls back to an
//! SDO poll every `POLL_EVERY_NS`, allocation-free in the cycle (expedited answers only).

use super::drive_check::ALARM_MODE;
use super::explain::mode_words;
use super::CanOpenMaster;
use crate::Alarm;
use cncgw_bus::canopen::od;
use cncgw_bus::{CanBus, Clock};

/// How often 0x6061 is read by SDO from a drive that cannot map it.
pub(super) const POLL_EVERY_NS: u64 = 20_000_000;
/// How long a drive may take to show a mode it was asked for. Drives that switch only
/// between two SYNCs or after an internal delay take tens to hundreds of ms.
pub const MODE_TIMEOUT_MS: u64 = 2000;

/// The mode of one drive.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ModeTrack {
    /// What the master asked for (0x6060); 0 = nothing yet.
    pub want: i8,
    /// The last 0x6061 heard (TPDO or SDO poll).
    pub shown: Option<i8>,
    /// 0x6061 travels in TPDO1; else it is polled by SDO.
    pub in_pdo: bool,
    /// Next SDO poll (poll mode), and whether one is under way.
    pub poll_next_ns: u64,
    pub polling: bool,
    /// The drive has shown `want` since it was asked for it: from then on another mode is
    /// a change behind the master's back (alarm 2005 while running).
    pub confirmed: bool,
    /// A TPDO with another mode than the confirmed one, waiting for the next to agree.
    pub odd_frames: u8,
}

impl ModeTrack {
    /// The drive shows the mode the master asked for (or the master asked for none: a
    /// service tool's session without start-up).
    pub fn ok(&self) -> bool {
        self.want == 0 || self.shown == Some(self.want)
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    /// Ask node `i` for mode `m` (0x6060) and wait, running the cycle (SYNC, held targets),
    /// until it shows it in 0x6061; alarm 2005 naming the mode it shows after
    /// `MODE_TIMEOUT_MS`.
    pub(super) fn change_mode(&mut self, clock: &mut dyn Clock, i: usize, m: i8) -> Result<(), Alarm> {
        self.nodes[i].mode.want = m;
        self.nodes[i].mode.confirmed = false;
        self.write(clock, i, od::MODES_OF_OPERATION, 0, &[m as u8])?;
        self.wait_modes(clock, &[i])
    }

    /// Run the cycle until every node of `which` shows its wanted mode.
    pub(super) fn wait_modes(&mut self, clock: &mut dyn Clock, which: &[usize]) -> Result<(), Alarm> {
        if which.iter().all(|&i| self.nodes[i].mode.ok()) {
            return Ok(());
        }
        let done = self.run_cycles(clock, MODE_TIMEOUT_MS * 1_000_000, |m| Ok(which.iter().all(|&i| m.nodes[i].mode.ok())))?;
        if done {
            return Ok(());
        }
        let i = which.iter().copied().find(|&i| !self.nodes[i].mode.ok()).unwrap_or(0);
        let t = self.nodes[i].mode;
        let shown = match t.shown {
            Some(s) => format!("it still reports {} in 0x6061", mode_words(s)),
            None => "its mode display 0x6061 was never heard (no TPDO1 and no answer to reading it)".into(),
        };
        Err(self.node_alarm(
            i,
            ALARM_MODE,
            format!(
                "asked for {} (0x6060), {shown} after {MODE_TIMEOUT_MS} ms; nothing was enabled. Check the drive's mode settings (some drives take the mode only from their own configuration, or only in a given state)",
                mode_words(t.want)
            ),
        ))
    }

    /// In `receive`, per node: a TPDO1 of the wrong length that persists (alarm 2018, naming
    /// both lengths), and a drive that left its confirmed mode while running (alarm 2005).
    /// Allocation-free until it raises the alarm.
    pub(super) fn check_tpdo_and_mode(&mut self, i: usize) -> Option<Alarm> {
        let n = &mut self.nodes[i];
        if !n.mode.confirmed && n.mode.want != 0 && n.mode.ok() {
            n.mode.confirmed = true;
        }
        if n.bad_len >= super::BAD_LEN_ALARM {
            let (cob, got, total) = (n.spec.tpdo_cob, n.bad_len_last, n.bad_len_total);
            let want = n.tpdo_len.map_or("at least 6".to_string(), |l| l.to_string());
            let mapped = if n.mode.in_pdo {
                "0x6041 statusword, 0x6064 position actual, 0x6061 mode display"
            } else {
                "0x6041 statusword, 0x6064 position actual"
            };
            return Some(self.node_fault(
                i,
                crate::alarm::TPDO_LENGTH,
                format!(
                    "TPDO1 (COB-ID 0x{cob:03X}) arrives with {got} bytes, start-up mapped {want} ({mapped}): the drive did not take the mapping, or another device sends on this COB-ID; {total} frame(s) of the wrong length so far. Check the drive's PDO configuration (axes.NAME.tpdo_cob_id)"
                ),
            ));
        }
        let n = &self.nodes[i];
        if self.running && n.mode.confirmed && !n.mode.ok() {
            let (want, shown) = (n.mode.want, n.mode.shown.unwrap_or(0));
            return Some(self.node_fault(
                i,
                ALARM_MODE,
                format!(
                    "the drive left {} for {} (0x6061) while running; its set-points were stopped. Something else changed its mode: its own panel, a service tool, its fault logic",
                    mode_words(want),
                    mode_words(shown)
                ),
            ));
        }
        None
    }

    /// In `receive`: poll 0x6061 by SDO from drives that cannot map it. Allocation-free.
    pub(super) fn poll_modes(&mut self, now_ns: u64) -> Result<(), Alarm> {
        let diag_node = self.diag.as_ref().map(|d| d.node);
        for i in 0..self.nodes.len() {
            let n = &mut self.nodes[i];
            if n.mode.in_pdo || n.mode.want == 0 || diag_node == Some(i) {
                continue;
            }
            if n.mode.polling {
                let out = n.sdo.poll(now_ns);
                if let Some(r) = n.sdo.take_expedited() {
                    n.mode.polling = false;
                    if let Ok(v) = r {
                        n.mode.shown = Some(v as u8 as i8);
                    }
                }
                if let Some(f) = out {
                    self.send(&f)?;
                }
            } else if now_ns >= n.mode.poll_next_ns && !n.sdo.busy() {
                n.mode.polling = true;
                n.mode.poll_next_ns = now_ns + POLL_EVERY_NS;
                let f = n.sdo.start_upload_small(od::MODES_DISPLAY, 0, now_ns);
                self.send(&f)?;
            }
        }
        Ok(())
    }
}
