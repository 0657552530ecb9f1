//! Fixed PDO mappings (issue 21.4). Many drives do not let RPDO1/TPDO1 be remapped: the
//! mapping objects are read-only (0x06010002), or a write aborts 0x06040041 (not mappable),
//! 0x06040043 (general parameter incompatibility) or 0x08000022 (not in this state). Start-up
//! then reads the mapping the drive has and uses it if it carries what the cycle needs —
//! controlword and the mode's target (0x607A in CSP, 0x60C1:1 in IP) in the RPDO, statusword
//! and position actual (0x6064) in the TPDO, at whatever offsets — and says so; the mode
//! display 0x6061 is taken from the TPDO when it is there, else polled by SDO
//! (`mode_track`). A mapping that lacks one of them, or carries an object the master has no
//! value for, is alarm 2009 naming the object. As CODESYS's CANopen manager does with a
//! device whose EDS marks its PDOs fixed: it takes the device's mapping as it is.

use super::CanOpenMaster;
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::od;
use cncgw_bus::canopen::pdo::MapEntry;
use cncgw_bus::canopen::sdo::abort;
use cncgw_bus::{CanBus, Clock};

/// Alarm: the drive's PDO mapping cannot be changed and does not carry what the cycle needs.
pub const ALARM_MAPPING: u32 = crate::alarm::FIXED_PDO;

/// What the master puts into one mapped object of RPDO1.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Slot {
    Controlword,
    /// The cyclic target (position, or velocity in CSV).
    Target,
    /// 0x6060 in a fixed RPDO: the mode the master asks for, every cycle.
    Mode,
    /// Velocity offset (0x60B1): none, 0.
    Zero,
    /// The torque offset 0x60B2 of the friction feed-forward (`friction`), per mille.
    TorqueOffset,
}

/// RPDO1 as the drive maps it: each slot's offset in bytes, and the length.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct RpdoLayout {
    pub len: usize,
    pub slots: Vec<(Slot, usize)>,
}

impl RpdoLayout {
    /// The master's mapping with friction feed-forward: controlword, target, torque offset.
    pub fn with_torque_offset() -> Self {
        RpdoLayout { len: super::RPDO1_LEN + 2, slots: vec![(Slot::Controlword, 0), (Slot::Target, 2), (Slot::TorqueOffset, 6)] }
    }
}

impl Default for RpdoLayout {
    /// The master's own mapping: controlword, target (6 bytes).
    fn default() -> Self {
        RpdoLayout { len: super::RPDO1_LEN, slots: vec![(Slot::Controlword, 0), (Slot::Target, 2)] }
    }
}

/// TPDO1 as the drive maps it: offsets of statusword, position actual, mode display.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct TpdoLayout {
    pub status: usize,
    pub pos: usize,
    pub mode: Option<usize>,
}

impl Default for TpdoLayout {
    fn default() -> Self {
        TpdoLayout { status: 0, pos: 2, mode: Some(6) }
    }
}

/// Whether an abort on writing a mapping object says the mapping is fixed.
pub(super) fn refuses_remapping(e: &SdoError) -> bool {
    matches!(e, SdoError::Abort { code } if matches!(*code, abort::READ_ONLY | abort::UNSUPPORTED_ACCESS | abort::NOT_MAPPABLE | abort::PARAM_INCOMPATIBLE | abort::DEVICE_INCOMPATIBLE | abort::PDO_TOO_LONG | abort::STORE_STATE))
}

fn obj(e: &MapEntry) -> String {
    format!("0x{:04X}:{:02X}", e.index, e.sub)
}

/// "0x6040:00 (16 bit), 0x607A:00 (32 bit)".
pub(super) fn describe(entries: &[MapEntry]) -> String {
    if entries.is_empty() {
        return "nothing".into();
    }
    entries.iter().map(|e| format!("{} ({} bit)", obj(e), e.bits)).collect::<Vec<_>>().join(", ")
}

