//! Spindle–axis synchronisation on the emulated drives (sim-drives: a heavy, soft spindle and
//! stiff feed axes), in simulated time, measured from the drives' *actual* positions.
//! `cargo run --release --example sync_figures` prints the same figures.

use cncgw::config::MachineConfig;
use cncgw::control::embedded::measure::{
    g92_1_moves, monitor_stats, phase_spread, rigid_tap_moves, run_moves, tap_sync_error, thread_pass_moves, thread_phases, CuttingLoad,
};
use cncgw::motion::{alarms, Limits};

fn tap(rpm: f64, correction: bool) -> (f64, f64, f64) {
    let cfg = MachineConfig::embedded();
    let mut l = Limits::from_config(&cfg);
    l.sync_correction = correction;
    l.sync_err_limit_um = f64::INFINITY;
    let run = run_moves(&cfg, l, rigid_tap_moves(2.0, -30.0, 1.5, rpm), Some(CuttingLoad::m10_tap(0.0))).unwrap();
    run.result.as_ref().unwrap();
    assert!(run.summary.at_program_end(), "{:#?}", run.summary);
    let (max, rms, n) = tap_sync_error(&run, 1.5, (2, 3)).unwrap();
    assert!(n > 200, "the tap was traced ({n} cycles)");
    let s = run.drive("s1").unwrap();
    let peak = run.rows.iter().map(|r| r.spindle_rpm.abs()).fold(0.0, f64::max);
    // The spindle really turned the tap's 20 revolutions down and back.
    let turned = run.rows.iter().map(|r| r.act[s]).fold(f64::INFINITY, f64::min);
    // Within 1.5°: braked on the bell-shaped profile against the tap's torque, the spindle
    // turns back short of the commanded end.
    assert!((turned + 32.0 / 1.5 * 360.0).abs() < 1.5, "bottom at {turned}°");
    (max, rms, peak)
}

/// Cut: the tap's torque against the motion turns with it at the bottom, 6.9 / 5.3 / 6.6 µm at
/// S1000/2000/3000 (4.7–4.9 µm until 2026-12-01, measured with that torque pushing the tool on
/// — the harness had its sign the wrong way round).
#[test]
fn rigid_tap_m10_under_its_cutting_load_follows_the_spindle_with_the_correction() {
    for rpm in [1000.0, 2000.0, 3000.0] {
        let (max, rms, peak) = tap(rpm, true);
        eprintln!("S{rpm}: max {max:.2} µm, RMS {rms:.2} µm, peak {peak:.0} rpm");
        assert!(max <= 7.5, "S{rpm}: max sync error {max:.2} µm");
        assert!(rms <= 1.5, "S{rpm}: RMS sync error {rms:.2} µm");
        assert!(peak > rpm.min(2400.0) * 0.95, "S{rpm}: reached only {peak:.0} rpm");
    }
}

/// Cut at S3000: on 6.62 / 0.62 µm, off 11.05 / 3.52 µm (2026-12-01, the load against the
/// motion). The peak is the reversal's, where the correction follows the loads' turn late; the
/// RMS, the whole stroke, is where it shows.
#[test]
fn the_correction_beats_the_open_loop_tap() {
    let (on_max, on_rms, _) = tap(3000.0, true);
    let (off_max, off_rms, _) = tap(3000.0, false);
    eprintln!("S3000: on {on_max:.2}/{on_rms:.2} µm, off {off_max:.2}/{off_rms:.2} µm");
    assert!(on_max < 0.7 * off_max, "max: on {on_max:.2} vs off {off_max:.2}");
    assert!(on_rms < 0.5 * off_rms, "RMS: on {on_rms:.2} vs off {off_rms:.2}");
}

