//! Rigid tapping G84/G88 (manual 000), flexible tapping (004 §2.22.3) and G30 P99.

use crate::cycles_common;
use cncgw::canon::{Move, MoveKind, Pos, SpindleDir, TapReturn};
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::job::run_program_with;
use cncgw::interp::Interpreter;
use cycles_common::{run, run_cfg, run_err};

/// The embedded configuration with `params` (TOML lines) replacing the parameters of the
/// same numbers.
fn cfg_with(params: &str) -> MachineConfig {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).expect("config");
    let keys: Vec<&str> = params.lines().filter_map(|l| l.split('=').next()).map(|k| k.trim()).collect();
    let kept: Vec<&str> = text.lines().filter(|l| !keys.iter().any(|k| l.split('=').next().map(|x| x.trim()) == Some(*k))).collect();
    let text = kept.join("\n").replace("[parameters]", &format!("[parameters]\n{params}"));
    MachineConfig::from_toml("lathe.toml", &text).expect("config parses")
}

fn run_err_cfg(src: &str, cfg: &MachineConfig) -> cncgw::Alarm {
    cycles_common::run_err_cfg(src, cfg)
}

/// (kind, Z or X-diameter along the stroke, lead, rpm, step) of the moves.
fn taps(m: &[Move]) -> Vec<(&'static str, f64, f64, f64, u8)> {
    m.iter()
        .map(|m| {
            let step = m.tag.as_ref().map(|t| t.step).unwrap_or(0);
            match &m.kind {
                MoveKind::Tap { end, lead, rpm, .. } => ("tap", end.sub(m.work_offset).z, *lead, *rpm, step),
                MoveKind::Dwell { seconds } => ("dwell", *seconds, 0.0, 0.0, step),
                MoveKind::Rapid { end } => ("rapid", end.sub(m.work_offset).z, 0.0, 0.0, step),
                MoveKind::Aux { value, .. } => ("aux", *value, 0.0, 0.0, step),
                MoveKind::Spindle(s) => (
                    "spindle",
                    s.rpm,
                    0.0,
                    0.0,
                    match s.dir {
                        SpindleDir::Cw => 3,
                        SpindleDir::Ccw => 4,
                        SpindleDir::Stop => 5,
                    },
                ),
                k => (k.name(), 0.0, 0.0, 0.0, step),
            }
        })
        .collect()
}

