//! Issue 21: drives as machine builders buy them, emulated by sim-drives' named profiles
//! (`[[drive]] profile = "ip-only" | "pp-boot" | "no-1016" | "fixed-pdo"`), in simulated
//! time: `examples/first_part.nc` runs to its end point (within one count, on the drives' own
//! positions), or start-up stops before any motion with an alarm naming the object and
//! what to configure. Also start-up lists (`[[axes.NAME.sdo]]`) written and read back.

use cncgw::config::{CyclicMode, MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw::Alarm;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use sim_drives::config::Shape;
use sim_drives::{SimConfig, SimWorld};
use std::ffi::OsStr;
use std::path::Path;
use std::process::Output;

use crate::inproc_run::{run, Ran};
use crate::profiles_common;
use profiles_common::{machine_for, mixed, profiled, relaxed};

const IP: u32 = 1 << 7;

const FIRST_PART: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc");

/// `cncgw -v run --batch FLAGS --config DIR/lathe.toml REST`, its state in `dir`, RUST_LOG
/// unset (the tests read the `-v` lines).
fn run_verbose(dir: &Path, flags: &[&str], rest: &[&OsStr]) -> Output {
    let mut c = testkit::cli!().state(dir).command(&["-v", "run", "--batch"]);
    c.args(flags).arg("--config").arg(dir.join("lathe.toml")).args(rest).env_remove("RUST_LOG");
    c.output().expect("run cncgw")
}

fn first_part() -> String {
    std::fs::read_to_string(FIRST_PART).unwrap()
}

/// The default lathe with every axis in interpolated position.
fn ip_machine() -> MachineConfig {
    let mut cfg = MachineConfig::embedded();
    for a in cfg.axes.values_mut() {
        a.mode = CyclicMode::Ip;
    }
    cfg
}

impl Ran {
    /// At the end point of first_part (X100 Z5, X a diameter), within one count, on the
    /// drives' own positions.
    fn assert_at_end_point(&self) {
        let s = self.summary();
        assert!(s.at_program_end(), "{s:#?}");
        for (n, want) in [(1u8, 500_000i64), (2, 50_000)] {
            let p = self.world.drive(n).unwrap().position_unwrapped();
            assert!((p - want).abs() <= 1, "node {n} at {p}, end point {want}");
        }
    }
}

#[test]
fn ip_only_drives_run_first_part_in_interpolated_position_to_its_end_point() {
    let r = run(&ip_machine(), profiled("ip-only", |_| {}), &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        let d = r.world.drive(n).unwrap();
        assert_eq!(d.enabled_modes(), IP, "node {n} was enabled in another mode than IP");
        // Linear sub-mode and the interpolation period = the 2 ms cycle.
        assert_eq!(d.object(0x60C0, 0), Some(0), "node {n}");
        assert_eq!((d.object(0x60C2, 1), d.object(0x60C2, 2)), (Some(2), Some(-3)), "node {n}");
        // Set-points went into 0x60C1:1 by RPDO1.
        assert_eq!(d.object(0x1600, 2), Some(0x60C1_0120), "node {n}");
    }
    for a in &r.summary().axes[1..] {
        assert!(a.max_following_error < 0.05, "axis {} lagged {} mm: a jump", a.name, a.max_following_error);
    }
}

#[test]
fn csp_on_an_ip_only_drive_stops_before_motion_and_names_the_ip_key() {
    let r = run(&MachineConfig::embedded(), profiled("ip-only", |_| {}), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_MODE, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): this drive has no CSP (cyclic synchronous position) mode"), "{a}");
    assert!(a.message.contains("set axes.x.mode = \"ip\""), "{a}");
    r.assert_nothing_moved();
    // Without 0x6502 the refusal of 0x6060 = 8 (abort 0x06090030) says the same.
    let r = run(&MachineConfig::embedded(), profiled("ip-only", |s| s.supported_modes_object = false), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::SDO_CONFIG, "{a}");
    assert!(a.message.contains("it refuses 0x6060 = 8") && a.message.contains("axes.NAME.mode = \"ip\""), "{a}");
    assert!(a.message.contains("0x06090030"), "{a}");
    r.assert_nothing_moved();
}

#[test]
fn a_drive_booting_in_profile_position_is_switched_to_ip_and_confirmed_before_it_is_enabled() {
    // Boots in PP (0x6061 = 1); a new mode shows 200 SYNCs (400 ms) after 0x6060 is written.
    let sim = profiled("ip-only", |s| {
        s.boot_mode = 1;
        s.mode_switch_syncs = 200;
    });
    let r = run(&ip_machine(), sim, &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        assert_eq!(r.world.drive(n).unwrap().enabled_modes(), IP, "node {n} was enabled in PP");
    }
    assert!(r.summary().enable_time_s > 0.4, "waited for the mode: enabled after {} s", r.summary().enable_time_s);
}

/// The default lathe with `[[axes.x.sdo]]` entries appended (`(index, value, type)`, sub 0).
fn with_list(entries: &[(u16, i64, &str)]) -> MachineConfig {
    let mut t = EMBEDDED_LATHE.to_string();
    for (ix, v, ty) in entries {
        t.push_str(&format!("\n[[axes.x.sdo]]\nindex = 0x{ix:04X}\nsub = 0\nvalue = {v}\ntype = \"{ty}\"\n"));
    }
    MachineConfig::from_toml("list.toml", &t).unwrap_or_else(|e| panic!("{e}"))
}

const SHORT: &str = "G00 X20. Z2.\nM30\n";

#[test]
fn a_start_up_list_is_written_in_order_and_read_back() {
    let cfg = with_list(&[(0x2003, 1200, "u16"), (0x2005, -250, "i32"), (0x2006, 1230, "u16")]);
    let r = run(&cfg, profiled("plain", |_| {}), SHORT);
    assert!(r.summary().at_program_end(), "{:#?}", r.summary());
    let x = r.world.drive(1).unwrap();
    assert_eq!((x.object(0x2003, 0), x.object(0x2005, 0), x.object(0x2006, 0)), (Some(1200), Some(-250), Some(1230)));
    // Only axis x has a list.
    assert_eq!(r.world.drive(2).unwrap().object(0x2003, 0), Some(0));
}

#[test]
fn a_refused_start_up_write_stops_before_motion_and_leaves_the_drive_as_found() {
    // 0x2003 is taken, then 0x2004 (read-only) is refused.
    let cfg = with_list(&[(0x2003, 1200, "u16"), (0x2004, 1, "u8")]);
    let r = run(&cfg, profiled("plain", |_| {}), SHORT);
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::STARTUP_LIST, "{a}");
    assert!(
        a.message.starts_with("node 1 (axis x): start-up list axes.x.sdo[1] 0x2004:00 = 1 (u8): the drive refused the write (abort 0x06010002"),
        "{a}"
    );
    assert!(a.message.contains("nothing was enabled"), "{a}");
    r.assert_nothing_moved();
    assert_eq!(r.world.drive(1).unwrap().object(0x2003, 0), Some(0), "0x2003 written back as found");
    // Out of the drive's range: refused the same way, naming the value.
    let r = run(&with_list(&[(0x2003, 2500, "u16")]), profiled("plain", |_| {}), SHORT);
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::STARTUP_LIST, "{a}");
    assert!(a.message.contains("sdo[0] 0x2003:00 = 2500 (u16): the drive refused the write (abort 0x06090031"), "{a}");
}

