//! The cycle watchdog (alarm 2402) with an injected clock that jumps, and the per-set-point
//! limit guard (500/501), on the embedded machine with sim-drives in simulated time.

use cncgw::canon::Pos;
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{alarms, CycleLoop, RunSummary, Watchdog};
use cncgw::control::guard::Guard;
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw::interp::Interpreter;
use cncgw::motion::{Limits, AX_Z};
use cncgw::Alarm;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use sim_drives::report::Scenario;

const MS: u64 = 1_000_000;
const CYCLE: u64 = 2 * MS;

/// Simulated time whose waits come back late: from `from_ns` on, `count` waits each end
/// `late_ns` after their deadline (a descheduled cycle thread, a stalled kernel).
struct JumpClock {
    world: sim_drives::SimWorld,
    from_ns: u64,
    late_ns: u64,
    count: u32,
    /// Waits made late so far, and the instant of the first.
    jumps: u32,
    first_jump_ns: Option<u64>,
}

impl Clock for JumpClock {
    fn now_ns(&self) -> u64 {
        self.world.now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        if t >= self.from_ns && self.jumps < self.count {
            self.jumps += 1;
            self.first_jump_ns.get_or_insert(t);
            self.world.wait_until(t + self.late_ns);
        } else {
            self.world.wait_until(t);
        }
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

struct Outcome {
    result: Result<RunSummary, Alarm>,
    clock: JumpClock,
    /// Last target sent to each drive, counts.
    targets: Vec<i64>,
}

/// A Z feed at 3000 mm/min from Z2 to Z-150 (about 3 s) with the spindle turning.
const PROGRAM: &str = "G21\nG98 G97 M03 S800\nG00 X40 Z2\nG01 Z-150 F3000\nG00 X50\nZ2\nM30\n";

fn run(program: &str, from_ns: u64, late_ns: u64, count: u32, guard: Option<Guard>) -> Outcome {
    let cfg = MachineConfig::embedded();
    let interp = Interpreter::from_source("wd.nc", program, &cfg).expect("program parses");
    let wire = InprocBus::new();
    let world = sim_drives::SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut clock = JumpClock { world, from_ns, late_ns, count, jumps: 0, first_jump_ns: None };
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == cncgw::config::AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), spindle, CYCLE);
        lp.set_watchdog(Watchdog::from_config(&cfg));
        if let Some(g) = guard {
            lp.set_guard(g);
        }
        run_program(&mut lp, interp, &mut summary)
    };
    let targets = (0..master.axis_count()).map(|d| master.target_counts(d)).collect();
    Outcome { result: r.map(|_| summary), clock, targets }
}

/// Let the world run on for 1 s with nobody commanding: the drives still moving.
fn moving_after(o: &mut Outcome) -> Vec<(u8, i32)> {
    let t = o.clock.world.now_ns() + 1000 * MS;
    o.clock.world.wait_until(t);
    o.clock.world.drives().iter().map(|d| (d.node(), d.velocity_actual())).filter(|(_, v)| v.abs() > 50).collect()
}

fn record(name: &str, o: &Outcome, bound_cycles: u64) -> u64 {
    let first = o.clock.first_jump_ns.expect("the clock jumped");
    let stop = (o.clock.world.now_ns() - first) / CYCLE;
    let mut s = Scenario::new(format!("limits_watchdog/{name}"));
    s.faults_injected = o.clock.jumps as u64;
    s.stop_cycles = Some(stop);
    s.bound_cycles = Some(bound_cycles);
    s.record();
    stop
}

#[test]
fn the_defaults_are_documented_values() {
    let cfg = MachineConfig::embedded();
    assert_eq!(Watchdog::from_config(&cfg), Watchdog { max_consecutive: 5, max_missed: 25, catch_up: 10 });
    // Without a configuration the drives are assumed to hold their target over a late SYNC
    // (nothing is caught up); the embedded machine's emulated drives bridge 10 periods.
    assert_eq!(Watchdog::default(), Watchdog { max_consecutive: 5, max_missed: 25, catch_up: 0 });
    let bad = EMBEDDED_LATHE.replace("cycle_ms = 2.0", "cycle_ms = 2.0\nwatchdog_missed_cycles = 51");
    let e = MachineConfig::from_toml("bad.toml", &bad).unwrap_err().to_string();
    assert!(e.contains("machine.watchdog_missed_cycles: must be between 1 and 50"), "{e}");
}

#[test]
fn a_single_short_overrun_is_counted_and_the_program_runs_on() {
    // One wait 5 periods late, mid-way through the Z feed.
    let o = run(PROGRAM, 1500 * MS, 5 * CYCLE, 1, None);
    let s = o.result.as_ref().expect("runs to the end");
    assert_eq!(s.overruns, 1);
    assert!(s.at_program_end());
    let mut sc = Scenario::new("limits_watchdog/short_overrun_rides_through");
    sc.faults_injected = 1;
    sc.record();
}

#[test]
fn overruns_one_short_of_the_limit_in_a_row_are_counted_only() {
    // Four waits in a row, each 2 periods late: one short of the limit of 5 in a row.
    let cfg = MachineConfig::embedded();
    let wd = Watchdog::from_config(&cfg);
    let o = run(PROGRAM, 1500 * MS, 2 * CYCLE, wd.max_consecutive - 1, None);
    let s = o.result.as_ref().expect("below the limit the program runs to the end");
    assert_eq!(s.overruns, (wd.max_consecutive - 1) as u64);
    assert!(s.at_program_end());
}