#[track_caller]
fn same(got: &[(&'static str, f64, f64, f64, u8)], want: &[(&str, f64, f64, f64, u8)]) {
    assert_eq!(got.len(), want.len(), "got {got:?}");
    for (g, w) in got.iter().zip(want) {
        let ok = g.0 == w.0 && (g.1 - w.1).abs() < 1e-9 && (g.2 - w.2).abs() < 1e-9 && (g.3 - w.3).abs() < 1e-9 && g.4 == w.4;
        assert!(ok, "want {w:?}, got {g:?}\nall: {got:?}");
    }
}

/// Manual 000 standard rigid tapping example as printed: lead F/S = 2000/1000 = 2 mm;
/// (3) tap to Z-50 at S1000 (lead −2: the spindle turns forward going −Z), (4) dwell P3000 =
/// 3 s, (5) tap back to R = Z0, (6) no rapid: R is the initial plane. M29 stops nothing
/// (the spindle was not running) and G80 restores nothing.
#[test]
fn standard_rigid_tap_manual_example() {
    let src = "G98;\nG0 X50 Z0;\nM29 S1000;\nG84 Z-50 P3000 F2000;\nG80;\nM30;\n";
    let m = run(src);
    same(
        &taps(&m),
        &[
            ("rapid", 0.0, 0.0, 0.0, 0),
            ("aux", 29.0, 0.0, 0.0, 0),
            ("tap", -50.0, -2.0, 1000.0, 3),
            ("dwell", 3.0, 0.0, 0.0, 4),
            ("tap", 0.0, -2.0, 1000.0, 5),
            ("end", 0.0, 0.0, 0.0, 0),
        ],
    );
    assert!(m.iter().filter(|m| m.tag.is_some()).all(|m| &*m.tag.as_ref().unwrap().cycle == "G84"));
}

/// Manual 000 high-speed peck example (No.5200#5 = 0), d = No.5213 = 1 mm: (4) q = 4,
/// (5) back d, (6) q + d, … to Z-50; (8) dwell; (9) back to R.
#[test]
fn high_speed_peck_manual_example() {
    let cfg = cfg_with("5213 = 1.0");
    let m = run_cfg("G98;\nG0 X50 Z0;\nM29 S1000;\nG84 Z-50 Q4.0 P3000 F2000;\nG80;\nM30;\n", &cfg);
    let mut want = vec![("rapid", 0.0, 0.0, 0.0, 0), ("aux", 29.0, 0.0, 0.0, 0), ("tap", -4.0, -2.0, 1000.0, 3)];
    let mut depth: f64 = 4.0;
    while depth < 50.0 {
        want.push(("tap", -(depth - 1.0), -2.0, 1000.0, 3));
        depth = (depth + 4.0).min(50.0);
        want.push(("tap", -depth, -2.0, 1000.0, 3));
    }
    want.extend([("dwell", 3.0, 0.0, 0.0, 4), ("tap", 0.0, -2.0, 1000.0, 5), ("end", 0.0, 0.0, 0.0, 0)]);
    same(&taps(&m), &want);
}

/// Manual 000 peck example (No.5200#5 = 1), with a pull-out override of 150 % (No.5200#4,
/// No.5211 = 150): (4) q at S, (5) back to R at 1500 rpm, (6) in to d = 1 mm short of the last
/// depth at 1500 rpm (the "speed of cutting into the previous plane" is the pull-out one),
/// (7) q + d at S, … (9) dwell, (10) back to R at 1500 rpm.
#[test]
fn peck_manual_example_with_override() {
    let cfg = cfg_with("5200 = 48\n5211 = 150\n5213 = 1.0");
    let m = run_cfg("G98;\nG0 X50 Z0;\nM29 S1000;\nG84 Z-50 Q4.0 P3000 F2000;\nG80;\nM30;\n", &cfg);
    let mut want = vec![("rapid", 0.0, 0.0, 0.0, 0), ("aux", 29.0, 0.0, 0.0, 0), ("tap", -4.0, -2.0, 1000.0, 3)];
    let mut depth: f64 = 4.0;
    while depth < 50.0 {
        want.push(("tap", 0.0, -2.0, 1500.0, 3));
        want.push(("tap", -(depth - 1.0), -2.0, 1500.0, 3));
        depth = (depth + 4.0).min(50.0);
        want.push(("tap", -depth, -2.0, 1000.0, 3));
    }
    want.extend([("dwell", 3.0, 0.0, 0.0, 4), ("tap", 0.0, -2.0, 1500.0, 5), ("end", 0.0, 0.0, 0.0, 0)]);
    same(&taps(&m), &want);
}

/// The pull-out override table of manual 000, row by row.
#[test]
fn pull_out_override_table() {
    let out = |params: &str, j: &str| -> f64 {
        let cfg = cfg_with(params);
        let m = run_cfg(&format!("G98\nG0 X0 Z5\nM29 S1000\nG84 Z-10 F2000 {j}\nG80\n"), &cfg);
        taps(&m).iter().rev().find(|t| t.0 == "tap").map(|t| t.3).unwrap()
    };
    // No.5200#4 = 0: 100 % whatever J and No.5211 say.
    assert_eq!(out("5211 = 150", "J2000"), 1000.0);
    // #4 = 1, No.5201#4 = 1: J within 100–200 % → J; outside → 100 %; no J → No.5211.
    assert_eq!(out("5200 = 16\n5201 = 16\n5211 = 120", "J1800"), 1800.0);
    assert_eq!(out("5200 = 16\n5201 = 16\n5211 = 120", "J2500"), 1000.0);
    assert_eq!(out("5200 = 16\n5201 = 16\n5211 = 120", "J900"), 1000.0);
    assert_eq!(out("5200 = 16\n5201 = 16\n5211 = 120", ""), 1200.0);
    // No.5202#6 = 1: 100–2000 %.
    assert_eq!(out("5200 = 16\n5201 = 16\n5202 = 64", "J2500"), 2500.0);
    // No.5201#4 = 0: No.5211 even with J; No.5201#3 = 1: No.5211 in units of 10 %.
    assert_eq!(out("5200 = 16\n5211 = 180", "J1500"), 1800.0);
    assert_eq!(out("5200 = 16\n5201 = 8\n5211 = 15", ""), 1500.0);
    // J is kept until G80: a second hole without J still uses it.
    let cfg = cfg_with("5200 = 16\n5201 = 16");
    let m = run_cfg("G98\nG0 X0 Z5\nM29 S1000\nG84 Z-10 F2000 J1500\nX10\nG80\nM29 S1000\nG84 Z-10 F2000\nG80\n", &cfg);
    let outs: Vec<f64> = taps(&m).iter().filter(|t| t.0 == "tap" && t.4 == 5).map(|t| t.3).collect();
    assert_eq!(outs, [1500.0, 1500.0, 1000.0]);
}

/// No.5200#0 = 1: G84 with S is rigid tapping (no M29); G99: lead = F; No.7013 dwell at R and
/// No.5282 extra return; the spindle running before is stopped and given back after the
/// hole (004 step ⑦), before the rapid to the initial plane.
#[test]
fn g_code_mode_g99_extra_return_and_spindle_restore() {
    let cfg = cfg_with("5200 = 1\n5282 = 2.0\n7013 = 500");
    let m = run_cfg("G99\nM3 S1500\nG0 X0 Z5\nG84 Z-10 R-3 F1.5 S600\nG80\nM30\n", &cfg);
    same(
        &taps(&m),
        &[
            ("spindle", 1500.0, 0.0, 0.0, 3),
            ("rapid", 5.0, 0.0, 0.0, 0),
            ("spindle", 0.0, 0.0, 0.0, 5),
            ("rapid", 2.0, 0.0, 0.0, 2),
            ("tap", -10.0, -1.5, 600.0, 3),
            ("tap", 2.0, -1.5, 600.0, 5),
            ("tap", 4.0, -1.5, 600.0, 5),
            ("dwell", 0.5, 0.0, 0.0, 5),
            ("spindle", 1500.0, 0.0, 0.0, 3),
            ("rapid", 5.0, 0.0, 0.0, 6),
            ("end", 0.0, 0.0, 0.0, 0),
        ],
    );
    // Without S in that mode: PS0200.
    let a = run_err_cfg("G99\nG0 X0 Z5\nG84 Z-10 R-3 F1.5\n", &cfg);
    assert_eq!((a.number, a.pos.as_ref().unwrap().line, a.pos.as_ref().unwrap().col), (200, 3, 1));
}

/// Reverse-thread tapping: negative S, No.5170 = 1 or the direction signal flip the lead
/// (two of them cancel).
#[test]
fn reverse_thread() {
    let lead = |params: &str, s: &str, signal: bool| -> f64 {
        let cfg = cfg_with(params);
        let mut it = Interpreter::from_source("t.nc", &format!("G98\nG0 X0 Z5\nM29 S{s}\nG84 Z-10 F1000\nG80\n"), &cfg).unwrap();
        it.set_tap_reverse_signal(signal);
        let m: Vec<Move> = it.map(|m| m.unwrap()).collect();
        taps(&m).iter().find(|t| t.0 == "tap").unwrap().2
    };
    assert_eq!(lead("", "500", false), -2.0);
    assert_eq!(lead("", "-500", false), 2.0);
    assert_eq!(lead("5170 = 1", "500", false), 2.0);
    assert_eq!(lead("", "500", true), 2.0);
    assert_eq!(lead("5170 = 1", "-500", false), -2.0);
}

/// G88 taps along X (radius values), the hole positions in Z and C.
#[test]
fn g88_side_tapping() {
    let m = run("G98\nG0 X60 Z-10 C0\nM29 S500\nG88 Z-12 C90 X40 R-4 F500\nG80\n");
    let t: Vec<(f64, f64)> = m
        .iter()
        .filter_map(|m| match m.kind {
            MoveKind::Tap { end, lead, .. } => Some((end.x * 2.0, lead)),
            _ => None,
        })
        .collect();
    // R point radius 26 (X52); into −X: lead −1.
    assert_eq!(t, [(40.0, -1.0), (52.0, -1.0)]);
}

/// The rules between M29 and G84 (004 §2.22.1) and the S/F checks, with file:line:col.
#[test]
fn rigid_tapping_alarms() {
    let at = |src: &str, params: &str| {
        let a = run_err_cfg(src, &cfg_with(params));
        let p = a.pos.clone().unwrap();
        (a.number, p.line, p.col)
    };
    assert_eq!(at("G98\nM29 S500\nS600\nG84 Z-10 F500\n", ""), (203, 3, 1));
    assert_eq!(at("G98\nM29 S500\nG0 X10\nG84 Z-10 F500\n", ""), (204, 3, 4));
    assert_eq!(at("G98\nM29 S500\nG84 Z-10 F500\nM29 S500\n", ""), (203, 4, 1));
    assert_eq!(at("G98\nM29 S500\nM29 S500\n", ""), (203, 3, 1));
    assert_eq!(at("G98\nM29\n", ""), (200, 2, 1));
    assert_eq!(at("G98\nM29 S5000\n", "5241 = 3000"), (200, 2, 5));
    assert_eq!(at("G98\nM29 S500\nG84 Z-10\n", ""), (201, 3, 1));
    assert_eq!(at("G98\nM29 S500\nG84 Z-10 P1.5 F500\n", ""), (7, 3, 10));
    assert_eq!(at("G98\nM29 S500\nG84 Z-10 F500 K200\n", ""), (2510, 3, 15));
    assert_eq!(at("G98\nM29 S500\nG84 Z-10 F500 E5\n", ""), (2510, 3, 15));
    // M29 under No.5200#0 = 1.
    assert_eq!(at("G98\nM29 S500\n", "5200 = 1"), (203, 2, 1));
    // The M code comes from No.5210.
    let m = run_cfg("G98\nG0 X0 Z5\nM70 S500\nG84 Z-10 F500\nG80\n", &cfg_with("5210 = 70"));
    assert!(m.iter().any(|m| matches!(m.kind, MoveKind::Tap { .. })));
}

/// G80 clears the tapping S (000 note 5): a new G84 without M29 S is flexible tapping with
/// the modal S, not rigid.
#[test]
fn g80_clears_the_tapping_s() {
    let m = run("G98\nS700\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000\nG80\nG84 Z-10 F1400\nG80\n");
    let kinds: Vec<&str> = m.iter().filter(|m| m.tag.is_some()).map(|m| m.kind.name()).collect();
    assert_eq!(kinds, ["tap", "tap", "spindle", "feed", "spindle", "spindle", "feed", "spindle"]);
    // Flexible lead = F/S = 1400/700 = 2 mm per revolution.
    assert!(m.iter().any(|m| matches!(m.kind, MoveKind::Feed { feed: cncgw::canon::Feed::PerRev(l), .. } if l == 2.0)));
}

/// 004 §2.22.3 flexible tapping example, as printed: M3 S800, G84 Z160 P1 F1600: ④ feed
/// to Z160 at lead 2 following the spindle, M05, ⑤ dwell 1 s, ⑥ M04, ⑦ back to Z200, ⑧
/// M05. A second hole turns the spindle on forward again (note 2).
#[test]
fn flexible_tap_manual_example() {
    let m = run("G98\nG0 X0 Z200\nM3 S800\nG84 Z160 P1 F1600\nX10\nG80\nM30\n");
    let t = taps(&m);
    let hole = |i: usize, first: bool| {
        let mut v = vec![];
        if !first {
            v.push(("rapid", 200.0, 0.0, 0.0, 1));
            v.push(("spindle", 800.0, 0.0, 0.0, 3));
        }
        v.extend([
            ("feed", 0.0, 0.0, 0.0, 3),
            ("spindle", 800.0, 0.0, 0.0, 5),
            ("dwell", 1.0, 0.0, 0.0, 4),
            ("spindle", 800.0, 0.0, 0.0, 4),
            ("feed", 0.0, 0.0, 0.0, 5),
            ("spindle", 800.0, 0.0, 0.0, 5),
        ]);
        same(&t[i..i + v.len()], &v);
        i + v.len()
    };
    same(&t[..2], &[("rapid", 200.0, 0.0, 0.0, 0), ("spindle", 800.0, 0.0, 0.0, 3)]);
    let i = hole(2, true);
    let i = hole(i, false);
    same(&t[i..], &[("end", 0.0, 0.0, 0.0, 0)]);
    let ends: Vec<(f64, f64)> = m
        .iter()
        .filter_map(|m| match m.kind {
            MoveKind::Feed { end, feed: cncgw::canon::Feed::PerRev(l) } => Some((end.z, l)),
            _ => None,
        })
        .collect();
    assert_eq!(ends, [(160.0, 2.0), (200.0, 2.0), (160.0, 2.0), (200.0, 2.0)]);
}

/// K198 stays at the bottom; the next block starts there; G30 P99 then pulls the tap out
/// along the thread to R (+ No.5382) at S × override, and leaves G80.
#[test]
fn k198_and_g30_p99_in_the_program() {
    let cfg = cfg_with("5382 = 0.5\n5200 = 16\n5211 = 200");
    let src = "G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 R-3 F1000 K198\nG30 P99 S400\nG0 X20\nM30\n";
    let mut it = Interpreter::from_source("t.nc", src, &cfg).unwrap();
    let mut m = Vec::new();
    while let Some(x) = it.next_move().unwrap() {
        m.push(x);
    }
    same(
        &taps(&m),
        &[
            ("rapid", 5.0, 0.0, 0.0, 0),
            ("aux", 29.0, 0.0, 0.0, 0),
            ("rapid", 2.0, 0.0, 0.0, 2),
            ("tap", -10.0, -2.0, 500.0, 3),
            ("tap", 2.5, -2.0, 800.0, 5),
            ("rapid", 2.5, 0.0, 0.0, 0),
            ("end", 0.0, 0.0, 0.0, 0),
        ],
    );
    assert_eq!(&*m[4].tag.as_ref().unwrap().cycle, "G30 P99");
    assert!(it.drill_mode().is_none(), "G30 P99 leaves G80");
    let t = it.last_tap().unwrap();
    assert_eq!((t.axis, t.r_plane, t.lead, t.rpm, t.override_pct), ('Z', 2.0, -2.0, 500.0, 200.0));
    // Without a tap to return from.
    let a = run_err("G30 P99 S500\n");
    assert_eq!((a.number, a.pos.unwrap().col), (cncgw::alarm::TAP_RETURN, 1));
}

fn lims() -> cncgw::motion::Limits {
    let mut l = cncgw::motion::Limits::from_config(&MachineConfig::embedded());
    // `drive` below feeds back perfect drives: the actual is the last setpoint.
    l.feedback_delay = 1;
    l
}

/// Feed `m` into motion and step it with perfect feedback until idle or `max` cycles
/// (`stop_at`: request a controlled stop — a reset — at that cycle). Returns the setpoints.
fn drive(mo: &mut cncgw::motion::Motion, m: &[Move], max: usize, stop_at: Option<usize>) -> Vec<cncgw::motion::Setpoint> {
    let mut fb = cncgw::motion::Feedback { pos: mo.position(), spindle_rpm: 0.0, ..Default::default() };
    let mut out = Vec::new();
    let mut k = 0;
    for x in m {
        mo.push(x).unwrap_or_else(|a| panic!("{a}"));
    }
    while k < max {
        if Some(k) == stop_at {
            mo.stop();
        }
        let sp = mo.step(&fb);
        fb = cncgw::motion::Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        out.push(sp);
        k += 1;
        if mo.is_idle() && k > 2 {
            break;
        }
    }
    out
}

/// Interrupt a rigid tap in the middle (a reset: controlled stop), keep the tap state the
/// interpreter exposes, and in a NEW interpreter (the process restarted) `G30 P99 S_` pulls
/// the tool back to R with the spindle counter-rotating on the same thread: angle change =
/// 360° × Δz / lead all the way.
#[test]
fn interrupted_tap_returns_with_g30_p99() {
    let cfg = MachineConfig::embedded();
    let src = "G98\nG0 X0 Z5\nM29 S600\nG84 Z-30 R-3 F1200\nG80\nM30\n";
    let mut it = Interpreter::from_source("t.nc", src, &cfg).unwrap();
    let mut moves = Vec::new();
    while let Some(x) = it.next_move().unwrap() {
        moves.push(x);
    }
    let state: TapReturn = it.last_tap().unwrap();
    // On disk and back (what the persistence layer does).
    let saved = serde_json::to_string(&state).unwrap();
    let state: TapReturn = serde_json::from_str(&saved).unwrap();
    let mut mo = cncgw::motion::Motion::new(lims(), [0.0; 4]);
    // Stop 1.5 s into the program: inside the in-stroke (Z from 2 to -30 at 20 mm/s).
    let sps = drive(&mut mo, &moves, 200_000, Some(750));
    let here = sps.last().unwrap().pos;
    assert!(here[2] < 0.0 && here[2] > -30.0, "stopped mid-tap at z {}", here[2]);
    // Restart: a new interpreter, told where the tool is and what it was tapping.
    let mut it2 = Interpreter::from_source("ret.nc", "G30 P99 S500;\nM30;\n", &cfg).unwrap();
    it2.set_start_position(Pos { x: here[0], y: here[1], z: here[2], c: here[3] });
    it2.set_tap_return(Some(state));
    let back: Vec<Move> = it2.map(|m| m.unwrap()).collect();
    match back[0].kind {
        MoveKind::Tap { end, lead, rpm, spindle } => assert_eq!((end.z, lead, rpm, spindle), (2.0, -2.0, 500.0, 1)),
        ref k => panic!("{k:?}"),
    }
    let mut mo2 = cncgw::motion::Motion::new(lims(), here);
    let sps = drive(&mut mo2, &back, 200_000, None);
    let last = sps.last().unwrap().pos;
    assert_eq!(last[2], 2.0, "back at R");
    for s in &sps {
        let want = here[3] + 360.0 * (s.pos[2] - here[2]) / -2.0;
        assert!((s.pos[3] - want).abs() < 1e-6, "spindle {} vs {want} at z {}", s.pos[3], s.pos[2]);
    }
    // It turned backwards (M04 sense) while pulling out.
    assert!(sps.iter().any(|s| s.spindle_rpm < -400.0));
}

/// Through the whole chain (interpreter → motion → CANopen → emulated drives) in simulated
/// time: the tap moves Z and the spindle together and ends where it started.
#[test]
fn rigid_tap_runs_in_simulated_time() {
    use cncgw::control::cycle::{CycleLoop, RunSummary};
    use cncgw::drives::canopen::CanOpenMaster;
    use cncgw::motion::{Limits, AX_Z};
    use cncgw_bus::transport::inproc::InprocBus;
    let cfg = MachineConfig::embedded();
    let src = "G98\nG0 X0 Z5\nM29 S600\nG84 Z-20 R-3 P500 F1200\nG80\nM30\n";
    let interp = Interpreter::from_source("tap.nc", src, &cfg).unwrap();
    let wire = InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == cncgw::config::AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let mut max_rpm = 0.0f64;
    let mut min_z = f64::INFINITY;
    {
        let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(&cfg), spindle, 2_000_000);
        run_program_with(&mut lp, interp, &mut summary, &mut |p| {
            max_rpm = max_rpm.max(p.spindle_rpm.abs());
            min_z = min_z.min(p.pos[AX_Z]);
        })
        .unwrap();
        lp.finish();
    }
    assert!(summary.simulated && summary.at_program_end(), "{summary:#?}");
    // 22 mm in and out at 20 mm/s plus 0.5 s dwell: at least 2.7 s.
    assert!(summary.machining_time_s > 2.7 && summary.machining_time_s < 10.0, "{}", summary.machining_time_s);
    assert!(min_z < -19.0, "went down to {min_z}");
    assert!(max_rpm > 300.0, "spindle turned at {max_rpm} rpm");
    let s = summary.axes.iter().find(|a| a.name != "x" && a.name != "z" && a.name != "y").unwrap();
    // Spindle back at its start angle (11 revolutions in, 11 out).
    assert!((s.final_actual_counts - s.program_end_counts.unwrap_or(0)).abs() <= 1, "{s:?}");
    assert!(s.max_following_error < 30.0, "{s:?}");
}

// ---------------------------------------------------------------------------------------
// SINUMERIK CYCLE84 (rigid) and CYCLE840 (compensating chuck), manual 003 §1.6.

/// The issue's call `CYCLE84(5,0,2,-15,,0.5,3,,1.5,,500,500)`: RTP 5, RFP 0, SDIS 2,
/// DP -15, DTB 0.5, SDAC 3, PIT 1.5, SST 500, SST1 500: ② rapid to Z2, ③ tap to Z-15 (lead
/// −1.5: right hand, the spindle forward going in), ④ dwell 0.5 s, ⑤ tap out to Z2 at SST1,
/// ⑥ rapid to Z5 and M3 at the modal S.
#[test]
fn cycle84_issue_example() {
    let m = run("G98 S800\nG0 X0 Z20\nCYCLE84(5,0,2,-15,,0.5,3,,1.5,,500,500)\nM30\n");
    same(
        &taps(&m),
        &[
            ("rapid", 20.0, 0.0, 0.0, 0),
            ("rapid", 2.0, 0.0, 0.0, 2),
            ("tap", -15.0, -1.5, 500.0, 3),
            ("dwell", 0.5, 0.0, 0.0, 4),
            ("tap", 2.0, -1.5, 500.0, 5),
            ("rapid", 5.0, 0.0, 0.0, 6),
            ("spindle", 800.0, 0.0, 0.0, 3),
            ("end", 0.0, 0.0, 0.0, 0),
        ],
    );
}

/// MPIT: the metric coarse table (M10 = 1.5, M6 = 1.0), negative = left hand; SST1 the
/// retract speed; POSS orients the spindle (Cs) at the safety plane before the cut.
#[test]
fn cycle84_mpit_left_hand_and_poss() {
    let lead = |args: &str| -> Vec<(f64, f64)> {
        let m = run(&format!("G98 S800\nG0 X0 Z20\nCYCLE84({args})\n"));
        m.iter().filter_map(|m| if let MoveKind::Tap { lead, rpm, .. } = m.kind { Some((lead, rpm)) } else { None }).collect()
    };
    assert_eq!(lead("5,0,2,-15,,0,3,10,,,500,900"), [(-1.5, 500.0), (-1.5, 900.0)]);
    assert_eq!(lead("5,0,2,-15,,0,3,-6,,,500"), [(1.0, 500.0), (1.0, 500.0)]);
    assert_eq!(lead("5,0,2,-15,,0,3,10,1.5,,500"), [(-1.5, 500.0), (-1.5, 500.0)]);
    let m = run("G98 S800\nG0 X0 Z20 C10\nCYCLE84(5,0,2,-15,,0,5,,1,30,500)\n");
    match m[2].kind {
        MoveKind::Rapid { end } => assert_eq!((end.z, end.c), (2.0, 30.0)),
        ref k => panic!("{k:?}"),
    }
    // SDAC 5: the spindle stays stopped after the cycle.
    assert!(matches!(m.last().unwrap().kind, MoveKind::Spindle(s) if s.dir == SpindleDir::Stop));
}

/// Chip breaking (_VARI 1): cuts of _DAM 4, back _VRT 0.5 at SST1; chip removal (2): out to
/// the safety plane at SST1 and back in at SST.
#[test]
fn cycle84_chip_breaking_and_removal() {
    let strokes = |args: &str| -> Vec<(f64, f64)> {
        let m = run(&format!("G98 S800\nG0 X0 Z20\nCYCLE84({args})\n"));
        m.iter().filter_map(|m| if let MoveKind::Tap { end, rpm, .. } = m.kind { Some((end.z, rpm)) } else { None }).collect()
    };
    assert_eq!(
        strokes("5,0,2,-10,,0,3,,1,,400,800,,,,1,4,0.5"),
        [(-4.0, 400.0), (-3.5, 800.0), (-8.0, 400.0), (-7.5, 800.0), (-10.0, 400.0), (2.0, 800.0)]
    );
    assert_eq!(
        strokes("5,0,2,-10,,0,3,,1,,400,800,,,,2,4"),
        [(-4.0, 400.0), (2.0, 800.0), (-4.0, 400.0), (-8.0, 400.0), (2.0, 800.0), (-8.0, 400.0), (-10.0, 400.0), (2.0, 800.0)]
    );
}

/// CYCLE840 with encoder: a per-revolution feed of one pitch following the encoder, the
/// spindle reversed automatically (SDR 0) for the way out and SDAC again after it; without
/// encoder (ENC 1) and no pitch: the feed in force before the cycle.
#[test]
fn cycle840_with_and_without_encoder() {
    let m = run("G98 F300 S600\nG0 X0 Z20\nCYCLE840(5,0,2,-12,,0.4,0,3,0,,1.25)\n");
    same(
        &taps(&m),
        &[
            ("rapid", 20.0, 0.0, 0.0, 0),
            ("rapid", 2.0, 0.0, 0.0, 2),
            ("spindle", 600.0, 0.0, 0.0, 3),
            ("feed", 0.0, 0.0, 0.0, 3),
            ("dwell", 0.4, 0.0, 0.0, 4),
            ("spindle", 600.0, 0.0, 0.0, 4),
            ("feed", 0.0, 0.0, 0.0, 5),
            ("spindle", 600.0, 0.0, 0.0, 3),
            ("rapid", 5.0, 0.0, 0.0, 6),
        ],
    );
    let feeds: Vec<(f64, cncgw::canon::Feed)> =
        m.iter().filter_map(|m| if let MoveKind::Feed { end, feed } = m.kind { Some((end.z, feed)) } else { None }).collect();
    assert_eq!(feeds, [(-12.0, cncgw::canon::Feed::PerRev(1.25)), (2.0, cncgw::canon::Feed::PerRev(1.25))]);
    let m = run("G98 F300 S600\nG0 X0 Z20\nCYCLE840(5,0,2,-12,,0,4,3,1)\n");
    let feeds: Vec<cncgw::canon::Feed> = m.iter().filter_map(|m| if let MoveKind::Feed { feed, .. } = m.kind { Some(feed) } else { None }).collect();
    assert_eq!(feeds, [cncgw::canon::Feed::PerMin(300.0), cncgw::canon::Feed::PerMin(300.0)]);
}

/// CYCLE84/840 parameter alarms (SINUMERIK numbers).
#[test]
fn cycle84_840_alarms() {
    let num = |src: &str| run_err(&format!("G98 F100 S500\nG0 X0 Z20\n{src}\n")).number;
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,3,,,,500)"), 61001); // no pitch
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,3,11,,,500)"), 61001); // M11 is not a coarse size
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,3,10,2,,500)"), 61001); // M10 is 1.5, not 2
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,7,,1,,500)"), 61102);
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,3,,1)"), 61003); // no SST
    assert_eq!(num("CYCLE84(5,0,2,-15,,0,3,,1,,500,,,,,3)"), 61002);
    assert_eq!(num("CYCLE840(5,0,2,-15,,0,0,5,0,,1)"), 61102);
    assert_eq!(num("CYCLE840(5,0,2,-15,,0,0,3,0)"), 61001);
    assert_eq!(num("CYCLE840(5,0,2,-15,,0,0,3,7,,1)"), 61002);
}