/// Where the master's values go in a fixed RPDO1 whose cyclic target is `target`. Err: what
/// is missing or cannot be filled, in words.
pub(super) fn rpdo_layout(entries: &[MapEntry], target: (u16, u8)) -> Result<RpdoLayout, String> {
    let mut slots = Vec::new();
    let mut off = 0usize;
    for e in entries {
        let want_bits = match (e.index, e.sub) {
            (od::CONTROLWORD, 0) => Some((Slot::Controlword, 16)),
            (ix, sub) if (ix, sub) == target => Some((Slot::Target, 32)),
            (od::MODES_OF_OPERATION, 0) => Some((Slot::Mode, 8)),
            (0x60B1, 0) => Some((Slot::Zero, 32)),
            (od::TORQUE_OFFSET, 0) => Some((Slot::TorqueOffset, 16)),
            _ => None,
        };
        match want_bits {
            Some((slot, bits)) if bits == e.bits => slots.push((slot, off)),
            Some((_, bits)) => return Err(format!("it maps {} with {} bits, the object has {bits}", obj(e), e.bits)),
            None if (e.index, e.sub) == (od::TARGET_POSITION, 0) || (e.index, e.sub) == (od::INTERPOLATION_DATA, 1) => {
                let (mode, key) = if e.index == od::TARGET_POSITION { ("CSP", "\"csp\"") } else { ("IP", "\"ip\"") };
                return Err(format!(
                    "it carries {} ({mode}'s target), not 0x{:04X}:{:02X}: the drive takes set-points in {mode}; set axes.NAME.mode = {key}",
                    obj(e),
                    target.0,
                    target.1
                ));
            }
            None => {
                return Err(format!(
                    "it carries {}, which cncgw has no value for (it fills controlword, target, 0x6060 and the offsets 0x60B1/0x60B2)",
                    obj(e)
                ))
            }
        }
        off += e.bits as usize / 8;
    }
    if off > 8 {
        return Err("it is longer than a CAN frame".into());
    }
    for (slot, what) in
        [(Slot::Controlword, "the controlword 0x6040:00".to_string()), (Slot::Target, format!("the target 0x{:04X}:{:02X}", target.0, target.1))]
    {
        if !slots.iter().any(|s| s.0 == slot) {
            return Err(format!("it does not carry {what}"));
        }
    }
    Ok(RpdoLayout { len: off, slots })
}

/// Where statusword, position actual and (optionally) mode display sit in a fixed TPDO1,
/// and its length.
pub(super) fn tpdo_layout(entries: &[MapEntry]) -> Result<(TpdoLayout, usize), String> {
    let (mut status, mut pos, mut mode) = (None, None, None);
    let mut off = 0usize;
    for e in entries {
        match (e.index, e.sub, e.bits) {
            (od::STATUSWORD, 0, 16) => status = Some(off),
            (od::POSITION_ACTUAL, 0, 32) => pos = Some(off),
            (od::MODES_DISPLAY, 0, 8) => mode = Some(off),
            (od::STATUSWORD | od::POSITION_ACTUAL | od::MODES_DISPLAY, 0, b) => return Err(format!("it maps {} with {b} bits", obj(e))),
            _ => {} // other objects are read past
        }
        off += e.bits as usize / 8;
    }
    if off > 8 {
        return Err("it is longer than a CAN frame".into());
    }
    let status = status.ok_or("it does not carry the statusword 0x6041:00")?;
    let pos = pos.ok_or("it does not carry the position actual value 0x6064:00")?;
    Ok((TpdoLayout { status, pos, mode }, off))
}

impl<B: CanBus> CanOpenMaster<B> {
    /// The mapping of `map` (0x1600 / 0x1A00) as the drive has it.
    fn read_mapping(&mut self, clock: &mut dyn Clock, i: usize, map: u16) -> Result<Vec<MapEntry>, Alarm> {
        let n = self.read_u32(clock, i, map, 0).map_err(|e| {
            self.node_alarm(i, ALARM_MAPPING, format!("the drive refused remapping, and reading its mapping 0x{map:04X}:00 failed: {e}"))
        })?;
        let mut v = Vec::new();
        for s in 1..=(n.min(8) as u8) {
            let e = self.read_u32(clock, i, map, s).map_err(|e| {
                self.node_alarm(i, ALARM_MAPPING, format!("the drive refused remapping, and reading its mapping 0x{map:04X}:{s:02X} failed: {e}"))
            })?;
            v.push(MapEntry::decode(e));
        }
        Ok(v)
    }

    /// After a refused remapping: the PDO valid again with the configured COB-ID and
    /// transmission type (the communication parameters of fixed-mapping drives are writable).
    fn revalidate(&mut self, clock: &mut dyn Clock, i: usize, comm: u16, cob_id: u16, tx: u8) -> Result<(), Alarm> {
        self.write(clock, i, comm, 2, &[tx])?;
        self.write(clock, i, comm, 1, &(cob_id as u32).to_le_bytes())
    }

    /// RPDO1 could not be remapped (`why`): use the drive's own if it carries what the cycle
    /// needs. The text for the start-up line.
    pub(super) fn use_fixed_rpdo(&mut self, clock: &mut dyn Clock, i: usize, why: &SdoError) -> Result<String, Alarm> {
        let entries = self.read_mapping(clock, i, od::RPDO_MAP)?;
        let spec = self.nodes[i].spec.clone();
        let lay = rpdo_layout(&entries, spec.target_object()).map_err(|m| {
            self.node_alarm(
                i,
                ALARM_MAPPING,
                format!(
                    "RPDO1 cannot be remapped ({why}) and the drive's own mapping [{}] will not do: {m}. Map RPDO1 in the drive's own tool (controlword 0x6040 + target), or use its other fixed PDO set if it has one — nothing was enabled",
                    describe(&entries)
                ),
            )
        })?;
        self.revalidate(clock, i, od::RPDO_COMM, spec.rpdo_cob, spec.rpdo_tx)?;
        tracing::warn!(node = spec.node, axis = %spec.axis, "RPDO1 cannot be remapped ({why}): using the drive's fixed mapping [{}]", describe(&entries));
        // A fixed 0x60B2 carries the friction feed-forward where it is asked for (else 0).
        let n = &mut self.nodes[i];
        if spec.friction && lay.slots.iter().any(|&(s, _)| s == Slot::TorqueOffset) {
            n.friction = Some(Default::default());
        }
        n.rpdo_at = lay;
        Ok(format!("fixed RPDO1 0x{:03X} = [{}] (remapping refused: {why})", spec.rpdo_cob, describe(&entries)))
    }

