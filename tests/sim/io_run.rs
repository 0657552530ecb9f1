//! Machine I/O (issue 24 item 6) on the embedded machine, in simulated time: a CiA 401
//! module emulated by sim-drives on the in-process bus (node 10), M codes switching its
//! outputs and waiting for its inputs (FIN), the safety inputs stopping the machine.
//!
//! The clock samples the module's outputs and every drive after every wait, so each test
//! sees what the *devices* did.

use crate::io_common;
use crate::sim_probe;

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::control::job::run_program;
use cncgw::control::panel::{Panel, SafetyInputs};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::Alarm;
use cncgw_bus::cia402::State;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use io_common::SAFETY_AND_M_CODES;
use sim_drives::SimWorld;
use sim_probe::{Action, Probe, MS};

const NODE: u8 = 10;
const COOLANT: u32 = 1 << 0;
const CLAMP: u32 = 1 << 1;
const STROBE: u32 = 1 << 2;

/// The `[io]` of the tests: `emulate` is the module's wiring.
fn machine(emulate: &str, extra: &str) -> String {
    format!(
        r#"{EMBEDDED_LATHE}
[io]
fin_timeout_ms = 500
[io.devices.io1]
canopen_node = {NODE}
[io.devices.io1.emulate]
{emulate}
[io.inputs]
estop_ok = "io1.0"
door_closed = "io1.1"
chuck_clamped = "io1.2"
turret_in_position = "io1.3"
[io.outputs]
coolant = "io1.0"
chuck_clamp = "io1.1"
turret_index = "io1.2"
t1 = "io1.3"
t2 = "io1.4"
{SAFETY_AND_M_CODES}
[io.m.11]
clear = ["chuck_clamp"]
wait_off = ["chuck_clamped"]
[io.turret]
code = ["t1", "t2"]
strobe = "turret_index"
in_position = "turret_in_position"
{extra}
"#
    )
}

/// Closed E-stop chain and door; chuck clamped 300 ms after its valve; turret in position
/// 200 ms after its strobe.
const WIRED: &str = r#"inputs_on = [0, 1]
follow = [{ input = 2, output = 1, delay_ms = 300 }, { input = 3, output = 2, delay_ms = 200 }]"#;

struct Sample {
    t: u64,
    outputs: u32,
    x: i64,
    z: i64,
    /// The spindle's position, counts (1000 per degree).
    s: i64,
    state: Vec<State>,
}

impl Sample {
    /// The module's outputs and every drive.
    fn of(world: &SimWorld) -> Sample {
        let d = world.drives();
        Sample {
            t: world.now_ns(),
            outputs: world.io_outputs(NODE).unwrap_or(0),
            x: d[0].position_unwrapped(),
            z: d[1].position_unwrapped(),
            s: d[2].position_unwrapped(),
            state: d.iter().map(|d| d.state()).collect(),
        }
    }
}

struct Outcome {
    result: Result<(), Alarm>,
    summary: RunSummary,
    samples: Vec<Sample>,
}

impl Outcome {
    /// The first sample (after `from`) where `f` holds.
    fn first(&self, from: u64, f: impl Fn(&Sample) -> bool) -> Option<&Sample> {
        self.samples.iter().find(|s| s.t >= from && f(s))
    }
    /// The spindle's speed over the 10 ms before `t`, rpm (1000 counts per degree).
    fn rpm_at(&self, t: u64) -> f64 {
        let a = self.samples.iter().rev().find(|s| s.t <= t.saturating_sub(10 * MS)).unwrap();
        let b = self.samples.iter().rev().find(|s| s.t <= t).unwrap();
        (b.s - a.s) as f64 / 1000.0 / 360.0 / ((b.t - a.t) as f64 * 1e-9) * 60.0
    }
    /// When X and Z last moved.
    fn last_motion(&self) -> u64 {
        self.samples.windows(2).rfind(|w| (w[1].x - w[0].x).abs() > 1 || (w[1].z - w[0].z).abs() > 1).map_or(0, |w| w[1].t)
    }
    /// When the program's motion first moved X or Z (counts away from the start).
    fn first_motion(&self) -> Option<u64> {
        let s0 = self.samples.first()?;
        self.samples.iter().find(|s| (s.x - s0.x).abs() > 10 || (s.z - s0.z).abs() > 10).map(|s| s.t)
    }
}

fn run(cfg_text: &str, prog: &str, actions: Vec<(u64, Action)>) -> Outcome {
    run_panel(cfg_text, prog, actions, None)
}

