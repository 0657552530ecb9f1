//! A late cycle on an external SYNC (`bus.sync = "external"`, issue 21 item 6) must never
//! make a drive step back. The SYNC comes from drive 1 (sim-drives, 0x1005 bit 30), so it
//! does not wait for the master: when the master wakes on SYNC k but sends its set-points
//! only after SYNC k+1 has passed (the thread was preempted in between), the drive takes
//! them a SYNC later than planned. A set-point computed for k+1 and taken at k+2 lies a
//! period behind where the drive, bridging SYNC k+1 by extrapolating, already is: it steps
//! back. Reproduced here in simulated time by stalling the master between its wake-up and
//! its send (the world advances 1.25 periods), three cycles in a row in a feed, and judged
//! from the wire: the target each SYNC made the drive take (the last RPDO before it, or the
//! drive's extrapolation when none came) must advance by the feed's step at every SYNC.

use crate::profiles_common;

use cncgw::config::{MachineConfig, SyncSource};
use cncgw::control::cycle::{CycleLoop, RunSummary, Watchdog};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::{AxisFeedback, DriveBus};
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw::Alarm;
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{CanBus, Clock};
use sim_drives::SimWorld;
use std::cell::RefCell;
use std::rc::Rc;

const CYCLE: u64 = 2_000_000;
/// Z: 10000 counts/mm; F3000 mm/min = 0.1 mm per 2 ms.
const Z_STEP: i64 = -1000;
const Z_COB: u16 = 0x202;
const FEED: &str = "G21\nG98\nG00 X40 Z2\nG01 Z-100 F3000\nG00 X60\nM30\n";

/// The world as the clock, shared with the stalling bus wrapper.
struct Shared(Rc<RefCell<SimWorld>>);

impl Clock for Shared {
    fn now_ns(&self) -> u64 {
        self.0.borrow().now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        self.0.borrow_mut().wait_until(t)
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

/// The master, stalled `stalls` times between receive and transmit once Z passed `at_z`,
/// with every frame of the wire recorded in wire order.
struct Stalling<'a> {
    inner: &'a mut dyn DriveBus,
    world: Rc<RefCell<SimWorld>>,
    wire: InprocBus,
    tap: Option<InprocEndpoint>,
    frames: Vec<(u16, [u8; 8], u8)>,
    z_target: f64,
    at_z: f64,
    stalls: u32,
}

impl Stalling<'_> {
    fn drain(&mut self) {
        let tap = self.tap.get_or_insert_with(|| self.wire.endpoint());
        while let Ok(Some(f)) = tap.try_recv() {
            self.frames.push((f.cob_id(), f.data, f.len));
        }
    }
}

impl DriveBus for Stalling<'_> {
    fn startup(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        self.inner.startup(clock)
    }
    fn receive(&mut self, now_ns: u64) -> Result<(), Alarm> {
        self.drain();
        if self.stalls > 0 && self.z_target < self.at_z {
            // Woken on its SYNC, the thread is preempted past the next one.
            self.stalls -= 1;
            let t = self.world.borrow().now_ns() + CYCLE * 5 / 4;
            self.world.borrow_mut().wait_until(t);
        }
        self.inner.receive(now_ns)
    }
    fn feedback(&self, axis: usize) -> AxisFeedback {
        self.inner.feedback(axis)
    }
    fn set_target(&mut self, axis: usize, pos: f64) {
        if self.inner.axis_name(axis) == "z" {
            self.z_target = pos;
        }
        self.inner.set_target(axis, pos)
    }
    fn target_counts(&self, axis: usize) -> i64 {
        self.inner.target_counts(axis)
    }
    fn transmit(&mut self, now_ns: u64) -> Result<(), Alarm> {
        let r = self.inner.transmit(now_ns);
        self.drain();
        r
    }
    fn enable_step(&mut self) -> Result<bool, Alarm> {
        self.inner.enable_step()
    }
    fn quick_stop(&mut self) {
        self.inner.quick_stop()
    }
    fn shutdown(&mut self, clock: &mut dyn Clock) {
        self.inner.shutdown(clock)
    }
    fn axis_count(&self) -> usize {
        self.inner.axis_count()
    }
    fn axis_name(&self, axis: usize) -> &str {
        self.inner.axis_name(axis)
    }
    fn counts_per_unit(&self, axis: usize) -> f64 {
        self.inner.counts_per_unit(axis)
    }
    fn isolate_faults(&mut self, on: bool) -> bool {
        self.inner.isolate_faults(on)
    }
    fn faulted(&self) -> Option<usize> {
        self.inner.faulted()
    }
}

struct Outcome {
    result: Result<(), Alarm>,
    summary: RunSummary,
    stalls_left: u32,
    /// Z's target taken at each SYNC (None before the first set-point).
    taken: Vec<Option<i64>>,
}