#[test]
fn consecutive_overruns_stop_the_machine_with_2402() {
    // From 1.5 s on, every wait ends 1.5 periods late: every cycle overruns.
    let mut o = run(PROGRAM, 1500 * MS, 3 * CYCLE / 2, 1000, None);
    let a = o.result.as_ref().expect_err("the watchdog stops the run");
    assert_eq!(a.number, alarms::WATCHDOG, "{a}");
    assert!(a.message.contains("5 cycles in a row") && a.message.contains("machine.watchdog_overruns"), "{a}");
    // (The clock stays late through the controlled stop's own cycles too.)
    // The stop is a controlled one: it takes cycles of its own (late ones, here), then rest.
    let stop = record("consecutive_overruns", &o, 400);
    assert!(stop <= 400, "stopped {stop} cycles after the first late cycle");
    assert!(moving_after(&mut o).is_empty(), "every axis at rest");
}

#[test]
fn one_very_late_cycle_stops_the_machine_at_once() {
    let mut o = run(PROGRAM, 1500 * MS, 30 * CYCLE, 1, None);
    let a = o.result.as_ref().expect_err("the watchdog stops the run");
    assert_eq!(a.number, alarms::WATCHDOG, "{a}");
    assert!(a.message.contains("30 periods late"), "{a}");
    let stop = record("one_late_cycle", &o, 400);
    assert!(stop <= 400, "stopped {stop} cycles after the late cycle");
    assert!(moving_after(&mut o).is_empty(), "every axis at rest");
}

#[test]
fn a_setpoint_beyond_the_guard_is_never_sent() {
    // The guard's Z box ends at −100 (say, a fixture), the planner's travel at −400: the
    // feed to Z−150 passes `Motion::push` but its set-points past −100 must not go out.
    let cfg = MachineConfig::embedded();
    let mut g = Guard::from_limits(&Limits::from_config(&cfg));
    g.set_travel(AX_Z, -100.0, 5.0);
    let mut o = run(PROGRAM, u64::MAX, 0, 0, Some(g));
    let a = o.result.as_ref().expect_err("the guard stops the run");
    assert_eq!(a.number, cncgw::control::guard::MINUS_OVERTRAVEL, "{a}");
    assert!(a.message.contains("line 4") && a.message.contains("set-point Z-100."), "{a}");
    // Drive order: s1, x, z (config order by name). The last Z target sent is inside.
    let z = cfg.axes.keys().position(|k| k == "z").unwrap();
    let z_target_mm = o.targets[z] as f64 / cfg.axes["z"].counts_per_unit;
    assert!(z_target_mm >= -100.0 - 1e-6, "last Z target sent {z_target_mm}");
    assert!(moving_after(&mut o).is_empty(), "every axis at rest after quick stop");
    let mut s = Scenario::new("limits_watchdog/setpoint_guard");
    s.faults_injected = 1;
    s.record();
}

#[test]
fn a_program_whose_path_leaves_the_limits_is_refused_before_the_first_move() {
    let cfg = MachineConfig::embedded();
    let dir = std::env::temp_dir().join(format!("cncgw-guard-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // The arc's end points are inside; its bulge crosses Z+5 (centre Z0, radius 10).
    let bad = dir.join("bulge.nc");
    std::fs::write(&bad, "G98 G00 X20 Z0\nG02 X60 Z0 R10 F100\nG00 X100\nM30\n").unwrap();
    let ccw = dir.join("ccw.nc");
    std::fs::write(&ccw, "G98 G00 X20 Z0\nG03 X60 Z0 R10 F100\nG00 X100\nM30\n").unwrap();
    let vars = Default::default();
    let r1 = cncgw::control::guard::check_program_file(&bad, &cfg, Pos::ZERO, &vars);
    let r2 = cncgw::control::guard::check_program_file(&ccw, &cfg, Pos::ZERO, &vars);
    let e = r1.as_ref().err().or(r2.as_ref().err()).expect("one sense bulges past Z5");
    assert!(r1.is_ok() != r2.is_ok());
    assert_eq!(e.number, cncgw::motion::alarms::TRAVEL, "{e}");
    // A macro-computed path (the end point comes from a variable) is followed too.
    let mac = dir.join("macro.nc");
    std::fs::write(&mac, "#1=-390\nG98 G00 X20 Z0\n#1=#1-20\nG01 Z#1 F100\nM30\n").unwrap();
    let e = cncgw::control::guard::check_program_file(&mac, &cfg, Pos::ZERO, &vars).unwrap_err();
    assert!(e.message.contains("-410.0000") && e.pos.as_ref().map(|p| p.line) == Some(4), "{e}");
    // `cncgw run` refuses it after enabling the drives, before the first move.
    let prog = if r1.is_err() { &bad } else { &ccw };
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw")).arg("run").arg(prog).env("CNCGW_STATE_DIR", &dir).output().expect("cncgw runs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(err.contains("alarm 2301") && err.contains("refused before any motion") && err.contains("nothing was moved"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