#[test]
fn the_sync_monitor_stays_quiet_on_a_good_tap_and_alarms_on_a_tight_limit() {
    let cfg = MachineConfig::embedded();
    let l = Limits::from_config(&cfg);
    let run = run_moves(&cfg, l.clone(), rigid_tap_moves(2.0, -30.0, 1.5, 2000.0), Some(CuttingLoad::m10_tap(0.0))).unwrap();
    run.result.as_ref().unwrap();
    let worst = run.rows.iter().map(|r| r.sync_err_um.abs()).fold(0.0, f64::max);
    assert!(worst > 0.0 && worst < l.sync_err_limit_um, "monitor {worst} µm, limit {}", l.sync_err_limit_um);
    // A limit below what the drives can do stops spindle and Z together with alarm 2307.
    let mut tight = l;
    tight.sync_err_limit_um = 0.5;
    let run = run_moves(&cfg, tight, rigid_tap_moves(2.0, -30.0, 1.5, 2000.0), Some(CuttingLoad::m10_tap(0.0))).unwrap();
    assert_eq!(run.result.as_ref().err().map(|a| a.number), Some(alarms::SYNC_ERROR));
    let last = run.rows.last().unwrap();
    assert!(last.spindle_rpm.abs() < 5.0, "spindle stopped: {}", last.spindle_rpm);
}

#[test]
fn a_tap_too_fast_for_z_is_refused_before_anything_moves() {
    let cfg = MachineConfig::embedded();
    // Z: 12000 mm/min; lead 3 × S5000 = 15000 mm/min.
    let run = run_moves(&cfg, Limits::from_config(&cfg), rigid_tap_moves(2.0, -30.0, 3.0, 5000.0), None).unwrap();
    let a = run.result.as_ref().unwrap_err();
    assert_eq!(a.number, alarms::THREAD_TOO_FAST, "{a}");
    let s = run.drive("s1").unwrap();
    assert!(run.rows.iter().all(|r| r.cmd[s] == run.rows[0].cmd[s]), "the spindle never moved");
}

#[test]
fn thread_phase_does_not_move_with_the_rpm() {
    let cfg = MachineConfig::embedded();
    let rpms = [500.0, 1000.0, 1500.0];
    let run = run_moves(&cfg, Limits::from_config(&cfg), thread_pass_moves(15.0, 5.0, -20.0, 1.5, &rpms), None).unwrap();
    run.result.as_ref().unwrap();
    let ph = thread_phases(&run, -5.0, rpms.len()).unwrap();
    let spread = phase_spread(&ph);
    eprintln!("phases {ph:?}, spread {spread:.4}°");
    assert!(spread <= 0.1, "thread phase moved by {spread:.3}° between S500 and S1500: {ph:?}");
    // And it is the phase the program asked for: start angle 0 and Z−5 is 25 mm = 16⅔ rev
    // from Z5 → 240°.
    for p in &ph {
        let d = (p - 240.0).rem_euclid(360.0);
        assert!(d.min(360.0 - d) < 0.1, "phase {p}° ≠ 240°");
    }
}

