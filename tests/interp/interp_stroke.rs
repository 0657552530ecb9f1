//! G22/G23 stored stroke check 2 (manual 004 §2.10), notes 3, 4, 6, 7, 8.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::interp::Interpreter;
use cncgw::Alarm;

fn cfg(params: &str) -> MachineConfig {
    let text = EMBEDDED_LATHE.replace("[parameters]\n", &format!("[parameters]\n{params}\n"));
    MachineConfig::from_toml("t.toml", &text).unwrap_or_else(|e| panic!("{e}"))
}

fn first_alarm(src: &str, c: &MachineConfig) -> Option<Alarm> {
    let it = Interpreter::from_source("t.nc", src, c).unwrap_or_else(|e| panic!("{e:?}"));
    for m in it {
        if let Err(a) = m {
            return Some(a);
        }
    }
    None
}

fn at(a: &Option<Alarm>) -> Option<(u32, u32)> {
    a.as_ref().map(|a| (a.number, a.pos.as_ref().map(|p| p.line).unwrap_or(0)))
}

/// Forbidden inside X40…X100 (diameter), Z-50…Z0; the tool starts at machine zero.
const INSIDE: &str = "G98 G22 X100 Z0 I40 K-50\nG0 X200 Z10\nG1 X60 Z-10 F100\nM30\n";

#[test]
fn a_move_into_the_area_is_refused_at_its_block() {
    let c = cfg("");
    // The G01 crosses X100 at Z-4.3: into the area, moving mostly −X → OT0503.
    let a = first_alarm(&INSIDE.replace("G98 G22", "G98\nG22"), &c);
    assert_eq!(at(&a), Some((503, 4)), "{a:?}");
    // Around it is fine; G23 switches the check off.
    assert!(first_alarm("G98\nG22 X100 Z0 I40 K-50\nG0 X200 Z10\nG1 X60 Z5 F100\nX0\nM30\n", &c).is_none());
    assert!(first_alarm("G98\nG22 X100 Z0 I40 K-50\nG0 X200 Z10\nG23\nG1 X60 Z-10 F100\nM30\n", &c).is_none());
    // An arc that bulges into the area although its end points are outside.
    let a = first_alarm("G98\nG22 X100 Z0 I40 K-50\nG0 X120 Z10\nG1 Z-60 F100\nG3 X120 Z10 R50\nM30\n", &c);
    assert_eq!(at(&a).map(|x| x.1), Some(5), "{a:?}");
}

#[test]
fn note_6_alone_in_its_block() {
    let a = first_alarm("G22 G01 X100 Z0 I40 K-50\nM30\n", &cfg(""));
    assert_eq!(at(&a), Some((10, 1)), "{a:?}");
}

#[test]
fn note_8_wrong_order_disables_the_check() {
    // I > X: no check at all.
    assert!(first_alarm("G98\nG22 X40 Z0 I100 K-50\nG0 X200 Z10\nG1 X60 Z-10 F100\nM30\n", &cfg("")).is_none());
}

#[test]
fn boundary_from_no_1360_1375() {
    // 0.001 mm from reference point 1 (machine zero here), X as a diameter.
    let c = cfg("1360 = 100000\n1362 = 0\n1370 = 40000\n1372 = -50000");
    let a = first_alarm("G98\nG22\nG0 X200 Z10\nG1 X60 Z-10 F100\nM30\n", &c);
    assert_eq!(at(&a), Some((503, 4)), "{a:?}");
    // Without the parameters G22 needs the words.
    let a = first_alarm("G98\nG22\nM30\n", &cfg(""));
    assert_eq!(at(&a).map(|x| x.0), Some(10));
}

#[test]
fn outside_type_no_1002() {
    let c = cfg("1002 = 1");
    // Allowed: inside X0…X200, Z-100…Z20. Starting at machine zero (inside), leaving it alarms.
    let a = first_alarm("G98\nG22 X200 Z20 I-10 K-100\nG1 X100 Z-50 F100\nZ-150\nM30\n", &c);
    assert_eq!(at(&a), Some((503, 4)), "{a:?}");
    // Note 7: switching on while already outside alarms at once.
    let a = first_alarm("G98\nG0 X300\nG22 X200 Z20 I-10 K-100\nM30\n", &c);
    assert_eq!(at(&a).map(|x| x.1), Some(3), "{a:?}");
}

#[test]
fn note_4_reference_point_in_the_area() {
    let c = cfg("1240 = { x = 60.0, z = -10.0 }");
    let a = first_alarm("G22 X100 Z0 I40 K-50\nM30\n", &c);
    assert_eq!(at(&a).map(|x| x.1), Some(1), "{a:?}");
    assert!(a.unwrap().message.contains("reference point"));
}
