//! G32, G92 and G76 (manual 004 §2.17).

use crate::cycles_common;
use cycles_common::*;

#[test]
fn g32_manual_example_taper_thread_two_passes() {
    // §2.17.1 example, as printed.
    let m = run("G00 X28 Z3;\nG32 X51 W-75 F2.0;\nG00 X55;\nW75;\nX27;\nG32 X50 W-75 F2.0;\nG00 X55;\nW75;\nM30;\n");
    let w = motions(&m);
    assert_eq!(w.len(), 8);
    check(&w[0], "rapid", 28.0, 3.0, 0.0, 0);
    check(&w[1], "thread", 51.0, -72.0, 2.0, 0);
    assert!(!w[1].continuous && w[1].angle == 0.0 && w[1].cycle.is_none());
    check(&w[2], "rapid", 55.0, -72.0, 0.0, 0);
    check(&w[3], "rapid", 55.0, 3.0, 0.0, 0);
    check(&w[4], "rapid", 27.0, 3.0, 0.0, 0);
    check(&w[5], "thread", 50.0, -72.0, 2.0, 0);
    assert!(!w[5].continuous);
    check(&w[6], "rapid", 55.0, -72.0, 0.0, 0);
    check(&w[7], "rapid", 55.0, 3.0, 0.0, 0);
}

#[test]
fn g32_consecutive_blocks_are_continuous_and_ignore_later_q() {
    let m = run("G00 X30 Z5\nG32 Z-20 F1.5 Q90\nX40 Z-30 Q180\n(comment)\nZ-40\nG00 X50\nG32 Z-60 Q45\n");
    let w = motions(&m);
    check(&w[1], "thread", 30.0, -20.0, 1.5, 0);
    assert!(!w[1].continuous);
    assert_eq!(w[1].angle, 90.0);
    // Rule 2: Q180 of the second block is ignored; the lead stays 1.5 (modal F).
    check(&w[2], "thread", 40.0, -30.0, 1.5, 0);
    assert!(w[2].continuous);
    assert_eq!(w[2].angle, 90.0);
    // A comment line is not a block: the chain goes on.
    assert!(w[3].continuous);
    // G00 breaks the chain: the next thread waits for the one-revolution signal again.
    check(&w[5], "thread", 50.0, -60.0, 1.5, 0);
    assert!(!w[5].continuous);
    assert_eq!(w[5].angle, 45.0);
}

#[test]
fn g32_m_code_block_breaks_the_chain() {
    let w = motions(&run("G00 X30 Z5\nG32 Z-20 F1.5\nM08\nG32 Z-30\n"));
    assert!(!w[2].continuous);
}

#[test]
fn g32_inch_threads_e_and_inch_lead() {
    let w = motions(&run("G00 X30 Z5\nG32 Z-20 E10\n"));
    check(&w[1], "thread", 30.0, -20.0, 2.54, 0);
    let m = run("G20\nG00 X1.0 Z0.2\nG32 Z-1.0 F0.1\n");
    let w = motions(&m);
    assert!((w[1].f - 2.54).abs() < 1e-9, "{:?}", w[1]);
    assert!((w[1].z + 25.4).abs() < 1e-9);
}

#[test]
fn g32_lead_is_not_taken_from_a_feed_rate() {
    let a = run_err("G01 X30 Z5 F0.2\nG32 Z-20\n");
    assert_eq!(a.number, cncgw::alarm::FEED_ZERO, "{a}");
    let a = run_err("G00 X30 Z5\nG32 Z-20 F0\n");
    assert_eq!(a.number, cncgw::alarm::FEED_ZERO, "{a}");
}

#[test]
fn g32_q_range() {
    let a = run_err("G00 X30 Z5\nG32 Z-20 F1 Q361\n");
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE, "{a}");
    let a = run_err("G00 X30 Z5\nG32 Z-20 F1 Q-1\n");
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE, "{a}");
    let w = motions(&run("G00 X30 Z5\nG32 Z-20 F1 Q360\n"));
    assert_eq!(w[1].angle, 360.0);
}

