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
//!
//! The spindle at speed, where a step is 18° (1500 rpm, 2 ms) and its following-error window
//! 30°: a SYNC that reaches the master late (the clock ran on its timer meanwhile) or in a
//! burst after the link stalled must not make the master send two set-points before the
//! drives' next SYNC (they would take the second: a double step); and a controlled stop
//! (reset) on a master late past SYNCs steps by the SYNCs that passed, as the program does.

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
use cncgw_bus::{BusError, CanBus, CanFrame, Clock};
use sim_drives::SimWorld;
use std::cell::RefCell;
use std::collections::VecDeque;
use std::rc::Rc;
use std::sync::atomic::{AtomicI32, AtomicU64, Ordering};
use std::sync::Arc;

const CYCLE: u64 = 2_000_000;
/// Z: 10000 counts/mm; F3000 mm/min = 0.1 mm per 2 ms.
const Z_STEP: i64 = -1000;
const Z_COB: u16 = 0x202;
const FEED: &str = "G21\nG98\nG00 X40 Z2\nG01 Z-100 F3000\nG00 X60\nM30\n";
/// The spindle: node 3, 1000 counts/°; at 1500 rpm a step of 18° = 18 000 counts per 2 ms.
const S_NODE: u8 = 3;
const S_COB: u16 = 0x203;
const S_STEP: i64 = 18_000;
/// The spindle up to 1500 rpm, then the same feed (2 s).
const TURN: &str = "G21\nG98\nM03 S1500\nG04 P1000\nG00 X40 Z2\nG01 Z-100 F3000\nG00 X60\nM05\nM30\n";

/// The world as the clock, shared with the stalling bus wrapper; its time also published
/// for the master's side of the wire (`Link`).
struct Shared(Rc<RefCell<SimWorld>>, Arc<AtomicU64>);

impl Clock for Shared {
    fn now_ns(&self) -> u64 {
        let t = self.0.borrow().now_ns();
        self.1.store(t, Ordering::Relaxed);
        t
    }
    fn wait_until(&mut self, t: u64) {
        self.0.borrow_mut().wait_until(t);
        self.1.store(self.0.borrow().now_ns(), Ordering::Relaxed);
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

/// The master's end of the wire: from `at_ns` on, the link between it and the drives stalls
/// `stalls` times for `hold_ns` at each SYNC (both ways: what the drives send reaches the
/// master, and what the master sends reaches the drives, only when the stall ends — a
/// socketcand link or its server descheduled), with every frame kept in order.
struct Link {
    inner: InprocEndpoint,
    now: Arc<AtomicU64>,
    at_ns: u64,
    hold_ns: u64,
    stalls: u32,
    /// Stalls that happened.
    done: Arc<AtomicU64>,
    /// The master's frames not yet on the wire, and the drives' not yet with the master,
    /// each with the time it is let through.
    out: VecDeque<(u64, CanFrame)>,
    held: VecDeque<(u64, CanFrame)>,
}

impl Link {
    fn flush_out(&mut self, now: u64) -> Result<(), BusError> {
        while self.out.front().is_some_and(|f| f.0 <= now) {
            if let Some((_, f)) = self.out.pop_front() {
                self.inner.send(&f)?;
            }
        }
        Ok(())
    }
}

impl CanBus for Link {
    fn send(&mut self, f: &CanFrame) -> Result<(), BusError> {
        let now = self.now.load(Ordering::Relaxed);
        self.flush_out(now)?;
        match self.held.back().map(|h| h.0).filter(|r| *r > now) {
            Some(r) => self.out.push_back((r, *f)),
            None => self.inner.send(f)?,
        }
        Ok(())
    }
    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let now = self.now.load(Ordering::Relaxed);
        self.flush_out(now)?;
        while let Some(f) = self.inner.try_recv()? {
            let mut release = self.held.back().map_or(0, |h| h.0);
            if cncgw_bus::sync_source::is_sync(&f) && now >= self.at_ns && self.stalls > 0 && release <= now {
                self.stalls -= 1;
                self.done.fetch_add(1, Ordering::Relaxed);
                release = now + self.hold_ns;
            }
            self.held.push_back((release, f));
        }
        if self.held.front().is_some_and(|h| h.0 <= now) {
            return Ok(self.held.pop_front().map(|h| h.1));
        }
        Ok(None)
    }
    fn recv_timeout(&mut self, _: std::time::Duration) -> Result<Option<CanFrame>, BusError> {
        self.try_recv()
    }
    fn name(&self) -> &str {
        "link"
    }
}

/// Set by `Stalling` at `signal_at_ns`: SIGTERM, a reset.
static SIGNAL: AtomicI32 = AtomicI32::new(0);

/// The master, stalled `stalls` times by `stall_ns` between receive and transmit once Z passed
/// `at_z` (or once `signal_at_ns` has passed, when set), with every frame of the wire
/// recorded in wire order and the spindle drive's largest following error.
struct Stalling<'a> {
    inner: &'a mut dyn DriveBus,
    world: Rc<RefCell<SimWorld>>,
    wire: InprocBus,
    tap: Option<InprocEndpoint>,
    frames: Vec<(u16, [u8; 8], u8)>,
    z_target: f64,
    at_z: f64,
    stalls: u32,
    stall_ns: u64,
    signal_at_ns: Option<u64>,
    spindle_ferr: i64,
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
        let t = self.world.borrow().now_ns();
        let due = match self.signal_at_ns {
            Some(at) if t >= at => {
                SIGNAL.store(15, Ordering::Relaxed);
                // The stop's first cycle went out; stall in the ones after it.
                t >= at + 2 * CYCLE
            }
            Some(_) => false,
            None => self.z_target < self.at_z,
        };
        if self.stalls > 0 && due {
            // Woken on its SYNC, the thread is preempted past the next one.
            self.stalls -= 1;
            self.world.borrow_mut().wait_until(t + self.stall_ns);
        }
        let e = self.world.borrow().drive(S_NODE).map_or(0, |d| d.following_error() as i64);
        self.spindle_ferr = self.spindle_ferr.max(e.abs());
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
    /// The spindle's: the RPDO it took at each SYNC, None where none came (it extrapolated).
    spindle: Vec<Option<i64>>,
    spindle_ferr_deg: f64,
    link_stalls_left: u32,
    served_late: u64,
}