    /// TPDO1 could not be remapped: the drive's own, if it carries statusword and position.
    pub(super) fn use_fixed_tpdo(&mut self, clock: &mut dyn Clock, i: usize, why: &SdoError) -> Result<String, Alarm> {
        let entries = self.read_mapping(clock, i, od::TPDO_MAP)?;
        let spec = self.nodes[i].spec.clone();
        let (lay, len) = tpdo_layout(&entries).map_err(|m| {
            self.node_alarm(
                i,
                ALARM_MAPPING,
                format!(
                    "TPDO1 cannot be remapped ({why}) and the drive's own mapping [{}] will not do: {m}. Map TPDO1 in the drive's own tool (statusword 0x6041 + position actual 0x6064) — nothing was enabled",
                    describe(&entries)
                ),
            )
        })?;
        self.revalidate(clock, i, od::TPDO_COMM, spec.tpdo_cob, spec.tpdo_tx)?;
        tracing::warn!(node = spec.node, axis = %spec.axis, "TPDO1 cannot be remapped ({why}): using the drive's fixed mapping [{}]", describe(&entries));
        let n = &mut self.nodes[i];
        n.tpdo_at = lay;
        n.tpdo_len = Some(len as u8);
        n.mode.in_pdo = lay.mode.is_some();
        Ok(format!(
            "fixed TPDO1 0x{:03X} = [{}]{}",
            spec.tpdo_cob,
            describe(&entries),
            if lay.mode.is_some() { "" } else { " (no 0x6061: polled by SDO)" }
        ))
    }

    /// Whether a failed remapping (the write that failed, `try_map_pdo`) is the mapping
    /// object `map` refusing: a fixed mapping, worth the fallback.
    pub(super) fn fixed_fallback(map: u16, e: &(u16, u8, [u8; 4], SdoError)) -> bool {
        e.0 == map && refuses_remapping(&e.3)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const CW: MapEntry = MapEntry::new(0x6040, 0, 16);
    const TP: MapEntry = MapEntry::new(0x607A, 0, 32);
    const IPD: MapEntry = MapEntry::new(0x60C1, 1, 32);

    #[test]
    fn fixed_rpdos_in_any_order_with_fillable_extras() {
        let l = rpdo_layout(&[TP, CW], (0x607A, 0)).unwrap();
        assert_eq!(l, RpdoLayout { len: 6, slots: vec![(Slot::Target, 0), (Slot::Controlword, 4)] });
        let l = rpdo_layout(&[CW, MapEntry::new(0x6060, 0, 8), IPD], (0x60C1, 1)).unwrap();
        assert_eq!(l.slots, vec![(Slot::Controlword, 0), (Slot::Mode, 2), (Slot::Target, 3)]);
        assert_eq!(l.len, 7);
    }

    #[test]
    fn fixed_rpdos_that_will_not_do_are_named() {
        let e = rpdo_layout(&[CW, TP], (0x60C1, 1)).unwrap_err();
        assert!(e.contains("carries 0x607A:00 (CSP's target), not 0x60C1:01") && e.contains("axes.NAME.mode = \"csp\""), "{e}");
        let e = rpdo_layout(&[CW, MapEntry::new(0x60FF, 0, 32)], (0x607A, 0)).unwrap_err();
        assert!(e.starts_with("it carries 0x60FF:00, which cncgw has no value for"), "{e}");
        assert_eq!(rpdo_layout(&[TP], (0x607A, 0)).unwrap_err(), "it does not carry the controlword 0x6040:00");
    }

    #[test]
    fn fixed_tpdos_need_statusword_and_position() {
        let sw = MapEntry::new(0x6041, 0, 16);
        let pos = MapEntry::new(0x6064, 0, 32);
        let (l, len) = tpdo_layout(&[pos, MapEntry::new(0x6061, 0, 8), sw]).unwrap();
        assert_eq!((l, len), (TpdoLayout { status: 5, pos: 0, mode: Some(4) }, 7));
        let e = tpdo_layout(&[sw, MapEntry::new(0x606C, 0, 32)]).unwrap_err();
        assert_eq!(e, "it does not carry the position actual value 0x6064:00");
        assert!(refuses_remapping(&SdoError::Abort { code: 0x0800_0022 }) && !refuses_remapping(&SdoError::Abort { code: 0x0602_0000 }));
    }
}
