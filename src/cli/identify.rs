//! `cncgw identify AXIS`: commissioning — move one axis (a few millimetres back and forth
//! from where it stands, at three speeds) or the spindle (speed steps up and down), record the
//! set-point and the actual position every cycle, and fit the drive's response
//! (`sync::identify`): delay, velocity feed-forward, time constant, fit quality. Printed as an
//! `[axes.NAME.response]` table for the machine configuration, with the following-error window
//! the response asks for at the axis' maximum speed.

use super::run::{ExecOpts, Job, RunExtras};
use super::MachineArgs;
use super::OrSetup;
use crate::config::{AxisKind, MachineConfig};
use crate::control::trace::TraceData;
use crate::interp::Interpreter;
use crate::sync::identify::{fill_late, fresh_samples, identify, Response};
use std::path::PathBuf;

/// The command line of `cncgw identify`.
#[derive(clap::Args, Debug, Clone)]
pub struct IdentifyArgs {
    /// The axis to identify, as the configuration names it (x, z, s1, …).
    pub axis: String,
    /// How far a linear axis moves from where it stands (first towards minus), mm.
    #[arg(long, default_value_t = 10.0)]
    pub travel: f64,
    /// Move on a real bus without asking (scripts).
    #[arg(long)]
    pub yes: bool,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
    /// Keep the recorded trace here (CSV).
    #[arg(long, value_name = "FILE.csv")]
    pub trace: Option<PathBuf>,
}

/// Share of its configured acceleration a spindle's speed steps ramp with. A spindle with
/// more load than its motor was sized for saturates its torque at the full acceleration, and
/// a saturated response is not the linear one identified: a 0.07 kg·m² load on 70 N·m read τ
/// 13 % short, 0.09 kg·m² tenfold; at half, within 4 % up to 0.12 kg·m². (At a third the
/// coarse spindle encoder's delay read a cycle short: too little motion per cycle.)
const SPINDLE_ACCEL_SHARE: f64 = 0.5;

/// The spindle's speed steps, as shares of its maximum speed (the second is the fastest).
const SPINDLE_STEPS: [f64; 3] = [0.2, 0.5, 0.15];

/// Share of its maximum speed at which the probe run moves (`probe_program`): slow enough
/// that a drive with no velocity feed-forward and a soft loop (Kv 30/s) stays well inside a
/// spindle's 180° following-error window, fast enough to read its lag.
const PROBE_SPEED_SHARE: f64 = 0.05;
/// Share of its (already halved) acceleration a spindle's probe ramps with: a second-order
/// spindle with full feed-forward lags a·τ² while it ramps (τ 40 ms: 29° at 3000 rpm/s), so
/// the probe, which knows nothing yet, ramps gently and reads that lag too.
const PROBE_ACCEL_SHARE: f64 = 0.2;
/// Share of the following-error window the identification's fastest move may use up,
/// judged from the probe's lag.
const WINDOW_SHARE: f64 = 0.4;
/// Beyond one late actual position in this many the record is called unclean (a warning): a
/// gap filled over a host's stall (18 cycles at 5 ms) misses the ramp's corners it spans.
const LATE_SHARE_WARN: usize = 20;

/// Which run of the identification: the slow probe that reads the lag, or the excitation.
#[derive(Clone, Copy, PartialEq)]
enum Stage {
    Probe,
    Excite,
}

/// The G-code word that moves linear `axis` incrementally.
fn word(axis: &str) -> Result<&'static str, String> {
    match axis {
        "x" => Ok("U"),
        "z" => Ok("W"),
        "y" => Ok("V"),
        _ => Err(format!("axis {axis}: identify moves x, y, z or a spindle")),
    }
}

