//! S-curve figures: machining time of a part program and the largest change of any axis'
//! acceleration from one cycle to the next, without and with jerk limits.
//!
//! Run: `cargo run --release --example scurve_figures [-- PROGRAM.nc]` (default
//! examples/first_part.nc). The embedded machine with ideal drives (the actual is the last
//! setpoint, the spindle at its commanded speed), simulated time: the figures are the
//! planner's, independent of the machine running it. Jerk limits as Fanuc's No.1772 (the
//! acceleration's ramp time, jerk = max_accel / T) on every linear axis.

use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;
use cncgw::motion::{Feedback, Limits, Motion, AX_X, AX_Z, N_AXES};

struct Fig {
    time_s: f64,
    max_acc: [f64; 2],
    max_dacc: [f64; 2],
    max_dacc_in_block: [f64; 2],
}

fn run(cfg: &MachineConfig, text: &str, cycle_ms: f64) -> Result<Fig, String> {
    let mut cfg = cfg.clone();
    cfg.machine.cycle_ms = cycle_ms;
    let interp = Interpreter::from_source("part.nc", text, &cfg).map_err(|a| format!("{a:?}"))?;
    let lim = Limits::from_config(&cfg);
    let dt = lim.cycle_s;
    let mut m = Motion::new(lim, [50.0, 0.0, 0.0, 0.0]);
    let mut moves = interp.into_iter().peekable();
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    let (mut p, mut v, mut a) = (m.position(), [0.0; N_AXES], [0.0; N_AXES]);
    let mut f = Fig { time_s: 0.0, max_acc: [0.0; 2], max_dacc: [0.0; 2], max_dacc_in_block: [0.0; 2] };
    let mut cycles = 0u64;
    let mut started = false;
    let mut hist: Vec<(u32, [f64; 2])> = Vec::new();
    loop {
        while m.has_room() {
            match moves.next() {
                Some(Ok(mv)) => m.push(&mv).map_err(|a| a.to_string())?,
                Some(Err(a)) => return Err(a.to_string()),
                None => break,
            }
        }
        if m.is_idle() && moves.peek().is_none() {
            break;
        }
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        started |= sp.pos != p;
        if started {
            cycles += 1;
        }
        let mut dacc = [0.0; 2];
        for (k, i) in [AX_X, AX_Z].into_iter().enumerate() {
            let nv = (sp.pos[i] - p[i]) / dt;
            let na = (nv - v[i]) / dt;
            f.max_acc[k] = f.max_acc[k].max(na.abs());
            dacc[k] = (na - a[i]).abs();
            f.max_dacc[k] = f.max_dacc[k].max(dacc[k]);
            p[i] = sp.pos[i];
            v[i] = nv;
            a[i] = na;
        }
        hist.push((sp.line, dacc));
        if cycles > 50_000_000 {
            return Err("does not end".into());
        }
    }
    f.time_s = cycles as f64 * dt;
    // Within a block (no block change within 3 cycles): what the profile does, without the
    // velocity jumps of G64 corners.
    for k in 3..hist.len().saturating_sub(3) {
        if hist[k - 3..=k + 3].iter().all(|h| h.0 == hist[k].0) {
            for i in 0..2 {
                f.max_dacc_in_block[i] = f.max_dacc_in_block[i].max(hist[k].1[i]);
            }
        }
    }
    Ok(f)
}

fn main() {
    let path = std::env::args().nth(1).unwrap_or_else(|| "examples/first_part.nc".into());
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("{path}: {e}");
            std::process::exit(1);
        }
    };
    let base = MachineConfig::embedded();
    let amax = base.axes.get("z").map_or(0.0, |a| a.max_accel);
    println!("{path}: embedded machine, ideal drives, simulated time (max_accel X/Z {amax} mm/s²)");
    println!(
        "{:>7} {:>24} {:>10} {:>10} {:>10} {:>22} {:>24}",
        "cycle", "jerk mm/s³", "time s", "max|a| X", "max|a| Z", "max Δa/cycle X, Z", "same, within blocks X, Z"
    );
    for cycle_ms in [2.0, 1.0] {
        for t_ms in [0.0, 16.0, 32.0, 64.0] {
            let text_cfg = if t_ms > 0.0 {
                cncgw::config::EMBEDDED_LATHE.replace("[parameters]", &format!("[parameters]\n1772 = {t_ms}"))
            } else {
                cncgw::config::EMBEDDED_LATHE.to_string()
            };
            let cfg = MachineConfig::from_toml("lathe.toml", &text_cfg).expect("embedded config with No.1772");
            let label = if t_ms > 0.0 { format!("No.1772={t_ms} ms ({:.0})", amax / (t_ms / 1000.0)) } else { "off (trapezoid)".into() };
            match run(&cfg, &text, cycle_ms) {
                Ok(f) => println!(
                    "{:>4} ms {:>24} {:>10.3} {:>10.1} {:>10.1} {:>11.1} {:>10.1} {:>12.1} {:>11.1}   (j·dt = {:.1} mm/s²)",
                    cycle_ms,
                    label,
                    f.time_s,
                    f.max_acc[0],
                    f.max_acc[1],
                    f.max_dacc[0],
                    f.max_dacc[1],
                    f.max_dacc_in_block[0],
                    f.max_dacc_in_block[1],
                    if t_ms > 0.0 { amax / (t_ms / 1000.0) * cycle_ms / 1000.0 } else { f64::INFINITY },
                ),
                Err(e) => println!("{cycle_ms:>4} ms {label:>24} failed: {e}"),
            }
        }
    }
}
