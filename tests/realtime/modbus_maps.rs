//! Register maps as vendors have them (issue 22, docs/MODBUS_MAPS.md): holes between the
//! registers of the cyclic read (`reads`), optional registers a drive does not have
//! (`"none"`), a drive that only takes a coarser interpolation period than written, and
//! `cncgw config check --bus` finding the registers a live drive cannot read or write —
//! against sim-drives (in the test and as a process) and against a pymodbus drive (someone
//! else's register store and exceptions). Real time where `run` is used: serialized in
//! .config/nextest.toml.

use crate::modbus_common;

use modbus_common::{cncgw, on, summary, tcp_server, text, tmp, write, MODBUS_LATHE};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use testkit::Kill;

fn realistic(node: u8) -> sim_drives::ModbusQuirks {
    sim_drives::ModbusQuirks::realistic(if node == 2 { -8_000 } else { 0 })
}

/// Z's map as a drive without an interpolation period or watchdog register and with its
/// error code at 18: a hole at 17 between the statusword (10) and the error code.
const SPARSE_Z: &str = "[axes.z.cia402_map]\nerror_code = 18\ninterpolation_ms = \"none\"\ncomm_timeout_ms = \"none\"\n";

fn with_z_map(machine: &str, map: &str) -> String {
    let m = machine.replace("\n[axes.s1]", &format!("\n{map}\n[axes.s1]"));
    assert_ne!(m, machine);
    m
}

/// A drive without the optional registers runs when its map says `"none"` (skipped with a
/// warning, not refused); the hole in its feedback registers is read around with
/// `reads = "contiguous"`, while the default one-block read over it is refused naming the
/// read.
#[test]
fn a_sparse_map_runs_with_none_and_contiguous_reads() {
    let flag = Arc::new(AtomicBool::new(false));
    let served = with_z_map(MODBUS_LATHE, SPARSE_Z);
    let srv = tcp_server(&served, realistic, &flag);
    let addr = srv.local_addr().unwrap();
    let prog = write("sparse.nc", "O1\nG21\nG98\nG01 Z-2 F600\nM30\n");

    // The default read (one block 10–18 over the hole at 17): refused at start-up.
    let cfg = write("sparse-span.toml", &on(&served, addr));
    let o = cncgw(&["run", "--config", &cfg, &prog]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(3), "{t}");
    assert!(t.contains("axis z (unit 2) on link tcp: function 03 (read holding registers) at register 10 (0x000A), 9 registers"), "{t}");
    assert!(t.contains("exception 0x02 (Illegal data address)"), "{t}");

    let cfg = write("sparse.toml", &on(&with_z_map(MODBUS_LATHE, &format!("{SPARSE_Z}reads = \"contiguous\"\n")), addr));
    let o = cncgw(&["-v", "run", "--json", "--config", &cfg, &prog]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("axis z: the register map has no interpolation period register"), "{t}");
    assert!(t.contains("axis z: the register map has no communication watchdog register"), "{t}");
    let z = srv.with_drive(2, |d| d.position_unwrapped()).unwrap();
    assert!((z + 20_000).abs() <= 1, "z at {z} counts: {t}");
    // config check says what the map leaves out too.
    let o = cncgw(&["config", "check", &cfg]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("warning: axis z: the register map has no interpolation period register"), "{t}");
    flag.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}