fn run_panel(cfg_text: &str, prog: &str, actions: Vec<(u64, Action)>, panel: Option<&Panel>) -> Outcome {
    let cfg = MachineConfig::from_toml("io.toml", cfg_text).expect("machine config");
    let interp = Interpreter::from_source("io.nc", prog, &cfg).expect("program parses");
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(cfg_text).unwrap());
    for m in sim_drives::io401::from_machine_toml(cfg_text).unwrap().0 {
        world.add_io_module(m);
    }
    let mut probe = Probe::new(world, actions, Sample::of);
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let mut summary = RunSummary::default();
    let result = {
        let mut lp = CycleLoop::from_config(&mut master, &mut probe, &cfg);
        if let Some(p) = panel {
            lp.set_panel(p);
        }
        let r = run_program(&mut lp, interp, &mut summary);
        lp.finish();
        r
    };
    Outcome { result, summary, samples: probe.samples }
}

const CUT: &str = "G21 G98 G97\nM10\nM03 S600\nM08\nG00 X40 Z2\nG01 Z-100 F1200\nG00 X80 Z5\nM09\nM05\nM30\n";

#[test]
fn m08_switches_the_coolant_output_and_m09_clears_it() {
    let o = run(&machine(WIRED, ""), CUT, Vec::new());
    o.result.as_ref().unwrap();
    assert!(o.summary.ended);
    let on = o.first(0, |s| s.outputs & COOLANT != 0).expect("coolant on").t;
    let moved = o.first_motion().unwrap();
    assert!(on <= moved, "coolant on at {} ms, motion at {} ms", on / MS, moved / MS);
    let off = o.first(on, |s| s.outputs & COOLANT == 0).expect("coolant off").t;
    assert!(off > on + 4000 * MS, "M09 after the 5 s cut: {} ms", (off - on) / MS);
}

#[test]
fn m10_waits_for_the_clamped_input_before_the_next_block() {
    let o = run(&machine(WIRED, ""), CUT, Vec::new());
    o.result.as_ref().unwrap();
    let clamp = o.first(0, |s| s.outputs & CLAMP != 0).expect("clamp valve on").t;
    let moved = o.first_motion().unwrap();
    let coolant = o.first(0, |s| s.outputs & COOLANT != 0).unwrap().t;
    eprintln!("clamp valve {} ms, coolant {} ms, first motion {} ms", clamp / MS, coolant / MS, moved / MS);
    // The switch closes 300 ms after the valve: nothing after M10 before that.
    assert!(coolant >= clamp + 300 * MS, "M08 at {} ms, clamp at {} ms", coolant / MS, clamp / MS);
    assert!(moved >= clamp + 300 * MS);
}

#[test]
fn a_missing_confirmation_is_a_timeout_alarm_and_nothing_moves() {
    // The chuck switch is not wired: M10 is never confirmed.
    let o = run(&machine("inputs_on = [0, 1]", ""), CUT, Vec::new());
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::IO_FIN_TIMEOUT, "{a}");
    assert!(a.message.contains("M10") && a.message.contains("chuck_clamped on") && a.message.contains("500 ms"), "{a}");
    assert_eq!(o.first_motion(), None, "an axis moved");
    assert!(o.samples.iter().all(|s| s.outputs & COOLANT == 0), "M08 after the unconfirmed M10 ran");
}

#[test]
fn the_e_stop_input_takes_every_drive_out_of_operation_enabled_within_2_cycles() {
    let drop_at = 1500;
    let open: Action = Box::new(|w: &mut SimWorld| assert!(w.set_io_input(NODE, 0, Some(false))));
    let o = run(&machine(WIRED, ""), CUT, vec![(drop_at, open)]);
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::ESTOP, "{a}");
    assert!(a.message.contains("estop_ok"), "{a}");
    assert!(o.summary.rest.quick_stop, "{:?}", o.summary.rest);
    let t = drop_at * MS;
    assert!(o.first_motion().unwrap() < t, "the drop came before any motion");
    let out = o.first(t, |s| s.state.iter().all(|st| *st != State::OperationEnabled)).expect("every drive left Operation Enabled");
    eprintln!("out of Operation Enabled {} µs after the E-stop input opened", (out.t - t) / 1000);
    // As the panel's E-stop (tests/sim/stop_sequence.rs): within 2 cycles of 2 ms, plus the
    // sample's own cycle.
    assert!(out.t - t <= 3 * 2 * MS, "{} ms", (out.t - t) / MS);
}

#[test]
fn the_e_stop_input_dropped_by_a_timed_config_event_stops_the_machine() {
    let o = run(&machine(&format!("{WIRED}\nevents = [{{ input = 0, at_ms = 1500, value = false }}]"), ""), CUT, Vec::new());
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::ESTOP);
    let out = o.first(1500 * MS, |s| s.state.iter().all(|st| *st != State::OperationEnabled)).unwrap();
    assert!(out.t - 1500 * MS <= 3 * 2 * MS, "{} ms", (out.t - 1500 * MS) / MS);
}

