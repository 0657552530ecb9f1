//! `cncgw run`: run a part program on the embedded emulated machine or on a real bus.

use super::exit;
use super::MachineArgs;
use super::OrSetup;
use crate::canon::Pos;
use crate::config::MachineConfig;
use crate::control::cycle::{AxisSummary, CycleLoop, RunSummary};
use crate::control::rt::{RtOptions, RtStep};
use crate::control::trace::{Trace, TraceData};
use crate::drives::DriveBus;
use crate::interp::Interpreter;
use crate::motion::{Limits, AX_S, AX_X, AX_Y, AX_Z};
use cncgw_bus::Clock;
use std::path::Path;

/// Real-time setup of the cycle thread (real drives on a real PC). Each is optional; one the
/// system refuses is a warning, not an error. Each flag overrides the config's `[rt]` option.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RtArgs {
    /// Run the cycle thread at this SCHED_FIFO priority (1–99; needs root, CAP_SYS_NICE or an
    /// rtprio limit).
    #[arg(long, value_name = "1-99")]
    pub rt_priority: Option<i32>,
    /// Lock all memory (mlockall) so that no page fault delays a cycle.
    #[arg(long)]
    pub mlock: bool,
    /// Pin the cycle thread to this CPU (e.g. one isolated with isolcpus=).
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Sleep in steps of at most this many µs while waiting for a cycle (helps on virtual
    /// machines whose idle vCPUs are descheduled by the host).
    #[arg(long, value_name = "US")]
    pub max_sleep_us: Option<u64>,
    /// Busy-wait the last this many µs of each cycle wait (only with a core of its own).
    #[arg(long, value_name = "US")]
    pub spin_us: Option<u64>,
    /// Hold /dev/cpu_dma_latency at 0 (no deep C-states) while running.
    #[arg(long)]
    pub cpu_dma_latency: bool,
    /// Timer slack of the cycle thread in ns (Linux default 50 µs for normal threads).
    #[arg(long, value_name = "NS")]
    pub timer_slack_ns: Option<u64>,
}

/// What `cncgw run` does besides running: the per-cycle trace and the real-time setup.
#[derive(Clone, Debug, Default)]
pub struct RunExtras<'a> {
    pub trace: Option<&'a Path>,
    pub rt: RtOptions,
    /// The rigid-tap state file and what it held at start (`control::tapstate`); None = not kept.
    pub tap: Option<TapSetup>,
    /// Where every alarm of the run is appended (`cncgw alarms`); None = not kept.
    pub history: Option<crate::persist::AlarmHistory>,
    /// The axes' reference state (`reference`): checked at start, kept up to date at the end.
    /// None = no axis has a reference to manage.
    pub reference: Option<RefSetup>,
    /// The OPC UA server of `cncgw run` (`[opcua] enabled`); None = no server.
    pub opcua: Option<OpcUaSetup>,
}

/// The reference file of a run and the axes that must be referenced before anything moves.
#[derive(Clone, Debug)]
pub struct RefSetup {
    /// None: no state directory, so nothing is referenced.
    pub file: Option<crate::reference::ReferenceFile>,
    pub required: Vec<String>,
}

impl RefSetup {
    /// For a run of `cfg` with state in `state` (None when no axis has `homing`).
    pub fn new(cfg: &MachineConfig, state: Option<&crate::persist::StatePlace>) -> Option<RefSetup> {
        cfg.axes
            .values()
            .any(|a| a.homing.is_some())
            .then(|| RefSetup { file: state.map(|s| s.reference()), required: crate::reference::required(cfg) })
    }
}

/// Each drive's axis name, position and the tolerance the reference check allows it.
fn drive_positions(lp: &CycleLoop, cfg: &MachineConfig) -> Vec<(String, f64, f64)> {
    (0..lp.drives.axis_count())
        .map(|d| {
            let name = lp.drives.axis_name(d).to_string();
            // A drive at rest holds within its window; one that counted afresh from power-on
            // is off by where it stood (a coincidence within 0.1 mm is not caught).
            let tol = cfg.axes.get(&name).map_or(0.01, |a| a.following_error.abs().min(0.1).max(1.0 / a.counts_per_unit.abs().max(1e-9)));
            (name, lp.drives.feedback(d).pos, tol)
        })
        .collect()
}

/// At start (drives up, nothing moved): drop the references the drives' positions belie,
/// then alarm 224 if an axis that needs one has none.
fn reference_at_start(lp: &CycleLoop, cfg: &MachineConfig, r: Option<&RefSetup>) -> Result<(), crate::Alarm> {
    let Some(r) = r else { return Ok(()) };
    let here = drive_positions(lp, cfg);
    let table = match &r.file {
        Some(f) => f.update(|t| {
            for n in t.check_start(&here) {
                eprintln!("cncgw: {n}");
            }
        })?,
        None => crate::reference::Table::default(),
    };
    table.check(cfg, &r.required)
}

/// At the end: the references the bus saw lost (a drive rebooted, an encoder fault) are
/// dropped; the others remember where the axes stand.
fn reference_at_end(lp: &CycleLoop, cfg: &MachineConfig, r: Option<&RefSetup>) {
    let Some(f) = r.and_then(|r| r.file.as_ref()) else { return };
    let here = drive_positions(lp, cfg);
    let lost: Vec<(String, String)> =
        (0..lp.drives.axis_count()).filter_map(|d| lp.drives.position_lost(d).map(|w| (lp.drives.axis_name(d).to_string(), w))).collect();
    let r = f.update(|t| {
        for (axis, why) in &lost {
            if let Some(n) = t.lose(axis, &format!("its drive {why}")) {
                eprintln!("cncgw: {n}");
            }
        }
        t.update_positions(&here);
    });
    if let Err(a) = r {
        eprintln!("{a}");
    }
}

/// What the OPC UA server of a run needs besides the configuration.
#[derive(Clone, Debug)]
pub struct OpcUaSetup {
    /// The state directory (its certificates go under `opcua/pki`).
    pub state_dir: std::path::PathBuf,
    /// The configuration file's name (Identification.ConfigFile).
    pub config_name: String,
}

