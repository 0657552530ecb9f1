//! A part program on the embedded machine with the emulated drives of a given sim-drives
//! configuration, as `cncgw run` does it, and what the drives were left like: shared by
//! drive_profiles.rs and startup_shapes.rs.

use cncgw::config::MachineConfig;
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw::Alarm;
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use sim_drives::{SimConfig, SimWorld};

pub struct Ran {
    pub result: Result<RunSummary, Alarm>,
    pub world: SimWorld,
    pub master: CanOpenMaster<InprocEndpoint>,
    /// Power-on position (increments) of each drive, by node 1…3.
    pub start: [i64; 3],
}

/// `program` on `cfg`'s machine with the emulated drives of `sim`, as `cncgw run` does it.
pub fn run(cfg: &MachineConfig, sim: SimConfig, program: &str) -> Ran {
    let interp = Interpreter::from_source("first_part.nc", program, cfg).expect("program parses");
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, sim);
    let start = [1, 2, 3].map(|n| world.drive(n).unwrap().position_unwrapped());
    let mut master = CanOpenMaster::new(wire.endpoint(), cfg);
    let spindle = cfg.spindle_index();
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(cfg), spindle, 2_000_000);
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    Ran { result: r.map(|_| summary), world, master, start }
}

impl Ran {
    pub fn alarm(&self) -> &Alarm {
        match &self.result {
            Err(a) => a,
            Ok(s) => panic!("expected an alarm, the run ended: {s:?}"),
        }
    }

    pub fn summary(&self) -> &RunSummary {
        self.result.as_ref().unwrap_or_else(|a| panic!("{a}"))
    }

    /// Before any motion: no drive was ever enabled, and every one stands where it powered on.
    pub fn assert_nothing_moved(&self) {
        for (k, n) in [1u8, 2, 3].into_iter().enumerate() {
            let d = self.world.drive(n).unwrap();
            assert_eq!(d.enabled_modes(), 0, "node {n} was enabled");
            assert_eq!(d.position_unwrapped(), self.start[k], "node {n} moved");
        }
    }
}