#[test]
fn g92_manual_example_four_passes() {
    // §2.17.3 example, as printed (No.5130 = 0: no run-out).
    let m = run("M3 S300 G0 X150 Z50 T0101;\nG0 X65 Z5;\nG92 X58.7 Z-28 F3;\nX57.7;\nX57;\nX56.9;\nM30;\n");
    let w = motions(&m);
    check(&w[0], "rapid", 150.0, 50.0, 0.0, 0);
    check(&w[1], "rapid", 65.0, 5.0, 0.0, 0);
    let mut i = 2;
    for x in [58.7, 57.7, 57.0, 56.9] {
        check(&w[i], "rapid", x, 5.0, 0.0, 1);
        check(&w[i + 1], "thread", x, -28.0, 3.0, 2);
        assert!(!w[i + 1].continuous);
        check(&w[i + 2], "rapid", 65.0, -28.0, 0.0, 3);
        check(&w[i + 3], "rapid", 65.0, 5.0, 0.0, 4);
        assert_eq!(w[i].cycle.as_deref(), Some("G92"));
        i += 4;
    }
    assert_eq!(w.len(), i);
    assert_eq!(m.last().map(|m| m.kind.name()), Some("end"));
}

#[test]
fn g92_run_out_from_no5130_at_45_degrees() {
    // 5130 = 10 → 1.0 × lead = 3 mm on Z, 45°: X retracts 3 mm (radius) while Z finishes.
    let cfg = cfg_with("5130 = 10");
    let w = motions(&run_cfg("G0 X65 Z5\nG92 X58.7 Z-28 F3\n", &cfg));
    check(&w[1], "rapid", 58.7, 5.0, 0.0, 1);
    check(&w[2], "thread", 58.7, -25.0, 3.0, 2);
    assert!(!w[2].continuous);
    check(&w[3], "thread", 64.7, -28.0, 3.0, 2);
    assert!(w[3].continuous);
    check(&w[4], "rapid", 65.0, -28.0, 0.0, 3);
    check(&w[5], "rapid", 65.0, 5.0, 0.0, 4);
    // Note 6: the short-axis run-out is clamped to the retract distance (X62 → 1.65 mm).
    let w = motions(&run_cfg("G0 X62 Z5\nG92 X58.7 Z-28 F3\n", &cfg));
    check(&w[3], "thread", 62.0, -28.0, 3.0, 2);
    assert_eq!(w.len(), 5, "{w:?}"); // ③ has no length left
}

#[test]
fn g92_run_out_angle_no5131_keeps_lead_on_the_long_axis() {
    // 60°: short = 3·tan60 = 5.196 > 3, so X is that segment's long axis: lead scaled.
    let cfg = cfg_with("5130 = 10\n5131 = 60");
    let w = motions(&run_cfg("G0 X80 Z5\nG92 X58.7 Z-28 F3\n", &cfg));
    let s = 3.0 * 60f64.to_radians().tan();
    check(&w[3], "thread", 58.7 + 2.0 * s, -28.0, 3.0 * s / 3.0, 2);
}

#[test]
fn g92_run_out_longer_than_thread_alarms() {
    let cfg = cfg_with("5130 = 99"); // 9.9 × 3 = 29.7 mm > 20 + 5
    let a = run_err_cfg("G0 X65 Z5\nG92 X58.7 Z-20 F3\n", &cfg);
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE, "{a}");
}

#[test]
fn g92_multi_start_h() {
    let w = motions(&run("G0 X65 Z5\nG92 X58.7 Z-28 F2 H2\n"));
    assert_eq!(w.len(), 9);
    check(&w[2], "thread", 58.7, -28.0, 4.0, 2);
    check(&w[6], "thread", 58.7, -28.0, 4.0, 2);
    assert_eq!((w[2].angle, w[6].angle), (0.0, 180.0));
}

#[test]
fn g92_taper_r_and_modal_retention() {
    let w = motions(&run("G0 X70 Z5\nG92 X60 Z-30 R-2 F2\nX59\n"));
    check(&w[1], "rapid", 56.0, 5.0, 0.0, 1);
    check(&w[2], "thread", 60.0, -30.0, 2.0, 2);
    // Second block: X only; Z-30 and R-2 are kept (§2.15 note 2).
    check(&w[5], "rapid", 55.0, 5.0, 0.0, 1);
    check(&w[6], "thread", 59.0, -30.0, 2.0, 2);
    // R against U with |R| > |U/2| crosses the start point.
    let a = run_err("G0 X60 Z5\nG92 X64 Z-30 R-3 F2\n");
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE, "{a}");
}

