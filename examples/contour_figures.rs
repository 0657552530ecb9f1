//! Contour figures (issue 23): CAM contours of tiny G1 segments at the feed the machine allows.
//!
//! Run: `cargo run --release --example contour_figures` (add `-- --million` for the
//! million-block memory check).
//!
//! A half circle R20 cut into G1 chords (G64, feed per minute) on the embedded machine
//! (`config/lathe.toml`: 2 ms cycle, X/Z 2000 mm/s²), No.6023's feed clamp lifted so that
//! F6000 runs at F6000. Ideal drives (the actual is the last setpoint), SIMULATED time: the
//! path time is the number of cycles from the first moving setpoint to the one that lands on
//! the end point, times the cycle; the figures are the planner's, independent of the machine
//! running it. The optimum is `L/F + F/A` (cruise at F, trapezoid ramps at the axes' full
//! A = 2000 mm/s²: the centripetal acceleration F²/R is far below it). The cost per cycle
//! (`push` of the new blocks + `step`) is measured in real time on the machine running this.

use cncgw::canon::{Feed, Move, MoveKind, Pos, SrcPos};
use cncgw::config::MachineConfig;
use cncgw::motion::{Feedback, Limits, Motion, N_AXES};
use std::sync::Arc;
use std::time::Instant;

const R: f64 = 20.0;
/// Centre of the half circle: X (radius) and Z, inside the embedded machine's travel.
const CX: f64 = 30.0;
const CZ: f64 = -100.0;
const A_OPT: f64 = 2000.0;

fn mv(src: &Arc<str>, line: u32, kind: MoveKind, exact_stop: bool) -> Move {
    Move { src: SrcPos::new(src.clone(), line, 1), kind, exact_stop, work_offset: Pos::ZERO, tag: None }
}

/// Point `k` of `n` chords on `turns` half circles (angle from +Z towards +X and on around).
fn point(k: usize, n: usize) -> Pos {
    let th = std::f64::consts::PI * k as f64 / n as f64;
    Pos::xz(CX + R * th.sin(), CZ + R * th.cos())
}

/// The program as an iterator (a million blocks never sit in memory): the start point, `n`
/// chords per half circle over `halves` half circles, M30.
fn program(h: f64, f: f64, halves: usize) -> (impl Iterator<Item = Move>, f64) {
    let src: Arc<str> = Arc::from("contour.nc");
    let n = ((std::f64::consts::PI * R / h).round() as usize).max(1);
    let chord = 2.0 * R * (std::f64::consts::PI / (2.0 * n as f64)).sin();
    let total = n * halves;
    let head = std::iter::once(mv(&src, 1, MoveKind::Rapid { end: point(0, n) }, true));
    let s2 = src.clone();
    let body = (1..=total).map(move |k| mv(&s2, 2 + k as u32, MoveKind::Feed { end: point(k, n), feed: Feed::PerMin(f) }, false));
    let tail = std::iter::once(mv(&src, 3 + total as u32, MoveKind::End { code: 30 }, false));
    (head.chain(body).chain(tail), chord * total as f64)
}

struct Fig {
    path_s: f64,
    /// `step` time and push + step time of every cycle, µs (for the worst case over repeated
    /// runs).
    step_us: Vec<f64>,
    cycle_us: Vec<f64>,
    /// Largest axis acceleration and velocity seen (mm/s², mm/s).
    max_acc: f64,
    max_vel: f64,
    /// Largest change of an axis acceleration from one cycle to the next, mm/s² (S-curve).
    max_dacc: f64,
    /// Cost of one cycle's `push`es plus `step`, and of `step` alone: worst and mean, µs.
    worst_cycle_us: f64,
    worst_step_us: f64,
    mean_step_us: f64,
    end_err: f64,
}

