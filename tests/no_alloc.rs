//! The cycle loop allocates nothing after start: a counting global allocator (this test
//! binary only) counts every allocation made on the cycle thread from the first progress
//! report of `CycleLoop::run` to its return — planner, interpolator, sync monitor and
//! correction, CANopen master, trace recording. The emulated drives, which in a real machine
//! are other hardware, run inside the clock's `wait_until` and are not counted; nor are the
//! trace writer thread and the thread that feeds the moves.

use cncgw::canon::{Feed, Move, MoveKind, Plane, Pos, SpindleCmd, SpindleDir, SrcPos};
use cncgw::config::{AxisKind, MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::snapshot::{MachineState, Snapshot};
use cncgw::control::trace::{Trace, VecSink};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::motion::Limits;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

struct Counting;
static ALLOCS: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    static ARMED: Cell<bool> = const { Cell::new(false) };
}

fn armed() -> bool {
    ARMED.try_with(|a| a.get()).unwrap_or(false)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        if armed() {
            ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        if armed() {
            ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { System.realloc(p, l, n) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// The emulated drives as the clock, not counted while they run.
struct Uncounted<'w>(&'w mut sim_drives::SimWorld);

impl Clock for Uncounted<'_> {
    fn now_ns(&self) -> u64 {
        self.0.now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        let was = armed();
        ARMED.with(|a| a.set(false));
        self.0.wait_until(t);
        ARMED.with(|a| a.set(was));
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

fn mv(line: u32, kind: MoveKind, exact_stop: bool) -> Move {
    Move { src: SrcPos::new(Arc::from("noalloc.nc"), line, 1), kind, exact_stop, work_offset: Pos::ZERO, tag: None }
}

/// Every kind of cycle work: spindle ramps, rapids, a G64 chain of lines and arcs at a
/// per-revolution feed, thread passes, a dwell, a rigid tap with the sync correction, a
/// G92.1 stroke — about 20 s, so the trace recycles its chunks several times.
fn program() -> Vec<Move> {
    let sp = |rpm| MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm, css: None, max_rpm: None });
    let mut p = vec![mv(1, sp(1200.0), true), mv(2, MoveKind::Rapid { end: Pos::xz(10.0, 2.0) }, true)];
    let mut line = 3;
    for k in 0..6 {
        let z = -(k as f64) * 4.0;
        p.push(mv(line, MoveKind::Feed { end: Pos::xz(10.0, z - 2.0), feed: Feed::PerRev(0.2) }, false));
        p.push(mv(
            line + 1,
            MoveKind::Arc { end: Pos::xz(12.0, z - 4.0), center: Pos::xz(12.0, z - 2.0), cw: false, plane: Plane::Zx, feed: Feed::PerRev(0.2) },
            false,
        ));
        p.push(mv(line + 2, MoveKind::Feed { end: Pos::xz(10.0, z - 4.0), feed: Feed::PerRev(0.2) }, false));
        line += 3;
    }
    for rpm in [600.0, 900.0] {
        p.push(mv(line, sp(rpm), true));
        p.push(mv(line + 1, MoveKind::Rapid { end: Pos::xz(15.0, 5.0) }, true));
        p.push(mv(line + 2, MoveKind::Thread { end: Pos::xz(15.0, -20.0), lead: 1.5, start_angle: 0.0, continuous: false, lead_inc: 0.0 }, true));
        p.push(mv(line + 3, MoveKind::Rapid { end: Pos::xz(17.0, -20.0) }, true));
        line += 4;
    }
    p.push(mv(line, MoveKind::Dwell { seconds: 0.3 }, true));
    p.push(mv(line + 1, MoveKind::Rapid { end: Pos::xz(0.0, 2.0) }, true));
    p.push(mv(line + 2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.5, rpm: 1500.0, spindle: 1 }, true));
    p.push(mv(line + 3, MoveKind::Tap { end: Pos::xz(0.0, 2.0), lead: 1.5, rpm: 1500.0, spindle: 1 }, true));
    p.push(mv(line + 4, MoveKind::Rapid { end: Pos::xz(30.0, 5.0) }, true));
    // 30 mm at lead 2: 15 turns of the spindle in position mode.
    p.push(mv(line + 5, MoveKind::RigidThread { end: Pos { c: 5400.0, ..Pos::xz(30.0, -25.0) }, lead: 2.0, rpm: 500.0 }, true));
    p.push(mv(line + 6, MoveKind::Rapid { end: Pos { c: 5400.0, ..Pos::xz(40.0, 5.0) } }, true));
    p.push(mv(line + 7, MoveKind::End { code: 30 }, true));
    p
}

#[test]
fn the_cycle_loop_allocates_nothing_after_start() {
    run_counted(None);
}

/// The same with the OPC UA server's snapshot published every cycle, and a reader on another
/// thread copying it all the while (as the server's task does).
#[test]
fn publishing_the_snapshot_allocates_nothing() {
    let snap = Arc::new(Snapshot::new());
    let stop = Arc::new(AtomicBool::new(false));
    let (r, s) = (snap.clone(), stop.clone());
    let reader = std::thread::spawn(move || {
        let mut seen = 0u64;
        while !s.load(Ordering::Relaxed) {
            seen = seen.max(r.read().cycle);
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
        seen
    });
    run_counted(Some(snap.clone()));
    stop.store(true, Ordering::Relaxed);
    let seen = reader.join().unwrap();
    let last = snap.read();
    assert!(last.cycle > 5000 && seen > 0, "published {} records, the reader saw up to {seen}", last.cycle);
    assert_eq!((last.state, last.parts, last.alarm), (MachineState::Idle, 1, 0), "{last:?}");
}

/// The tests of this binary share the counter: one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

fn run_counted(snapshot: Option<Arc<Snapshot>>) {
    let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // The counter itself works: one allocation while armed is one count.
    ARMED.with(|a| a.set(true));
    let b = std::hint::black_box(Box::new(7u64));
    ARMED.with(|a| a.set(false));
    drop(b);
    assert_eq!(ALLOCS.swap(0, Ordering::Relaxed), 1);
    let cfg = MachineConfig::embedded();
    let wire = InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
    let mut clock = Uncounted(&mut world);
    let rows = Arc::new(Mutex::new(Vec::new()));
    let mut summary = RunSummary::default();
    let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), spindle, 2_000_000);
    let trace = Trace::spawn(lp.drive_names(), VecSink(rows.clone())).unwrap();
    lp.set_trace(trace);
    if let Some(s) = snapshot {
        lp.set_snapshot(s);
    }
    let start = lp.start(&mut summary).unwrap();
    let moves = program();
    let (tx, rx) = std::sync::mpsc::sync_channel(moves.len());
    for m in moves {
        tx.send(Ok(m)).unwrap();
    }
    drop(tx);
    let mut reports = 0u32;
    let r = lp.run(start, rx, &mut summary, &mut |_| {
        // From the first report on, every allocation on this thread counts.
        ARMED.with(|a| a.set(true));
        reports += 1;
    });
    ARMED.with(|a| a.set(false));
    let allocs = ALLOCS.load(Ordering::Relaxed);
    let st = lp.take_trace().unwrap().finish().unwrap();
    lp.finish();
    r.unwrap();
    assert!(summary.at_program_end(), "{summary:#?}");
    assert!(reports > 300, "armed for {reports} reports (~{} s)", reports as f64 * 0.05);
    assert!(st.rows > 9 * 1024 && st.dropped == 0, "{st:?}: the trace chunks were recycled");
    assert_eq!(rows.lock().unwrap().len() as u64, st.rows);
    assert_eq!(allocs, 0, "{allocs} allocations on the cycle thread after start");
}
