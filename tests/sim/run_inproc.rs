//! End to end on the embedded machine: part program → interpreter → motion → CANopen master
//! → in-process bus → emulated CiA 402 drives (sim-drives) in simulated time.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::run_program;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw_bus::transport::inproc::InprocBus;
use std::path::PathBuf;
use std::process::Command;

/// What a run ended with: the summary and the emulated drives, or the alarm and the summary.
type RunResult = Result<(RunSummary, Box<sim_drives::SimWorld>), (cncgw::Alarm, RunSummary)>;

#[allow(clippy::result_large_err)] // a test helper: the summary is what the tests look at
fn run_source(name: &str, text: &str) -> RunResult {
    run_on(EMBEDDED_LATHE, name, text)
}

/// `text` on the machine of `machine` (config TOML text).
#[allow(clippy::result_large_err)]
fn run_on(machine: &str, name: &str, text: &str) -> RunResult {
    let cfg = MachineConfig::from_toml("machine.toml", machine).expect("machine config");
    let interp = Interpreter::from_source(name, text, &cfg).expect("program parses");
    let wire = InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(machine).unwrap());
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == cncgw::config::AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(&cfg), spindle, 2_000_000);
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    match r {
        Ok(()) => Ok((summary, Box::new(world))),
        Err(a) => Err((a, summary)),
    }
}

#[test]
fn a_short_program_ends_within_one_count_of_its_end_point() {
    let prog = "G21\nG98\nG00 X40 Z2\nG01 Z-10 F600\nG01 X60 Z-20\nG00 X100 Z5\nM30\n";
    let (s, world) = run_source("short.nc", prog).map_err(|(a, _)| a).unwrap();
    assert!(s.simulated);
    assert!(s.at_program_end(), "{s:#?}");
    let x = s.axes.iter().find(|a| a.name == "x").unwrap();
    let z = s.axes.iter().find(|a| a.name == "z").unwrap();
    // X100 is a diameter: radius 50 mm × 10000 counts/mm.
    assert_eq!(x.program_end_counts, Some(500_000));
    assert_eq!(z.program_end_counts, Some(50_000));
    assert!((x.final_actual_counts - 500_000).abs() <= 1);
    assert!((z.final_actual_counts - 50_000).abs() <= 1);
    // The emulated drives agree with what the master saw.
    assert!((world.drive(1).unwrap().position_actual() as i64 - 500_000).abs() <= 1);
    assert!((world.drive(2).unwrap().position_actual() as i64 - 50_000).abs() <= 1);
    // Drives really followed: a following error, but a small one.
    assert!(x.max_following_error > 0.0 && x.max_following_error < 0.5, "{}", x.max_following_error);
    // Machining time is at least the feed move's length / feed (10 mm at 600 mm/min = 1 s).
    assert!(s.machining_time_s > 1.0 && s.machining_time_s < 30.0, "{}", s.machining_time_s);
}

#[test]
fn runs_are_deterministic_in_simulated_time() {
    let prog = "G21\nG98\nM03 S800\nG00 X30 Z1\nG01 Z-5 F300\nG02 X40 Z-10 R5\nG00 X80 Z5\nM05\nM30\n";
    let (a, _) = run_source("det.nc", prog).map_err(|(a, _)| a).unwrap();
    let (b, _) = run_source("det.nc", prog).map_err(|(a, _)| a).unwrap();
    assert_eq!(a, b);
}

#[test]
fn first_part_example_runs_from_the_cli() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let out = testkit::cli!().command::<&str>(&[]).args(["run", "--json"]).arg(root.join("examples/first_part.nc")).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    assert_eq!(v["at_program_end"], true);
    assert_eq!(v["simulated"], true);
    assert!(v["blocks"].as_u64().unwrap() >= 10);
    assert!(v["machining_time_s"].as_f64().unwrap() > 5.0);
}