/// The run's OPC UA server (`[opcua] enabled`), reading the cycle loop's snapshot.
struct Observer {
    #[cfg(feature = "opcua")]
    inner: Option<(std::sync::Arc<crate::control::snapshot::Snapshot>, crate::opcua::OpcUaServer)>,
}

impl Observer {
    /// Start the server before the drives (a client may watch start-up too), the snapshot set
    /// on `lp`. An enabled server that cannot start refuses the run.
    fn start(cfg: &MachineConfig, setup: Option<&OpcUaSetup>, lp: &mut CycleLoop, job: &Job) -> Result<Observer, String> {
        #[cfg(feature = "opcua")]
        {
            let Some(setup) = setup.filter(|_| cfg.opcua.enabled) else { return Ok(Observer { inner: None }) };
            let snap = std::sync::Arc::new(crate::control::snapshot::Snapshot::new());
            snap.set_program(&job.name, job.source.lines().count() as u32, lp.drive_names());
            let server = crate::opcua::OpcUaServer::start(cfg, &setup.config_name, snap.clone(), &setup.state_dir)?;
            eprintln!("cncgw: OPC UA server (read-only) on opc.tcp://{}/", server.addr);
            lp.set_snapshot(snap.clone());
            Ok(Observer { inner: Some((snap, server)) })
        }
        #[cfg(not(feature = "opcua"))]
        {
            let _ = (lp, job);
            match setup.filter(|_| cfg.opcua.enabled) {
                Some(_) => Err("this cncgw was built without the OPC UA server (cargo feature `opcua`): set [opcua] enabled = false, or build it with the feature".into()),
                None => Ok(Observer {}),
            }
        }
    }

    /// The alarm that ended the run, for the server's event (its text is not in the snapshot).
    fn alarm(&self, _a: &crate::Alarm) {
        #[cfg(feature = "opcua")]
        if let Some((s, _)) = &self.inner {
            s.set_alarm(_a);
        }
    }

    /// Let subscribed clients see the end, then stop the server.
    fn finish(self) {
        #[cfg(feature = "opcua")]
        if let Some((_, server)) = self.inner {
            server.finish();
        }
    }
}

/// Append `a` to the run's alarm history, if it keeps one (a failure to write it is said,
/// not fatal: the alarm itself has been shown).
fn record_alarm(extras: &RunExtras, program: &str, a: &crate::Alarm) {
    if let Some(h) = &extras.history {
        if let Err(e) = h.append(a, program) {
            eprintln!("warning: the alarm could not be added to the history {}: {e}", h.path.display());
        }
    }
}

/// Where the rigid-tap state is kept during a run, and the state loaded from it.
#[derive(Clone, Debug)]
pub struct TapSetup {
    pub file: std::path::PathBuf,
    pub loaded: Option<crate::persist::TapState>,
}

/// How a run meets its operator.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct OperatorArgs {
    /// No operator panel even on a terminal: no keys, simulated time as fast as the CPU,
    /// M00/M01 go on as if cycle start had been pressed (what a run without a terminal does).
    #[arg(long, conflicts_with = "realtime")]
    pub batch: bool,
    /// Pace the embedded emulated machine's simulated time to the wall clock even without a
    /// terminal (on a terminal it is paced anyway, so that keys act mid-program).
    #[arg(long)]
    pub realtime: bool,
}

/// The files a run reads and writes besides the program and the configuration.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunFiles<'a> {
    /// The machine's state directory (default: `persist::default_state_dir`).
    pub state_dir: Option<&'a Path>,
    /// Record every cycle to this CSV file.
    pub trace: Option<&'a Path>,
    /// The tool offset table.
    pub tools: Option<&'a Path>,
    /// Restart at this block (`cli::restart`).
    pub restart: Option<crate::interp::RestartAt>,
}