/// What disturbs the run: the master stalled (`stalls` × `stall_ns`, see `Stalling`), the
/// link stalled (`link_stalls` × `link_hold_ns` from `link_at_ns`, see `Link`).
#[derive(Clone, Copy)]
struct Setup {
    program: &'static str,
    hold: bool,
    stalls: u32,
    stall_ns: u64,
    signal_at_ns: Option<u64>,
    link_at_ns: u64,
    link_hold_ns: u64,
    link_stalls: u32,
}

impl Setup {
    fn feed(stalls: u32, hold: bool) -> Setup {
        Setup { program: FEED, hold, stalls, stall_ns: CYCLE * 5 / 4, signal_at_ns: None, link_at_ns: 0, link_hold_ns: 0, link_stalls: 0 }
    }
}

/// FEED on the default lathe with an external SYNC from drive 1 every 2 ms, the master
/// stalled `stalls` cycles in a row once Z is below -40 mm; `hold`: drives that hold their
/// target over a late SYNC (late_sync_extrapolation = 0) and a machine that knows it.
fn run(stalls: u32, hold: bool) -> Outcome {
    run_with(Setup::feed(stalls, hold))
}

fn run_with(setup: Setup) -> Outcome {
    let Setup { hold, stalls, .. } = setup;
    SIGNAL.store(0, Ordering::Relaxed);
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
    let now = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let link = Link {
        inner: wire.endpoint(),
        now: now.clone(),
        at_ns: setup.link_at_ns,
        hold_ns: setup.link_hold_ns,
        stalls: setup.link_stalls,
        done: done.clone(),
        out: VecDeque::new(),
        held: VecDeque::new(),
    };
    let (bus, mut clock) = cncgw_bus::sync_source::external_sync(Box::new(link), Shared(world.clone(), now), cfg.cycle_ns());
    let mut master = CanOpenMaster::new(bus, &cfg);
    let mut st = Stalling {
        inner: &mut master,
        world,
        wire,
        tap: None,
        frames: Vec::new(),
        z_target: 0.0,
        at_z: -40.0,
        stalls,
        stall_ns: setup.stall_ns,
        signal_at_ns: setup.signal_at_ns,
        spindle_ferr: 0,
    };
    let mut summary = RunSummary::default();
    let interp = Interpreter::from_source("feed.nc", setup.program, &cfg).unwrap();
    let result = {
        let mut lp = CycleLoop::new(&mut st, &mut clock, Limits::from_config(&cfg), cfg.spindle_index(), CYCLE);
        lp.set_watchdog(Watchdog::from_config(&cfg));
        lp.set_signal(&SIGNAL, |_| "SIGTERM");
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    let track = clock.track();
    drop(clock);
    let link_stalls_left = setup.link_stalls.saturating_sub(done.load(Ordering::Relaxed) as u32);
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
    let mut spindle = Vec::new();
    let mut pending = None;
    for (cob, d, len) in &st.frames {
        if *cob == S_COB && *len >= 6 {
            pending = Some(i32::from_le_bytes([d[2], d[3], d[4], d[5]]) as i64);
        } else if *cob == 0x080 && *len <= 1 {
            spindle.push(pending.take());
        }
    }
    Outcome {
        result,
        summary,
        stalls_left: st.stalls,
        taken,
        spindle,
        spindle_ferr_deg: st.spindle_ferr as f64 / 1000.0,
        link_stalls_left,
        served_late: track.served_late(),
    }
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

/// The spindle's step at each SYNC from the targets it took, a SYNC without one bridged as
/// sim-drives does (the last step again, for up to `CSP_EXTRAPOLATE_DEFAULT` SYNCs, then hold).
fn spindle_steps(o: &Outcome) -> Vec<i64> {
    let (mut cur, mut step, mut missed) = (None::<i64>, 0i64, 0i64);
    let mut steps = Vec::new();
    for t in &o.spindle {
        let next = match (*t, cur) {
            (Some(t), _) => {
                missed = 0;
                Some(t)
            }
            (None, Some(c)) => {
                missed += 1;
                Some(if missed <= sim_drives::drive::CSP_EXTRAPOLATE_DEFAULT { c + step } else { c })
            }
            (None, None) => None,
        };
        if let (Some(n), Some(c)) = (next, cur) {
            step = n - c;
            steps.push(step);
        }
        cur = next;
    }
    steps
}

/// The spindle at 1500 rpm while the link to the drives stalls once for `hold_ns` at a SYNC.
fn turn_with_link_stall(hold_ns: u64) -> Outcome {
    let mut s = Setup::feed(0, false);
    s.program = TURN;
    s.link_at_ns = 1_800_000_000;
    s.link_hold_ns = hold_ns;
    s.link_stalls = 1;
    run_with(s)
}

fn assert_spindle_steps_whole(o: &Outcome, what: &str) {
    let steps = spindle_steps(o);
    assert!(steps.len() > 1000, "{what}: {} SYNCs", steps.len());
    let top = steps.iter().max().copied().unwrap_or(0);
    assert!((top - S_STEP).abs() <= 100, "{what}: the spindle took a step of {top} counts at a SYNC, 1500 rpm is {S_STEP}");
    assert!(steps.iter().all(|s| *s >= 0), "{what}: the spindle stepped back: {steps:?}");
    assert!(o.spindle_ferr_deg < 5.0, "{what}: spindle following error {:.1}° (2.2° undisturbed)", o.spindle_ferr_deg);
}

#[test]
fn a_sync_reaching_the_master_late_gives_the_spindle_no_double_step() {
    // 0.6 periods late: the clock ran its cycle on the timer; the late SYNC is that cycle's,
    // not the next one's (before the fix: a step of 36 000 counts, 18.8° of following error).
    let o = turn_with_link_stall(CYCLE * 6 / 10);
    o.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(o.link_stalls_left, 0, "the link stalled");
    assert!(o.summary.at_program_end(), "{:?}", o.summary.axes);
    assert_spindle_steps_whole(&o, "SYNC 0.6 periods late");
    // (Start-up's NMT reset reboots the producing drive: its first SYNC back is one too.)
    assert!(o.served_late >= 1, "{}", o.served_late);
}

#[test]
fn a_burst_of_syncs_after_the_link_stalled_is_not_counted_twice() {
    // 2.2 periods: three SYNCs reach the master back to back, two of them for slots its timer
    // served (before the fix: the clock jumped two periods, a step of 54 000 counts).
    let o = turn_with_link_stall(CYCLE * 11 / 5);
    o.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(o.link_stalls_left, 0, "the link stalled");
    assert!(o.summary.at_program_end(), "{:?}", o.summary.axes);
    assert_spindle_steps_whole(&o, "SYNCs 2.2 periods late");
    assert!(o.served_late >= 2, "{}", o.served_late);
}

#[test]
fn a_reset_on_a_master_late_past_external_syncs_stops_the_spindle_on_its_ramp() {
    // Reset at 1.8 s (1500 rpm, Z feeding); in the stop the master is late past the next SYNC
    // three times. The stop steps by the SYNCs that passed: the drive, having bridged each by
    // extrapolating, never gets a set-point behind it.
    let mut s = Setup::feed(3, false);
    s.program = TURN;
    s.signal_at_ns = Some(1_800_000_000);
    let o = run_with(s);
    let a = o.result.as_ref().expect_err("reset");
    assert_eq!(a.number, cncgw::alarm::RESET, "{a}");
    assert_eq!(o.stalls_left, 0, "the stalls happened");
    let r = o.summary.rest;
    assert!(r.at_rest && !r.quick_stop, "{r:?}");
    let steps = spindle_steps(&o);
    assert!(steps.iter().all(|s| *s >= 0 && *s <= S_STEP + 100), "{steps:?}");
    // The ramp (6000 rpm/s: 144 counts less per SYNC) kept, but for the drive's constant-speed
    // extrapolation over a SYNC the master missed (its set-point after that is three ramp
    // steps down).
    let worst = steps.windows(2).map(|w| (w[1] - w[0]).abs()).max().unwrap_or(0);
    assert!(worst <= 3 * 144 + 20, "the spindle's step changed by {worst} counts at one SYNC: {steps:?}");
    assert!(o.spindle_ferr_deg < 5.0, "spindle following error {:.1}°", o.spindle_ferr_deg);
}
