//! G88 side rigid tapping (manual 000) through the whole chain — interpreter → motion →
//! cycle loop → CANopen → emulated drives — in simulated time: the tap strokes run along X
//! (a radius), the spindle locked to X by the lead.

use cncgw::config::MachineConfig;
use cncgw::control::embedded::measure::{monitor_stats, run_moves, SimRun};
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;

fn moves(src: &str, cfg: &MachineConfig) -> Vec<cncgw::canon::Move> {
    let it = Interpreter::from_source("g88.nc", src, cfg).unwrap_or_else(|e| panic!("{e:?}"));
    it.map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

/// Over the cycles the spindle is commanded away from the tap's start angle `th_r` (the
/// hole's C), from the drives' *actual* positions: the largest
/// |(x − x_R) − lead·(θ − θ_R)/360| in µm, the cycles measured, the lowest actual X. The
/// G88 block is line 4.
fn x_lock(run: &SimRun, x_r: f64, th_r: f64, lead: f64) -> (f64, usize, f64) {
    let (x, s) = (run.drive("x").unwrap(), run.drive("s1").unwrap());
    // Well inside the first stroke, then back to its first cycle (the spindle leaving θ_R)
    // and on to the spindle's return to θ_R at the end of the last stroke.
    let deep = run.rows.iter().position(|r| r.line == 4 && r.cmd[x] < x_r - 0.1).expect("tapped below R");
    let first = run.rows[..deep].iter().rposition(|r| r.cmd[s] == th_r).expect("the tap started at θ_R") + 1;
    let last = deep + run.rows[deep..].iter().position(|r| r.cmd[s] == th_r).expect("the spindle came back");
    let (mut worst, mut low) = (0.0f64, f64::INFINITY);
    for r in &run.rows[first..=last] {
        let e = ((r.act[x] - x_r) - lead * (r.act[s] - th_r) / 360.0) * 1000.0;
        worst = worst.max(e.abs());
        low = low.min(r.act[x]);
    }
    (worst, last - first + 1, low)
}

/// R on the initial plane (X60 = radius 30), hole at Z-12 C90, bottom X30 = radius 15, lead
/// F/S = 1.5 mm going −X (so −1.5: the spindle turns forward going in): 10 revolutions in,
/// 10 out, X back exactly on R.
#[test]
fn g88_taps_along_x_locked_to_the_spindle_and_ends_on_r() {
    let cfg = MachineConfig::embedded();
    let src = "G98\nG0 X60 Z-10 C0\nM29 S1000\nG88 Z-12 C90 X30 F1500\nG80\nM30\n";
    let m = moves(src, &cfg);
    let leads: Vec<f64> = m.iter().filter_map(|m| if let cncgw::canon::MoveKind::Tap { lead, .. } = m.kind { Some(lead) } else { None }).collect();
    assert_eq!(leads, [-1.5, -1.5]);
    let run = run_moves(&cfg, Limits::from_config(&cfg), m, None).unwrap();
    run.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(run.summary.simulated && run.summary.at_program_end(), "{:#?}", run.summary);
    let (worst, n, low) = x_lock(&run, 30.0, 90.0, -1.5);
    eprintln!("G88 S1000 lead 1.5: max |x − lead·θ/360| {worst:.2} µm over {n} cycles, bottom {low:.4}");
    // 15 mm at 25 mm/s each way (1.2 s = 600 cycles) plus the ramps.
    assert!(n > 600, "the tap was measured over {n} cycles");
    assert!(worst <= 6.0, "spindle–X sync error {worst:.2} µm");
    assert!((low - 15.0).abs() < 0.01, "bottom at X radius {low}");
    // The sync monitor watched the X strokes and stayed within its limit.
    let (mon_max, _, mon_n) = monitor_stats(&run).unwrap();
    assert!(mon_n > 600 && mon_max < Limits::from_config(&cfg).sync_err_limit_um, "monitor {mon_max} µm over {mon_n}");
    // The spindle turned 10 revolutions (−X is forward, M03: the angle grows) and back.
    let s = run.drive("s1").unwrap();
    let top = run.rows.iter().map(|r| r.act[s]).fold(f64::NEG_INFINITY, f64::max);
    // Within 1.5°: the spindle turns back up to 1.2° short of the command on the bell-shaped
    // profile (its dry friction; X follows it).
    assert!((top - (90.0 + 3600.0)).abs() < 1.5, "deepest spindle angle {top}");
    // X ends exactly on R (radius 30 = 300000 counts): the correction has faded out.
    let x = run.summary.axes.iter().find(|a| a.name == "x").unwrap();
    assert_eq!(x.final_target_counts, 300_000);
    assert!((x.final_actual_counts - 300_000).abs() <= 1, "{x:?}");
}

/// With an R point below the initial plane and pecks (Q, radius): every stroke keeps the
/// same X–angle relation; action 6 takes X back to the initial plane.
#[test]
fn g88_peck_with_r_point_keeps_one_thread() {
    let cfg = MachineConfig::embedded();
    let src = "G98\nG0 X60 Z-10 C0\nM29 S800\nG88 Z-12 X36 R-4 Q4 F800\nG80\nM30\n";
    let m = moves(src, &cfg);
    let strokes = m.iter().filter(|m| matches!(m.kind, cncgw::canon::MoveKind::Tap { .. })).count();
    assert!(strokes >= 4, "pecks: {strokes} strokes");
    let run = run_moves(&cfg, Limits::from_config(&cfg), m, None).unwrap();
    run.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(run.summary.at_program_end(), "{:#?}", run.summary);
    let (worst, n, low) = x_lock(&run, 26.0, 0.0, -1.0);
    eprintln!("G88 peck S800 lead 1: max {worst:.2} µm over {n} cycles, bottom {low:.4}");
    assert!(worst <= 6.0, "spindle–X sync error {worst:.2} µm");
    assert!((low - 18.0).abs() < 0.01, "bottom at X radius {low}");
    let x = run.summary.axes.iter().find(|a| a.name == "x").unwrap();
    assert_eq!(x.final_target_counts, 300_000, "action 6: back on the initial plane");
}

/// The sync correction works on X as on Z: without it (open loop, both from one profile) the
/// spindle's lag shows as a much larger X–spindle error.
#[test]
fn the_sync_correction_acts_on_x() {
    let cfg = MachineConfig::embedded();
    let src = "G98\nG0 X60 Z-10 C0\nM29 S2000\nG88 Z-12 C90 X30 F3000\nG80\nM30\n";
    let worst = |corr: bool| {
        let mut l = Limits::from_config(&cfg);
        l.sync_correction = corr;
        l.sync_err_limit_um = f64::INFINITY;
        let run = run_moves(&cfg, l, moves(src, &cfg), None).unwrap();
        run.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
        x_lock(&run, 30.0, 90.0, -1.5).0
    };
    let (on, off) = (worst(true), worst(false));
    eprintln!("G88 S2000: max {on:.2} µm with the correction, {off:.2} µm without");
    assert!(on <= 6.0 && on < 0.6 * off, "on {on:.2} off {off:.2}");
}