/// Another drilling cycle after rigid tapping without G80 ends rigid tapping like G80 and
/// the G83 holes drill normally; the spindle state from before M29 (M03 S1500) came back at
/// the end of the tapped hole (004 step ⑦) and is not output again.
#[test]
fn another_cycle_after_rigid_tapping_ends_it() {
    let m = run("G98\nM3 S1500\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000\nG83 X10 Z-5 F100\nG80\n");
    let t = taps(&m);
    same(
        &t[4..],
        &[
            ("tap", -10.0, -2.0, 500.0, 3),
            ("tap", 5.0, -2.0, 500.0, 5),
            ("spindle", 1500.0, 0.0, 0.0, 3),
            ("rapid", 5.0, 0.0, 0.0, 1),
            ("feed", 0.0, 0.0, 0.0, 3),
            ("rapid", 5.0, 0.0, 0.0, 5),
        ],
    );
    assert_eq!(m[6].src.line, 5);
    assert_eq!(t.iter().filter(|r| r.0 == "spindle" && r.1 == 1500.0).count(), 2);
    let a = run_err("G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000\nG83 X10 Z-5 F100\nM29 S400\nS300\nG84 Z-10\n");
    // After leaving rigid tapping M29 is allowed again (line 6); S before G84 is not.
    assert_eq!((a.number, a.pos.unwrap().line), (203, 7));
}

