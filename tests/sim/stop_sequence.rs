//! Every stop is a controlled stop (issue 19): whatever ends a run — the program's end without
//! M05, a program alarm, one drive's fault, reset, E-stop, a termination signal — spindle and
//! axes come to rest before torque goes off, and the summary says how.
//!
//! In simulated time on the embedded machine. The clock samples every drive after every wait
//! (position, velocity, CiA 402 state), so each test sees what the *drives* did — above all
//! the speed of every motor at the instant its power stage went off (leaving Operation
//! Enabled, Quick Stop Active or Fault Reaction Active), which must be zero.

use crate::sim_probe;

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, Rest, RunSummary};
use cncgw::control::job::run_program;
use cncgw::control::panel::Panel;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::Limits;
use cncgw::Alarm;
use cncgw_bus::cia402::State;
use cncgw_bus::transport::inproc::InprocBus;
use sim_drives::SimWorld;
use sim_probe::{Action, Probe, Sample, MS};
use std::sync::atomic::{AtomicI32, Ordering};

/// Below this a motor counts as at rest, counts/s: 1 rpm of the spindle (6°/s at 1000
/// counts/°), 0.2 mm/s of a feed axis (at 10 000 counts/mm) — the drives' own standstill
/// windows (sim-drives: 0.1 rad/s of the motor).
fn rest_limit(node: u8) -> i32 {
    if node == 3 {
        6000
    } else {
        2000
    }
}

struct Outcome {
    result: Result<(), Alarm>,
    summary: RunSummary,
    samples: Vec<Sample>,
    nodes: Vec<u8>,
}

fn powered(s: State) -> bool {
    matches!(s, State::OperationEnabled | State::QuickStopActive | State::FaultReactionActive)
}

impl Outcome {
    /// Each drive's speed (counts/s) at the first sample after its power stage went off for
    /// good (powered before, never again after).
    fn speed_at_torque_off(&self) -> Vec<(u8, i32)> {
        let n = self.nodes.len();
        (0..n)
            .map(|d| {
                let last_on = self.samples.iter().rposition(|s| powered(s.state[d]));
                let off = last_on.and_then(|i| self.samples.get(i + 1)).expect("the drive was switched off");
                (self.nodes[d], off.vel[d])
            })
            .collect()
    }

    fn assert_rest_before_torque_off(&self) {
        let r = &self.summary.rest;
        eprintln!(
            "rest: {:.3} s to standstill, spindle {:.2} rpm at torque off, quick stop {}; speeds at torque off (counts/s): {:?}",
            r.time_s,
            r.spindle_rpm_at_off,
            r.quick_stop,
            self.speed_at_torque_off()
        );
        for (node, v) in self.speed_at_torque_off() {
            assert!(v.abs() <= rest_limit(node), "node {node} was switched off at {v} counts/s");
        }
    }
}

struct Setup {
    sim: Option<&'static str>,
    actions: Vec<(u64, Action)>,
    panel: Option<Panel>,
    signal: Option<&'static AtomicI32>,
}

fn run(program: &str, setup: Setup) -> Outcome {
    let cfg = MachineConfig::embedded();
    let interp = Interpreter::from_source("stop.nc", program, &cfg).expect("program parses");
    let sim = match setup.sim {
        Some(t) => sim_drives::SimConfig::from_toml(t).unwrap(),
        None => sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(),
    };
    let wire = InprocBus::new();
    let world = SimWorld::new(&wire, sim);
    let nodes = world.drives().iter().map(|d| d.node()).collect();
    let mut probe = Probe::new(world, setup.actions, Sample::of);
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let mut summary = RunSummary::default();
    let result = {
        let mut lp = CycleLoop::new(&mut master, &mut probe, Limits::from_config(&cfg), cfg.spindle_index(), 2_000_000);
        if let Some(p) = &setup.panel {
            lp.set_panel(p);
        }
        if let Some(s) = setup.signal {
            lp.set_signal(s, |_| "SIGTERM");
        }
        let r = run_program(&mut lp, interp, &mut summary);
        // What `cncgw run` does last: torque off.
        lp.finish();
        r
    };
    Outcome { result, summary, samples: probe.samples, nodes }
}

fn setup() -> Setup {
    Setup { sim: None, actions: Vec::new(), panel: None, signal: None }
}

