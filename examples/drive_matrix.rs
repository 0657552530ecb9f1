//! The spindle–axis sync figures on every drive model of `tests/drive_models/` (or the sim-drives
//! configurations given as arguments), in simulated time on the embedded machine: one table.
//!
//! Run: `cargo run --release --example drive_matrix [--param NO=VALUE …] [--jitter-us N]
//! [--air] [MODEL.toml …]` (`--air`: the taps without the cutting load, as `cncgw run
//! --sim-config` runs them; `--param 5365=20`: the embedded machine with that parameter set, e.g. a
//! bell-shaped rigid-tap acceleration; `--jitter-us 300`: every SYNC sent 0–300 µs late at
//! random, a real-time PC's wake-up jitter, still in simulated time).
//!
//! Per model: rigid tap M10×1.5 at S3000, 35 mm (Z2 → Z−33), and at S6000 over 200 mm
//! (Z2 → Z−198), cutting load on (unless `--air`); a G92.1 rigid thread (lead 2, S1000, Z5 → Z−40); the same
//! G92 thread (lead 1.5) at S500, S1000 and S1500 and the spread of its phase. Sync errors
//! are from the drives' *actual* positions: max and RMS in µm. Any alarm is shown.

use cncgw::config::MachineConfig;
use cncgw::control::embedded::matrix::{measure_model_with, MatrixRow};
use std::path::PathBuf;

fn main() {
    let mut cfg = MachineConfig::embedded();
    let mut files: Vec<PathBuf> = Vec::new();
    let mut jitter_ns = 0u64;
    let mut cut = true;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--air" {
            cut = false;
            continue;
        }
        if a == "--jitter-us" {
            let v = args.next().unwrap_or_default();
            let Ok(us) = v.parse::<u64>() else {
                eprintln!("error: --jitter-us wants microseconds, got {v:?}");
                std::process::exit(2);
            };
            jitter_ns = us * 1000;
            continue;
        }
        if a != "--param" {
            files.push(PathBuf::from(a));
            continue;
        }
        let kv = args.next().unwrap_or_default();
        let Some((no, v)) = kv.split_once('=').and_then(|(n, v)| Some((n.to_string(), v.parse::<f64>().ok()?))) else {
            eprintln!("error: --param wants NO=VALUE, got {kv:?}");
            std::process::exit(2);
        };
        cfg.parameters.insert(no, toml::Value::Float(v));
    }
    if files.is_empty() {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/drive_models");
        files = match std::fs::read_dir(&dir) {
            Ok(d) => d.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.extension().is_some_and(|x| x == "toml")).collect(),
            Err(e) => {
                eprintln!("error: {}: {e}", dir.display());
                std::process::exit(2);
            }
        };
        files.sort();
    }
    println!("| model | tap S3000 35 mm max / RMS µm | tap S6000 200 mm max / RMS µm | G92.1 S1000 max / RMS µm | thread phase spread S500–1500 | alarms |");
    println!("|---|---|---|---|---|---|");
    for f in &files {
        let name = f.file_stem().map_or("?".into(), |s| s.to_string_lossy().into_owned());
        let text = match std::fs::read_to_string(f) {
            Ok(t) => t,
            Err(e) => {
                eprintln!("error: {}: {e}", f.display());
                std::process::exit(2);
            }
        };
        match measure_model_with(&cfg, &text, jitter_ns, cut) {
            Ok(r) => println!("{}", row(&name, &r)),
            Err(e) => {
                eprintln!("error: {}: {e}", f.display());
                std::process::exit(2);
            }
        }
    }
}

fn row(name: &str, r: &MatrixRow) -> String {
    let pair = |p: Option<(f64, f64)>| p.map_or("—".to_string(), |(m, s)| format!("{m:.2} / {s:.2}"));
    format!(
        "| {name} | {} | {} | {} | {} | {} |",
        pair(r.tap_3000),
        pair(r.tap_6000),
        pair(r.g92_1),
        r.phase_spread.map_or("—".to_string(), |p| format!("{p:.3}°")),
        if r.alarms.is_empty() { "none".to_string() } else { r.alarms.join("; ") }
    )
}
