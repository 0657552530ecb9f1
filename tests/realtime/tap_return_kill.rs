//! The controller process dies in the middle of a rigid tap, and comes back.
//!
//! `sim-drives --socketcand` runs as its own process (this host's kernel has no SocketCAN);
//! `cncgw run --bus socketcand://…` taps a hole (M29 S500, G84 Z-20 from R = Z2, lead 1.5)
//! and is killed with SIGKILL while the tap-state file says "in the hole". Asserted:
//! (a) the drives stop by themselves — the master's heartbeat, consumed by every drive
//!     (0x1016 = 3 × 100 ms, 0x6007 = 1, set by cncgw's start-up), times out: each drive sends
//!     EMCY 0x8130, its statusword leaves Operation Enabled and its position stops changing,
//!     within 3 heartbeat periods + 200 ms of the kill. A test client on the same socketcand
//!     bus sees it: it only listens while cncgw lives; once cncgw is dead (no SYNC, so no
//!     TPDOs) it reads 0x6041 and 0x6064 by expedited SDO uploads.
//! (b) the tap-state file is whole and says where the tool is;
//! (c) a second `cncgw run` of `G30 P99 S500` with the same --state-dir, against the same
//!     sim-drives process (its start-up fault-resets the drives), brings the tool out along
//!     the thread to R with the spindle turning back in sync (computed from the --trace
//!     columns) and clears the state.
//! Plus: SIGKILL in the middle of tap-state writes leaves the old or the new state, never a
//! torn one. Real time: these run alone (.config/nextest.toml).

use cncgw::persist::{TapState, TapStateFile};
use cncgw_bus::canopen::emcy::Emcy;
use cncgw_bus::canopen::sdo::{SdoRequest, SdoResponse};
use cncgw_bus::transport::socketcand::Socketcand;
use cncgw_bus::{CanBus, CanFrame};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use testkit::{bin, Kill};

const HEARTBEAT_MS: u64 = 100;
const CYCLE_MS: f64 = 2.0;

fn tmp(name: &str) -> PathBuf {
    testkit::tmp!("tap_return_kill", name)
}

/// The default lathe with the tolerances of a shared 2-core machine (as tests/realtime/modbus_run.rs):
/// a descheduled process must not fault the run on its feedback age or following error.
/// The sync error limit (100 µm) is the default.
fn machine() -> PathBuf {
    let lathe = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).unwrap();
    let m = lathe
        .replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 300")
        .replace("following_error = 1.0\n\n[axes.s1]", "following_error = 5.0\n\n[axes.s1]");
    assert!(m.contains("heartbeat_ms = 100"), "config/lathe.toml changed shape");
    let p = tmp("machine.toml");
    std::fs::write(&p, m).unwrap();
    p
}

fn start_sim(cfg: &Path) -> (Kill, u16, PathBuf) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let log = tmp("sim.log");
    let sim = Kill(
        Command::new(bin!("sim-drives"))
            .args(["--config", &cfg.display().to_string(), "--socketcand", &format!("127.0.0.1:{port}")])
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(t0.elapsed().as_secs() < 10, "sim-drives --socketcand did not start: {}", std::fs::read_to_string(&log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(20));
    }
    (sim, port, log)
}

/// An SDO answer: (time, node, index, value).
type Read = (Instant, u8, u16, i64);
type Frames = Vec<(Instant, CanFrame)>;

/// A client on the bus: records every frame with its arrival time; once `poll` is set it
/// reads statusword and position of nodes 1–3 by SDO, one request at a time.
struct Observer {
    frames: Arc<Mutex<Frames>>,
    reads: Arc<Mutex<Vec<Read>>>,
    poll: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
    handle: Option<std::thread::JoinHandle<()>>,
}