pub fn run(program: &Path, machine: &MachineArgs, json: bool, files: RunFiles, max_blocks: u64, rt: &RtArgs, op: &OperatorArgs) -> i32 {
    let RunFiles { state_dir, trace, tools, restart } = files;
    let (cfg, cfg_text) = match super::machine_config(machine).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    // `run -`: the program comes on standard input, read whole (it is checked before motion).
    let stdin_text = match super::mdi::program_from_stdin(program) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: {e}");
            return exit::INPUT;
        }
    };
    let open = |cfg: &MachineConfig| match &stdin_text {
        Some(t) => Interpreter::with_program_dir("<stdin>", t, cfg, Some(Path::new("."))),
        None => Interpreter::from_file(program, cfg),
    };
    // The whole program is checked before anything moves.
    let mut interp = match open(&cfg) {
        Ok(i) => i,
        Err(alarms) => {
            for a in &alarms {
                eprintln!("{a}");
            }
            eprintln!("{} error(s); nothing was moved", alarms.len());
            return exit::INPUT;
        }
    };
    interp.set_block_budget(max_blocks);
    // The offsets: `--tools FILE` wins for the tool table, else the stored one (`cncgw offsets`).
    let state_root = state_dir.map(Path::to_path_buf).or_else(crate::persist::default_state_dir);
    if cfg.opcua.enabled && state_root.is_none() {
        eprintln!("error: [opcua] needs a state directory for its certificates: give --state-dir or set CNCGW_STATE_DIR");
        return exit::SETUP;
    }
    let tables = match super::resolve_tables(state_root.as_deref(), &cfg.machine.name, tools) {
        Ok(t) => t,
        Err(code) => {
            eprintln!("nothing was moved");
            return code;
        }
    };
    eprintln!("cncgw: {}", tables.source);
    tables.apply(&mut interp);
    let source = stdin_text.clone().unwrap_or_else(|| std::fs::read_to_string(program).unwrap_or_default());
    // The machine's state (common variables #401–#600, the rigid-tap state), kept per machine
    // and per place it runs, under a lock so that no other run interleaves with this one.
    let (state, _state_lock) = match lock_state(state_root.as_deref(), &cfg, &run_place(&cfg, machine)) {
        Ok(s) => s,
        Err(a) => {
            eprintln!("{a}");
            return exit::SETUP;
        }
    };
    // Common variables #401–#600 survive power-off: load them, store them after the run.
    let vars_file = state.as_ref().map(|s| s.common_vars());
    let mut interp = interp;
    if let Some(f) = &vars_file {
        match f.load() {
            Ok(v) => interp.set_common_vars(v),
            Err(a) => {
                eprintln!("{a}");
                return exit::SETUP;
            }
        }
    }
    // The rigid-tap state lives beside them: with the tool still in a tapped hole, only a
    // program that starts with the G30 P99 return may run.
    let tap_file = state.as_ref().map(|s| s.tap_state());
    let tap_state = match tap_file.as_ref().map(|f| f.load()).transpose() {
        Ok(s) => s.flatten(),
        Err(a) => {
            eprintln!("{a}");
            return exit::SETUP;
        }
    };
    if let Some(st) = tap_state.filter(|s| s.in_hole) {
        if let Err(a) = check_tap_return_program(open(&cfg), &st) {
            eprintln!("{a}");
            eprintln!("nothing was moved");
            return exit::ALARM;
        }
        eprintln!(
            "cncgw: the tool is in the hole of the rigid tap of line {} ({} {:.4} mm, R plane {:.4}, lead {}): G30 P99 returns along it",
            st.line, st.axis, st.position, st.r_plane, st.lead
        );
        interp.set_tap_return(Some(st.tap_return()));
    }
    // A restart is refused before the drives are enabled when the scan says so.
    if let Some(a) =
        restart.and_then(|at| super::restart::precheck(at, open(&cfg), &tables, interp.common_vars(), tap_state.is_some_and(|s| s.in_hole)))
    {
        eprintln!("{a}");
        return exit::INPUT;
    }
    let job = Job {
        name: program.display().to_string(),
        source,
        first: Some(interp),
        make: Box::new(|_| {
            open(&cfg).map(|mut i| {
                i.set_block_budget(max_blocks);
                tables.apply(&mut i);
                i
            })
        }),
        feed: restart
            .map(|at| -> Box<dyn FnOnce(Interpreter, Pos) -> Box<dyn MoveFeed>> { Box::new(move |i, start| super::restart::feed(at, i, start)) }),
    };
    let mut opts = ExecOpts {
        json,
        print_summary: true,
        extras: RunExtras {
            trace,
            rt: rt.resolve(&cfg.rt),
            tap: tap_file.map(|f| TapSetup { file: f.path, loaded: tap_state }),
            history: state.as_ref().map(|s| s.alarm_history()),
            reference: RefSetup::new(&cfg, state.as_ref()),
            opcua: state_root.clone().filter(|_| cfg.opcua.enabled).map(|state_dir| OpcUaSetup {
                state_dir,
                config_name: machine.config.as_ref().map_or_else(|| "<embedded config/lathe.toml>".to_string(), |p| p.display().to_string()),
            }),
        },
        operator: None,
        pace: op.realtime,
        live: false,
    };
    let (code, vars, _) = with_operator(op, &mut opts, |opts| run_job(&cfg, &cfg_text, machine, job, opts));
    if let (Some(f), Some(v)) = (&vars_file, vars) {
        if let Err(a) = f.save(&v) {
            eprintln!("{a}");
            return if code == exit::OK { exit::SETUP } else { code };
        }
    }
    code
}

/// The machine's state (common variables #401–#600, the rigid-tap state), kept per machine
/// and per place it runs, checked writable and locked so that no other run interleaves with
/// this one. None without a state directory.
fn lock_state(
    root: Option<&Path>,
    cfg: &MachineConfig,
    place: &str,
) -> Result<(Option<crate::persist::StatePlace>, Option<super::lock::Lock>), crate::Alarm> {
    let Some(st) = root.map(|d| crate::persist::StatePlace::new(d, &cfg.machine.name, place)) else { return Ok((None, None)) };
    for n in &st.notes {
        eprintln!("cncgw: {n}");
    }
    // Everything checkable before motion: the state can be written and is ours.
    st.check_writable()?;
    let lock = super::lock::state(&st.dir, &st.key)?;
    Ok((Some(st), Some(lock)))
}

impl RtArgs {
    /// The config's [rt], each option overridden by its command-line flag.
    pub fn resolve(&self, cfg: &crate::config::RtConfig) -> RtOptions {
        let flags = RtOptions {
            priority: self.rt_priority,
            mlock: self.mlock,
            cpu: self.cpu,
            max_sleep_us: self.max_sleep_us,
            spin_us: self.spin_us,
            cpu_dma_latency: self.cpu_dma_latency,
            timer_slack_ns: self.timer_slack_ns,
        };
        RtOptions::resolve(cfg, &flags)
    }
}

/// Where a run runs, for its state files and its bus lock: `inproc` for the embedded
/// emulated machine, else the bus (`--bus`, or the configuration's; a Modbus-only machine by
/// its first link).
pub fn run_place(cfg: &MachineConfig, machine: &MachineArgs) -> String {
    let bus = machine.bus.clone().unwrap_or_else(|| cfg.bus.interface.clone());
    if bus != "none" {
        return bus;
    }
    match cfg.modbus.iter().next() {
        Some((_, l)) => format!("modbus-{}", l.address.as_deref().or(l.device.as_deref()).unwrap_or("link")),
        None => bus,
    }
}

/// Run `f` with the operator panel on the terminal when there is one (stdin and stderr are
/// terminals and not `--batch`): raw keys read by a thread, the terminal restored after `f`
/// whatever happens (an alarm, a panic, Ctrl-C — which is read as a key and presses reset).
pub fn with_operator<R>(op: &OperatorArgs, opts: &mut ExecOpts, f: impl FnOnce(&mut ExecOpts) -> R) -> R {
    use std::io::IsTerminal;
    let tty = std::io::stdin().is_terminal() && std::io::stderr().is_terminal();
    if op.batch || !tty {
        super::term::catch_termination(true);
        return f(opts);
    }
    let guard = match super::term::RawMode::enter() {
        Ok(g) => g,
        Err(e) => {
            eprintln!("warning: cannot read single keys from the terminal ({e}); running without the operator panel");
            return f(opts);
        }
    };
    let panel = crate::control::panel::Panel::new();
    super::term::spawn_key_reader(panel.clone());
    super::term::catch_termination(false);
    opts.operator = Some(panel);
    // Simulated time is paced to the wall clock so that a person's keys land mid-program.
    opts.pace = true;
    let r = f(opts);
    drop(guard);
    r
}