/// The manual's flexible tapping example (004 §2.22.3) 200 mm nearer the chuck (the travel
/// limits), two holes, through motion with
/// perfect drives under `params` and feed override `ovr`: (spindle rpm fed back, Z, action)
/// of every cycle.
fn flex_run(params: &str, ovr: f64) -> Vec<(f64, f64, u32)> {
    let cfg = cfg_with(params);
    let m = run_cfg("G98\nG0 X0 Z0\nM3 S800\nG84 Z-40 P1 F1600\nX10\nG80\nM30\n", &cfg);
    let mut l = cncgw::motion::Limits::from_config(&cfg);
    l.feedback_delay = 1;
    let mut mo = cncgw::motion::Motion::new(l, [0.0; cncgw::motion::N_AXES]);
    mo.set_feed_override(ovr);
    let sp = drive(&mut mo, &m, 200_000, None);
    let mut rpm = 0.0;
    sp.iter()
        .map(|s| {
            // What the cycle saw: the speed of the setpoint before.
            let r = (rpm, s.pos[2], s.line);
            rpm = s.spindle_rpm;
            r
        })
        .collect()
}

/// 004 §2.22.3 note 3: the tapping axis follows the spindle (one lead per revolution), not
/// the feed override: at S800 and lead 2 it runs 1600 mm/min with the override at 50 %.
#[test]
fn flexible_tap_follows_the_spindle_whatever_the_feed_override() {
    for ovr in [0.5, 1.0, 1.5] {
        let t = flex_run("5275 = 0\n5276 = 0", ovr);
        let dt = 0.002;
        // Every cycle of the in-stroke at full speed moves lead × rpm × dt.
        let full: Vec<f64> = t
            .windows(2)
            .filter(|w| w[0].1 > -35.0 && w[1].1 < -5.0 && w[1].1 < w[0].1 && (w[1].0 - 800.0).abs() < 1e-9)
            .map(|w| (w[0].1 - w[1].1) / dt * 60.0)
            .collect();
        assert!(full.len() > 100, "ovr {ovr}: {} cycles at full speed", full.len());
        for v in full {
            assert!((v - 1600.0).abs() < 1e-6, "ovr {ovr}: {v} mm/min");
        }
    }
}