/// §2.17.4 example, M68×6: depths 1.8, 1.8√2, 1.8√3, then k − d = 3.58 (√4·1.8 = 3.6 ≥
/// 3.58), then two finishing passes at 3.68. a = 60°: infeed shifted by depth·tan 30° towards
/// −Z; r = 05 → run-out 0.5 × 6 = 3 mm at 45°.
#[test]
fn g76_manual_example_m68x6() {
    let src = "G50 X100 Z50 M3 S300;\nG00 X80 Z10;\nG76 P020560 Q0.15 R0.1;\nG76 X60.64 Z-62 P3.68 Q1.8 F6;\nG00 X100 Z50;\nM30;\n";
    let w = motions(&run(src));
    let depths = [1.8, 1.8 * 2f64.sqrt(), 1.8 * 3f64.sqrt(), 3.58, 3.68, 3.68];
    let steps = [[1, 2, 3, 4], [5, 2, 3, 4], [5, 2, 3, 4], [5, 6, 7, 8], [9, 9, 9, 9], [9, 9, 9, 9]];
    let tan30 = 30f64.to_radians().tan();
    check(&w[0], "rapid", 80.0, 10.0, 0.0, 0);
    let mut i = 1;
    for (dn, st) in depths.iter().zip(steps) {
        let xr = 34.0 - dn; // radius of B_n: B = 30.32 + 3.68
        let z = 10.0 - dn * tan30;
        check(&w[i], "rapid", 2.0 * xr, z, 0.0, st[0]);
        check(&w[i + 1], "thread", 2.0 * xr, -59.0, 6.0, st[1]);
        assert!(!w[i + 1].continuous);
        check(&w[i + 2], "thread", 2.0 * (xr + 3.0), -62.0, 6.0, st[1]);
        assert!(w[i + 2].continuous);
        check(&w[i + 3], "rapid", 80.0, -62.0, 0.0, st[2]);
        check(&w[i + 4], "rapid", 80.0, 10.0, 0.0, st[3]);
        assert_eq!(w[i].cycle.as_deref(), Some("G76"));
        i += 5;
    }
    check(&w[i], "rapid", 100.0, 50.0, 0.0, 0);
    assert_eq!(w.len(), i + 1);
}

#[test]
fn g76_parameters_are_kept_between_cycles() {
    // The first block wrote m = 1, r = 0, a = 0, Δdmin = 0.5, d = 0; a later G76 without
    // the first block uses them.
    let src = "G00 X80 Z10\nG76 P010000 Q0.5 R0\nG76 X70 Z-20 P2 Q1 F2\nG76 X70 Z-20 P2 Q1\n";
    let w = motions(&run(src));
    // Depths (step ⑤: max(√n·Δd, √(n−1)·Δd + Δdmin)): 1, max(√2, 1.5) = 1.5,
    // max(√3, √2 + 0.5) = 1.9142, max(2, √3 + 0.5) → 2 = k: last. Then 1 finishing.
    let xs = [72.0, 71.0, 2.0 * (37.0 - (2f64.sqrt() + 0.5)), 70.0, 70.0]; // B = 35 + 2 (radius)
    assert_eq!(w.len(), 1 + 2 * 5 * 4);
    for half in 0..2 {
        for (j, x) in xs.iter().enumerate() {
            let k = 1 + half * 20 + j * 4;
            check(&w[k], "rapid", *x, 10.0, 0.0, w[k].step);
            check(&w[k + 1], "thread", *x, -20.0, 2.0, w[k + 1].step);
        }
    }
    assert_eq!(w[17].step, 9);
}