/// The program of a run: the interpreter to run and how to make a fresh one for the start
/// position (the slow-link check runs the program once more; `tap-test` writes its program
/// only once the start position is known).
pub struct Job<'a> {
    /// For messages.
    pub name: String,
    /// The program text (the display shows the block in execution).
    pub source: String,
    /// The interpreter to run, if already made (checked, common variables loaded).
    pub first: Option<Interpreter>,
    #[allow(clippy::type_complexity)]
    pub make: Box<dyn Fn(Pos) -> Result<Interpreter, Vec<crate::Alarm>> + 'a>,
    /// Where the moves come from instead of the interpreter itself (MDI: `cli::mdi`), made
    /// from it and the start position; None = the interpreter.
    #[allow(clippy::type_complexity)]
    pub feed: Option<Box<dyn FnOnce(Interpreter, Pos) -> Box<dyn MoveFeed> + 'a>>,
}

/// A source of moves for the interpreter thread, which hands back the common variables at
/// the end.
pub use crate::control::job::MoveFeed;

/// Options of `run_job`.
#[derive(Default)]
pub struct ExecOpts<'a> {
    pub json: bool,
    /// Print the run's summary (table or JSON) on stdout.
    pub print_summary: bool,
    pub extras: RunExtras<'a>,
    /// The operator panel the cycle loop reads (interactive run); None = batch.
    pub operator: Option<crate::control::panel::Panel>,
    /// Pace simulated time to the wall clock.
    pub pace: bool,
    /// The moves come as a person types them (MDI): the embedded machine is paced and never
    /// waits for the next block in simulated time (it would hold the last one back), and no
    /// progress bar is drawn over the prompt.
    pub live: bool,
}

/// Open the machine's drives (`--config`, `--bus`) and run `job` on them. Returns the exit
/// code, the common variables at the end, and the run's summary.
#[allow(clippy::type_complexity)]
pub fn run_job(
    cfg: &MachineConfig,
    cfg_text: &str,
    machine: &MachineArgs,
    job: Job,
    opts: &ExecOpts,
) -> (i32, Option<std::collections::HashMap<u32, f64>>, RunSummary) {
    // One controller per bus (the emulated one is private to this run).
    let _bus_lock = match super::lock::bus(&run_place(cfg, machine)) {
        Ok(l) => l,
        Err(a) => {
            eprintln!("{a}");
            return (exit::SETUP, None, RunSummary::default());
        }
    };
    let mut modbus = crate::drives::modbus::ModbusDrives::new(cfg);
    modbus.set_rt_priority(opts.extras.rt.priority);
    // The CANopen bus is opened only if an axis is on it.
    let mut can = None;
    // A real bus waits as [rt] says (max_sleep_us, spin_us).
    let real_clock = || -> Box<dyn Clock> { Box::new(cncgw_bus::RealClock::with_wake(opts.extras.rt.wake())) };
    let mut clock: Box<dyn Clock> = real_clock();
    let mut what = Vec::new();
    if cfg.has_canopen() {
        if !modbus.is_empty() && machine.on_embedded_bus(cfg) {
            eprintln!(
                "error: the embedded emulated bus (inproc) is CANopen only and runs in simulated time; a machine with Modbus axes runs in real time: give the CANopen axes a real bus (--bus vcan0, --bus socketcand://HOST:PORT/can0) and start the Modbus drives (e.g. sim-drives --modbus-tcp ADDR)"
            );
            return (exit::SETUP, None, RunSummary::default());
        }
        match super::open_bus(cfg, cfg_text, machine.bus.as_deref(), machine.sim_config.as_deref()) {
            Ok((m, c, _, w)) => {
                can = Some(m);
                // Not used yet: a real one is replaced by one that waits as configured.
                // An external SYNC's clock waits on the bus, not as [rt] says.
                clock = if c.is_simulated() || cfg.bus.sync == crate::config::SyncSource::External { c } else { real_clock() };
                what.push(w);
            }
            Err(e) => {
                eprintln!("error: {e}");
                return (exit::SETUP, None, RunSummary::default());
            }
        }
    }
    for (name, l) in &cfg.modbus {
        what.push(format!(
            "Modbus link {name} ({})",
            match l.transport {
                crate::config::LinkTransport::Tcp => format!("TCP {}", l.address.as_deref().unwrap_or("")),
                crate::config::LinkTransport::Rtu => format!("RTU {} {} baud", l.device.as_deref().unwrap_or(""), l.baud),
            }
        ));
    }
    let mut parts: Vec<&mut dyn DriveBus> = Vec::new();
    if let Some(m) = can.as_mut() {
        parts.push(m);
    }
    if !modbus.is_empty() {
        parts.push(&mut modbus);
    }
    let order: Vec<String> = cfg.axes.keys().cloned().collect();
    let mut drives = match crate::drives::multi::MultiBus::new(parts, &order) {
        Ok(d) => d,
        Err(a) => {
            eprintln!("{a}");
            return (exit::SETUP, None, RunSummary::default());
        }
    };
    let paced = (opts.pace || opts.live) && clock.is_simulated();
    eprintln!("cncgw: {} on {}{}", job.name, what.join(" + "), if paced { ", simulated time paced to the wall clock" } else { "" });
    if paced {
        let mut p = Paced::new(&mut *clock);
        p.live = opts.live;
        execute(&mut drives, &mut p, cfg, job, opts)
    } else {
        execute(&mut drives, &mut *clock, cfg, job, opts)
    }
}

/// A simulated clock that never runs ahead of the wall clock: an interactive run on the
/// embedded emulated machine happens at the speed a person sees, so feed hold lands
/// mid-program. (Simulated time still decides everything the drives do; only its pace
/// changes.)
pub struct Paced<'c> {
    inner: &'c mut dyn Clock,
    wall0: std::time::Instant,
    sim0: u64,
    /// Say "not simulated", so that the cycle loop takes moves as they come and holds the
    /// machine between them as in real time (MDI).
    pub live: bool,
}

impl<'c> Paced<'c> {
    pub fn new(inner: &'c mut dyn Clock) -> Self {
        let sim0 = inner.now_ns();
        Paced { inner, wall0: std::time::Instant::now(), sim0, live: false }
    }
}