impl Setup {
    /// Drive `node` faults with EMCY `code` at `ms` (the probe's clock).
    fn fault_at(&mut self, ms: u64, node: u8, code: u16) {
        self.actions.push((
            ms,
            Box::new(move |w: &mut SimWorld| {
                w.inject_fault(node, code);
            }),
        ));
    }
}

/// The spindle turning at S1000 and X, Z moving.
const TURNING: &str = "G21\nG98 G97\nM03 S1000\nG00 X40 Z2\nG01 Z-150 F3000\nG00 X50\nZ2\nM30\n";

fn check_rest(r: &Rest) {
    assert!(r.at_rest, "{r:?}");
    assert!(r.spindle_rpm_at_off.abs() < 1.0, "spindle at {} rpm when handed back for torque off", r.spindle_rpm_at_off);
}

#[test]
fn a_program_that_ends_without_m05_stops_the_spindle_before_torque_off() {
    let o = run("G21\nG98 G97\nM03 S1500\nG00 X40 Z2\nG01 Z-20 F3000\nM30\n", setup());
    o.result.as_ref().unwrap();
    assert!(o.summary.at_program_end());
    check_rest(&o.summary.rest);
    assert!(!o.summary.rest.quick_stop);
    o.assert_rest_before_torque_off();
    eprintln!("program end: {}", o.summary.rest.describe());
}

#[test]
fn a_feed_axis_fault_stops_the_turning_spindle_under_control() {
    let mut s = setup();
    s.fault_at(1400, 1, 0x2310);
    let o = run(TURNING, s);
    let a = o.result.as_ref().expect_err("the fault stops the run");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{a}");
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
    // The spindle was not quick-stopped: it ramped down under control (never left Operation
    // Enabled before it stood still).
    let ds = o.nodes.iter().position(|n| *n == 3).unwrap();
    let first_off = o.samples.iter().find(|s| !powered(s.state[ds]) && s.t > 1400 * MS).unwrap();
    assert!(first_off.vel[ds].abs() <= rest_limit(3), "{first_off:?}");
}

/// A second drive faulting while the others stop under control after the first: every drive
/// is sent quick stop, and the alarm names both faults and does not claim the others stopped
/// under control.
#[test]
fn a_second_fault_during_a_fault_stop_is_named_and_quick_stops_every_drive() {
    let mut s = setup();
    s.fault_at(1400, 1, 0x2310);
    s.fault_at(1420, 2, 0x7500);
    let o = run(TURNING, s);
    let a = o.result.as_ref().expect_err("the faults stop the run");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{a}");
    assert!(a.message.contains("0x2310") && a.message.contains("while the others stopped, alarm"), "{a}");
    assert!(a.message.contains("every drive was sent quick stop"), "{a}");
    assert!(!a.message.contains("under control"), "{a}");
    assert!(o.summary.rest.quick_stop, "{:?}", o.summary.rest);
}

/// A drive that faults after the program's end, while the drives settle onto their end
/// point, is the run's alarm and says the program had ended.
#[test]
fn a_fault_while_settling_at_the_program_end_says_the_program_had_ended() {
    const ENDS_TURNING: &str = "G21\nG98 G97\nM03 S1500\nG00 X40 Z2\nG01 Z-20 F3000\nM30\n";
    let clean = run(ENDS_TURNING, setup());
    clean.result.as_ref().unwrap();
    // The same run, X faulting 0.3 s after the end (program time; the probe's clock also
    // counts the drives' start-up): the spindle still creeping onto its angle.
    let end_ms = (clean.summary.machining_time_s * 1000.0) as u64;
    let mut s = setup();
    s.fault_at(end_ms + 300, 1, 0x2310);
    let o = run(ENDS_TURNING, s);
    assert!(o.summary.ended, "the program reached its end");
    let a = o.result.as_ref().expect_err("the fault is the run's alarm");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{a}");
    assert!(a.message.contains("0x2310") && a.message.contains("the program had reached its end at line 6"), "{a}");
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
}

