//! How many drives one sim-drives process emulates in real time at a 1 ms cycle.
//!
//!     cargo run --release -p sim-drives --example capacity [-- SECONDS [N...]]
//!
//! For each N: `run_realtime` serves N linear drives (CSP, all enabled, all moving) on an
//! in-process bus; a master thread sends N RPDO1 + SYNC every 1 ms and waits for the N
//! TPDO1. A cycle passes when every TPDO arrived and the last within 1 ms of the SYNC. The
//! figure is the largest N with every cycle passing (default 5 s per N) and every drive
//! still enabled (a drive that tripped fails its N).
//!
//! On a shared machine one stall of the process (another job's burst) fails an N, so run
//! it at real-time priority for the figure of the emulator itself (as root):
//!
//!     chrt -f 20 target/release/examples/capacity

use cncgw_bus::canopen::{nmt::NmtCommand, sync_frame};
use cncgw_bus::cia402::State;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::{CanBus, CanFrame};
use sim_drives::{run_realtime, DriveConfig, DriveKind, SimConfig};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

const CYCLE: Duration = Duration::from_millis(1);

struct Result {
    cycles: u64,
    missed: u64,
    p50_us: f64,
    p99_us: f64,
    max_us: f64,
    enabled: usize,
    /// CPU time of the sim-drives thread / wall time (1.0 = one core busy).
    cpu: f64,
}

/// CPU time of the calling thread, ns (Linux: first field of /proc/thread-self/schedstat).
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok().and_then(|s| s.split_whitespace().next().and_then(|x| x.parse().ok())).unwrap_or(0)
}

