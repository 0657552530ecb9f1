//! Real-time setup of the cycle thread on a real PC: SCHED_FIFO priority, locked memory,
//! CPU affinity, the PM QoS CPU latency request, timer slack, and how the cycle thread waits
//! (`cncgw_bus::WakeStrategy`). Each is optional, and one the system does not permit is a
//! warning with what to do, not a failure: the controller still runs, with more jitter.

use cncgw_bus::WakeStrategy;

/// What to ask for (the config's `[rt]` and `cncgw run --rt-priority/--mlock/--cpu/…`, see
/// [`RtOptions::resolve`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RtOptions {
    /// SCHED_FIFO priority 1–99 for the calling thread.
    pub priority: Option<i32>,
    /// mlockall(MCL_CURRENT | MCL_FUTURE): no page faults in the cycle.
    pub mlock: bool,
    /// Pin the calling thread to this CPU.
    pub cpu: Option<usize>,
    /// Longest single sleep of a cycle wait, µs (None = one sleep to the deadline).
    pub max_sleep_us: Option<u64>,
    /// Busy-wait the last this many µs of a cycle wait (None = never).
    pub spin_us: Option<u64>,
    /// Hold /dev/cpu_dma_latency at 0 (PM QoS) while the process runs.
    pub cpu_dma_latency: bool,
    /// prctl(PR_SET_TIMERSLACK) of the calling thread, ns.
    pub timer_slack_ns: Option<u64>,
}

impl RtOptions {
    pub fn any(&self) -> bool {
        self.priority.is_some()
            || self.mlock
            || self.cpu.is_some()
            || self.max_sleep_us.is_some()
            || self.spin_us.is_some()
            || self.cpu_dma_latency
            || self.timer_slack_ns.is_some()
    }

    /// What `cncgw run` asks for: the config file's `[rt]`, each option overridden by the
    /// command line where given (`cli`, from `--rt-priority/--mlock/--cpu/--max-sleep-us/
    /// --spin-us/--cpu-dma-latency/--timer-slack-ns`). `--mlock` and `--cpu-dma-latency` are
    /// switches, so they can only add to what the file says.
    pub fn resolve(file: &crate::config::RtConfig, cli: &RtOptions) -> RtOptions {
        RtOptions {
            priority: cli.priority.or(file.priority),
            mlock: cli.mlock || file.mlock,
            cpu: cli.cpu.or(file.cpu),
            max_sleep_us: cli.max_sleep_us.or(file.max_sleep_us),
            spin_us: cli.spin_us.or(file.spin_us),
            cpu_dma_latency: cli.cpu_dma_latency || file.cpu_dma_latency,
            timer_slack_ns: cli.timer_slack_ns.or(file.timer_slack_ns),
        }
    }

    /// How the cycle thread's `RealClock` waits (`RealClock::with_wake`).
    pub fn wake(&self) -> WakeStrategy {
        WakeStrategy { max_sleep_ns: self.max_sleep_us.unwrap_or(0).saturating_mul(1000), spin_ns: self.spin_us.unwrap_or(0).saturating_mul(1000) }
    }
}

/// Outcome of one request: what was done, or why not and what to do about it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RtStep {
    Done(String),
    Refused(String),
    /// Done, but with a caveat the operator should read (e.g. it has no effect here).
    Warn(String),
}

/// Apply `o` to the calling thread (call it on the cycle thread, before the loop starts).
/// Never fails; returns one line per request.
pub fn apply(o: &RtOptions) -> Vec<RtStep> {
    let mut out = Vec::new();
    if o.mlock {
        out.push(mlock());
    }
    if let Some(cpu) = o.cpu {
        out.push(affinity(cpu));
    }
    if let Some(p) = o.priority {
        out.push(fifo(p));
    }
    if let Some(ns) = o.timer_slack_ns {
        out.push(timer_slack(ns));
    }
    if o.cpu_dma_latency {
        out.push(cpu_dma_latency());
    }
    if o.max_sleep_us.is_some() || o.spin_us.is_some() {
        out.push(wake_note(o));
    }
    out
}

/// What the cycle wait will do; a warning when it spins on a core it does not own.
fn wake_note(o: &RtOptions) -> RtStep {
    let steps = match o.max_sleep_us {
        Some(m) => format!("sleeps in steps of at most {m} µs"),
        None => "sleeps to the deadline".into(),
    };
    match o.spin_us.filter(|&s| s > 0) {
        None => RtStep::Done(format!("cycle wait {steps}")),
        Some(s) if o.cpu.is_some() && o.priority.is_some() => RtStep::Done(format!("cycle wait {steps}, then spins the last {s} µs")),
        Some(s) => RtStep::Warn(format!(
            "cycle wait {steps}, then spins the last {s} µs without a core of its own (set both cpu and priority, on a CPU isolated with isolcpus=): it takes that CPU time from every other process on the machine, emulated drives included"
        )),
    }
}

