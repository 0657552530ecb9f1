//! Start-up lists (`[[axes.NAME.sdo]]`): the vendor parameters a drive needs (gains, brake
//! delay, current limit, encoder type, …) written in pre-operational after the standard
//! configuration, in the order given, and each read back and compared — what a CiA 306-3
//! concise DCF does, with the check a SINUMERIK's drive commissioning makes of every
//! parameter it downloads. A refused write or a value that reads back otherwise is alarm
//! 2008, naming the object, the value written and the value read; nothing is enabled and
//! start-up leaves the drive as it found it (`restore` writes the old values back).

use super::CanOpenMaster;
use crate::config::{SdoType, StartupSdo};
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::sdo::abort_text;
use cncgw_bus::{CanBus, Clock};

/// Alarm: a start-up list entry was refused or reads back another value.
pub const ALARM_STARTUP_LIST: u32 = crate::alarm::STARTUP_LIST;

impl<B: CanBus> CanOpenMaster<B> {
    /// Write node `i`'s start-up list and read every entry back.
    pub(super) fn write_startup_list(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let list = self.nodes[i].spec.sdo.clone();
        let axis = self.nodes[i].spec.axis.clone();
        for (k, e) in list.iter().enumerate() {
            let at = format!("start-up list axes.{axis}.sdo[{k}] {}", e.describe());
            if let Err(err) = self.try_write(clock, i, e.index, e.sub, &e.bytes()) {
                let why = match err {
                    SdoError::Abort { code } => format!("abort 0x{code:08X} {}", abort_text(code)),
                    e => e.to_string(),
                };
                return Err(self.node_alarm(
                    i,
                    ALARM_STARTUP_LIST,
                    format!(
                        "{at}: the drive refused the write ({why}); check index, sub-index, type and range against the drive's manual or EDS (`cncgw config check` checks them against axes.{axis}.eds) — nothing was enabled"
                    ),
                ));
            }
            let read = self.sdo(clock, i, super::Sdo::Up(e.index, e.sub));
            match read {
                Ok(b) if e.ty.decode(&b) == e.value && b.len() == e.ty.size() => {}
                Ok(b) => {
                    let got = e.ty.decode(&b);
                    let len = if b.len() == e.ty.size() { String::new() } else { format!(" ({} bytes, the type has {})", b.len(), e.ty.size()) };
                    return Err(self.node_alarm(
                        i,
                        ALARM_STARTUP_LIST,
                        format!(
                            "{at}: written {}, read back {got}{len}: the drive changed the value (rounded to its resolution, or limited). Set the value the drive keeps, or check the object's unit in its manual — nothing was enabled",
                            e.value
                        ),
                    ));
                }
                Err(err) => {
                    // Write-only objects (access codes, commands) cannot be read back.
                    if matches!(err, SdoError::Abort { code: cncgw_bus::canopen::sdo::abort::WRITE_ONLY }) {
                        tracing::info!(node = self.nodes[i].spec.node, "{at}: write-only, written without read-back");
                        continue;
                    }
                    return Err(self.node_alarm(
                        i,
                        ALARM_STARTUP_LIST,
                        format!("{at}: written, but reading it back failed ({err}); check the object in the drive's manual — nothing was enabled"),
                    ));
                }
            }
        }
        if !list.is_empty() {
            tracing::info!(node = self.nodes[i].spec.node, axis = %axis, "start-up list: {} object(s) written and read back", list.len());
        }
        Ok(())
    }
}

/// Check start-up list entries against the drive's EDS (`cncgw config check`): each object
/// exists, is writable, has the entry's size, and the value lies in the EDS's
/// LowLimit/HighLimit where it gives them. One line per problem.
pub fn check_list_against_eds(axis: &str, list: &[StartupSdo], eds: &cncgw_bus::canopen::eds::Eds) -> Vec<String> {
    let mut out = Vec::new();
    for (k, e) in list.iter().enumerate() {
        let at = format!("axes.{axis}.sdo[{k}] {}", e.describe());
        if let Err(m) = eds.check_write(e.index, e.sub, e.ty.size()) {
            out.push(format!("{at}: {m}"));
            continue;
        }
        if let Some(ent) = eds.get(e.index, e.sub) {
            let eds_type = cncgw_bus::canopen::eds::data_type_name(ent.data_type);
            if ent.size().is_some() && cia301_type(e.ty) != ent.data_type {
                out.push(format!(
                    "{at}: the EDS gives DataType {eds_type}, the entry says {} ({})",
                    e.ty.name(),
                    eds.describe(e.index, e.sub).unwrap_or_default()
                ));
            }
            if let Some(lo) = ent.low_limit.filter(|&lo| e.value < lo) {
                out.push(format!("{at}: below the EDS's LowLimit {lo} ({})", eds.describe(e.index, e.sub).unwrap_or_default()));
            }
            if let Some(hi) = ent.high_limit.filter(|&hi| e.value > hi) {
                out.push(format!("{at}: above the EDS's HighLimit {hi} ({})", eds.describe(e.index, e.sub).unwrap_or_default()));
            }
        }
    }
    out
}

/// The CiA 301 data type number of a start-up list type.
fn cia301_type(t: SdoType) -> u16 {
    match t {
        SdoType::I8 => 0x0002,
        SdoType::I16 => 0x0003,
        SdoType::I32 => 0x0004,
        SdoType::U8 => 0x0005,
        SdoType::U16 => 0x0006,
        SdoType::U32 => 0x0007,
    }
}
