//! G80–G89 drilling and boring (manual 004 §2.21) and the shared hole-cycle rules.

use crate::cycles_common;
use cncgw::canon::{Feed, Move, MoveKind, SpindleDir};
use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;
use cycles_common::*;

/// One move as the tests read it: kind, X diameter, Z, C (work coordinates), a value (feed,
/// lead, dwell seconds, aux code, spindle rpm), the spindle direction or the rpm of a tap,
/// and the cycle step.
#[derive(Clone, Debug, PartialEq)]
pub struct R {
    kind: &'static str,
    x: f64,
    z: f64,
    c: f64,
    v: f64,
    w: f64,
    step: u8,
}

fn rows(m: &[Move]) -> Vec<R> {
    let mut at = (0.0, 0.0, 0.0);
    m.iter()
        .map(|m| {
            if let Some(e) = m.kind.end() {
                let e = e.sub(m.work_offset);
                at = (e.x * 2.0, e.z, e.c);
            }
            let (v, w) = match &m.kind {
                MoveKind::Feed { feed: Feed::PerMin(f) | Feed::PerRev(f), .. } => (*f, 0.0),
                MoveKind::Tap { lead, rpm, .. } => (*lead, *rpm),
                MoveKind::Dwell { seconds } => (*seconds, 0.0),
                MoveKind::Aux { value, .. } => (*value, 0.0),
                MoveKind::Spindle(s) => (
                    s.rpm,
                    match s.dir {
                        SpindleDir::Cw => 3.0,
                        SpindleDir::Ccw => 4.0,
                        SpindleDir::Stop => 5.0,
                    },
                ),
                _ => (0.0, 0.0),
            };
            R { kind: m.kind.name(), x: at.0, z: at.1, c: at.2, v, w, step: m.tag.as_ref().map(|t| t.step).unwrap_or(0) }
        })
        .collect()
}

/// Expect `(kind, x, z, c, v, step)` rows from index `i` on; returns the index after them.
#[track_caller]
fn expect(r: &[R], i: usize, want: &[(&str, f64, f64, f64, f64, u8)]) -> usize {
    for (k, w) in want.iter().enumerate() {
        let g = r.get(i + k).unwrap_or_else(|| panic!("row {} missing, want {w:?}", i + k));
        let ok = g.kind == w.0
            && (g.x - w.1).abs() < 1e-6
            && (g.z - w.2).abs() < 1e-6
            && (g.c - w.3).abs() < 1e-6
            && (g.v - w.4).abs() < 1e-9
            && g.step == w.5;
        assert!(ok, "row {}: want {w:?}, got {g:?}", i + k);
    }
    i + want.len()
}

/// §2.21.1 example as printed, No.5101 = 1 (peck) and d = No.5113 = 1 mm. The R point is
/// the initial plane Z-4 + R4 = Z0 (see drill.rs about the listing's comment). Each hole:
/// ① rapid to the hole on Z-4, ② rapid to Z0, ③ 5 mm cut, ④ rapid to R, ⑤ rapid to 1 mm
/// short of the last depth, ⑥ cut q + d, … ⑧ dwell 3 s, ⑨ rapid to R, ⑩ to Z-4.
#[test]
fn g83_manual_example_peck() {
    let cfg = cfg_with("5101 = 1\n5113 = 1.0");
    let src = "G98\nM19\nM3 S1500\nG0 X50 C0 Z-4\nG83 X100 Z-50 R4 Q5 P3 F200\nC120\nC240\nG80 M05\nM20\nM30\n";
    let r = rows(&run_cfg(src, &cfg));
    let mut i = expect(&r, 0, &[("aux", 0.0, 0.0, 0.0, 19.0, 0), ("spindle", 0.0, 0.0, 0.0, 1500.0, 0), ("rapid", 50.0, -4.0, 0.0, 0.0, 0)]);
    for c in [0.0, 120.0, 240.0] {
        i = expect(&r, i, &[("rapid", 100.0, -4.0, c, 0.0, 1), ("rapid", 100.0, 0.0, c, 0.0, 2), ("feed", 100.0, -5.0, c, 200.0, 3)]);
        for n in 1..10 {
            let last = -5.0 * n as f64;
            i = expect(&r, i, &[("rapid", 100.0, 0.0, c, 0.0, 3), ("rapid", 100.0, last + 1.0, c, 0.0, 3), ("feed", 100.0, last - 5.0, c, 200.0, 3)]);
        }
        i = expect(&r, i, &[("dwell", 100.0, -50.0, c, 3.0, 4), ("rapid", 100.0, 0.0, c, 0.0, 5), ("rapid", 100.0, -4.0, c, 0.0, 6)]);
    }
    i = expect(&r, i, &[("spindle", 100.0, -4.0, 240.0, 1500.0, 0), ("aux", 100.0, -4.0, 240.0, 20.0, 0), ("end", 100.0, -4.0, 240.0, 0.0, 0)]);
    assert_eq!(r[i - 3].w, 5.0, "G80 M05 stops the live tool");
    assert_eq!(r.len(), i);
}

