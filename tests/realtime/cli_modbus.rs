//! The service commands on a Modbus bus (`--bus modbus-tcp://HOST:PORT`) against the
//! `sim-drives --modbus-tcp` binary on loopback: scan, drive status, monitor (read-only, from
//! the holding registers) and jog (through the controller's Modbus master), all parsed from
//! `--json`. Real time: serialized in .config/nextest.toml. Needs the workspace's binaries
//! (`cargo build --workspace --bins`).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use testkit::Kill;

use testkit::Out;

fn cncgw(args: &[&str]) -> Out {
    testkit::cli!().run(args)
}

fn json(o: &Out) -> serde_json::Value {
    serde_json::from_str(o.stdout.trim()).unwrap_or_else(|e| panic!("not JSON ({e}): {}\n{}", o.stdout, o.stderr))
}

/// `sim-drives --modbus-tcp 127.0.0.1:PORT` (the default lathe's drives, units 1–3).
fn sim_drives() -> (Kill, String) {
    sim_drives_with(&[])
}

/// The same with more arguments (`--fault …`, `--config …`).
fn sim_drives_with(extra: &[&str]) -> (Kill, String) {
    let bin = std::path::Path::new(env!("CARGO_BIN_EXE_cncgw")).with_file_name("sim-drives");
    assert!(bin.exists(), "{} is missing: run `cargo build --workspace --bins` first", bin.display());
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let child = Command::new(bin).args(["--modbus-tcp", &addr]).args(extra).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let k = Kill(child);
    let t0 = Instant::now();
    while std::net::TcpStream::connect(&addr).is_err() {
        assert!(t0.elapsed() < Duration::from_secs(10), "sim-drives did not listen on {addr}");
        std::thread::sleep(Duration::from_millis(50));
    }
    (k, format!("modbus-tcp://{addr}"))
}

