//! The sync law on drives it was not tuned for: every model of `tests/drive_models/` (other
//! gains, feed-forward, inertia, friction, encoder resolution, transport delay, a compliant
//! belt with backlash), in simulated time on the embedded machine, from the drives' actual
//! positions. `cargo run --release --example drive_matrix` prints the same figures as a table.
//!
//! The bounds are issue 17's (rigid tap M10×1.5: ≤ 5 µm at S3000 over 35 mm, ≤ 10 µm at S6000
//! over 200 mm; the same G92 thread at S500–S1500 within 0.1°), except where a model is marked
//! with what this law reaches on it today (the goal stays the issue's).
//!
//! The cut figures (an M10 tap's torque against the motion: 8 N·m on the spindle, 0.3 N·m on
//! Z, from Z0 down) were measured until 2026-12-01 with that torque's sign the wrong way round
//! in the harness (`embedded::measure::Loaded`): it pushed the tool on. Against the motion,
//! as now, the tap's reversal at the bottom costs 5–7 µm on every model (the spindle's and Z's
//! loads turn with the motion there) and the belt, no longer wound up by a load that pushed
//! it, 5.7 instead of 10 µm; the bounds below are those figures with a margin.

use cncgw::config::MachineConfig;
use cncgw::control::embedded::matrix::{measure_model, measure_model_jittered, measure_model_with};
use cncgw::control::embedded::measure::{run_moves_jittered, thread_pass_moves};
use cncgw::motion::Limits;

/// (model, S3000 max µm, S6000 max µm, G92.1 max µm, phase spread °).
const BOUNDS: [(&str, f64, f64, f64, f64); 9] = [
    // Cut, the tap's torque turns with the motion at the bottom: 6.4 / 7.0 µm there (0.9 µm
    // in the air).
    ("default", 7.5, 10.0, 5.0, 0.1),
    // Cut: 5.9 / 6.9 µm.
    ("soft_spindle", 7.0, 10.0, 5.0, 0.1),
    // Cut: 5.7 / 6.6 µm.
    ("heavy_spindle", 7.0, 10.0, 5.0, 0.1),
    // Cut: 6.1 / 6.8 µm.
    ("coarse_spindle_encoder", 7.0, 10.0, 5.0, 0.1),
    // Cut: the tap's torque turns at the bottom, where a low feed-forward Z follows the
    // spindle's turn-back late (6.1 / 6.7 µm; 0.9 µm in the air, see below).
    ("lowff_z", 7.0, 10.0, 5.0, 0.1),
    // Cut: 5.2 / 5.9 µm with the friction feed-forward.
    ("delay1", 6.5, 10.0, 5.0, 0.1),
    // Two cycles of transport delay on every drive (7.0 / 5.7 µm cut, 1.4 µm in the air).
    ("delay2", 8.0, 10.0, 7.5, 0.1),
    // The belt's lost motion and compliance, cut: 5.7 / 5.7 µm where the cut's torque turns
    // at the bottom (10.0 / 8.9 µm under the harness' old load that pushed the tool on and
    // wound the belt up). G92.1 3.2 µm (the friction feed-forward is off behind a belt). The
    // thread phase 0.02° with the smoothed lead-in (0.17° with an acceleration step,
    // `THREAD_LEADIN_SMOOTH_S`).
    ("belt_z", 6.5, 6.5, 5.0, 0.1),
    // Four times the dry friction: 5.4 / 6.2 µm cut, 1.9 µm in the air, with the friction
    // feed-forward (without it Z sticks for 9 cycles as the tap starts: 12.4 µm).
    ("high_friction", 6.0, 10.0, 5.0, 0.1),
];

#[test]
fn every_drive_model_holds_the_tap_and_the_thread() {
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models");
    let mut seen = 0;
    for (name, b3, b6, bg, bp) in BOUNDS {
        let text = std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap();
        let r = measure_model(&cfg, &text).unwrap();
        eprintln!("{name}: {r:?}");
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let (m3, rms3) = r.tap_3000.unwrap();
        let (m6, _) = r.tap_6000.unwrap();
        let (mg, _) = r.g92_1.unwrap();
        let p = r.phase_spread.unwrap();
        // RMS: 1.6 µm on the belt, cut; 0.1–0.8 µm elsewhere.
        assert!(m3 <= b3 && rms3 <= 1.75, "{name}: tap S3000 max {m3:.2} µm (bound {b3}), RMS {rms3:.2}");
        assert!(m6 <= b6, "{name}: tap S6000 max {m6:.2} µm (bound {b6})");
        assert!(mg <= bg, "{name}: G92.1 max {mg:.2} µm (bound {bg})");
        assert!(p <= bp, "{name}: thread phase spread {p:.3}° (bound {bp})");
        seen += 1;
    }
    let files = std::fs::read_dir(&dir).unwrap().filter(|e| e.as_ref().is_ok_and(|e| e.path().extension().is_some_and(|x| x == "toml"))).count();
    assert_eq!(seen, files, "every model file has its bounds here");
}

