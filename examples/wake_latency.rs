//! Wake-up lateness of a bare periodic loop, several ways of waiting side by side (issue 8,
//! figure 3: what `RealClock` should do). No bus, no drives: only the wait.
//!
//! Run: `cargo run --release --example wake_latency -- [--seconds 120] [--period-us 2000]
//!       [--block-ms 1000] [--variants sleep,abs,chunk500,spin150,...] [--fifo 50] [--cpu N]`
//!
//! Every variant runs in blocks of `--block-ms`, the variants interleaved round-robin until
//! `--seconds` have passed, so that whatever load the machine has falls on all of them alike.
//! Per variant it prints the lateness of each wake-up (wake − deadline) p50/p99/max in µs, the
//! wake-ups a whole period late (missed), and the CPU time the waiting thread used
//! (getrusage(RUSAGE_THREAD), user + system, in % of one CPU).
//!
//! Variants (names joined by `+` combine; e.g. `chunk500+spin50+fifo+qos`):
//! - `sleep`: `std::thread::sleep` of the time left (relative nanosleep), as `RealClock::new`.
//! - `abs`: `clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)` to the deadline.
//! - `timerfd`: a one-shot absolute `timerfd` per wait, then a blocking read.
//! - `chunkM`: absolute sleeps of at most M µs until the deadline.
//! - `spinS`: sleep until S µs before the deadline, then busy-wait.
//! - `fifo`: the thread at SCHED_FIFO (priority `--fifo`, default 50) during the block;
//!   otherwise SCHED_OTHER.
//! - `qos`: /dev/cpu_dma_latency held open with 0 written during the block (the PM QoS
//!   request that keeps a PC out of deep C-states).
//! - `slack1`: prctl(PR_SET_TIMERSLACK, 1 ns) during the block (SCHED_OTHER threads default
//!   to 50 µs of timer slack; SCHED_FIFO threads have none).
//!
//! Figures on this project's machine (Firecracker VM, 2 vCPUs, no cpuidle driver; another
//! engineer compiling on one core, load 1.1–1.6, host steal 0.3–0.9 %), 22 Nov 2026.
//! Lateness after one sleep of the given length, SCHED_FIFO 50, period 2 ms,
//! `--seconds 64 --variants abs+fifo,chunk1000+fifo,…`:
//!
//! | longest sleep | 2 ms (abs) | 1000 µs | 500 µs | 300 µs | 200 µs | 100 µs | 50 µs |
//! |---------------|-----------:|--------:|-------:|-------:|-------:|-------:|------:|
//! | p50 µs        | 68         | 54      | 31     | 21     | 10     | 6.4    | 5.0   |
//! | p99 µs        | 689        | 919     | 677    | 875    | 229    | 70     | 36    |
//! | CPU %         | 1.8        | 2.8     | 3.7    | 4.7    | 6.0    | 8.0    | 12.9  |
//!
//! The lateness falls with the length of the sleep, as halt polling by the host predicts (a
//! vCPU that halts briefly is polled, one that halts long is descheduled). Strategies side by
//! side, `--seconds 70 --period-us 2000|1000` (p50 / p99 µs, missed, CPU %):
//!
//! | variant              | 2 ms                 | 1 ms                 |
//! |----------------------|----------------------|----------------------|
//! | sleep (std)          | 132 / 977, 19, 2.0   | 104 / 487, 46, 2.7   |
//! | abs + qos            | 121 / 311, 1, 1.8    | 108 / 318, 31, 3.0   |
//! | timerfd              | 78 / 433, 5, 2.2     | 56 / 517, 67, 3.2    |
//! | chunk100             | 57 / 170, 2, 6.6     | 55 / 224, 43, 7.3    |
//! | chunk100 + slack1    | 7.0 / 143, 2, 8.4    | 7.6 / 108, 43, 9.7   |
//! | abs + fifo           | 82 / 292, 1, 1.9     | 58 / 350, 37, 2.9    |
//! | abs + fifo + qos     | 77 / 328, 4, 1.9     | 50 / 283, 23, 2.6    |
//! | chunk100 + fifo      | 8.0 / 72, 0, 9.6     | 6.2 / 52, 6, 8.6     |
//! | chunk50 + fifo       | 7.0 / 97, 7, 15.2    | 5.5 / 36, 7, 13.3    |
//! | chunk200+spin30+fifo | 0.4 / 79, 2, 6.6     | 0.1 / 169, 30, 7.1   |
//!
//! /dev/cpu_dma_latency exists and is writable here but changes nothing (no cpuidle driver:
//! the idle loop is a plain HLT whatever the PM QoS request). Timer slack explains the 50 µs
//! between SCHED_OTHER and SCHED_FIFO sleeps. Spinning gains little over 100 µs steps and
//! costs a core share the emulated drives need. The missed wake-ups are stalls of 2–10 ms,
//! the host running something else (steal), which nothing in the guest avoids.

