//! Helpers shared by the cycle tests: run a program, and view its moves in workpiece
//! coordinates (X as a diameter), as the manual's figures show them.
#![allow(dead_code)]

use cncgw::canon::{Feed, Move, MoveKind};
use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;
use cncgw::Alarm;

pub fn cfg_with(params: &str) -> MachineConfig {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).expect("config");
    let text = text.replace("[parameters]\n", &format!("[parameters]\n{params}\n"));
    MachineConfig::from_toml("lathe.toml", &text).expect("config parses")
}

pub fn run_cfg(src: &str, cfg: &MachineConfig) -> Vec<Move> {
    let it = Interpreter::from_source("t.nc", src, cfg).unwrap_or_else(|e| panic!("{e:?}"));
    it.map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

pub fn run(src: &str) -> Vec<Move> {
    run_cfg(src, &MachineConfig::embedded())
}

pub fn run_err_cfg(src: &str, cfg: &MachineConfig) -> Alarm {
    let it = Interpreter::from_source("t.nc", src, cfg).unwrap_or_else(|e| panic!("{e:?}"));
    for m in it {
        if let Err(a) = m {
            return a;
        }
    }
    panic!("no alarm")
}

pub fn run_err(src: &str) -> Alarm {
    run_err_cfg(src, &MachineConfig::embedded())
}

/// A motion in workpiece coordinates: kind, X diameter, Z, feed or lead, step tag.
#[derive(Clone, Debug)]
pub struct W {
    pub kind: &'static str,
    pub x: f64,
    pub z: f64,
    /// Feed (feed moves) or lead (threads); 0 for rapids.
    pub f: f64,
    pub cycle: Option<String>,
    pub step: u8,
    pub angle: f64,
    pub continuous: bool,
}

pub fn motions(moves: &[Move]) -> Vec<W> {
    moves
        .iter()
        .filter_map(|m| {
            let end = m.kind.end()?;
            let w = end.sub(m.work_offset);
            let (f, angle, continuous) = match &m.kind {
                MoveKind::Feed { feed: Feed::PerMin(v) | Feed::PerRev(v), .. } => (*v, 0.0, false),
                MoveKind::Thread { lead, start_angle, continuous, .. } => (*lead, *start_angle, *continuous),
                _ => (0.0, 0.0, false),
            };
            Some(W {
                kind: m.kind.name(),
                x: w.x * 2.0,
                z: w.z,
                f,
                cycle: m.tag.as_ref().map(|t| t.cycle.to_string()),
                step: m.tag.as_ref().map(|t| t.step).unwrap_or(0),
                angle,
                continuous,
            })
        })
        .collect()
}

/// Assert one motion: kind, X (diameter), Z, feed/lead, step (0 = untagged).
#[track_caller]
pub fn check(w: &W, kind: &str, x: f64, z: f64, f: f64, step: u8) {
    let ok = w.kind == kind && (w.x - x).abs() < 1e-6 && (w.z - z).abs() < 1e-6 && (w.f - f).abs() < 1e-9 && w.step == step;
    assert!(ok, "expected {kind} X{x} Z{z} f{f} step {step}, got {w:?}");
}