#[test]
fn a_syntax_error_is_reported_with_position_and_nothing_moves() {
    let dir = std::env::temp_dir().join(format!("cncgw-syntax-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join("bad.nc");
    std::fs::write(&p, "G21\nG00 X10 Z5\nG01 Z-5 F100\nG01 X20 Z-10 Q?\nM30\n").unwrap();
    let out = testkit::cli!().command::<&str>(&[]).arg("run").arg(&p).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("bad.nc:4:"), "{stderr}");
    assert!(stderr.contains("G01 X20 Z-10 Q?"), "the block text is shown: {stderr}");
    assert!(stderr.contains("nothing was moved"), "{stderr}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn pdo_cob_ids_and_transmission_types_come_from_the_config() {
    // Z's PDOs on non-default COB-IDs, its feedback every second SYNC: the drive is
    // configured that way over SDO and the program still ends on its end point.
    let machine = EMBEDDED_LATHE.replace("node = 2\n", "node = 2\nrpdo_cob_id = 0x222\ntpdo_cob_id = 0x1A2\ntpdo_transmission = 2\n");
    let (s, world) = run_on(&machine, "cob.nc", "G98\nG00 X20 Z-5\nG01 Z-30 F600\nG00 X100 Z5\nM30\n").unwrap_or_else(|(a, _)| panic!("{a}"));
    assert!(s.at_program_end(), "{s:?}");
    let z = world.drive(2).unwrap();
    assert_eq!(z.object(0x1400, 1), Some(0x222));
    assert_eq!(z.object(0x1800, 1), Some(0x1A2));
    assert_eq!(z.object(0x1800, 2), Some(2));
}

/// `run --tools` applies the same table as `plan --tools` (issue 24.1): the axes end where
/// the plan's last move says, geometry + wear of the offset taken up.
#[test]
fn run_and_plan_take_the_same_tool_table() {
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("t.nc");
    std::fs::write(&prog, "G0 X100 Z5\nT0101\nG0 X20 Z4\nM30\n").unwrap();
    let tools = dir.path().join("tools.toml");
    std::fs::write(&tools, "[1]\nx = -10.0\nz = -5.0\nwear_x = 0.2\nwear_z = 0.1\n").unwrap();
    let cncgw =
        |args: &[&str]| Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", dir.path().join("state")).args(args).output().unwrap();
    let (p, t) = (prog.to_str().unwrap(), tools.to_str().unwrap());
    let plan = cncgw(&["plan", p, "--tools", t]);
    assert!(plan.status.success(), "{}", String::from_utf8_lossy(&plan.stderr));
    let run = cncgw(&["run", "--batch", "--json", p, "--tools", t]);
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let v: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    let end = |axis: &str| v["axes"].as_array().unwrap().iter().find(|a| a["axis"] == axis).unwrap()["final_actual_counts"].as_i64().unwrap();
    // Machine X (radius) = 10 + (−10 + 0.2)/2 = 5.1 mm, Z = 4 − 5 + 0.1 = −0.9 mm; 10 000 counts/mm.
    assert_eq!((end("x"), end("z")), (51_000, -9_000), "{v}");
    // The plan prints work coordinates: the programmed X20 Z5 (the offset is in the machine position).
    let last_move = String::from_utf8_lossy(&plan.stdout).lines().rfind(|l| l.contains("\"rapid\"")).unwrap().to_string();
    assert!(last_move.contains("\"x\":20.0") && last_move.contains("\"z\":4.0"), "{last_move}");
    // Without the table the same program ends at the programmed X (radius 10 mm).
    let bare: serde_json::Value = serde_json::from_slice(&cncgw(&["run", "--batch", "--json", p]).stdout).unwrap();
    let x = bare["axes"].as_array().unwrap().iter().find(|a| a["axis"] == "x").unwrap()["final_actual_counts"].as_i64().unwrap();
    assert_eq!(x, 100_000);
    // A bad table is refused before anything moves.
    std::fs::write(&tools, "[1]\nx = \"far\"\n").unwrap();
    let bad = cncgw(&["run", "--batch", p, "--tools", t]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nothing was moved"));
}