impl Observer {
    fn start(port: u16) -> Observer {
        let mut bus = Socketcand::connect(&format!("127.0.0.1:{port}"), "can0").expect("join the socketcand bus");
        let frames = Arc::new(Mutex::new(Vec::new()));
        let reads = Arc::new(Mutex::new(Vec::new()));
        let poll = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let (f2, r2, p2, s2) = (frames.clone(), reads.clone(), poll.clone(), stop.clone());
        let handle = std::thread::spawn(move || {
            let objects = [(1u8, 0x6041u16), (2, 0x6041), (3, 0x6041), (1, 0x6064), (2, 0x6064), (3, 0x6064)];
            let mut k = 0usize;
            let mut pending: Option<(u8, u16, Instant)> = None;
            while !s2.load(Ordering::Relaxed) {
                if p2.load(Ordering::Relaxed) && pending.is_none_or(|(_, _, t)| t.elapsed() > Duration::from_millis(50)) {
                    let (node, index) = objects[k % objects.len()];
                    k += 1;
                    if bus.send(&SdoRequest::InitiateUpload { index, sub: 0 }.encode(node)).is_ok() {
                        pending = Some((node, index, Instant::now()));
                    }
                }
                match bus.recv_timeout(Duration::from_millis(1)) {
                    Ok(Some(f)) => {
                        let now = Instant::now();
                        if let (Some((node, index, _)), true) = (pending, f.cob_id() == 0x580 + pending.map_or(0, |p| p.0) as u16) {
                            if let Some(SdoResponse::InitiateUpload { index: i, expedited: true, data, size, .. }) = SdoResponse::decode(&f) {
                                if i == index {
                                    let v = match size {
                                        Some(2) => u16::from_le_bytes([data[0], data[1]]) as i64,
                                        _ => i32::from_le_bytes(data) as i64,
                                    };
                                    r2.lock().unwrap().push((now, node, index, v));
                                    pending = None;
                                }
                            }
                        }
                        f2.lock().unwrap().push((now, f));
                    }
                    Ok(None) => {}
                    Err(_) => return,
                }
            }
        });
        Observer { frames, reads, poll, stop, handle: Some(handle) }
    }

    fn finish(mut self) -> (Frames, Vec<Read>) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
        let f = std::mem::take(&mut *self.frames.lock().unwrap());
        let r = std::mem::take(&mut *self.reads.lock().unwrap());
        (f, r)
    }
}

fn load_state(f: &TapStateFile) -> Option<TapState> {
    f.load().ok().flatten()
}

/// `cncgw`'s trace: rows of (line, z_act, s1_act).
fn trace_rows(path: &Path) -> Vec<(u32, f64, f64)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap_or_else(|| panic!("no {n} in {head:?}"));
    let (cl, cz, cs) = (col("line"), col("z_act"), col("s1_act"));
    lines
        .map(|l| {
            let v: Vec<&str> = l.split(',').collect();
            (v[cl].parse().unwrap(), v[cz].parse().unwrap(), v[cs].parse().unwrap())
        })
        .collect()
}

