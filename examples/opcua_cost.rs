//! What the OPC UA server costs the cycle (issue 26): the cycle loop (`CycleLoop`, as `cncgw
//! run`) drives a program against the emulated drives in this process (`sim_drives`, the
//! in-process bus) on the **wall clock**, three times back to back:
//!
//! 1. no server (no snapshot published: `[opcua]` absent);
//! 2. the server on (the snapshot published every cycle, the server's task copying it every
//!    50 ms), no client;
//! 3. the server on with 10 asyncua clients (examples/opcua_clients.py in build/venv, one
//!    process, a session and a 100 ms subscription each: 16 variables and the events);
//! 4. the same 10 clients on Basic256Sha256 Sign&Encrypt (their certificate made by the
//!    script and trusted in the server's PKI).
//!
//! Printed per run: the cycle's work (wake-up to the next wait: computing, the bus, the
//! snapshot's publish) and the wake-up lateness, p50/p99/max in µs, missed cycles; the
//! process's RSS after the run; the clients' notifications. Figures of a real-time loop on
//! whatever machine runs it: on a shared, loaded 2-vCPU VM they move with the load (run the
//! cases back to back, compare within one invocation). The server offers None on loopback
//! and Basic256Sha256 Sign&Encrypt, anonymous; runs 2 and 3 use None, run 4 Sign&Encrypt
//! (what it costs is the server's and the clients' CPU, not the cycle thread's code).
//!
//!     cargo run --release --example opcua_cost -- [--seconds 30] [--clients 10]

use cncgw::config::{AxisKind, MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::Feed;
use cncgw::control::snapshot::Snapshot;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::{CanBus, Clock, RealClock};
use std::io::BufRead;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};

/// The wall clock, timing each cycle's work (wake-up → next wait) and each wake-up's lateness
/// once `armed`, into buffers allocated up front.
struct TimedClock {
    inner: RealClock,
    armed: Arc<AtomicBool>,
    woke: Option<u64>,
    work: Vec<u64>,
    late: Vec<u64>,
}

impl Clock for TimedClock {
    fn now_ns(&self) -> u64 {
        self.inner.now_ns()
    }
    fn wait_until(&mut self, t_ns: u64) {
        let armed = self.armed.load(Ordering::Relaxed);
        if let (true, Some(w)) = (armed, self.woke) {
            if self.work.len() < self.work.capacity() {
                self.work.push(self.inner.now_ns().saturating_sub(w));
            }
        }
        self.inner.wait_until(t_ns);
        let now = self.inner.now_ns();
        self.woke = Some(now);
        if armed && self.late.len() < self.late.capacity() {
            self.late.push(now.saturating_sub(t_ns));
        }
    }
}

fn pct(v: &mut [u64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize] as f64 / 1000.0
}

/// Z strokes under S500 for about `seconds` (as examples/jitter.rs).
fn program(seconds: f64) -> String {
    let mut p = String::from("G21\nG98\nM03 S500\nG00 X40 Z2\n");
    for _ in 0..(seconds / 1.9).ceil().max(1.0) as usize {
        p += "G01 Z-48 F3000\nG01 X42 Z2\nG01 X40\n";
    }
    p + "G00 X100 Z5\nM05\nM30\n"
}

fn rss_mib() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kib = s.lines().find(|l| l.starts_with("VmRSS:")).and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok()).unwrap_or(0.0);
    kib / 1024.0
}

struct Figures {
    summary: RunSummary,
    work: Vec<u64>,
    late: Vec<u64>,
    result: Result<(), String>,
}

/// The embedded lathe with the shared-host tolerances of examples/jitter.rs (a stall is
/// measured, not a fault).
fn config(port: u16) -> MachineConfig {
    let mut cfg = MachineConfig::embedded();
    cfg.bus.feedback_timeout_ms = 100.0;
    cfg.machine.watchdog_overruns = 0;
    cfg.machine.watchdog_missed_cycles = 50;
    for a in cfg.axes.values_mut() {
        a.following_error = if a.kind == AxisKind::Spindle { 720.0 } else { 5.0 };
    }
    cfg.opcua.host = "127.0.0.1".into();
    cfg.opcua.port = port;
    cfg.opcua.security_policies = vec!["none".into(), "basic256sha256".into()];
    cfg.opcua.allow_none_on_loopback = true;
    cfg.opcua.anonymous = true;
    cfg
}