#[test]
fn service_commands_on_modbus_tcp() {
    let (_sim, bus) = sim_drives();
    let b = bus.as_str();

    let o = cncgw(&["scan", "--bus", b, "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    let nodes = v["nodes"].as_array().unwrap();
    let units: Vec<u64> = nodes.iter().map(|n| n["unit"].as_u64().unwrap()).collect();
    assert_eq!(units, [1, 2, 3]);
    for n in nodes {
        assert!(n["error"].is_null(), "{n}");
        assert_eq!(n["state"], "Switch On Disabled", "{n}");
        assert_eq!(n["profile"], "cia402");
    }
    // The table for a person.
    let o = cncgw(&["scan", "--bus", b]);
    assert_eq!(o.code, 0);
    assert!(o.stdout.contains("Modbus TCP 127.0.0.1:") && o.stdout.contains("Switch On Disabled"), "{}", o.stdout);

    let o = cncgw(&["drive", "status", "2", "--bus", b, "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    assert_eq!((v["axis"].as_str(), v["statusword"].as_str(), v["position"].as_f64()), (Some("z"), Some("0x0250"), Some(0.0)));
    assert_eq!(v["bits"].as_array().unwrap().len(), 16);
    let o = cncgw(&["drive", "status", "9", "--bus", b]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("no axis of the configuration has Modbus unit id 9"), "{}", o.stderr);

    let o = cncgw(&["monitor", "--once", "--bus", b, "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(json(&o)["drives"].as_array().unwrap().len(), 3);

    // Moving iron on a real bus needs --yes.
    let o = cncgw(&["jog", "z", "--by", "-5", "--bus", b]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("--yes"), "{}", o.stderr);
    let o = cncgw(&["jog", "z", "--by", "-5", "--speed", "600", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    assert!(o.stdout.starts_with("axis z (unit 2): 0.0000 → -"), "{}", o.stdout);
    // The drives keep their position between commands: read it back from the registers.
    let v = json(&cncgw(&["drive", "status", "2", "--bus", b, "--json"]));
    let z = v["position"].as_f64().unwrap();
    assert!((z + 5.0).abs() <= 2e-4, "Z at {z} after jogging by -5");
    // Homing in mode 6, method 35 (here is home) with the home offset written to its
    // register: Z reads 3; again without an offset: 0.
    let o = cncgw(&["drive", "home", "2", "--bus", b]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("--yes"), "{}", o.stderr);
    let o = cncgw(&["drive", "home", "2", "--offset", "3", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("homing method 35") && o.stdout.contains("position now 3.0000 mm"), "{}", o.stdout);
    let o = cncgw(&["drive", "home", "2", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("homed in mode 6") && o.stdout.contains("position now 0.0000 mm"), "{}", o.stdout);
    let v = json(&cncgw(&["drive", "status", "2", "--bus", b, "--json"]));
    assert_eq!((v["position"].as_f64(), v["state"].as_str(), v["mode"].as_i64()), (Some(0.0), Some("Switch On Disabled"), Some(8)), "{v}");
    let o = cncgw(&["jog", "z", "--to", "10", "--bus", b, "--yes"]);
    assert_eq!(o.code, 2, "{}", o.stderr);
    assert!(o.stderr.contains("outside axis z's travel"), "{}", o.stderr);

    // CANopen-only commands say so.
    let o = cncgw(&["sdo", "read", "1", "0x6041", "0", "--bus", b]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("is a Modbus bus: this is a CANopen command"), "{}", o.stderr);
}

#[test]
fn modbus_bus_errors_say_what_to_do() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let bus = format!("modbus-tcp://127.0.0.1:{port}");
    let o = cncgw(&["scan", "--bus", &bus]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("sim-drives --modbus-tcp"), "{}", o.stderr);
    let o = cncgw(&["scan", "--bus", "modbus-rtu:///dev/null-no-such-tty?baud=9600"]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("/dev/null-no-such-tty"), "{}", o.stderr);
    let o = cncgw(&["scan", "--bus", "modbus-rtu:///dev/ttyUSB0?baud=fast"]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("baud=fast is not a number"), "{}", o.stderr);
}

/// Disable → enable → status on every unit; the enabled drive stays enabled (no watchdog
/// left from a previous controller run).
#[test]
fn drive_enable_disable_on_modbus_tcp() {
    let (_sim, bus) = sim_drives();
    let b = bus.as_str();
    let o = cncgw(&["drive", "enable", "1", "--bus", b]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("--yes"), "{}", o.stderr);
    // A controller run leaves the drives' watchdog set (whether or not the jog itself
    // keeps its 2 ms link cycle on a loaded machine).
    let _ = cncgw(&["jog", "x", "--by", "1", "--speed", "600", "--bus", b, "--yes"]);

    let o = cncgw(&["drive", "disable", "1", "--bus", b]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.starts_with("unit 1 (axis x) on Modbus TCP 127.0.0.1:"), "{}", o.stdout);
    assert!(o.stdout.contains("Switch On Disabled"), "{}", o.stdout);
    let x0 = json(&cncgw(&["drive", "status", "1", "--bus", b, "--json"]))["position"].as_f64().unwrap();
    let o = cncgw(&["drive", "enable", "1", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains(" → Operation Enabled (statusword 0x"), "{}", o.stdout);
    assert!(o.stdout.contains("mode 8 (cyclic synchronous position)"), "{}", o.stdout);
    // Still enabled well after the 200 ms watchdog the jog set, and where it was.
    std::thread::sleep(Duration::from_millis(600));
    let v = json(&cncgw(&["drive", "status", "1", "--bus", b, "--json"]));
    assert_eq!(v["state"], "Operation Enabled", "{v}");
    assert!((v["position"].as_f64().unwrap() - x0).abs() <= 2e-4, "{v} (was at {x0})");
    let o = cncgw(&["drive", "enable", "1", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Operation Enabled (statusword 0x") && o.stdout.contains("already there"), "{}", o.stdout);
    let o = cncgw(&["drive", "fault-reset", "1", "--bus", b]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("not in fault, nothing to reset"), "{}", o.stdout);
    let o = cncgw(&["drive", "disable", "1", "--bus", b]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Operation Enabled → Switch On Disabled"), "{}", o.stdout);
    assert_eq!(json(&cncgw(&["drive", "status", "1", "--bus", b, "--json"]))["state"], "Switch On Disabled");
    let o = cncgw(&["drive", "enable", "9", "--bus", b, "--yes"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("no axis of the configuration has Modbus unit id 9"), "{}", o.stderr);
}

/// A fault injected in the emulated drive: disable says so, fault-reset clears it, enable
/// then reaches Operation Enabled.
#[test]
fn drive_fault_reset_on_modbus_tcp() {
    let (_sim, bus) = sim_drives_with(&["--fault", "3:raise=0x2310"]);
    let b = bus.as_str();
    let v = json(&cncgw(&["drive", "status", "3", "--bus", b, "--json"]));
    assert_eq!((v["state"].as_str(), v["error_code"].as_str()), (Some("Fault"), Some("0x2310")), "{v}");
    let o = cncgw(&["drive", "disable", "3", "--bus", b]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("unit 3 is in Fault (no torque): error code 0x2310") && o.stderr.contains("cncgw drive fault-reset 3"), "{}", o.stderr);
    let o = cncgw(&["drive", "fault-reset", "3", "--bus", b]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Fault → Switch On Disabled"), "{}", o.stdout);
    let o = cncgw(&["drive", "enable", "3", "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Switch On Disabled → Operation Enabled"), "{}", o.stdout);
    let v = json(&cncgw(&["drive", "status", "3", "--bus", b, "--json"]));
    assert_eq!((v["state"].as_str(), v["error_code"].as_str()), (Some("Operation Enabled"), Some("0x0000")), "{v}");
}

/// The PR register map: servo on / off through its register, homing refused.
#[test]
fn pr_drive_power_on_modbus_tcp() {
    let lathe = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe.toml")).unwrap();
    assert!(lathe.contains("[axes.z]\n"));
    let cfg = lathe.replace("[axes.z]\n", "[axes.z]\nmodbus_profile = \"pr\"\n");
    let path = std::env::temp_dir().join(format!("cncgw-mbsvc-pr-{}.toml", std::process::id()));
    std::fs::write(&path, cfg).unwrap();
    let p = path.to_str().unwrap();
    let (_sim, bus) = sim_drives_with(&["--config", p]);
    let b = bus.as_str();
    let o = cncgw(&["drive", "enable", "2", "--config", p, "--bus", b, "--yes"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Switch On Disabled → Operation Enabled (status register 0x") && o.stdout.contains("servo on"), "{}", o.stdout);
    let v = json(&cncgw(&["drive", "status", "2", "--config", p, "--bus", b, "--json"]));
    assert_eq!((v["profile"].as_str(), v["state"].as_str()), (Some("pr"), Some("Operation Enabled")), "{v}");
    let o = cncgw(&["drive", "disable", "2", "--config", p, "--bus", b]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("Operation Enabled → Switch On Disabled"), "{}", o.stdout);
    let o = cncgw(&["drive", "home", "2", "--config", p, "--bus", b, "--yes"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("not supported by this register map"), "{}", o.stderr);
    let _ = std::fs::remove_file(&path);
}

/// Issue 24: homing onto a limit switch over Modbus. sim-drives (the process) serves Z's
/// negative limit switch at -3 mm (physical counts, `[axes.z.emulate] switches`), seen in the
/// map's `digital_inputs` (0x60FD) as on CANopen. `cncgw home z` with method 17 (search the
/// negative switch, home where it releases) and offset 1.5 mm: Z stands at 1.5 mm and the
/// reference file says method 17 at that position. Then a vendor map table that does not
/// name the homing registers (the drive has none): method 17 is alarm 2017 before anything
/// is written or moved, and `config check` says so first.
#[test]
fn home_onto_the_negative_limit_switch_over_modbus_tcp() {
    let lathe = include_str!("../../config/lathe-modbus.toml");
    let homing = "homing = { method = 17, offset = 1.5, speed = 600.0, zero_speed = 60.0 }\n[axes.z.emulate]\nswitches = { negative = -30000 }\n";
    let machine = lathe.replace("following_error = 1.0\n\n[axes.s1]", &format!("following_error = 1.0\n{homing}\n[axes.s1]"));
    assert!(machine.contains(homing), "lathe-modbus.toml's Z block changed");
    let dir = testkit::tmp!("cli_modbus", "home-switch");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("machine.toml");
    std::fs::write(&cfg, &machine).unwrap();
    let (_sim, bus) = sim_drives_with(&["--config", cfg.to_str().unwrap()]);
    let addr = bus.trim_start_matches("modbus-tcp://").to_string();
    let machine = machine.replace("address = \"127.0.0.1:5020\"", &format!("address = \"{addr}\""));
    std::fs::write(&cfg, &machine).unwrap();
    let state = dir.join("state");
    let cli = || testkit::cli!().state(&state);

    let o = cli().run(&["home", "z", "--config", cfg.to_str().unwrap(), "--yes"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.contains("homed in mode 6 with homing method 17") && o.stdout.contains("axis Z: referenced (homing method 17)"), "{}", o.stdout);
    let o = cli().run(&["drive", "status", "2", "--config", cfg.to_str().unwrap(), "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    let z = v["position"].as_f64().or_else(|| v[0]["position"].as_f64()).unwrap_or_else(|| panic!("{v}"));
    eprintln!("Modbus home, method 17, switch at -3 mm, offset 1.5 mm: Z at {z:.4} mm");
    assert!((z - 1.5).abs() <= 0.005, "Z at {z} mm after homing onto 1.5 mm: {v}");
    // Homed at the switch's edge and stopped just past it: off the switch (bit 0 clear).
    assert_eq!(v["digital_inputs"], 0, "{v}");
    // 0.5 mm further negative it is on the switch: bit 0 of 0x60FD.
    let o = cli().run(&["jog", "z", "--to", "1.0", "--config", cfg.to_str().unwrap(), "--yes"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let v = json(&cli().run(&["drive", "status", "2", "--config", cfg.to_str().unwrap(), "--json"]));
    assert_eq!(v["digital_inputs"], 1, "{v}");
    let z = v["position"].as_f64().unwrap();
    let file = std::fs::read_dir(&state).unwrap().flatten().map(|e| e.path()).find(|p| p.display().to_string().ends_with(".reference.toml"));
    let text = std::fs::read_to_string(file.expect("reference file in the state dir")).unwrap();
    let pos: f64 = text.lines().find_map(|l| l.strip_prefix("position = ")).expect("a position in the reference").parse().unwrap();
    assert!(text.contains("[axes.z]") && text.contains("method = 17") && (pos - 1.5).abs() <= 0.005, "{text}");

    // A vendor's map for Z that names no homing register.
    let vendor = machine.replace("[axes.z.emulate]", "[axes.z.cia402_map]\nerror_code = 16\n\n[axes.z.emulate]");
    let vcfg = dir.join("vendor.toml");
    std::fs::write(&vcfg, &vendor).unwrap();
    let o = cli().run(&["config", "check", vcfg.to_str().unwrap()]);
    assert!(
        o.stdout.contains("axis z: its homing (method 17) needs the homing method 0x6098")
            && o.stdout.contains("`cncgw home` refuses it (alarm 2017)"),
        "{}{}",
        o.stdout,
        o.stderr
    );
    let o = cli().run(&["home", "z", "--config", vcfg.to_str().unwrap(), "--yes"]);
    assert_eq!(o.code, 1, "{}{}", o.stdout, o.stderr);
    assert!(
        o.stderr.contains("alarm 2017: unit 2: homing method 17 refused before any motion")
            && o.stderr.contains("homing method 0x6098 (homing_method"),
        "{}",
        o.stderr
    );
    assert!(o.stderr.contains("nothing was written or moved"), "{}", o.stderr);
    let o = cli().run(&["drive", "status", "2", "--config", cfg.to_str().unwrap(), "--json"]);
    let v = json(&o);
    let z2 = v["position"].as_f64().or_else(|| v[0]["position"].as_f64()).unwrap();
    assert!((z2 - z).abs() < 1e-3, "Z moved from {z} to {z2}");
}
