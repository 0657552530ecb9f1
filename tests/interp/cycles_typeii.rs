//! G71/G72 type II (manual 004 §2.16.1 "连续凹槽加工", notes 1–7): a contour with two
//! pockets, every pass worked out by hand.

use crate::cycles_common;
use cycles_common::*;

/// A at X60 Z2 (radius 30); the contour X50 → pocket 1 down to X30 → back to X50 → pocket 2
/// down to X30 → up to X56. Δd = 3, e = 0.5, no allowance.
const TWO_POCKETS: &str = "G98 G00 X60 Z2\nG71 U3 R0.5 F100\nG71 P1 Q2\nN1 G01 X50 Z0\nZ-10\nX30 Z-15\nZ-20\nX50 Z-25\nZ-30\n\
X30 Z-35\nZ-40\nX56 Z-45\nN2 Z-50\nG00 X70\nM30\n";

/// Z where the last wall (X30 Z-40 → X56 Z-45) is at radius `r`.
fn wall2(r: f64) -> f64 {
    -40.0 - (r - 15.0) / 13.0 * 5.0
}

#[test]
fn g71_type_ii_two_pockets_pass_by_pass() {
    let w = motions(&run(TWO_POCKETS));
    let f = 100.0;
    #[rustfmt::skip]
    let want: Vec<(&str, f64, f64, f64, u8)> = vec![
        ("rapid", 60.0, 2.0, 0.0, 0),
        // Main chain. Level radius 27: from the ns move (crossed at Z0.8) to the last wall.
        ("feed", 54.0, 0.8, f, 1), ("feed", 54.0, wall2(27.0), f, 2), ("feed", 55.0, wall2(27.0) + 0.5, f, 3),
        // Level 24 starts on pocket 1's wall: over it at the retreat height, G01 down.
        ("rapid", 55.0, -10.5, 0.0, 4),
        ("feed", 48.0, -10.5, f, 1), ("feed", 48.0, -24.5, f, 2), ("feed", 49.0, -24.0, f, 3), ("rapid", 49.0, -12.0, 0.0, 4),
        ("feed", 42.0, -12.0, f, 1), ("feed", 42.0, -23.0, f, 2), ("feed", 43.0, -22.5, f, 3), ("rapid", 43.0, -13.5, 0.0, 4),
        ("feed", 36.0, -13.5, f, 1), ("feed", 36.0, -21.5, f, 2), ("feed", 37.0, -21.0, f, 3),
        // Out of pocket 1 straight up to A's level.
        ("rapid", 60.0, -21.0, 0.0, 4),
        // Pocket 2 (note 3): rapid over it, down to e above level 27, G01 on.
        ("rapid", 60.0, -30.5, 0.0, 4), ("rapid", 55.0, -30.5, 0.0, 4),
        ("feed", 48.0, -30.5, f, 1), ("feed", 48.0, wall2(24.0), f, 2), ("feed", 49.0, wall2(24.0) + 0.5, f, 3), ("rapid", 49.0, -32.0, 0.0, 4),
        ("feed", 42.0, -32.0, f, 1), ("feed", 42.0, wall2(21.0), f, 2), ("feed", 43.0, wall2(21.0) + 0.5, f, 3), ("rapid", 43.0, -33.5, 0.0, 4),
        ("feed", 36.0, -33.5, f, 1), ("feed", 36.0, wall2(18.0), f, 2), ("feed", 37.0, wall2(18.0) + 0.5, f, 3),
        ("rapid", 60.0, wall2(18.0) + 0.5, 0.0, 4),
        // Back to A, then the ns move and the contour.
        ("rapid", 60.0, 2.0, 0.0, 4),
        ("feed", 50.0, 0.0, f, 5),
        ("feed", 50.0, -10.0, f, 6), ("feed", 30.0, -15.0, f, 6), ("feed", 30.0, -20.0, f, 6), ("feed", 50.0, -25.0, f, 6),
        ("feed", 50.0, -30.0, f, 6), ("feed", 30.0, -35.0, f, 6), ("feed", 30.0, -40.0, f, 6), ("feed", 56.0, -45.0, f, 6),
        ("feed", 56.0, -50.0, f, 6),
        // Note 7: out to A + allowance (0) + Δd (3, radius), over A, to A.
        ("rapid", 66.0, -50.0, 0.0, 7), ("rapid", 66.0, 2.0, 0.0, 7), ("rapid", 60.0, 2.0, 0.0, 7),
        // The program continues after N2.
        ("rapid", 70.0, 2.0, 0.0, 0),
    ];
    assert_eq!(w.len(), want.len(), "{w:#?}");
    for (g, (k, x, z, f, s)) in w.iter().zip(&want) {
        check(g, k, *x, *z, *f, *s);
    }
}

