//! G22/G23 carried in the move stream to the per-set-point guard: the cycle loop switches
//! stored stroke check 2 when execution reaches the block, and a set-point entering the area
//! is never sent (502/503), even when the interpreter's own check never saw the move.
//! Embedded machine, sim-drives in simulated time.

use cncgw::canon::{Feed, Move, MoveKind, Pos, SrcPos, StrokeArea};
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::control::cycle::{CycleLoop, RunSummary};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw::interp::cycles::stroke::MINUS_ALARM;
use cncgw::interp::plan::{move_to_json, move_to_text};
use cncgw::interp::Interpreter;
use cncgw::motion::{Event, Feedback, Limits, Motion, AX_S, AX_X, AX_Y, AX_Z};
use cncgw::Alarm;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use sim_drives::SimWorld;

const CYCLE: u64 = 2_000_000;

/// The interpreter's moves for `program` (no M30), then `extra` pushed directly (bypassing
/// the interpreter and its G22 check), then M30.
fn moves(program: &str, cfg: &MachineConfig, start: Pos, extra: &[Move]) -> Vec<Move> {
    let mut it = Interpreter::from_source("g22.nc", program, cfg).expect("program parses");
    it.set_start_position(start);
    let mut v: Vec<Move> = it.map(|m| m.expect("the interpreter's check passes")).collect();
    v.extend_from_slice(extra);
    v.push(mv(99, MoveKind::End { code: 30 }));
    v
}

fn mv(line: u32, kind: MoveKind) -> Move {
    Move { src: SrcPos::new("direct".into(), line, 1), kind, exact_stop: true, work_offset: Pos::ZERO, tag: None }
}

/// A feed along X only, to X radius 30 (Ø60) at Z−20: into the G22 area below.
fn into_area() -> Move {
    mv(50, MoveKind::Feed { end: Pos { x: 30.0, y: 0.0, z: -20.0, c: 0.0 }, feed: Feed::PerMin(3000.0) })
}

struct Outcome {
    result: Result<(), Alarm>,
    world: SimWorld,
    /// Last X target sent, mm (radius).
    x_sent: f64,
}

fn run(program: &str, extra: &[Move]) -> Outcome {
    let cfg = MachineConfig::embedded();
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut master = CanOpenMaster::new(wire.endpoint(), &cfg);
    let spindle = cfg.axes.values().position(|a| a.kind == cncgw::config::AxisKind::Spindle);
    let mut summary = RunSummary::default();
    let result = {
        let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(&cfg), spindle, CYCLE);
        match lp.start(&mut summary) {
            Err(a) => Err(a),
            Ok(start) => {
                let p = Pos { x: start[AX_X], y: start[AX_Y], z: start[AX_Z], c: start[AX_S] };
                let (tx, rx) = std::sync::mpsc::sync_channel(1024);
                for m in moves(program, &cfg, p, extra) {
                    tx.send(Ok(m)).unwrap();
                }
                drop(tx);
                lp.run(start, rx, &mut summary, &mut |_| {})
            }
        }
    };
    let x = cfg.axes.keys().position(|k| k == "x").unwrap();
    let x_sent = master.target_counts(x) as f64 / cfg.axes["x"].counts_per_unit;
    Outcome { result, world, x_sent }
}

/// G22 area X Ø40…Ø100 (radius 20…50), Z −50…0, inside forbidden (No.1002#0 = 0).
const G22_ON: &str = "G98\nG22 X100 Z0 I40 K-50\nG0 X200 Z2\nZ-20\n";

#[test]
fn a_setpoint_entering_the_g22_area_is_stopped_before_it_is_sent() {
    let mut o = run(G22_ON, &[into_area()]);
    let a = o.result.as_ref().expect_err("the guard stops the run");
    assert!(a.number == MINUS_ALARM, "X moves towards −: 503, {a}");
    assert!(a.message.contains("line 50") && a.message.contains("set-point X49.") && a.message.contains("G22"), "{a}");
    // The last X target sent is still outside the area (radius ≥ 50).
    assert!(o.x_sent >= 50.0 - 1e-6, "last X target sent {}", o.x_sent);
    assert!(o.x_sent < 100.0, "X did move towards the area: {}", o.x_sent);
    // Quick stop: nothing moves a second later.
    let t = o.world.now_ns() + 1_000_000_000;
    o.world.wait_until(t);
    let moving: Vec<_> = o.world.drives().iter().filter(|d| d.velocity_actual().abs() > 50).map(|d| d.node()).collect();
    assert!(moving.is_empty(), "drives still moving: {moving:?}");
}

#[test]
fn g23_switches_the_setpoint_check_off() {
    let o = run(&format!("{G22_ON}G23\n"), &[into_area()]);
    assert!(o.result.is_ok(), "{:?}", o.result);
    assert!((o.x_sent - 30.0).abs() < 1e-3, "X reached radius 30: {}", o.x_sent);
    // And the area only applies from the G22 on: the same move before it runs.
    let o = run("G98\nG0 X200 Z2\nZ-20\n", &[into_area(), mv(60, MoveKind::StrokeCheck { area: None })]);
    assert!(o.result.is_ok(), "{:?}", o.result);
}