impl Clock for Paced<'_> {
    fn now_ns(&self) -> u64 {
        self.inner.now_ns()
    }
    fn wait_until(&mut self, t_ns: u64) {
        let due = self.wall0 + std::time::Duration::from_nanos(t_ns.saturating_sub(self.sim0));
        let now = std::time::Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
        self.inner.wait_until(t_ns)
    }
    fn is_simulated(&self) -> bool {
        self.inner.is_simulated() && !self.live
    }
    fn poll_sync(&mut self) -> Option<u64> {
        self.inner.poll_sync()
    }
}

/// `cncgw trace plot FILE.csv -o FILE.svg`.
pub fn trace_plot(file: &Path, out: &Path) -> i32 {
    let text = match std::fs::read_to_string(file) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: cannot read {}: {e}", file.display());
            return exit::INPUT;
        }
    };
    let data = match TraceData::parse(&text) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: {}: {e}", file.display());
            return exit::INPUT;
        }
    };
    match crate::control::trace::plot_svg(&data, out) {
        Ok(()) => {
            eprintln!("wrote {}", out.display());
            exit::OK
        }
        Err(e) => {
            eprintln!("error: cannot draw {}: {e}", out.display());
            exit::SETUP
        }
    }
}

fn execute(
    drives: &mut dyn DriveBus,
    clock: &mut dyn Clock,
    cfg: &MachineConfig,
    mut job: Job,
    opts: &ExecOpts,
) -> (i32, Option<std::collections::HashMap<u32, f64>>, RunSummary) {
    let extras = &opts.extras;
    let mut lp = CycleLoop::from_config(drives, clock, cfg);
    if let Some(path) = extras.trace {
        match Trace::csv(path, lp.drive_names()) {
            Ok(t) => lp.set_trace(t),
            Err(e) => {
                eprintln!("error: cannot write the trace {}: {e}", path.display());
                return (exit::SETUP, None, RunSummary::default());
            }
        }
    }
    if let Some(p) = &opts.operator {
        lp.set_panel(p);
    }
    lp.set_signal(&super::term::SIGNAL, super::term::signal_name);
    let observer = match Observer::start(cfg, extras.opcua.as_ref(), &mut lp, &job) {
        Ok(o) => o,
        Err(e) => {
            eprintln!("error: {e}; nothing was moved");
            return (exit::SETUP, None, RunSummary::default());
        }
    };
    let mut summary = RunSummary::default();
    let start = match lp.start(&mut summary) {
        Ok(s) => s,
        Err(a) => {
            observer.alarm(&a);
            observer.finish();
            eprintln!("{a}");
            // A bus or Modbus link that cannot be opened is setup, as a CAN interface that
            // cannot be opened is; the drives' own refusals are alarms.
            let code = if matches!(a.number, crate::alarm::CAN_BUS | crate::alarm::MODBUS_LINK) { exit::SETUP } else { exit::ALARM };
            return (code, None, summary);
        }
    };
    let start_pos = crate::control::job::start_pos(&start);
    let mut interp = match job.first.take().map(Ok).unwrap_or_else(|| (job.make)(start_pos)) {
        Ok(i) => i,
        Err(alarms) => {
            lp.finish();
            for a in &alarms {
                eprintln!("{a}");
            }
            eprintln!("{} error(s); nothing was moved", alarms.len());
            return (exit::INPUT, None, summary);
        }
    };
    interp.set_start_position(start_pos);
    // The rigid-tap state: published by the cycle, written by its own thread (started
    // before the real-time setup below, so that it does not inherit it).
    let tap_writer = match start_tap_writer(&mut lp, extras, &start) {
        Ok(w) => w,
        Err(e) => {
            eprintln!("error: cannot start the rigid-tap state writer: {e}");
            lp.finish();
            return (exit::SETUP, None, summary);
        }
    };
    let checked = reference_at_start(&lp, cfg, extras.reference.as_ref()).and_then(|()| checks_before_motion(&mut lp, &job, cfg, &interp, start_pos));
    if let Err(a) = checked {
        observer.alarm(&a);
        lp.finish();
        summary.rest.at_rest = true; // nothing was moved
        if opts.print_summary {
            print_summary(&summary, opts.json, Some(&a));
        }
        record_alarm(extras, &job.name, &a);
        eprintln!("{a}");
        eprintln!("nothing was moved");
        observer.finish();
        return (exit::ALARM, None, summary);
    }
    // The interpreter runs ahead of motion, macro statements included (as on a Fanuc, where
    // macro statements are executed while the blocks before them are buffered).
    let it: Box<dyn MoveFeed> = match job.feed.take() {
        Some(f) => f(interp, start_pos),
        None => Box::new(interp),
    };
    let feed = match crate::control::job::Feed::spawn(it) {
        Ok(f) => f,
        Err(a) => {
            eprintln!("error: {a}");
            lp.finish();
            return (exit::SETUP, None, summary);
        }
    };
    let lines: Vec<&str> = job.source.lines().collect();
    let mut display = Display::new(opts, &lines);
    // The cycle loop runs on this thread; set it up only now, so that the interpreter and
    // trace threads (already started) do not inherit the real-time policy or the pinning.
    for step in crate::control::rt::apply(&extras.rt) {
        match step {
            RtStep::Done(m) => eprintln!("cncgw: {m}"),
            RtStep::Refused(m) | RtStep::Warn(m) => eprintln!("warning: {m}"),
        }
    }
    let (r, vars) = feed.run(&mut lp, start, &mut summary, &mut |p| display.show(p), opts.live);
    display.close();
    lp.finish();
    reference_at_end(&lp, cfg, extras.reference.as_ref());
    if let Err(a) = &r {
        observer.alarm(a);
    }
    let tap_failed = close_writers(&mut lp, tap_writer);
    let code = outcome(r, &summary, opts, &job.name);
    observer.finish();
    (if tap_failed && code == exit::OK { exit::SETUP } else { code }, vars, summary)
}