/// No.5276 (manual 000): the retract waits until the encoder reads the reversed spindle at
/// No.5276 × 0.1 rpm; without it the tool starts out with the spindle barely turning.
#[test]
fn flexible_tap_retract_waits_for_no_5276() {
    let first_out = |t: &[(f64, f64, u32)]| {
        let bottom = t.iter().position(|s| (s.1 + 40.0).abs() < 1e-9).expect("reaches the bottom");
        let k = t[bottom..].iter().position(|s| s.1 > -40.0 + 1e-9).expect("retracts") + bottom;
        t[k].0
    };
    let rpm = first_out(&flex_run("5275 = 0\n5276 = 3000", 1.0));
    assert!(rpm <= -300.0 && rpm > -300.0 - 6000.0 * 0.002 - 1e-9, "retract started at {rpm} rpm");
    let rpm = first_out(&flex_run("5275 = 0\n5276 = 0", 1.0));
    assert!(rpm > -300.0 && rpm < 0.0, "retract started at {rpm} rpm");
}

/// No.5275 (manual 000): the axis lags the encoder by that many cycles and is compensated:
/// by the end of the spindle's run-up the tool is N × cycle × v further in than without.
#[test]
fn flexible_tap_lag_compensation_no_5275() {
    // The second hole starts the spindle from standstill at R (note 2).
    let z_at_full = |t: &[(f64, f64, u32)]| {
        let start = t.iter().rposition(|s| s.1.abs() < 1e-9 && s.0 == 0.0).expect("second hole at R");
        let k = t[start..].iter().position(|s| (s.0 - 800.0).abs() < 1e-9).expect("full speed") + start;
        t[k].1
    };
    let plain = z_at_full(&flex_run("5275 = 0\n5276 = 0", 1.0));
    let comp = z_at_full(&flex_run("5275 = 4\n5276 = 0", 1.0));
    let want = 4.0 * 0.002 * 1600.0 / 60.0;
    assert!((plain - comp - want).abs() < 0.02 * want, "ahead by {} mm, want {want}", plain - comp);
}