fn run(n: u8, seconds: f64) -> Result {
    let bus = InprocBus::new();
    let mut m = bus.endpoint();
    let drives = (1..=n).map(|i| DriveConfig::new(i, DriveKind::Linear, &format!("a{i}"), 1000.0)).collect();
    let cfg = SimConfig { drives, step_us: 50 };
    let stop = Arc::new(AtomicBool::new(false));
    let st = stop.clone();
    let ep = bus.endpoint();
    let sim = std::thread::spawn(move || {
        let c0 = thread_cpu_ns();
        let t0 = Instant::now();
        let _ = run_realtime(Box::new(ep), cfg, st);
        (thread_cpu_ns().saturating_sub(c0)) as f64 / t0.elapsed().as_nanos() as f64
    });
    // Boot (the last node boots 1 + 0.5 n ms after the start), CSP by SDO, NMT start.
    std::thread::sleep(Duration::from_millis(20 + n as u64));
    for i in 1..=n {
        m.send(&CanFrame::new(0x600 + i as u16, &[0x2F, 0x60, 0x60, 0, 8, 0, 0, 0])).unwrap();
        // 0x60C2 = 1 × 10⁻³ s, as cncgw's master writes it.
        m.send(&CanFrame::new(0x600 + i as u16, &[0x2F, 0xC2, 0x60, 1, 1, 0, 0, 0])).unwrap();
        m.send(&CanFrame::new(0x600 + i as u16, &[0x2F, 0xC2, 0x60, 2, 0xFD, 0, 0, 0])).unwrap();
    }
    std::thread::sleep(Duration::from_millis(20));
    m.send(&NmtCommand::Start.frame(0)).unwrap();
    std::thread::sleep(Duration::from_millis(10));
    while m.try_recv().ok().flatten().is_some() {}

    let mut cw = vec![0u16; n as usize + 1];
    let mut state = vec![State::NotReadyToSwitchOn; n as usize + 1];
    let mut gaps: Vec<u32> = Vec::new();
    let mut prev_sent = Instant::now();
    let mut first_emcy: Option<(u64, CanFrame)> = None;
    let mut enabled_at: Vec<Option<f64>> = vec![None; n as usize + 1];
    let mut lat = Vec::new();
    let (mut cycles, mut missed) = (0u64, 0u64);
    let warmup = 200u64;
    let total = warmup + (seconds * 1000.0) as u64;
    let t0 = Instant::now();
    for k in 0..total {
        let due = t0 + CYCLE * k as u32;
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
        let t = k as f64 * 1e-3;
        // TPDOs still queued belong to an earlier SYNC (that cycle already counts as
        // missed): drop them so they are not taken for this cycle's.
        while let Ok(Some(f)) = m.try_recv() {
            if (0x81..=0x80 + n as u16).contains(&f.cob_id()) && f.len >= 2 && f.data[0..2] != [0, 0] && first_emcy.is_none() {
                first_emcy = Some((k, f));
            }
        }
        for i in 1..=n {
            // Every axis on its own slow sine from where it was enabled: the servo loops
            // all work (a step would trip the following-error window).
            let target = match (state[i as usize], enabled_at[i as usize]) {
                (State::OperationEnabled, Some(te)) => ((500.0 + 50.0 * i as f64) * (1.0 - ((t - te) * 3.0).cos())) as i32,
                _ => 0,
            };
            let mut d = [0u8; 6];
            d[..2].copy_from_slice(&cw[i as usize].to_le_bytes());
            d[2..].copy_from_slice(&target.to_le_bytes());
            m.send(&CanFrame::new(0x200 + i as u16, &d)).unwrap();
        }
        m.send(&sync_frame(None)).unwrap();
        let sent = Instant::now();
        gaps.push((sent - prev_sent).as_micros() as u32);
        prev_sent = sent;
        let deadline = sent + CYCLE;
        let mut got = 0usize;
        let mut last = sent;
        while got < n as usize {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            match m.recv_timeout(left) {
                Ok(Some(f)) if (0x181..=0x180 + n as u16).contains(&f.cob_id()) && f.len >= 2 => {
                    let i = (f.cob_id() - 0x180) as usize;
                    let s = State::from_statusword(u16::from_le_bytes([f.data[0], f.data[1]]));
                    state[i] = s;
                    if s == State::OperationEnabled && enabled_at[i].is_none() {
                        enabled_at[i] = Some(k as f64 * 1e-3);
                    }
                    cw[i] = s.controlword_towards(State::OperationEnabled);
                    got += 1;
                    last = Instant::now();
                }
                Ok(Some(f)) if (0x81..=0x80 + n as u16).contains(&f.cob_id()) && f.len >= 2 && f.data[0..2] != [0, 0] => {
                    if first_emcy.is_none() {
                        first_emcy = Some((k, f));
                        eprintln!("EMCY {f:?} at cycle {k}; SYNC gaps (µs) before: {:?}", &gaps[gaps.len().saturating_sub(30)..]);
                    }
                }
                Ok(_) => {}
                Err(_) => break,
            }
        }
        if k >= warmup {
            cycles += 1;
            if got < n as usize {
                missed += 1;
            } else {
                lat.push((last - sent).as_secs_f64() * 1e6);
            }
        }
    }
    stop.store(true, Ordering::Relaxed);
    let cpu = sim.join().unwrap_or(f64::NAN);
    lat.sort_by(|a, b| a.total_cmp(b));
    let q = |p: f64| if lat.is_empty() { f64::NAN } else { lat[((lat.len() - 1) as f64 * p) as usize] };
    let enabled = state.iter().filter(|s| **s == State::OperationEnabled).count();
    if enabled < n as usize {
        eprintln!("N={n}: states {:?}; first EMCY (cycle, frame) {first_emcy:?}", &state[1..]);
    }
    Result { cycles, missed, p50_us: q(0.5), p99_us: q(0.99), max_us: q(1.0), enabled, cpu }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let seconds: f64 = args.first().and_then(|s| s.parse().ok()).unwrap_or(5.0);
    let ns: Vec<u8> = if args.len() > 1 {
        args[1..].iter().filter_map(|s| s.parse().ok()).collect()
    } else {
        vec![8, 16, 24, 32, 40, 48, 56, 64, 80, 96, 112, 127]
    };
    println!("sim-drives capacity: N drives (CSP, enabled, moving), 1 ms SYNC on the in-process bus, {seconds} s each");
    println!("{:>4} {:>8} {:>7} {:>9} {:>9} {:>9} {:>8} {:>8}", "N", "cycles", "missed", "p50 µs", "p99 µs", "max µs", "enabled", "sim CPU");
    let mut best = 0;
    let mut failed = false;
    let mut best_p99 = 0;
    let mut per_drive = Vec::new();
    for n in ns {
        let r = run(n, seconds);
        let pass = r.missed == 0 && r.max_us < 1000.0 && r.enabled == n as usize;
        println!(
            "{n:>4} {:>8} {:>7} {:>9.0} {:>9.0} {:>9.0} {:>8} {:>7.0}% {}",
            r.cycles,
            r.missed,
            r.p50_us,
            r.p99_us,
            r.max_us,
            r.enabled,
            r.cpu * 100.0,
            if pass { "ok" } else { "FAIL" }
        );
        if r.cpu.is_finite() && r.cpu > 0.0 {
            per_drive.push(r.cpu / n as f64);
        }
        if r.p99_us < 1000.0 && r.enabled == n as usize && r.missed * 100 <= r.cycles * 2 {
            best_p99 = n;
        }
        if pass {
            best = n;
        } else {
            failed = true;
        }
        if r.missed * 2 > r.cycles {
            break;
        }
    }
    println!(
        "largest N with every cycle's TPDOs within 1 ms: {best} drives{}",
        if failed { " (a smaller N failed too: stalls from other load; see the table)" } else { "" }
    );
    println!("largest N with p99 < 1 ms, ≤ 2 % of cycles missed and every drive enabled: {best_p99} drives");
    if !per_drive.is_empty() {
        // The figure a quiet core would give: one core's worth of drives at the measured
        // CPU cost per drive (the measured N is also limited by what else runs).
        let c = per_drive.iter().sum::<f64>() / per_drive.len() as f64;
        println!("CPU per drive at 1 ms: {:.2} % of a core → ≈ {:.0} drives fill one core", c * 100.0, 1.0 / c);
    }
    if let Ok(l) = std::fs::read_to_string("/proc/loadavg") {
        println!("load average during the run: {}", l.split_whitespace().take(3).collect::<Vec<_>>().join(" "));
    }
    println!("command: cargo run --release -p sim-drives --example capacity");
}