#[test]
fn realtime_sigkill_mid_tap_drives_stop_and_g30_p99_brings_the_tap_out() {
    let cfg = machine();
    let (sim, port, sim_log) = start_sim(&cfg);
    let state_dir = tmp("state");
    let _ = std::fs::remove_dir_all(&state_dir);
    let cfg_s = cfg.display().to_string();
    let sd = state_dir.display().to_string();
    let bus = format!("socketcand://127.0.0.1:{port}/can0");
    let tap_file = cncgw::persist::StatePlace::new(&state_dir, "cncgw default lathe (X/Z + Cs spindle)", &bus).tap_state();
    let mut sc = sim_drives::report::Scenario::new("survive/sigkill_mid_tap_canopen");
    sc.faults_injected = 1;

    // --- The tap, killed in the hole.
    let prog = tmp("tap.nc");
    // R point = initial Z5 + R-3 = Z2; lead = F/S = 750/500 = 1.5 mm.
    std::fs::write(&prog, "O1\nG21\nG98 G97\nG00 X0 Z5\nM29 S500\nG84 Z-20 R-3 F750\nG80\nG00 Z5\nM30\n").unwrap();
    let obs = Observer::start(port);
    let run_log = tmp("run1.log");
    let mut cnc = Kill(
        Command::new(bin!("cncgw"))
            .args(["run", "--config", &cfg_s, "--bus", &bus, "--state-dir", &sd])
            .arg(&prog)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&run_log).unwrap())
            .spawn()
            .unwrap(),
    );
    // Watch the state file; kill once the tool is 6 mm deep (mid-tap).
    let t0 = Instant::now();
    let seen = loop {
        if let Some(s) = load_state(&tap_file).filter(|s| s.in_hole && s.position < -4.0) {
            break s;
        }
        if let Ok(Some(st)) = cnc.0.try_wait() {
            panic!("cncgw ended before the tap ({st}): {}", std::fs::read_to_string(&run_log).unwrap_or_default());
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no in-hole state: {}", std::fs::read_to_string(&run_log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(2));
    };
    let t_kill = Instant::now();
    cnc.0.kill().unwrap(); // SIGKILL
    let status = cnc.0.wait().unwrap();
    obs.poll.store(true, Ordering::Relaxed);
    assert_eq!(status.code(), None, "killed by the signal, not ended: {status}");
    std::thread::sleep(Duration::from_millis(1500));
    let (frames, reads) = obs.finish();

    // (a) Each drive: EMCY 0x8130, statusword out of Operation Enabled, position at rest.
    let ms = |t: Instant| t.saturating_duration_since(t_kill).as_secs_f64() * 1e3;
    let bound_ms = (3 * HEARTBEAT_MS + 200) as f64;
    let mut worst_ms = 0.0f64;
    for node in 1..=3u8 {
        let emcy = frames
            .iter()
            .filter(|(t, _)| *t >= t_kill)
            .find(|(_, f)| Emcy::decode(f).is_some_and(|(n, e)| n == node && e.code == 0x8130))
            .map(|(t, _)| ms(*t))
            .unwrap_or_else(|| {
                panic!("node {node}: no EMCY 0x8130 after the kill; sim-drives: {}", std::fs::read_to_string(&sim_log).unwrap_or_default())
            });
        let sw: Vec<_> = reads.iter().filter(|r| r.1 == node && r.2 == 0x6041).collect();
        let left_oe = sw
            .iter()
            .find(|r| r.3 & 0x6F != 0x27)
            .map(|r| ms(r.0))
            .unwrap_or_else(|| panic!("node {node}: statusword never left Operation Enabled: {sw:?}"));
        let pos: Vec<_> = reads.iter().filter(|r| r.1 == node && r.2 == 0x6064).collect();
        assert!(pos.len() >= 10, "node {node}: {} position reads", pos.len());
        let last = pos.last().unwrap().3;
        // At rest from the first read after the last one that differs from the end by more
        // than 1 µm (X, Z: 10 counts) or 0.1° (the spindle: 100 counts; a spindle holding
        // position hunts by a few counts).
        let tol = if node == 3 { 100 } else { 10 };
        let moving_until = pos.iter().rev().find(|r| (r.3 - last).abs() > tol).map_or(0.0, |r| ms(r.0));
        let at_rest = pos.iter().find(|r| ms(r.0) > moving_until).map_or(f64::INFINITY, |r| ms(r.0));
        eprintln!("node {node}: EMCY 0x8130 after {emcy:.0} ms, statusword out of Operation Enabled by {left_oe:.0} ms, position at rest by {at_rest:.0} ms of the kill");
        assert!(emcy <= bound_ms, "node {node}: EMCY {emcy:.0} ms after the kill > {bound_ms} ms");
        assert!(left_oe <= bound_ms, "node {node}: still enabled {left_oe:.0} ms after the kill");
        assert!(at_rest <= bound_ms, "node {node}: still moving {at_rest:.0} ms after the kill");
        worst_ms = worst_ms.max(emcy).max(left_oe).max(at_rest);
    }
    sc.stop_cycles = Some((worst_ms / CYCLE_MS).ceil() as u64);
    sc.bound_cycles = Some((bound_ms / CYCLE_MS) as u64);

    // (b) The state file is whole and says where the tool is.
    let st = match tap_file.load() {
        Ok(Some(s)) => s,
        other => {
            sc.data_lost += 1;
            sc.record();
            panic!("tap state after the kill: {other:?}");
        }
    };
    assert!(st.in_hole && st.axis == 'Z' && st.r_plane == 2.0 && st.direction_in == -1.0 && st.lead == -1.5 && st.rpm == 500.0, "{st:?}");
    assert!(st.position <= seen.position && st.position > -20.0, "{st:?} (seen {seen:?} before the kill)");
    let z_end = reads.iter().rfind(|r| r.1 == 2 && r.2 == 0x6064).unwrap().3 as f64 / 10_000.0;
    // The file is ≤ 20 ms old at the kill; the axis stopped after it.
    assert!(z_end <= st.position + 1e-3 && z_end > st.position - 2.0, "Z stopped at {z_end} mm, the state says {}", st.position);
    eprintln!("state at the kill: Z {:.4} mm, spindle {:.1}°; Z came to rest at {z_end:.4} mm", st.position, st.spindle_deg);

    // A program that is not G30 P99 is refused, and nothing moves.
    let other = tmp("other.nc");
    std::fs::write(&other, "O3\nG00 X20 Z50\nM30\n").unwrap();
    let o = Command::new(bin!("cncgw")).args(["run", "--config", &cfg_s, "--bus", &bus, "--state-dir", &sd]).arg(&other).output().unwrap();
    let t = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{t}");
    assert!(t.contains("alarm 2410") && t.contains("G30 P99"), "{t}");

    // (c) G30 P99 against the same sim-drives process.
    let ret = tmp("return.nc");
    std::fs::write(&ret, "O2\nG30 P99 S500\nM30\n").unwrap();
    let trace = tmp("return.csv");
    let o = Command::new(bin!("cncgw"))
        .args(["run", "--json", "--config", &cfg_s, "--bus", &bus, "--state-dir", &sd, "--trace", &trace.display().to_string()])
        .arg(&ret)
        .output()
        .unwrap();
    let t = format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    eprintln!("{t}");
    if o.status.code() == Some(101) {
        sc.panics += 1;
    }
    assert!(o.status.success(), "{t}");
    let after = tap_file.load();
    if !matches!(after, Ok(Some(s)) if !s.in_hole) {
        sc.data_lost += 1;
    }
    sc.record();
    let after = after.unwrap().unwrap();
    assert!(!after.in_hole, "the state is cleared at R: {after:?}");
    // The return along the thread: line 2 of the trace.
    let rows: Vec<_> = trace_rows(&trace).into_iter().filter(|r| r.0 == 2).collect();
    assert!(rows.len() > 100, "{} trace rows of the return", rows.len());
    let (_, z0, s0) = rows[0];
    let (_, z1, s1) = *rows.last().unwrap();
    assert!((z0 - z_end).abs() < 0.01, "the return starts where Z stopped: {z0} vs {z_end}");
    // The program ends on R: Z2 within a count (the run's own end-point check).
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["at_program_end"], true, "{t}");
    let z_axis = v["axes"].as_array().unwrap().iter().find(|a| a["axis"] == "z").unwrap();
    assert!((z_axis["final_actual_counts"].as_i64().unwrap() - 20_000).abs() <= 1, "Z ends on R (Z2): {z_axis}");
    // (The trace's line changes to M30's when the set-point lands; the drive is a few µm short.)
    assert!((z1 - 2.0).abs() < 0.02, "the return's last row is at R: Z {z1}");
    // Counter-rotation: going out the spindle turns back, one turn per 1.5 mm.
    let turns = (s1 - s0) / 360.0;
    assert!(turns < 0.0 && (turns + (z1 - z0) / 1.5).abs() < 0.01, "{turns} turns for {} mm", z1 - z0);
    let err_um = rows.iter().map(|&(_, z, s)| ((z - z0) - (-1.5) * (s - s0) / 360.0).abs() * 1e3).fold(0.0, f64::max);
    eprintln!("G30 P99: Z {z0:.4} → {z1:.4} mm, spindle {turns:.3} turns, largest sync error (trace, actual positions) {err_um:.1} µm");
    assert!(err_um < 100.0, "sync error {err_um:.1} µm on the way out");
    drop(sim);
}