/// 004 §2.17.4 step ⑤ to the letter: once the minimum cut applies, the depth is
/// √(n−1)·Δd + Δdmin (not the previous depth + Δdmin): Δd 0.4, Δdmin 0.25, k 1.2 gives
/// 0.4, 0.65, 0.8157, 0.9428, 1.05, 1.1444, then 1.2 (k − d), then the finishing pass.
#[test]
fn g76_minimum_cut_follows_step_5() {
    let w = motions(&run("G0 X26 Z4\nG76 P010060 Q0.25 R0\nG76 X20.8 Z-20 P1.2 Q0.4 F2\nM30\n"));
    let s = |n: f64| n.sqrt() * 0.4;
    let depths = [0.4, s(1.0) + 0.25, s(2.0) + 0.25, s(3.0) + 0.25, s(4.0) + 0.25, s(5.0) + 0.25, 1.2, 1.2];
    assert!((depths[2] - 0.8157).abs() < 1e-4 && (depths[5] - 1.1444).abs() < 1e-4);
    let threads: Vec<_> = w.iter().filter(|m| m.kind == "thread").collect();
    assert_eq!(threads.len(), depths.len(), "7 rough passes and 1 finishing pass");
    for (t, d) in threads.iter().zip(depths) {
        // B = 10.4 + 1.2 = 11.6 (radius); the cut is at B − d.
        assert!((t.x - 2.0 * (11.6 - d)).abs() < 1e-3, "pass at X{} for depth {d}", t.x);
    }
}

#[test]
fn g76_first_depth_larger_than_height_gives_one_rough_pass() {
    // Note 6. Defaults: m = 1, d = 0.
    let w = motions(&run("G00 X80 Z10\nG76 X70 Z-20 P2 Q5 F2\n"));
    assert_eq!(w.len(), 1 + 4 + 4);
    check(&w[1], "rapid", 70.0, 10.0, 0.0, 1);
    check(&w[5], "rapid", 70.0, 10.0, 0.0, 9);
}

#[test]
fn g76_alarms() {
    let num = |s: &str| run_err(&format!("G00 X80 Z10\n{s}\n")).number;
    assert_eq!(num("G76 X70 Z-20 Q1 F2"), 62); // no P(k)
    assert_eq!(num("G76 X70 Z-20 P2 F2"), 62); // no Q(Δd)
    assert_eq!(num("G76 P010060 Q3\nG76 X70 Z-20 P2 Q1 F2"), 62); // note 7: Δdmin > k
    assert_eq!(num("G76 R2.5\nG76 X70 Z-20 P2 Q1 F2"), 62); // note 7: d > k
    assert_eq!(num("G76 X70 W0 P2 Q1 F2"), 62); // face thread
    assert_eq!(num("G76 P000560"), 62); // m = 0
    assert_eq!(num("G76 P0205.6"), 7);
    assert_eq!(num("G76 P019960\nG76 X70 Z-5 P2 Q1 F2"), 2510); // note 8: run-out 19.8 > 15
    assert_eq!(num("G76 X70 Z-20 P2 Q0.0001 F2"), 62); // too many passes
}

/// §2.17.2 example as printed: first lead 4 mm, +0.2 mm per revolution.
#[test]
fn g34_manual_example() {
    let src = "G00 X60 Z4 M03 S500;\nG00 U-10;\nG00 U-0.7;\nG34 W-78 F4 K0.2;\nG00 U10;\nZ4;\nG00 X50;\nG00 U-1.0;\nG34 W-78 F4 K0.2;\nG00 U10;\nZ4;\nM30;\n";
    let m = run(src);
    let w = motions(&m);
    check(&w[2], "rapid", 49.3, 4.0, 0.0, 0);
    check(&w[3], "thread", 49.3, -74.0, 4.0, 0);
    check(&w[4], "rapid", 59.3, -74.0, 0.0, 0);
    check(&w[5], "rapid", 59.3, 4.0, 0.0, 0);
    check(&w[7], "rapid", 49.0, 4.0, 0.0, 0);
    check(&w[8], "thread", 49.0, -74.0, 4.0, 0);
    let incs: Vec<f64> = m
        .iter()
        .filter_map(|m| match m.kind {
            cncgw::canon::MoveKind::Thread { lead_inc, .. } => Some(lead_inc),
            _ => None,
        })
        .collect();
    assert_eq!(incs, [0.2, 0.2]);
}