/// The tapping spindle of each `Tap` stroke.
fn tap_spindles(m: &[Move]) -> Vec<u8> {
    m.iter().filter_map(|m| if let MoveKind::Tap { spindle, .. } = m.kind { Some(spindle) } else { None }).collect()
}

/// Manual 000 note 2: E1–E4 in the G84 block selects the tapping spindle until G80; without
/// E, No.5200#7 = 1 takes the M24–M27 selection (held until another), No.5200#7 = 0 the
/// spindle selection signals (this machine: spindle 1), M24–M27 being ordinary M codes then.
/// The strokes carry it, and so do `cncgw plan`'s JSON lines and the G30 P99 state.
#[test]
fn spindle_selection_e_and_m24_m27() {
    let prog = |sel: &str, e: &str| format!("G98\nG0 X0 Z5\n{sel}\nM29 S500\nG84 Z-10 F1000 {e}\nG80\nM29 S500\nG84 Z-10 F1000\nG80\nM30\n");
    // E2 for the first mode only.
    let m = run(&prog("", "E2"));
    assert_eq!(tap_spindles(&m), [2, 2, 1, 1]);
    // No.5200#7 = 1: M26 selects spindle 3 for both modes; E overrides it.
    let cfg = cfg_with("5200 = 128");
    assert_eq!(tap_spindles(&run_cfg(&prog("M26", ""), &cfg)), [3, 3, 3, 3]);
    assert_eq!(tap_spindles(&run_cfg(&prog("M26", "E4"), &cfg)), [4, 4, 3, 3]);
    // No.5200#7 = 0: M26 selects nothing (and is output as an ordinary M code).
    let m = run(&prog("M26", ""));
    assert_eq!(tap_spindles(&m), [1, 1, 1, 1]);
    assert!(m.iter().any(|m| m.kind == MoveKind::Aux { letter: 'M', value: 26.0 }));
    // The plan line shows it.
    let m = run(&prog("", "E2"));
    let tap = m.iter().find(|m| m.kind.name() == "tap").unwrap();
    let v: serde_json::Value = serde_json::from_str(&cncgw::interp::plan::move_to_json(tap)).unwrap();
    assert_eq!((v["kind"].as_str(), v["spindle"].as_u64(), v["rpm"].as_f64()), (Some("tap"), Some(2), Some(500.0)));
    // K198 keeps it for G30 P99.
    let mut it =
        Interpreter::from_source("t.nc", "G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000 E3 K198\nG30 P99\nM30\n", &MachineConfig::embedded()).unwrap();
    let mut all = Vec::new();
    while let Some(x) = it.next_move().unwrap() {
        all.push(x);
    }
    assert_eq!(tap_spindles(&all), [3, 3]);
    assert_eq!(it.last_tap().unwrap().spindle, 3);
    // E out of range.
    let a = run_err("G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000 E5\n");
    assert_eq!((a.number, a.pos.unwrap().col), (cncgw::alarm::VALUE_RANGE, 16));
}