#[test]
fn the_door_opening_is_a_controlled_stop_with_an_alarm() {
    let open: Action = Box::new(|w: &mut SimWorld| assert!(w.set_io_input(NODE, 1, Some(false))));
    let o = run(&machine(WIRED, ""), CUT, vec![(1500, open)]);
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::IO_DOOR_OPEN, "{a}");
    assert!(a.message.contains("door_closed") && a.message.contains("close the door"), "{a}");
    let r = o.summary.rest;
    assert!(!r.quick_stop && r.at_rest, "a controlled stop: {r:?}");
    // The drives stayed enabled while the axes braked on the path (no quick stop).
    let t = 1500 * MS;
    assert!(o.samples.iter().filter(|s| s.t > t && s.t < t + 100 * MS).all(|s| s.state.iter().all(|st| *st == State::OperationEnabled)));
}

#[test]
fn the_chuck_opening_while_the_spindle_turns_stops_the_machine() {
    let open: Action = Box::new(|w: &mut SimWorld| assert!(w.set_io_input(NODE, 2, Some(false))));
    let o = run(&machine(WIRED, ""), CUT, vec![(1500, open)]);
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::IO_CHUCK_UNCLAMPED);
    assert!(!o.summary.rest.quick_stop && o.summary.rest.at_rest);
}

#[test]
fn a_program_does_not_start_with_the_door_open() {
    let o = run(&machine("inputs_on = [0]", ""), CUT, Vec::new());
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::IO_DOOR_OPEN, "{a}");
    assert!(a.message.starts_with("before the start"), "{a}");
    assert_eq!(o.first_motion(), None);
}

#[test]
fn a_t_code_indexes_the_turret_and_waits_for_in_position() {
    let prog = "G21 G98\nT0201\nG00 X40 Z2\nM30\n";
    let o = run(&machine(WIRED, ""), prog, Vec::new());
    o.result.as_ref().unwrap();
    let strobe = o.first(0, |s| s.outputs & STROBE != 0).expect("strobe");
    // Station 2 in binary on t1, t2 while the strobe is on.
    assert_eq!(strobe.outputs & (0b11 << 3), 0b10 << 3, "outputs {:05b}", strobe.outputs);
    let off = o.first(strobe.t, |s| s.outputs & STROBE == 0).expect("strobe off at FIN").t;
    assert!(off >= strobe.t + 200 * MS);
    assert!(o.first_motion().unwrap() >= off);
}

#[test]
fn the_example_config_runs_a_program_with_chuck_coolant_and_turret_from_the_cli() {
    let dir = testkit::tmp!("io_run", "example");
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("io.nc");
    std::fs::write(&prog, "G21 G98 G97\nM10\nT0303\nM03 S500\nM08\nG00 X40 Z2\nG01 Z-5 F600\nG00 X60 Z5\nM09\nM05\nM30\n").unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--batch", "--config", concat!(env!("CARGO_MANIFEST_DIR"), "/config/lathe-io.toml")])
        .arg(&prog)
        .env("CNCGW_STATE_DIR", dir.join("state"))
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert_eq!(o.status.code(), Some(0), "{text}");
    assert_eq!(text.matches("ok (within 1 count)").count(), 2, "{text}");
}

/// M30 / M02 without M09 and M05 before them: the coolant goes off and the spindle starts
/// braking at the program's end, as a Fanuc 0i-TF's ladder does (manual 004 §2.19:
/// "M30; 程序结束, 关主轴、冷却液") — not seconds later when the run takes torque off.
#[test]
fn m30_and_m02_switch_the_coolant_off_and_stop_the_spindle() {
    for end in ["M30", "M02"] {
        let prog = format!("G21 G98 G97\nM10\nM03 S600\nM08\nG00 X40 Z2\nG01 Z-20 F1200\n{end}\n");
        let o = run(&machine(WIRED, ""), &prog, Vec::new());
        o.result.as_ref().unwrap();
        assert!(o.summary.ended, "{end}");
        let on = o.first(0, |s| s.outputs & COOLANT != 0).expect("coolant on").t;
        let off = o.first(on, |s| s.outputs & COOLANT == 0).expect("coolant off").t;
        let stop = o.last_motion();
        eprintln!("{end}: last axis motion {} ms, coolant off {} ms", stop / MS, off / MS);
        // The end comes after the last move; nothing waits for the drives to settle first.
        assert!(off >= stop && off <= stop + 20 * MS, "{end}: coolant off at {} ms, last motion at {} ms", off / MS, stop / MS);
        let before = o.rpm_at(off - 4 * MS);
        assert!((before - 600.0).abs() < 5.0, "{end}: {before} rpm before the end");
        // 6000 rpm/s: 600 rpm to rest in 100 ms.
        let after = o.rpm_at(off + 60 * MS);
        assert!((0.0..300.0).contains(&after), "{end}: {after} rpm 60 ms after the end");
        // At rest after its position loop's overshoot (≈ 15 rpm, settled by 200 ms).
        assert!(o.rpm_at(off + 250 * MS).abs() < 1.0, "{end}: the spindle did not stop");
        // The chuck stays clamped: the part is still in it.
        assert!(o.samples.iter().filter(|s| s.t >= off && s.t <= off + 150 * MS).all(|s| s.outputs & CLAMP != 0));
    }
}