/// The issue's own condition: the taps in the air, as `cncgw run --batch --sim-config MODEL`
/// runs them (no cutting load in the emulator). Every model within 5 µm at S3000 and 10 µm
/// at S6000 (the four-fold dry friction too, by the friction feed-forward: 12.4 µm without).
#[test]
fn in_the_air_every_tap_is_within_the_issues_bounds() {
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models");
    for (name, ..) in BOUNDS {
        let text = std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap();
        let r = measure_model_with(&cfg, &text, 0, false).unwrap();
        eprintln!("{name} in the air: {r:?}");
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let (b3, b6) = (5.0, 10.0);
        let (m3, m6) = (r.tap_3000.unwrap().0, r.tap_6000.unwrap().0);
        assert!(m3 <= b3 && m6 <= b6, "{name}: tap S3000 {m3:.2} µm (bound {b3}), S6000 {m6:.2} µm (bound {b6})");
    }
}

/// A real-time PC sends its SYNC late now and then. With every SYNC 0–0.3 ms late at random
/// (still simulated time), the sampled spindle angle is noisy by up to 5° at S3000: the law
/// that fed that noise forward stopped every model by alarm 2307 (issue 17, 17.6); it must
/// ride it on the stiff and the slow models alike. lowff_z and belt_z: their G92 thread
/// stopped by alarm 2307 when the lag's split into a delay and a settling first read a
/// 50-cycle settling out of the noise (2026-11-30, `LagModel::split` now checks it against
/// the two-term fit). Since the loop takes each sampled position back to its slot
/// (`Feedback::late_s`, 2026-11-30) the noise is gone at the source: delay2 went from 69 to
/// 6.4 µm, the G92.1 stroke from 5–40 µm to 1.5–7.6, the thread's phase spread from 0.9–3.4°
/// to 0.04–0.32°, and sp_heavy6 (0.24 kg·m²), stopped by alarm 2307 in every tap before —
/// its governor read the noise as speed and never saw it out of torque — taps within 4.3 µm.
#[test]
fn the_tap_and_the_thread_ride_a_jittery_sync() {
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models");
    // (model, tap S3000 and S6000 max µm) — measured (cut, the load against the motion,
    // 2026-12-01) 6.2/7.2, 5.9/6.6, 6.6/7.8, 4.8/7.2, 6.0/6.6, 5.5/5.5, 6.3/7.4 µm; G92.1
    // 1.5–7.6 µm, phase spread 0.02–0.19°.
    let models = [
        ("default", 8.0),
        ("soft_spindle", 7.5),
        ("delay1", 8.5),
        ("delay2", 10.0),
        ("lowff_z", 8.0),
        ("belt_z", 7.0),
        ("heavy_variants/sp_heavy6", 8.5),
    ];
    for (name, bound) in models {
        let text = std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap();
        let r = measure_model_jittered(&cfg, &text, 300_000).unwrap();
        eprintln!("{name} with 0.3 ms SYNC jitter: {r:?}");
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let (m3, _) = r.tap_3000.unwrap();
        let (m6, _) = r.tap_6000.unwrap();
        assert!(m3 <= bound && m6 <= bound, "{name}: tap S3000 max {m3:.2} µm, S6000 {m6:.2} µm (bound {bound})");
        let (mg, _) = r.g92_1.unwrap();
        assert!(mg <= 10.0, "{name}: G92.1 max {mg:.2} µm (bound 10)");
        let spread = r.phase_spread.unwrap();
        assert!(spread <= 0.5, "{name}: thread phase spread {spread:.3}° (bound 0.5°)");
    }
}

