//! Cycle timing in real time (issue 8, figure 3): the cycle loop (`CycleLoop::run`, the same
//! code as `cncgw run`) drives a program against emulated drives on the wall clock, and every
//! wake-up of the cycle thread is timed against its deadline.
//!
//! Run: `cargo run --release --example jitter -- [--seconds 60] [--cycle-ms 2] [--mode inproc|socketcand|both]
//!       [--rt-priority N] [--cpu N] [--mlock] [--strict]
//!       [--max-sleep-us US] [--spin-us US] [--cpu-dma-latency] [--timer-slack-ns NS] [--compare]`
//!
//! `--max-sleep-us`, `--spin-us`, `--cpu-dma-latency`, `--timer-slack-ns` are the `[rt]`
//! keys of the same names (`cncgw_bus::WakeStrategy`, `control::rt`). `--compare` runs each
//! case twice back to back, first without those four (priority, CPU and mlock kept), then
//! with them, so that both see the same load. Each run is on a fresh thread, so that one
//! run's thread settings do not carry over to the next.
//!
//! By default the following-error windows are 720° (spindle) and 5 mm (axes), the feedback
//! timeout 100 ms (as tests/realtime/realtime_inproc.rs does for the spindle) and the cycle watchdog
//! relaxed (`watchdog_overruns = 0`: off; `watchdog_missed_cycles = 50`: the most allowed), so that a stall on a loaded
//! host is measured instead of ending the run with a fault; `--strict` keeps the config's.
//!
//! - `inproc`: the drives (`sim_drives::run_realtime`) on another thread of this process,
//!   on the in-process bus.
//! - `socketcand`: the drives as a separate process, `sim-drives --socketcand 127.0.0.1:PORT`
//!   (the binary next to this example's directory: build it with `cargo build --release
//!   --bins` first), the master connected over loopback TCP.
//!
//! Printed per run: lateness of each wake-up (wake − deadline) and period jitter
//! (|wake_k − wake_{k−1} − T|), p50/p99/max in µs, and missed cycles (the loop's overruns:
//! a whole period late), and the host's steal time during the run (a VM's vCPUs waiting for
//! the host). The figures depend on the machine and its load; a shared or virtualised host is
//! not a real-time one.
//!
//! ## Figures (22 Nov 2026, this project's machine: Firecracker VM, 2 vCPUs, no cpuidle driver)
//!
//! Taken inside an emulated VM: not comparable to a PC. `--seconds 60 --mode both
//! --rt-priority 50 --max-sleep-us 100 --compare` (each case plain, then with 100 µs sleep
//! steps, back to back), three rounds at different loads (1-min load average at start → end;
//! the host's steal time was 100–770 ms per 70 s run). Cells: period jitter p99 µs / missed
//! cycles / wake-up lateness p50 µs.
//!
//! | case               | A plain      | A steps ≤100 µs | B plain      | B steps ≤100 µs | C plain      | C steps ≤100 µs |
//! |--------------------|--------------|-----------------|--------------|-----------------|--------------|-----------------|
//! | 2 ms in-process    | 260 / 27 / 45 | 115 / 36 / 5.2 | 842 / 106 / 58 | 126 / 28 / 7.2 | 260 / 28 / 52 | 83 / 19 / 8.1  |
//! | 2 ms socketcand    | 438 / 45 / 48 | 94 / 24 / 5.0  | 259 / 26 / 56  | 159 / 38 / 7.8 | 373 / 60 / 48 | 394 / 66 / 7.2 |
//! | 1 ms in-process    | 147 / 55 / 32 | 65 / 23 / 6.6 ¹ | 146 / 43 / 34 | 66 / 19 / 4.7  | 151 / 66 / 27 | 65 / 21 / 4.7  |
//! | 1 ms socketcand    | 154 / 72 / 28 | 104 / 44 / 5.3 | 102 / 45 / 30  | 27 / 17 / 4.7  | 262 / 140 / 36 | 74 / 17 / 5.0 |
//!
//! A: load 0.10 → 0.98 (quiet guest); B: 2.02 → 0.15; C: 2.04 → 1.45 (another engineer
//! compiling). ¹ stopped after 41 s by the cycle watchdog (a 38 ms stall; the example did not
//! yet apply its relaxed watchdog then). A fourth round at 1 ms only (`--cycle-ms 1`, load
//! 1.80 → 0.20, steal 210–260 ms per run): in-process 165 / 64 / 28 → 59 / 12 / 4.7,
//! socketcand 154 / 60 / 23 → 72 / 39 / 4.8.
//!
//! Sleeping in 100 µs steps cuts the typical lateness from 25–60 µs to 5–8 µs and the p99
//! period jitter 1.5–7× in 13 of 14 pairs: p99 ≤ 100 µs in 7 of 8 runs at 1 ms and 2 of 6 at
//! 2 ms; plain sleeping reached it in none. No configuration avoided missed cycles: every run had
//! 12–140, each a stall of 5–38 ms while the host ran something else (steal), which the guest
//! cannot prevent. At 2 ms the same disturbances per second are twice the share of the cycles,
//! hence the weaker p99. The cost is ≈ 8 % of a core instead of 2 % for the waiting
//! (`examples/wake_latency.rs`, which also shows that /dev/cpu_dma_latency changes nothing here).