/// M11 (chuck unclamp) while M03 is in force is refused before its valve switches (alarm
/// 2604): the chuck stays clamped, the spindle and the axes stop under control.
#[test]
fn m11_while_the_spindle_turns_is_refused_and_the_chuck_stays_clamped() {
    let prog = "G21 G98 G97\nM10\nM03 S600\nG00 X40 Z2\nM11\nG00 X60\nM30\n";
    let o = run(&machine(WIRED, ""), prog, Vec::new());
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::IO_UNCLAMP_TURNING, "{a}");
    assert!(a.message.contains("M11") && a.message.contains("line 5") && a.message.contains("M05"), "{a}");
    let clamp = o.first(0, |s| s.outputs & CLAMP != 0).expect("clamp valve on").t;
    // Until the run takes torque off (the master clears every output then).
    let on = |s: &&Sample| s.state.iter().all(|st| *st == State::OperationEnabled);
    assert!(o.samples.iter().filter(|s| s.t > clamp).take_while(on).all(|s| s.outputs & CLAMP != 0), "the unclamp valve switched");
    let r = o.summary.rest;
    assert!(!r.quick_stop && r.at_rest, "a controlled stop: {r:?}");
    let end = o.samples.last().unwrap().t;
    assert!(o.rpm_at(end).abs() < 1.0, "the spindle still turns");
    // X never went on to 60 mm (diameter: 30 mm radius = 300 000 counts).
    assert!(o.samples.iter().all(|s| s.x <= 200_000 + 10), "the block after M11 ran");
}

/// M05 then M11: the unclamp waits for the spindle to stand (it coasts ~100 ms), then
/// switches and waits for the chuck switch to open; the program ends normally.
#[test]
fn m11_after_m05_waits_for_the_spindle_to_stand() {
    let prog = "G21 G98 G97\nM10\nM03 S600\nG00 X40 Z2\nM05\nM11\nM30\n";
    let o = run(&machine(WIRED, ""), prog, Vec::new());
    o.result.as_ref().unwrap();
    let clamp = o.first(0, |s| s.outputs & CLAMP != 0).unwrap().t;
    let unclamp = o.first(clamp, |s| s.outputs & CLAMP == 0).expect("unclamp valve").t;
    let rpm = o.rpm_at(unclamp);
    eprintln!("unclamp at {} ms, spindle {rpm:.2} rpm, {:.0} rpm 40 ms before", unclamp / MS, o.rpm_at(unclamp - 40 * MS));
    assert!(rpm.abs() < 1.0, "unclamped while the spindle turned at {rpm} rpm");
    // M05 came just before M11: the spindle took ≥ 100 ms (6000 rpm/s) to stop first.
    let full = o.first(clamp, |s| s.t > 20 * MS && o.rpm_at(s.t) > 590.0).expect("spindle at speed").t;
    let braking = o.first(full, |s| o.rpm_at(s.t) < 590.0).expect("M05").t;
    assert!(unclamp >= braking + 100 * MS, "unclamp {} ms after M05", (unclamp - braking) / MS);
}

/// The operator panel shows the safety inputs as the cycle loop reads them; the door that
/// stopped the run is still shown open afterwards.
#[test]
fn the_panel_shows_e_stop_door_and_chuck() {
    let panel = Panel::new();
    assert_eq!(panel.safety(), SafetyInputs::default(), "nothing read yet");
    let open: Action = Box::new(|w: &mut SimWorld| assert!(w.set_io_input(NODE, 1, Some(false))));
    let o = run_panel(&machine(WIRED, ""), CUT, vec![(1500, open)], Some(&panel));
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::IO_DOOR_OPEN);
    assert_eq!(panel.safety(), SafetyInputs { estop: Some(true), door: Some(false), chuck: Some(true) });
    // Refused at the start (door open, chuck not clamped yet): shown too.
    let panel = Panel::new();
    let o = run_panel(&machine("inputs_on = [0]", ""), CUT, Vec::new(), Some(&panel));
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::IO_DOOR_OPEN);
    assert_eq!(panel.safety(), SafetyInputs { estop: Some(true), door: Some(false), chuck: Some(false) });
}