/// FEED on the default lathe with an external SYNC from drive 1 every 2 ms, the master
/// stalled `stalls` cycles in a row once Z is below -40 mm; `hold`: drives that hold their
/// target over a late SYNC (late_sync_extrapolation = 0) and a machine that knows it.
fn run(stalls: u32, hold: bool) -> Outcome {
    let text = if hold {
        cncgw::config::EMBEDDED_LATHE.replace("late_sync_extrapolation = 10", "late_sync_extrapolation = 0")
    } else {
        cncgw::config::EMBEDDED_LATHE.to_string()
    };
    let mut cfg = MachineConfig::from_toml("lathe.toml", &text).unwrap();
    cfg.bus.sync = SyncSource::External;
    let mut sim = profiles_common::mixed(["plain"; 3], Some(2000));
    for d in &mut sim.drives {
        d.late_sync_extrapolation = cfg.late_sync_extrapolation();
    }
    let wire = InprocBus::new();
    let world = Rc::new(RefCell::new(SimWorld::new(&wire, sim)));
    let (bus, mut clock) = cncgw_bus::sync_source::external_sync(Box::new(wire.endpoint()), Shared(world.clone()), cfg.cycle_ns());
    let mut master = CanOpenMaster::new(bus, &cfg);
    let mut st = Stalling { inner: &mut master, world, wire, tap: None, frames: Vec::new(), z_target: 0.0, at_z: -40.0, stalls };
    let mut summary = RunSummary::default();
    let interp = Interpreter::from_source("feed.nc", FEED, &cfg).unwrap();
    let result = {
        let mut lp = CycleLoop::new(&mut st, &mut clock, Limits::from_config(&cfg), cfg.spindle_index(), CYCLE);
        lp.set_watchdog(Watchdog::from_config(&cfg));
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    // What each SYNC made Z's drive take: the last RPDO since the SYNC before, else (none
    // came) its own extrapolation of the last step — or, holding, the last target again.
    let mut taken: Vec<Option<i64>> = Vec::new();
    let mut pending = None;
    for (cob, d, len) in &st.frames {
        if *cob == Z_COB && *len >= 6 {
            pending = Some(i32::from_le_bytes([d[2], d[3], d[4], d[5]]) as i64);
        } else if *cob == 0x080 && *len <= 1 {
            let n = taken.len();
            let t = pending.take().or_else(|| match (n.checked_sub(2).and_then(|i| taken[i]), taken.last().copied().flatten()) {
                (Some(a), Some(b)) if !hold => Some(2 * b - a),
                (_, b) => b,
            });
            taken.push(t);
        }
    }
    Outcome { result, summary, stalls_left: st.stalls, taken }
}

/// The steps between the targets Z took at consecutive SYNCs in the feed's steady part
/// (Z between -10 and -90 mm).
fn steady_steps(o: &Outcome) -> Vec<i64> {
    let in_feed = |t: i64| (-900_000..=-100_000).contains(&t);
    o.taken
        .windows(2)
        .filter_map(|w| match (w[0], w[1]) {
            (Some(a), Some(b)) if in_feed(a) && in_feed(b) => Some(b - a),
            _ => None,
        })
        .collect()
}

#[test]
fn a_master_late_past_the_next_external_sync_never_makes_an_extrapolating_drive_step_back() {
    let o = run(3, false);
    o.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(o.stalls_left, 0, "the stalls happened");
    assert!(o.summary.at_program_end(), "{:?}", o.summary.axes);
    let steps = steady_steps(&o);
    assert!(steps.len() > 500, "{} steps in the feed", steps.len());
    for (k, s) in steps.iter().enumerate() {
        assert!((s - Z_STEP).abs() <= 20, "SYNC {k} of the feed: Z's drive took a step of {s} counts, the feed's is {Z_STEP}: {steps:?}");
    }
    // Each of the three late cycles is reported as the internal-SYNC cycle reports one.
    assert!(o.summary.overruns >= 3, "{} overruns", o.summary.overruns);
}

#[test]
fn a_master_late_past_the_next_external_sync_gives_a_holding_drive_no_jump() {
    let o = run(3, true);
    o.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(o.stalls_left, 0, "the stalls happened");
    assert!(o.summary.at_program_end(), "{:?}", o.summary.axes);
    // A drive that holds over a late SYNC stands still for it and goes on with the next
    // step: nothing is caught up (the path's time base is held back), nothing goes back.
    let steps = steady_steps(&o);
    assert!(steps.len() > 500, "{} steps in the feed", steps.len());
    for (k, s) in steps.iter().enumerate() {
        assert!(*s == 0 || (s - Z_STEP).abs() <= 20, "SYNC {k} of the feed: Z's drive took a step of {s} counts, the feed's is {Z_STEP}: {steps:?}");
    }
    assert!(steps.iter().filter(|s| **s == 0).count() <= 3, "{steps:?}");
    assert!(o.summary.overruns >= 3, "{} overruns", o.summary.overruns);
}
