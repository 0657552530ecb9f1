//! Cost of one `Motion::step()` call (the per-cycle work of the interpolator), and a check
//! that `step` does not allocate: this binary counts every heap allocation.
//!
//! Run: `cargo bench -p cncgw --bench motion_step` (criterion prints time per step).

use cncgw::canon::{Feed, Move, MoveKind, Plane, Pos, SpindleCmd, SpindleDir, SrcPos};
use cncgw::config::MachineConfig;
use cncgw::motion::{Feedback, Limits, Motion, AX_S, N_AXES};
use criterion::{criterion_group, criterion_main, Criterion};
use std::alloc::{GlobalAlloc, Layout, System};
use std::hint::black_box;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

struct Counting;
static ALLOCS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.realloc(p, l, n) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

const START: [f64; N_AXES] = [40.0, 0.0, 2.0, 0.0];

fn mv(line: u32, kind: MoveKind, exact_stop: bool) -> Move {
    Move { src: SrcPos::new(Arc::from("bench.nc"), line, 1), kind, exact_stop, work_offset: Pos::ZERO, tag: None }
}

/// A turning program: spindle, rapid, a G64 profile of lines and arcs with per-rev feed, a
/// thread pass, back to the start.
fn program() -> Vec<Move> {
    let f = Feed::PerRev(0.2);
    let mut p = vec![
        mv(1, MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm: 1200.0, css: None, max_rpm: None }), false),
        mv(2, MoveKind::Rapid { end: Pos::xz(10.0, 2.0) }, true),
    ];
    let mut z = 0.0;
    let mut x = 10.0;
    for i in 0..20 {
        p.push(mv(10 + i, MoveKind::Feed { end: Pos::xz(x, z - 5.0), feed: f }, false));
        z -= 5.0;
        p.push(mv(
            10 + i,
            MoveKind::Arc { end: Pos::xz(x + 2.0, z - 2.0), center: Pos::xz(x + 2.0, z), cw: false, plane: Plane::Zx, feed: f },
            false,
        ));
        x += 2.0;
        z -= 2.0;
        p.push(mv(10 + i, MoveKind::Feed { end: Pos::xz(x + 0.5, z - 0.5), feed: f }, false));
        x += 0.5;
        z -= 0.5;
    }
    p.push(mv(50, MoveKind::Rapid { end: Pos::xz(x + 2.0, z) }, true));
    p.push(mv(51, MoveKind::Rapid { end: Pos::xz(x + 2.0, 2.0) }, true));
    p.push(mv(52, MoveKind::Rapid { end: Pos::xz(9.0, 2.0) }, true));
    p.push(mv(53, MoveKind::Thread { end: Pos::xz(9.0, -40.0), lead: 1.5, start_angle: 0.0, continuous: false, lead_inc: 0.0 }, true));
    p.push(mv(54, MoveKind::Rapid { end: Pos::xz(START[0], START[2]) }, true));
    p
}

/// Push as much of the program as fits; returns how many moves were pushed.
fn feed(m: &mut Motion, prog: &[Move], next: &mut usize) {
    while m.has_room() && *next < prog.len() {
        if let Err(e) = m.push(&prog[*next]) {
            panic!("benchmark program refused: {e}");
        }
        *next += 1;
    }
}

/// The embedded machine; `scurve`: with jerk limits (No.1772 = 32 ms: jerk = max_accel / 0.032 s).
fn fresh(scurve: bool) -> Motion {
    let cfg = if scurve {
        let t = cncgw::config::EMBEDDED_LATHE.replace("[parameters]", "[parameters]\n1772 = 32");
        MachineConfig::from_toml("lathe.toml", &t).expect("embedded config with No.1772")
    } else {
        MachineConfig::embedded()
    };
    Motion::new(Limits::from_config(&cfg), START)
}

/// Steps of the whole program, asserting that no step allocates; also the slowest step.
fn check_no_alloc(scurve: bool) -> (usize, Duration) {
    let prog = program();
    let mut m = fresh(scurve);
    let mut worst = Duration::ZERO;
    let mut next = 0;
    feed(&mut m, &prog, &mut next);
    let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
    let mut n = 0;
    while !m.is_idle() {
        let before = ALLOCS.load(Ordering::Relaxed);
        let t = Instant::now();
        let sp = m.step(&fb);
        worst = worst.max(t.elapsed());
        let after = ALLOCS.load(Ordering::Relaxed);
        assert_eq!(before, after, "step() allocated at cycle {n}");
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        n += 1;
        assert!(n < 10_000_000, "program does not finish");
    }
    (n, worst)
}

fn bench(c: &mut Criterion) {
    for scurve in [false, true] {
        bench_one(c, scurve);
    }
}

fn bench_one(c: &mut Criterion, scurve: bool) {
    let (cycles, worst) = check_no_alloc(scurve);
    eprintln!(
        "motion_step{}: program of {} moves = {cycles} cycles, no allocation in step(), slowest step {:.1} µs (one run, includes preemption)",
        if scurve { " (S-curve)" } else { "" },
        program().len(),
        worst.as_secs_f64() * 1e6
    );
    let prog = program();
    let name = if scurve { "motion_step_turning_program_scurve" } else { "motion_step_turning_program" };
    c.bench_function(name, |b| {
        let mut m = fresh(scurve);
        let mut next = 0;
        let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            let mut done = 0u64;
            while done < iters {
                if m.is_idle() {
                    // Restart the program (outside the timed part).
                    m = fresh(scurve);
                    next = 0;
                    fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
                    feed(&mut m, &prog, &mut next);
                }
                let t = Instant::now();
                while done < iters && !m.is_idle() {
                    let sp = black_box(m.step(black_box(&fb)));
                    fb.pos = sp.pos;
                    fb.spindle_rpm = sp.spindle_rpm;
                    fb.pos[AX_S] = sp.pos[AX_S];
                    done += 1;
                }
                total += t.elapsed();
            }
            total
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
