//! Real-time setup of the cycle thread on a real PC: SCHED_FIFO priority, locked memory,
//! CPU affinity. Each is optional, and one the system does not permit is a warning with
//! what to do, not a failure: the controller still runs, with more jitter.

/// What to ask for (the config's `[rt]` and `cncgw run --rt-priority/--mlock/--cpu`, see
/// [`RtOptions::resolve`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RtOptions {
    /// SCHED_FIFO priority 1–99 for the calling thread.
    pub priority: Option<i32>,
    /// mlockall(MCL_CURRENT | MCL_FUTURE): no page faults in the cycle.
    pub mlock: bool,
    /// Pin the calling thread to this CPU.
    pub cpu: Option<usize>,
}

impl RtOptions {
    pub fn any(&self) -> bool {
        self.priority.is_some() || self.mlock || self.cpu.is_some()
    }

    /// What `cncgw run` asks for: the config file's `[rt]`, each option overridden by the
    /// command line where given (`cli`, from `--rt-priority/--mlock/--cpu`). `--mlock` is a
    /// switch, so it can only add memory locking to what the file says.
    pub fn resolve(file: &crate::config::RtConfig, cli: &RtOptions) -> RtOptions {
        RtOptions {
            priority: cli.priority.or(file.priority),
            mlock: cli.mlock || file.mlock,
            cpu: cli.cpu.or(file.cpu),
        }
    }
}

/// Outcome of one request: what was done, or why not and what to do about it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RtStep {
    Done(String),
    Refused(String),
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
    out
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
    RtStep::Refused(format!(
        "cannot pin the cycle thread to CPU {cpu} ({msg}); this machine has {n} CPUs, or a cpuset forbids it. Running unpinned"
    ))
}

#[cfg(target_os = "linux")]
fn fifo(priority: i32) -> RtStep {
    if !(1..=99).contains(&priority) {
        return RtStep::Refused(format!("SCHED_FIFO priority must be 1–99, got {priority}; running with normal scheduling"));
    }
    let param = libc::sched_param { sched_priority: priority };
    // SAFETY: pthread_self is always valid for the calling thread; param lives across the call.
    let r = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if r == 0 {
        return RtStep::Done(format!("cycle thread at SCHED_FIFO priority {priority}"));
    }
    let msg = std::io::Error::from_raw_os_error(r).to_string();
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

#[cfg(not(target_os = "linux"))]
fn fifo(priority: i32) -> RtStep {
    RtStep::Refused(format!("SCHED_FIFO is implemented for Linux only; priority {priority} ignored"))
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
        assert_eq!(c.rt, crate::config::RtConfig { priority: Some(80), mlock: true, cpu: Some(1) });
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
        assert_eq!(RtOptions::resolve(&file, &RtOptions::default()), RtOptions { priority: Some(80), mlock: false, cpu: Some(1) });
        // Each flag replaces only its own option.
        let cli = RtOptions { priority: Some(20), mlock: true, cpu: None };
        assert_eq!(RtOptions::resolve(&file, &cli), RtOptions { priority: Some(20), mlock: true, cpu: Some(1) });
        let cli = RtOptions { priority: None, mlock: false, cpu: Some(0) };
        assert_eq!(RtOptions::resolve(&file, &cli), RtOptions { priority: Some(80), mlock: false, cpu: Some(0) });
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
        let r = std::thread::spawn(|| apply(&RtOptions { priority: Some(150), mlock: false, cpu: Some(100_000) }))
            .join()
            .unwrap();
        assert_eq!(r.len(), 2);
        for s in &r {
            match s {
                RtStep::Refused(m) => assert!(m.contains("CPU 100000") || m.contains("1–99"), "{m}"),
                RtStep::Done(m) => panic!("granted: {m}"),
            }
        }
    }

    #[test]
    fn pinning_to_an_existing_cpu_works_or_says_why() {
        let r = std::thread::spawn(|| apply(&RtOptions { cpu: Some(0), ..Default::default() })).join().unwrap();
        match &r[0] {
            RtStep::Done(m) => assert!(m.contains("CPU 0")),
            RtStep::Refused(m) => assert!(m.contains("CPU 0") && m.contains("unpinned"), "{m}"),
        }
        // A FIFO request either works or explains what to do; never panics.
        let r = std::thread::spawn(|| apply(&RtOptions { priority: Some(10), ..Default::default() })).join().unwrap();
        match &r[0] {
            RtStep::Done(m) => assert!(m.contains("SCHED_FIFO priority 10")),
            RtStep::Refused(m) => assert!(m.contains("CAP_SYS_NICE"), "{m}"),
        }
    }
}