/// A drive that interpolates only over multiples of 4 ms holds 8 ms after 5 ms is written:
/// the link follows it (every drive is told 8 ms and the link runs at 8 ms), and the program
/// ends on its end point.
#[test]
fn the_link_cycle_follows_the_drives_interpolation_period() {
    let flag = Arc::new(AtomicBool::new(false));
    let srv = tcp_server(MODBUS_LATHE, |n| sim_drives::ModbusQuirks { interpolation_grid_ms: if n == 2 { 4 } else { 0 }, ..realistic(n) }, &flag);
    let machine = on(MODBUS_LATHE, srv.local_addr().unwrap()).replace("\ntimeout_ms = 20 ", "\ncycle_ms = 5\ntimeout_ms = 20 ");
    let cfg = write("grid.toml", &machine);
    let prog = write("grid.nc", "O1\nG21\nG98\nG01 X10 Z-2 F600\nM30\n");
    let o = cncgw(&["-v", "run", "--json", "--config", &cfg, &prog]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("axis z's drive holds an interpolation period of 8 ms after 5 ms was written: the link runs at 8 ms"), "{t}");
    assert!(t.contains("link cycle 8 ms"), "{t}");
    for n in 1..=3 {
        let held = srv.with_drive(n, |d| d.object(0x60C2, 1).unwrap_or(0)).unwrap();
        assert_eq!(held, 8, "unit {n} interpolates over {held} ms: {t}");
    }
    let (x, z) = (srv.with_drive(1, |d| d.position_unwrapped()).unwrap(), srv.with_drive(2, |d| d.position_unwrapped()).unwrap());
    assert!((x - 50_000).abs() <= 1 && (z + 20_000).abs() <= 1, "x {x}, z {z}: {t}");
    flag.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}

/// A free port's address on 127.0.0.1, and a wait until something listens there.
fn free_addr() -> String {
    format!("127.0.0.1:{}", TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port())
}