#[test]
fn a_value_the_drive_keeps_otherwise_is_a_start_up_alarm_naming_both_values() {
    // The drive keeps its current limit in whole amperes: 1234 (0.1 A) reads back 1230.
    let r = run(&with_list(&[(0x2006, 1234, "u16")]), profiled("plain", |_| {}), SHORT);
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::STARTUP_LIST, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): start-up list axes.x.sdo[0] 0x2006:00 = 1234 (u16): written 1234, read back 1230"), "{a}");
    r.assert_nothing_moved();
}

#[test]
fn config_check_checks_start_up_lists_against_the_eds() {
    let eds = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds");
    let mut cfg = with_list(&[(0x2003, 1200, "u16"), (0x2003, 2500, "u16"), (0x2004, 1, "u8"), (0x2005, 7, "u32"), (0x2999, 1, "u8")]);
    cfg.axes.get_mut("x").unwrap().eds = Some(eds.to_string());
    let m = CanOpenMaster::new(InprocBus::new().endpoint(), &cfg);
    let p = m.offline_check(cfg.bus.bitrate);
    assert_eq!(p.len(), 4, "{p:#?}");
    assert!(p[0].starts_with("axes.x.eds: axes.x.sdo[1] 0x2003:00 = 2500 (u16): above the EDS's HighLimit 2000"), "{}", p[0]);
    assert!(p[1].starts_with("axes.x.eds: axes.x.sdo[2] 0x2004:00 = 1 (u8): ") && p[1].contains("AccessType=ro"), "{}", p[1]);
    assert!(p[2].contains("axes.x.sdo[3] 0x2005:00 = 7 (u32): the EDS gives DataType INTEGER32, the entry says u32"), "{}", p[2]);
    assert!(p[3].contains("axes.x.sdo[4] 0x2999:00 = 1 (u8): ") && p[3].contains("0x2999:00 is not in the EDS"), "{}", p[3]);
    // Values outside the type and objects start-up owns are refused when the file is read.
    let t = format!("{EMBEDDED_LATHE}\n[[axes.z.sdo]]\nindex = 0x2003\nvalue = 70000\ntype = \"u16\"\n[[axes.z.sdo]]\nindex = 0x1600\nsub = 1\nvalue = 0\ntype = \"u32\"\n");
    let e = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
    assert!(e.contains("axes.z.sdo[0]: value 70000 does not fit type u16 (0 … 65535)"), "{e}");
    assert!(e.contains("axes.z.sdo[1]: 0x1600 is configured by start-up itself"), "{e}");
}