/// The rigid-tap state writer of a run with a tap-state file (`extras.tap`), its watch set
/// on the loop. A run that starts with the tool in a hole says how far the spindle stands
/// from the stored thread.
fn start_tap_writer(
    lp: &mut CycleLoop,
    extras: &RunExtras,
    start: &[f64; crate::motion::N_AXES],
) -> std::io::Result<Option<crate::control::tapstate::TapPersister>> {
    let Some(TapSetup { file, loaded }) = extras.tap.clone() else { return Ok(None) };
    if let Some(st) = loaded.filter(|s| s.in_hole) {
        let ax = match st.axis {
            'X' => AX_X,
            'Y' => AX_Y,
            _ => AX_Z,
        };
        // On a real machine the thread holds tap and spindle together; a spindle turned
        // against the axis since (by hand, or drives that stopped each on its own ramp)
        // shows here. The return takes the angle it finds as the thread's reference.
        eprintln!(
            "cncgw: tap return from {} {:.4} mm: the spindle stands {:.2}° from the thread stored at the interruption",
            st.axis,
            start[ax],
            st.phase_error_deg(start[ax], start[AX_S])
        );
    }
    let slot = crate::control::tapstate::TapSlot::new(loaded);
    let file = crate::persist::TapStateFile { path: file };
    let w = crate::control::tapstate::TapPersister::spawn(file, slot.clone(), std::time::Duration::from_millis(TAP_STATE_PERIOD_MS), loaded)?;
    lp.set_tap_watch(crate::control::tapstate::TapWatch::new(slot, Some(w.thread()), start, loaded));
    Ok(Some(w))
}

/// What is checked before anything moves: the spindle-synchronised moves against the cycle
/// of every axis on a link with its own cycle (Modbus), then the program's whole path
/// against the travel limits and the G22 area.
fn checks_before_motion(lp: &mut CycleLoop, job: &Job, cfg: &MachineConfig, interp: &Interpreter, start_pos: Pos) -> Result<(), crate::Alarm> {
    let mut slow = Vec::new();
    for d in 0..lp.drives.axis_count() {
        if let Some((link, link_what, cycle_s)) = lp.drives.link_cycle(d) {
            let name = lp.drives.axis_name(d).to_string();
            eprintln!("cncgw: axis {name}: Modbus link {link} ({link_what}), link cycle {:.0} ms", cycle_s * 1e3);
            let axis = if Some(d) == cfg.spindle_index() { "s".to_string() } else { name };
            slow.push(crate::sync::link_check::SlowAxis { axis, link, cycle_s });
        }
    }
    if !slow.is_empty() {
        check_links(job, cfg, &slow, start_pos)?;
        spindle_control(lp, job, cfg, start_pos);
    }
    let Ok(mut pre) = (job.make)(start_pos) else { return Ok(()) };
    pre.set_start_position(start_pos);
    pre.set_common_vars(interp.common_vars().clone());
    pre.set_tap_return(interp.tap_return());
    let tool = crate::motion::polygon::ToolSpindle::from_config(cfg);
    crate::control::guard::check_program_with(pre, &Limits::from_config(cfg), start_pos, tool.as_ref(), 2_000_000)
}

/// Close the trace and the rigid-tap state writer, saying what they wrote; true if the tap
/// state could not be stored.
fn close_writers(lp: &mut CycleLoop, tap_writer: Option<crate::control::tapstate::TapPersister>) -> bool {
    let tap_failed = match tap_writer.map(|w| w.finish()) {
        Some(st) if st.failures > 0 => {
            eprintln!("error: the rigid-tap state could not be stored {} time(s): {}", st.failures, st.last_error.unwrap_or_default());
            true
        }
        _ => false,
    };
    if let Some(t) = lp.take_trace() {
        match t.finish() {
            Ok(st) if st.dropped > 0 => {
                eprintln!("trace: {} cycles written, {} lost (the disk was too slow)", st.rows, st.dropped)
            }
            Ok(st) => eprintln!("trace: {} cycles written", st.rows),
            Err(e) => eprintln!("error: writing the trace: {e}"),
        }
    }
    tap_failed
}

/// The run's end as the operator reads it (summary, alarm, rest) and its exit code.
fn outcome(r: Result<(), crate::Alarm>, summary: &RunSummary, opts: &ExecOpts, name: &str) -> i32 {
    match r {
        Err(a) => {
            if opts.print_summary {
                print_summary(summary, opts.json, Some(&a));
            }
            record_alarm(&opts.extras, name, &a);
            eprintln!("{a}");
            let when = if summary.ended { "the program had reached its end" } else { "the program stopped at this alarm" };
            eprintln!("{when}; {}", summary.rest.describe());
            if let Some(h) = following_error_hint(&a, summary) {
                eprintln!("{h}");
            }
            // Hunts before the alarm (one still going on at it is in its message).
            for t in summary.axes.iter().filter(|x| x.hunt.is_some_and(|h| !h.at_alarm)).filter_map(|x| x.hunt_text()) {
                eprintln!("warning: {t}");
            }
            exit::ALARM
        }
        Ok(()) => {
            if opts.print_summary {
                print_summary(summary, opts.json, None);
            }
            if !summary.rest.at_rest || summary.rest.quick_stop {
                eprintln!("warning: {}", summary.rest.describe());
            }
            for t in summary.axes.iter().filter_map(|a| a.hunt_text()) {
                eprintln!("warning: {t}");
            }
            if summary.at_program_end() {
                exit::OK
            } else {
                eprintln!("error: an axis did not reach the program's end point within its in-position width (axes.NAME.in_position)");
                for t in summary.axes.iter().filter_map(|a| a.settle_text()) {
                    eprintln!("  {t}");
                }
                exit::NOT_MET
            }
        }
    }
}

/// An axis' in-position width in its operator units, e.g. "0.0100 mm" (`AxisSummary::units`).
fn pos_width(a: &AxisSummary) -> String {
    let (unit, diameter, k) = a.units();
    let on = if diameter { " on the diameter" } else { "" };
    format!("{:.4} {unit}{on}", a.in_position_counts as f64 * k)
}

