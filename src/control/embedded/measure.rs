//! Measuring spindle–axis synchronisation on the emulated drives, in simulated time: the
//! whole chain (motion → cycle loop → CANopen master → in-process bus → sim-drives with the
//! spindle's and the feed axes' different dynamics), recorded with the cycle trace. Used by
//! the tests (bounds) and `examples/sync_figures.rs` (the figures).

use crate::canon::{Move, MoveKind, Pos, SpindleCmd, SpindleDir, SrcPos};
use crate::config::{AxisKind, MachineConfig, EMBEDDED_LATHE};
use crate::control::cycle::{CycleLoop, RunSummary};
use crate::control::trace::{Trace, TraceRow, VecSink};
use crate::drives::canopen::CanOpenMaster;
use crate::motion::Limits;
use crate::Alarm;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use std::sync::{Arc, Mutex};

/// Cutting load while the tool is in the material (below `surface_z`): torques on the motor
/// shafts, against the direction of motion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CuttingLoad {
    pub surface_z: f64,
    /// Spindle, N·m (tapping torque).
    pub spindle_nm: f64,
    /// Z motor, N·m (thrust through the screw).
    pub z_nm: f64,
}

impl CuttingLoad {
    /// An M10 tap in steel: ≈ 8 N·m at the spindle, a little thrust on Z.
    pub fn m10_tap(surface_z: f64) -> CuttingLoad {
        CuttingLoad { surface_z, spindle_nm: 8.0, z_nm: 0.3 }
    }
}

/// A simulated run: the trace of every cycle and the result.
#[derive(Debug)]
pub struct SimRun {
    /// Drive names, in the trace's drive order.
    pub names: Vec<String>,
    pub rows: Vec<TraceRow>,
    pub summary: RunSummary,
    pub result: Result<(), Alarm>,
}

impl SimRun {
    /// Index of a drive in the trace.
    pub fn drive(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }
}

/// The emulated drives as the cycle loop's clock, applying the cutting load before every
/// step of the physics.
struct Loaded<'w> {
    world: &'w mut sim_drives::SimWorld,
    load: Option<CuttingLoad>,
    spindle_node: u8,
    z_node: u8,
    z_counts_per_mm: f64,
    /// Each cycle wakes (and sends its SYNC) up to this late, uniformly at random (a real-time
    /// PC's wake-up jitter), ns; 0 = on the dot.
    jitter_ns: u64,
    /// xorshift64 state of the jitter (fixed seed: runs are reproducible).
    rng: u64,
}

impl Clock for Loaded<'_> {
    fn now_ns(&self) -> u64 {
        self.world.now_ns()
    }

    fn wait_until(&mut self, t_ns: u64) {
        if let Some(l) = self.load {
            let z = self.world.drive(self.z_node).map(|d| d.position_unwrapped() as f64 / self.z_counts_per_mm);
            let cutting = z.is_some_and(|z| z < l.surface_z);
            // sim-drives' load torque opposes positive motion (its drive torque less the
            // load): a load against the motion has the sign of the speed. (Until 2026-12-01
            // this was the other way round: the "cutting load" pushed the tool on.)
            let against = |v: i32, nm: f64| if cutting && v != 0 { nm * (v as f64).signum() } else { 0.0 };
            if let Some(d) = self.world.drive_mut(self.spindle_node) {
                let v = d.velocity_actual();
                d.set_load_torque(against(v, l.spindle_nm));
            }
            if let Some(d) = self.world.drive_mut(self.z_node) {
                let v = d.velocity_actual();
                d.set_load_torque(against(v, l.z_nm));
            }
        }
        let late = self.jitter();
        self.world.wait_until(t_ns + late)
    }

    fn is_simulated(&self) -> bool {
        true
    }
}

impl Loaded<'_> {
    fn jitter(&mut self) -> u64 {
        if self.jitter_ns > 0 {
            let mut x = self.rng;
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            self.rng = x;
            x % self.jitter_ns
        } else {
            0
        }
    }
}

/// Run canonical moves (machine coordinates) on the embedded machine's emulated drives in
/// simulated time, tracing every cycle.
pub fn run_moves(cfg: &MachineConfig, limits: Limits, moves: Vec<Move>, load: Option<CuttingLoad>) -> Result<SimRun, Alarm> {
    let sim_cfg =
        sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).map_err(|e| Alarm::new(crate::alarm::HARNESS, format!("emulated drives: {e}")))?;
    run_moves_on(cfg, sim_cfg, limits, moves, load)
}