fn wait_listening(addr: &str, child: &mut Kill, log: &std::path::Path) {
    let deadline = Instant::now() + Duration::from_secs(15);
    while TcpStream::connect(addr).is_err() {
        if let Ok(Some(st)) = child.0.try_wait() {
            panic!("the server exited ({st}) before listening on {addr}: {}", std::fs::read_to_string(log).unwrap_or_default());
        }
        assert!(Instant::now() < deadline, "nothing listens on {addr} after 15 s: {}", std::fs::read_to_string(log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `config check --bus` against `sim-drives` as a process: with the map the drives have,
/// every register reads and writes back (exit 0); a drive without the interpolation period
/// register (Z here) is reported by name, address and exception, as optional (exit 1).
#[test]
fn config_check_bus_reads_the_map_from_sim_drives() {
    let addr = free_addr();
    let served = write("sim-served.toml", &with_z_map(MODBUS_LATHE, "[axes.z.cia402_map]\ninterpolation_ms = \"none\"\n"));
    let log = tmp("sim-drives.log");
    let mut sim = Kill(
        Command::new(testkit::bin!("sim-drives"))
            .args(["--config", &served, "--modbus-tcp", &addr])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    wait_listening(&addr, &mut sim, &log);
    let bus = format!("modbus-tcp://{addr}");
    let shipped = concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe-modbus.toml");
    let o = cncgw(&["config", "check", shipped, "--bus", &bus]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("live: axis x (unit 1, cia402 map) on Modbus TCP"), "{t}");
    assert!(t.contains("18 register(s) read, 12 written back, none failed"), "x and the spindle have every register: {t}");
    // Z's served map table names no homing register nor the digital inputs: sim-drives
    // serves none of them (issue 24: a map table names every register its drive has).
    assert!(t.contains("axis z (unit 2): homing_method (register 24 = 0x0018, 1 register): cannot read"), "{t}");
    assert!(t.contains("axis z (unit 2): digital_inputs (register 33 = 0x0021, 2 registers): cannot read"), "{t}");
    assert!(
        t.contains("axis z (unit 2): interpolation_ms (register 20 = 0x0014, 1 register): cannot read: unit 2: exception 0x02 (Illegal data address) reading register 20 (1); so not written back — optional: if the drive has no such register, set interpolation_ms = \"none\" in [axes.z.cia402_map]"),
        "{t}"
    );
    // With the map the drive has: nothing fails.
    let o = cncgw(&["config", "check", &served, "--bus", &bus, "--json"]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "{t}");
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap_or_else(|e| panic!("{e}: {t}"));
    let live = j["live"].as_array().unwrap();
    assert_eq!(live.len(), 3, "{t}");
    assert!(live.iter().all(|a| a["failed"].as_array().unwrap().is_empty()), "{t}");
    // The PR map, checked against the cia402 drives: every PR register is missing.
    let pr = write("pr-check.toml", &MODBUS_LATHE.replace("node = 1                    # Modbus unit id", "node = 1\nmodbus_profile = \"pr\""));
    let o = cncgw(&["config", "check", &pr, "--bus", &bus]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("axis x (unit 1): block (register 25088 = 0x6200, 7 registers): cannot read"), "{t}");
}

/// build/venv's python, or None when the test is skipped on request (`CNCGW_SKIP_PYTHON=1`
/// outside CI).
fn venv_python() -> Option<PathBuf> {
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_PYTHON").as_deref() == Ok("1") && !ci {
        eprintln!("CNCGW_SKIP_PYTHON=1: pymodbus drive test skipped on request");
        return None;
    }
    let python = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("build/venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `scripts/install-test-deps.sh --python`, or set CNCGW_SKIP_PYTHON=1 to skip this test on purpose",
        python.display()
    );
    Some(python)
}

/// A Modbus spindle in speed against servos someone else built from the docs (pymodbus,
/// tests/python/modbus_servo.py: its own CiA 402 machine with 20 ms switch-on delays, a 60 ms
/// spindle, 15 ms feed axes, fault 0x8611 on its window in position): M03 S1500 and a
/// G99 turning pass run with the spindle in mode 9 and no fault, the feed per revolution
/// within 2 % of F0.15 from the spindle's measured speed.
#[test]
fn a_pymodbus_spindle_turns_in_speed_at_its_feed_per_revolution() {
    let Some(python) = venv_python() else { return };
    let addr = free_addr();
    let port = addr.rsplit(':').next().unwrap().to_string();
    let log = tmp("servo.log");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/modbus_servo.py");
    let mut py =
        Kill(Command::new(&python).args([script, &port]).stdout(std::fs::File::create(&log).unwrap()).stderr(Stdio::null()).spawn().unwrap());
    wait_listening(&addr, &mut py, &log);
    let cfg = write("servo.toml", &on(MODBUS_LATHE, addr.parse().unwrap()));
    let prog = write("servo.nc", "O1\nG21 G99 G97\nM03 S1500\nG04 X1\nG01 Z-4 F0.15\nM05\nM30\n");
    let trace = tmp("servo.csv");
    let o = cncgw(&["run", "--json", "--config", &cfg, "--trace", &trace.display().to_string(), &prog]);
    drop(py);
    let t = format!("{}\n{}", text(&o), std::fs::read_to_string(&log).unwrap_or_default());
    assert!(o.status.success(), "{t}");
    assert!(t.contains("spindle s1: in speed"), "{t}");
    // No fault: no alarm in the summary, none in the log or the servo's (the summary's own
    // keys name `rest.fault_reaction`).
    let quiet = |s: &str| !s.contains("fault");
    let servo_log = std::fs::read_to_string(&log).unwrap_or_default();
    assert!(t.contains("unit 3: mode 9") && summary(&o)["alarm"].is_null(), "{t}");
    assert!(quiet(&String::from_utf8_lossy(&o.stderr)) && quiet(&servo_log), "{t}");
    // Z's travel over the spindle's turns, the middle 80 % of line 5.
    let csv = std::fs::read_to_string(&trace).unwrap();
    let _ = std::fs::remove_file(&trace);
    let mut lines = csv.lines();
    let cols: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| cols.iter().position(|c| *c == n).unwrap();
    let (line, z, s) = (col("line"), col("z_act"), col("s1_act"));
    let rows: Vec<Vec<f64>> =
        lines.map(|l| l.split(',').map(|v| v.parse().unwrap_or(f64::NAN)).collect::<Vec<f64>>()).filter(|r| r[line] == 5.0).collect();
    assert!(rows.len() > 100, "line 5 has {} trace rows: {t}", rows.len());
    let (a, b) = (&rows[rows.len() / 10], &rows[rows.len() * 9 / 10]);
    let feed = (a[z] - b[z]).abs() / ((b[s] - a[s]).abs() / 360.0);
    eprintln!("pymodbus servos: G99 F0.15 turned at {feed:.4} mm/rev ({:+.2} %)", (feed / 0.15 - 1.0) * 100.0);
    assert!((feed / 0.15 - 1.0).abs() < 0.02, "turned at {feed:.4} mm/rev for F0.15: {t}");
}

/// `config check --bus` against a drive someone else built from the docs (pymodbus'
/// simulator device, tests/python/modbus_drive.py) that lacks the interpolation period and
/// the following-error window: both are named for each axis; the rest reads and writes.
#[test]
fn config_check_bus_finds_the_registers_a_pymodbus_drive_lacks() {
    let Some(python) = venv_python() else { return };
    let addr = free_addr();
    let port = addr.rsplit(':').next().unwrap().to_string();
    let log = tmp("pymodbus.log");
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/modbus_drive.py");
    let mut py = Kill(
        Command::new(&python)
            .args([script, &port, "1,2,3", "interpolation_ms", "following_error_window"])
            .stdout(std::fs::File::create(&log).unwrap())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    wait_listening(&addr, &mut py, &log);
    let shipped = concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe-modbus.toml");
    let o = cncgw(&["config", "check", shipped, "--bus", &format!("modbus-tcp://{addr}")]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    for (axis, unit) in [("x", 1), ("z", 2), ("s1", 3)] {
        assert!(
            t.contains(&format!("live: axis {axis} (unit {unit}, cia402 map) on Modbus TCP {addr}: 16 register(s) read, 10 written back, 2 failed:")),
            "{t}"
        );
        assert!(t.contains(&format!("axis {axis} (unit {unit}): interpolation_ms (register 20 = 0x0014, 1 register): cannot read: unit {unit}: exception 0x02 (Illegal data address)")), "{t}");
        assert!(t.contains(&format!("axis {axis} (unit {unit}): following_error_window (register 21 = 0x0015, 2 registers): cannot read")), "{t}");
    }
    // The window is not optional: no "none" hint for it.
    assert!(!t.contains("set following_error_window = \"none\""), "{t}");
}

/// Issue 24: `cncgw home` on a Modbus axis writes the axis's homing (method, offset, speeds,
/// acceleration) into the map's homing registers before mode 6. Z homes with method 34 (the
/// next index pulse moving positive, at the zero speed) and the home offset -2.5 mm: it
/// stands at -2.5 mm (plus the few counts it takes to stop) and the reference file says so.
/// A map without the method register refuses method 34 naming the register, moving nothing.
#[test]
fn home_writes_method_offset_and_speeds_into_the_homing_registers() {
    let flag = Arc::new(AtomicBool::new(false));
    let srv = tcp_server(MODBUS_LATHE, |_| sim_drives::ModbusQuirks::default(), &flag);
    let homing = "homing = { method = 34, offset = -2.5, speed = 300.0, zero_speed = 60.0, accel = 500.0 }\n";
    let machine = on(MODBUS_LATHE, srv.local_addr().unwrap())
        .replace("following_error = 1.0\n\n[axes.s1]", &format!("following_error = 1.0\n{homing}\n[axes.s1]"));
    assert!(machine.contains(homing), "lathe-modbus.toml's Z block changed");
    let state = tmp("state-home");
    let _ = std::fs::remove_dir_all(&state);
    let home = |cfg: &str| testkit::cli!().state(&state).output(&["home", "z", "--config", cfg, "--yes"]);

    // Without the method register: refused before anything is written (exit 1: an axis
    // of `cncgw home` failed).
    let cfg = write("home-nomethod.toml", &with_z_map(&machine, "[axes.z.cia402_map]\nhoming_method = \"none\"\n"));
    let o = home(&cfg);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("no register for the homing method 0x6098 (homing_method"), "{t}");
    assert_eq!(srv.with_drive(2, |d| d.object(0x6098, 0).unwrap_or(0)).unwrap(), 35, "{t}");

    let cfg = write("home.toml", &machine);
    let o = home(&cfg);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "{t}");
    assert!(t.contains("homed in mode 6 with homing method 34") && t.contains("axis Z: referenced (homing method 34)"), "{t}");
    // What the drive was given, in counts (10 000 per mm): 300 and 60 mm/min, 500 mm/s².
    let obj = |i: u16, s: u8| srv.with_drive(2, |d| d.object(i, s).unwrap_or(0)).unwrap();
    assert_eq!((obj(0x6098, 0), obj(0x607C, 0), obj(0x6099, 1), obj(0x6099, 2), obj(0x609A, 0)), (34, -25_000, 50_000, 10_000, 5_000_000), "{t}");
    let z = srv.with_drive(2, |d| d.position_unwrapped()).unwrap();
    eprintln!("Modbus home, method 34, offset -2.5 mm: Z at {z} counts");
    assert!((z + 25_000).abs() <= 50, "Z at {z} counts after homing onto -2.5 mm: {t}");
    let file = std::fs::read_dir(&state).unwrap().flatten().map(|e| e.path()).find(|p| p.display().to_string().ends_with(".reference.toml"));
    let text = std::fs::read_to_string(file.expect("reference file in the state dir")).unwrap();
    let pos: f64 = text.lines().find_map(|l| l.strip_prefix("position = ")).expect("a position in the reference").parse().unwrap();
    assert!(text.contains("[axes.z]") && text.contains("method = 34") && (pos + 2.5).abs() <= 0.005, "{text}");
    flag.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}

/// Issue 24: method 35 ("the present position is home") on a map without `homing_method`.
/// It was let through as "the drive's own homing": mode 6 ran whatever method the drive had
/// in its parameters (a switch search is motion nobody asked for) and the reference said
/// "method 35". cncgw keeps no controller-side reference shift (`mbus::homing_missing`), so
/// it is refused with alarm 2017 before anything is written or moved — by `cncgw home` and by
/// `drive home --method 35` — and `config check` says so first; no reference is recorded.
#[test]
fn method_35_on_a_map_without_the_method_register_is_refused_before_anything_moves() {
    let flag = Arc::new(AtomicBool::new(false));
    let srv = tcp_server(MODBUS_LATHE, |_| sim_drives::ModbusQuirks::default(), &flag);
    let homing = "homing = { method = 35, offset = 4.0 }\n";
    let machine = on(MODBUS_LATHE, srv.local_addr().unwrap())
        .replace("following_error = 1.0\n\n[axes.s1]", &format!("following_error = 1.0\n{homing}\n[axes.s1]"));
    assert!(machine.contains(homing), "lathe-modbus.toml's Z block changed");
    let cfg = write("home35-nomethod.toml", &with_z_map(&machine, "[axes.z.cia402_map]\nhoming_method = \"none\"\n"));
    let state = tmp("state-home35");
    let _ = std::fs::remove_dir_all(&state);
    let obj = |i: u16, s: u8| srv.with_drive(2, |d| d.object(i, s).unwrap_or(i64::MIN)).unwrap();
    let before = (obj(0x6060, 0), obj(0x6061, 0), obj(0x607C, 0), obj(0x6098, 0), srv.with_drive(2, |d| d.position_unwrapped()).unwrap());
    let untouched = |t: &str| {
        let now = (obj(0x6060, 0), obj(0x6061, 0), obj(0x607C, 0), obj(0x6098, 0), srv.with_drive(2, |d| d.position_unwrapped()).unwrap());
        assert_eq!(now, before, "the drive was written or moved (mode, mode shown, home offset, method, position): {t}");
        assert_ne!(now.1, 6, "the drive went into homing mode: {t}");
    };

    let o = testkit::cli!().state(&state).output(&["config", "check", &cfg]);
    let t = text(&o);
    assert!(t.contains("axis z: its homing (method 35) needs the homing method 0x6098 (homing_method"), "{t}");

    let o = testkit::cli!().state(&state).output(&["home", "z", "--config", &cfg, "--yes"]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("alarm 2017") && t.contains("homing method 35 refused before any motion"), "{t}");
    assert!(t.contains("not even 35") && t.contains("nothing was written or moved"), "{t}");
    assert!(!t.contains("referenced"), "{t}");
    untouched(&t);
    let refs: Vec<_> = std::fs::read_dir(&state)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.display().to_string().ends_with(".reference.toml"))
        .collect();
    for p in refs {
        let r = std::fs::read_to_string(&p).unwrap();
        assert!(!r.contains("[axes.z]"), "Z recorded referenced: {r}");
    }

    let o = testkit::cli!().state(&state).output(&["drive", "home", "2", "--method", "35", "--config", &cfg, "--yes"]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(2), "{t}");
    assert!(t.contains("alarm 2017") && t.contains("homing method 0x6098 (homing_method"), "{t}");
    untouched(&t);
    flag.store(true, Ordering::Relaxed);
    srv.join().unwrap();
}