#[test]
fn g34_lead_range() {
    let num = |s: &str| run_err(&format!("G00 X60 Z4\n{s}\n")).number;
    assert_eq!(num("G34 W-78 F4"), 14); // K missing
    assert_eq!(num("G34 W-78 F4 K0.001"), 14);
    assert_eq!(num("G34 W-78 F4 K500"), 14);
    // 4² − 2·0.2·78 < 0: the lead would reach zero.
    assert_eq!(num("G34 W-78 F4 K-0.2"), 14);
    // √(400² + 2·400·78) ≈ 474 ok; F480 K400 → 537 > 500.
    assert_eq!(num("G34 W-78 F480 K400"), 14);
    // Consecutive G32 → G34 is one continuous thread.
    let m = run("G00 X60 Z4\nG32 W-10 F4\nG34 W-20 F4 K0.1\n");
    let w = motions(&m);
    assert!(!w[1].continuous && w[2].continuous);
}

/// Manual 002's G78 example. As printed, P020545 has r = 05, outside the infeed-mode range
/// 0–4 the same page gives, so it is refused (alarm 62) rather than guessed.
#[test]
fn g78_manual_example_as_printed_is_refused() {
    let a = run_err("G00 X80 Z10\nG78 P020545 Q0.15 R0.5\nG78 X60 Z-60 P3 Q1.8 F300 J1.5 K2\nG00 X80 Z10\n");
    assert_eq!(a.number, 62, "{a}");
    assert!(a.message.contains("infeed mode"), "{a}");
}

/// The same example with r = 00 (centre infeed): decreasing depths 1.8, then k − d = 2.5
/// (√2·1.8 ≥ 2.5), two finishing passes at k = 3; run-out K2 on Z, J1.5 on X.
#[test]
fn g78_example_with_centre_infeed() {
    let w = motions(&run("G00 X80 Z10\nG78 P020045 Q0.15 R0.5\nG78 X60 Z-60 P3 Q1.8 F300 J1.5 K2\nG00 X80 Z10\n"));
    let mut i = 1;
    for (dn, st) in [(1.8, [3, 4, 5, 5]), (2.5, [3, 4, 5, 5]), (3.0, [7, 7, 8, 8]), (3.0, [7, 7, 8, 8])] {
        let xr = 33.0 - dn;
        check(&w[i], "rapid", 2.0 * xr, 10.0, 0.0, st[0]);
        check(&w[i + 1], "thread", 2.0 * xr, -58.0, 300.0, st[1]);
        check(&w[i + 2], "thread", 2.0 * (xr + 1.5), -60.0, 300.0, st[1]);
        check(&w[i + 3], "rapid", 80.0, -60.0, 0.0, st[2]);
        check(&w[i + 4], "rapid", 80.0, 10.0, 0.0, st[3]);
        assert_eq!(w[i].cycle.as_deref(), Some("G78"));
        i += 5;
    }
    assert_eq!(w.len(), i + 1);
}

#[test]
fn g78_infeed_modes_and_constant_depth() {
    let t = 22.5f64.to_radians().tan();
    // Left/right alternating (4), constant depth (D0): depths 1, 2, then 2.5, finishing at the
    // last rough pass's Z.
    let src = "G00 X80 Z10\nG78 P010445 Q0 R0.5 D0\nG78 X60 Z-60 P3 Q1 F2\n";
    let w = motions(&run(src));
    let exp = [(1.0, -1.0), (2.0, 1.0), (2.5, -1.0), (3.0, -1.0)];
    for (j, (dn, s)) in exp.iter().enumerate() {
        let shift = if j == 3 { -2.5 * t } else { s * dn * t };
        check(&w[1 + 4 * j], "rapid", 2.0 * (33.0 - dn), 10.0 + shift, 0.0, w[1 + 4 * j].step);
    }
    // Right flank (2) keeps shifting +Z.
    let w = motions(&run("G00 X80 Z10\nG78 P010245 Q0 R0\nG78 X60 Z-60 P3 Q1 F2\n"));
    check(&w[1], "rapid", 64.0, 10.0 + t, 0.0, 3);
    // E and L are not described by the manual.
    assert_eq!(run_err("G00 X80 Z10\nG78 P010245 E1\n").number, 10);
}