/// A Z that hunts on its own on a set-point that stands still (a belt with lost motion, a slow
/// speed filter: ±28 µm on a constant set-point, its velocity loop through the target on nearly
/// every 2 ms cycle; a random model of `random_drive_models --loops`, 2026-12-01).
const HUNTING_Z: &str = "[[drive]]\nnode = 3\nkind = \"spindle\"\naxis = \"s1\"\ncounts_per_unit = 1000.0\ncounts_per_rev = 360000\n\n\
        [[drive]]\nnode = 1\nkind = \"linear\"\naxis = \"x\"\ncounts_per_unit = 10000.0\ncounts_per_rev = 100000\n\n\
        [[drive]]\nnode = 2\nkind = \"linear\"\naxis = \"z\"\ncounts_per_unit = 10000.0\ncounts_per_rev = 100000\n[drive.physics]\n\
        kv = 29.6\nvelocity_ff = 0.983\nload_stiffness = 17.9\nload_damping = 0.0153\nbacklash_deg = 0.1\n\
        vel_kp = 0.5942\nvel_ti_ms = 7.56\nspeed_filter_ms = 0.837\ncurrent_loop_tc_ms = 0.4124\n";

/// A Z that hunts on its own after the program's end (a belt with lost motion, a slow speed
/// filter: ±28 µm on a constant set-point, its velocity loop through the target on nearly every
/// 2 ms cycle) never settles; coming to rest it trips its
/// overcurrent (0x2310). That fault is the run's alarm, not just "quick stop was sent"
/// (found on a random model of `random_drive_models --loops`, 2026-12-01), and the alarm
/// names the hunt before it.
#[test]
fn a_fault_while_coming_to_rest_after_the_program_end_is_the_run_s_alarm() {
    let mut s = setup();
    s.sim = Some(HUNTING_Z);
    let o = run("G21\nG98\nG1 W-5 F300\nG4 P200\nG1 W5 F300\nG4 P200\nM30\n", s);
    assert!(o.summary.ended, "the program reached its end");
    let a = o.result.as_ref().expect_err("the fault is the run's alarm");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{a}");
    assert!(a.message.starts_with("after the program's end, while the drives came to rest") && a.message.contains("0x2310"), "{a}");
    // And the cause is named: Z hunted about its end point while the run waited for it.
    let z = o.summary.axes.iter().find(|a| a.name == "z").unwrap();
    let m = z.settle_miss.expect("Z had not settled");
    assert!(m.hunts() && m.peak_counts > 100, "{m:?}");
    assert!(a.message.contains("before that, axis z hunted about its end point"), "{a}");
    // Z's own fault reaction takes its torque (a drive's overcurrent trip is its own); the
    // others were quick-stopped and stood still.
    assert!(o.summary.rest.quick_stop && o.summary.rest.at_rest, "{:?}", o.summary.rest);
}

/// The same Z hunting through a dwell mid-program is named with the dwell's line, and where
/// it faults while at it (here 0x8611, injected mid-dwell), the alarm says it was hunting —
/// a following-error fault reads as lag at speed otherwise.
#[test]
fn a_drive_that_hunts_on_a_dwell_is_named_with_its_line() {
    const DWELL: &str = "G21\nG98\nG1 W-5 F300\nG4 P1500\nG1 W5 F300\nM30\n";
    let mut s = setup();
    s.sim = Some(HUNTING_Z);
    let o = run(DWELL, s);
    let z = o.summary.axes.iter().find(|a| a.name == "z").unwrap();
    let h = z.hunt.expect("Z hunted through the dwell");
    assert!(h.line == 4 && !h.at_alarm && h.miss.peak_counts > 100 && h.miss.crossings > 100, "{h:?}");
    assert!((h.miss.waited_s - 1.5).abs() < 0.05, "{h:?}");
    let t = z.hunt_text().unwrap();
    assert!(t.starts_with("axis z hunted at line 4 (1.50 s on its set-point): ±0.0") && t.contains("`cncgw identify z`"), "{t}");
    // X stood still too, and settled.
    assert_eq!(o.summary.axes.iter().find(|a| a.name == "x").unwrap().hunt, None);

    // The dwell runs from about 1.2 s (the drives' start-up included): Z faults at 2 s.
    let mut s = setup();
    s.sim = Some(HUNTING_Z);
    s.fault_at(2000, 2, 0x8611);
    let o = run(DWELL, s);
    let a = o.result.as_ref().expect_err("the fault is the run's alarm");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{a}");
    assert!(a.message.contains("0x8611") && a.message.contains("; axis z was hunting when the run stopped at line 4 ("), "{a}");
    let h = o.summary.axes.iter().find(|a| a.name == "z").unwrap().hunt.unwrap();
    assert!(h.at_alarm && h.line == 4, "{h:?}");
    check_rest(&o.summary.rest);
}

