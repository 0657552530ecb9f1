//! G90 and G94 (manual 004 §2.15).

use crate::cycles_common;
use cycles_common::*;

/// §2.15.1 example (blank Φ125×110). The printed text lost the G90 words in extraction and
/// merged two lines ("X110 Z-30 X100"); the program below restores them. G98 is added
/// because this machine powers on in G99 and the example's F200 is mm/min.
#[test]
fn g90_manual_example() {
    let src = "G98\nM03 S300\nG00 X130 Z3\nG90 X120 Z-110 F200\nX110 Z-30\nX100\nX90\nX80\nX70\nX60\nG00 X120 Z-30\n\
               G90 X120 Z-44 R-7.5 F150\nZ-56 R-15\nZ-68 R-22.5\nZ-80 R-30\nM30\n";
    let w = motions(&run(src));
    check(&w[0], "rapid", 130.0, 3.0, 0.0, 0);
    // A→D Φ120 cut.
    check(&w[1], "rapid", 120.0, 3.0, 0.0, 1);
    check(&w[2], "feed", 120.0, -110.0, 200.0, 2);
    check(&w[3], "feed", 130.0, -110.0, 200.0, 3);
    check(&w[4], "rapid", 130.0, 3.0, 0.0, 4);
    assert_eq!(w[1].cycle.as_deref(), Some("G90"));
    // Φ110…Φ60 to Z-30: Z kept from "X110 Z-30" (§2.15 note 2).
    let mut i = 5;
    for x in [110.0, 100.0, 90.0, 80.0, 70.0, 60.0] {
        check(&w[i], "rapid", x, 3.0, 0.0, 1);
        check(&w[i + 1], "feed", x, -30.0, 200.0, 2);
        check(&w[i + 2], "feed", 130.0, -30.0, 200.0, 3);
        check(&w[i + 3], "rapid", 130.0, 3.0, 0.0, 4);
        i += 4;
    }
    check(&w[i], "rapid", 120.0, -30.0, 0.0, 0);
    i += 1;
    // Taper: A = (X120, Z-30); C = (X120, Z); B = C's X + 2R on A's Z. ① has no X motion, so
    // the first move is the taper cut; ③ has no length either (C's X is A's X).
    for (z, r) in [(-44.0, -7.5), (-56.0, -15.0), (-68.0, -22.5), (-80.0, -30.0)] {
        check(&w[i], "rapid", 120.0 + 2.0 * r, -30.0, 0.0, 1);
        check(&w[i + 1], "feed", 120.0, z, 150.0, 2);
        check(&w[i + 2], "rapid", 120.0, -30.0, 0.0, 4);
        i += 3;
    }
    assert_eq!(w.len(), i);
}

/// §2.15.2 example (blank Φ125×112), as printed; G98 added as for G90.
#[test]
fn g94_manual_example() {
    let src = "G98\nG00 X130 Z5 M3 S500;\nG94 X0 Z0 F200;\nX120 Z-110 F300;\nG00 X120 Z0;\nG94 X108 Z-30 R-10;\nX96 R-20;\nX84 R-30;\nX72 R-40;\nX60 R-50;\nM30;\n";
    let w = motions(&run(src));
    check(&w[0], "rapid", 130.0, 5.0, 0.0, 0);
    check(&w[1], "rapid", 130.0, 0.0, 0.0, 1);
    check(&w[2], "feed", 0.0, 0.0, 200.0, 2);
    check(&w[3], "feed", 0.0, 5.0, 200.0, 3);
    check(&w[4], "rapid", 130.0, 5.0, 0.0, 4);
    assert_eq!(w[4].cycle.as_deref(), Some("G94"));
    check(&w[5], "rapid", 130.0, -110.0, 0.0, 1);
    check(&w[6], "feed", 120.0, -110.0, 300.0, 2);
    check(&w[7], "feed", 120.0, 5.0, 300.0, 3); // the Φ120 outer cut
    check(&w[8], "rapid", 130.0, 5.0, 0.0, 4);
    check(&w[9], "rapid", 120.0, 0.0, 0.0, 0);
    let mut i = 10;
    for (x, r) in [(108.0, -10.0), (96.0, -20.0), (84.0, -30.0), (72.0, -40.0), (60.0, -50.0)] {
        check(&w[i], "rapid", 120.0, -30.0 + r, 0.0, 1);
        check(&w[i + 1], "feed", x, -30.0, 300.0, 2);
        check(&w[i + 2], "feed", x, 0.0, 300.0, 3);
        check(&w[i + 3], "rapid", 120.0, 0.0, 0.0, 4);
        i += 4;
    }
    assert_eq!(w.len(), i);
}

