//! G80–G89 drilling and boring (manual 004 §2.21) and the shared hole-cycle rules.

mod cycles_common;
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
                MoveKind::Spindle(s) => (s.rpm, match s.dir {
                    SpindleDir::Cw => 3.0,
                    SpindleDir::Ccw => 4.0,
                    SpindleDir::Stop => 5.0,
                }),
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
        let ok = g.kind == w.0 && (g.x - w.1).abs() < 1e-6 && (g.z - w.2).abs() < 1e-6 && (g.c - w.3).abs() < 1e-6 && (g.v - w.4).abs() < 1e-9 && g.step == w.5;
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
            i = expect(&r, i, &[
                ("rapid", 100.0, 0.0, c, 0.0, 3),
                ("rapid", 100.0, last + 1.0, c, 0.0, 3),
                ("feed", 100.0, last - 5.0, c, 200.0, 3),
            ]);
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
    expect(&r, 1, &[
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
    ]);
    assert_eq!(r.len(), 12);
}

/// Without Q: one cut to the bottom. W is the depth from the R point.
#[test]
fn g83_without_q_and_incremental_depth() {
    let r = rows(&run("G98\nG0 X20 Z10\nG83 W-12 R-8 F50\nG80\n"));
    expect(&r, 1, &[
        ("rapid", 20.0, 2.0, 0.0, 0.0, 2),
        ("feed", 20.0, -10.0, 0.0, 50.0, 3),
        ("rapid", 20.0, 2.0, 0.0, 0.0, 5),
        ("rapid", 20.0, 10.0, 0.0, 0.0, 6),
    ]);
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
        expect(&r, i, &[
            ("rapid", *x, 5.0, 0.0, 0.0, if k == 0 { 0 } else { 1 }),
            ("rapid", *x, 2.0, 0.0, 0.0, 2),
            ("feed", *x, -20.0, 0.0, 80.0, 3),
            ("dwell", *x, -20.0, 0.0, 2.0, 4),
            ("feed", *x, 2.0, 0.0, 80.0, 5),
            ("rapid", *x, 5.0, 0.0, 0.0, 6),
        ]);
    }
    assert_eq!(r.len(), 12);
    // G89: drilling axis X (G18); R is a radius distance: X80 (radius 40) − 5 = radius 35.
    let r = rows(&run("G98\nG0 X80 Z-10 C0\nG89 Z-15 C90 X40 R-5 F60\nG80\n"));
    expect(&r, 1, &[
        ("rapid", 80.0, -15.0, 90.0, 0.0, 1),
        ("rapid", 70.0, -15.0, 90.0, 0.0, 2),
        ("feed", 40.0, -15.0, 90.0, 60.0, 3),
        ("feed", 70.0, -15.0, 90.0, 60.0, 5),
        ("rapid", 80.0, -15.0, 90.0, 0.0, 6),
    ]);
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
        i = expect(&r, i, &[
            ("rapid", 60.0, -10.0, c, 0.0, 1),
            ("rapid", 56.0, -10.0, c, 0.0, 2),
            ("feed", 48.0, -10.0, c, 100.0, 3),
            ("rapid", 56.0, -10.0, c, 0.0, 3),
            ("rapid", 49.0, -10.0, c, 0.0, 3),
            ("feed", 40.0, -10.0, c, 100.0, 3),
            ("rapid", 56.0, -10.0, c, 0.0, 5),
            ("rapid", 60.0, -10.0, c, 0.0, 6),
        ]);
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
    assert_eq!(a.number, 2510);
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
        i = expect(&r, i, &[
            ("rapid", 30.0, 5.0, c, 0.0, 1),
            ("aux", 30.0, 5.0, c, 68.0, 1),
            ("rapid", 30.0, 3.0, c, 0.0, 2),
            ("feed", 30.0, -5.0, c, 100.0, 3),
            ("rapid", 30.0, 3.0, c, 0.0, 5),
            ("aux", 30.0, 3.0, c, 69.0, 5),
            ("dwell", 30.0, 3.0, c, 0.25, 5),
            ("rapid", 30.0, 5.0, c, 0.0, 6),
        ]);
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
    assert_eq!((a.number, a.pos.as_ref().unwrap().col), (2510, 18));
    let a = run_err("G99\nG0 X0 Z5\nG83 Z-5 R-2\n");
    assert_eq!(a.number, 11, "{a}");
    let a = run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 Q-1 F100\n");
    assert_eq!(a.number, 2510);
    // K198 is for rigid tapping only.
    assert_eq!(run_err("G98\nG0 X0 Z5\nG83 Z-5 R-2 F100 K198\n").number, 2510);
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
