//! CiA 401 I/O modules on the drives' bus (`[io.devices.*] canopen_node`).
//!
//! Start-up (after the drives are configured, before the NMT start that covers every node):
//! the module's boot-up after the reset communication, device type 0x1000 = 401, then its
//! PDOs mapped by the master as for a drive: TPDO1 (0x180 + node) = the digital inputs
//! 0x6000:01… (8 bits per sub-index), transmission type 1 (every SYNC: its silence is
//! measurable like a drive's), RPDO1 (0x200 + node) = the outputs 0x6200:01…, transmission
//! type 255 (applied on receipt). Every cycle `transmit` sends the outputs before SYNC and
//! `receive` takes the inputs; a module that answers no SYNC for `bus.feedback_timeout_ms`
//! is alarm 2603 (the cycle loop cannot tell an E-stop chain from a module that is gone).

use super::{le_u32, CanOpenMaster};
use crate::drives::canopen::sdo_client::{SdoClient, SdoError};
use crate::Alarm;
use cncgw_bus::canopen::nmt::{decode_heartbeat, NmtState};
use cncgw_bus::canopen::pdo::MapEntry;
use cncgw_bus::canopen::{cob, od};
use cncgw_bus::{CanBus, CanFrame, Clock};

/// CiA 401 objects.
const DIGITAL_INPUTS: u16 = 0x6000;
const DIGITAL_OUTPUTS: u16 = 0x6200;

pub(super) struct IoModule {
    node: u8,
    sdo: SdoClient,
    in_bytes: u8,
    out_bytes: u8,
    booted: bool,
    inputs: u32,
    have_in: bool,
    in_ns: u64,
    syncs_unanswered: u32,
    outputs: u32,
    /// Configured and started: its silence is an alarm.
    running: bool,
}

impl IoModule {
    /// Its SDO client and node id, for the master's blocking transfers.
    pub(super) fn sdo_channel(&mut self) -> (&mut SdoClient, u8) {
        (&mut self.sdo, self.node)
    }

    pub(super) fn new(node: u8, inputs: u8, outputs: u8, sdo_timeout_ms: u32) -> IoModule {
        IoModule {
            node,
            sdo: SdoClient::new(node, sdo_timeout_ms),
            in_bytes: pdo_bytes(inputs),
            out_bytes: pdo_bytes(outputs),
            booted: false,
            inputs: 0,
            have_in: false,
            in_ns: 0,
            syncs_unanswered: 0,
            outputs: 0,
            running: false,
        }
    }
}

/// Bytes of a module's PDO for `bits` inputs or outputs (8 per sub-index of 0x6000/0x6200).
pub(crate) fn pdo_bytes(bits: u8) -> u8 {
    bits.div_ceil(8).clamp(1, 4)
}

impl IoModule {
    pub(super) fn clear_outputs(&mut self) {
        self.outputs = 0;
    }