/// A drive that faulted its following-error window (EMCY 0x8611): how far behind the run saw
/// it and what to do — a soft drive's lag grows with its speed, and a window that suits
/// another drive trips it at full speed (a spindle on Kv 8.7/s with 95 % feed-forward lags
/// some 200° at S6000).
fn following_error_hint(a: &crate::Alarm, summary: &RunSummary) -> Option<String> {
    if a.number != crate::alarm::DRIVE_FAULT || !a.message.contains("0x8611") {
        return None;
    }
    let name = a.message.split("(axis ").nth(1)?.split(')').next()?;
    let ax = summary.axes.iter().find(|x| x.name == name)?;
    // A hunt that tripped it is named in the alarm (`AxisSummary::hunt_text`): not lag.
    if ax.hunt.is_some_and(|h| h.at_alarm) {
        return None;
    }
    let (unit, ..) = axis_units(ax);
    Some(format!(
        "hint: axis {name} was up to {:.3} {unit} behind its set-points in this run (as the controller reads it, the feedback's delay included); if that is its lag at speed rather than a jam, its window (0x6065, axes.{name}.following_error) is too small for its drive — `cncgw identify {name}` measures the lag and proposes a window, `cncgw config check` warns below it",
        ax.max_following_error
    ))
}

/// How often the rigid-tap state is written while the tool moves in a hole (ms).
pub const TAP_STATE_PERIOD_MS: u64 = 20;

/// With the tool in a tapped hole, the program's first motion must be the G30 P99 return
/// (`control::tapstate::check_return_first`).
fn check_tap_return_program(pre: Result<Interpreter, Vec<crate::Alarm>>, st: &crate::persist::TapState) -> Result<(), crate::Alarm> {
    let mut pre = pre.map_err(|a| {
        a.into_iter().next().unwrap_or_else(|| crate::Alarm::new(crate::control::tapstate::TAP_IN_HOLE, "the program cannot be read"))
    })?;
    pre.set_tap_return(Some(st.tap_return()));
    let mut p = Pos::ZERO;
    match st.axis {
        'X' => p.x = st.position,
        'Y' => p.y = st.position,
        _ => p.z = st.position,
    }
    pre.set_start_position(p);
    crate::control::tapstate::check_return_first(st, pre)
}

enum Display {
    Bar(indicatif::ProgressBar),
    Panel(super::term::PanelDisplay),
}

impl Display {
    /// The operator panel's status lines, or a progress bar (hidden for MDI, where the
    /// prompt is).
    fn new(opts: &ExecOpts, lines: &[&str]) -> Display {
        match &opts.operator {
            Some(p) => Display::Panel(super::term::PanelDisplay::new(p.clone(), lines)),
            None if opts.live => Display::Bar(indicatif::ProgressBar::hidden()),
            None => {
                let bar = indicatif::ProgressBar::new((lines.len() as u64).max(1));
                bar.set_style(
                    indicatif::ProgressStyle::with_template("{spinner} {elapsed_precise} line {pos}/{len} {wide_bar} {msg}")
                        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                );
                Display::Bar(bar)
            }
        }
    }

    fn show(&mut self, p: &crate::control::cycle::Progress) {
        match self {
            Display::Bar(bar) => {
                bar.set_position(p.line as u64);
                let (x, z, f, s) = (p.pos[AX_X] * 2.0, p.pos[AX_Z], p.feed, p.spindle_rpm);
                bar.set_message(format!("X{x:.3} Z{z:.3} F{f:.0} S{s:.0} sync {:.1} µm", p.sync_err_um));
            }
            Display::Panel(d) => d.show(p),
        }
    }

    fn close(self) {
        match self {
            Display::Bar(bar) => bar.finish_and_clear(),
            Display::Panel(mut d) => d.close(),
        }
    }
}

/// Run the interpreter over the whole program once and check each synchronised move
/// against the slow links (bounded: a program that never ends is checked as it runs up to
/// two million moves).
fn check_links(job: &Job, cfg: &MachineConfig, slow: &[crate::sync::link_check::SlowAxis], start: Pos) -> Result<(), crate::Alarm> {
    let Ok(mut pre) = (job.make)(start) else { return Ok(()) };
    pre.set_start_position(start);
    let mut check = crate::sync::link_check::LinkCheck::new(slow, cfg.machine.sync_error_limit_um, start);
    for m in pre.take(2_000_000) {
        match m {
            Ok(m) => check.check(&m)?,
            Err(_) => break, // the run itself reports program alarms at their block
        }
    }
    Ok(())
}

/// A work spindle on a link with its own cycle (Modbus) runs in speed unless the program
/// steers its angle (Cs, rigid tap, G92.1, polar, polygon): a position set-point once per
/// link cycle (45 ms on RTU) at 1500 rpm is 400° of travel per cycle, which no honest
/// following-error window holds. In position, the window follows from the link cycle and
/// the program's highest speed (`SpindleUse::position_window`); the taps and G92.1 threads
/// the link cannot hold in sync were refused just before (alarm 2203, `check_links`).
fn spindle_control(lp: &mut CycleLoop, job: &Job, cfg: &MachineConfig, start: Pos) {
    use crate::drives::SpindleControl;
    let Some(sd) = cfg.spindle_index() else { return };
    let Some((link, _, cycle_s)) = lp.drives.link_cycle(sd) else { return };
    let Some(axis) = cfg.axes.values().nth(sd) else { return };
    let Ok(mut pre) = (job.make)(start) else { return };
    pre.set_start_position(start);
    let u = crate::sync::link_check::SpindleUse::scan(pre.take(2_000_000).map_while(Result::ok), axis.max_speed);
    let name = lp.drives.axis_name(sd).to_string();
    let window = u.position_window(axis.following_error, cycle_s);
    let why = match &u.position {
        None if lp.drives.set_spindle_control(sd, SpindleControl::Speed) => {
            eprintln!("cncgw: spindle {name}: in speed (cyclic synchronous velocity) over link {link}: the program does not steer its angle");
            return;
        }
        None => "its drive has no speed mode (a pr map)".to_string(),
        Some(what) => format!("{what} steers its angle"),
    };
    if lp.drives.set_spindle_control(sd, SpindleControl::Position { window }) {
        eprintln!(
            "cncgw: spindle {name}: in position over link {link} ({why}), following-error window {window:.0}° (configured {:.0}° + two {:.0} ms link cycles at {:.0} rpm)",
            axis.following_error,
            cycle_s * 1e3,
            u.max_rpm
        );
    } else {
        eprintln!("cncgw: spindle {name}: in position over link {link} ({why}); its drive has no following-error window register");
    }
}