/// High-speed peck (No.5101 = 0): ③ cut q, ④ rapid back d (No.5113), ③ cut q + d … ⑥ dwell,
/// ⑦ rapid to R, ⑧ to the initial plane.
#[test]
fn g83_high_speed_peck() {
    let cfg = cfg_with("5101 = 0\n5113 = 0.5");
    let r = rows(&run_cfg("G98\nG0 X0 Z5\nG83 Z-8 R-3 Q3 P1.5 F100\nG80\n", &cfg));
    expect(
        &r,
        1,
        &[
            ("rapid", 0.0, 2.0, 0.0, 0.0, 2),
            ("feed", 0.0, -1.0, 0.0, 100.0, 3),
            ("rapid", 0.0, -0.5, 0.0, 0.0, 3),
            ("feed", 0.0, -4.0, 0.0, 100.0, 3),
            ("rapid", 0.0, -3.5, 0.0, 0.0, 3),
            ("feed", 0.0, -7.0, 0.0, 100.0, 3),
            ("rapid", 0.0, -6.5, 0.0, 0.0, 3),
            ("feed", 0.0, -8.0, 0.0, 100.0, 3),
            ("dwell", 0.0, -8.0, 0.0, 1.5, 4),
            ("rapid", 0.0, 2.0, 0.0, 0.0, 5),
            ("rapid", 0.0, 5.0, 0.0, 0.0, 6),
        ],
    );
    assert_eq!(r.len(), 12);
}

/// Without Q: one cut to the bottom. W is the depth from the R point.
#[test]
fn g83_without_q_and_incremental_depth() {
    let r = rows(&run("G98\nG0 X20 Z10\nG83 W-12 R-8 F50\nG80\n"));
    expect(
        &r,
        1,
        &[
            ("rapid", 20.0, 2.0, 0.0, 0.0, 2),
            ("feed", 20.0, -10.0, 0.0, 50.0, 3),
            ("rapid", 20.0, 2.0, 0.0, 0.0, 5),
            ("rapid", 20.0, 10.0, 0.0, 0.0, 6),
        ],
    );
    assert_eq!(r.len(), 5);
}

