//! The simulated world as the cycle loop's clock, shared by the simulated-time tests
//! (io_run, stop_sequence, fault_matrix): after every wait it fires the actions due (a panel
//! button, a wire fault, an input changing) and samples the devices, so a test sees what the
//! *drives* did, not what the controller thinks.
//!
//! (A module of the tests rather than of `testkit`: testkit would need sim-drives, whose own
//! tests depend on testkit.)
#![allow(dead_code)]

use cncgw_bus::cia402::State;
use cncgw_bus::Clock;
use sim_drives::SimWorld;

pub const MS: u64 = 1_000_000;

/// Something done to the world at a time of the run.
pub type Action = Box<dyn FnMut(&mut SimWorld)>;

/// Every drive after a wait: actual position, velocity and CiA 402 state, in the world's order.
#[derive(Clone, Debug)]
pub struct Sample {
    pub t: u64,
    pub pos: Vec<i64>,
    pub vel: Vec<i32>,
    pub state: Vec<State>,
}

impl Sample {
    pub fn of(world: &SimWorld) -> Sample {
        let d = world.drives();
        Sample {
            t: world.now_ns(),
            pos: d.iter().map(|d| d.position_unwrapped()).collect(),
            vel: d.iter().map(|d| d.velocity_actual()).collect(),
            state: d.iter().map(|d| d.state()).collect(),
        }
    }
}

/// The world as a [`Clock`], taking a sample `S` of it after every wait.
pub struct Probe<S = Sample> {
    pub world: SimWorld,
    pub samples: Vec<S>,
    /// (time, action), fired once at the first wait that reaches the time.
    actions: Vec<(u64, Option<Action>)>,
    take: fn(&SimWorld) -> S,
}

impl<S> Probe<S> {
    /// `actions` at (ms from the start, action); `take` makes a sample of the world.
    pub fn new(world: SimWorld, actions: Vec<(u64, Action)>, take: fn(&SimWorld) -> S) -> Probe<S> {
        Probe { world, samples: Vec::new(), actions: actions.into_iter().map(|(ms, a)| (ms * MS, Some(a))).collect(), take }
    }

    /// Run the world on (nobody commanding) for `ms`, waiting `step_ns` at a time, sampling.
    pub fn idle(&mut self, ms: u64, step_ns: u64) {
        let end = self.now_ns() + ms * MS;
        while self.now_ns() < end {
            let t = self.now_ns() + step_ns;
            self.wait_until(t);
        }
    }
}

impl<S> Clock for Probe<S> {
    fn now_ns(&self) -> u64 {
        self.world.now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        self.world.wait_until(t);
        let now = self.world.now_ns();
        for (at, a) in self.actions.iter_mut() {
            if *at <= now {
                if let Some(mut f) = a.take() {
                    f(&mut self.world);
                }
            }
        }
        let s = (self.take)(&self.world);
        self.samples.push(s);
    }
    fn is_simulated(&self) -> bool {
        true
    }
}
