//! G40/G41/G42 tool nose radius compensation (manual 004 §2.18): the compensated points of
//! known contours, worked out by hand for a nose radius of 0.4 mm and imaginary tip 3.

use cncgw::canon::{Move, MoveKind};
use cncgw::config::MachineConfig;
use cncgw::interp::{parse_tool_table, Interpreter};
use cncgw::Alarm;

const TABLE: &str = "
[1]
r = 0.4
tip = 3
[2]
r = 0.4
tip = 0
[3]
r = 0.4
tip = 8
";

fn interp(src: &str) -> Interpreter {
    let mut it = Interpreter::from_source("t.nc", src, &MachineConfig::embedded()).unwrap_or_else(|e| panic!("{e:?}"));
    it.set_tool_table(parse_tool_table("tools.toml", TABLE).expect("table"));
    it
}

fn run(src: &str) -> Vec<Move> {
    interp(src).map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

fn alarm(src: &str) -> Alarm {
    for m in interp(src) {
        if let Err(a) = m {
            return a;
        }
    }
    panic!("no alarm")
}

/// (kind, X diameter, Z) of every motion.
fn pts(m: &[Move]) -> Vec<(&'static str, f64, f64)> {
    m.iter().filter_map(|m| m.kind.end().map(|e| (m.kind.name(), 2.0 * e.x, e.z))).collect()
}

fn assert_pts(got: &[(&str, f64, f64)], want: &[(&str, f64, f64)]) {
    assert_eq!(got.len(), want.len(), "{got:?}");
    for (g, w) in got.iter().zip(want) {
        assert_eq!(g.0, w.0, "{got:?}");
        assert!((g.1 - w.1).abs() < 1e-4 && (g.2 - w.2).abs() < 1e-4, "got {g:?}, want {w:?}\n{got:?}");
    }
}

/// R(2 − √2): how far a tip-3 imaginary tip moves along Z on a 45° chamfer.
const C45: f64 = 0.4 * (2.0 - std::f64::consts::SQRT_2);

#[test]
fn chamfer_and_shoulder_of_an_od_contour() {
    let m = run("T0101\nG0 X16 Z2\nG42 G1 Z0 F0.1\nG1 X20 Z-2\nZ-20\nG40 G0 X30\nM30\n");
    assert_pts(
        &pts(&m),
        &[
            ("rapid", 16.0, 2.0),
            // Start-up: shortening (α = 225°), the offset lines meet R·tan(22.5°) before Z0.
            ("feed", 16.0, -C45),
            // Chamfer → cylinder: lengthening (α = 135°).
            ("feed", 20.0, -2.0 - C45),
            // Cylinder → the G40 move up +X: shortening (α = 270°), the tip-3 corner is the
            // programmed corner itself.
            ("feed", 20.0, -20.0),
            ("rapid", 30.0, -20.0),
        ],
    );
}

#[test]
fn tip_0_offsets_the_nose_centre() {
    let m = run("T0202\nG0 X16 Z2\nG42 G1 Z0 F0.1\nZ-10\nG40 G0 X30\nM30\n");
    // The centre runs R above the cylinder; at the corner with the G40 move it stops R
    // before Z-10.
    assert_pts(&pts(&m), &[("rapid", 16.0, 2.0), ("feed", 16.8, 0.0), ("feed", 16.8, -9.6), ("rapid", 30.0, -10.0)]);
}

#[test]
fn fillet_arc_shrinks_by_the_radius_and_its_centre_moves_with_the_tip() {
    let m = run("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nZ-10\nG2 X30 Z-15 R5\nG1 X40\nG40 G0 X50\nM30\n");
    assert_pts(
        &pts(&m),
        &[("rapid", 20.0, 2.0), ("feed", 20.0, -0.4), ("feed", 20.0, -10.4), ("arc", 29.2, -15.0), ("feed", 39.2, -15.0), ("rapid", 50.0, -15.0)],
    );
    let arc = m.iter().find_map(|m| match &m.kind {
        MoveKind::Arc { center, cw, .. } => Some((*center, *cw)),
        _ => None,
    });
    let (c, cw) = arc.expect("an arc");
    assert!(cw);
    // Centre (Z-10, X radius 15) shifted by the tip vector R·(−1, −1).
    assert!((c.z + 10.4).abs() < 1e-9 && (c.x - 14.6).abs() < 1e-9, "{c:?}");
}

#[test]
fn acute_outer_corner_inserts_a_line() {
    let m = run("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nZ-10\nX10 Z-5\nG40 G0 X40\nM30\n");
    let p = pts(&m);
    // α = 45°: the cylinder's offset line is extended by R (centre Z-10.4), then one line to
    // the back cut's offset line extended backwards by R.
    let s = std::f64::consts::FRAC_1_SQRT_2 * 0.4;
    assert_pts(&p[..4], &[("rapid", 20.0, 2.0), ("feed", 20.0, -0.4), ("feed", 20.0, -10.8), ("feed", 19.2, -10.0 - 2.0 * s - 0.4)]);
    assert!(p.len() >= 6, "{p:?}");
}

#[test]
fn groove_narrower_than_the_nose_is_interference_3605() {
    let a = alarm("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nZ-10\nX18\nZ-10.5\nX20\nZ-20\nG40 G0 X30\nM30\n");
    assert_eq!(a.number, cncgw::alarm::NOSE_INTERFERENCE, "{a}");
    assert_eq!(a.pos.as_ref().map(|p| p.line), Some(6), "{a}");
}

#[test]
fn the_manual_alarms() {
    // Note 2: G41 ↔ G42 without G40.
    let a = alarm("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nG41 Z-5\nM30\n");
    assert_eq!((a.number, a.pos.as_ref().map(|p| (p.line, p.col))), (3576, Some((4, 1))), "{a}");
    // Note 3: T during compensation.
    let a = alarm("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nT0202\nM30\n");
    assert_eq!(a.number, cncgw::alarm::NOSE_T_CODE, "{a}");
    // Note 1: the path turns back (corner angle under 0.1°).
    let a = alarm("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nZ-10\nZ0\nG40 G0 X30\nM30\n");
    assert_eq!((a.number, a.pos.as_ref().map(|p| p.line)), (3607, Some(5)), "{a}");
    // Start-up and cancel on an arc (Fanuc PS0034).
    let a = alarm("T0101\nG0 X20 Z2\nG42 G2 X22 Z1 R1 F0.1\nM30\n");
    assert_eq!(a.number, cncgw::alarm::NOSE_ARC_STARTUP, "{a}");
    let a = alarm("T0101\nG0 X20 Z2\nG42 G1 Z0 F0.1\nG40 G2 X22 Z-1 R1\nM30\n");
    assert_eq!(a.number, cncgw::alarm::NOSE_ARC_STARTUP, "{a}");
}

#[test]
fn cycles_keep_their_programmed_points() {
    // §2.16 note 5 (G71–G76): a cycle's moves are not offset. A straight G90 with tip 3 is
    // offset, but the tip-3 point of a nose touching lines along the axes is the programmed
    // point itself, so it keeps its path too.
    let plain = run("T0101\nG0 X50 Z2\nG90 X40 Z-20 F0.2\nG0 X60\nM30\n");
    let comp = run("T0101\nG0 X50 Z2\nG42\nG90 X40 Z-20 F0.2\nG40\nG0 X60\nM30\n");
    assert_eq!(pts(&plain), pts(&comp));
    let plain = run("T0101\nG0 X50 Z2\nG71 U1 R0.5\nG71 P10 Q20 U0.2 W0.1 F0.2\nN10 G0 X30\nG1 Z-20\nN20 X50\nG0 X60\nM30\n");
    let comp = run("T0101\nG0 X50 Z2\nG42\nG71 U1 R0.5\nG71 P10 Q20 U0.2 W0.1 F0.2\nN10 G0 X30\nG1 Z-20\nN20 X50\nG40\nG0 X60\nM30\n");
    assert_eq!(pts(&plain), pts(&comp));
}

#[test]
fn without_a_tool_radius_the_path_is_unchanged() {
    let src = "G0 X16 Z2\nG42 G1 Z0 F0.1\nG1 X20 Z-2\nZ-20\nG40 G0 X30\nM30\n";
    let m: Vec<Move> = Interpreter::from_source("t.nc", src, &MachineConfig::embedded()).unwrap().map(|m| m.unwrap()).collect();
    assert_pts(&pts(&m), &[("rapid", 16.0, 2.0), ("feed", 16.0, 0.0), ("feed", 20.0, -2.0), ("feed", 20.0, -20.0), ("rapid", 30.0, -20.0)]);
}

#[test]
fn g70_runs_the_contour_compensated() {
    // G42 at N10 and G40 at N20 inside the contour: G71 roughs the programmed contour, G70
    // finishes it with the nose radius compensated (tip 3, R0.4).
    let src = "T0101\nG0 X60 Z2\nG71 U1 R0.5 F0.2\nG71 P10 Q20\nN10 G42 G0 X20\nG1 Z-10 F0.1\nN20 G40 X60\nG70 P10 Q20\nM30\n";
    let m = run(src);
    let g70: Vec<_> = m.iter().filter(|m| m.tag.as_ref().is_some_and(|t| &*t.cycle == "G70")).collect();
    let p = pts(&g70.iter().map(|m| (*m).clone()).collect::<Vec<_>>());
    // Start-up on the ns rapid: shortening (α = 270°), the tip-3 point lands R before Z2 on
    // the offset of the face line; the cylinder then ends on the cancel move's offset line.
    assert_pts(&p, &[("rapid", 20.0, 1.2), ("feed", 20.0, -10.0), ("feed", 60.0, -10.0), ("rapid", 60.0, 2.0)]);
    // The G71 passes themselves are not compensated: the last pass ends on the programmed
    // contour (X20 Z-10 → X60).
    let g71: Vec<Move> = m.iter().filter(|m| m.tag.as_ref().is_some_and(|t| &*t.cycle == "G71")).cloned().collect();
    assert!(pts(&g71).iter().any(|w| w.0 == "feed" && (w.1 - 20.0).abs() < 1e-9 && (w.2 + 10.0).abs() < 1e-9));
}

#[test]
fn g52_ends_the_offset_for_a_moment() {
    // §2.12.3 note 2. Tip 0, R0.4: the cylinder's offset ends perpendicular at Z-10 before
    // G52, and the next move starts up again from there.
    let m = run("T0202\nG0 X16 Z2\nG42 G1 Z-10 F0.1\nG52 W0\nG1 Z-20\nG40 G0 X30\nM30\n");
    assert_pts(&pts(&m), &[("rapid", 16.0, 2.0), ("feed", 16.8, -10.0), ("feed", 16.8, -19.6), ("rapid", 30.0, -20.0)]);
}

/// The G90/G94 moves (kind, X diameter, Z) of a program.
fn cycle_pts(m: &[Move], cycle: &str) -> Vec<(&'static str, f64, f64)> {
    let c: Vec<Move> = m.iter().filter(|m| m.tag.as_ref().is_some_and(|t| &*t.cycle == cycle)).cloned().collect();
    pts(&c)
}

/// G90 under G42 (manual 004 is silent; Fanuc 0i-TF): the manual's taper passes (§2.15.1
/// example, `G00 X120 Z-30; G90 X120 Z-44 F150; Z-56 R-15`). ③ has no length there (C
/// is at A's X), so ② runs on its offset line until the tip reaches X120. Tip 3, R0.4: the
/// nose centre runs R inside the taper, the tip point R·(−1, −1) from it, so the tip runs
/// 0.4·(0.8815 + 0.4722 − 1) = 0.1415 mm below the programmed taper: B (on Z-30) and C (on
/// X120) move along it. Tip 8: the tip is R straight below the centre (worked out separately
/// from the nose circle tangent to the taper).
#[test]
fn g90_taper_is_offset_by_the_tip() {
    let src = |t: &str| format!("{t}\nG0 X130 Z3\nG0 X120 Z-30\nG42\nG90 X120 Z-44 R-7.5 F150\nZ-56 R-15\nG40\nG0 X130\nM30\n");
    let m = run(&src("T0101"));
    assert_pts(
        &cycle_pts(&m, "G90"),
        &[
            ("rapid", 104.67899, -30.0),
            ("feed", 120.0, -44.29961),
            ("rapid", 120.0, -30.0),
            ("rapid", 89.66205, -30.0),
            ("feed", 120.0, -56.29289),
            ("rapid", 120.0, -30.0),
        ],
    );
    let m = run(&src("T0303"));
    assert_pts(
        &cycle_pts(&m, "G90"),
        &[
            ("rapid", 105.10756, -30.0),
            ("feed", 120.0, -43.89961),
            ("rapid", 120.0, -30.0),
            ("rapid", 90.12359, -30.0),
            ("feed", 120.0, -55.89289),
            ("rapid", 120.0, -30.0),
        ],
    );
    // Without G42 the same passes are the programmed ones.
    let m = run("T0101\nG0 X130 Z3\nG0 X120 Z-30\nG90 X120 Z-44 R-7.5 F150\nM30\n");
    assert_pts(&cycle_pts(&m, "G90"), &[("rapid", 105.0, -30.0), ("feed", 120.0, -44.0), ("rapid", 120.0, -30.0)]);
}

/// A straight G90 with tip 8 (the tip R below the nose centre): the cylinder's line is the
/// tip's, but the shoulder ③ is touched by the nose's side, the centre R before Z-20: C and
/// D move to Z-19.6.
#[test]
fn g90_straight_tip_8_stops_r_before_the_shoulder() {
    let want = [("rapid", 40.0, 2.0), ("feed", 40.0, -19.6), ("feed", 50.0, -19.6), ("rapid", 50.0, 2.0)];
    let m = run("T0303\nG0 X50 Z2\nG42\nG90 X40 Z-20 F0.2\nG40\nG0 X60\nM30\n");
    assert_pts(&cycle_pts(&m, "G90"), &want);
    // The side comes from the cycle and the tip, not from G41/G42 (Fanuc).
    let m = run("T0303\nG0 X50 Z2\nG41\nG90 X40 Z-20 F0.2\nG40\nG0 X60\nM30\n");
    assert_pts(&cycle_pts(&m, "G90"), &want);
}

/// G94 under G42, the manual's taper face (§2.15.2 example, `G00 X120 Z0; G94 X108 Z-30
/// R-10`): ② (B Z-40 → C Z-30 at X108) offset inside, ③ (Z retract at X108) is a line along
/// Z, where tip 3 and tip 8 both put the tip on the programmed X; ② moves by the tip.
#[test]
fn g94_taper_is_offset_by_the_tip() {
    let m = run("T0101\nG0 X120 Z0\nG42\nG94 X108 Z-30 R-10 F0.2\nG40\nG0 X130\nM30\n");
    assert_pts(&cycle_pts(&m, "G94"), &[("rapid", 120.0, -40.28921), ("feed", 108.0, -30.28921), ("feed", 108.0, 0.0), ("rapid", 120.0, 0.0)]);
    let m = run("T0303\nG0 X120 Z0\nG42\nG94 X108 Z-30 R-10 F0.2\nG40\nG0 X130\nM30\n");
    assert_pts(&cycle_pts(&m, "G94"), &[("rapid", 120.0, -39.88921), ("feed", 108.0, -29.88921), ("feed", 108.0, 0.0), ("rapid", 120.0, 0.0)]);
}

/// A G90 pass shorter than the nose allows: with tip 8 the shoulder pushes C R back, past
/// the start of a 0.1 mm long cut — interference 3605 at the cycle block, before any move.
#[test]
fn g90_too_short_for_the_nose_is_3605() {
    let a = alarm("T0303\nG0 X50 Z0\nG42\nG90 X49.8 Z-0.1 F0.2\nG40\nM30\n");
    assert_eq!((a.number, a.pos.as_ref().map(|p| p.line)), (3605, Some(4)), "{a}");
}

/// Interference beyond one pair of blocks (3605): a hook — the contour runs back under
/// itself (Z-5 → X38.8 Z-4.2 → X39.4 Z-3.3), a short step down (X37.4) and on along Z-8.3
/// 0.3 mm (radius) under the hook's point. Every pair of neighbouring blocks compensates
/// cleanly, but on the last cut the nose (tip 0, R0.4: its centre at X38.2, 0.6 mm in
/// radius from the point X38.8 Z-4.2) would cut 0.1 mm into the hook three blocks back. The
/// check over the look-ahead finds it before anything of it is emitted.
#[test]
fn interference_three_blocks_ahead_is_3605() {
    let src = "T0202\nG0 X44 Z2\nG42 G1 X40 Z0 F0.1\nZ-5\nX38.8 Z-4.2\nX39.4 Z-3.3\nX37.4\nZ-8.3\nG40 G0 X50\nM30\n";
    let mut it = interp(src);
    let mut got = Vec::new();
    let a = loop {
        match it.next() {
            Some(Ok(m)) => got.push(m),
            Some(Err(a)) => break a,
            None => panic!("no alarm; moves {:?}", pts(&got)),
        }
    };
    assert_eq!((a.number, a.pos.as_ref().map(|p| p.line)), (3605, Some(8)), "{a}");
    assert!(a.message.contains("line 5") && a.message.contains("3 blocks before"), "{a}");
    // Nothing of the hook was let out: the moves before the alarm end before line 5's.
    assert!(got.iter().all(|m| m.src.line < 5), "{:?}", got.iter().map(|m| m.src.line).collect::<Vec<_>>());
    // The same contour with the last cut 0.5 mm lower (X36.4: the nose clears the point by
    // 0.1 mm) runs.
    let ok = run(&src.replace("X37.4", "X36.4"));
    assert!(pts(&ok).iter().any(|p| (p.1 - 37.2).abs() < 1e-6 && (p.2 + 8.3).abs() < 0.5), "{:?}", pts(&ok));
}
