//! T codes with the tool table, G28/G30 reference points from the parameters, M91/M92.

use cncgw::canon::{Move, MoveKind, Pos};
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::interp::{parse_tool_table, plan, Interpreter, ToolTable};
use cncgw::Alarm;

const TABLE: &str = "
[1]
x = -10.0     # diameter
z = 5.0
wear_x = 0.2
wear_z = -0.1
r = 0.4
tip = 3
[2]
x = 4.0
z = -1.0
";

fn table() -> ToolTable {
    parse_tool_table("tools.toml", TABLE).expect("valid table")
}

fn interp(src: &str, cfg: &MachineConfig, t: Option<ToolTable>) -> Interpreter {
    let mut it = Interpreter::from_source("t.nc", src, cfg).unwrap_or_else(|e| panic!("{e:?}"));
    if let Some(t) = t {
        it.set_tool_table(t);
    }
    it
}

fn run_with(src: &str, cfg: &MachineConfig, t: Option<ToolTable>) -> Vec<Move> {
    interp(src, cfg, t).map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

fn first_alarm(it: Interpreter) -> Alarm {
    for m in it {
        if let Err(a) = m {
            return a;
        }
    }
    panic!("no alarm")
}

fn ends(m: &[Move]) -> Vec<Pos> {
    m.iter().filter_map(|m| m.kind.end()).collect()
}

fn close(a: Pos, b: Pos) -> bool {
    (a.x - b.x).abs() < 1e-9 && (a.z - b.z).abs() < 1e-9
}

fn cfg_with(params: &str) -> MachineConfig {
    let text = format!("{EMBEDDED_LATHE}\n{params}\n");
    MachineConfig::from_toml("t.toml", &text).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn tool_table_parses_and_rejects_bad_entries() {
    let t = table();
    let o = t.get(1).expect("offset 1");
    assert_eq!((o.x, o.z, o.wear_x, o.wear_z, o.r, o.tip), (-10.0, 5.0, 0.2, -0.1, 0.4, 3));
    assert_eq!(t.get(2).expect("offset 2").r, 0.0);
    for (bad, key) in [("[1]\ntip = 12", "tip"), ("[1]\nr = -1", "r"), ("[abc]\nx = 1", "[abc]"), ("[1]\nq = 1", "q")] {
        let e = parse_tool_table("tools.toml", bad).expect_err(bad);
        assert_eq!(e.number, cncgw::alarm::CONFIG);
        assert!(e.message.contains(key), "{bad}: {}", e.message);
    }
}

#[test]
fn t_code_offset_is_taken_up_by_each_axis_with_its_next_move() {
    let cfg = MachineConfig::embedded();
    let src = "G0 X50 Z10\nT0101\nG0 X40\nW-2\nG0 Z0\nT0100\nG0 X40 Z0\nM30";
    let mut it = interp(src, &cfg, Some(table()));
    let mut moves = Vec::new();
    let mut tool_after_t0101 = None;
    while let Some(m) = it.next_move().expect("runs") {
        if m.kind == (MoveKind::Aux { letter: 'T', value: 101.0 }) {
            tool_after_t0101 = Some(it.active_tool());
        }
        moves.push(m);
    }
    let t = tool_after_t0101.expect("T0101 is passed on as an aux move for the turret");
    assert_eq!((t.tool, t.offset, t.nose_radius, t.tip), (1, 1, 0.4, 3));
    assert_eq!(it.active_tool().offset, 0, "T0100 cancels the offset");
    let e = ends(&moves);
    // X offset (-10 + 0.2) diameter = -4.9 radius; Z offset 5 - 0.1 = 4.9.
    let want = [Pos::xz(25.0, 10.0), Pos::xz(15.1, 10.0), Pos::xz(15.1, 12.9), Pos::xz(15.1, 4.9), Pos::xz(20.0, 0.0)];
    assert_eq!(e.len(), want.len(), "{moves:?}");
    for (a, b) in e.iter().zip(want) {
        assert!(close(*a, b), "{a:?} != {b:?}");
    }
    // The operator reads programmed coordinates: the applied offset is in work_offset.
    let j = plan::move_to_json(&moves[2]);
    assert!(j.contains("\"x\":40.0") && j.contains("\"z\":10.0"), "{j}");
}

#[test]
fn t_in_a_block_with_motion_applies_with_it() {
    let m = run_with("T0202 G0 X40 Z0\nM30", &MachineConfig::embedded(), Some(table()));
    assert_eq!(m[0].kind, MoveKind::Aux { letter: 'T', value: 202.0 }, "the turret indexes before the move");
    assert!(close(m[1].kind.end().expect("rapid"), Pos::xz(22.0, -1.0)), "{:?}", m[1]);
}

#[test]
fn offset_number_not_in_the_table_is_alarm_30() {
    let a = first_alarm(interp("G0 X10 Z0\nT0505\nM30", &MachineConfig::embedded(), Some(table())));
    assert_eq!(a.number, 30);
    assert_eq!(a.pos.as_ref().map(|p| p.line), Some(2));
    // Without a table every offset reads as zero.
    let m = run_with("T0505\nG0 X10 Z0\nM30", &MachineConfig::embedded(), None);
    assert!(close(m[1].kind.end().expect("rapid"), Pos::xz(5.0, 0.0)));
}

#[test]
fn g28_g30_go_to_the_reference_points_of_the_parameters() {
    let cfg = cfg_with("1240 = { x = 200.0, z = 100.0 }\n1242 = { x = 150, z = -20 }");
    let m = run_with("G0 X100 Z-50\nG28 U0 W10\nG0 X60 Z-10\nG30 P3 X80\nM30", &cfg, None);
    let e = ends(&m);
    let want = [
        Pos::xz(50.0, -50.0),
        Pos::xz(50.0, -40.0), // intermediate point
        Pos::xz(100.0, 100.0),
        Pos::xz(30.0, -10.0),
        Pos::xz(40.0, -10.0),
        Pos::xz(75.0, -10.0), // only X returns
    ];
    assert_eq!(e.len(), want.len(), "{m:?}");
    for (a, b) in e.iter().zip(want) {
        assert!(close(*a, b), "{a:?} != {b:?}");
    }
    // G30 without P is P2, which this configuration lacks; P5 does not exist.
    for (src, col) in [("G30 U0\nM30", 1), ("G30 P5 W0\nM30", 5)] {
        let a = first_alarm(interp(src, &cfg, None));
        assert_eq!(a.number, 46, "{src}: {a}");
        assert_eq!(a.pos.as_ref().map(|p| p.col), Some(col), "{src}: {a}");
    }
    // No.1240 absent: the reference point is machine zero.
    let m = run_with("G0 X100 Z-50\nG28 U0 W0\nM30", &MachineConfig::embedded(), None);
    assert!(close(ends(&m)[2], Pos::ZERO));
}

#[test]
fn per_axis_parameter_must_be_numbers() {
    let text = format!("{EMBEDDED_LATHE}\n1241 = {{ x = \"far\" }}\n");
    let e = MachineConfig::from_toml("t.toml", &text).expect_err("string in a per-axis parameter").to_string();
    assert!(e.contains("parameters.1241"), "{e}");
    assert_eq!(cfg_with("1241 = { x = 10, z = 2.5 }").param_axis(1241, "z"), Some(2.5));
}

const JUMP: &str = "N10 M92 P100\nG0 X10 Z0\nN100 G0 X20 Z0\nN110 M91 P200\nG0 X30\nN200 M30\n";

fn xs(m: &[Move]) -> Vec<f64> {
    ends(m).iter().map(|p| p.x * 2.0).collect()
}

#[test]
fn m91_m92_jump_on_the_input_signal() {
    let cfg = MachineConfig::embedded();
    // Default: every input off → M92 goes on, M91 jumps.
    assert_eq!(xs(&run_with(JUMP, &cfg, None)), [10.0, 20.0]);
    // Input on → M92 jumps, M91 goes on.
    let mut it = interp(JUMP, &cfg, None);
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let s2 = seen.clone();
    it.set_input_source(move |m| {
        s2.lock().expect("lock").push(m);
        true
    });
    let m: Vec<Move> = it.map(|m| m.expect("runs")).collect();
    assert_eq!(xs(&m), [20.0, 30.0]);
    assert_eq!(*seen.lock().expect("lock"), [92, 91]);
}

#[test]
fn m91_m92_alarms() {
    let cfg = MachineConfig::embedded();
    let e = Interpreter::from_source("t.nc", "M92 P999\nM30", &cfg).err().expect("static error");
    assert_eq!(e[0].number, 78);
    let a = first_alarm(interp("M91\nM30", &cfg, None));
    assert_eq!(a.number, 9);
    let a = first_alarm(interp("#1=0\nM91 P#1\nM30", &cfg, None));
    assert_eq!(a.number, 128);
}
