//! G71 and G70 (manual 004 §2.16.1, §2.16.4).

use crate::cycles_common;
use cycles_common::*;

/// §2.16.1 example as printed, with G98 first (the machine powers on in G99; F200 is mm/min).
const G71_EXAMPLE: &str = "G98\nG00 X200 Z10 M03 S800;\nG71 U2 R1 F200;\nG71 P80 Q120 U0.5 W2.0;\nN80 G00 X40 S1200;\n\
G01 Z-30 F100;\nX60 W-30;\nW-20;\nN120 X100 W-10;\nG70 P80 Q120;\nM30;\n";

/// Z of the rough contour (finishing contour + (Δu/2, Δw) = (0.25, 2)) at radius `x`.
fn rough_z(x: f64) -> f64 {
    let pts: [(f64, f64); 4] = [(20.25, -28.0), (30.25, -58.0), (30.25, -78.0), (50.25, -88.0)];
    for w in pts.windows(2) {
        let ((x0, z0), (x1, z1)) = (w[0], w[1]);
        if x >= x0.min(x1) && x <= x0.max(x1) {
            return if x1 == x0 { z0 } else { z0 + (x - x0) / (x1 - x0) * (z1 - z0) };
        }
    }
    -88.0 // above C': the pass runs to C''s Z
}

#[test]
fn g71_g70_manual_example() {
    let m = run(G71_EXAMPLE);
    let w = motions(&m);
    check(&w[0], "rapid", 200.0, 10.0, 0.0, 0);
    // Δd = 2 (radius): passes at depth 2k while 2k < 100 − 20.25 → k = 1..39.
    let mut i = 1;
    for k in 1..=39 {
        let xr = 100.0 - 2.0 * k as f64;
        let z = rough_z(xr);
        check(&w[i], "rapid", 2.0 * xr, 10.0, 0.0, 1); // ns is G00: rapid infeed
        check(&w[i + 1], "feed", 2.0 * xr, z, 200.0, 2);
        check(&w[i + 2], "feed", 2.0 * (xr + 1.0), z + 1.0, 200.0, 3); // 45° by e = 1
        check(&w[i + 3], "rapid", 2.0 * (xr + 1.0), 10.0, 0.0, 4);
        i += 4;
    }
    // Last pass along the rough contour B'→C', then back to A.
    check(&w[i], "rapid", 40.5, 12.0, 0.0, 5);
    check(&w[i + 1], "feed", 40.5, -28.0, 200.0, 6);
    check(&w[i + 2], "feed", 60.5, -58.0, 200.0, 6);
    check(&w[i + 3], "feed", 60.5, -78.0, 200.0, 6);
    check(&w[i + 4], "feed", 100.5, -88.0, 200.0, 6);
    check(&w[i + 5], "rapid", 200.0, -88.0, 0.0, 7); // X out first, then Z
    check(&w[i + 6], "rapid", 200.0, 10.0, 0.0, 7);
    i += 7;
    // The contour blocks are not run after G71; G70 runs them with their own F (and S1200).
    check(&w[i], "rapid", 40.0, 10.0, 0.0, 1);
    check(&w[i + 1], "feed", 40.0, -30.0, 100.0, 1);
    check(&w[i + 2], "feed", 60.0, -60.0, 100.0, 1);
    check(&w[i + 3], "feed", 60.0, -80.0, 100.0, 1);
    check(&w[i + 4], "feed", 100.0, -90.0, 100.0, 1);
    check(&w[i + 5], "rapid", 200.0, 10.0, 0.0, 2);
    assert_eq!(w[i].cycle.as_deref(), Some("G70"));
    assert_eq!(w.len(), i + 6);
    // S1200 only takes effect in G70: exactly one spindle change to 1200 rpm, after G71.
    let s: Vec<f64> = m
        .iter()
        .filter_map(|m| match &m.kind {
            cncgw::canon::MoveKind::Spindle(c) => Some(c.rpm),
            _ => None,
        })
        .collect();
    assert_eq!(s, [800.0, 1200.0]);
    // The contour's lines are reported as the G70 moves' source.
    let g70_first = m.iter().find(|m| m.tag.as_ref().is_some_and(|t| &*t.cycle == "G70")).unwrap();
    assert_eq!(g70_first.src.line, 5);
}

#[test]
fn g71_depth_and_retract_are_kept() {
    // No.5147/5148 written by the first block serve a later G71 without it.
    let src = "G98 G00 X60 Z2\nG71 U1.5 R0.5 F100\nG71 P1 Q2\nN1 G01 X50\nN2 Z-10\nG00 X60 Z2\nG71 P1 Q2\n";
    let w = motions(&run(src));
    // depth 5 (radius): passes at 1.5, 3.0, 4.5, then the contour.
    let n = w.iter().filter(|w| w.step == 2).count();
    assert_eq!(n, 6);
    check(&w[3], "feed", 58.0, -9.5, 100.0, 3); // level above C': to C's Z, 45° back by 0.5
}