fn run(lim: &Limits, prog: impl Iterator<Item = Move>, end: Pos) -> Fig {
    let dt = lim.cycle_s;
    let mut m = Motion::new(lim.clone(), [0.0, 0.0, 0.0, 0.0]);
    let mut prog = prog.peekable();
    // Position on the start first (the rapid is not part of the figure).
    if let Some(r) = prog.next() {
        m.push(&r).expect("rapid");
    }
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    while !m.is_idle() {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: 0.0, ..Default::default() };
    }
    let (mut p, mut v, mut a) = (m.position(), [0.0; N_AXES], [0.0; N_AXES]);
    let mut f = Fig {
        path_s: 0.0,
        step_us: Vec::with_capacity(1 << 20),
        cycle_us: Vec::with_capacity(1 << 20),
        max_acc: 0.0,
        max_vel: 0.0,
        max_dacc: 0.0,
        worst_cycle_us: 0.0,
        worst_step_us: 0.0,
        mean_step_us: 0.0,
        end_err: 0.0,
    };
    let (mut cycles, mut moving, mut last_move) = (0u64, false, 0u64);
    let mut step_total = 0.0;
    loop {
        let t0 = Instant::now();
        while m.has_room() {
            match prog.next() {
                Some(mv) => m.push(&mv).expect("program refused"),
                None => break,
            }
        }
        let t1 = Instant::now();
        let sp = m.step(&fb);
        let t2 = Instant::now();
        let (step_us, cyc_us) = ((t2 - t1).as_secs_f64() * 1e6, (t2 - t0).as_secs_f64() * 1e6);
        f.worst_step_us = f.worst_step_us.max(step_us);
        f.worst_cycle_us = f.worst_cycle_us.max(cyc_us);
        step_total += step_us;
        f.step_us.push(step_us);
        f.cycle_us.push(cyc_us);
        fb = Feedback { pos: sp.pos, spindle_rpm: 0.0, ..Default::default() };
        cycles += 1;
        let moved = sp.pos != p;
        moving |= moved;
        if moved {
            last_move = cycles;
        }
        for i in 0..3 {
            let nv = (sp.pos[i] - p[i]) / dt;
            f.max_vel = f.max_vel.max(nv.abs());
            let na = (nv - v[i]) / dt;
            f.max_acc = f.max_acc.max(na.abs());
            f.max_dacc = f.max_dacc.max((na - a[i]).abs());
            v[i] = nv;
            a[i] = na;
        }
        p = sp.pos;
        if !moving {
            cycles = 0;
        }
        if m.is_idle() && prog.peek().is_none() {
            break;
        }
        assert!(cycles < 100_000_000, "does not end");
    }
    f.path_s = last_move as f64 * dt;
    f.mean_step_us = step_total / cycles.max(1) as f64;
    f.end_err = ((p[0] - end.x).powi(2) + (p[2] - end.z).powi(2)).sqrt();
    f
}

/// The worst cycle of a deterministic run measured `REPEAT` times, taking for each cycle the
/// least of its times: a cycle that was preempted by another process (this machine is shared
/// with builds) in one run is not in all of them; the raw maximum is printed too.
const REPEAT: usize = 5;

fn robust_worst(runs: &[Vec<f64>]) -> f64 {
    let n = runs.iter().map(|r| r.len()).min().unwrap_or(0);
    (0..n).map(|k| runs.iter().map(|r| r[k]).fold(f64::INFINITY, f64::min)).fold(0.0, f64::max)
}

/// Runs a program `REPEAT` times: the first run's figure, with the worst step and push + step
/// over the runs (robust, see `robust_worst`).
fn measure(lim: &Limits, h: f64, f: f64, halves: usize) -> (Fig, f64, [f64; 2]) {
    let n = ((std::f64::consts::PI * R / h).round() as usize).max(1);
    let mut figs = Vec::new();
    let mut len = 0.0;
    for _ in 0..REPEAT {
        let (prog, l) = program(h, f, halves);
        len = l;
        figs.push(run(lim, prog, point(n * halves, n)));
    }
    let steps: Vec<Vec<f64>> = figs.iter().map(|g| g.step_us.clone()).collect();
    let cycles: Vec<Vec<f64>> = figs.iter().map(|g| g.cycle_us.clone()).collect();
    let worst = [robust_worst(&steps), robust_worst(&cycles)];
    (figs.swap_remove(0), len, worst)
}

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmRSS:")).map(|l| l.to_string()))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|n| n.parse().ok()))
        .unwrap_or(0)
}