use cncgw::config::{AxisKind, MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::Feed;
use cncgw::control::rt::{RtOptions, RtStep};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::{CanBus, Clock, RealClock};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// `--strict`: the configured following-error windows and feedback timeout (default: the
/// shared-host tolerances of tests/realtime/realtime_inproc.rs).
static TOLERANT: AtomicBool = AtomicBool::new(true);

/// The wall clock, timing every wake-up once `armed` (into buffers allocated up front, so
/// that measuring does not allocate in the cycle).
struct TimedClock {
    inner: RealClock,
    period: u64,
    armed: Arc<AtomicBool>,
    last: Option<u64>,
    late: Vec<u64>,
    jitter: Vec<u64>,
}

impl Clock for TimedClock {
    fn now_ns(&self) -> u64 {
        self.inner.now_ns()
    }
    fn wait_until(&mut self, t_ns: u64) {
        self.inner.wait_until(t_ns);
        if !self.armed.load(Ordering::Relaxed) {
            return;
        }
        let now = self.inner.now_ns();
        if self.late.len() < self.late.capacity() {
            self.late.push(now.saturating_sub(t_ns));
        }
        if let Some(prev) = self.last {
            if self.jitter.len() < self.jitter.capacity() {
                self.jitter.push((now - prev).abs_diff(self.period));
            }
        }
        self.last = Some(now);
    }
}

fn pct(v: &mut [u64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    let i = ((v.len() - 1) as f64 * p).round() as usize;
    v[i] as f64 / 1000.0
}

/// A program that keeps the axes and the spindle busy for about `seconds`: Z strokes of
/// 50 mm at F3000 (≈1 s each) under S500.
fn program(seconds: f64) -> String {
    let mut p = String::from("G21\nG98\nM03 S500\nG00 X40 Z2\n");
    let n = (seconds / 1.9).ceil().max(1.0) as usize;
    for _ in 0..n {
        p += "G01 Z-48 F3000\nG01 X42 Z2\nG01 X40\n";
    }
    p += "G00 X100 Z5\nM05\nM30\n";
    p
}

struct Figures {
    summary: RunSummary,
    late: Vec<u64>,
    jitter: Vec<u64>,
    result: Result<(), String>,
    /// Host steal time during the run, ms (both vCPUs).
    steal_ms: u64,
}

/// Steal time of all CPUs so far, ms (/proc/stat, USER_HZ = 100): time the host ran
/// something else while this VM's vCPUs wanted to run. 0 on bare metal.
fn steal_ms() -> u64 {
    let stat = std::fs::read_to_string("/proc/stat").unwrap_or_default();
    stat.lines().next().and_then(|l| l.split_whitespace().nth(8)).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0) * 10
}

fn run(bus: Box<dyn CanBus>, cycle_ms: f64, seconds: f64, rt: &RtOptions) -> Figures {
    let rt = rt.clone();
    let steal0 = steal_ms();
    let r = std::thread::spawn(move || run_on_this_thread(bus, cycle_ms, seconds, &rt)).join();
    cncgw::control::rt::release_cpu_dma_latency();
    let mut f = r.unwrap_or_else(|_| Figures {
        summary: RunSummary::default(),
        late: vec![],
        jitter: vec![],
        result: Err("the run's thread panicked".into()),
        steal_ms: 0,
    });
    f.steal_ms = steal_ms().saturating_sub(steal0);
    f
}

fn run_on_this_thread(bus: Box<dyn CanBus>, cycle_ms: f64, seconds: f64, rt: &RtOptions) -> Figures {
    let mut cfg = MachineConfig::embedded();
    cfg.machine.cycle_ms = cycle_ms;
    if TOLERANT.load(Ordering::Relaxed) {
        // A shared host is not a real-time one: a stall of tens of ms would fault the spindle
        // drive (following error) or the feedback watchdog and end the run. The same
        // tolerances as tests/realtime/realtime_inproc.rs, so that the run goes on and is measured.
        cfg.bus.feedback_timeout_ms = 100.0;
        // The cycle watchdog stops the run at a host stall of 25 periods (a vCPU
        // descheduled for 25 ms at 1 ms): relaxed to the most allowed, so that the stall is counted.
        cfg.machine.watchdog_overruns = 0;
        cfg.machine.watchdog_missed_cycles = 50;
        for a in cfg.axes.values_mut() {
            a.following_error = if a.kind == AxisKind::Spindle { 720.0 } else { 5.0 };
        }
    }
    let period = (cycle_ms * 1e6) as u64;
    let cycles = (seconds * 1000.0 / cycle_ms) as usize + 20_000;
    let armed = Arc::new(AtomicBool::new(false));
    let mut clock = TimedClock {
        inner: RealClock::with_wake(rt.wake()),
        period,
        armed: armed.clone(),
        last: None,
        late: Vec::with_capacity(cycles),
        jitter: Vec::with_capacity(cycles),
    };
    let interp = match Interpreter::from_source("jitter.nc", &program(seconds), &cfg) {
        Ok(i) => i,
        Err(a) => return Figures { summary: RunSummary::default(), late: vec![], jitter: vec![], result: Err(format!("{a:?}")), steal_ms: 0 },
    };
    let mut master = CanOpenMaster::new(bus, &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), spindle, period);
        // As `cncgw run`: the watchdog limits from the config (relaxed above unless --strict).
        lp.set_watchdog(cncgw::control::cycle::Watchdog::from_config(&cfg));
        let r = lp.start(&mut summary).and_then(|start| {
            let feed = Feed::interpreter(interp, &start)?;
            // As `cncgw run`: the cycle thread only, after the interpreter thread started.
            for s in cncgw::control::rt::apply(rt) {
                match s {
                    RtStep::Done(m) => eprintln!("  {m}"),
                    RtStep::Refused(m) | RtStep::Warn(m) => eprintln!("  warning: {m}"),
                }
            }
            armed.store(true, Ordering::Relaxed);
            feed.run(&mut lp, start, &mut summary, &mut |_| {}, false).0
        });
        lp.finish();
        r
    };
    Figures { summary, late: clock.late, jitter: clock.jitter, result: r.map_err(|a| a.to_string()), steal_ms: 0 }
}