/// `run_moves` on emulated drives of the given configuration (another drive model).
pub fn run_moves_on(
    cfg: &MachineConfig,
    sim_cfg: sim_drives::SimConfig,
    limits: Limits,
    moves: Vec<Move>,
    load: Option<CuttingLoad>,
) -> Result<SimRun, Alarm> {
    run_moves_jittered(cfg, sim_cfg, limits, moves, load, 0)
}

/// `run_moves_on` with every cycle's SYNC sent up to `jitter_ns` late (uniform, reproducible):
/// a real-time PC's wake-up jitter, in simulated time.
pub fn run_moves_jittered(
    cfg: &MachineConfig,
    sim_cfg: sim_drives::SimConfig,
    limits: Limits,
    moves: Vec<Move>,
    load: Option<CuttingLoad>,
    jitter_ns: u64,
) -> Result<SimRun, Alarm> {
    let wire = InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim_cfg);
    let mut master = CanOpenMaster::new(wire.endpoint(), cfg);
    let spindle = cfg.spindle_index();
    let node_of = |k: AxisKind, name: Option<&str>| {
        cfg.axes.iter().find(|(n, a)| a.kind == k && name.is_none_or(|w| n.as_str() == w)).map(|(_, a)| (a.node, a.counts_per_unit))
    };
    let (spindle_node, _) = node_of(AxisKind::Spindle, None).unwrap_or((0, 1.0));
    let (z_node, z_cpu) = node_of(AxisKind::Linear, Some("z")).unwrap_or((0, 1.0));
    let mut clock = Loaded { world: &mut world, load, spindle_node, z_node, z_counts_per_mm: z_cpu, jitter_ns, rng: 0x1234_5678_9ABC_DEF1 };
    let rows = Arc::new(Mutex::new(Vec::new()));
    let mut summary = RunSummary::default();
    let mut lp = CycleLoop::new(&mut master, &mut clock, limits, spindle, cfg.cycle_ns());
    let names = lp.drive_names();
    let trace = Trace::spawn(names.clone(), VecSink(rows.clone()))
        .map_err(|e| Alarm::new(crate::alarm::HARNESS, format!("cannot start the trace writer: {e}")))?;
    lp.set_trace(trace);
    let result = crate::control::job::run_moves(&mut lp, moves, &mut summary, &mut |_| {});
    if let Some(t) = lp.take_trace() {
        t.finish().map_err(|e| Alarm::new(crate::alarm::HARNESS, format!("trace: {e}")))?;
    }
    lp.finish();
    let rows = std::mem::take(&mut *rows.lock().map_err(|_| Alarm::new(crate::alarm::HARNESS, "trace buffer poisoned"))?);
    Ok(SimRun { names, rows, summary, result })
}

fn mv(line: u32, kind: MoveKind) -> Move {
    Move { src: SrcPos::new(Arc::from("sync.nc"), line, 1), kind, exact_stop: true, work_offset: Pos::ZERO, tag: None }
}

/// One rigid-tap hole at X0: rapid to the R point, tap to `bottom` and back at `rpm`.
pub fn rigid_tap_moves(r_z: f64, bottom: f64, lead: f64, rpm: f64) -> Vec<Move> {
    vec![
        mv(1, MoveKind::Rapid { end: Pos::xz(0.0, r_z) }),
        mv(2, MoveKind::Tap { end: Pos::xz(0.0, bottom), lead, rpm, spindle: 1 }),
        mv(3, MoveKind::Tap { end: Pos::xz(0.0, r_z), lead, rpm, spindle: 1 }),
        mv(4, MoveKind::End { code: 30 }),
    ]
}

/// Sync error of a rigid tap from the trace's *actual* positions, µm, for every cycle of
/// the tap's strokes (lines `tap_lines.0 ..= tap_lines.1`) from the first spindle motion
/// on: (Z − Z_R) − lead·(θ − θ_R)/360,
/// with Z_R, θ_R the commanded R point and spindle angle the tap starts from (the relation
/// the tap cuts, as the sync monitor uses it). (max |e|, RMS e, cycles).
pub fn tap_sync_error(run: &SimRun, lead: f64, tap_lines: (u32, u32)) -> Option<(f64, f64, usize)> {
    let (z, s) = (run.drive("z")?, spindle_index(run)?);
    let first = run.rows.iter().position(|r| r.line == tap_lines.0)?;
    let last = run.rows.iter().rposition(|r| r.line == tap_lines.1)?;
    let r0 = run.rows.get(first.checked_sub(1)?)?;
    let (z0, th0) = (r0.cmd[z], r0.cmd[s]);
    // From the first cycle the spindle is commanded to turn (not the in-position wait).
    let first = first + run.rows[first..=last].iter().position(|r| r.cmd[s] != th0)?;
    let (mut max, mut sq, mut n) = (0.0f64, 0.0, 0usize);
    for r in &run.rows[first..=last] {
        let e = ((r.act[z] - z0) - lead * (r.act[s] - th0) / 360.0) * 1000.0;
        max = max.max(e.abs());
        sq += e * e;
        n += 1;
    }
    (n > 0).then(|| (max, (sq / n as f64).sqrt(), n))
}