/// Z behind a belt, varied around belt_z (`tests/drive_models/belt_variants/`: stiffness,
/// damping, lost motion, friction behind the belt, feed-forward, position gain). In the air,
/// as `cncgw run --batch --sim-config MODEL` runs the tap: within the issue's bounds and no
/// alarm, but four-fold friction behind the belt, 6.4 µm at S3000 (held to 7). Before
/// 2026-11-29: 10.0 µm there, 8.3 µm on ff 0.90, 7.6 µm on Kv 15 and its G92 thread stopped
/// by alarm 2307 (it began while Z still ran in from the rapid); a lightly damped belt at Kv
/// 20/s with 90 % feed-forward stopped its G92 by alarm 2307 in the lead-in until the thread
/// led through its lag's settling. The thread phase on lightly damped belts: 0.13–0.36° since
/// the lead-in's second average (2026-11-30; 0.2–0.45° before), 0.05–0.10° since each pass
/// takes up the belt in the cutting direction before its lead-in (`machine.thread_take_up_mm`,
/// 2026-11-30, evening). belt_kv15 (Kv 15/s, its lag settling over 67 ms) was held to 0.25°
/// until 2026-12-02: the online fit read that time short through the samples where the
/// command turns (27 cycles for 33), so Z ran ahead where S1500's line begins (0.207°); a
/// thread's lead-in now takes the fit without the turns (`LagModel::thread_split`): 0.048°.
#[test]
fn belt_variants_hold_the_tap_in_the_air() {
    for (name, r) in in_the_air("belt_variants", 11) {
        let p = r.phase_spread.unwrap();
        assert!(p <= 0.1, "{name}: thread phase spread {p:.3}° (bound 0.1°)");
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let b3 = if name == "belt_friction4" { 7.0 } else { 5.0 };
        let (m3, m6, mg) = (r.tap_3000.unwrap().0, r.tap_6000.unwrap().0, r.g92_1.unwrap().0);
        assert!(m3 <= b3 && m6 <= 10.0, "{name}: tap S3000 {m3:.2} µm (bound {b3}), S6000 {m6:.2} µm (bound 10)");
        // Four-fold friction behind the belt: 7.0 µm since the lag fits learn faster (6.5
        // before, `LAG_FIT_FLOOR_MM_S`).
        let bg = if name == "belt_friction4" { 7.5 } else { 7.0 };
        assert!(mg <= bg, "{name}: G92.1 {mg:.2} µm (bound {bg})");
    }
}

/// Z with less velocity feed-forward than lowff_z (`tests/drive_models/lowff_variants/`: 80 %
/// at Kv 50/s, 85 % at 30 and 40/s, 90 % at 25/s), in the air: every bound of the issue, no
/// alarm. Before the lag fits weighed their samples alike (2026-11-29) the first tap began
/// with half the lag learnt: 85 % at Kv 30 gave 4.1 / 4.1 / 5.4 µm (S3000 / S6000 / G92.1),
/// now 2.7 / 2.7 / 2.6. (Below ≈ 75 % at Kv 50 the lag at rapid passes the embedded config's
/// 1 mm window: alarm 2010, a window to size from `cncgw identify`.)
#[test]
fn lowff_variants_hold_the_tap_and_the_thread_in_the_air() {
    hold_the_tap_and_the_thread_in_the_air("lowff_variants", 4, 5.0);
}

/// Mixes of a transport delay and a low velocity feed-forward on Z
/// (`tests/drive_models/delay_lowff_variants/`: 85 % and 90 % with every drive two cycles
/// late, 85 % with Z alone two cycles late), in the air: the tap's bounds, no alarm. Before
/// the lag's split into a delay and a settling (`sync::lag`, 2026-11-30) the lead filtered
/// the delay's share too and missed where the tap's acceleration ends: 7.4, 5.1 and 6.7 µm
/// at S3000, now 1.9, 1.4 and 1.9. The G92.1 stroke is held to delay2's 7.5 µm (4.8, 4.8,
/// 1.9; before 9.3, 7.9, 6.4; delay2 itself 6.6).
#[test]
fn delay_lowff_variants_hold_the_tap_and_the_thread_in_the_air() {
    hold_the_tap_and_the_thread_in_the_air("delay_lowff_variants", 3, 7.5);
}