use std::io::Write;
use std::time::Duration;

#[derive(Clone, Debug, Default)]
struct Variant {
    name: String,
    /// 0 = std sleep, 1 = abs clock_nanosleep, 2 = timerfd.
    how: u8,
    chunk_ns: u64,
    spin_ns: u64,
    fifo: bool,
    qos: bool,
    slack1: bool,
}

impl Variant {
    fn parse(s: &str) -> Result<Variant, String> {
        let mut v = Variant { name: s.to_string(), ..Default::default() };
        for part in s.split('+') {
            let num = |p: &str| p.parse::<u64>().map(|us| us * 1000).map_err(|_| format!("bad number in {part}"));
            match part {
                "sleep" => v.how = 0,
                "abs" => v.how = 1,
                "timerfd" => v.how = 2,
                "fifo" => v.fifo = true,
                "qos" => v.qos = true,
                "slack1" => v.slack1 = true,
                p if p.starts_with("chunk") => {
                    v.chunk_ns = num(&p[5..])?;
                    v.how = 1;
                }
                p if p.starts_with("spin") => {
                    v.spin_ns = num(&p[4..])?;
                    if v.how == 0 {
                        v.how = 1;
                    }
                }
                other => return Err(format!("unknown variant part {other}")),
            }
        }
        Ok(v)
    }
}

fn mono_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn ts(ns: u64) -> libc::timespec {
    libc::timespec { tv_sec: (ns / 1_000_000_000) as libc::time_t, tv_nsec: (ns % 1_000_000_000) as libc::c_long }
}

fn abs_sleep(ns: u64) {
    let t = ts(ns);
    // SAFETY: t lives across the call; the remaining-time pointer may be null for TIMER_ABSTIME.
    while unsafe { libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &t, std::ptr::null_mut()) } == libc::EINTR {}
}

fn thread_cpu_ns() -> u64 {
    // SAFETY: getrusage writes the rusage we own.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut ru) };
    let tv = |t: libc::timeval| t.tv_sec as u64 * 1_000_000_000 + t.tv_usec as u64 * 1000;
    tv(ru.ru_utime) + tv(ru.ru_stime)
}

struct Waiter {
    tfd: i32,
}

impl Waiter {
    fn wait(&self, v: &Variant, d: u64) {
        let sleep_to = d.saturating_sub(v.spin_ns);
        loop {
            let now = mono_ns();
            if now >= sleep_to {
                break;
            }
            let to = if v.chunk_ns > 0 { sleep_to.min(now + v.chunk_ns) } else { sleep_to };
            match v.how {
                0 => std::thread::sleep(Duration::from_nanos(to - now)),
                1 => abs_sleep(to),
                _ => {
                    let spec = libc::itimerspec { it_interval: ts(0), it_value: ts(to) };
                    let mut buf = [0u8; 8];
                    // SAFETY: valid timerfd, spec and buf live across the calls.
                    unsafe {
                        libc::timerfd_settime(self.tfd, libc::TFD_TIMER_ABSTIME, &spec, std::ptr::null_mut());
                        libc::read(self.tfd, buf.as_mut_ptr().cast(), 8);
                    }
                }
            }
        }
        while mono_ns() < d {
            std::hint::spin_loop();
        }
    }
}

#[derive(Default)]
struct Stats {
    late: Vec<u64>,
    missed: u64,
    cpu_ns: u64,
    wall_ns: u64,
}

fn pct(v: &mut [u64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize] as f64 / 1000.0
}

/// (steal, total) jiffies of all CPUs from /proc/stat: time the host ran something else
/// while this VM's vCPUs wanted to run.
fn steal_jiffies() -> (u64, u64) {
    let stat = std::fs::read_to_string("/proc/stat").unwrap_or_default();
    let v: Vec<u64> = stat.lines().next().unwrap_or("").split_whitespace().skip(1).filter_map(|x| x.parse().ok()).collect();
    (v.get(7).copied().unwrap_or(0), v.iter().take(8).sum())
}

fn set_fifo(prio: i32) -> bool {
    let param = libc::sched_param { sched_priority: prio };
    let policy = if prio > 0 { libc::SCHED_FIFO } else { libc::SCHED_OTHER };
    // SAFETY: pthread_self is valid; param lives across the call.
    unsafe { libc::pthread_setschedparam(libc::pthread_self(), policy, &param) == 0 }
}