/// The take-up before a thread pass (`machine.thread_take_up_mm`): the G92 passes return to
/// their start against the thread's direction, so each first creeps 0.3 mm along the thread
/// at no more than 2 mm/s, stands, and then starts its lead-in from there; a pass whose
/// start was reached in the cutting direction starts at once; with the key at 0 none creeps.
#[test]
fn a_thread_pass_takes_up_against_its_return() {
    let run_with = |take_up: f64, approach_in_cut: bool| {
        let mut cfg = MachineConfig::embedded();
        cfg.machine.thread_take_up_mm = take_up;
        let mut moves = thread_pass_moves(15.0, 4.0, -20.0, 1.5, &[800.0]);
        if approach_in_cut {
            // Come down onto the start from Z5 (the cutting direction) instead of up from Z0.
            moves.insert(1, cncgw::canon::Move { kind: cncgw::canon::MoveKind::Rapid { end: cncgw::canon::Pos::xz(17.0, 5.0) }, ..moves[1].clone() });
        } else {
            moves.insert(1, cncgw::canon::Move { kind: cncgw::canon::MoveKind::Rapid { end: cncgw::canon::Pos::xz(17.0, 0.0) }, ..moves[1].clone() });
        }
        let run = run_moves(&cfg, Limits::from_config(&cfg), moves, None).unwrap();
        run.result.as_ref().unwrap();
        let (z, s) = (run.drive("z").unwrap(), run.drive("s1").unwrap());
        let rows: Vec<_> = run.rows.iter().filter(|r| r.line == 4).collect();
        let dt = rows[1].t_s - rows[0].t_s;
        // Z's set-points in the thread block: what it travels at no more than 2 mm/s before
        // it first stands again (the take-up, then the wait for the armed angle) — or 0 where
        // its first motion is already the lead-in (faster than that).
        let step = |k: usize| rows[k].cmd[z] - rows[k + 1].cmd[z];
        let first = (0..rows.len() - 1).find(|k| step(*k) != 0.0).unwrap();
        let end = (first..rows.len() - 1).find(|k| step(*k) == 0.0 || step(*k) / dt > 2.0 + 1e-9).unwrap();
        // From the thread's start, Z4 (the block's first row already carries a step).
        let crept = if step(end) == 0.0 { 4.0 - rows[end].cmd[z] } else { 0.0 };
        // The spindle was at speed before it (the creep does not wait for it).
        assert!(rows[first].spindle_rpm.is_finite() && run.rows.iter().any(|r| r.cmd[s] != run.rows[0].cmd[s]));
        crept
    };
    let (back, cut, off) = (run_with(0.3, false), run_with(0.3, true), run_with(0.0, false));
    eprintln!("crept before the lead-in: {back:.4} mm after a return, {cut:.4} approached in the cut, {off:.4} with the key at 0");
    assert!((back - 0.3).abs() < 1e-6, "took up {back} mm, not 0.3");
    assert!(cut.abs() < 1e-9 && off.abs() < 1e-9, "{cut} / {off} mm");
}

#[test]
fn g92_1_rigid_thread_is_corrected_too() {
    let cfg = MachineConfig::embedded();
    let stats = |corr: bool| {
        let mut l = Limits::from_config(&cfg);
        l.sync_correction = corr;
        l.sync_err_limit_um = f64::INFINITY;
        let run = run_moves(&cfg, l, g92_1_moves(15.0, 5.0, -40.0, 2.0, 1000.0), None).unwrap();
        run.result.as_ref().unwrap();
        assert!(run.summary.at_program_end());
        monitor_stats(&run).unwrap()
    };
    let (on, off) = (stats(true), stats(false));
    eprintln!("G92.1 S1000: on {on:?}, off {off:?}");
    assert!(on.2 > 500, "monitored {} cycles", on.2);
    assert!(on.0 <= 5.0 && on.0 < 0.5 * off.0, "max on {} off {}", on.0, off.0);
    assert!(on.1 < 0.5 * off.1, "RMS on {} off {}", on.1, off.1);
}

#[test]
fn a_dwell_at_the_bottom_keeps_the_lock_and_the_tap_ends_on_r() {
    use cncgw::canon::{Move, MoveKind};
    let cfg = MachineConfig::embedded();
    let mut l = Limits::from_config(&cfg);
    l.sync_err_limit_um = f64::INFINITY;
    let mut moves: Vec<Move> = rigid_tap_moves(2.0, -20.0, 1.5, 1500.0);
    // Dwell 0.2 s at the bottom, between the strokes (same line as the way back).
    let mut dwell = moves[2].clone();
    dwell.kind = MoveKind::Dwell { seconds: 0.2 };
    moves.insert(2, dwell);
    let run = run_moves(&cfg, l, moves, Some(CuttingLoad::m10_tap(0.0))).unwrap();
    run.result.as_ref().unwrap();
    assert!(run.summary.at_program_end(), "{:#?}", run.summary);
    let (max, rms, _) = tap_sync_error(&run, 1.5, (2, 3)).unwrap();
    eprintln!("tap with dwell: max {max:.2} µm, RMS {rms:.2} µm");
    // 6.2 µm, the load against the motion turning with it at the bottom.
    assert!(max <= 7.0 && rms <= 1.5, "max {max:.2} RMS {rms:.2}");
    // The correction has faded out: Z ends exactly on R (2 mm = 20000 counts).
    let z = run.summary.axes.iter().find(|a| a.name == "z").unwrap();
    assert_eq!(z.final_target_counts, 20_000);
}