    /// Its cyclic frames' data lengths: outputs (RPDO1) and inputs (TPDO1).
    pub(super) fn pdo_lens(&self) -> [usize; 2] {
        [self.out_bytes as usize, self.in_bytes as usize]
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    /// A frame of an I/O module (boot-up, heartbeat, TPDO1, EMCY): handled, true.
    pub(super) fn io_frame(&mut self, f: &CanFrame, now_ns: u64) -> bool {
        let (func, node) = cob::split(f.cob_id());
        let Some(m) = self.io.iter_mut().find(|m| m.node == node) else { return false };
        if let Some((_, st)) = decode_heartbeat(f) {
            if st == NmtState::BootUp {
                m.booted = true;
                m.have_in = false;
            }
            return true;
        }
        if func == cob::TPDO1 && f.len as usize >= m.in_bytes as usize {
            let mut b = [0u8; 4];
            b[..m.in_bytes as usize].copy_from_slice(&f.data[..m.in_bytes as usize]);
            m.inputs = u32::from_le_bytes(b);
            m.have_in = true;
            m.in_ns = now_ns;
            m.syncs_unanswered = 0;
        }
        // SDO answers outside a transfer, EMCY: nothing the cycle needs.
        true
    }

    fn io_alarm(&self, k: usize, msg: impl std::fmt::Display) -> Alarm {
        Alarm::new(crate::alarm::IO_DEVICE, format!("I/O module (CiA 401) node {} on {}: {msg}", self.io[k].node, self.bus.name()))
    }

    /// One expedited SDO transfer with I/O module `k`.
    fn io_sdo(&mut self, clock: &mut dyn Clock, k: usize, ix: u16, sub: u8, data: Option<&[u8]>) -> Result<Vec<u8>, SdoError> {
        let req = match data {
            Some(d) => super::Sdo::Down(ix, sub, d),
            None => super::Sdo::Up(ix, sub),
        };
        self.transfer(clock, super::Peer::Io(k), req)
    }

    fn io_write(&mut self, clock: &mut dyn Clock, k: usize, ix: u16, sub: u8, data: &[u8]) -> Result<(), Alarm> {
        self.io_sdo(clock, k, ix, sub, Some(data)).map(|_| ()).map_err(|e| {
            self.io_alarm(k, format_args!("writing 0x{ix:04X}:{sub:02X} failed: {e}; is it a CiA 401 module with changeable PDO mapping?"))
        })
    }

    /// Boot-up, device type, PDO mapping of every I/O module.
    pub(super) fn start_io_modules(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        let deadline = clock.now_ns() + self.boot_timeout_ms as u64 * 1_000_000;
        while let Some(k) = self.io.iter().position(|m| !m.booted) {
            if clock.now_ns() >= deadline {
                return Err(self.io_alarm(
                    k,
                    format_args!(
                        "no boot-up message within {} ms after NMT reset communication; check its power, wiring, bitrate and node id",
                        self.boot_timeout_ms
                    ),
                ));
            }
            self.settle(clock, 1);
        }
        for k in 0..self.io.len() {
            let dt = self
                .io_sdo(clock, k, od::DEVICE_TYPE, 0, None)
                .map(|v: Vec<u8>| le_u32(&v))
                .map_err(|e| self.io_alarm(k, format_args!("reading device type 0x1000 failed: {e}")))?;
            if dt & 0xFFFF != 401 {
                return Err(self.io_alarm(
                    k,
                    format_args!("device type 0x1000 = 0x{dt:08X} is not a CiA 401 I/O device (profile 401 = 0x0191 expected); check io.devices.*.canopen_node"),
                ));
            }
            let (node, nin, nout) = (self.io[k].node, self.io[k].in_bytes, self.io[k].out_bytes);
            let ins: Vec<MapEntry> = (1..=nin).map(|s| MapEntry::new(DIGITAL_INPUTS, s, 8)).collect();
            let outs: Vec<MapEntry> = (1..=nout).map(|s| MapEntry::new(DIGITAL_OUTPUTS, s, 8)).collect();
            self.io_map(clock, k, od::TPDO_COMM, od::TPDO_MAP, cob::TPDO1 + node as u16, 1, &ins)?;
            self.io_map(clock, k, od::RPDO_COMM, od::RPDO_MAP, cob::RPDO1 + node as u16, 255, &outs)?;
            // Outputs off until the program switches one.
            for s in 1..=nout {
                self.io_write(clock, k, DIGITAL_OUTPUTS, s, &[0])?;
            }
            self.io[k].running = true;
            tracing::info!(node, inputs = nin * 8, outputs = nout * 8, "I/O module (CiA 401) configured");
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn io_map(&mut self, clock: &mut dyn Clock, k: usize, comm: u16, map: u16, cob_id: u16, tx_type: u8, entries: &[MapEntry]) -> Result<(), Alarm> {
        self.io_write(clock, k, comm, 1, &(0x8000_0000u32 | cob_id as u32).to_le_bytes())?;
        self.io_write(clock, k, map, 0, &[0])?;
        for (s, e) in entries.iter().enumerate() {
            self.io_write(clock, k, map, s as u8 + 1, &e.encode().to_le_bytes())?;
        }
        self.io_write(clock, k, map, 0, &[entries.len() as u8])?;
        self.io_write(clock, k, comm, 2, &[tx_type])?;
        self.io_write(clock, k, comm, 1, &(cob_id as u32).to_le_bytes())
    }

    /// The outputs of every module, before SYNC.
    pub(super) fn transmit_io(&mut self) -> Result<(), Alarm> {
        for k in 0..self.io.len() {
            let m = &mut self.io[k];
            if !m.running {
                continue;
            }
            m.syncs_unanswered = m.syncs_unanswered.saturating_add(1);
            let f = CanFrame::new(cob::RPDO1 + m.node as u16, &m.outputs.to_le_bytes()[..m.out_bytes as usize]);
            self.send(&f)?;
        }
        Ok(())
    }

    /// A module silent for longer than the feedback timeout (and SYNCs unanswered).
    pub(super) fn check_io(&self, now_ns: u64) -> Result<(), Alarm> {
        let timeout_syncs = (self.feedback_timeout_ns / self.cycle_ns.max(1)).max(1) as u32;
        for (k, m) in self.io.iter().enumerate() {
            let age = now_ns.saturating_sub(m.in_ns);
            if self.running && m.running && m.have_in && age > self.feedback_timeout_ns && m.syncs_unanswered > timeout_syncs {
                return Err(self.io_alarm(
                    k,
                    format_args!(
                        "no inputs (TPDO1) for {:.1} ms: the module answered none of the last {} SYNCs; the machine was stopped. Check its power, cable and PDO configuration",
                        age as f64 * 1e-6,
                        m.syncs_unanswered
                    ),
                ));
            }
        }
        Ok(())
    }

    pub(super) fn io_inputs_of(&self, node: u8) -> Option<u32> {
        self.io.iter().find(|m| m.node == node && m.have_in).map(|m| m.inputs)
    }

    pub(super) fn set_io_outputs_of(&mut self, node: u8, bits: u32) {
        if let Some(m) = self.io.iter_mut().find(|m| m.node == node) {
            m.outputs = bits;
        }
    }
}