/// The PM QoS request, held until [`release_cpu_dma_latency`] or the end of the process
/// (closing the file withdraws it).
static DMA_LATENCY: std::sync::Mutex<Option<std::fs::File>> = std::sync::Mutex::new(None);

const DMA_LATENCY_PATH: &str = "/dev/cpu_dma_latency";

fn cpu_dma_latency() -> RtStep {
    use std::io::Write;
    let f = std::fs::OpenOptions::new().write(true).open(DMA_LATENCY_PATH).and_then(|mut f| {
        f.write_all(&0i32.to_ne_bytes())?;
        Ok(f)
    });
    let f = match f {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return RtStep::Refused(format!(
                "{DMA_LATENCY_PATH} does not exist (a kernel without PM QoS, or not Linux); CPU idle states are left as they are"
            ))
        }
        Err(e) => {
            return RtStep::Refused(format!(
                "cannot hold {DMA_LATENCY_PATH} at 0 ({e}); CPUs may sleep in deep C-states and wake cycles late. Run as root, or make it writable for this user (a udev rule)"
            ))
        }
    };
    if let Ok(mut g) = DMA_LATENCY.lock() {
        *g = Some(f);
    }
    // Without a cpuidle driver (typical of a virtual machine) the kernel idles with a plain
    // HLT whatever the request says.
    let driver = std::fs::read_to_string("/sys/devices/system/cpu/cpuidle/current_driver").unwrap_or_default();
    match driver.trim() {
        "" | "none" => RtStep::Warn(format!(
            "{DMA_LATENCY_PATH} held at 0, but this system has no cpuidle driver (a virtual machine?), so it changes nothing here"
        )),
        d => RtStep::Done(format!("{DMA_LATENCY_PATH} held at 0 µs (cpuidle driver {d}): no deep C-states")),
    }
}

/// Withdraw the PM QoS request of [`RtOptions::cpu_dma_latency`] (it is withdrawn anyway when
/// the process ends).
pub fn release_cpu_dma_latency() {
    if let Ok(mut g) = DMA_LATENCY.lock() {
        *g = None;
    }
}

#[cfg(target_os = "linux")]
fn timer_slack(ns: u64) -> RtStep {
    if ns == 0 {
        return RtStep::Refused("timer slack must be ≥ 1 ns (0 would restore the default); left as it is".into());
    }
    // SAFETY: prctl with integer arguments only.
    let r = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, ns as libc::c_ulong, 0 as libc::c_ulong, 0 as libc::c_ulong, 0 as libc::c_ulong) };
    if r == 0 {
        return RtStep::Done(format!("cycle thread timer slack {ns} ns"));
    }
    let (_, msg) = errno_text();
    RtStep::Refused(format!("cannot set the timer slack to {ns} ns ({msg}); wake-ups may be up to 50 µs later"))
}

#[cfg(not(target_os = "linux"))]
fn timer_slack(ns: u64) -> RtStep {
    RtStep::Refused(format!("timer slack is implemented for Linux only; {ns} ns ignored"))
}

fn errno_text() -> (i32, String) {
    let e = std::io::Error::last_os_error();
    (e.raw_os_error().unwrap_or(0), e.to_string())
}

#[cfg(target_os = "linux")]
fn mlock() -> RtStep {
    // SAFETY: mlockall takes flags only and touches no memory of ours.
    let r = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
    if r == 0 {
        return RtStep::Done("memory locked (mlockall)".into());
    }
    let (_, msg) = errno_text();
    RtStep::Refused(format!(
        "cannot lock memory (mlockall: {msg}); page faults may delay cycles. Raise the locked-memory limit (`ulimit -l unlimited`, or memlock in /etc/security/limits.conf) or grant CAP_IPC_LOCK"
    ))
}

#[cfg(target_os = "linux")]
fn affinity(cpu: usize) -> RtStep {
    let n = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    if cpu >= libc::CPU_SETSIZE as usize {
        return RtStep::Refused(format!("CPU {cpu} does not exist (this machine has {n}); not pinned"));
    }
    // SAFETY: a zeroed cpu_set_t is a valid empty set; CPU_SET indexes within CPU_SETSIZE
    // (checked above); sched_setaffinity reads the set we pass.
    let r = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set)
    };
    if r == 0 {
        return RtStep::Done(format!("cycle thread pinned to CPU {cpu}"));
    }
    let (_, msg) = errno_text();
    RtStep::Refused(format!("cannot pin the cycle thread to CPU {cpu} ({msg}); this machine has {n} CPUs, or a cpuset forbids it. Running unpinned"))
}

