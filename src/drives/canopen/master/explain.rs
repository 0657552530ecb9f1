//! SDO aborts at start-up in words for the object they hit: what the abort means for the
//! machine builder and what to configure. The generic abort text (CiA 301) says what the
//! drive refused; this says why it matters here.

use super::le_u32;
use cncgw_bus::canopen::od;
use cncgw_bus::canopen::sdo::abort;
use cncgw_bus::cia402::mode;

fn is_rpdo_map(ix: u16) -> bool {
    (0x1600..=0x17FF).contains(&ix)
}
fn is_tpdo_map(ix: u16) -> bool {
    (0x1A00..=0x1BFF).contains(&ix)
}
fn is_pdo_comm(ix: u16) -> bool {
    (0x1400..=0x15FF).contains(&ix) || (0x1800..=0x19FF).contains(&ix)
}

/// "RPDO1" for 0x1600 / 0x1400, "TPDO1" for 0x1A00 / 0x1800.
fn pdo_name(ix: u16) -> String {
    match ix {
        0x1400..=0x15FF => format!("RPDO{}", ix - 0x1400 + 1),
        0x1600..=0x17FF => format!("RPDO{}", ix - 0x1600 + 1),
        0x1800..=0x19FF => format!("TPDO{}", ix - 0x1800 + 1),
        _ => format!("TPDO{}", ix.wrapping_sub(0x1A00) + 1),
    }
}

/// What an abort `code` on a write of `data` to `index:sub` means at start-up, with what to
/// do; `None` where the generic text says it all.
pub fn explain_write(index: u16, sub: u8, code: u32, data: &[u8]) -> Option<String> {
    let refused_value =
        matches!(code, abort::INVALID_VALUE | abort::VALUE_TOO_HIGH | abort::VALUE_TOO_LOW | abort::GENERAL | abort::PARAM_INCOMPATIBLE);
    Some(match (index, code) {
        (od::MODES_OF_OPERATION, _) if refused_value => {
            let m = data.first().map(|&b| b as i8).unwrap_or(0);
            format!(
                "this drive has no {} mode (it refuses 0x6060 = {m}); cncgw runs an axis in cyclic synchronous position (8) or, with axes.NAME.mode = \"ip\", in interpolated position (7), a spindle in speed mode also in cyclic synchronous velocity (9): set axes.NAME.mode to a mode the drive has (its 0x6502 or manual lists them), or use a drive (or firmware) with that mode",
                mode_short(m)
            )
        }
        (ix, abort::READ_ONLY | abort::UNSUPPORTED_ACCESS) if is_rpdo_map(ix) || is_tpdo_map(ix) => format!(
            "fixed PDO mapping: the drive does not let {} be remapped (start-up takes a fixed mapping that carries what the cycle needs, but this change of mapping — a spindle's speed mode — needs it written); map it in the drive's own tool, or use a drive whose PDO mapping can be written",
            pdo_name(ix)
        ),
        (ix, abort::NOT_MAPPABLE) if (is_rpdo_map(ix) || is_tpdo_map(ix)) && sub > 0 => {
            let obj = le_u32(data) >> 16;
            format!(
                "the drive cannot map 0x{obj:04X} into {} (a fixed or restricted PDO mapping: its EDS lists the objects its PDOs take)",
                pdo_name(ix)
            )
        }
        (ix, abort::PDO_TOO_LONG) if is_rpdo_map(ix) || is_tpdo_map(ix) => {
            format!("the drive's {} takes fewer bytes than cncgw maps (a restricted PDO mapping)", pdo_name(ix))
        }
        (ix, abort::PARAM_INCOMPATIBLE | abort::DEVICE_INCOMPATIBLE | abort::INVALID_VALUE) if is_rpdo_map(ix) || is_tpdo_map(ix) => format!(
            "the drive refuses the mapping cncgw writes to {} (a fixed or restricted PDO mapping)",
            pdo_name(ix)
        ),
        (ix, abort::INVALID_VALUE | abort::READ_ONLY | abort::VALUE_TOO_HIGH) if is_pdo_comm(ix) && sub == 1 => format!(
            "the drive does not let {}'s COB-ID be changed to 0x{:03X} (a fixed COB-ID): set axes.NAME.{}_cob_id to the one the drive uses",
            pdo_name(ix),
            le_u32(data) & 0x7FF,
            if ix < 0x1800 { "rpdo" } else { "tpdo" }
        ),
        (ix, _) if is_pdo_comm(ix) && sub == 2 && refused_value => format!(
            "the drive does not take transmission type {} for {} (axes.NAME.{}_transmission)",
            data.first().copied().unwrap_or(0),
            pdo_name(ix),
            if ix < 0x1800 { "rpdo" } else { "tpdo" }
        ),
        (od::INTERPOLATION_PERIOD, abort::NO_OBJECT | abort::NO_SUBINDEX) => {
            "the drive has no interpolation time period (0x60C2): it is not a cyclic-synchronous drive, or needs another firmware".to_string()
        }
        (od::INTERPOLATION_PERIOD | od::COMM_CYCLE_PERIOD, _) if refused_value => {
            "the drive does not take this cycle period: set machine.cycle_ms to one it takes (its manual lists them; 1, 2 and 4 ms are common)".to_string()
        }
        (od::FOLLOWING_ERROR_WINDOW, abort::VALUE_TOO_HIGH) => {
            "the following-error window is larger than the drive takes: lower axes.NAME.following_error".to_string()
        }
        (od::SOFTWARE_LIMIT, _) if refused_value || code == abort::MAX_LESS_THAN_MIN => {
            "the software limits are outside what the drive takes: check axes.NAME.min / max and counts_per_unit".to_string()
        }
        (_, abort::STORE_STATE) => {
            "the drive refuses this write in its present state (many drives take it only in Switch On Disabled, or pre-operational)".to_string()
        }
        (ix, abort::NO_OBJECT | abort::NO_SUBINDEX) => format!("the drive has no object 0x{ix:04X}:{sub:02X}, which cncgw needs (its EDS lists what it has)"),
        (ix, abort::READ_ONLY) => format!("the drive has 0x{ix:04X}:{sub:02X} read-only; cncgw needs to write it"),
        _ => return None,
    })
}