/// The program of `stage` for `axis`. The excitation: speed steps that show the delay, the
/// jump of the feed-forward and the lag's time constant. The probe: one slow move (or
/// spindle speed) and back, from which the lag at speed is read before the excitation's
/// speeds are chosen.
fn program(cfg: &MachineConfig, axis: &str, travel: f64, start: crate::canon::Pos, stage: Stage) -> Result<String, String> {
    let a = cfg
        .axes
        .get(axis)
        .ok_or_else(|| format!("no axis {axis} in the configuration (axes: {})", cfg.axes.keys().cloned().collect::<Vec<_>>().join(", ")))?;
    let probe = (PROBE_SPEED_SHARE * a.max_speed).round().max(1.0);
    match a.kind {
        AxisKind::Spindle if stage == Stage::Probe => Ok(format!("G21\nG97 M03 S{probe}\nG4 P800\nM05\nG4 P700\nM30\n")),
        AxisKind::Spindle => {
            let [s1, s2, s3] = SPINDLE_STEPS.map(|f| (a.max_speed * f).round());
            Ok(format!("G21\nG97 M03 S{s1}\nG4 P600\nS{s2}\nG4 P600\nS{s3}\nG4 P400\nM05\nG4 P600\nM30\n"))
        }
        AxisKind::Linear => {
            let word = word(axis)?;
            // First towards whichever side has the room (within the travel limits).
            let at = match axis {
                "x" => start.x,
                "y" => start.y,
                _ => start.z,
            };
            let room_minus = a.min.is_none_or(|lo| at - travel >= lo);
            let room_plus = a.max.is_none_or(|hi| at + travel <= hi);
            let sign = match (room_minus, room_plus) {
                (true, _) => 1.0, // minus first (the moves are -d, +d)
                (false, true) => -1.0,
                _ => {
                    return Err(format!(
                        "axis {axis} at {at:.3} has not {travel} mm of room on either side within its travel: jog it or give a smaller --travel"
                    ))
                }
            };
            // X is programmed as a diameter: U moves twice the radius.
            let d = sign * if axis == "x" { travel * 2.0 } else { travel };
            if stage == Stage::Probe {
                return Ok(format!("G21\nG98\nG1 {word}{} F{probe}\nG4 P200\nG1 {word}{} F{probe}\nG4 P200\nM30\n", -d / 2.0, d / 2.0));
            }
            let f = |k: f64| (a.max_speed * k).round();
            // Speed steps within a stroke as well as from rest: the position loop's lag shows
            // in both, the dry friction only where the axis starts, stops or reverses.
            Ok(format!(
                "G21\nG98\nG1 {word}{} F{}\nG1 {word}{} F{}\nG4 P200\nG1 {word}{} F{}\nG1 {word}{} F{}\nG4 P200\nG0 {word}{}\nG4 P200\nG0 {word}{}\nG4 P300\nM30\n",
                -d / 2.0,
                f(0.1),
                -d / 2.0,
                f(0.3),
                d / 2.0,
                f(0.3),
                d / 2.0,
                f(0.1),
                -d,
                d
            ))
        }
    }
}

/// `cncgw identify`.
pub fn run(machine: &MachineArgs, a: &IdentifyArgs) -> i32 {
    use super::exit;
    let (mut cfg, cfg_text) = match super::machine_config(machine).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    // The window is proposed for the configured maximum speed, whatever the run kept to.
    let nominal = cfg.clone();
    // The drive's own CSP response is what is identified: the friction feed-forward (a
    // torque added where the axis starts and reverses) is off for the run, as a drive's
    // autotuning turns its compensations off; a spindle ramps at `SPINDLE_ACCEL_SHARE`.
    for ax in cfg.axes.values_mut() {
        ax.friction_compensation = false;
        if ax.kind == AxisKind::Spindle {
            ax.max_accel *= SPINDLE_ACCEL_SHARE;
        }
    }
    // Checked before anything is opened (from the travel's middle: the start is not known).
    let check = program(&cfg, &a.axis, a.travel, crate::canon::Pos::ZERO, Stage::Excite);
    if let Err(e) = check.or_else(|e| if e.contains("room") { Ok(String::new()) } else { Err(e) }) {
        eprintln!("error: {e}");
        return exit::INPUT;
    }
    if let Err(c) = super::service::confirm_motion(machine, a.yes, &format!("an identification run of axis {}", a.axis)) {
        return c;
    }
    // The probe first: a drive that lags far (no feed-forward, a soft loop) would leave its
    // following-error window at the excitation's speeds before anything was learnt.
    let mut probe = cfg.clone();
    for ax in probe.axes.values_mut().filter(|ax| ax.kind == AxisKind::Spindle) {
        ax.max_accel *= PROBE_ACCEL_SHARE;
    }
    let (cmd, act, _) = match record(&probe, &cfg_text, machine, a, Stage::Probe) {
        Ok(r) => r,
        Err(c) => return c,
    };
    if let Some(r) = identify(&cmd, &act, cfg.cycle_s(), 10) {
        keep_within_window(&mut cfg, &a.axis, &r);
    }
    let (cmd, act, late) = match record(&cfg, &cfg_text, machine, a, Stage::Excite) {
        Ok(r) => r,
        Err(c) => return c,
    };
    let Some(r) = identify(&cmd, &act, cfg.cycle_s(), 10) else {
        eprintln!("error: axis {} did not move enough to identify it", a.axis);
        return exit::NOT_MET;
    };
    report(&nominal, &a.axis, &r, late, a.json);
    if late * LATE_SHARE_WARN > r.samples {
        eprintln!(
            "warning: {late} of {} actual positions came late and were interpolated: the bus or this computer was too busy for a clean record; run it again on a quiet machine",
            r.samples
        );
    }
    if r.vaf < 0.9 {
        eprintln!(
            "warning: the model accounts for only {:.1} % of the motion: the drive is not first-order-like (check its tuning, a resonance, friction)",
            r.vaf * 100.0
        );
    }
    exit::OK
}

