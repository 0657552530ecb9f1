//! `cncgw identify` (issue 17.2) on the emulated drives of `tests/drive_models/`, in simulated
//! time (`--sim-config`, the embedded machine): the delay and the time constant it finds
//! against the truth of each model, the velocity lag it predicts against a lag measured in a
//! separate run, and the tap with the identified responses in the machine configuration.
//!
//! `cargo test --test identify -- --nocapture identified_vs_truth` prints the table that the
//! README's commissioning section shows.
//!
//! The truth, computed here independently of the fit:
//! - **delay** = 2 + `transport_delay_cycles` cycles, from the emulator's structure: a CSP
//!   target written in cycle k is latched at the next SYNC and reached by the drive's linear
//!   interpolation one period later, where the actual position the controller reads in cycle
//!   k + 2 is sampled; a model's transport delay queues the target that many SYNCs more. The
//!   inner loops add no delay in this sense (the delay is the part of the constant-speed lag
//!   the position loop does not explain, and a PI velocity loop has no lag at constant speed).
//! - **τ** = the dominant (slowest) pole of the drive's own closed cascade — position loop Kv
//!   with the velocity loop, current loop, speed filter and (belt) two-mass mechanics inside —
//!   measured on sim-drives' `Servo` itself: a small position step, no friction, no encoder
//!   quantisation (a 1000× finer position unit and a 40-bit speed encoder), no backlash, and
//!   the log-slope of the remaining error between 30 % and 3 % of the step. It is ≈ 1/Kv (the
//!   velocity loop and the speed filter shift it by 1–5 %): the table shows both.

use cncgw::config::{DriveResponse, MachineConfig};
use cncgw::control::embedded::matrix::measure_model_with;
use sim_drives::servo::step_trace;
use std::path::PathBuf;

const MODELS: [&str; 9] =
    ["default", "soft_spindle", "heavy_spindle", "coarse_spindle_encoder", "lowff_z", "delay1", "delay2", "belt_z", "high_friction"];

fn model(name: &str) -> String {
    format!("{}/tests/drive_models/{name}.toml", env!("CARGO_MANIFEST_DIR"))
}

fn cncgw(args: &[&str]) -> std::process::Output {
    testkit::cli!().output(args)
}

fn identify(axis: &str, m: &str) -> serde_json::Value {
    identify_file(axis, &model(m))
}

