//! Machine I/O with sim-drives as a process, in real time: the drives and a CiA 401 module
//! (node 10) on sim-drives' socketcand server, a Modbus TCP I/O unit (`--modbus-io`) for the
//! turret, and `cncgw run --bus socketcand://…` as an operator runs it. The wiring is the
//! machine config's `[io.devices.*.emulate]`; the E-stop chain opens by a timed event.

use crate::io_common;

use io_common::SAFETY_AND_M_CODES;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use testkit::{bin, Kill};

fn tmp(name: &str) -> PathBuf {
    testkit::tmp!("io_process", name)
}

fn machine(modbus: &str, emulate_io1: &str) -> String {
    let lathe = include_str!("../../config/lathe.toml").replace("feedback_timeout_ms = 20", "feedback_timeout_ms = 200");
    format!(
        r#"{lathe}
[io]
fin_timeout_ms = 1000
[io.devices.io1]
canopen_node = 10
[io.devices.io1.emulate]
{emulate_io1}
[io.devices.turret]
modbus = "{modbus}"
inputs = 4
outputs = 4
poll_ms = 5
[io.devices.turret.emulate]
follow = [{{ input = 0, output = 0, delay_ms = 150 }}]
[io.inputs]
estop_ok = "io1.0"
door_closed = "io1.1"
chuck_clamped = "io1.2"
turret_in_position = "turret.0"
[io.outputs]
coolant = "io1.0"
chuck_clamp = "io1.1"
turret_index = "turret.0"
{SAFETY_AND_M_CODES}
[io.turret]
strobe = "turret_index"
in_position = "turret_in_position"
"#
    )
}

const WIRED: &str = r#"inputs_on = [0, 1]
follow = [{ input = 2, output = 1, delay_ms = 200 }]"#;

fn free_addr() -> String {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    format!("127.0.0.1:{port}")
}

/// Start sim-drives on `cfg`, run `prog` with cncgw; (exit code, stdout + stderr).
fn run(name: &str, emulate_io1: &str, prog: &str) -> (Option<i32>, String) {
    let (can, mb) = (free_addr(), free_addr());
    let cfg = tmp(&format!("{name}.toml"));
    std::fs::write(&cfg, machine(&mb, emulate_io1)).unwrap();
    let log = tmp(&format!("{name}-sim.log"));
    let _sim = Kill(
        Command::new(bin!("sim-drives"))
            .args(["--socketcand", &can, "--modbus-io", "--config"])
            .arg(&cfg)
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap(),
    );
    let t0 = Instant::now();
    while std::net::TcpStream::connect(&can).is_err() || std::net::TcpStream::connect(&mb).is_err() {
        assert!(t0.elapsed().as_secs() < 10, "sim-drives did not start: {}", std::fs::read_to_string(&log).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(20));
    }
    let p = tmp(&format!("{name}.nc"));
    std::fs::write(&p, prog).unwrap();
    let o = Command::new(bin!("cncgw"))
        .args(["run", "--batch", "--bus", &format!("socketcand://{can}/can0"), "--config"])
        .arg(&cfg)
        .arg(&p)
        .env("CNCGW_STATE_DIR", tmp(&format!("{name}-state")))
        .env_remove("RUST_LOG")
        .stdin(Stdio::null())
        .output()
        .expect("run cncgw");
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    (o.status.code(), text)
}

#[test]
fn a_program_with_coolant_chuck_and_turret_runs_to_its_end_over_socketcand_and_modbus() {
    let (code, out) = run("ok", WIRED, "G21 G98\nM10\nT0101\nM08\nG00 X40 Z2\nG01 Z-10 F1200\nG00 X60 Z5\nM09\nM30\n");
    assert_eq!(code, Some(0), "{out}");
    // M10 (CiA 401 input) and T0101 (the Modbus unit's input) were confirmed, or it would
    // have ended in alarm 2600.
    assert_eq!(out.matches("ok (within 1 count)").count(), 2, "{out}");
}

#[test]
fn a_chuck_that_never_reports_clamped_is_alarm_2600_over_socketcand() {
    let (code, out) = run("fin", "inputs_on = [0, 1]", "G21 G98\nM10\nG00 X40 Z2\nM30\n");
    assert_ne!(code, Some(0), "{out}");
    assert!(out.contains("2600") && out.contains("M10") && out.contains("chuck_clamped on"), "{out}");
}

#[test]
fn the_e_stop_chain_opening_mid_program_is_alarm_2400_over_socketcand() {
    let (code, out) = run(
        "estop",
        &format!("{WIRED}\nevents = [{{ input = 0, at_ms = 2500, value = false }}]"),
        "G21 G98\nM10\nG00 X40 Z2\nG01 Z-100 F1200\nM30\n",
    );
    assert_ne!(code, Some(0), "{out}");
    assert!(out.contains("2400") && out.contains("estop_ok"), "{out}");
}