fn main() {
    let cfg = MachineConfig::embedded();
    let mut lim = Limits::from_config(&cfg);
    lim.feed_clamp = f64::INFINITY;
    println!("half circle R{R} as G1 chords, G64, embedded machine ({} ms cycle, queue {} blocks), simulated time", lim.cycle_s * 1e3, lim.queue_len);
    println!("| chords | F | path time | optimum | mean speed | ratio | max axis acc | max axis vel | end error | step worst (raw) / mean | push+step worst (raw) |");
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    for f in [3000.0, 6000.0] {
        for h in [0.5, 0.1, 0.05, 0.02, 0.01] {
            let (fig, len, worst) = measure(&lim, h, f, 1);
            let v = f / 60.0;
            let opt = len / v + v / A_OPT;
            println!(
                "| {h} mm | {f} | {:.3} s | {:.3} s | {:.0} mm/min | {:.2} | {:.0} mm/s² | {:.1} mm/s | {:.1e} mm | {:.1} ({:.0}) / {:.2} µs | {:.0} ({:.0}) µs |",
                fig.path_s,
                opt,
                len / fig.path_s * 60.0,
                opt / fig.path_s,
                fig.max_acc,
                fig.max_vel,
                fig.end_err,
                worst[0],
                fig.worst_step_us,
                fig.mean_step_us,
                worst[1],
                fig.worst_cycle_us,
            );
        }
    }
    // S-curve: No.1772 = 32 ms on every linear axis (jerk = 2000 / 0.032 = 62 500 mm/s³).
    let t = cncgw::config::EMBEDDED_LATHE.replace("[parameters]", "[parameters]\n1772 = 32");
    let cfg = MachineConfig::from_toml("lathe.toml", &t).expect("embedded config with No.1772");
    let mut lim = Limits::from_config(&cfg);
    lim.feed_clamp = f64::INFINITY;
    println!("\nthe same with S-curve, No.1772 = 32 ms (j·dt = {:.0} mm/s² per cycle)", 2000.0 / 0.032 * lim.cycle_s);
    println!("| chords | F | path time | optimum (ramps v/A + A/J) | ratio | max axis acc | max axis Δacc per cycle |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for f in [3000.0, 6000.0] {
        for h in [0.5, 0.05, 0.02, 0.01] {
            let (prog, len) = program(h, f, 1);
            let n = ((std::f64::consts::PI * R / h).round() as usize).max(1);
            let fig = run(&lim, prog, point(n, n));
            let v = f / 60.0;
            let opt = len / v + v / A_OPT + 0.032;
            println!(
                "| {h} mm | {f} | {:.3} s | {:.3} s | {:.2} | {:.0} mm/s² | {:.0} mm/s² |",
                fig.path_s,
                opt,
                opt / fig.path_s,
                fig.max_acc,
                fig.max_dacc
            );
        }
    }
    let mut lim = Limits::from_config(&MachineConfig::embedded());
    lim.feed_clamp = f64::INFINITY;
    if std::env::args().any(|a| a == "--million") {
        let halves = 160; // 160 half circles of 6283 chords of 0.01 mm: 1 005 280 blocks
        let (prog, len) = program(0.01, 6000.0, halves);
        let before = rss_kib();
        let n = ((std::f64::consts::PI * R / 0.01).round() as usize).max(1);
        let fig = run(&lim, prog, point(n * halves, n));
        let after = rss_kib();
        let v = 100.0;
        println!(
            "million blocks (0.01 mm, F6000, {len:.0} mm): path {:.1} s (optimum {:.1} s), RSS {before} KiB before, {after} KiB after (of which this figure's per-cycle time records: {} KiB); step worst {:.2} µs (raw) mean {:.2} µs, push+step worst {:.0} µs (raw)",
            fig.path_s,
            len / v + v / A_OPT,
            fig.step_us.len() * 16 / 1024,
            fig.worst_step_us,
            fig.mean_step_us,
            fig.worst_cycle_us
        );
    }
}