const CHILD_ENV: &str = "CNCGW_TAPSTATE_KILL_CHILD";

/// Generation `n` of the state: every field derived from `n`, so a mixed file shows.
fn generation(n: u64) -> TapState {
    let g = n as f64;
    TapState {
        in_hole: n % 2 == 1,
        axis: 'Z',
        r_plane: 2.0,
        direction_in: -1.0,
        lead: -1.5,
        rpm: 500.0,
        override_pct: 100.0 + (n % 100) as f64,
        position: -g * 1e-3,
        spindle_deg: g * 0.24,
        line: (n % 1000) as u32,
    }
}

fn is_generation(s: &TapState) -> Option<u64> {
    let n = (-s.position * 1e3).round() as u64;
    (generation(n) == *s).then_some(n)
}

#[test]
fn tap_state_writer_child() {
    // Only does something when started by the test below: the real writer thread, fed by a
    // cycle publishing a new state every 200 µs (entries and exits wake it at once).
    let Some(path) = std::env::var_os(CHILD_ENV) else { return };
    let file = TapStateFile { path: PathBuf::from(path) };
    let start = file.load().ok().flatten().and_then(|s| is_generation(&s)).unwrap_or(0);
    let slot = cncgw::control::tapstate::TapSlot::new(None);
    let w = cncgw::control::tapstate::TapPersister::spawn(file, slot.clone(), Duration::from_millis(1), None).unwrap();
    let wake = w.thread();
    let mut n = start;
    loop {
        n += 1;
        slot.store(&Some(generation(n)));
        wake.unpark();
        std::thread::sleep(Duration::from_micros(200));
    }
}