#[test]
fn reset_stops_spindle_and_axes_before_torque_off() {
    let p = Panel::new();
    let pr = p.clone();
    let mut s = setup();
    s.panel = Some(p);
    s.actions.push((1300, Box::new(move |_: &mut SimWorld| pr.press_reset())));
    let o = run(TURNING, s);
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::RESET);
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
}

#[test]
fn e_stop_brakes_every_drive_on_its_ramp_to_standstill() {
    let p = Panel::new();
    let pr = p.clone();
    let mut s = setup();
    s.panel = Some(p);
    s.actions.push((1300, Box::new(move |_: &mut SimWorld| pr.set_estop(true))));
    let o = run(TURNING, s);
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::ESTOP);
    let r = o.summary.rest;
    assert!(r.quick_stop && r.at_rest, "{r:?}");
    o.assert_rest_before_torque_off();
    // Out of Operation Enabled within 2 cycles of the press.
    let t = 1300 * MS;
    let out = o.samples.iter().find(|s| s.t > t && s.state.iter().all(|st| *st != State::OperationEnabled)).unwrap();
    assert!(out.t - t <= 3 * 2 * MS, "{} ms", (out.t - t) / MS);
}

#[test]
fn a_program_alarm_stops_spindle_and_axes_before_torque_off() {
    // X500 is beyond X's travel: refused as it reaches motion (alarm 2301), a controlled stop.
    let o = run("G21\nG98 G97\nM03 S1200\nG00 X40 Z2\nG01 Z-40 F3000\nG00 X500\nM30\n", setup());
    assert_eq!(o.result.as_ref().unwrap_err().number, cncgw::alarm::TRAVEL);
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
}

#[test]
fn a_termination_signal_is_a_reset() {
    static SIG: AtomicI32 = AtomicI32::new(0);
    let mut s = setup();
    s.signal = Some(&SIG);
    s.actions.push((1300, Box::new(|_: &mut SimWorld| SIG.store(15, Ordering::Relaxed))));
    let o = run(TURNING, s);
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::RESET, "{a}");
    assert!(a.message.contains("SIGTERM"), "{a}");
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
}

#[test]
fn a_slow_axis_stands_on_its_stop_point_before_torque_off() {
    // A soft X (position gain 15/s, 97 % feed-forward): after a reset it still creeps onto its
    // stop point long after the path stopped; torque must not go off before it is there.
    const SOFT_X: &str = "[[drive]]\nnode = 3\nkind = \"spindle\"\naxis = \"s1\"\ncounts_per_unit = 1000.0\ncounts_per_rev = 360000\n\n\
        [[drive]]\nnode = 1\nkind = \"linear\"\naxis = \"x\"\ncounts_per_unit = 10000.0\ncounts_per_rev = 100000\n[drive.physics]\nkv = 15.0\nvelocity_ff = 0.97\n\n\
        [[drive]]\nnode = 2\nkind = \"linear\"\naxis = \"z\"\ncounts_per_unit = 10000.0\ncounts_per_rev = 100000\n";
    let p = Panel::new();
    let pr = p.clone();
    let mut s = setup();
    s.sim = Some(SOFT_X);
    s.panel = Some(p);
    s.actions.push((700, Box::new(move |_: &mut SimWorld| pr.press_reset())));
    let o = run("G21\nG98\nG00 X100 Z2\nG00 X10\nM30\n", s);
    let a = o.result.as_ref().unwrap_err();
    assert_eq!(a.number, cncgw::alarm::RESET, "{a}");
    check_rest(&o.summary.rest);
    o.assert_rest_before_torque_off();
    // X stands on the commanded stop point (the last set-point) within a micrometre.
    let dx = o.nodes.iter().position(|n| *n == 1).unwrap();
    let last_on = o.samples.iter().rposition(|s| powered(s.state[dx])).unwrap();
    let stop = o.summary.axes.iter().find(|a| a.name == "x").unwrap().final_target_counts;
    let at = o.samples[last_on].pos[dx];
    assert!((at - stop).abs() <= 10, "X at {at} counts, stop point {stop}");
}