#[test]
fn type_ii_ignores_the_z_allowance_and_keeps_x() {
    // Note 2: W is ignored; U0.4 (diameter) raises every level end on the walls by 0.2.
    let src = TWO_POCKETS.replace("G71 P1 Q2", "G71 P1 Q2 U0.4 W2.0");
    let w = motions(&run(&src));
    // The ns move ends at B' = X50.4 Z0 (not Z2).
    assert!(w.iter().any(|m| m.step == 5 && (m.x - 50.4).abs() < 1e-9 && m.z.abs() < 1e-9), "{w:#?}");
    // Level 24 ends on pocket 1's rising wall moved up by 0.2: Z = −20 − (24 − 15.2)/10·5.
    assert!(w.iter().any(|m| m.step == 2 && (m.x - 48.0).abs() < 1e-9 && (m.z + 24.4).abs() < 1e-9), "{w:#?}");
}

#[test]
fn type_ii_alarms() {
    let num = |c: &str| run_err(&format!("G98 G00 X60 Z2\nG71 U1 R0.5 F100\nG71 P1 Q9\n{c}")).number;
    // Note 4: Z must be monotonic.
    assert_eq!(num("N1 G01 X50 Z0\nZ-10\nN9 X56 Z-5\n"), 64);
    // Eleven pockets: eleven V-shaped dips below X50.
    let mut c = String::from("N1 G01 X50 Z0\n");
    for i in 0..11 {
        let z = -10.0 * i as f64;
        c.push_str(&format!("X40 Z{}\nX50 Z{}\n", z - 5.0, z - 10.0));
    }
    c.push_str("N9 Z-120\n");
    let a = run_err(&format!("G98 G00 X60 Z2\nG71 U1 R0.5 F100\nG71 P1 Q9\n{c}"));
    assert_eq!(a.number, 64, "{a}");
    assert!(a.message.contains("11 pockets"), "{a}");
    // Ten are fine.
    let c10 = c.replacen("X40 Z-105\nX50 Z-110\n", "", 1);
    let m = run(&format!("G98 G00 X60 Z2\nG71 U1 R0.5 F100\nG71 P1 Q9\n{c10}"));
    assert!(m.len() > 40);
}

#[test]
fn g72_type_ii_facing_pocket() {
    // G72: infeed along Z, cuts along X. A at X62 Z2; the contour from Z-10 at X60 down to
    // X20 with one dip to Z-16 in the middle. Δd = 2 (Z), e = 0.5.
    let src = "G98 G00 X62 Z2\nG72 W2 R0.5 F100\nG72 P1 Q2\nN1 G01 X60 Z-10\nX50\nX40 Z-16\nX30\nX24 Z-10\nN2 X20\nG00 Z5\nM30\n";
    let w = motions(&run(src));
    let rows: Vec<(f64, f64)> = w.iter().filter(|m| m.step == 2).map(|m| (m.z, m.x)).collect();
    // Levels Z0 … Z-8 run over the whole face to X20; Z-10 … Z-14 are inside the dip.
    assert_eq!(rows.len(), 8, "{rows:?}");
    for (i, (z, x)) in rows.iter().enumerate() {
        assert!((z - (2.0 - 2.0 * (i + 1) as f64)).abs() < 1e-9, "{rows:?}");
        if i < 5 {
            assert!((x - 20.0).abs() < 1e-9, "{rows:?}");
        }
    }
    // Z-12 inside the dip: from the falling wall X50→X40 (radius 25→20 over Z-10→-16) at
    // radius 25 − 5·2/6, to the rising wall X30→X24 (radius 15→12) at radius 15 − 3·4/6.
    let r_in = 25.0 - 5.0 * 2.0 / 6.0;
    let r_out = 15.0 - 3.0 * 4.0 / 6.0;
    assert!((rows[6].1 - 2.0 * r_out).abs() < 1e-9, "{rows:?}");
    let i12 = w.iter().position(|m| m.step == 2 && (m.z + 12.0).abs() < 1e-9).expect("level Z-12");
    let inf = &w[i12 - 1];
    assert!((inf.x - 2.0 * r_in).abs() < 1e-9 && (inf.z + 12.0).abs() < 1e-9 && inf.step == 1 && inf.kind == "feed", "{inf:?}");
}