#[test]
fn drives_without_a_heartbeat_consumer_are_guarded_and_run_to_the_end_point() {
    let r = run(&MachineConfig::embedded(), profiled("no-1016", |_| {}), &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        // Guarded (life time factor 3, the heartbeat producer off: CiA 301 has one or the
        // other); the exit switched the guard time off again (0x100C = 0).
        let d = r.world.drive(n).unwrap();
        assert_eq!((d.object(0x100D, 0), d.object(0x1017, 0), d.object(0x100C, 0)), (Some(3), Some(0), Some(0)), "node {n}");
        assert!(!r.master.guarded(n), "node {n}: guarding ended with the run");
    }
}

/// `cncgw -v run --batch` with `--config` = the default lathe with `extra` after each axis'
/// node line, and a sim-drives file giving nodes 1–3 the named profiles. (code, stdout, stderr)
fn cli_run(name: &str, modes: [&str; 3], profiles: [&str; 3]) -> (i32, String, String) {
    let dir = std::env::temp_dir().join(format!("cncgw_drive_profiles_{name}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut sim = String::new();
    let mut lathe = EMBEDDED_LATHE.to_string();
    for (k, (kind, axis, cpu)) in [("linear", "x", 10000.0), ("linear", "z", 10000.0), ("spindle", "s1", 1000.0)].into_iter().enumerate() {
        let node = k + 1;
        sim.push_str(&format!(
            "[[drive]]\nnode = {node}\nkind = \"{kind}\"\naxis = \"{axis}\"\ncounts_per_unit = {cpu:?}\nprofile = \"{}\"\n",
            profiles[k]
        ));
        lathe = lathe.replacen(&format!("\nnode = {node}\n"), &format!("\nnode = {node}\nmode = \"{}\"\n", modes[k]), 1);
    }
    std::fs::write(dir.join("drives.toml"), sim).unwrap();
    std::fs::write(dir.join("lathe.toml"), lathe).unwrap();
    let drives = dir.join("drives.toml");
    let o = run_verbose(&dir, &[], &[OsStr::new("--sim-config"), drives.as_os_str(), OsStr::new(FIRST_PART)]);
    let _ = std::fs::remove_dir_all(&dir);
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn cncgw_run_logs_per_drive_the_mode_mapping_and_error_control_it_chose_and_why() {
    let (code, out, err) = cli_run("mix", ["ip", "csp", "csp"], ["ip-only", "no-1016", "pp-boot"]);
    assert_eq!(code, 0, "{out}{err}");
    assert_eq!(out.matches("ok (within 1 count)").count(), 2, "{out}");
    let line = |node: u8| {
        err.lines()
            .find(|l| l.contains("start-up: mode") && l.contains(&format!("node={node}")))
            .unwrap_or_else(|| panic!("no start-up line for node {node}: {err}"))
    };
    let x = line(1);
    assert!(x.contains("start-up: mode IP (interpolated position) (axes.x.mode = \"ip\")"), "{x}");
    assert!(x.contains("mapping: remapped RPDO1 0x201 = controlword + 0x60C1:01"), "{x}");
    assert!(x.contains("error control: heartbeat both ways"), "{x}");
    let z = line(2);
    assert!(z.contains("error control: node guarding (no 0x1016 heartbeat consumer): 0x100C = 100 ms, 0x100D = 3"), "{z}");
    let s = line(3);
    assert!(s.contains("mode CSP (cyclic synchronous position) (the default), booted in profile position (1) and switched by 0x6060"), "{s}");
}

#[test]
fn fixed_pdo_drives_run_on_their_own_mapping() {
    let r = run(&MachineConfig::embedded(), profiled("fixed-pdo", |_| {}), &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        let d = r.world.drive(n).unwrap();
        // Their mapping as at power-on (statusword + position: 0x6061 polled by SDO).
        assert_eq!((d.object(0x1A00, 0), d.object(0x1A00, 2)), (Some(2), Some(0x6064_0020)), "node {n}");
        assert_eq!(r.master.mode_display(n), Some(8), "node {n}: its mode was read");
    }
}

#[test]
fn a_fixed_mapping_without_the_ip_target_stops_before_motion_naming_the_object() {
    // IP but no CSP, and a fixed RPDO1 of controlword + 0x607A (CSP's target).
    let r = run(&ip_machine(), profiled("ip-only", |s| s.fixed_pdo = true), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::FIXED_PDO, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): RPDO1 cannot be remapped (SDO abort 0x06010002"), "{a}");
    assert!(
        a.message.contains(
            "the drive's own mapping [0x6040:00 (16 bit), 0x607A:00 (32 bit)] will not do: it carries 0x607A:00 (CSP's target), not 0x60C1:01"
        ),
        "{a}"
    );
    r.assert_nothing_moved();
}

// ---- Over socketcand on loopback, in real time: sim-drives' server with shaped drives, and
// `cncgw run --bus socketcand://…` as an operator runs it.

#[test]
fn ip_only_fixed_pdo_and_pp_boot_drives_over_socketcand_end_at_the_end_point() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let server = sim_drives::socketcand::SocketcandServer::bind("127.0.0.1:0", "can0").expect("bind");
    let addr = server.local_addr().to_string();
    let sim = mixed(["ip-only", "fixed-pdo", "pp-boot"], None);
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    let hub = std::thread::spawn(move || sim_drives::run_realtime(Box::new(server), sim, s));
    let dir = std::env::temp_dir().join(format!("cncgw_drive_profiles_socketcand_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let lathe = machine_for(EMBEDDED_LATHE, ["ip-only", "fixed-pdo", "pp-boot"]);
    std::fs::write(dir.join("lathe.toml"), lathe).unwrap();
    std::fs::write(dir.join("short.nc"), "G98 G00 X40. Z2.\nG01 Z-10. F1200\nG00 X60. Z5.\nM30\n").unwrap();
    let o = run_verbose(&dir, &["--bus", &format!("socketcand://{addr}/can0")], &[dir.join("short.nc").as_os_str()]);
    stop.store(true, Ordering::Relaxed);
    let _ = hub.join();
    let _ = std::fs::remove_dir_all(&dir);
    let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.status.code(), Some(0), "{out}{err}");
    assert_eq!(out.matches("ok (within 1 count)").count(), 2, "{out}");
    assert!(err.contains("start-up: mode IP (interpolated position) (axes.x.mode = \"ip\")"), "{err}");
    assert!(err.contains("fixed RPDO1 0x202 = [0x6040:00 (16 bit), 0x607A:00 (32 bit)]"), "{err}");
    assert!(err.contains("booted in profile position (1) and switched by 0x6060"), "{err}");
}

#[test]
fn every_example_profile_in_config_drives_runs_first_part_to_its_end_point() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/config/drives");
    let ip = MachineConfig::load(std::path::Path::new(&format!("{dir}/lathe-ip.toml"))).unwrap();
    assert_eq!(ip.axes["z"].sdo.len(), 1);
    let mut seen = 0;
    for name in Shape::PROFILES.iter().filter(|&&p| p != "plain") {
        let sim = SimConfig::from_file(std::path::Path::new(&format!("{dir}/{name}.toml"))).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(sim.drives.iter().all(|d| Some(&d.shape) == Shape::profile(name).as_ref()), "{name}: every drive of the profile");
        let cfg = match *name {
            "ip-only" => ip.clone(),
            "user-units" => MachineConfig::load(std::path::Path::new(&format!("{dir}/lathe-user-units.toml"))).unwrap(),
            _ => MachineConfig::embedded(),
        };
        let r = run(&cfg, sim, &first_part());
        if *name == "user-units" {
            // On the drives' own positions in µm: X50 (radius) is 50000 units, 500000 increments.
            let s = r.summary();
            assert!(s.at_program_end(), "{s:#?}");
            let (x, z) = (r.world.drive(1).unwrap(), r.world.drive(2).unwrap());
            assert_eq!((x.position_actual(), z.position_actual()), (50_000, 5_000));
        } else {
            r.assert_at_end_point();
        }
        seen += 1;
    }
    assert_eq!(seen, 5);
}

#[test]
fn an_ip_drive_that_stops_being_active_while_running_is_alarm_2005() {
    let cfg = ip_machine();
    let interp = Interpreter::from_source("first_part.nc", &first_part(), &cfg).unwrap();
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, profiled("ip-only", |_| {}));
    // 3 s in (the run is under way): Z's IP buffer goes off, as on an underrun.
    world.schedule_faults(vec![sim_drives::FaultAt { node: 2, sub: 10, value: 1, at_ns: 3_000_000_000 }]);
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let mut summary = RunSummary::default();
    let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(&cfg), cfg.spindle_index(), 2_000_000);
    let r = run_program(&mut lp, interp, &mut summary);
    lp.finish();
    let a = r.expect_err("the run must stop");
    assert_eq!(a.number, cncgw::alarm::DRIVE_MODE, "{a}");
    assert!(a.message.starts_with("node 2 (axis z): statusword bit 12 (ip mode active) dropped while running"), "{a}");
    assert!(!summary.at_program_end());
}

#[test]
fn drives_without_the_objects_the_master_only_prefers_are_warned_about_not_refused() {
    // No 0x605A quick stop option, no stop reactions, no 0x607D software limits.
    let r = run(&MachineConfig::embedded(), profiled("plain", |s| s.optional_402_objects = false), &first_part());
    r.assert_at_end_point();
    let x = r.world.drive(1).unwrap();
    assert_eq!((x.object(0x605A, 0), x.object(0x607D, 1)), (None, None), "the drive really lacks them");
}

#[test]
fn a_profile_move_and_homing_on_an_ip_axis_come_back_to_ip_without_an_alarm() {
    use cncgw::drives::DriveBus;
    use cncgw_bus::Clock;
    let cfg = ip_machine();
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, profiled("ip-only", |_| {}));
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).unwrap_or_else(|a| panic!("{a}"));
    m.profile_move(&mut w, 1, 10.0, 50.0, 500.0).unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(m.mode_display(1), Some(7), "back in IP");
    m.home(&mut w, 2, 35, 10.0, 1.0, 100.0, 2000).unwrap_or_else(|a| panic!("{a}"));
    assert_eq!(m.mode_display(2), Some(7), "back in IP");
    // Half a second of cycles holding there: IP active again, no alarm 2005.
    let mut t = w.now_ns();
    for _ in 0..250 {
        t += 2_000_000;
        w.wait_until(t);
        m.receive(t).unwrap_or_else(|a| panic!("{a}"));
        m.transmit(t).unwrap_or_else(|a| panic!("{a}"));
    }
    let x = w.drive(1).unwrap();
    assert!((x.position_unwrapped() - 100_000).abs() <= 10, "{}", x.position_unwrapped());
    assert_eq!(x.statusword() & 0x1000, 0x1000, "ip mode active");
    assert_eq!(x.enabled_modes(), 1 << 7 | 1 << 1, "IP and PP only");
}