/// §2.21.2 G85 boring: ③ feed in, ④ dwell, ⑤ feed out to R, ⑥ rapid to the initial plane.
/// G89 the same along X, the hole positions in Z and C.
#[test]
fn g85_and_g89_boring() {
    let r = rows(&run("G98\nG0 X30 Z5\nG85 Z-20 R-3 P2 F80\nX40\nG80\n"));
    for (k, x) in [30.0, 40.0].iter().enumerate() {
        // The first hole's ① has no length (the tool is there already): not emitted.
        let i = if k == 0 { 0 } else { 6 };
        expect(
            &r,
            i,
            &[
                ("rapid", *x, 5.0, 0.0, 0.0, if k == 0 { 0 } else { 1 }),
                ("rapid", *x, 2.0, 0.0, 0.0, 2),
                ("feed", *x, -20.0, 0.0, 80.0, 3),
                ("dwell", *x, -20.0, 0.0, 2.0, 4),
                ("feed", *x, 2.0, 0.0, 80.0, 5),
                ("rapid", *x, 5.0, 0.0, 0.0, 6),
            ],
        );
    }
    assert_eq!(r.len(), 12);
    // G89: drilling axis X (G18); R is a radius distance: X80 (radius 40) − 5 = radius 35.
    let r = rows(&run("G98\nG0 X80 Z-10 C0\nG89 Z-15 C90 X40 R-5 F60\nG80\n"));
    expect(
        &r,
        1,
        &[
            ("rapid", 80.0, -15.0, 90.0, 0.0, 1),
            ("rapid", 70.0, -15.0, 90.0, 0.0, 2),
            ("feed", 40.0, -15.0, 90.0, 60.0, 3),
            ("feed", 70.0, -15.0, 90.0, 60.0, 5),
            ("rapid", 80.0, -15.0, 90.0, 0.0, 6),
        ],
    );
}

/// G87 side drilling pecks along X (radius values); K repeats with an incremental C.
#[test]
fn g87_side_peck_and_k_repeats() {
    let cfg = cfg_with("5101 = 1\n5113 = 0.5");
    let r = rows(&run_cfg("G98\nG0 X60 Z-10 C0\nG87 H90 X40 R-2 Q4 F100 K4\nG80\n", &cfg));
    let mut i = 1;
    for n in 1..=4 {
        let c = 90.0 * n as f64;
        // R point radius 28 (X56); pecks of 4 mm radius: 24, 20 (bottom).
        i = expect(
            &r,
            i,
            &[
                ("rapid", 60.0, -10.0, c, 0.0, 1),
                ("rapid", 56.0, -10.0, c, 0.0, 2),
                ("feed", 48.0, -10.0, c, 100.0, 3),
                ("rapid", 56.0, -10.0, c, 0.0, 3),
                ("rapid", 49.0, -10.0, c, 0.0, 3),
                ("feed", 40.0, -10.0, c, 100.0, 3),
                ("rapid", 56.0, -10.0, c, 0.0, 5),
                ("rapid", 60.0, -10.0, c, 0.0, 6),
            ],
        );
    }
    assert_eq!(r.len(), i);
    // K0: the data is stored, nothing drills; the next position block drills.
    let r = rows(&run("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100 K0\nX10\nG80\n"));
    assert_eq!(r.iter().filter(|r| r.kind == "feed").count(), 1);
}

/// The cycle is modal until G80 or a group-01 code; a block without axis words drills
/// nothing; G80 clears the drilling data (a new G83 needs its bottom again).
#[test]
fn modal_rules_and_cancel() {
    let r = rows(&run("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100\nM08\nX10\nG00 X20\nX30\n"));
    let feeds: Vec<f64> = r.iter().filter(|r| r.kind == "feed").map(|r| r.x).collect();
    assert_eq!(feeds, [0.0, 10.0]);
    // After G00 the block X30 is an ordinary rapid.
    assert_eq!((r.last().unwrap().kind, r.last().unwrap().x), ("rapid", 30.0));
    let a = run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100\nG80\nG83 X10\n");
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE);
    assert_eq!(a.pos.as_ref().map(|p| (p.line, p.col)), Some((5, 1)));
    assert!(a.message.contains("no hole bottom"), "{a}");
}