#[test]
fn g90_four_sign_cases() {
    // Figure 2.24: (U, W, R) → the tool visits B = (C.x + R, A.z), C, D = (A.x, C.z), A.
    for (u, r) in [(20.0, 3.0), (-20.0, -3.0), (20.0, -3.0), (-20.0, 3.0)] {
        let w = motions(&run(&format!("G98 G00 X50 Z5\nG90 U{u} W-20 R{r} F100\n")));
        let cx = 50.0 + u;
        check(&w[1], "rapid", cx + 2.0 * r, 5.0, 0.0, 1);
        check(&w[2], "feed", cx, -15.0, 100.0, 2);
        check(&w[3], "feed", 50.0, -15.0, 100.0, 3);
        check(&w[4], "rapid", 50.0, 5.0, 0.0, 4);
    }
    // |R| > |U/2| with opposite signs.
    assert_eq!(run_err("G98 G00 X50 Z5\nG90 U20 W-20 R-11 F100\n").number, cncgw::alarm::VALUE_RANGE);
    assert_eq!(run_err("G98 G00 X50 Z5\nG94 U-20 W-5 R6 F100\n").number, cncgw::alarm::VALUE_RANGE);
}

#[test]
fn g94_four_sign_cases() {
    for (u, r) in [(20.0, -3.0), (-20.0, -3.0), (20.0, 3.0), (-20.0, 3.0)] {
        let w = motions(&run(&format!("G98 G00 X50 Z5\nG94 U{u} W-10 R{r} F100\n")));
        let cx = 50.0 + u;
        check(&w[1], "rapid", 50.0, -5.0 + r, 0.0, 1);
        check(&w[2], "feed", cx, -5.0, 100.0, 2);
        check(&w[3], "feed", cx, 5.0, 100.0, 3);
        check(&w[4], "rapid", 50.0, 5.0, 0.0, 4);
    }
}

#[test]
fn retained_values_survive_g04_and_clear_on_other_codes() {
    // G04 keeps Z-30; the following X block cuts to Z-30.
    let w = motions(&run("G98 G00 X50 Z5\nG90 X40 Z-30 F100\nG04 P100\nX30\n"));
    check(&w[6], "feed", 30.0, -30.0, 100.0, 2);
    // G50 (group 00) clears: "G90 X30" alone then keeps the current Z: a cut of no length,
    // only the X moves of ① and ③.
    let w = motions(&run("G98 G00 X50 Z5\nG90 X40 Z-30 F100\nG50 S2000\nG90 X30\n"));
    check(&w[5], "rapid", 30.0, 5.0, 0.0, 1);
    check(&w[6], "feed", 50.0, 5.0, 100.0, 3);
    assert_eq!(w.len(), 7);
    // G94 does not inherit G90's values.
    let w = motions(&run("G98 G00 X50 Z5\nG90 X40 Z-30 F100\nG94 X30\n"));
    check(&w[5], "feed", 30.0, 5.0, 100.0, 2);
}

#[test]
fn cycles_need_the_zx_plane_and_a_feed() {
    assert_eq!(run_err("G98 G00 X50 Z5\nG17\nG90 X40 Z-30 F100\n").number, 10);
    assert_eq!(run_err("G98 G00 X50 Z5\nG90 X40 Z-30 C10 F100\n").number, 21);
    assert_eq!(run_err("G00 X50 Z5\nG98\nG90 X40 Z-30\n").number, cncgw::alarm::FEED_ZERO);
}