/// One run on its own thread; `snap`: publish into it, after telling `ready` the drive names
/// are set and waiting for `go` (the server and its clients start in between).
fn run(cfg: &MachineConfig, seconds: f64, snap: Option<Arc<Snapshot>>, ready: mpsc::Sender<()>, go: mpsc::Receiver<()>) -> Figures {
    let wire = InprocBus::new();
    let stop = Arc::new(AtomicBool::new(false));
    let sim_bus: Box<dyn CanBus> = Box::new(wire.endpoint());
    let sim_stop = stop.clone();
    let sim =
        std::thread::spawn(move || sim_drives::run_realtime(sim_bus, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(), sim_stop));
    let cfg = cfg.clone();
    let bus: Box<dyn CanBus> = Box::new(wire.endpoint());
    let r = std::thread::spawn(move || {
        let period = (cfg.machine.cycle_ms * 1e6) as u64;
        let cycles = (seconds * 1000.0 / cfg.machine.cycle_ms) as usize + 20_000;
        let armed = Arc::new(AtomicBool::new(false));
        let mut clock = TimedClock {
            inner: RealClock::new(),
            armed: armed.clone(),
            woke: None,
            work: Vec::with_capacity(cycles),
            late: Vec::with_capacity(cycles),
        };
        let src = program(seconds);
        let interp = Interpreter::from_source("opcua_cost.nc", &src, &cfg).map_err(|a| format!("{a:?}"))?;
        let mut master = CanOpenMaster::new(bus, &cfg);
        let spindle = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
        if let Some(s) = &snap {
            s.set_program("opcua_cost.nc", src.lines().count() as u32, (0..master.axis_count()).map(|d| master.axis_name(d).to_string()).collect());
        }
        let _ = ready.send(());
        let _ = go.recv();
        let mut summary = RunSummary::default();
        let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), spindle, period);
        lp.set_watchdog(cncgw::control::cycle::Watchdog::from_config(&cfg));
        if let Some(s) = snap {
            lp.set_snapshot(s);
        }
        let r = lp.start(&mut summary).and_then(|start| {
            let feed = Feed::interpreter(interp, &start)?;
            armed.store(true, Ordering::Relaxed);
            feed.run(&mut lp, start, &mut summary, &mut |_| {}, false).0
        });
        lp.finish();
        Ok::<_, String>(Figures { summary, work: clock.work, late: clock.late, result: r.map_err(|a| a.to_string()) })
    })
    .join();
    stop.store(true, Ordering::Relaxed);
    let _ = sim.join();
    match r {
        Ok(Ok(f)) => f,
        Ok(Err(e)) => Figures { summary: RunSummary::default(), work: vec![], late: vec![], result: Err(e) },
        Err(_) => Figures { summary: RunSummary::default(), work: vec![], late: vec![], result: Err("the run's thread panicked".into()) },
    }
}

fn report(what: &str, cycle_ms: f64, mut f: Figures, extra: &str) {
    println!(
        "{what:<28} {cycle_ms} ms {:>7} cycles | cycle work p50 {:>6.1} p99 {:>6.1} max {:>8.1} µs | wake-up late p50 {:>6.1} p99 {:>7.1} max {:>8.1} µs | missed {} | RSS {:.1} MiB{extra}{}",
        f.summary.cycles,
        pct(&mut f.work, 0.5),
        pct(&mut f.work, 0.99),
        pct(&mut f.work, 1.0),
        pct(&mut f.late, 0.5),
        pct(&mut f.late, 0.99),
        pct(&mut f.late, 1.0),
        f.summary.overruns,
        rss_mib(),
        match &f.result {
            Ok(()) => String::new(),
            Err(e) => format!(" [stopped: {e}]"),
        }
    );
}

fn main() {
    let (mut seconds, mut clients) = (30.0, 10usize);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seconds" => seconds = args.next().and_then(|v| v.parse().ok()).unwrap_or(30.0),
            "--clients" => clients = args.next().and_then(|v| v.parse().ok()).unwrap_or(10),
            _ => eprintln!("unknown argument {a}"),
        }
    }
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let python = root.join("build/venv/bin/python");
    let state = std::env::temp_dir().join(format!("cncgw_opcua_cost_{}", std::process::id()));
    let port = std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).unwrap_or(48_400);
    let cfg = config(port);
    println!(
        "{} s per run, cycle {} ms, in-process emulated drives on the wall clock; RSS 0 = before any run: {:.1} MiB",
        seconds,
        cfg.machine.cycle_ms,
        rss_mib()
    );
    let runs = [
        ("no server", false, 0, false),
        ("server, no client", true, 0, false),
        ("server + clients", true, clients, false),
        ("server + clients, S&E", true, clients, true),
    ];
    for (label, server, n, secure) in runs {
        let (ready_tx, ready_rx) = mpsc::channel();
        let (go_tx, go_rx) = mpsc::channel();
        let snap = server.then(|| Arc::new(Snapshot::new()));
        let cfg2 = cfg.clone();
        let snap2 = snap.clone();
        let runner = std::thread::spawn(move || run(&cfg2, seconds, snap2, ready_tx, go_rx));
        let _ = ready_rx.recv();
        let mut srv = None;
        let mut child = None;
        if let Some(s) = &snap {
            match cncgw::opcua::OpcUaServer::start(&cfg, "embedded", s.clone(), &state) {
                Ok(v) => srv = Some(v),
                Err(e) => eprintln!("{e}"),
            }
        }
        if n > 0 {
            let url = format!("opc.tcp://127.0.0.1:{port}/");
            let pki = state.join("opcua/pki");
            let spawned = Command::new(&python)
                .arg(root.join("examples/opcua_clients.py"))
                .args([url.as_str(), &n.to_string(), &format!("{}", seconds + 8.0), cfg.machine.name.as_str()])
                .args(secure.then_some(&pki))
                .stdout(Stdio::piped())
                .spawn();
            match spawned {
                Ok(mut c) => {
                    let mut out = std::io::BufReader::new(c.stdout.take().unwrap());
                    let mut line = String::new();
                    let _ = out.read_line(&mut line);
                    eprintln!("clients: {}", line.trim());
                    child = Some((c, out));
                }
                Err(e) => eprintln!("cannot start {}: {e} (scripts/install-test-deps.sh --python)", python.display()),
            }
        }
        let _ = go_tx.send(());
        let f =
            runner.join().unwrap_or_else(|_| Figures { summary: RunSummary::default(), work: vec![], late: vec![], result: Err("panicked".into()) });
        let rss = rss_mib();
        let mut extra = String::new();
        if let Some((mut c, mut out)) = child {
            let mut line = String::new();
            let _ = out.read_line(&mut line);
            let _ = c.wait();
            extra = format!(" | clients: {}", line.trim());
        }
        report(label, cfg.machine.cycle_ms, f, &format!(" (at the run's end {rss:.1}){extra}"));
        if let Some(s) = srv {
            s.finish();
        }
    }
    let _ = std::fs::remove_dir_all(&state);
}
