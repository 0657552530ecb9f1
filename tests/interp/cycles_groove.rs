//! G74 and G75 (manual 004 §2.16.5, §2.16.6).

use crate::cycles_common;
use cycles_common::*;

/// §2.16.5 example, G98 added (F50 is mm/min; the machine powers on in G99). P and Q take no
/// decimal point (least input increment, Fanuc's rule, see `groove.rs`): the manual's `P3 Q5`
/// means 3 mm / 5 mm, written `P3000 Q5000` (or `P3. Q5.`); as printed it pecks 5 µm and is
/// refused before anything moves.
#[test]
fn g74_manual_example() {
    let a = run_err("G98\nG0 X40 Z5 M3 S500;\nG74 R0.5;\nG74 X20 Z-20 P3 Q5 F50;\nM30;\n");
    assert_eq!(a.number, 62, "{a}");
    let with_point = motions(&run("G98\nG0 X40 Z5 M3 S500;\nG74 R0.5;\nG74 X20 Z-20 P3. Q5. F50;\nM30;\n"));
    let w = motions(&run("G98\nG0 X40 Z5 M3 S500;\nG74 R0.5;\nG74 X20 Z-20 P3000 Q5000 F50;\nM30;\n"));
    assert_eq!(format!("{with_point:?}"), format!("{w:?}"));
    check(&w[0], "rapid", 40.0, 5.0, 0.0, 0);
    let mut i = 1;
    let xs = [40.0, 34.0, 28.0, 22.0, 20.0]; // Δi = 3 mm radius per pass, the last one at X20
    for (n, x) in xs.iter().enumerate() {
        let zs = [0.0, 0.5, -5.0, -4.5, -10.0, -9.5, -15.0, -14.5, -20.0];
        let st = [1, 2, 3, 2, 3, 2, 3, 2, 3];
        for (z, s) in zs.iter().zip(st) {
            let kind = if s == 2 { "rapid" } else { "feed" };
            check(&w[i], kind, *x, *z, if s == 2 { 0.0 } else { 50.0 }, s);
            i += 1;
        }
        // ④ has no length (R(Δd) omitted); ⑤ back to Z5.
        check(&w[i], "rapid", *x, 5.0, 0.0, 5);
        i += 1;
        if n + 1 < xs.len() {
            check(&w[i], "rapid", xs[n + 1], 5.0, 0.0, 6);
        } else {
            check(&w[i], "rapid", 40.0, 5.0, 0.0, 7);
        }
        assert_eq!(w[i].cycle.as_deref(), Some("G74"));
        i += 1;
    }
    assert_eq!(w.len(), i);
}

/// §2.16.6 example as printed: `P6000 Q3000` in least input increments is 6 mm / 3 mm
/// (Fanuc's rule for P/Q, see `groove.rs`). G98 for F150.
#[test]
fn g75_manual_example() {
    let src = "G98\nG00 X150 Z50 M3 S500;\nG0 X125 Z-20;\nG75 R0.5 F150;\nG75 X40 Z-50 P6000 Q3000;\nG0 X150 Z50;\nM30;\n";
    let w = motions(&run(src));
    check(&w[1], "rapid", 125.0, -20.0, 0.0, 0);
    let mut i = 2;
    for n in 0..11 {
        let z = -20.0 - 3.0 * n as f64;
        // Pecks of 6 mm (radius) with 0.5 back, from radius 62.5 to 20.
        for k in 1..=7 {
            let r = 62.5 - 6.0 * k as f64;
            check(&w[i], "feed", 2.0 * r, z, 150.0, if k == 1 { 1 } else { 3 });
            check(&w[i + 1], "rapid", 2.0 * (r + 0.5), z, 0.0, 2);
            i += 2;
        }
        check(&w[i], "feed", 40.0, z, 150.0, 3);
        check(&w[i + 1], "rapid", 125.0, z, 0.0, 5);
        i += 2;
        if n < 10 {
            check(&w[i], "rapid", 125.0, z - 3.0, 0.0, 6);
        } else {
            check(&w[i], "rapid", 125.0, -20.0, 0.0, 7);
        }
        i += 1;
    }
    check(&w[i], "rapid", 150.0, 50.0, 0.0, 0);
    assert_eq!(w.len(), i + 1);
}

#[test]
fn g75_side_retract_and_partial_last_step() {
    // R(Δd) = 1: ④ retracts Z by 1 towards +Z (B_f's Z is below A's), the last step is
    // shorter (Z-7 after Z-5).
    let w = motions(&run("G98 G0 X50 Z0\nG75 R0\nG75 X40 Z-7 P10000 Q5000 R1 F100\n"));
    check(&w[1], "feed", 40.0, 0.0, 100.0, 1);
    check(&w[2], "rapid", 40.0, 1.0, 0.0, 4);
    check(&w[3], "rapid", 50.0, 1.0, 0.0, 5);
    check(&w[4], "rapid", 50.0, -5.0, 0.0, 6);
    check(&w[5], "feed", 40.0, -5.0, 100.0, 1);
    check(&w[8], "rapid", 50.0, -7.0, 0.0, 6);
    check(&w[12], "rapid", 50.0, 0.0, 0.0, 7);
    assert_eq!(w.len(), 13);
}

#[test]
fn g74_alarms() {
    assert_eq!(run_err("G98 G0 X40 Z5\nG74 X20 Z-20 Q5000 F50\n").number, 62); // no Δi
    assert_eq!(run_err("G98 G0 X40 Z5\nG74 X20 Z-20 P3000 F50\n").number, 62); // no Δk
                                                                               // Drilling on the axis: X omitted, no P needed.
    let w = motions(&run("G98 G0 X0 Z5\nG74 R1\nG74 Z-10 Q6.0 F50\n"));
    check(&w[1], "feed", 0.0, -1.0, 50.0, 1);
    check(&w[2], "rapid", 0.0, 0.0, 0.0, 2);
    check(&w[3], "feed", 0.0, -7.0, 50.0, 3);
    check(&w[4], "rapid", 0.0, -6.0, 0.0, 2);
    check(&w[5], "feed", 0.0, -10.0, 50.0, 3);
    check(&w[6], "rapid", 0.0, 5.0, 0.0, 5);
    assert_eq!(w.len(), 7);
}