fn main() {
    let mut seconds = 120.0;
    let mut period_us = 2000u64;
    let mut block_ms = 1000u64;
    let mut fifo_prio = 50;
    let mut cpu: Option<usize> = None;
    let mut names = String::from(
        "sleep,sleep+slack1,abs,timerfd,chunk200,chunk500,chunk800,spin50,spin150,spin400,abs+qos,sleep+fifo,abs+fifo,chunk200+fifo,chunk500+fifo,spin150+fifo,chunk500+spin50+fifo",
    );
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = || args.next().unwrap_or_default();
        match a.as_str() {
            "--seconds" => seconds = val().parse().unwrap_or(seconds),
            "--period-us" => period_us = val().parse().unwrap_or(period_us),
            "--block-ms" => block_ms = val().parse().unwrap_or(block_ms),
            "--variants" => names = val(),
            "--fifo" => fifo_prio = val().parse().unwrap_or(fifo_prio),
            "--cpu" => cpu = val().parse().ok(),
            other => {
                eprintln!("unknown argument {other}; see the doc comment of examples/wake_latency.rs");
                std::process::exit(2);
            }
        }
    }
    let variants: Vec<Variant> = match names.split(',').map(Variant::parse).collect() {
        Ok(v) => v,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(2);
        }
    };
    if let Some(c) = cpu {
        // SAFETY: zeroed cpu_set_t is empty; c < CPU_SETSIZE for any real machine.
        unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            libc::CPU_SET(c, &mut set);
            libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set);
        }
    }
    let period = period_us * 1000;
    let per_block = (block_ms * 1000 / period_us).max(1) as usize;
    let rounds = ((seconds * 1000.0) / (block_ms as f64 * variants.len() as f64)).ceil().max(1.0) as usize;
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "wake-up lateness, period {period_us} µs, {} variants × {rounds} blocks of {block_ms} ms interleaved; load average {}",
        variants.len(),
        load.trim()
    );
    // SAFETY: plain timerfd creation.
    let tfd = unsafe { libc::timerfd_create(libc::CLOCK_MONOTONIC, 0) };
    let w = Waiter { tfd };
    let mut stats: Vec<Stats> = variants.iter().map(|_| Stats { late: Vec::with_capacity(rounds * per_block), ..Default::default() }).collect();
    let steal0 = steal_jiffies();
    let mut qos_note = None;
    let mut fifo_note = None;
    for _ in 0..rounds {
        for (v, s) in variants.iter().zip(stats.iter_mut()) {
            let qos = if v.qos {
                match std::fs::OpenOptions::new().write(true).open("/dev/cpu_dma_latency") {
                    Ok(mut f) => match f.write_all(&0i32.to_ne_bytes()) {
                        Ok(()) => Some(f),
                        Err(e) => {
                            qos_note.get_or_insert(format!("qos: write /dev/cpu_dma_latency: {e}"));
                            None
                        }
                    },
                    Err(e) => {
                        qos_note.get_or_insert(format!("qos: open /dev/cpu_dma_latency: {e}"));
                        None
                    }
                }
            } else {
                None
            };
            if v.fifo && !set_fifo(fifo_prio) {
                fifo_note.get_or_insert(format!("fifo: SCHED_FIFO {fifo_prio} refused: {}", std::io::Error::last_os_error()));
            }
            if v.slack1 {
                // SAFETY: prctl with integer arguments.
                unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
            }
            // Settle into the new mode for one period before measuring.
            let t0 = mono_ns() + period;
            w.wait(v, t0);
            let c0 = thread_cpu_ns();
            let mut k = 1u64;
            let mut n = 0;
            while n < per_block {
                let d = t0 + k * period;
                w.wait(v, d);
                let now = mono_ns();
                let late = now - d;
                s.late.push(late);
                n += 1;
                if late >= period {
                    // As the cycle loop: skip to the next deadline still ahead.
                    let skip = late / period;
                    s.missed += skip;
                    k += skip;
                }
                k += 1;
            }
            s.cpu_ns += thread_cpu_ns() - c0;
            s.wall_ns += mono_ns() - t0;
            if v.slack1 {
                // SAFETY: 0 restores the default slack.
                unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 0 as libc::c_ulong, 0, 0, 0) };
            }
            if v.fifo {
                set_fifo(0);
            }
            drop(qos);
        }
    }
    let steal1 = steal_jiffies();
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "after: load average {}; steal {:.1} % of all CPU time during the run",
        load.trim(),
        100.0 * (steal1.0 - steal0.0) as f64 / (steal1.1 - steal0.1).max(1) as f64
    );
    for n in [qos_note, fifo_note].into_iter().flatten() {
        println!("note: {n}");
    }
    println!("{:<26} {:>7} {:>8} {:>8} {:>9} {:>7} {:>7}", "variant", "wakes", "p50 µs", "p99 µs", "max µs", "missed", "CPU %");
    for (v, s) in variants.iter().zip(stats.iter_mut()) {
        println!(
            "{:<26} {:>7} {:>8.1} {:>8.1} {:>9.1} {:>7} {:>7.1}",
            v.name,
            s.late.len(),
            pct(&mut s.late, 0.5),
            pct(&mut s.late, 0.99),
            pct(&mut s.late, 1.0),
            s.missed,
            100.0 * s.cpu_ns as f64 / s.wall_ns.max(1) as f64
        );
    }
}
