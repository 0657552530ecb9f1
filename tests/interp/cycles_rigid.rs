//! G92.1 rigid thread cycle (manual 001 §3.24.10).

use crate::cycles_common;
use cncgw::canon::{Move, MoveKind};
use cycles_common::*;

/// (kind, X diameter, Z, C, lead, rpm, step) of the motions.
fn rows(m: &[Move]) -> Vec<(&'static str, f64, f64, f64, f64, f64, u8)> {
    m.iter()
        .filter_map(|m| {
            let e = m.kind.end()?.sub(m.work_offset);
            let (lead, rpm) = match m.kind {
                MoveKind::RigidThread { lead, rpm, .. } => (lead, rpm),
                _ => (0.0, 0.0),
            };
            Some((m.kind.name(), e.x * 2.0, e.z, e.c, lead, rpm, m.tag.as_ref().map(|t| t.step).unwrap_or(0)))
        })
        .collect()
}

#[track_caller]
fn row(r: &(&'static str, f64, f64, f64, f64, f64, u8), kind: &str, x: f64, z: f64, c: f64, step: u8) {
    let ok = r.0 == kind && (r.1 - x).abs() < 1e-6 && (r.2 - z).abs() < 1e-6 && (r.3 - c).abs() < 1e-6 && r.6 == step;
    assert!(ok, "expected {kind} X{x} Z{z} C{c} step {step}, got {r:?}");
}

/// The manual's example program O0012, as printed: four passes; each cut turns the spindle
/// 33 mm / 3 mm = 11 revolutions, so it is back at its start angle and ④ moves no spindle.
#[test]
fn g92_1_manual_example() {
    let src = "O0012;\nG0 X150 Z50;\nT0101;\nM14;\nG0 X65 Z5;\nG92.1 X58.7 Z-28 F3 S600;\nX57.7;\nX57;\nX56.9;\nM15;\nM30;\n";
    let m = run(src);
    let r = rows(&m);
    row(&r[1], "rapid", 65.0, 5.0, 0.0, 0);
    let mut i = 2;
    for (n, x) in [58.7, 57.7, 57.0, 56.9].iter().enumerate() {
        let c0 = 3960.0 * n as f64;
        row(&r[i], "rapid", *x, 5.0, c0, 1);
        row(&r[i + 1], "rigid_thread", *x, -28.0, c0 + 3960.0, 2);
        assert_eq!((r[i + 1].4, r[i + 1].5), (3.0, 600.0));
        row(&r[i + 2], "rapid", 65.0, -28.0, c0 + 3960.0, 3);
        row(&r[i + 3], "rapid", 65.0, 5.0, c0 + 3960.0, 4);
        i += 4;
    }
    assert_eq!(r.len(), i);
    let auxes: Vec<f64> = m.iter().filter_map(|m| if let MoveKind::Aux { letter: 'M', value } = m.kind { Some(value) } else { None }).collect();
    assert_eq!(auxes, [14.0, 15.0]);
}

/// Note 8: from 30°, a 6-start thread cuts its second start from 90°, and ④ brings the
/// spindle back to 30° turning on in the cutting direction.
#[test]
fn g92_1_multi_start_angles() {
    let m = run("G0 X65 Z5 C30\nG92.1 X58.7 Z-5.5 F3 L6 S600\n");
    let r = rows(&m);
    // Lead 18 (6 × 3 would be G92's H; G92.1's F is the lead): 10.5/3 = 3.5 rev = 1260°.
    row(&r[1], "rapid", 58.7, 5.0, 30.0, 1);
    row(&r[2], "rigid_thread", 58.7, -5.5, 1290.0, 2);
    row(&r[4], "rapid", 65.0, 5.0, 1470.0, 4); // 1470 ≡ 30 (mod 360), first ≥ 1290
    row(&r[5], "rapid", 58.7, 5.0, 1530.0, 1); // start 2 at 90°
    row(&r[6], "rigid_thread", 58.7, -5.5, 2790.0, 2);
    assert_eq!(r.iter().filter(|r| r.0 == "rigid_thread").count(), 6);
}

#[test]
fn g92_1_left_hand_and_alarms() {
    let r = rows(&run("G0 X65 Z5\nG92.1 X58.7 Z-1 F-3 S600\n"));
    row(&r[2], "rigid_thread", 58.7, -1.0, -720.0, 2); // 6 mm / 3 = 2 rev, turning backwards
    assert_eq!(r[2].4, -3.0);
    let r = rows(&run("G0 X65 Z5 C10\nG92.1 X58.7 Z-0.5 F-3 S600\n"));
    // 5.5 / 3 rev = 660° back to -650, then ④ on down to -710 ≡ 10 (mod 360).
    row(&r[4], "rapid", 65.0, 5.0, -710.0, 4);
    assert_eq!(run_err("G0 X65 Z5\nG92.1 X58.7 Z-28 F3\n").number, cncgw::alarm::VALUE_RANGE); // no S
    assert_eq!(run_err("G0 X65 Z5\nG92.1 X58.7 Z5 F3 S600\n").number, cncgw::alarm::VALUE_RANGE); // face
    assert_eq!(run_err("G0 X65 Z5\nG92.1 X58.7 Z-28 S600\n").number, cncgw::alarm::FEED_ZERO); // no lead
    assert_eq!(run_err("G0 X65 Z5\nG92.1 X58.7 Z-28 F3 L100 S600\n").number, cncgw::alarm::VALUE_RANGE);
    assert_eq!(run_err("G0 X60 Z5\nG92.1 X64 Z-28 R-3 F3 S600\n").number, cncgw::alarm::VALUE_RANGE);
    // Inch threads: I8 → 3.175 mm.
    let r = rows(&run("G0 X65 Z5\nG92.1 X58.7 Z-28 I8 S600\n"));
    assert!((r[2].4 - 3.175).abs() < 1e-12);
}
