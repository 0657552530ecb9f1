//! The real-time path without kernel CAN: the master with the wall clock on the in-process
//! bus, the emulated drives served by `sim_drives::run_realtime` on their own thread — the
//! same code as `cncgw run --bus vcan0` against `sim-drives --bus vcan0`, minus the kernel.

use cncgw::config::{AxisKind, MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::RealClock;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[test]
fn a_program_runs_in_real_time_against_drives_on_another_thread() {
    // The test host is shared with the rest of the suite (tests run in parallel), so it is not
    // a real-time machine: the same timing tolerances as the vcan tier (tests/vcan_tier.rs).
    let mut cfg = MachineConfig::embedded();
    cfg.machine.cycle_ms = 4.0;
    cfg.bus.feedback_timeout_ms = 100.0;
    cfg.axes.get_mut("s1").unwrap().following_error = 90.0;
    let prog = "G21\nG98\nM03 S1500\nG00 X40 Z2\nG01 Z-10 F1200\nG01 X60 Z-20\nG02 X80 Z-30 R10\nG00 X100 Z5\nM05\nM30\n";
    let interp = Interpreter::from_source("rt.nc", prog, &cfg).unwrap();
    let wire = InprocBus::new();
    let stop = Arc::new(AtomicBool::new(false));
    let sim_bus: Box<dyn cncgw_bus::CanBus> = Box::new(wire.endpoint());
    let sim_stop = stop.clone();
    let sim =
        std::thread::spawn(move || sim_drives::run_realtime(sim_bus, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(), sim_stop));
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let mut clock = RealClock::new();
    let spindle = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), spindle, 4_000_000);
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    stop.store(true, Ordering::Relaxed);
    sim.join().unwrap().unwrap();
    eprintln!("{summary:#?}");
    r.unwrap();
    assert!(!summary.simulated);
    assert!(summary.at_program_end());
}