#[test]
fn sigkill_mid_tap_state_write_leaves_old_or_new_state() {
    let dir = tmp("kill");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("m.tap-state.toml");
    let exe = std::env::current_exe().unwrap();
    let mut last = 0;
    let mut seed = 0x9E37_79B9_7F4A_7C15u64;
    let mut sc = sim_drives::report::Scenario::new("survive/sigkill_mid_tap_state_write");
    let rounds = 25;
    for round in 0..rounds {
        let mut child = Command::new(&exe)
            .args(["--exact", "tap_return_kill::tap_state_writer_child", "--nocapture", "--test-threads=1"])
            .env(CHILD_ENV, &path)
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        std::thread::sleep(Duration::from_millis(20 + seed % 60));
        child.kill().unwrap(); // SIGKILL
        let st = child.wait().unwrap();
        sc.faults_injected += 1;
        if st.code() == Some(101) {
            sc.panics += 1;
        }
        let f = TapStateFile { path: path.clone() };
        match f.load() {
            Ok(None) => assert_eq!(last, 0, "round {round}: the file vanished after a completed write"),
            Ok(Some(s)) => match is_generation(&s) {
                Some(n) if n >= last => last = n,
                _ => {
                    sc.data_lost += 1;
                    eprintln!("round {round}: not a generation at or after {last}: {s:?}");
                }
            },
            Err(a) => {
                sc.data_lost += 1;
                eprintln!("round {round}: {a}");
            }
        }
    }
    sc.record();
    assert_eq!(sc.data_lost, 0, "torn or lost tap states");
    assert_eq!(sc.panics, 0);
    assert!(last > 0, "the writer never completed a write");
    eprintln!("{rounds} kills, last generation on disk {last}");
    // Loading removes the temporaries of the killed writers.
    let _ = TapStateFile { path: path.clone() }.load();
    let names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, ["m.tap-state.toml"], "temporaries of killed writes are cleaned up at load");
}

/// Counts allocations made on a thread while it is armed (this test binary only).
struct Counting;
static ALLOCS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
thread_local! {
    static ARMED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}
unsafe impl std::alloc::GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: std::alloc::Layout) -> *mut u8 {
        if ARMED.try_with(|a| a.get()).unwrap_or(false) {
            ALLOCS.fetch_add(1, Ordering::Relaxed);
        }
        unsafe { std::alloc::System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: std::alloc::Layout) {
        unsafe { std::alloc::System.dealloc(p, l) }
    }
}
#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn the_cycle_side_publishes_without_allocating_and_the_writer_follows() {
    use cncgw::canon::{CycleTag, Move, MoveKind, Pos, SrcPos};
    use cncgw::control::tapstate::{TapPersister, TapSlot, TapWatch};
    let dir = tmp("noalloc");
    let _ = std::fs::remove_dir_all(&dir);
    let file = TapStateFile::new(&dir, "m");
    let slot = TapSlot::new(None);
    let w = TapPersister::spawn(TapStateFile { path: file.path.clone() }, slot.clone(), Duration::from_millis(20), None).unwrap();
    let mut watch = TapWatch::new(slot, Some(w.thread()), &[0.0, 0.0, 2.0, 0.0], None);
    let mv = |z: f64, rpm: f64| Move {
        src: SrcPos::new("t.nc".into(), 5, 1),
        kind: MoveKind::Tap { end: Pos::xz(0.0, z), lead: -1.5, rpm, spindle: 1 },
        exact_stop: true,
        work_offset: Pos::ZERO,
        tag: Some(CycleTag { cycle: "G84".into(), step: 3 }),
    };
    let (m_in, m_out) = (mv(-20.0, 500.0), mv(2.0, 500.0));
    // 1000 cycles in (2 ms each, 12.5 mm/s), 1000 out, as the cycle thread would call it.
    let z = |k: usize| if k < 1000 { 2.0 - 0.022 * k as f64 } else { -20.0 + 0.022 * (k - 1000) as f64 };
    let mut in_hole_seen = false;
    ARMED.with(|a| a.set(true));
    watch.on_push(&m_in);
    watch.on_push(&m_out);
    for k in 0..=2000 {
        let p = [0.0, 0.0, z(k), (2.0 - z(k)) / 1.5 * 360.0];
        watch.on_cycle(5, &p, &p);
        if k == 500 {
            ARMED.with(|a| a.set(false));
            std::thread::sleep(Duration::from_millis(50));
            in_hole_seen = file.load().unwrap().is_some_and(|s| s.in_hole && s.position < -5.0);
            ARMED.with(|a| a.set(true));
        }
    }
    ARMED.with(|a| a.set(false));
    assert_eq!(ALLOCS.load(Ordering::Relaxed), 0, "the cycle side allocated");
    let stats = w.finish();
    assert!(in_hole_seen, "the writer had the tool in the hole on disk mid-tap");
    let end = file.load().unwrap().unwrap();
    assert!(!end.in_hole && (end.position - 2.0).abs() < 1e-9, "{end:?}");
    assert_eq!(stats.failures, 0);
    eprintln!("{} writes for one 2 × 2 s hole", stats.writes);
}

