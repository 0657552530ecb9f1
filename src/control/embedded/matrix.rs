//! The sync figures of one drive model (a sim-drives configuration), in simulated time on the
//! embedded machine: what `examples/drive_matrix.rs` prints and `tests/sim/drive_matrix.rs` bounds.

use super::measure::{
    g92_1_moves, monitor_stats, phase_spread, rigid_tap_moves, run_moves_jittered, tap_sync_error, thread_pass_moves, thread_phases, CuttingLoad,
    SimRun,
};
use crate::config::MachineConfig;
use crate::motion::Limits;

/// Figures of one model: (max, RMS) sync error in µm from the actual positions, the thread
/// phase spread in degrees, and the alarms any run raised.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MatrixRow {
    pub tap_3000: Option<(f64, f64)>,
    pub tap_6000: Option<(f64, f64)>,
    pub g92_1: Option<(f64, f64)>,
    pub phase_spread: Option<f64>,
    pub phases: Vec<f64>,
    pub alarms: Vec<String>,
}

/// Run the matrix's programs on the drives of `sim_toml` (a sim-drives configuration). The
/// sync monitor's limit is left as configured: an alarm 2307 shows as an alarm.
pub fn measure_model(cfg: &MachineConfig, sim_toml: &str) -> Result<MatrixRow, String> {
    measure_model_jittered(cfg, sim_toml, 0)
}

/// `measure_model` with every SYNC sent up to `jitter_ns` late (`run_moves_jittered`).
pub fn measure_model_jittered(cfg: &MachineConfig, sim_toml: &str, jitter_ns: u64) -> Result<MatrixRow, String> {
    measure_model_with(cfg, sim_toml, jitter_ns, true)
}

/// `measure_model_jittered`, the taps cut (`cut`: an M10 tap's torque from Z0 down) or in
/// the air, as `cncgw run --sim-config` runs them (the emulator has no cutting load there).
pub fn measure_model_with(cfg: &MachineConfig, sim_toml: &str, jitter_ns: u64, cut: bool) -> Result<MatrixRow, String> {
    let sim = sim_drives::SimConfig::from_toml(sim_toml)?;
    let limits = Limits::from_config(cfg);
    let mut row = MatrixRow::default();
    let mut run = |what: &str, moves| -> Result<SimRun, String> {
        let load = load(what).filter(|_| cut);
        let r = run_moves_jittered(cfg, sim.clone(), limits.clone(), moves, load, jitter_ns).map_err(|a| a.to_string())?;
        if let Err(a) = &r.result {
            row.alarms.push(format!("{what}: alarm {}", a.number));
        }
        Ok(r)
    };
    let t = run("S3000", rigid_tap_moves(2.0, -33.0, 1.5, 3000.0))?;
    let t6 = run("S6000", rigid_tap_moves(2.0, -198.0, 1.5, 6000.0))?;
    let g = run("G92.1", g92_1_moves(15.0, 5.0, -40.0, 2.0, 1000.0))?;
    let rpms = [500.0, 1000.0, 1500.0];
    let th = run("G92", thread_pass_moves(15.0, 5.0, -20.0, 1.5, &rpms))?;
    row.tap_3000 = tap_sync_error(&t, 1.5, (2, 3)).map(|(m, r, _)| (m, r));
    row.tap_6000 = tap_sync_error(&t6, 1.5, (2, 3)).map(|(m, r, _)| (m, r));
    row.g92_1 = monitor_stats(&g).map(|(m, r, _)| (m, r));
    if let Some(p) = thread_phases(&th, -5.0, rpms.len()) {
        row.phase_spread = Some(phase_spread(&p));
        row.phases = p;
    }
    Ok(row)
}

/// The taps cut (an M10 tap's load from Z0 down); the threads are cut in the air.
fn load(what: &str) -> Option<CuttingLoad> {
    what.starts_with('S').then(|| CuttingLoad::m10_tap(0.0))
}