#[test]
fn a_stroke_check_pushed_directly_takes_effect_in_program_order() {
    // Moves pushed directly: the area switched on after the first feed, which ends inside it
    // (allowed: it was not on yet), so the second feed, leaving and re-entering, stops.
    let area = StrokeArea {
        lo: Pos { x: 20.0, y: f64::NEG_INFINITY, z: -50.0, c: 0.0 },
        hi: Pos { x: 50.0, y: f64::INFINITY, z: 0.0, c: 0.0 },
        outside: false,
    };
    let extra = [
        mv(10, MoveKind::Feed { end: Pos { x: 100.0, y: 0.0, z: -20.0, c: 0.0 }, feed: Feed::PerMin(3000.0) }),
        mv(11, MoveKind::StrokeCheck { area: Some(area) }),
        into_area(),
    ];
    let o = run("G98\n", &extra);
    let a = o.result.expect_err("stopped");
    assert_eq!(a.number, MINUS_ALARM, "{a}");
    assert!(a.message.contains("line 50"), "{a}");
}

#[test]
fn motion_reports_the_switch_when_execution_reaches_it() {
    let cfg = MachineConfig::embedded();
    let mut m = Motion::new(Limits::from_config(&cfg), [100.0, 0.0, -20.0, 0.0]);
    let area = StrokeArea {
        lo: Pos { x: 20.0, y: f64::NEG_INFINITY, z: -50.0, c: 0.0 },
        hi: Pos { x: 50.0, y: f64::INFINITY, z: 0.0, c: 0.0 },
        outside: true,
    };
    m.push(&mv(1, MoveKind::Feed { end: Pos { x: 90.0, y: 0.0, z: -20.0, c: 0.0 }, feed: Feed::PerMin(600.0) })).unwrap();
    m.push(&mv(2, MoveKind::StrokeCheck { area: Some(area) })).unwrap();
    m.push(&mv(3, MoveKind::StrokeCheck { area: None })).unwrap();
    let fb = Feedback::default();
    let mut seen = Vec::new();
    for _ in 0..5000 {
        let sp = m.step(&fb);
        if let Event::Stroke2(a) = sp.event {
            seen.push((sp.line, a, sp.pos[AX_X]));
        }
    }
    assert_eq!(seen.len(), 2, "{seen:?}");
    // Reached after the feed has ended, not when pushed.
    assert_eq!(seen[0].0, 2);
    assert!((seen[0].2 - 90.0).abs() < 1e-9, "{seen:?}");
    let a = seen[0].1.expect("G22 on");
    assert_eq!((a.lo, a.hi, a.outside), ([20.0, f64::NEG_INFINITY, -50.0], [50.0, f64::INFINITY, 0.0], true));
    assert_eq!((seen[1].0, seen[1].1), (3, None));
}

#[test]
fn the_interpreter_emits_g22_and_g23_in_order_and_plan_shows_them() {
    let cfg = MachineConfig::embedded();
    let it = Interpreter::from_source("p.nc", "G98\nG22 X100 Z0 I40 K-50\nG0 X200 Z10\nG23\nG22 X40 Z0 I100 K-50\nM30\n", &cfg).unwrap();
    let ms: Vec<Move> = it.map(|m| m.unwrap()).collect();
    let sc: Vec<&Move> = ms.iter().filter(|m| matches!(m.kind, MoveKind::StrokeCheck { .. })).collect();
    assert_eq!(sc.len(), 3, "{ms:?}");
    let MoveKind::StrokeCheck { area: Some(a) } = &sc[0].kind else { panic!("{:?}", sc[0]) };
    assert_eq!((a.lo.x, a.lo.z, a.hi.x, a.hi.z, a.outside), (20.0, -50.0, 50.0, 0.0, false));
    assert_eq!(sc[0].src.line, 2);
    // G23; then corners in the wrong order disable the check (§2.10 note 8).
    assert_eq!((sc[1].src.line, &sc[1].kind), (4, &MoveKind::StrokeCheck { area: None }));
    assert_eq!((sc[2].src.line, &sc[2].kind), (5, &MoveKind::StrokeCheck { area: None }));
    // Between G22 and G23 comes the rapid, in program order.
    let i = ms.iter().position(|m| m.src.line == 3).unwrap();
    let j = ms.iter().position(|m| m.src.line == 2).unwrap();
    let k = ms.iter().position(|m| m.src.line == 4).unwrap();
    assert!(j < i && i < k);

    let j = move_to_json(sc[0]);
    assert_eq!(j, r#"{"file":"p.nc","forbid":"inside","hi":{"x":100.0,"z":0.0},"kind":"stroke_check","line":2,"lo":{"x":40.0,"z":-50.0}}"#);
    assert_eq!(move_to_json(sc[1]), r#"{"file":"p.nc","forbid":"none","kind":"stroke_check","line":4}"#);
    let t = move_to_text(sc[0]);
    assert!(t.contains("stroke_check") && t.contains("forbid inside X40.000…100.000 Z-50.000…0.000"), "{t}");
    assert!(move_to_text(sc[1]).contains("stroke_check off"), "{}", move_to_text(sc[1]));
}