/// The entry gate with the real writer and file: at the first set-point past R the file
/// already says "in the hole" (what a SIGKILL at that instant leaves: the write was fsynced),
/// and the cycle side, gate included, does not allocate.
#[test]
fn the_first_stroke_leaves_r_only_with_the_entry_on_disk() {
    use cncgw::canon::{CycleTag, Move, MoveKind, Pos, SrcPos};
    use cncgw::control::tapstate::{TapPersister, TapSlot, TapWatch};
    use cncgw::motion::{Feedback, Limits, Motion};
    let dir = tmp("gate");
    let _ = std::fs::remove_dir_all(&dir);
    let file = TapStateFile::new(&dir, "m");
    let slot = TapSlot::new(None);
    let w = TapPersister::spawn(TapStateFile { path: file.path.clone() }, slot.clone(), Duration::from_millis(20), None).unwrap();
    let start = [0.0, 0.0, 2.0, 0.0];
    let mut watch = TapWatch::new(slot, Some(w.thread()), &start, None);
    let mut l = Limits::from_config(&cncgw::config::MachineConfig::embedded());
    l.feedback_delay = 1;
    let mut m = Motion::new(l, start);
    m.gate_taps();
    let mv = |z: f64| Move {
        src: SrcPos::new("t.nc".into(), 5, 1),
        kind: MoveKind::Tap { end: Pos::xz(0.0, z), lead: -1.5, rpm: 500.0, spindle: 1 },
        exact_stop: true,
        work_offset: Pos::ZERO,
        tag: Some(CycleTag { cycle: "G84".into(), step: 3 }),
    };
    let moves = [mv(-20.0), mv(2.0)];
    for t in &moves {
        m.push(t).unwrap();
        watch.on_push(t);
    }
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    let mut on_disk_at_entry = None;
    let mut cycles_at_r = 0;
    let t0 = Instant::now();
    ARMED.with(|a| a.set(true));
    while !m.is_idle() && t0.elapsed() < Duration::from_secs(20) {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        watch.on_cycle(sp.line, &sp.pos, &fb.pos);
        if sp.pos[2] < 2.0 && on_disk_at_entry.is_none() {
            ARMED.with(|a| a.set(false));
            on_disk_at_entry = Some(file.load());
            ARMED.with(|a| a.set(true));
        }
        cycles_at_r += m.tap_waiting().is_some() as u32;
        let open = watch.gate(m.tap_waiting()).expect("the writer answers within the timeout");
        m.open_tap_gate(open);
        // A 2 ms cycle.
        std::thread::sleep(Duration::from_millis(2));
    }
    ARMED.with(|a| a.set(false));
    assert_eq!(ALLOCS.load(Ordering::Relaxed), 0, "the cycle side allocated");
    let st = on_disk_at_entry.expect("the tool entered the hole").unwrap().expect("a state on disk");
    assert!(st.in_hole && st.r_plane == 2.0 && st.lead == -1.5 && st.axis == 'Z' && st.direction_in == -1.0 && st.line == 5, "{st:?}");
    assert!(m.is_idle() && (m.position()[2] - 2.0).abs() < 1e-9);
    let stats = w.finish();
    assert_eq!(stats.failures, 0);
    assert!(!file.load().unwrap().unwrap().in_hole);
    eprintln!(
        "the first stroke waited {cycles_at_r} cycles at R ({:.1} ms) for the entry state to be on disk",
        watch.max_ack_wait().as_secs_f64() * 1e3
    );
}
