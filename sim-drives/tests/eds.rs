//! The hand-written EDS of the emulated drive (tests/python/sim_drive.eds, used by the
//! python canopen peer) against the drive's object dictionary, both ways: every object of
//! the file exists with its type, access and PDO mappability, and every object of the drive
//! is in the file.

use cncgw_bus::canopen::eds::{data_type_size, Eds, EdsAccess};
use sim_drives::od::{Access, DType};
use sim_drives::{DriveConfig, DriveKind, SimDrive};
use std::path::PathBuf;

fn eds() -> Eds {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/python/sim_drive.eds");
    Eds::load(&p).unwrap()
}

fn type_ok(dt: DType, eds_type: u16) -> bool {
    match dt {
        DType::Str => eds_type == 0x0009,
        DType::Domain => eds_type == 0x000F,
        DType::I8 => eds_type == 0x0002,
        DType::I16 => eds_type == 0x0003,
        DType::I32 => eds_type == 0x0004,
        DType::U8 => eds_type == 0x0005,
        DType::U16 => eds_type == 0x0006,
        DType::U32 => eds_type == 0x0007,
    }
}

fn access_ok(a: Access, e: EdsAccess) -> bool {
    match a {
        Access::Const | Access::Ro => matches!(e, EdsAccess::Ro | EdsAccess::Const),
        Access::Rw => matches!(e, EdsAccess::Rw | EdsAccess::Rww | EdsAccess::Rwr),
        Access::Wo => e == EdsAccess::Wo,
    }
}

#[test]
fn the_eds_describes_the_emulated_drive() {
    let eds = eds();
    let d = SimDrive::new(DriveConfig::new(1, DriveKind::Linear, "x", 10000.0), 50);
    let mut wrong = Vec::new();
    for ((index, sub), e) in eds.entries.iter() {
        let here = eds.describe(*index, *sub).unwrap_or_default();
        match d.od().get(*index, *sub) {
            None => wrong.push(format!("{here}: not in the drive")),
            Some(o) => {
                if !type_ok(o.dtype, e.data_type) {
                    wrong.push(format!("{here}: DataType 0x{:04X}, the drive has {:?}", e.data_type, o.dtype));
                }
                if !access_ok(o.access, e.access) {
                    wrong.push(format!("{here}: AccessType {}, the drive has {:?}", e.access.name(), o.access));
                }
                if o.pdo != e.pdo_mapping {
                    wrong.push(format!(
                        "{here}: PDOMapping {}, the drive {}",
                        e.pdo_mapping as u8,
                        if o.pdo { "maps it" } else { "does not map it" }
                    ));
                }
                assert!(data_type_size(e.data_type).is_some() || matches!(o.dtype, DType::Str | DType::Domain));
            }
        }
    }
    for ((index, sub), o) in d.od().iter() {
        if eds.get(index, sub).is_none() {
            wrong.push(format!("0x{index:04X}:{sub:02X} ({:?}, {:?}) is in the drive but not in {}", o.dtype, o.access, eds.file));
        }
    }
    assert!(wrong.is_empty(), "{} disagreements:\n{}", wrong.len(), wrong.join("\n"));
}
