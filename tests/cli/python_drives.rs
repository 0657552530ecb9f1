//! Drives we did not write in Rust: python `canopen` LocalNodes (tests/python/canopen_drive.py)
//! shaped like commercial drives, on a socketcand bus on loopback, driven by `cncgw run
//! examples/first_part.nc` in real time — a second opinion to sim-drives' `[drive.shape]`
//! (tests/sim/startup_shapes.rs). Either the program runs to its end point on the drives' own
//! positions, or it stops before any motion with an alarm that says what the drive is.
//!
//! Needs the project venv (`scripts/install-test-deps.sh --python`); without it this test
//! FAILS naming that command; CNCGW_SKIP_PYTHON=1 skips it deliberately.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The project venv's python, or None when CNCGW_SKIP_PYTHON=1 skips python tests on
/// purpose (never on CI); a missing venv fails naming the command that makes it.
fn venv_python() -> Option<PathBuf> {
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") && !ci {
        eprintln!("CNCGW_SKIP_PYTHON=1: python drives test skipped on request");
        return None;
    }
    let python = root().join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python`, or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );
    Some(python)
}

/// A socketcand bus with no emulated drive on it (sim-drives' server as the hub).
fn hub() -> (String, Arc<AtomicBool>, std::thread::JoinHandle<()>) {
    hub_at(None)
}

/// `hub`, its thread under SCHED_FIFO `priority` where this machine allows it (a hub that
/// forwards frames late makes every drive's TPDO late).
fn hub_at(priority: Option<i32>) -> (String, Arc<AtomicBool>, std::thread::JoinHandle<()>) {
    // The server's accept and client threads start in `bind` and inherit this thread's policy.
    let fifo = |p: i32| {
        let param = libc::sched_param { sched_priority: p };
        // SAFETY: sets the calling thread's own scheduling; a refusal (no permission) is ignored.
        unsafe { libc::sched_setscheduler(0, if p > 0 { libc::SCHED_FIFO } else { libc::SCHED_OTHER }, &param) };
    };
    if let Some(p) = priority {
        fifo(p);
    }
    let server = sim_drives::socketcand::SocketcandServer::bind("127.0.0.1:0", "can0").expect("bind");
    if priority.is_some() {
        fifo(0);
    }
    let addr = server.local_addr().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let cfg = sim_drives::SimConfig { drives: Vec::new(), step_us: 50 };
    let t = std::thread::spawn(move || {
        if let Some(p) = priority {
            fifo(p);
        }
        let _ = sim_drives::run_realtime(Box::new(server), cfg, s);
    });
    (addr, stop, t)
}

struct Outcome {
    code: i32,
    stdout: String,
    stderr: String,
    /// Per node (1, 2, 3): the python drive's report.
    drives: Vec<serde_json::Value>,
}

/// `cncgw run --batch examples/first_part.nc` against three python drives of `shape`.
fn run(python: &PathBuf, shape: &str) -> Outcome {
    run_cfg(python, shape, |c| c)
}

/// `python` running tests/python/canopen_drive.py's `shape` on the hub at `port`, once it
/// said it is ready; its standard output (the drives' final state, one JSON line each).
fn start_drives(mut python: Command, port: &str, shape: &str) -> (std::process::Child, BufReader<std::process::ChildStdout>) {
    let mut py = python
        .arg(root().join("tests/python/canopen_drive.py"))
        .args(["127.0.0.1", port, shape])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start python");
    let mut out = BufReader::new(py.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    assert_eq!(line.trim(), "ready", "python drives did not start");
    (py, out)
}

/// `run` with the machine configuration changed by `edit`.
fn run_cfg(python: &PathBuf, shape: &str, edit: impl Fn(String) -> String) -> Outcome {
    let (addr, stop, hub) = hub();
    let port = addr.rsplit_once(':').unwrap().1.to_string();
    let (mut py, out) = start_drives(Command::new(python), &port, shape);
    let dir = std::env::temp_dir().join(format!("cncgw_python_drives_{shape}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Python handles every SYNC and PDO in one interpreter: a 5 ms cycle, and feedback may
    // be 100 ms old before it counts as lost.
    let cfg =
        cncgw::config::EMBEDDED_LATHE.replace("cycle_ms = 2.0", "cycle_ms = 5.0").replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 100");
    assert_ne!(cfg, cncgw::config::EMBEDDED_LATHE);
    let cfg = edit(cfg);
    std::fs::write(dir.join("machine.toml"), cfg).unwrap();
    let started = Instant::now();
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        // -v: the start-up lines (mode, mapping, error control per drive) the tests read.
        .args(["-v", "run", "--batch", "--bus", &format!("socketcand://{addr}/can0"), "--config"])
        .arg(dir.join("machine.toml"))
        .arg(root().join("examples/first_part.nc"))
        .env("CNCGW_STATE_DIR", &dir)
        .env_remove("RUST_LOG")
        .output()
        .expect("run cncgw");
    eprintln!("{shape}: cncgw ran {:.1} s", started.elapsed().as_secs_f64());
    // SAFETY: a signal to our own child process.
    unsafe {
        libc::kill(py.id() as i32, libc::SIGTERM);
    }
    let mut drives = Vec::new();
    for l in out.lines().map_while(Result::ok) {
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&l) {
            drives.push(v);
        }
    }
    let _ = py.wait();
    let mut perr = String::new();
    if let Some(mut e) = py.stderr.take() {
        let _ = std::io::Read::read_to_string(&mut e, &mut perr);
    }
    stop.store(true, Ordering::Relaxed);
    let _ = hub.join();
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(drives.len(), 3, "python drives' report missing: {perr}");
    Outcome {
        code: o.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        drives,
    }
}

impl Outcome {
    fn enabled_modes(&self, node: usize) -> Vec<i64> {
        self.drives[node - 1]["enabled_modes"].as_array().unwrap().iter().map(|v| v.as_i64().unwrap()).collect()
    }
    fn position(&self, node: usize) -> i64 {
        self.drives[node - 1]["position"].as_i64().unwrap()
    }
    /// The drive's own position actual 0x6064, in its position units.
    fn position_actual(&self, node: usize) -> i64 {
        self.drives[node - 1]["position_actual"].as_i64().unwrap()
    }
    /// cncgw's start-up line for `node`: which mode, mapping, error control and units it
    /// chose and why.
    fn startup_line(&self, node: usize) -> &str {
        self.stderr
            .lines()
            .find(|l| l.contains("start-up: mode") && l.contains(&format!("node={node}")))
            .unwrap_or_else(|| panic!("no start-up line for node {node}: {}", self.stderr))
    }
    fn nothing_moved(&self) {
        for n in 1..=3 {
            assert!(self.enabled_modes(n).is_empty(), "node {n} was enabled: {:?}", self.drives);
            assert_eq!(self.position(n), 0, "node {n} moved");
        }
    }
}

#[test]
fn realtime_python_drives_shaped_like_commercial_ones() {
    let Some(python) = venv_python() else { return };

    // Boots in profile position, switches 300 ms and 50 SYNCs after being asked.
    let o = run(&python, "pp_boot");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![8], "node {n} was enabled in another mode than CSP");
    }
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");
    for n in 1..=3 {
        let l = o.startup_line(n);
        assert!(
            l.contains("start-up: mode CSP (cyclic synchronous position) (the default), booted in profile position (1) and switched by 0x6060"),
            "{l}"
        );
        assert!(l.contains(&format!("mapping: remapped RPDO1 0x{:03X} = controlword + 0x607A:00", 0x200 + n)), "{l}");
        assert!(l.contains("error control: heartbeat both ways"), "{l}");
    }

    // Positions in µm.
    let o = run(&python, "user_units");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2006: node 1 (axis x): the drive scales positions: 1 position unit = 10 encoder increments"), "{}", o.stderr);
    assert!(o.stderr.contains("Set axes.x.counts_per_unit = 1000"), "{}", o.stderr);
    o.nothing_moved();

    // Produces SYNC itself: named, and nothing reset.
    let o = run(&python, "sync_producer");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2007: node 1 (axis x): the drive produces SYNC itself (0x1005 = 0x40000080"), "{}", o.stderr);
    o.nothing_moved();
    assert!(o.drives.iter().all(|d| d["resets"] == 0), "{:?}", o.drives);

    // No heartbeat consumer, and no remote frames over socketcand for node guarding: runs,
    // and says the drive will not stop by itself if the controller dies.
    let o = run(&python, "no_1016");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("has no heartbeat consumer (0x1016)") && o.stderr.contains("carries no remote frames"), "{}", o.stderr);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000));
    for n in 1..=3 {
        let l = o.startup_line(n);
        assert!(l.contains("start-up: mode CSP (cyclic synchronous position) (the default);"), "{l}");
        assert!(
            l.contains("error control: none: no 0x1016 socketcand://") && l.contains("carries no remote frames for node guarding (warning)"),
            "{l}"
        );
    }

    // No 0x6502: the mode is checked in 0x6061.
    let o = run(&python, "no_6502");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000));
}

/// Issue 21: python drives with interpolated position and no CSP, a second opinion to
/// sim-drives' "ip-only" profile: refused in CSP naming the key, run in IP to the end point.
#[test]
fn realtime_python_ip_only_drives() {
    let Some(python) = venv_python() else { return };
    let o = run(&python, "ip_only");
    assert_eq!(o.code, 3, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("alarm 2005: node 1 (axis x): this drive has no CSP") && o.stderr.contains("set axes.x.mode = \"ip\""), "{}", o.stderr);
    o.nothing_moved();
    let o = run_cfg(&python, "ip_only", |c| {
        let mut c = c;
        for n in 1..=3 {
            c = c.replacen(&format!("\nnode = {n}\n"), &format!("\nnode = {n}\nmode = \"ip\"\n"), 1);
        }
        c
    });
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![7], "node {n} was enabled in another mode than IP");
    }
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");
}

/// Issue 21: python drives with fixed PDO mappings, a second opinion to sim-drives'
/// "fixed-pdo" profile. Each refuses remapping as one vendor does — node 1 RPDO 0x06040041
/// (not mappable) / TPDO 0x08000022 (device state), node 2 0x06040043 (parameter
/// incompatibility) / 0x06040041, node 3 0x08000022 / 0x06040043 — and offers its own sets
/// in its EDS, in an order that is not the master's: RPDO1 = target, controlword; TPDO1 =
/// position actual, statusword, mode display. cncgw takes them, says so, and first_part
/// ends at its end point.
#[test]
fn realtime_python_fixed_pdo_drives() {
    let Some(python) = venv_python() else { return };
    let o = run(&python, "fixed_pdo");
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![8], "node {n} was enabled in another mode than CSP");
    }
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");
    for (n, rpdo_abort, tpdo_abort) in [(1usize, "0x06040041", "0x08000022"), (2, "0x06040043", "0x06040041"), (3, "0x08000022", "0x06040043")] {
        let l = o.startup_line(n);
        let rpdo =
            format!("mapping: fixed RPDO1 0x{:03X} = [0x607A:00 (32 bit), 0x6040:00 (16 bit)] (remapping refused: SDO abort {rpdo_abort}", 0x200 + n);
        assert!(l.contains(&rpdo), "node {n}: {l}");
        // The mode display is in the drive's TPDO: not polled by SDO.
        let tpdo = format!("fixed TPDO1 0x{:03X} = [0x6064:00 (32 bit), 0x6041:00 (16 bit), 0x6061:00 (8 bit)];", 0x180 + n);
        assert!(l.contains(&tpdo), "node {n}: {l}");
        assert!(o.stderr.contains(&format!("TPDO1 cannot be remapped (SDO abort {tpdo_abort}")), "node {n}: {}", o.stderr);
    }
}

/// Issue 21: python drives counting positions in user units (0x6092:1 = a tenth of the
/// increments per revolution: 1 µm, 0.01°), run with the axes declared in those units —
/// counts_per_unit in the drive's units, travel_per_rev for start-up's check against the
/// factor group — as config/drives/lathe-user-units.toml does for sim-drives' "user-units".
#[test]
fn realtime_python_user_units_drives_run_in_their_units() {
    let Some(python) = venv_python() else { return };
    let o = run_cfg(&python, "user_units", |c| {
        let c = c.replacen("counts_per_unit = 10000.0", "counts_per_unit = 1000.0\ntravel_per_rev = 10.0\n#", 2);
        let c = c.replacen("counts_per_unit = 1000.0    # counts per degree", "counts_per_unit = 100.0\ntravel_per_rev = 360.0\n#", 1);
        assert_eq!(c.matches("travel_per_rev").count(), 3, "config/lathe.toml changed shape");
        c
    });
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    // X100 (radius 50 mm) Z5 in the drives' own units (µm), and in encoder increments.
    assert_eq!((o.position_actual(1), o.position_actual(2)), (50_000, 5_000), "{:?}", o.drives);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000));
    for n in 1..=3 {
        assert_eq!(o.enabled_modes(n), vec![8]);
        assert!(o.startup_line(n).contains("units: 1 unit = 10 increments"), "{}", o.startup_line(n));
    }
}

/// Issue 21: `bus.sync = "external"` with a python drive producing the SYNC (node 1, 0x1005
/// bit 30, every 5 ms = the cycle): cncgw's cycle runs on it, cncgw sends no SYNC, and
/// first_part ends at its end point.
#[test]
fn realtime_python_drive_produces_the_sync_cncgw_runs_on() {
    let Some(python) = venv_python() else { return };
    let o = run_cfg(&python, "ext_sync", |c| {
        // SYNC comes from a python interpreter on a shared machine: measured gaps of 34 ms when
        // it stalls. 20 cycles (100 ms, the feedback timeout) before alarm 2022, not 5.
        let c = c.replacen("feedback_timeout_ms = 100", "feedback_timeout_ms = 100\nsync = \"external\"\nsync_loss_cycles = 20", 1);
        assert!(c.contains("sync = \"external\""));
        c
    });
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("cycle on the external SYNC") && o.stderr.contains("external SYNC heard"), "{}", o.stderr);
    assert!(o.stderr.contains("the drive produces the SYNC the cycle runs on (0x1005 = 0x40000080)"), "{}", o.stderr);
    assert_eq!((o.position(1), o.position(2)), (500_000, 50_000), "X100 Z5 on the drives' own positions");
    // Node 2 heard exactly the SYNCs node 1 produced: none came from cncgw.
    let (sent, heard) = (o.drives[0]["syncs_sent"].as_i64().unwrap(), o.drives[1]["syncs_heard"].as_i64().unwrap());
    assert!(sent > 5000, "a first_part is ~35 s of 5 ms cycles: {sent} SYNCs");
    assert_eq!(heard, sent, "SYNCs other than node 1's were on the bus");
}

/// One `cncgw tap-test` against python drives of `shape` (tap_sN: a spindle of time constant
/// N ms with one extra cycle of transport delay, a Z with its own dynamics; see
/// tests/python/canopen_drive.py).
struct Tap {
    code: i32,
    stderr: String,
    /// The figures tap-test printed (`--json`), Null when it printed none.
    json: serde_json::Value,
    /// Longest time between two cycles of the controller's trace, ms (a host stall).
    gap_ms: f64,
    /// Cycles in which a moving drive's feedback did not change while its command did: its
    /// TPDO came a cycle late (python did not keep the cycle).
    late_tpdo: usize,
    drives: Vec<serde_json::Value>,
}

/// The cycle the python drives keep: at 2 ms one interpreter handling three drives' SYNC,
/// RPDO and TPDO sends the spindle's TPDO a cycle late a few times per tap (measured
/// 2026-11-28, README "Spindle sync on drives we did not tune for").
const TAP_CYCLE_MS: f64 = 5.0;

/// `program` under SCHED_FIFO `prio` where this machine lets us (`chrt`), else as it is: a
/// python drive that keeps its cycle only with real-time priority on a loaded machine.
fn realtime(program: &Path, prio: u8) -> Command {
    let allowed = Command::new("chrt").args(["-f", "1", "true"]).status().is_ok_and(|s| s.success());
    if allowed {
        let mut c = Command::new("chrt");
        c.args(["-f", &prio.to_string()]).arg(program);
        c
    } else {
        Command::new(program)
    }
}

/// The embedded lathe as the python drives need it: a 5 ms cycle (`TAP_CYCLE_MS`), feedback
/// up to 100 ms old, the spindle's following-error window, and no late SYNC bridged (the
/// python drives run on the SYNCs they receive).
fn python_lathe(spindle_window_deg: f64) -> String {
    let cfg = cncgw::config::EMBEDDED_LATHE
        .replace("cycle_ms = 2.0", &format!("cycle_ms = {TAP_CYCLE_MS:.1}"))
        .replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 100")
        .replace("following_error = 180.0 ", &format!("following_error = {spindle_window_deg:.1} "))
        .replace("late_sync_extrapolation = 10", "late_sync_extrapolation = 0");
    assert!(cfg.contains(&format!("following_error = {spindle_window_deg:.1} ")) && cfg.contains("cycle_ms = 5.0"));
    assert!(!cfg.contains("late_sync_extrapolation = 10"));
    cfg
}

/// TPDOs that came a cycle late in `trace` (usize::MAX when it does not parse): an actual
/// that stands for a cycle after moving more than one count, while its command moves on (a
/// slide settling onto its count in 1-count steps is not one). One count: 0.1 µm on Z,
/// 0.001° on the spindle.
fn late_tpdos(trace: &str) -> usize {
    cncgw::control::trace::TraceData::parse(trace).map_or(usize::MAX, |d| {
        [("s1", 1e-3), ("z", 1e-4)]
            .iter()
            .map(|&(n, count)| {
                let (c, a) = (d.column(&format!("{n}_cmd")).unwrap_or_default(), d.column(&format!("{n}_act")).unwrap_or_default());
                (2..a.len().min(c.len())).filter(|&i| a[i] == a[i - 1] && (a[i - 1] - a[i - 2]).abs() > 1.5 * count && c[i] != c[i - 1]).count()
            })
            .sum()
    })
}

/// `cncgw ARGS --bus socketcand://… --yes --config …` on the python drives of `shape` (hub,
/// drives and cncgw under SCHED_FIFO where allowed), the lathe's spindle window
/// `spindle_window_deg`: cncgw's output, the drives' final reports (after SIGTERM) and the
/// run's directory (CNCGW_STATE_DIR; the caller reads what it wrote there and removes it).
fn on_python_drives(
    python: &Path,
    shape: &str,
    spindle_window_deg: f64,
    tag: &str,
    args: impl FnOnce(&Path) -> Vec<std::ffi::OsString>,
) -> (std::process::Output, Vec<serde_json::Value>, PathBuf) {
    let (addr, stop, hub) = hub_at(Some(45));
    let port = addr.rsplit_once(':').unwrap().1.to_string();
    let (mut py, out) = start_drives(realtime(python, 40), &port, shape);
    let dir = std::env::temp_dir().join(format!("cncgw_python_{tag}_{shape}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("machine.toml"), python_lathe(spindle_window_deg)).unwrap();
    let o = realtime(Path::new(env!("CARGO_BIN_EXE_cncgw")), 50)
        .args(args(&dir))
        .args(["--bus", &format!("socketcand://{addr}/can0"), "--yes"])
        .arg("--config")
        .arg(dir.join("machine.toml"))
        .env("CNCGW_STATE_DIR", &dir)
        .output()
        .expect("run cncgw");
    // SAFETY: a signal to our own child process.
    unsafe {
        libc::kill(py.id() as i32, libc::SIGTERM);
    }
    let drives: Vec<serde_json::Value> = out.lines().map_while(Result::ok).filter_map(|l| serde_json::from_str(&l).ok()).collect();
    let _ = py.wait();
    stop.store(true, Ordering::Relaxed);
    let _ = hub.join();
    (o, drives, dir)
}

/// The last JSON line of `o`'s standard output, Null when it printed none.
fn last_json(o: &std::process::Output) -> serde_json::Value {
    String::from_utf8_lossy(&o.stdout).lines().rev().find_map(|l| serde_json::from_str(l).ok()).unwrap_or(serde_json::Value::Null)
}

fn tap(python: &Path, shape: &str, spindle_window_deg: f64) -> Tap {
    let (o, drives, dir) = on_python_drives(python, shape, spindle_window_deg, "tap", |dir| {
        let mut a: Vec<std::ffi::OsString> =
            ["tap-test", "--lead", "1.5", "--depth", "35", "--rpm", "3000", "--json", "-o"].iter().map(Into::into).collect();
        a.push(dir.join("tap.svg").into());
        a
    });
    let json = last_json(&o);
    let trace = std::fs::read_to_string(dir.join("tap.csv")).unwrap_or_default();
    let gap_ms = cncgw::control::trace::TraceData::parse(&trace).map_or(f64::INFINITY, |d| {
        let t = d.column("t_s").unwrap_or_default();
        t.windows(2).map(|w| (w[1] - w[0]) * 1e3).fold(0.0, f64::max)
    });
    let late_tpdo = late_tpdos(&trace);
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(drives.len(), 3, "python drives' report missing");
    Tap { code: o.status.code().unwrap_or(-1), stderr: String::from_utf8_lossy(&o.stderr).into_owned(), json, gap_ms, late_tpdo, drives }
}

/// Issue 17: the rigid tap M10×1.5, 35 mm, S3000 (`cncgw tap-test`) on CiA 402 drives we did
/// not write, whose dynamics are not sim-drives': python drives with a second-order spindle
/// (τ 15 ms and 40 ms, velocity feed-forward, one extra cycle of transport delay) and a Z of
/// its own (τ 6 ms, 97 % feed-forward), in real time over socketcand at a 5 ms cycle, the
/// drives holding on a late SYNC (`late_sync_extrapolation = 0`).
///
/// Measured 2026-11-28 on a loaded 2-core VM (release build, chrt; README): a tap in which no
/// frame is late gives the same figures every time — max 16.4 µm / RMS 2.1 µm (τ 15 ms),
/// 19.9 / 3.5 µm (τ 40 ms); with the bell-shaped tap and one-SYNC pairing 4.21 and 8.01 µm
/// (2026-11-28 12:53; the same on 2026-11-29 with the tap starting on a still Z). The bound,
/// 50 µm, is half the machine's sync limit (100 µm, alarm 2307) and 2.5 × the worst of the
/// first figures: scheduling noise within a cycle (python and a debug
/// build here, no real-time priority) must not fail it, a sync law that does not follow the
/// drives does. Only a tap in which every TPDO came on time (no moving drive's feedback a
/// cycle old) and the controller did not stall is judged; another is run again, up to 8
/// times: a host stall inside the tap is alarm 2403 (the drives do not bridge it), and one
/// spindle TPDO a cycle late can end in alarm 2307 with the sync law of 2026-11-28 (its stale
/// angle paired with Z's fresh position). Python, cncgw and the hub run under SCHED_FIFO where allowed.
#[test]
fn realtime_rigid_tap_on_python_drives() {
    const BOUND_UM: f64 = 50.0;
    let Some(python) = venv_python() else { return };
    // (shape, the spindle's following-error window 0x6065: about 3 × its lag a·τ² at the
    // tap's 5000 rpm/s — 6.8° and 48° —; `cncgw identify` proposes 24° and 184° for the
    // lathe's 6000 rpm/s; the lathe's 30° for τ 15 ms)
    for (shape, window) in [("tap_s15", 30.0), ("tap_s40", 150.0)] {
        let mut judged = None;
        for attempt in 1..=8 {
            let t = tap(&python, shape, window);
            let s = &t.json["sync_error"];
            eprintln!(
                "{shape} attempt {attempt}: exit {}, sync error max {} µm RMS {} µm, longest cycle {:.1} ms, late TPDOs {}",
                t.code, s["max_um"], s["rms_um"], t.gap_ms, t.late_tpdo
            );
            if t.late_tpdo > 0 || t.stderr.contains("alarm 2403") {
                eprintln!("  a late TPDO or a stall: not judged ({})", t.stderr.lines().find(|l| l.contains("alarm")).unwrap_or("no alarm"));
                continue;
            }
            judged = Some(t);
            break;
        }
        let t = judged.unwrap_or_else(|| panic!("{shape}: in every tap of 8 a TPDO came late or the controller stalled: nothing to judge"));
        assert!(!t.stderr.contains("alarm 2307"), "{shape}: the sync monitor stopped the tap: {}", t.stderr);
        assert_eq!(t.code, 0, "{shape}: {}", t.stderr);
        let max = t.json["sync_error"]["max_um"].as_f64().expect("figures");
        assert!(max <= BOUND_UM, "{shape}: sync error max {max} µm > {BOUND_UM} µm: {}", t.json);
        assert!(t.json["sync_error"]["cycles"].as_u64().unwrap() > 300, "{shape}: the whole tap was measured: {}", t.json);
        for (d, node) in t.drives.iter().zip(1..) {
            assert_eq!(d["error"], 0, "node {node} faulted: {d}");
            assert_eq!(d["enabled_modes"], serde_json::json!([8]), "node {node}: {d}");
        }
        // Z came back to R (2 mm above where it stood) on the drive's own position, within
        // its dynamics' settling (the spindle turned back to where it started).
        assert!((t.drives[1]["position"].as_i64().unwrap() - 20_000).abs() <= 10, "{:?}", t.drives);
    }
}

/// `cncgw identify AXIS` over socketcand on the python drives of `shape`, in real time:
/// its JSON (Null when it printed none), its standard error, and the late TPDOs of the
/// excitation's trace.
fn identify_on(python: &Path, shape: &str, axis: &str, spindle_window_deg: f64) -> (serde_json::Value, String, usize) {
    let (o, _, dir) = on_python_drives(python, shape, spindle_window_deg, &format!("identify_{axis}"), |dir| {
        let mut a: Vec<std::ffi::OsString> = ["identify", axis, "--json", "--trace"].iter().map(Into::into).collect();
        a.push(dir.join("identify.csv").into());
        a
    });
    let late = late_tpdos(&std::fs::read_to_string(dir.join("identify.csv")).unwrap_or_default());
    let _ = std::fs::remove_dir_all(&dir);
    (last_json(&o), String::from_utf8_lossy(&o.stderr).into_owned(), late)
}

/// Issue 17, "identify works on real drives": `cncgw identify` on CiA 402 drives we did not
/// write, over socketcand in real time (5 ms cycle), against the law the python drives
/// follow (`canopen_drive.py` tap_s40: a critically damped second order, τ²ÿ + 2τẏ + y =
/// r + 2τ·ff·ṙ). Truth at 5 ms: the pipeline is two cycles (latched at the next SYNC,
/// interpolated over one period, read back at the SYNC after), the spindle one more; the
/// spindle (τ 40 ms, ff 1) lags nothing of its own at constant speed and τ² = 1600 ms² per
/// unit of acceleration; Z (τ 6 ms, ff 0.97) lags 2τ(1 − ff) = 0.36 ms of its own.
///
/// Measured 2026-11-30 (release build, chrt, the machine otherwise idle): s1 delay 3.07
/// cycles, velocity lag 15.11 ms (0.11 of it its own), accel lag 1594 ms², window proposed
/// 184° (3 × (0.11 ms × 36000°/s + 1594 ms² × 36000°/s²)); z delay 2.04, velocity lag
/// 10.33 ms, own lag 0.33 ms. Until then the spindle's proposal was 0° ("no lag of its own"). Judged
/// is only a run in which no actual came late — none filled by identify (`late_samples`), none
/// held by the test's own count — and which ran at full speed (a probe that read a stall as
/// lag slows the excitation, "the run keeps to …", and the spindle's lag per unit of
/// acceleration then reads half: 797 and 812 ms² for 1600 in two CI runs); a run that printed
/// nothing (a python drive that stalled left NMT operational, alarm 2014) is not judged either.
/// Up to 10 runs. Filled runs are not judged: on a host stalling on its own (fresh-clone CI,
/// 2026-12-03) one with 6 of 395 filled read Z's own lag 0.11 ms for 0.36 at a fit of 100 %,
/// and one with 33 of 548 the spindle's delay 8.07 cycles for 3 — the drive process had stalled
/// itself, which no filling recovers (README "Late frames").
#[test]
fn realtime_identify_on_python_drives() {
    let Some(python) = venv_python() else { return };
    let dt = TAP_CYCLE_MS * 1e-3;
    // (axis, delay in cycles, velocity lag s, own lag s, accel lag s²: None where not judged)
    for (axis, delay, lag, own, accel) in [("s1", 3.0, 3.0 * dt, 0.0, Some(0.04f64 * 0.04)), ("z", 2.0, 2.0 * dt + 0.36e-3, 0.36e-3, None)] {
        let mut printed = 0;
        let judged = (1..=10).find_map(|attempt| {
            let (r, err, late) = identify_on(&python, "tap_s40", axis, 180.0);
            eprintln!("{axis} attempt {attempt}: late TPDOs {late}: {r}");
            if r.is_null() {
                eprintln!("  identify printed nothing: {err}");
                return None;
            }
            printed += 1;
            let clean = late == 0 && r["late_samples"].as_u64() == Some(0) && !err.contains("the run keeps to");
            clean.then_some(r)
        });
        assert!(printed > 0, "{axis}: identify printed nothing in any of 10 runs");
        let r = judged.unwrap_or_else(|| panic!("{axis}: in every run of 10 an actual came late or the run was slowed: nothing to judge"));
        let got = |k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        assert!((got("delay_cycles") / delay - 1.0).abs() <= 0.1, "{axis}: delay {} cycles for {delay}", got("delay_cycles"));
        assert!((got("velocity_lag_ms") * 1e-3 / lag - 1.0).abs() <= 0.1, "{axis}: velocity lag {} ms for {:.2}", got("velocity_lag_ms"), lag * 1e3);
        assert!((got("own_lag_ms") * 1e-3 - own).abs() <= 0.03 * dt, "{axis}: own lag {} ms for {:.2}", got("own_lag_ms"), own * 1e3);
        if let Some(a) = accel {
            assert!((got("accel_lag_ms2") * 1e-6 / a - 1.0).abs() <= 0.1, "{axis}: accel lag {} ms² for {:.0}", got("accel_lag_ms2"), a * 1e6);
            // The lathe's spindle: 6000 rpm/s = 36000°/s².
            let need = 3.0 * a * 36000.0;
            assert!(got("proposed_following_error") >= 0.9 * need, "{axis}: window {}° for {need:.0}°", got("proposed_following_error"));
        }
    }
    // With the lathe's old 30° window the same spindle lags 29° at the excitation's 3000
    // rpm/s: the probe reads that lag and the run keeps its acceleration within the window
    // (until 2026-11-30 the drive faulted, 0x8611, alarm 2010, and nothing was identified).
    // What it proposes from that gentler run is not asserted: in real time it varied from run
    // to run (175° on an idle machine; 142° and 37° in two CI runs, 2026-11-30).
    let (r, err, _) = identify_on(&python, "tap_s40", "s1", 30.0);
    assert!(!err.contains("alarm"), "{err}");
    assert!(err.contains("per unit of acceleration: the run keeps to"), "{err}");
    assert!(r["proposed_following_error"].is_number(), "identify printed no result: {r} {err}");
}