#[test]
fn g71_alarms() {
    let num = |s: &str| run_err(&format!("G98 G00 X60 Z2\nG71 U1 R0.5 F100\n{s}")).number;
    assert_eq!(num("G71 P1\nN1 G01 X50\nN2 Z-10\n"), 61);
    assert_eq!(num("G71 P1 Q3\nN1 G01 X50\nN2 Z-10\n"), 63);
    assert_eq!(num("G71 P1 Q2\nN1 X50\nN2 Z-10\n"), 65); // ns without G00/G01
    assert_eq!(num("G71 P1 Q2\nN1 G01 X50\nN2 G32 Z-10\n"), 66);
    assert_eq!(num("G71 P1 Q3\nN1 G01 X50\nN2 G04 P10\nG28 U0\nN3 Z-10\n"), 66);
    // Not monotonic in X (a pocket): type I refuses it.
    assert_eq!(num("G71 P1 Q3\nN1 G01 X40\nZ-10\nX30 Z-15\nN3 X60 Z-20\n"), 64);
    assert_eq!(num("G71 P1 Q3\nN1 G01 X40 Z0\nZ-10\nN3 X50 Z-5\n"), 64); // type II, Z turns back (note 4)
    assert_eq!(run_err("G98 G00 X60 Z2\nG71 P1 Q2 F100\nN1 G01 X50\nN2 Z-10\n").number, 62);
    // no Δd
}

#[test]
fn g71_contour_with_arc_cuts_to_the_arc() {
    // Contour: X20 → Z-10 → G02 to X40 Z-20 (R10, centre (X20, Z-20) radius 10 … as radius
    // values: centre x = 10, z = -20).
    let src = "G98 G00 X44 Z2\nG71 U2 R0.5 F100\nG71 P1 Q3\nN1 G00 X20\nG01 Z-10\nN3 G02 X40 Z-20 R10\n";
    let w = motions(&run(src));
    // Levels radius 20, 18, 16, 14, 12 (depth 2..10 < 12). At radius x the arc's Z is
    // -10 - sqrt(100 - (x-10)^2)... the centre is (10, -20)? A G02 from (10,-10) to (20,-20)
    // with R10 has its centre at (20, -10): z = -10 - sqrt(100 - (x - 20)^2).
    for (j, xr) in [20.0, 18.0, 16.0, 14.0, 12.0].iter().enumerate() {
        let expect = -10.0 - (100.0 - (xr - 20.0f64).powi(2)).sqrt();
        let cut = &w[1 + 4 * j + 1];
        assert!((cut.x - 2.0 * xr).abs() < 1e-9);
        assert!((cut.z - expect).abs() < 0.02, "level {xr}: {} vs {expect}", cut.z);
    }
    let arc = w.iter().find(|w| w.kind == "arc").expect("the contour pass keeps the arc");
    assert_eq!(arc.step, 6);
}

/// §2.16.2 example as printed, with G98 first (F300 is mm/min) and M30 added.
#[test]
fn g72_manual_example() {
    let src = "G98\nG00 X176 Z10 M3 S500 T0202;\nG72 W2.0 R0.5 F300;\nG72 P10 Q20 U0.2 W0.1;\nN10 G00 Z-55 S800;\n\
G01 X160 F120;\nX80 W20;\nW15;\nN20 X40 W20;\nG70 P10 Q20;\nM30;\n";
    let w = motions(&run(src));
    // Rough contour (radius X, Z) = finishing contour + (0.1, 0.1).
    let pts: [(f64, f64); 5] = [(-54.9, 88.1), (-54.9, 80.1), (-34.9, 40.1), (-19.9, 40.1), (0.1, 20.1)];
    let rough_x = |z: f64| {
        for s in pts.windows(2) {
            let ((z0, x0), (z1, x1)) = (s[0], s[1]);
            if z >= z0.min(z1) && z <= z0.max(z1) && z1 != z0 {
                return x0 + (z - z0) / (z1 - z0) * (x1 - x0);
            }
        }
        20.1
    };
    check(&w[0], "rapid", 176.0, 10.0, 0.0, 0);
    let mut i = 1;
    // Δd = 2 in Z: passes at Z8 … Z-54 (depth 64 < 64.9).
    for k in 1..=32 {
        let z = 10.0 - 2.0 * k as f64;
        let x = rough_x(z);
        check(&w[i], "rapid", 176.0, z, 0.0, 1);
        check(&w[i + 1], "feed", 2.0 * x, z, 300.0, 2);
        check(&w[i + 2], "feed", 2.0 * (x + 0.5), z + 0.5, 300.0, 3);
        check(&w[i + 3], "rapid", 176.0, z + 0.5, 0.0, 4);
        assert_eq!(w[i].cycle.as_deref(), Some("G72"));
        i += 4;
    }
    check(&w[i], "rapid", 176.2, -54.9, 0.0, 5);
    for (j, (z, x)) in pts[1..].iter().enumerate() {
        check(&w[i + 1 + j], "feed", 2.0 * x, *z, 300.0, 6);
    }
    check(&w[i + 5], "rapid", 40.2, 10.0, 0.0, 7); // Z out of the face first, then X
    check(&w[i + 6], "rapid", 176.0, 10.0, 0.0, 7);
    i += 7;
    // G70.
    for (j, (x, z, f)) in
        [(176.0, -55.0, 0.0), (160.0, -55.0, 120.0), (80.0, -35.0, 120.0), (80.0, -20.0, 120.0), (40.0, 0.0, 120.0)].iter().enumerate()
    {
        check(&w[i + j], if j == 0 { "rapid" } else { "feed" }, *x, *z, *f, 1);
    }
    check(&w[i + 5], "rapid", 176.0, 10.0, 0.0, 2);
    assert_eq!(w.len(), i + 6);
}