/// Run `stage`'s program and return the axis' commanded and actual positions, every cycle,
/// the actuals that came late filled from the fresh ones around them (`fill_late`), and how
/// many were. The excitation's trace is kept where `--trace` says (as recorded).
fn record(cfg: &MachineConfig, cfg_text: &str, machine: &MachineArgs, a: &IdentifyArgs, stage: Stage) -> Result<(Vec<f64>, Vec<f64>, usize), i32> {
    use super::exit;
    let keep = a.trace.clone().filter(|_| stage == Stage::Excite);
    let csv = keep.clone().unwrap_or_else(|| std::env::temp_dir().join(format!("cncgw-identify-{}.csv", std::process::id())));
    let job = Job {
        name: format!("identify {}", a.axis),
        source: String::new(),
        first: None,
        make: Box::new(|start| {
            let prog = program(cfg, &a.axis, a.travel, start, stage)
                .map_err(|e| vec![crate::Alarm::new(crate::alarm::IDENTIFY_PLAN, format!("identify: {e}"))])?;
            Interpreter::from_source("identify.nc", &prog, cfg)
        }),
        feed: None,
    };
    let opts = ExecOpts { extras: RunExtras { trace: Some(&csv), ..RunExtras::default() }, ..ExecOpts::default() };
    let (code, _, _) = super::run::run_job(cfg, cfg_text, machine, job, &opts);
    if code != exit::OK {
        return Err(code);
    }
    let data = std::fs::read_to_string(&csv).map_err(|e| e.to_string()).and_then(|t| TraceData::parse(&t));
    if keep.is_none() {
        let _ = std::fs::remove_file(&csv);
    }
    let data = data.map_err(|e| {
        eprintln!("error: the trace {}: {e}", csv.display());
        exit::SETUP
    })?;
    match (data.column(&format!("{}_cmd", a.axis)), data.column(&format!("{}_act", a.axis))) {
        (Some(c), Some(x)) => {
            let mut act = x.to_vec();
            let col = |k: &str| data.column(&format!("{}_{k}", a.axis)).map_or(vec![0.0; act.len()], <[f64]>::to_vec);
            let (ferr, age) = (col("ferr"), col("age"));
            let late = fill_late(&mut act, &fresh_samples(c, x, &ferr, &age));
            Ok((c.to_vec(), act, late))
        }
        _ => {
            eprintln!("error: the trace has no columns of axis {}", a.axis);
            Err(exit::SETUP)
        }
    }
}

/// Lower `axis`' maximum speed for the excitation so that the drive's own lag, as the probe
/// `r` read it, stays within `WINDOW_SHARE` of its following-error window at the fastest
/// speed the excitation asks for (a spindle's half speed, a linear axis' rapid); and its
/// acceleration so that the lag while accelerating (`Response::accel_lag`) does too: a
/// second-order spindle with full feed-forward (python peer, τ 40 ms) lags nothing at speed
/// and 29° at 3000 rpm/s, and faulted a 30° window (0x8611) until 2026-11-30.
fn keep_within_window(cfg: &mut MachineConfig, axis: &str, r: &Response) {
    let lag = own_lag_s(r, cfg.cycle_s());
    let Some(ax) = cfg.axes.get_mut(axis) else { return };
    if !(ax.following_error > 0.0) {
        return;
    }
    let budget = WINDOW_SHARE * ax.following_error;
    // The fastest speed asked for, as a share of max_speed, and the units/s at which the lag
    // uses up its share of the window.
    let (top, unit, accel_unit) = match ax.kind {
        AxisKind::Spindle => (SPINDLE_STEPS[1], "rpm", "rpm/s"),
        AxisKind::Linear => (1.0, "mm/min", "mm/s²"),
    };
    if lag > 0.0 {
        let allowed = ax.max_speed * (budget / lag) / (top * ax.max_speed_units_s());
        if allowed < ax.max_speed {
            eprintln!(
                "cncgw: identify {axis}: the drive lags {:.1} ms of its own at speed: the run keeps to {:.0} % of max_speed ({allowed:.0} {unit}) to stay within its following-error window {}",
                lag * 1e3,
                100.0 * allowed / ax.max_speed,
                ax.following_error
            );
            ax.max_speed = allowed;
        }
    }
    if r.accel_lag > 0.0 {
        let allowed = ax.max_accel * (budget / r.accel_lag) / ax.max_accel_units_s2();
        if allowed < ax.max_accel {
            eprintln!(
                "cncgw: identify {axis}: the drive lags {:.0} ms² of its own per unit of acceleration: the run keeps to {allowed:.0} {accel_unit} to stay within its following-error window {}",
                r.accel_lag * 1e6,
                ax.following_error
            );
            ax.max_accel = allowed;
        }
    }
}