/// Mixes of a coarse spindle encoder and a transport delay
/// (`tests/drive_models/coarse_delay_variants/`: 4096 and 8192 counts per revolution, every
/// drive two cycles late), in the air: the tap's bounds, no alarm, G92.1 held to delay2's
/// 7.5 µm. The delay lead's acceleration term multiplied the quantised spindle lag's second
/// difference by 6 into ±5 µm of Z set-point noise: 9.08 and 3.41 µm at S3000 before
/// 2026-12-01 (G92.1 16.5 and 8.8), now 3.78 and 2.28 (6.7, 7.0;
/// `sync::correction::LAG_ACCEL_SMOOTHING`).
#[test]
fn coarse_delay_variants_hold_the_tap_and_the_thread_in_the_air() {
    hold_the_tap_and_the_thread_in_the_air("coarse_delay_variants", 2, 7.5);
}

/// A coarse spindle encoder (4096 counts, 0.088°) on the spindle and stiffer velocity loops
/// on Z (`tests/drive_models/coarse_loop_variants/`, random models of
/// `examples/random_drive_models.rs`), in the air: every bound of the issue, no alarm, and
/// the thread's long axis follows the spindle no rougher than the encoder reads it. Before the
/// thread's angle was smoothed (`sync::angle_filter`, 2026-12-03) the counts' error and the
/// speed taken from them, times the prediction's horizon, shook Z's set-point by 1.6–1.8
/// counts' worth (sd 0.040–0.045°; the drives' Z by up to ±0.2°) and the thread's start moved
/// 0.110, 0.109 and 0.101° between S500, S1000 and S1500 (now 0.075, 0.097, 0.077 — what is
/// left is mostly the one reading of the count the phase is measured from).
#[test]
fn coarse_loop_variants_follow_the_spindle_smoothly() {
    hold_the_tap_and_the_thread_in_the_air("coarse_loop_variants", 3, 5.0);
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models/coarse_loop_variants");
    for name in ["e4096_j078", "e4096_vloops_both", "e4096_vloops_z"] {
        let sim = sim_drives::SimConfig::from_toml(&std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap()).unwrap();
        let moves = thread_pass_moves(15.0, 5.0, -20.0, 1.5, &[500.0, 1000.0, 1500.0]);
        let run = run_moves_jittered(&cfg, sim, Limits::from_config(&cfg), moves, None, 0).unwrap();
        assert!(run.result.is_ok(), "{name}: {:?}", run.result);
        let z = run.drive("z").unwrap();
        // One count's reading error, uniform: its standard deviation, degrees.
        let count_sd = 360.0 / 4096.0 / 12f64.sqrt();
        for line in [4, 14, 24] {
            // Z's set-point on the synchronous line, in spindle degrees (lead 1.5 mm).
            let zs: Vec<f64> = run.rows.iter().filter(|r| r.line == line && r.cmd[z] < -2.0 && r.cmd[z] > -18.0).map(|r| r.cmd[z] * 240.0).collect();
            let sd = residual_sd(&zs);
            assert!(
                zs.len() > 200 && sd <= 1.3 * count_sd,
                "{name}, line {line}: Z set-point {sd:.4}° off its line (sd; a count reads {count_sd:.4}°)"
            );
        }
    }
}

/// Standard deviation of `ys` about their least-squares line (one sample per cycle).
fn residual_sd(ys: &[f64]) -> f64 {
    let n = ys.len() as f64;
    let mx = (n - 1.0) / 2.0;
    let my = ys.iter().sum::<f64>() / n;
    let sxx: f64 = (0..ys.len()).map(|i| (i as f64 - mx).powi(2)).sum();
    let b = ys.iter().enumerate().map(|(i, y)| (i as f64 - mx) * (y - my)).sum::<f64>() / sxx;
    (ys.iter().enumerate().map(|(i, y)| (y - my - b * (i as f64 - mx)).powi(2)).sum::<f64>() / n).sqrt()
}