fn report(what: &str, cycle_ms: f64, mut f: Figures) {
    let late_t = f.late.iter().filter(|&&l| l >= (cycle_ms * 1e6) as u64).count();
    println!(
        "{what:<36} {cycle_ms:>4} ms {:>7.1} s {:>8} cycles | late p50 {:>7.1} p99 {:>7.1} max {:>8.1} µs | period jitter p50 {:>7.1} p99 {:>7.1} max {:>8.1} µs | missed {} ({} wake-ups ≥ 1 period late) | steal {} ms{}",
        f.summary.cycles as f64 * cycle_ms / 1000.0,
        f.summary.cycles,
        pct(&mut f.late, 0.5),
        pct(&mut f.late, 0.99),
        pct(&mut f.late, 1.0),
        pct(&mut f.jitter, 0.5),
        pct(&mut f.jitter, 0.99),
        pct(&mut f.jitter, 1.0),
        f.summary.overruns,
        late_t,
        f.steal_ms,
        match &f.result {
            Ok(()) if f.summary.at_program_end() => String::new(),
            Ok(()) => " [not at the program end]".into(),
            Err(e) => format!(" [stopped: {e}]"),
        }
    );
}

fn main() {
    let mut seconds = 60.0;
    let mut cycles: Vec<f64> = vec![2.0, 1.0];
    let mut mode = String::from("both");
    let mut rt = RtOptions::default();
    let mut compare = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = || args.next().unwrap_or_default();
        match a.as_str() {
            "--seconds" => seconds = val().parse().unwrap_or(60.0),
            "--cycle-ms" => cycles = vec![val().parse().unwrap_or(2.0)],
            "--mode" => mode = val(),
            "--rt-priority" => rt.priority = val().parse().ok(),
            "--cpu" => rt.cpu = val().parse().ok(),
            "--mlock" => rt.mlock = true,
            "--strict" => TOLERANT.store(false, Ordering::Relaxed),
            "--max-sleep-us" => rt.max_sleep_us = val().parse().ok(),
            "--spin-us" => rt.spin_us = val().parse().ok(),
            "--cpu-dma-latency" => rt.cpu_dma_latency = true,
            "--timer-slack-ns" => rt.timer_slack_ns = val().parse().ok(),
            "--compare" => compare = true,
            other => {
                eprintln!("unknown argument {other}; see the doc comment of examples/jitter.rs");
                std::process::exit(2);
            }
        }
    }
    let ncpu = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "cycle timing in real time, {seconds} s per run; {ncpu} CPUs, load average {}{}",
        load.trim(),
        if TOLERANT.load(Ordering::Relaxed) {
            "; shared-host tolerances (following-error windows 720° / 5 mm, feedback timeout 100 ms, cycle watchdog relaxed)"
        } else {
            ""
        }
    );
    let plain = RtOptions { max_sleep_us: None, spin_us: None, cpu_dma_latency: false, timer_slack_ns: None, ..rt.clone() };
    let variants: Vec<(String, RtOptions)> = if compare {
        vec![(String::new(), plain), (format!(" {}", wake_label(&rt)), rt.clone())]
    } else {
        vec![(if rt == plain { String::new() } else { format!(" {}", wake_label(&rt)) }, rt.clone())]
    };
    for &ms in &cycles {
        for (label, rt) in &variants {
            run_case(&mode, ms, seconds, label, rt);
        }
    }
}