/// The alarm that ended a run, for the summary: number, text, and the line it names.
fn alarm_json(a: Option<&crate::Alarm>) -> serde_json::Value {
    match a {
        Some(a) => serde_json::json!({
            "number": a.number,
            "message": a.message,
            "file": a.pos.as_ref().map(|p| p.file.to_string()),
            "line": a.pos.as_ref().map(|p| p.line),
        }),
        None => serde_json::Value::Null,
    }
}

/// An axis' positions in the operator's units (`AxisSummary::units`): (unit, diameter?,
/// counts → that unit).
fn axis_units(a: &AxisSummary) -> (&'static str, bool, impl Fn(i64) -> f64) {
    let (unit, diameter, k) = a.units();
    (unit, diameter, move |c: i64| c as f64 * k)
}

fn print_summary(s: &RunSummary, json: bool, alarm: Option<&crate::Alarm>) {
    if json {
        let axes: Vec<_> = s
            .axes
            .iter()
            .map(|a| {
                let (unit, diameter, at) = axis_units(a);
                serde_json::json!({
                    "axis": a.name,
                    "unit": unit,
                    "diameter": diameter,
                    "max_following_error": a.max_following_error,
                    "final_actual": at(a.final_actual_counts),
                    "final_target": at(a.final_target_counts),
                    "program_end": a.program_end_counts.map(&at),
                    "final_actual_counts": a.final_actual_counts,
                    "final_target_counts": a.final_target_counts,
                    "program_end_counts": a.program_end_counts,
                    "in_position_counts": a.in_position_counts,
                    "in_position": a.in_position(),
                    "settle_miss": a.settle_miss.map(|m| serde_json::json!({
                        "off_counts": m.off_counts, "step_counts": m.step_counts, "crossings": m.crossings,
                        "peak_counts": m.peak_counts, "hunt_hz": m.hunt_hz, "resolved": m.resolved, "waited_s": m.waited_s, "hunts": m.hunts(),
                    })),
                    "hunt": a.hunt.map(|h| serde_json::json!({
                        "line": h.line, "at_alarm": h.at_alarm, "crossings": h.miss.crossings, "peak_counts": h.miss.peak_counts,
                        "hunt_hz": h.miss.hunt_hz, "resolved": h.miss.resolved, "stood_s": h.miss.waited_s,
                    })),
                })
            })
            .collect();
        let v = serde_json::json!({
            "blocks": s.blocks,
            "moves": s.moves,
            "machining_time_s": s.machining_time_s,
            "enable_time_s": s.enable_time_s,
            "cycles": s.cycles,
            "overruns": s.overruns,
            "simulated": s.simulated,
            "at_program_end": s.at_program_end(),
            "ended_at_m02_m30": s.ended,
            "alarm": alarm_json(alarm),
            "rest": {
                "at_rest": s.rest.at_rest,
                "quick_stop": s.rest.quick_stop,
                "timed_out": s.rest.timed_out,
                "time_s": s.rest.time_s,
                "fault_reaction": s.rest.fault_reaction,
                "spindle_rpm_at_torque_off": s.rest.spindle_rpm_at_off,
            },
            "spindle_accel_managed_rpm_s": s.spindle_accel_rpm_s,
            "spindle_accel_at_torque_limit": s.spindle_accel_at_torque_limit,
            "spindle_overload_accel_rpm_s": s.spindle_overload_rpm_s,
            "axes": axes,
        });
        println!("{v}");
        return;
    }
    if let Some(a) = alarm {
        println!("stopped by alarm {:04}{}", a.number, a.pos.as_ref().map_or(String::new(), |p| format!(" at {p}")));
    }
    println!(
        "blocks {}  moves {}  machining time {:.3} s{}  cycles {} (overruns {})  drives enabled after {:.3} s",
        s.blocks,
        s.moves,
        s.machining_time_s,
        if s.simulated { " (simulated)" } else { "" },
        s.cycles,
        s.overruns,
        s.enable_time_s
    );
    if let Some(a) = s.spindle_accel_rpm_s.filter(|_| s.spindle_accel_at_torque_limit) {
        println!(
            "spindle: its drive reached its torque limit (max torque 0x6072) accelerating it, with nothing left to follow its set-points: about {a:.0} rpm/s at the limit; the run planned with 80 % of that from then on — set the spindle's max_accel (and No.5261/5271) lower, or give it more torque"
        );
    } else if let Some(a) = s.spindle_accel_rpm_s {
        println!(
            "spindle: it managed only {a:.0} rpm/s of the acceleration asked of it; the run planned with 80 % of that from then on — set the spindle's max_accel (and No.5261/5271) to what it can do, or check its drive's torque limit"
        );
    }
    if let Some(a) = s.spindle_overload_rpm_s {
        println!(
            "spindle: its amplifier's overload load (I²t, axes.NAME.overload_pct/overload_s) passed a quarter of its rating; the run planned with {a:.0} rpm/s from then on, near 150 % of its rated torque — set the spindle's max_accel (and No.5261/5271) lower, or give taps time to cool"
        );
    }
    println!(
        "{:<5} {:>18} {:>18} {:>18} {:>18}  result (positions: X as a diameter)",
        "axis", "max follow. error", "final actual", "final target", "program end"
    );
    for a in &s.axes {
        let (unit, _, at) = axis_units(a);
        let pos = |c: i64| format!("{:.4} {unit}", at(c));
        let (end, ok) = match a.program_end_counts {
            Some(e) => (
                pos(e),
                match a.final_actual_counts - e {
                    off if off.abs() <= 1 => "ok (within 1 count)".to_string(),
                    off if a.in_position() => format!("ok ({off} counts off, in position: within {})", pos_width(a)),
                    off => format!("NOT AT END POINT ({off} counts off, in-position width {})", pos_width(a)),
                },
            ),
            None => ("-".to_string(), "-".to_string()),
        };
        println!(
            "{:<5} {:>18} {:>18} {:>18} {:>18}  {}",
            a.name,
            format!("{:.4} {unit}", a.max_following_error),
            pos(a.final_actual_counts),
            pos(a.final_target_counts),
            end,
            ok
        );
    }
}