/// `cncgw identify AXIS --json` on the model in `file`: its answer.
fn identify_file(axis: &str, file: &str) -> serde_json::Value {
    let o = cncgw(&["identify", axis, "--json", "--sim-config", file]);
    assert!(o.status.success(), "{file}: {}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// The truth of `axis` in model `m`: (delay in cycles, τ in s, 1/Kv in s, Kv's feed-forward).
fn truth(axis: &str, m: &str) -> (f64, f64, f64, f64) {
    truth_of(axis, &model(m))
}

/// The same for the model in `file`.
fn truth_of(axis: &str, file: &str) -> (f64, f64, f64, f64) {
    let sim = sim_drives::SimConfig::from_toml(&std::fs::read_to_string(file).unwrap()).unwrap();
    let d = sim.drives.iter().find(|d| d.axis == axis).unwrap();
    let mut p = d.physics.clone();
    p.coulomb_friction = 0.0;
    p.viscous_friction = 0.0;
    p.speed_encoder_bits = 40;
    p.extra.encoder_counts_per_rev = 0;
    p.extra.backlash_deg = 0.0;
    let cpr = d.counts_per_rev * 1000;
    // 0.01 rad: far from the speed and torque limits on every kind of drive.
    let step = 0.01 / (2.0 * std::f64::consts::PI) * cpr as f64;
    let tr = step_trace(&p, cpr, step, 50e-6, 3.0, 50e-6);
    let at = |frac: f64| tr.iter().find(|(_, x)| step - x <= frac * step).map(|(t, x)| (*t, step - x)).unwrap();
    let ((t1, e1), (t2, e2)) = (at(0.3), at(0.03));
    let tau = (t2 - t1) / (e1 / e2).ln();
    (2.0 + p.extra.transport_delay_cycles as f64, tau, 1.0 / p.kv, p.velocity_ff)
}

#[test]
fn identified_vs_truth() {
    let mut bad = vec![];
    eprintln!("| model | axis | delay identified / truth (cycles) | τ identified / truth (ms) | 1/Kv (ms) | ff identified / Kv's | VAF % |");
    eprintln!("| --- | --- | --- | --- | --- | --- | --- |");
    for m in MODELS {
        for axis in ["z", "s1"] {
            let r = identify(axis, m);
            let (d0, tau0, inv_kv, ff0) = truth(axis, m);
            let d = r["delay_cycles"].as_f64().unwrap();
            let tau = r["time_constant_ms"].as_f64().unwrap() * 1e-3;
            let ff = r["feed_forward"].as_f64().unwrap();
            eprintln!(
                "| {m} | {axis} | {d:.2} / {d0:.0} | {:.1} / {:.1} | {:.1} | {ff:.4} / {ff0} | {:.2} |",
                tau * 1e3,
                tau0 * 1e3,
                inv_kv * 1e3,
                r["vaf_pct"].as_f64().unwrap(),
            );
            if (d / d0 - 1.0).abs() > 0.1 || (tau / tau0 - 1.0).abs() > 0.1 || (ff - ff0).abs() > 0.005 {
                bad.push(format!("{m} {axis}: delay {d:.2} vs {d0}, τ {:.1} ms vs {:.1} ms", tau * 1e3, tau0 * 1e3));
            }
        }
    }
    assert!(bad.is_empty(), "identified beyond 10 % of the truth: {bad:#?}");
}

/// The variants outside the matrix (`tests/drive_models/variants/`: Z with 0–8-fold friction,
/// other gains (Kv 15 to 90/s), feed-forward, inertia, encoder, backlash, velocity loop, a
/// belt with friction, Kv 20/s with four-fold friction; spindles on Kv 8/s, with eight-fold
/// friction, with delay; three on a 4096-line encoder, `senc_*`, whose delay the ARX step read
/// a cycle or two early until 2026-11-30; a spindle of 0.13 kg·m² on 85 N·m, `sj13`): the
/// delay and τ within 10 % of the truth. Until 2026-11-29 (evening) Kv 15/s read τ 15 % short,
/// Kv 20/s with four-fold friction 24 % (the fit through the breakaways' transients), and the
/// slow velocity loop 15 % long; until 2026-11-30 (late) `sj13` 16 % long (68 ms for 58.5: its
/// velocity loop is barely faster than its position loop, `identify::FAST_OVER_SLOW_RELAXED`).
#[test]
fn identified_vs_truth_on_the_variants() {
    let bad = beyond_bounds_in("variants", 23, |m| if m.starts_with('s') { "s1" } else { "z" });
    assert!(bad.is_empty(), "identified beyond the bounds: {bad:#?}");
}

/// Identify every model of `tests/drive_models/DIR` (there must be `count`) on the axis
/// `axis_of` names for it: those whose delay or τ is beyond 10 % of the truth.
fn beyond_bounds_in(dir: &str, count: usize, axis_of: fn(&str) -> &'static str) -> Vec<String> {
    let dir = format!("{}/tests/drive_models/{dir}", env!("CARGO_MANIFEST_DIR"));
    let mut names: Vec<String> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path().file_stem().unwrap().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names.len(), count, "{names:?}");
    let mut bad = vec![];
    for m in &names {
        let axis = axis_of(m);
        let file = format!("{dir}/{m}.toml");
        let r = identify_file(axis, &file);
        let (d0, tau0, ..) = truth_of(axis, &file);
        let d = r["delay_cycles"].as_f64().unwrap();
        let tau = r["time_constant_ms"].as_f64().unwrap() * 1e-3;
        eprintln!("{m} {axis}: delay {d:.2} / {d0}, τ {:.1} / {:.1} ms", tau * 1e3, tau0 * 1e3);
        if (d / d0 - 1.0).abs() > 0.1 || (tau / tau0 - 1.0).abs() > 0.1 {
            bad.push(format!("{m} {axis}: delay {d:.2} vs {d0}, τ {:.1} ms vs {:.1} ms", tau * 1e3, tau0 * 1e3));
        }
    }
    bad
}

/// The belts (`tests/drive_models/belt_variants/`: belt_z with lost motion, more or less
/// damping, stiffness, friction, Kv 15/s, 90 % feed-forward): Z's delay and τ within 10 % of
/// the truth. Until 2026-11-29 (late) six of them read a delay of 1.0–1.7 cycles for 2: the
/// excitation's cruises, recorded to the trace's 1 nm, never counted as steady, and the lag
/// regressed over every row came out short (`identify::RECORD_QUANTUM`); with 0.5° of lost
/// motion the belt still ringing at a speed corner crossed the answer's threshold a cycle
/// early.
#[test]
fn identified_vs_truth_on_the_belts() {
    let bad = beyond_bounds_in("belt_variants", 11, |_| "z");
    assert!(bad.is_empty(), "identified beyond the bounds: {bad:#?}");
}

/// A spindle encoder of 4096 counts per revolution (`identify_only/spindle_enc4096`): a count
/// (0.088°) is far above the speed corners a spindle makes in a cycle and the ARX step
/// response is noise, so the output-error fit decides the delay (`identify::dead_time_oe`).
/// Until 2026-11-29 (late) it read 0 cycles for 2 (ff 0.925 for 0.998).
#[test]
fn a_coarse_spindle_encoder_s_delay_is_identified() {
    let file = format!("{}/tests/drive_models/identify_only/spindle_enc4096.toml", env!("CARGO_MANIFEST_DIR"));
    let r = identify_file("s1", &file);
    let (d0, tau0, _, ff0) = truth_of("s1", &file);
    let (d, tau, ff) = (r["delay_cycles"].as_f64().unwrap(), r["time_constant_ms"].as_f64().unwrap() * 1e-3, r["feed_forward"].as_f64().unwrap());
    assert!((d / d0 - 1.0).abs() <= 0.1, "delay {d:.2} vs {d0}");
    assert!((tau / tau0 - 1.0).abs() <= 0.1, "τ {:.1} ms vs {:.1} ms", tau * 1e3, tau0 * 1e3);
    assert!((ff - ff0).abs() <= 0.005, "ff {ff:.4} vs {ff0}");
}

/// Lightly damped belts (`identify_only/belt_k4_ringing`, `belt_k5_ringing`): still ringing
/// from the last speed change, some of their speed corners answer a cycle before the drive
/// acts (lags 1, 1, 2; which corners do moved with a 3 % change of the excitation's speed),
/// and their delay read 1.0 for 2 — the first until 2026-11-29, the second in between on
/// 2026-11-30. The dead time is now the later of the corners' and the ARX step's reading.
#[test]
fn a_ringing_belt_s_delay_is_identified() {
    for m in ["belt_k4_ringing", "belt_k5_ringing"] {
        assert_delay_and_tau("z", &format!("{}/tests/drive_models/identify_only/{m}.toml", env!("CARGO_MANIFEST_DIR")));
    }
}

/// Z behind a belt with sim-drives' own dry friction (`identify_only/belt_sticks`): where the
/// demand stops the slide sticks while the motor settles against the wound belt, slower than
/// the loop that moves the slide, and τ read 14 % long through those rows (35.7 for 31.2 ms)
/// until 2026-12-01. Those rows are left out where they explain the motion worse than its own
/// fit (`identify::SETTLES_APART`): within 10 %.
#[test]
fn a_belt_whose_slide_sticks_is_identified() {
    assert_delay_and_tau("z", &format!("{}/tests/drive_models/identify_only/belt_sticks.toml", env!("CARGO_MANIFEST_DIR")));
}

/// `cncgw identify axis` on model `file`: delay and τ within 10 % of the truth.
fn assert_delay_and_tau(axis: &str, file: &str) {
    let r = identify_file(axis, file);
    let (d0, tau0, ..) = truth_of(axis, file);
    let (d, tau) = (r["delay_cycles"].as_f64().unwrap(), r["time_constant_ms"].as_f64().unwrap() * 1e-3);
    assert!((d / d0 - 1.0).abs() <= 0.1, "{file}: delay {d:.2} vs {d0}");
    assert!((tau / tau0 - 1.0).abs() <= 0.1, "{file}: τ {:.1} ms vs {:.1} ms", tau * 1e3, tau0 * 1e3);
}

/// A spindle with more load than its motor was sized for (`heavy_variants/sp_j12`: 0.12 kg·m²
/// on 70 N·m) saturated its torque in the identification's speed steps at the configured
/// acceleration and read τ tenfold (2 s against 58 ms); they ramp at half of it now
/// (`SPINDLE_ACCEL_SHARE`): within 10 %. (0.24 kg·m² on 120 N·m still reads 13 % short.)
#[test]
fn a_spindle_beyond_its_torque_is_identified() {
    assert_delay_and_tau("s1", &format!("{}/tests/drive_models/heavy_variants/sp_j12.toml", env!("CARGO_MANIFEST_DIR")));
}

/// A spindle drive with no velocity feed-forward (`identify_only/spindle_no_ff`: Kv 30/s,
/// ff 0) lags 200° at 1000 rpm, beyond its 180° following-error window at the speeds the
/// identification steps to (the drive faulted, 0x8611, and nothing was identified). The slow
/// probe reads the lag first and the run keeps within the window: the velocity lag (what the
/// sync laws use) within 5 %, τ within 10 %, and the window proposed for full speed. (Its
/// delay is read late where nothing follows at once: 4 cycles for 2.)
#[test]
fn a_spindle_without_feed_forward_is_identified_within_its_window() {
    let file = format!("{}/tests/drive_models/identify_only/spindle_no_ff.toml", env!("CARGO_MANIFEST_DIR"));
    let o = cncgw(&["identify", "s1", "--json", "--sim-config", &file]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("to stay within its following-error window"), "{err}");
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let (d0, tau0, inv_kv, ff) = truth_of("s1", &file);
    let lag0 = d0 * 0.002 + (1.0 - ff) * inv_kv;
    let (lag, tau) = (r["velocity_lag_ms"].as_f64().unwrap() * 1e-3, r["time_constant_ms"].as_f64().unwrap() * 1e-3);
    assert!((lag / lag0 - 1.0).abs() <= 0.05, "velocity lag {:.1} ms vs {:.1} ms", lag * 1e3, lag0 * 1e3);
    assert!((tau / tau0 - 1.0).abs() <= 0.1, "τ {:.1} ms vs {:.1} ms", tau * 1e3, tau0 * 1e3);
    let (w, own) = (r["proposed_following_error"].as_f64().unwrap(), r["own_lag_ms"].as_f64().unwrap() * 1e-3);
    assert!(w >= 3.0 * own * 6000.0 * 6.0 * 0.99, "window {w:.0}° for {:.1} ms at 6000 rpm", own * 1e3);
}

/// The lag of Z's actual behind its command in the middle of a 60 mm move at F1500, ms.
fn measured_lag_ms(m: &str) -> f64 {
    let dir = std::env::temp_dir().join(format!("cncgw-identify-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("lag.nc");
    std::fs::write(&prog, "G21\nG98\nG1 W-60 F1500\nM30\n").unwrap();
    let trace: PathBuf = dir.join(format!("{m}.csv"));
    let o = cncgw(&["run", "--batch", "--sim-config", &model(m), "--trace", trace.to_str().unwrap(), prog.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&trace).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    let head: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let (c, a) = (head.iter().position(|h| *h == "z_cmd").unwrap(), head.iter().position(|h| *h == "z_act").unwrap());
    let rows: Vec<Vec<f64>> = text.lines().skip(1).map(|l| l.split(',').map(|x| x.parse().unwrap_or(0.0)).collect()).collect();
    let mid = rows.len() / 2;
    let v = 1500.0 / 60.0;
    (rows[mid][c] - rows[mid][a]).abs() / v * 1e3
}

#[test]
fn identify_finds_the_delay_and_the_velocity_lag() {
    let base = identify("z", "default");
    for (m, extra) in [("delay1", 1.0), ("delay2", 2.0)] {
        let r = identify("z", m);
        let d = r["delay_cycles"].as_f64().unwrap() - base["delay_cycles"].as_f64().unwrap();
        assert!((d - extra).abs() < 0.15, "{m}: delay {} vs default {}", r["delay_cycles"], base["delay_cycles"]);
    }
    for m in ["default", "lowff_z", "belt_z", "delay2"] {
        let r = identify("z", m);
        let lag = r["velocity_lag_ms"].as_f64().unwrap();
        let meas = measured_lag_ms(m);
        eprintln!("{m}: identified velocity lag {lag:.2} ms, measured {meas:.2} ms, {r}");
        assert!((lag / meas - 1.0).abs() < 0.1, "{m}: identified {lag:.2} ms, measured {meas:.2} ms");
        assert!(r["vaf_pct"].as_f64().unwrap() > 99.0, "{r}");
    }
}

/// "The tap with the identified model": z and s1 identified on each model, their responses
/// put into the machine configuration as `[axes.NAME.response]` does, and the rigid tap
/// M10×1.5 run in the air in simulated time (S3000 over 35 mm, S6000 over 200 mm), the sync
/// error from the actual positions. Today the sync law does not read the response (it learns
/// the lags online, `sync::lag`); this holds the bounds with the sections in place.
#[test]
fn the_tap_with_the_identified_responses_meets_the_bounds() {
    for m in MODELS {
        let mut cfg = MachineConfig::embedded();
        for axis in ["z", "s1"] {
            let r = identify(axis, m);
            cfg.axes.get_mut(axis).unwrap().response = Some(DriveResponse {
                delay_cycles: r["delay_cycles"].as_f64().unwrap(),
                feed_forward: r["feed_forward"].as_f64().unwrap(),
                time_constant_ms: r["time_constant_ms"].as_f64().unwrap(),
                accel_lag_ms2: r["accel_lag_ms2"].as_f64().unwrap(),
            });
        }
        let text = std::fs::read_to_string(model(m)).unwrap();
        let row = measure_model_with(&cfg, &text, 0, false).unwrap();
        assert!(row.alarms.is_empty(), "{m}: {:?}", row.alarms);
        let (b3, b6) = (5.0, 10.0);
        let (m3, m6) = (row.tap_3000.unwrap().0, row.tap_6000.unwrap().0);
        eprintln!("{m}: tap with the identified responses S3000 {m3:.2} µm, S6000 {m6:.2} µm");
        assert!(m3 <= b3 && m6 <= b6, "{m}: tap S3000 {m3:.2} µm (bound {b3}), S6000 {m6:.2} µm (bound {b6})");
    }
}