/// The wait options of `rt` in a few words, for the report line.
fn wake_label(rt: &RtOptions) -> String {
    let mut l = Vec::new();
    if let Some(m) = rt.max_sleep_us {
        l.push(format!("sleep≤{m}µs"));
    }
    if let Some(s) = rt.spin_us {
        l.push(format!("spin{s}µs"));
    }
    if rt.cpu_dma_latency {
        l.push("qos0".into());
    }
    if let Some(n) = rt.timer_slack_ns {
        l.push(format!("slack{n}ns"));
    }
    if l.is_empty() {
        "plain".into()
    } else {
        format!("[{}]", l.join(","))
    }
}

fn run_case(mode: &str, ms: f64, seconds: f64, label: &str, rt: &RtOptions) {
    {
        if mode == "inproc" || mode == "both" {
            let wire = InprocBus::new();
            let stop = Arc::new(AtomicBool::new(false));
            let sim_bus: Box<dyn CanBus> = Box::new(wire.endpoint());
            let sim_stop = stop.clone();
            let sim = std::thread::spawn(move || {
                sim_drives::run_realtime(sim_bus, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(), sim_stop)
            });
            let f = run(Box::new(wire.endpoint()), ms, seconds, rt);
            stop.store(true, Ordering::Relaxed);
            let _ = sim.join();
            report(&format!("in-process{label}"), ms, f);
        }
        if mode == "socketcand" || mode == "both" {
            let exe = std::env::current_exe().ok();
            let sim = exe.as_ref().and_then(|e| e.parent()?.parent().map(|d| d.join("sim-drives"))).filter(|p| p.exists());
            let Some(sim) = sim else {
                eprintln!("socketcand: no sim-drives binary next to this example; `cargo build --release --bins` first");
                return;
            };
            let port = 29_600 + (std::process::id() % 300) as u16;
            let addr = format!("127.0.0.1:{port}");
            let mut child = match std::process::Command::new(&sim).args(["--socketcand", &addr]).env("RUST_LOG", "warn").spawn() {
                Ok(c) => c,
                Err(e) => {
                    eprintln!("cannot start {}: {e}", sim.display());
                    return;
                }
            };
            let mut bus = None;
            for _ in 0..100 {
                std::thread::sleep(Duration::from_millis(50));
                if let Ok(b) = cncgw_bus::transport::socketcand::Socketcand::connect(&addr, "can0") {
                    bus = Some(b);
                    break;
                }
            }
            match bus {
                Some(b) => report(&format!("socketcand{label}"), ms, run(Box::new(b), ms, seconds, rt)),
                None => eprintln!("socketcand: cannot connect to sim-drives at {addr}"),
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}