/// The lag the drive itself sees between its demand and its actual position at constant
/// speed, s: the velocity lag beyond the whole cycles of delay (transport, interpolation and
/// the feedback's own cycle do not count in the drive's following error). A CSP drive's
/// pipeline runs on the SYNC, in whole cycles; a fraction of a cycle is the drive's own: a
/// second-order python peer (Z τ 6 ms, 97 % feed-forward, own lag 0.36 ms) reads a delay of
/// 2.04 cycles, and beyond that delay only 0.11 ms.
pub fn own_lag_s(r: &Response, dt: f64) -> f64 {
    (r.velocity_lag_s(dt) - (r.delay_cycles as f64 + r.delay_fraction).round() * dt).max(0.0)
}

/// The drive's own lag at the axis' maximum speed and acceleration together (the end of a
/// ramp to full speed), in the axis' units (mm, degrees): a drive with full feed-forward lags
/// only while it accelerates (`Response::accel_lag`); a lead ahead is no lag.
pub fn own_lag_at_max(cfg: &MachineConfig, axis: &str, r: &Response) -> f64 {
    let ax = &cfg.axes[axis];
    own_lag_s(r, cfg.cycle_s()) * ax.max_speed_units_s() + r.accel_lag.max(0.0) * ax.max_accel_units_s2()
}

/// The following-error window (0x6065) the response asks for: three times the drive's own
/// lag at the axis' maximum speed and acceleration (`own_lag_at_max`).
pub fn proposed_window(cfg: &MachineConfig, axis: &str, r: &Response) -> f64 {
    3.0 * own_lag_at_max(cfg, axis, r)
}

fn report(cfg: &MachineConfig, axis: &str, r: &Response, late: usize, json: bool) {
    let dt = cfg.cycle_s();
    let unit = if cfg.axes[axis].kind == AxisKind::Spindle { "degrees" } else { "mm" };
    let window = proposed_window(cfg, axis, r);
    if json {
        println!(
            "{}",
            serde_json::json!({
                "axis": axis, "delay_cycles": r.delay_cycles as f64 + r.delay_fraction, "feed_forward": r.feed_forward,
                "time_constant_ms": r.time_constant_s * 1e3, "velocity_lag_ms": r.velocity_lag_s(dt) * 1e3,
                "own_lag_ms": own_lag_s(r, dt) * 1e3, "accel_lag_ms2": r.accel_lag * 1e6,
                "vaf_pct": r.vaf * 100.0, "samples": r.samples, "late_samples": late,
                "proposed_following_error": window, "following_error": cfg.axes[axis].following_error, "unit": unit,
            })
        );
        return;
    }
    println!("# cncgw identify {axis}: {} cycles of {} ms, the model accounts for {:.1} % of the motion", r.samples, dt * 1e3, r.vaf * 100.0);
    if late > 0 {
        println!("# {late} actual positions came late (a frame after its SYNC) and were interpolated from the fresh ones around them");
    }
    println!("[axes.{axis}.response]");
    println!(
        "delay_cycles = {:.1}        # set-point to the first change of the actual position the controller reads",
        r.delay_cycles as f64 + r.delay_fraction
    );
    println!("feed_forward = {:.4}      # share of a speed change that follows at once", r.feed_forward);
    println!("time_constant_ms = {:.2}   # of the rest (≈ 1/Kv)", r.time_constant_s * 1e3);
    println!("accel_lag_ms2 = {:.1}      # the drive's own lag per unit of acceleration", r.accel_lag * 1e6);
    println!(
        "# velocity lag {:.2} ms as the controller reads it, {:.2} ms of it the drive's own: at maximum speed and acceleration it lags its demand {:.4} {unit}",
        r.velocity_lag_s(dt) * 1e3,
        own_lag_s(r, dt) * 1e3,
        window / 3.0
    );
    let now = cfg.axes[axis].following_error;
    if window == 0.0 {
        println!("# no lag of the drive's own beyond the delay, at speed or accelerating: the configured following_error {now} stands");
    } else {
        println!(
            "# following_error (0x6065) of at least {window:.4} {unit} suggested (3 × that lag); configured {now}{}",
            if now < window { " — TOO SMALL: the drive would fault at full speed" } else { "" }
        );
    }
}