/// §2.16.3 example as printed: three passes offset (Δi + Δu/2, Δk + Δw) = (16, 16),
/// (8.5, 8.5), (1, 1) (radius), each a copy of the contour.
#[test]
fn g73_manual_example() {
    let src = "G99 G00 X200 Z10 M3 S500;\nG73 U15 W15 R3;\nG73 P1 Q2 U2 W1 F0.3;\nN1 G0 X80 Z0;\nG01 W-20 F0.15 S600;\n\
X120 W-10;\nW-20;\nG02 X160 W-20 R20;\nN2 G01 X180 W-10;\nG70 P1 Q2;\nM30;\n";
    let w = motions(&run(src));
    check(&w[0], "rapid", 200.0, 10.0, 0.0, 0);
    let contour = [(80.0, 0.0), (80.0, -20.0), (120.0, -30.0), (120.0, -50.0), (160.0, -70.0), (180.0, -80.0)];
    let mut i = 1;
    for o in [16.0, 8.5, 1.0] {
        check(&w[i], "rapid", 200.0 + 2.0 * o, 10.0 + o, 0.0, 1);
        check(&w[i + 1], "rapid", 80.0 + 2.0 * o, o, 0.0, 2);
        for (j, (x, z)) in contour[1..].iter().enumerate() {
            let kind = if j == 3 { "arc" } else { "feed" };
            let f = if kind == "arc" { 0.0 } else { 0.3 };
            check(&w[i + 2 + j], kind, x + 2.0 * o, z + o, f, 3);
        }
        check(&w[i + 7], "rapid", 200.0, 10.0, 0.0, 4);
        assert_eq!(w[i].cycle.as_deref(), Some("G73"));
        i += 8;
    }
    // G70: the contour with its own F0.15.
    check(&w[i], "rapid", 80.0, 0.0, 0.0, 1);
    check(&w[i + 1], "feed", 80.0, -20.0, 0.15, 1);
    check(&w[i + 5], "feed", 180.0, -80.0, 0.15, 1);
    check(&w[i + 6], "rapid", 200.0, 10.0, 0.0, 2);
    assert_eq!(w.len(), i + 7);
}

/// An ID contour (infeed +X, Δu < 0): passes grow outwards, the allowance moves the rough
/// contour inwards, and ⑦ leaves the bore along X before Z.
#[test]
fn g71_inside_diameter() {
    let w = motions(&run("G98 G00 X20 Z2\nG71 U2 R0.5 F100\nG71 P1 Q3 U-0.5 W0.1\nN1 G00 X60\nG01 Z-20\nN3 X40 Z-30\n"));
    check(&w[1], "rapid", 24.0, 2.0, 0.0, 1);
    check(&w[2], "feed", 24.0, -29.9, 100.0, 2);
    check(&w[3], "feed", 23.0, -29.4, 100.0, 3);
    // Level X44 (radius 22) meets the rough taper from (29.75, -19.9) to (19.75, -29.9).
    check(&w[22], "feed", 44.0, -27.65, 100.0, 2);
    let n = w.len();
    check(&w[n - 5], "rapid", 59.5, 2.1, 0.0, 5);
    check(&w[n - 3], "feed", 39.5, -29.9, 100.0, 6);
    check(&w[n - 2], "rapid", 20.0, -29.9, 0.0, 7);
    check(&w[n - 1], "rapid", 20.0, 2.0, 0.0, 7);
}

#[test]
fn g71_too_many_passes_alarms_before_any_move() {
    let src = "G98 G00 X200 Z2\nG71 U0.001 R0.5 F100\nG71 P1 Q2\nN1 G00 X20\nN2 G01 Z-10\n";
    let it = cncgw::interp::Interpreter::from_source("t.nc", src, &cncgw::config::MachineConfig::embedded()).unwrap();
    let out: Vec<_> = it.collect();
    let tagged = out.iter().filter(|m| matches!(m, Ok(m) if m.tag.is_some())).count();
    assert_eq!(tagged, 0);
    assert!(out.iter().any(|m| matches!(m, Err(a) if a.number == 62)));
}
