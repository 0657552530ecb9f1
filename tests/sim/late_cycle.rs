//! A late cycle must never make a drive jump (issue 28). The controller is paused — in
//! simulated time: the clock jumps — for 1, 5, 10 and 20 cycles in a feed, a rapid, a thread
//! and a rigid tap, against drives that *hold* their target over a late SYNC (sim-drives with
//! `late_sync_extrapolation = 0`, the machine configured so). Asserted from the set-points the
//! master actually sent: no step larger than one cycle's travel at the axis' maximum speed;
//! the feed and the rapid run on to their end (the path's time base held back by the stall);
//! in the thread and the tap — whose time base cannot be shifted — a controlled stop with
//! alarm 2403 naming the controller's own stall, spindle and axes at rest.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary, Watchdog};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::{AxisFeedback, DriveBus};
use cncgw::interp::Interpreter;
use cncgw::motion::{Limits, AX_S};
use cncgw::Alarm;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use sim_drives::SimWorld;

const MS: u64 = 1_000_000;
const CYCLE: u64 = 2 * MS;

/// The world as the clock; once, at `stall_at`, the controller "wakes" `stall` cycles late.
struct Stalling {
    world: SimWorld,
    stall_at: u64,
    stall: u64,
}

impl Clock for Stalling {
    fn now_ns(&self) -> u64 {
        self.world.now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        let t = if self.stall > 0 && t >= self.stall_at {
            let late = t + self.stall * CYCLE + CYCLE / 4;
            self.stall = 0;
            late
        } else {
            t
        };
        self.world.wait_until(t);
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

/// The master, recording every set-point it is given (drive order).
struct Recorder<'a> {
    inner: &'a mut dyn DriveBus,
    sent: Vec<Vec<f64>>,
    cur: Vec<f64>,
}

impl DriveBus for Recorder<'_> {
    fn startup(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        self.inner.startup(clock)
    }
    fn receive(&mut self, now_ns: u64) -> Result<(), Alarm> {
        self.inner.receive(now_ns)
    }
    fn feedback(&self, axis: usize) -> AxisFeedback {
        self.inner.feedback(axis)
    }
    fn set_target(&mut self, axis: usize, pos: f64) {
        self.cur[axis] = pos;
        self.inner.set_target(axis, pos)
    }
    fn target_counts(&self, axis: usize) -> i64 {
        self.inner.target_counts(axis)
    }
    fn transmit(&mut self, now_ns: u64) -> Result<(), Alarm> {
        self.sent.push(self.cur.clone());
        self.inner.transmit(now_ns)
    }
    fn enable_step(&mut self) -> Result<bool, Alarm> {
        let r = self.inner.enable_step();
        for d in 0..self.cur.len() {
            self.cur[d] = self.inner.feedback(d).pos;
        }
        r
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
    /// Largest set-point step of each drive, as a fraction of one cycle at its maximum speed.
    worst_step: Vec<(String, f64)>,
}

fn run(program: &str, stall_at_ms: u64, stall: u64) -> Outcome {
    // Drives that hold their target over a late SYNC, and a machine that knows it.
    let text = EMBEDDED_LATHE.replace("late_sync_extrapolation = 10", "late_sync_extrapolation = 0");
    let cfg = MachineConfig::from_toml("hold.toml", &text).unwrap();
    assert_eq!(cfg.late_sync_extrapolation(), 0);
    let sim = sim_drives::SimConfig::from_machine_toml(&text).unwrap();
    assert!(sim.drives.iter().all(|d| d.late_sync_extrapolation == 0));
    let wire = InprocBus::new();
    let mut clock = Stalling { world: SimWorld::new(&wire, sim), stall_at: stall_at_ms * MS, stall };
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let n = cfg.axes.len();
    let mut rec = Recorder { inner: &mut master, sent: Vec::new(), cur: vec![0.0; n] };
    let mut summary = RunSummary::default();
    let interp = Interpreter::from_source("late.nc", program, &cfg).unwrap();
    let result = {
        let mut lp = CycleLoop::new(&mut rec, &mut clock, Limits::from_config(&cfg), cfg.spindle_index(), CYCLE);
        lp.set_watchdog(Watchdog::from_config(&cfg));
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    let limits = Limits::from_config(&cfg);
    let worst_step = cfg
        .axes
        .iter()
        .enumerate()
        .map(|(d, (name, a))| {
            let vmax = if a.kind == cncgw::config::AxisKind::Spindle { limits.vmax[AX_S] } else { a.max_speed / 60.0 };
            let step = rec.sent.windows(2).map(|w| (w[1][d] - w[0][d]).abs()).fold(0.0, f64::max);
            (name.clone(), step / (vmax * CYCLE as f64 * 1e-9))
        })
        .collect();
    Outcome { result, summary, worst_step }
}

fn assert_no_jump(o: &Outcome, what: &str) {
    for (name, f) in &o.worst_step {
        assert!(*f <= 1.0 + 1e-6, "{what}: {name} stepped {f:.2} × one cycle at its maximum speed");
    }
}

const FEED: &str = "G21\nG98\nG00 X40 Z2\nG01 Z-100 F3000\nG00 X60\nM30\n";
const RAPID: &str = "G21\nG98\nG00 X40 Z2\nG00 Z-200\nG00 X60\nM30\n";
const THREAD: &str = "G21\nG97 M03 S800\nG00 X45 Z5\nG92 X38 Z-60 F2\nG00 X50\nM30\n";
const TAP: &str = "G21\nG99\nG00 X0 Z5\nM29 S1000\nG84 Z-30 R-3 F1.5\nG80\nM30\n";

#[test]
fn a_stalled_feed_or_rapid_resumes_without_a_jump() {
    for (what, prog, at) in [("feed", FEED, 900), ("rapid", RAPID, 800)] {
        for stall in [1, 5, 10, 20] {
            let o = run(prog, at, stall);
            let w = format!("{what}, stall of {stall} cycles");
            o.result.as_ref().unwrap_or_else(|a| panic!("{w}: {a}"));
            assert!(o.summary.at_program_end(), "{w}: {:?}", o.summary.axes);
            assert!(o.summary.overruns >= 1, "{w}: the stall was seen");
            assert_no_jump(&o, &w);
            eprintln!("{w}: largest steps {:?}", o.worst_step);
        }
    }
}

#[test]
fn a_stall_inside_a_thread_or_tap_is_a_controlled_stop_naming_it() {
    for (what, prog, at) in [("thread", THREAD, 1300), ("tap", TAP, 800)] {
        for stall in [1, 5, 10, 20] {
            let o = run(prog, at, stall);
            let w = format!("{what}, stall of {stall} cycles");
            let a = o.result.as_ref().expect_err(&w);
            assert_eq!(a.number, cncgw::alarm::STALL_IN_SYNC, "{w}: {a}");
            assert!(a.message.contains("stall of this computer, not of a drive"), "{a}");
            assert!(o.summary.rest.at_rest, "{w}: {:?}", o.summary.rest);
            assert_no_jump(&o, &w);
        }
    }
}