/// A mode by its short CiA 402 name: "CSP" for 8.
pub fn mode_short(m: i8) -> String {
    match m {
        1 => "PP (profile position)".into(),
        3 => "PV (profile velocity)".into(),
        4 => "PT (profile torque)".into(),
        6 => "HM (homing)".into(),
        7 => "IP (interpolated position)".into(),
        8 => "CSP (cyclic synchronous position)".into(),
        9 => "CSV (cyclic synchronous velocity)".into(),
        10 => "CST (cyclic synchronous torque)".into(),
        0 => "no mode (0)".into(),
        m => format!("manufacturer-specific mode {m}"),
    }
}

/// The modes 0x6502 lists, in words: "PP, HM, CSP" (bits 0…9 = modes 1…10; bits 16–31 are
/// the manufacturer's).
pub fn supported_modes_text(bits: u32) -> String {
    let names = ["PP", "VL", "PV", "PT", "-", "HM", "IP", "CSP", "CSV", "CST"];
    let mut v: Vec<String> = (0..10).filter(|b| bits & (1 << b) != 0 && *b != 4).map(|b| names[b as usize].to_string()).collect();
    if bits & 0xFFFF_0000 != 0 {
        v.push(format!("manufacturer-specific (0x{:04X})", bits >> 16));
    }
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// Whether 0x6502 lists `m` (a standard mode 1…10).
pub fn supports(bits: u32, m: i8) -> bool {
    (1..=10).contains(&m) && bits & (1 << (m - 1)) != 0
}

/// An abort that says the object is absent.
pub fn is_absent(code: u32) -> bool {
    matches!(code, abort::NO_OBJECT | abort::NO_SUBINDEX)
}

/// The short text of `mode::name` with its number, for alarms: "profile position (1)".
pub fn mode_words(m: i8) -> String {
    format!("{} ({m})", mode::name(m))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_up_aborts_in_words() {
        let e = explain_write(0x6060, 0, abort::INVALID_VALUE, &[8]).unwrap();
        assert!(e.starts_with("this drive has no CSP (cyclic synchronous position) mode"), "{e}");
        let e = explain_write(0x1600, 0, abort::READ_ONLY, &[0]).unwrap();
        assert!(e.starts_with("fixed PDO mapping: the drive does not let RPDO1 be remapped"), "{e}");
        let e = explain_write(0x1600, 2, abort::NOT_MAPPABLE, &0x607A_0020u32.to_le_bytes()).unwrap();
        assert!(e.starts_with("the drive cannot map 0x607A into RPDO1"), "{e}");
        let e = explain_write(0x1A00, 0, abort::READ_ONLY, &[0]).unwrap();
        assert!(e.contains("TPDO1"), "{e}");
        let e = explain_write(0x1400, 1, abort::INVALID_VALUE, &0x201u32.to_le_bytes()).unwrap();
        assert!(e.contains("RPDO1's COB-ID be changed to 0x201") && e.contains("rpdo_cob_id"), "{e}");
        let e = explain_write(0x60C2, 1, abort::NO_OBJECT, &[2]).unwrap();
        assert!(e.contains("no interpolation time period"), "{e}");
        assert!(explain_write(0x6065, 0, abort::TOGGLE, &[0; 4]).is_none());
    }

    #[test]
    fn supported_modes() {
        assert_eq!(supported_modes_text(0x1A1), "PP, HM, CSP, CSV");
        assert_eq!(supported_modes_text(0x25), "PP, PV, HM");
        assert_eq!(supported_modes_text(0x0001_0000), "manufacturer-specific (0x0001)");
        assert!(supports(0x1A1, 8) && !supports(0x25, 8) && !supports(0xFFFF, 0));
    }
}