/// The C-axis clamp M code of the block is output after ① and its unclamp code (+1) after
/// the return to R, then No.5111's dwell; it is not executed as an ordinary M code.
#[test]
fn clamp_m_code() {
    let cfg = cfg_with("5111 = 250");
    let r = rows(&run_cfg("G98\nG0 X30 Z5 C0\nG83 C45 Z-5 R-2 F100 M68\nC90\nG80\n", &cfg));
    let mut i = 1;
    for c in [45.0, 90.0] {
        i = expect(
            &r,
            i,
            &[
                ("rapid", 30.0, 5.0, c, 0.0, 1),
                ("aux", 30.0, 5.0, c, 68.0, 1),
                ("rapid", 30.0, 3.0, c, 0.0, 2),
                ("feed", 30.0, -5.0, c, 100.0, 3),
                ("rapid", 30.0, 3.0, c, 0.0, 5),
                ("aux", 30.0, 3.0, c, 69.0, 5),
                ("dwell", 30.0, 3.0, c, 0.25, 5),
                ("rapid", 30.0, 5.0, c, 0.0, 6),
            ],
        );
    }
    assert_eq!(r.len(), i);
}

/// Plane selection picks the drilling axis (No.5209#0 = 0); No.5209#0 = 1 fixes Z / X.
#[test]
fn drilling_axis_by_plane_and_5209() {
    // G17: G83's axis is X; the hole position is given in Z.
    let r = rows(&run("G98\nG17\nG0 X50 Z-5\nG83 Z-7 X30 R-4 F100\nG80\n"));
    expect(&r, 1, &[("rapid", 50.0, -7.0, 0.0, 0.0, 1), ("rapid", 42.0, -7.0, 0.0, 0.0, 2), ("feed", 30.0, -7.0, 0.0, 100.0, 3)]);
    let cfg = cfg_with("5209 = 1");
    let r = rows(&run_cfg("G98\nG17\nG0 X50 Z5\nG83 X30 Z-7 R-4 F100\nG80\n", &cfg));
    expect(&r, 1, &[("rapid", 30.0, 5.0, 0.0, 0.0, 1), ("rapid", 30.0, 1.0, 0.0, 0.0, 2), ("feed", 30.0, -7.0, 0.0, 100.0, 3)]);
}