fn fifo(priority: i32) -> RtStep {
    if !(1..=99).contains(&priority) {
        return RtStep::Refused(format!("SCHED_FIFO priority must be 1–99, got {priority}; running with normal scheduling"));
    }
    let Err(msg) = cncgw_bus::rt::fifo_current_thread(priority) else {
        return RtStep::Done(format!("cycle thread at SCHED_FIFO priority {priority}"));
    };
    RtStep::Refused(format!(
        "cannot run the cycle thread at SCHED_FIFO priority {priority} ({msg}); running with normal scheduling, expect more jitter. Run as root, grant CAP_SYS_NICE (`setcap cap_sys_nice+ep $(which cncgw)`), or allow it with rtprio in /etc/security/limits.conf"
    ))
}

#[cfg(not(target_os = "linux"))]
fn mlock() -> RtStep {
    RtStep::Refused("memory locking is implemented for Linux only; continuing without".into())
}

#[cfg(not(target_os = "linux"))]
fn affinity(cpu: usize) -> RtStep {
    RtStep::Refused(format!("CPU pinning is implemented for Linux only; CPU {cpu} ignored"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(rt: &str) -> crate::config::MachineConfig {
        let t = format!("{}\n[rt]\n{rt}\n", crate::config::EMBEDDED_LATHE);
        crate::config::MachineConfig::from_toml("t.toml", &t).unwrap()
    }

    #[test]
    fn rt_table_is_read_and_checked() {
        assert_eq!(crate::config::MachineConfig::embedded().rt, crate::config::RtConfig::default());
        let c = cfg("priority = 80\nmlock = true\ncpu = 1");
        assert_eq!(c.rt, crate::config::RtConfig { priority: Some(80), mlock: true, cpu: Some(1), ..Default::default() });
        let t = format!("{}\n[rt]\npriority = 0\n", crate::config::EMBEDDED_LATHE);
        let e = crate::config::MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(e.contains("rt.priority") && e.contains("1–99"), "{e}");
        let t = format!("{}\n[rt]\nprio = 5\n", crate::config::EMBEDDED_LATHE);
        assert!(crate::config::MachineConfig::from_toml("t.toml", &t).is_err(), "unknown key accepted");
    }

    #[test]
    fn command_line_overrides_the_file_option_by_option() {
        let file = cfg("priority = 80\ncpu = 1").rt;
        // Nothing on the command line: the file.
        assert_eq!(
            RtOptions::resolve(&file, &RtOptions::default()),
            RtOptions { priority: Some(80), mlock: false, cpu: Some(1), ..Default::default() }
        );
        // Each flag replaces only its own option.
        let cli = RtOptions { priority: Some(20), mlock: true, cpu: None, ..Default::default() };
        assert_eq!(RtOptions::resolve(&file, &cli), RtOptions { priority: Some(20), mlock: true, cpu: Some(1), ..Default::default() });
        let cli = RtOptions { priority: None, mlock: false, cpu: Some(0), ..Default::default() };
        assert_eq!(RtOptions::resolve(&file, &cli), RtOptions { priority: Some(80), mlock: false, cpu: Some(0), ..Default::default() });
        // No file table: the command line alone.
        assert_eq!(RtOptions::resolve(&Default::default(), &cli), cli);
    }

    #[test]
    fn nothing_asked_nothing_done() {
        assert!(apply(&RtOptions::default()).is_empty());
        assert!(!RtOptions::default().any());
    }

    #[test]
    fn bad_requests_are_refused_with_a_reason_not_a_failure() {
        // Each on its own thread: a granted request must not change the test runner's.
        let r =
            std::thread::spawn(|| apply(&RtOptions { priority: Some(150), mlock: false, cpu: Some(100_000), ..Default::default() })).join().unwrap();
        assert_eq!(r.len(), 2);
        for s in &r {
            match s {
                RtStep::Refused(m) => assert!(m.contains("CPU 100000") || m.contains("1–99"), "{m}"),
                RtStep::Done(m) | RtStep::Warn(m) => panic!("granted: {m}"),
            }
        }
    }

    #[test]
    fn pinning_to_an_existing_cpu_works_or_says_why() {
        let r = std::thread::spawn(|| apply(&RtOptions { cpu: Some(0), ..Default::default() })).join().unwrap();
        match &r[0] {
            RtStep::Done(m) => assert!(m.contains("CPU 0")),
            RtStep::Refused(m) => assert!(m.contains("CPU 0") && m.contains("unpinned"), "{m}"),
            RtStep::Warn(m) => panic!("{m}"),
        }
        // A FIFO request either works or explains what to do; never panics.
        let r = std::thread::spawn(|| apply(&RtOptions { priority: Some(10), ..Default::default() })).join().unwrap();
        match &r[0] {
            RtStep::Done(m) => assert!(m.contains("SCHED_FIFO priority 10")),
            RtStep::Refused(m) => assert!(m.contains("CAP_SYS_NICE"), "{m}"),
            RtStep::Warn(m) => panic!("{m}"),
        }
    }

    #[test]
    fn wake_keys_are_read_checked_and_overridden() {
        let c = cfg("max_sleep_us = 500\nspin_us = 50\ncpu_dma_latency = true\ntimer_slack_ns = 1");
        assert_eq!(
            c.rt,
            crate::config::RtConfig {
                max_sleep_us: Some(500),
                spin_us: Some(50),
                cpu_dma_latency: true,
                timer_slack_ns: Some(1),
                ..Default::default()
            }
        );
        let o = RtOptions::resolve(&c.rt, &RtOptions::default());
        assert!(o.any());
        assert_eq!(o.wake(), WakeStrategy { max_sleep_ns: 500_000, spin_ns: 50_000 });
        // The command line replaces each value; the switch only adds.
        let o = RtOptions::resolve(&c.rt, &RtOptions { max_sleep_us: Some(200), spin_us: Some(0), ..Default::default() });
        assert_eq!(o.wake(), WakeStrategy { max_sleep_ns: 200_000, spin_ns: 0 });
        assert!(o.cpu_dma_latency);
        // Nothing said: one sleep to the deadline, no spin (the shared-machine default).
        assert_eq!(RtOptions::default().wake(), WakeStrategy::default());
        assert_eq!(RtOptions::resolve(&Default::default(), &Default::default()).wake(), WakeStrategy::default());
        let bad = |rt: &str, key: &str| {
            let t = format!("{}\n[rt]\n{rt}\n", crate::config::EMBEDDED_LATHE);
            let e = crate::config::MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
            assert!(e.contains(key), "{rt}: {e}");
        };
        bad("max_sleep_us = 0", "rt.max_sleep_us");
        bad("max_sleep_us = 5", "rt.max_sleep_us");
        // The embedded lathe's cycle is 2 ms: a margin of a whole cycle would spin forever.
        bad("spin_us = 2000", "rt.spin_us");
        bad("timer_slack_ns = 0", "rt.timer_slack_ns");
        bad("cpu_dma_latency = 1", "cpu_dma_latency");
    }

    #[test]
    fn wake_requests_are_reported_and_spinning_without_a_core_warns() {
        let r = apply(&RtOptions { max_sleep_us: Some(500), ..Default::default() });
        assert_eq!(r, vec![RtStep::Done("cycle wait sleeps in steps of at most 500 µs".into())]);
        let r = apply(&RtOptions { spin_us: Some(50), ..Default::default() });
        match &r[0] {
            RtStep::Warn(m) => assert!(m.contains("spins the last 50 µs") && m.contains("isolcpus"), "{m}"),
            s => panic!("{s:?}"),
        }
        // With its own core and priority the spin is no warning (only the note is checked:
        // run on a thread so that a granted FIFO request does not change the test runner).
        let r = std::thread::spawn(|| wake_note(&RtOptions { spin_us: Some(50), cpu: Some(0), priority: Some(10), ..Default::default() }))
            .join()
            .unwrap();
        assert_eq!(r, RtStep::Done("cycle wait sleeps to the deadline, then spins the last 50 µs".into()));
    }

    #[test]
    fn pm_qos_request_is_held_or_refused_with_a_reason() {
        match cpu_dma_latency() {
            RtStep::Done(m) => assert!(m.contains("held at 0"), "{m}"),
            RtStep::Warn(m) => assert!(m.contains("held at 0") && m.contains("no cpuidle driver"), "{m}"),
            RtStep::Refused(m) => assert!(m.contains(DMA_LATENCY_PATH) && (m.contains("does not exist") || m.contains("cannot hold")), "{m}"),
        }
        release_cpu_dma_latency();
        assert!(DMA_LATENCY.lock().map(|g| g.is_none()).unwrap_or(false));
    }

    #[test]
    fn timer_slack_is_set_on_the_calling_thread() {
        let r = std::thread::spawn(|| {
            let done = timer_slack(1);
            // SAFETY: prctl with integer arguments only; PR_GET_TIMERSLACK returns the value.
            #[cfg(target_os = "linux")]
            let now = unsafe { libc::prctl(libc::PR_GET_TIMERSLACK, 0 as libc::c_ulong, 0 as libc::c_ulong, 0 as libc::c_ulong, 0 as libc::c_ulong) };
            #[cfg(not(target_os = "linux"))]
            let now = 1;
            (done, now, timer_slack(0))
        })
        .join()
        .unwrap();
        if cfg!(target_os = "linux") {
            assert!(matches!(&r.0, RtStep::Done(m) if m.contains("1 ns")), "{:?}", r.0);
            assert_eq!(r.1, 1);
        }
        assert!(matches!(&r.2, RtStep::Refused(_)), "{:?}", r.2);
    }
}