fn spindle_index(run: &SimRun) -> Option<usize> {
    run.names.iter().position(|n| n.starts_with('s'))
}

/// Thread passes: for each rpm, spindle on, rapid to (x, z_start), thread to z_end, out,
/// back. Each pass is the same thread (start angle 0).
pub fn thread_pass_moves(x: f64, z_start: f64, z_end: f64, lead: f64, rpms: &[f64]) -> Vec<Move> {
    let mut v = Vec::new();
    let mut line = 1;
    for &rpm in rpms {
        v.push(mv(line, MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm, css: None, max_rpm: None })));
        v.push(mv(line + 1, MoveKind::Rapid { end: Pos::xz(x + 2.0, z_start) }));
        v.push(mv(line + 2, MoveKind::Rapid { end: Pos::xz(x, z_start) }));
        v.push(mv(line + 3, MoveKind::Thread { end: Pos::xz(x, z_end), lead, start_angle: 0.0, continuous: false, lead_inc: 0.0 }));
        v.push(mv(line + 4, MoveKind::Rapid { end: Pos::xz(x + 2.0, z_end) }));
        line += 10;
    }
    v.push(mv(line, MoveKind::Rapid { end: Pos::xz(x + 2.0, z_start) }));
    v.push(mv(line + 1, MoveKind::End { code: 30 }));
    v
}

/// Thread phase of each pass: the *actual* spindle angle (mod 360) at which the *actual* Z
/// crosses `z_ref` in the thread block (line 4, 14, 24, …), interpolated between cycles.
pub fn thread_phases(run: &SimRun, z_ref: f64, passes: usize) -> Option<Vec<f64>> {
    let (z, s) = (run.drive("z")?, spindle_index(run)?);
    let mut out = Vec::new();
    for p in 0..passes {
        let line = 4 + 10 * p as u32;
        let w =
            run.rows.windows(2).find(|w| w[1].line == line && (w[0].act[z] - z_ref) * (w[1].act[z] - z_ref) <= 0.0 && w[0].act[z] != w[1].act[z])?;
        let f = (z_ref - w[0].act[z]) / (w[1].act[z] - w[0].act[z]);
        let th = w[0].act[s] + f * (w[1].act[s] - w[0].act[s]);
        out.push(th.rem_euclid(360.0));
    }
    Some(out)
}

/// Largest difference between two angles of a set, degrees, on the circle.
pub fn phase_spread(phases: &[f64]) -> f64 {
    let mut worst = 0.0f64;
    for a in phases {
        for b in phases {
            let d = (a - b).rem_euclid(360.0);
            worst = worst.max(d.min(360.0 - d));
        }
    }
    worst
}

/// One G92.1 rigid thread stroke along Z at radius `x` (the spindle in position mode from
/// C0), then out in X.
pub fn g92_1_moves(x: f64, z_start: f64, z_end: f64, lead: f64, rpm: f64) -> Vec<Move> {
    let turn = 360.0 * (z_start - z_end).abs() / lead;
    vec![
        mv(1, MoveKind::Rapid { end: Pos::xz(x, z_start) }),
        mv(2, MoveKind::RigidThread { end: Pos { c: turn, ..Pos::xz(x, z_end) }, lead, rpm }),
        mv(3, MoveKind::Rapid { end: Pos { c: turn, ..Pos::xz(x + 2.0, z_end) } }),
        mv(4, MoveKind::End { code: 30 }),
    ]
}

/// The sync monitor's own figure (`Motion::sync_error`, traced as `sync_err_um`) over the
/// cycles it measured: (max |e|, RMS e, cycles).
pub fn monitor_stats(run: &SimRun) -> Option<(f64, f64, usize)> {
    let v: Vec<f64> = run.rows.iter().map(|r| r.sync_err_um).filter(|e| *e != 0.0).collect();
    let n = v.len();
    (n > 0).then(|| (v.iter().fold(0.0f64, |m, e| m.max(e.abs())), (v.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt(), n))
}