/// Velocity loops other than sim-drives' (`tests/drive_models/velocity_loop_variants/`: Kp,
/// integral time, speed filter and current loop varied on spindle and Z, with high friction or
/// a heavy spindle), in the air: every bound of the issue, no alarm. Where the sync correction
/// slowed Z's command to a creep at the tap's bottom and turned it back, the friction
/// feed-forward took out only the creep's share of what the drive held and the slide stuck for
/// 8 cycles: 6.3 / 4.8 µm (vfric_both, S3000 / S6000), 5.4 µm (vfric_z, S3000), 6.2 and 5.7 µm
/// (vfric_both2, vheavy_both, S6000) before 2026-11-30; now 3.1 / 3.2, 4.0, 3.9 and 2.8.
#[test]
fn velocity_loop_variants_hold_the_tap_and_the_thread_in_the_air() {
    hold_the_tap_and_the_thread_in_the_air("velocity_loop_variants", 4, 6.0);
}
/// Every model of `tests/drive_models/SUB` (at least `min`), in the air: no alarm, the
/// issue's tap bounds (S3000 5 µm, S6000 10 µm) and thread phase (0.1°), G92.1 within
/// `g92_1` µm.
fn hold_the_tap_and_the_thread_in_the_air(sub: &str, min: usize, g92_1: f64) {
    for (name, r) in in_the_air(sub, min) {
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let (m3, m6, mg) = (r.tap_3000.unwrap().0, r.tap_6000.unwrap().0, r.g92_1.unwrap().0);
        assert!(m3 <= 5.0 && m6 <= 10.0, "{name}: tap S3000 {m3:.2} µm (bound 5), S6000 {m6:.2} µm (bound 10)");
        assert!(mg <= g92_1, "{name}: G92.1 {mg:.2} µm (bound {g92_1})");
        let p = r.phase_spread.unwrap();
        assert!(p <= 0.1, "{name}: thread phase spread {p:.3}° (bound 0.1)");
    }
}

/// Spindles whose torque cannot give the configured acceleration
/// (`tests/drive_models/heavy_variants/`: load 0.12 and 0.15 kg·m² on 70 N·m; 0.135 on 81
/// N·m, which manages 98 %; 0.24 on 120 N·m): the governor (`sync::governor`) finds what the
/// spindle manages and plans with 80 % of it (at 90 % sp_j15 faulted its window in the S3000
/// tap; sp_j135 was not found at all before the governor also took 2 % of the acceleration
/// seen for 100 ms as falling behind, 2026-11-30: alarm 2010, now 1.14 µm). In
/// the air: before (2026-11-29), the S3000 tap and the G92 passes faulted the spindle's 180°
/// window (alarm 2010, 0x8611); now 1.1 and 1.5 µm, the threads within 0.02°. The S6000 tap
/// over 200 mm accelerates or brakes for most of its 5 s near the peak torque, which tripped
/// the drive's own I²t (0x2310, alarm 2010) in both until the amplifier's overload was
/// modelled (`sync::overload`, 2026-11-30): now 1.0 and 1.1 µm, no alarm. Where the drive
/// gives its max torque 0x6072 (all but sp_j12_no_limit) the torque margin
/// (`sync::torque_margin`, 2026-12-02) finds them at their limit within the first ramp, before
/// the governor would; sp_j12_no_limit keeps the governor's path.
#[test]
fn heavy_variants_are_governed_in_the_air() {
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models/heavy_variants");
    for (name, bp) in [("sp_j12", 0.1), ("sp_j12_no_limit", 0.1), ("sp_j135", 0.1), ("sp_j15", 0.1), ("sp_heavy6", 0.1)] {
        let text = std::fs::read_to_string(dir.join(format!("{name}.toml"))).unwrap();
        let r = measure_model_with(&cfg, &text, 0, false).unwrap();
        eprintln!("{name} in the air: {r:?}");
        assert!(r.alarms.is_empty(), "{name}: {:?}", r.alarms);
        let (m3, m6, mg) = (r.tap_3000.unwrap().0, r.tap_6000.unwrap().0, r.g92_1.unwrap().0);
        assert!(m3 <= 5.0, "{name}: tap S3000 {m3:.2} µm (bound 5)");
        assert!(m6 <= 10.0, "{name}: tap S6000 {m6:.2} µm (bound 10)");
        assert!(mg <= 7.0, "{name}: G92.1 {mg:.2} µm (bound 7)");
        let p = r.phase_spread.unwrap();
        assert!(p <= bp, "{name}: thread phase spread {p:.3}° (bound {bp})");
    }
}

/// Every model of `tests/drive_models/SUB` (at least `min`), measured in the air: (name, row).
fn in_the_air(sub: &str, min: usize) -> Vec<(String, cncgw::control::embedded::matrix::MatrixRow)> {
    let cfg = MachineConfig::embedded();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models").join(sub);
    let mut files: Vec<_> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "toml")).collect();
    files.sort();
    assert!(files.len() >= min, "{files:?}");
    files
        .iter()
        .map(|f| {
            let name = f.file_stem().unwrap().to_string_lossy().into_owned();
            let r = measure_model_with(&cfg, &std::fs::read_to_string(f).unwrap(), 0, false).unwrap();
            eprintln!("{name} in the air: {r:?}");
            (name, r)
        })
        .collect()
}