/// Alarms with their numbers and columns.
#[test]
fn drilling_alarms() {
    let a = run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100 K100\n");
    assert_eq!((a.number, a.pos.as_ref().unwrap().col), (cncgw::alarm::VALUE_RANGE, 18));
    let a = run_err("G99\nG0 X0 Z5\nG83 Z-5 R-2\n");
    assert_eq!(a.number, cncgw::alarm::FEED_ZERO, "{a}");
    let a = run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 Q-1 F100\n");
    assert_eq!(a.number, cncgw::alarm::VALUE_RANGE);
    // A tiny Q cannot flood the queue: at most 20000 pecks per block.
    let a = run_err("G98\nG0 X0 Z5\nG83 Z-1000 R-1 Q0.01 F100 K9\n");
    assert_eq!((a.number, a.pos.as_ref().unwrap().col), (cncgw::alarm::VALUE_RANGE, 16));
    // K198 is for rigid tapping only.
    assert_eq!(run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100 K198\n").number, cncgw::alarm::VALUE_RANGE);
}

/// No.5155: the drilling mode kept through a reset, or not.
#[test]
fn reset_keeps_the_mode_only_with_5155() {
    for (p, kept) in [("5155 = 1", true), ("5155 = 0", false)] {
        let cfg = cfg_with(p);
        let mut it = Interpreter::from_source("t.nc", "G98\nG0 X0 Z5\nG83 Z-5 R-2 F100\n", &cfg).unwrap();
        while it.next_move().unwrap().is_some() {}
        assert!(it.drill_mode().is_some());
        let keep = it.drill_modal_after_reset();
        assert_eq!(keep.is_some(), kept, "{p}");
        // Given back to a restarted interpreter, the next position block drills with it.
        if let Some(m) = keep {
            let mut it2 = Interpreter::from_source("t.nc", "G98 F100\nX10\n", &cfg).unwrap();
            it2.set_start_position(cncgw::canon::Pos::xz(0.0, 5.0));
            it2.set_drill_modal(Some(m));
            let r = rows(&it2.map(|m| m.unwrap()).collect::<Vec<_>>());
            assert!(r.iter().any(|r| r.kind == "feed" && r.x == 10.0 && r.z == -5.0), "{r:?}");
        }
    }
    let _ = MachineConfig::embedded();
}

// ---------------------------------------------------------------------------------------
// SINUMERIK CYCLE81/82/83/85/86 and MCALL (manual 003).

/// The tutorial's CYCLE81: RTP 100, RFP 0, SDIS 1, Z1 25 inc (DPR), DT 0.6 s. As a single
/// call it drills where the tool stands: ② rapid to the safety plane Z1, ③ feed to Z-25,
/// ④ dwell 0.6 s, ⑥ rapid to RTP Z100. With MCALL it drills nothing in its own block and
/// drills after every following positioning block until a bare MCALL.
#[test]
fn cycle81_tutorial_single_and_mcall() {
    let src = "G98 F100 S800 M3\nG0 X0 Z120\nCYCLE81(100,0,1,,25,0.6,0,1,11)\nMCALL CYCLE81(100,0,1,,25,0.6,0,1,11)\nX20\nX40 C90\nMCALL\nX60\nM30\n";
    let m = run(src);
    let r = rows(&m);
    let hole = |x: f64, c: f64| -> Vec<(&str, f64, f64, f64, f64, u8)> {
        vec![("rapid", x, 1.0, c, 0.0, 2), ("feed", x, -25.0, c, 100.0, 3), ("dwell", x, -25.0, c, 0.6, 4), ("rapid", x, 100.0, c, 0.0, 6)]
    };
    let mut i = expect(&r, 0, &[("spindle", 0.0, 0.0, 0.0, 800.0, 0), ("rapid", 0.0, 120.0, 0.0, 0.0, 0)]);
    i = expect(&r, i, &hole(0.0, 0.0));
    // Line 4 (MCALL …) made nothing: the next move is line 5's positioning.
    assert_eq!(m[i].src.line, 5);
    i = expect(&r, i, &[("rapid", 20.0, 100.0, 0.0, 0.0, 0)]);
    i = expect(&r, i, &hole(20.0, 0.0));
    i = expect(&r, i, &[("rapid", 40.0, 100.0, 90.0, 0.0, 0)]);
    i = expect(&r, i, &hole(40.0, 90.0));
    i = expect(&r, i, &[("rapid", 60.0, 100.0, 90.0, 0.0, 0), ("end", 60.0, 100.0, 90.0, 0.0, 0)]);
    assert_eq!(r.len(), i);
    assert!(m.iter().filter(|m| m.tag.is_some()).all(|m| &*m.tag.as_ref().unwrap().cycle == "CYCLE81"));
}

/// Depth by diameter (_GMODE 1: Ø11 with the 90° centre drill = 5.5 deep), DP absolute vs
/// DPR (DPR wins), _AMODE 2 = DP, and the shank depth of CYCLE82 (118°, r = 5 from the tool
/// table: the tip is 5 / tan 59° deeper).
#[test]
fn cycle81_82_depth_modes() {
    let z3 = |src: &str| -> f64 {
        let r = rows(&run(&format!("G98 F100\nG0 X0 Z50\n{src}\n")));
        r.iter().find(|r| r.kind == "feed").unwrap().z
    };
    assert!((z3("CYCLE81(10,0,1,,11,0,1)") + 5.5).abs() < 1e-9);
    assert_eq!(z3("CYCLE82(10,0,1,-8,3)"), -3.0);
    assert_eq!(z3("CYCLE82(10,0,1,-8)"), -8.0);
    assert_eq!(z3("CYCLE82(10,0,1,-8,3,0,0,1,2)"), -8.0);
    assert_eq!(z3("CYCLE82(10,0,1,-8,3,0,0,1,1)"), -3.0);
    let cfg = MachineConfig::embedded();
    let mut it = Interpreter::from_source("t.nc", "G98 F100\nT0303\nG0 X0 Z50\nCYCLE82(10,0,1,,20,0,0,1,21)\n", &cfg).unwrap();
    it.set_tool_table(cncgw::interp::parse_tool_table("tools.toml", "[3]\nr = 5.0\n").unwrap());
    let r = rows(&it.map(|m| m.unwrap()).collect::<Vec<_>>());
    let z = r.iter().find(|r| r.kind == "feed").unwrap().z;
    assert!((z - (-20.0 - 5.0 / 59f64.to_radians().tan())).abs() < 1e-9, "{z}");
}

/// CYCLE83 chip removal (VARI 1): first depth FDPR 5 at F × FRF 0.5, then DAM 2 less each
/// time (not below 2): 5, 3, 2, 2, … After each stage DTB, rapid out to the safety plane,
/// DTS, rapid back to 1 mm (automatic V3) short of the last depth. _DTD at the bottom.
#[test]
fn cycle83_chip_removal() {
    let r = rows(&run("G98 F200\nG0 X0 Z20\nCYCLE83(10,0,2,-12,,,5,2,0.3,0.7,0.5,1,,,,1.5)\n"));
    let mut i = expect(&r, 1, &[("rapid", 0.0, 2.0, 0.0, 0.0, 2), ("feed", 0.0, -5.0, 0.0, 100.0, 3)]);
    for (last, next) in [(5.0, 8.0), (8.0, 10.0), (10.0, 12.0)] {
        i = expect(
            &r,
            i,
            &[
                ("dwell", 0.0, -last, 0.0, 0.3, 3),
                ("rapid", 0.0, 2.0, 0.0, 0.0, 3),
                ("dwell", 0.0, 2.0, 0.0, 0.7, 3),
                ("rapid", 0.0, -(last - 1.0), 0.0, 0.0, 3),
                ("feed", 0.0, -next, 0.0, 200.0, 3),
            ],
        );
    }
    i = expect(&r, i, &[("dwell", 0.0, -12.0, 0.0, 1.5, 4), ("rapid", 0.0, 10.0, 0.0, 0.0, 6)]);
    assert_eq!(r.len(), i);
}

/// CYCLE83 chip breaking (VARI 0): FDEP absolute -4, DAM 0 (every stage 4 mm), back by
/// _VRT 0.5 after each; _DTD empty = DTB at the bottom.
#[test]
fn cycle83_chip_breaking() {
    let r = rows(&run("G98 F150\nG0 X0 Z20\nCYCLE83(10,0,1,-10,,-4,,0,0.2,,,0,,,0.5)\n"));
    expect(
        &r,
        1,
        &[
            ("rapid", 0.0, 1.0, 0.0, 0.0, 2),
            ("feed", 0.0, -4.0, 0.0, 150.0, 3),
            ("dwell", 0.0, -4.0, 0.0, 0.2, 3),
            ("rapid", 0.0, -3.5, 0.0, 0.0, 3),
            ("feed", 0.0, -8.0, 0.0, 150.0, 3),
            ("dwell", 0.0, -8.0, 0.0, 0.2, 3),
            ("rapid", 0.0, -7.5, 0.0, 0.0, 3),
            ("feed", 0.0, -10.0, 0.0, 150.0, 3),
            ("dwell", 0.0, -10.0, 0.0, 0.2, 4),
            ("rapid", 0.0, 10.0, 0.0, 0.0, 6),
        ],
    );
    assert_eq!(r.len(), 11);
}

/// CYCLE85: in at FFR, dwell, out at RFF to the safety plane, rapid to RTP.
#[test]
fn cycle85_reaming() {
    let r = rows(&run("G98 F10\nG0 X30 Z20\nCYCLE85(10,0,2,-15,,1,120,300)\n"));
    expect(
        &r,
        1,
        &[
            ("rapid", 30.0, 2.0, 0.0, 0.0, 2),
            ("feed", 30.0, -15.0, 0.0, 120.0, 3),
            ("dwell", 30.0, -15.0, 0.0, 1.0, 4),
            ("feed", 30.0, 2.0, 0.0, 300.0, 5),
            ("rapid", 30.0, 10.0, 0.0, 0.0, 6),
        ],
    );
}

/// CYCLE86: spindle SDIR on, bore, dwell, oriented stop at POSS (Cs), retract by RPA/RPAP,
/// up to RTP, back in the plane, spindle on again; without retract values it goes straight
/// up (the tutorial's "不退刀返回").
#[test]
fn cycle86_boring_with_and_without_retract() {
    let r = rows(&run("G98 F60 S500\nG0 X40 Z20 C0\nCYCLE86(10,0,2,-20,,0.5,3,-0.5,,0.2,45)\n"));
    expect(
        &r,
        1,
        &[
            ("rapid", 40.0, 2.0, 0.0, 0.0, 2),
            ("spindle", 40.0, 2.0, 0.0, 500.0, 3),
            ("feed", 40.0, -20.0, 0.0, 60.0, 3),
            ("dwell", 40.0, -20.0, 0.0, 0.5, 4),
            ("spindle", 40.0, -20.0, 0.0, 500.0, 4),
            ("rapid", 40.0, -20.0, 45.0, 0.0, 4),
            ("rapid", 39.0, -19.8, 45.0, 0.0, 5),
            ("rapid", 39.0, 10.0, 45.0, 0.0, 6),
            ("rapid", 40.0, 10.0, 45.0, 0.0, 6),
            ("spindle", 40.0, 10.0, 45.0, 500.0, 6),
        ],
    );
    assert_eq!((r[2].w, r[5].w, r[10].w), (3.0, 5.0, 3.0));
    let r = rows(&run("G98 F60 S500\nG0 X40 Z20 C0\nCYCLE86(10,0,2,-20,,0,4,,,,90)\n"));
    let kinds: Vec<(&str, f64, f64)> = r.iter().skip(1).map(|r| (r.kind, r.z, r.c)).collect();
    assert_eq!(
        kinds,
        [
            ("rapid", 2.0, 0.0),
            ("spindle", 2.0, 0.0),
            ("feed", -20.0, 0.0),
            ("spindle", -20.0, 0.0),
            ("rapid", -20.0, 90.0),
            ("rapid", 10.0, 90.0),
            ("spindle", 10.0, 90.0)
        ]
    );
}

/// Bad parameters: SINUMERIK cycle alarm numbers, at the call's line.
#[test]
fn siemens_cycle_alarms() {
    let at = |src: &str| {
        let a = run_err(&format!("G98 F100 S500\nG0 X0 Z20\n{src}\n"));
        (a.number, a.pos.as_ref().unwrap().line)
    };
    assert_eq!(at("CYCLE81(10,0,1,5)"), (61101, 3)); // depth above RFP
    assert_eq!(at("CYCLE81(10,0,1)"), (61101, 3)); // no depth
    assert_eq!(at("CYCLE86(10,0,1,-5,,0,5)"), (61102, 3));
    assert_eq!(at("CYCLE83(10,0,1,-10,,5)"), (61107, 3));
    assert_eq!(at("CYCLE83(10,0,1,-10,,,3,,,,,2)"), (61002, 3));
    assert_eq!(at("CYCLE83(10,0,1,-10,,,3,,,,2)"), (2510, 3));
    assert_eq!(at("CYCLE85(10,0,1,-10,,0,100)"), (61003, 3));
    // Unknown cycles and too many parameters are found before anything runs, all of them.
    let e =
        Interpreter::from_source("t.nc", "G0 X0\nCYCLE81(10,0,1,-10,,0,0,0,0,0)\nCYCLE87(10,0,1,-10)\n", &MachineConfig::embedded()).err().unwrap();
    let got: Vec<(u32, u32, u32)> = e.iter().map(|a| (a.number, a.pos.as_ref().unwrap().line, a.pos.as_ref().unwrap().col)).collect();
    assert_eq!(got, [(12340, 2, 29), (10, 3, 1)]);
    assert_eq!(at("MCALL CYCLE81(10,0,1)"), (61101, 3));
    // The column is the offending parameter's.
    let col = |src: &str| run_err(&format!("G98 F100 S500\nG0 X0 Z20\n{src}\n")).pos.unwrap().col;
    assert_eq!(col("CYCLE81(10,0,1,5)"), 16);
    assert_eq!(col("CYCLE86(10,0,1,-5,,0,5)"), 22);
    assert_eq!(col("CYCLE83(10,0,1,-10,,,3,,,,2)"), 27);
    assert_eq!(col("MCALL CYCLE86(10,0,1,-5,,0,5)"), 28);
    // An MCALL run in a later block points at that block.
    let a = run_err("G98 F100 S500\nG0 X0 Z20\nMCALL CYCLE81(10,0,1,-5)\nG99\nX10\n");
    assert_eq!((a.number, a.pos.as_ref().map(|p| (p.line, p.col))), (61003, Some((5, 1))));
    // Syntax: missing `)` is found before anything runs, with its column.
    let e = Interpreter::from_source("t.nc", "G0 X0\nCYCLE81(10,0,1,-5\n", &MachineConfig::embedded()).err().unwrap();
    assert_eq!((e[0].number, e[0].pos.as_ref().unwrap().line, e[0].pos.as_ref().unwrap().col), (9, 2, 18));
    // Parameters may be macro expressions and variables.
    let r = rows(&run("G98 F100\n#1=-6\nG0 X0 Z20\nCYCLE81(10,0,[1+1],#1)\n"));
    assert_eq!((r[1].z, r[2].z), (2.0, -6.0));
}

/// Random drilling / tapping / SINUMERIK text never panics, under several parameter sets.
mod robust {
    use super::*;
    use proptest::prelude::*;

    /// The embedded configuration with `params` replacing the parameters of those numbers.
    fn cfg_with(params: &str) -> MachineConfig {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).expect("config");
        let keys: Vec<&str> = params.lines().filter_map(|l| l.split('=').next()).map(|k| k.trim()).collect();
        let kept: Vec<&str> = text.lines().filter(|l| !keys.iter().any(|k| l.split('=').next().map(|x| x.trim()) == Some(*k))).collect();
        let text = kept.join("\n").replace("[parameters]", &format!("[parameters]\n{params}"));
        MachineConfig::from_toml("lathe.toml", &text).expect("config parses")
    }

    fn drain(src: &str, cfg: &MachineConfig) {
        if let Ok(mut it) = Interpreter::from_source("f.nc", src, cfg) {
            it.set_endless_loop_limit(1000);
            for _ in 0..3000 {
                match it.next_move() {
                    Ok(Some(_)) => {}
                    _ => break,
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 300, .. ProptestConfig::default() })]
        #[test]
        fn drilling_text_never_panics(
            lines in proptest::collection::vec(
                "(G8[0-9] |G30 P99 |M29 |M2[4-7] |MCALL |CYCLE8[1-6]\\(|CYCLE840\\(|G9[89] |[XZUWCHRQPKFSJDE][-]?[0-9]{1,3}(\\.[0-9])? |[,)])",
                0..40,
            ),
            params in 0usize..4,
        ) {
            let cfg = cfg_with(["", "5200 = 255", "5101 = 1\n5113 = 2", "5209 = 1\n5155 = 1\n5282 = 1"][params]);
            let text: String = lines.concat().replace("G30", "\nG30").replace("CYCLE", "\nCYCLE").replace("MCALL", "\nMCALL").replace("M29", "\nM29");
            drain(&text, &cfg);
        }
    }
}