/// A state file written before the spindle field existed reads as spindle 1.
#[test]
fn tap_return_without_spindle_reads_spindle_1() {
    let t: TapReturn = serde_json::from_str(r#"{"axis":"Z","r_plane":2.0,"lead":-2.0,"rpm":500.0,"override_pct":100.0}"#).unwrap();
    assert_eq!(t.spindle, 1);
}

/// The machine drives one spindle: a tap on spindle 2 is refused by motion at `push`, with
/// an alarm saying what to do, before anything moves; spindle 1 runs.
#[test]
fn motion_refuses_a_tap_on_a_spindle_the_machine_lacks() {
    let m = run("G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000 E2\nG80\nM30\n");
    let mut mo = cncgw::motion::Motion::new(lims(), [0.0; cncgw::motion::N_AXES]);
    let mut refused = None;
    for x in &m {
        if let Err(a) = mo.push(x) {
            refused = Some((a, x.kind.clone()));
            break;
        }
    }
    let (a, k) = refused.expect("refused");
    assert!(matches!(k, MoveKind::Tap { spindle: 2, .. }), "{k:?}");
    assert_eq!(a.number, cncgw::alarm::UNSUPPORTED, "{a}");
    assert!(a.message.contains("spindle 2") && a.message.contains("E1"), "{a}");
    assert_eq!(a.pos.as_ref().map(|p| p.line), Some(4));
    let m = run("G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000 E1\nG80\nM30\n");
    let mut mo = cncgw::motion::Motion::new(lims(), [0.0; cncgw::motion::N_AXES]);
    let sp = drive(&mut mo, &m, 200_000, None);
    assert!(sp.iter().any(|s| (s.pos[2] + 10.0).abs() < 1e-9), "taps to the bottom");
}

/// No.5200#2 = 1 (manual 000): cancelling rigid tapping waits for RGTAP = 0 — an exact-stop
/// wait point at the G80 block that nothing after it passes before motion is there. With
/// #2 = 0, or for flexible tapping, no wait point.
#[test]
fn rigid_cancel_waits_with_no_5200_2() {
    let src = "G98\nG0 X0 Z5\nM29 S500\nG84 Z-10 F1000\nG80\nG0 X20\nM30\n";
    let waits = |m: &[Move]| {
        m.iter().filter(|m| m.kind == MoveKind::Dwell { seconds: 0.0 }).map(|m| (m.src.line, m.exact_stop, m.tag.is_none())).collect::<Vec<_>>()
    };
    assert_eq!(waits(&run_cfg(src, &cfg_with("5200 = 4"))), [(5, true, true)]);
    assert!(waits(&run(src)).is_empty());
    assert!(waits(&run_cfg("G98\nS500 M3\nG0 X0 Z5\nG84 Z-10 F1000\nG80\nM30\n", &cfg_with("5200 = 4"))).is_empty());
    // The wait point sits after the hole's last stroke and before the next block's move.
    let m = run_cfg(src, &cfg_with("5200 = 4"));
    let i = m.iter().position(|m| m.kind == MoveKind::Dwell { seconds: 0.0 }).unwrap();
    assert!(m[..i].iter().any(|m| m.kind.name() == "tap") && m[i + 1..].iter().all(|m| m.kind.name() != "tap"));
    assert!(m[i + 1..].iter().any(|m| m.src.line == 6));
}

/// CYCLE84 POSS orients the spindle that turns the tool (issue 20.7): the work spindle (C)
/// on a machine whose drilling tool stands still — also on a machine that has a tool spindle
/// for polygon turning; where a driven tool drills (machine.drilling_spindle = "tool"), the
/// cycles that would turn, tap with or orient the work spindle under it are refused before
/// anything moves, and the setting needs a tool spindle.
#[test]
fn cycle84_poss_orients_the_spindle_that_turns_the_tool() {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe-polygon.toml")).unwrap();
    let polygon = MachineConfig::from_toml("lathe-polygon.toml", &text).unwrap();
    let prog = "G98 S800\nG0 X0 Z20 C10\nCYCLE84(5,0,2,-15,,0,5,,1,30,500)\nM30\n";
    let m = run_cfg(prog, &polygon);
    assert!(matches!(m[2].kind, MoveKind::Rapid { end } if end.c == 30.0), "{:?}", m[2].kind);

    let driven = MachineConfig::from_toml("t.toml", &text.replace("drilling_spindle = \"work\"", "drilling_spindle = \"tool\"")).unwrap();
    for cycle in ["CYCLE84(5,0,2,-15,,0,5,,1,30,500)", "CYCLE86(5,0,2,-15,,0,3,,,,30)", "CYCLE840(5,0,2,-15,,0,0,3,1,1.0)"] {
        let a = run_err_cfg(&format!("G98 S800 F100\nG0 X0 Z20 C10\n{cycle}\nM30\n"), &driven);
        assert_eq!((a.number, a.pos.as_ref().map(|p| p.line)), (10, Some(3)), "{cycle}: {a}");
        assert!(a.message.contains("drilling_spindle = \"tool\""), "{a}");
    }
    // Without a tool spindle the setting is refused with the config.
    let lathe = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).unwrap();
    let e = MachineConfig::from_toml("t.toml", &lathe.replace("[machine]", "[machine]\ndrilling_spindle = \"tool\"")).unwrap_err();
    assert!(format!("{e}").contains("drilling_spindle"), "{e}");
}