// ---- External SYNC (bus.sync = "external", issue 21 item 6): node 1 produces SYNC
// (0x1005 bit 30) and the master's cycle runs on it.

/// The master's bus, counting the SYNCs the master sends (it must send none).
struct CountSyncs<B> {
    inner: B,
    sent: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl<B: cncgw_bus::CanBus> cncgw_bus::CanBus for CountSyncs<B> {
    fn send(&mut self, f: &cncgw_bus::CanFrame) -> Result<(), cncgw_bus::BusError> {
        if cncgw_bus::sync_source::is_sync(f) {
            self.sent.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        self.inner.send(f)
    }
    fn try_recv(&mut self) -> Result<Option<cncgw_bus::CanFrame>, cncgw_bus::BusError> {
        self.inner.try_recv()
    }
    fn recv_timeout(&mut self, t: std::time::Duration) -> Result<Option<cncgw_bus::CanFrame>, cncgw_bus::BusError> {
        self.inner.recv_timeout(t)
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
}

/// The default lathe's drives with node 1 producing SYNC every 2 ms.
fn sync_from_node_1() -> SimConfig {
    mixed(["plain"; 3], Some(2000))
}

struct RanExt {
    result: Result<(), Alarm>,
    summary: RunSummary,
    world: SimWorld,
    track: cncgw_bus::sync_source::SyncTrack,
    master_syncs: u64,
}

/// `program` with `bus.sync = "external"`, the cycle waiting on the SYNC node 1 produces.
fn run_external(sim: SimConfig, program: &str, faults: Vec<sim_drives::FaultAt>) -> RanExt {
    run_external_on(MachineConfig::embedded(), sim, program, faults)
}

/// `run_external` on the machine `cfg`.
fn run_external_on(mut cfg: MachineConfig, sim: SimConfig, program: &str, faults: Vec<sim_drives::FaultAt>) -> RanExt {
    cfg.bus.sync = cncgw::config::SyncSource::External;
    let interp = Interpreter::from_source("first_part.nc", program, &cfg).expect("program parses");
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, sim);
    world.schedule_faults(faults);
    let sent = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counted = CountSyncs { inner: wire.endpoint(), sent: sent.clone() };
    let (bus, mut clock) = cncgw_bus::sync_source::external_sync(Box::new(counted), &mut world, cfg.cycle_ns());
    let mut master = CanOpenMaster::new(bus, &cfg);
    let mut summary = RunSummary::default();
    let result = {
        let mut lp = CycleLoop::new(&mut master, &mut clock, Limits::from_config(&cfg), cfg.spindle_index(), cfg.cycle_ns());
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    let track = clock.track();
    drop(clock);
    RanExt { result, summary, world, track, master_syncs: sent.load(std::sync::atomic::Ordering::Relaxed) }
}

#[test]
fn first_part_runs_to_its_end_point_on_a_sync_produced_by_a_drive() {
    let r = run_external(sync_from_node_1(), &first_part(), Vec::new());
    if let Err(a) = &r.result {
        panic!("{a}");
    }
    assert!(r.summary.at_program_end(), "{:#?}", r.summary);
    for (n, want) in [(1u8, 500_000i64), (2, 50_000)] {
        let p = r.world.drive(n).unwrap().position_unwrapped();
        assert!((p - want).abs() <= 1, "node {n} at {p}, end point {want}");
    }
    assert_eq!(r.master_syncs, 0, "the master sent SYNC although bus.sync = \"external\"");
    // Every cycle woke on a SYNC of node 1: SYNC went missing only while start-up's NMT
    // reset rebooted the producer, and there were at least as many SYNCs as cycles.
    assert!(r.track.unlocks() <= 1, "{:?}", r.track);
    assert!(r.track.syncs() >= r.summary.cycles, "{} SYNCs, {} cycles", r.track.syncs(), r.summary.cycles);
}

#[test]
fn an_external_sync_that_stops_is_alarm_2022_and_a_controlled_stop() {
    let mute = sim_drives::FaultAt { node: 1, sub: sim_drives::drive::fault_sub::SYNC_MUTED, value: 1, at_ns: 3_000_000_000 };
    let r = run_external(sync_from_node_1(), &first_part(), vec![mute]);
    let Err(a) = &r.result else {
        panic!(
            "the run ended although SYNC stopped: {:?} master SYNCs {} world at {} 0x2100:11 = {:?}",
            r.track,
            r.master_syncs,
            r.world.now_ns(),
            r.world.drive(1).unwrap().object(0x2100, 11)
        )
    };
    assert_eq!(a.number, cncgw::alarm::SYNC_LOST, "{a}");
    assert!(a.message.contains("external SYNC lost") && a.message.contains("stopped under control"), "{a}");
    // Stopped where SYNC went (3 s), not at the program's end (33.5 s). The path stop is a
    // controlled one; the emulated drives, seeing no SYNC, stop on their own watchdog, which
    // the master then answers with quick stop (`rest`).
    assert!(r.summary.machining_time_s < 3.5 && !r.summary.ended, "{:#?}", r.summary);
    assert_eq!(r.master_syncs, 0);
    assert!(r.track.unlocks() >= 1);
}

#[test]
fn external_sync_without_a_producer_stops_before_start_up() {
    let r = run_external(SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(), &first_part(), Vec::new());
    let a = r.result.as_ref().expect_err("started without SYNC");
    assert_eq!(a.number, cncgw::alarm::SYNC_LOST, "{a}");
    assert!(a.message.contains("no SYNC (COB-ID 0x080) was heard"), "{a}");
    for n in 1..=3 {
        assert_eq!(r.world.drive(n).unwrap().enabled_modes(), 0);
    }
}

#[test]
fn first_part_over_socketcand_runs_on_the_sync_drive_1_produces_and_ends_within_one_count() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let server = sim_drives::socketcand::SocketcandServer::bind("127.0.0.1:0", "can0").expect("bind");
    let addr = server.local_addr().to_string();
    let stop = std::sync::Arc::new(AtomicBool::new(false));
    let s = stop.clone();
    // The vcan tier's relaxed timing (profiles_common::relaxed): on this shared machine the
    // cycle thread wakes late now and then, and with an external SYNC a late set-point misses
    // its SYNC (the master's own SYNC would wait for it). A 4 ms cycle, a 90° spindle window.
    let sim = mixed(["plain"; 3], Some(4000));
    let hub = std::thread::spawn(move || sim_drives::run_realtime(Box::new(server), sim, s));
    let dir = std::env::temp_dir().join(format!("cncgw_drive_profiles_extsync_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let lathe = relaxed(EMBEDDED_LATHE, true);
    std::fs::write(dir.join("lathe.toml"), lathe).unwrap();
    let o = run_verbose(&dir, &["--json", "--bus", &format!("socketcand://{addr}/can0")], &[OsStr::new(FIRST_PART)]);
    stop.store(true, Ordering::Relaxed);
    let _ = hub.join();
    let _ = std::fs::remove_dir_all(&dir);
    let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.status.code(), Some(0), "{out}{err}");
    assert!(err.contains("cycle on the external SYNC") && err.contains("external SYNC heard"), "{err}");
    assert!(err.contains("the drive produces the SYNC the cycle runs on"), "{err}");
    profiles_common::assert_json_at_end_point(&out);
}

/// The vcan tier's profile sets (profiles_common::MIXED_SETS), here in simulated time: the
/// combination itself (which the vcan tier then runs in real time between two processes)
/// ends first_part at its end point, on the drives' own positions; the second set on the
/// SYNC of its node 1 too, as the vcan tier also runs it.
#[test]
fn the_vcan_tiers_mixed_profile_sets_run_first_part_to_its_end_point() {
    let (b, _) = profiles_common::MIXED_SETS[1];
    for (profiles, external) in profiles_common::MIXED_SETS.into_iter().chain([(b, true)]) {
        let cfg = MachineConfig::from_toml("mixed.toml", &machine_for(EMBEDDED_LATHE, profiles)).unwrap_or_else(|e| panic!("{e}"));
        let (summary, world) = if external {
            let r = run_external_on(cfg, mixed(profiles, Some(2000)), &first_part(), Vec::new());
            assert!(r.result.is_ok(), "{profiles:?}: {:?}", r.result);
            assert_eq!(r.master_syncs, 0);
            (r.summary, r.world)
        } else {
            let r = run(&cfg, mixed(profiles, None), &first_part());
            (r.summary().clone(), r.world)
        };
        assert!(summary.at_program_end(), "{profiles:?}: {summary:#?}");
        // X100 (a diameter: radius 50 mm) Z5, in increments (10000/mm) or user units (1000/mm).
        for (k, want) in [500_000i64, 50_000].into_iter().enumerate() {
            let d = world.drive(k as u8 + 1).unwrap();
            let (p, want) = if profiles[k] == "user-units" { (d.position_actual() as i64, want / 10) } else { (d.position_unwrapped(), want) };
            assert!((p - want).abs() <= 1, "{profiles:?}: node {} at {p}, end point {want}", k + 1);
        }
        if profiles[0] == "ip-only" {
            assert_eq!(world.drive(1).unwrap().enabled_modes(), IP, "X ran in IP");
        }
    }
}
