//! G12.1/G13.1 polar coordinate interpolation (manual 004 §2.7, the figure 2.12 program) and
//! G51.2/G50.2 polygon turning (§2.8, EX3).

use cncgw::canon::{Move, MoveKind, PolygonCmd};
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::interp::{parse_tool_table, Interpreter};
use cncgw::Alarm;

/// §2.7 fig. 2.12, as printed, with G98 (the machine powers on in G99).
const FIG_2_12: &str = "G98\nN100 G00 X150 C0 Z0\nN110 G12.1\nN120 G42 G01 X60 F200\nN130 C25\nN140 G03 X50 C30 R5\n\
N150 G01 X-50\nN160 G03 X-60 C25 R5\nN170 G01 C-25\nN180 G03 X-50 C-30 R5\nN190 G01 X50\nN200 G03 X60 C-25 R5\nN210 C0\n\
N220 G40 X150\nN230 G13.1\nN240 Z100\nN250 M30\n";

fn interp(src: &str, cfg: &MachineConfig, tools: Option<&str>) -> Interpreter {
    let mut it = Interpreter::from_source("t.nc", src, cfg).unwrap_or_else(|e| panic!("{e:?}"));
    if let Some(t) = tools {
        it.set_tool_table(parse_tool_table("tools.toml", t).expect("table"));
    }
    it
}

/// The lathe with a tool spindle (polygon turning needs one).
const POLYGON_LATHE: &str = include_str!("../../config/lathe-polygon.toml");

/// No.3403#5 = 0: G02/G03 without R is a straight line (§2.3 note 2), which fig. 2.12 relies
/// on: its N210 C0 is modal G03 without R.
fn cfg() -> MachineConfig {
    let text = POLYGON_LATHE.replace("[parameters]\n", "[parameters]\n3403 = 0\n");
    MachineConfig::from_toml("t.toml", &text).expect("config")
}

fn run(src: &str, tools: Option<&str>) -> Vec<Move> {
    interp(src, &cfg(), tools).map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

fn alarm_cfg(src: &str, cfg: &MachineConfig) -> Alarm {
    for m in interp(src, cfg, None) {
        if let Err(a) = m {
            return a;
        }
    }
    panic!("no alarm")
}

fn alarm(src: &str) -> Alarm {
    alarm_cfg(src, &MachineConfig::embedded())
}

/// (virtual to [x diameter, c], machine X diameter, machine C degrees, arc?) of each polar move.
fn polar(m: &[Move]) -> Vec<([f64; 2], f64, f64, bool)> {
    m.iter()
        .filter_map(|m| match &m.kind {
            MoveKind::Polar { end, to, center, .. } => Some(([to[0] * 2.0, to[1]], end.x * 2.0, end.c, center.is_some())),
            _ => None,
        })
        .collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-6
}

#[test]
fn figure_2_12_without_nose_radius() {
    let m = run(FIG_2_12, None);
    let p = polar(&m);
    let want: [([f64; 2], bool); 11] = [
        ([60.0, 0.0], false),
        ([60.0, 25.0], false),
        ([50.0, 30.0], true),
        ([-50.0, 30.0], false),
        ([-60.0, 25.0], true),
        ([-60.0, -25.0], false),
        ([-50.0, -30.0], true),
        ([50.0, -30.0], false),
        ([60.0, -25.0], true),
        ([60.0, 0.0], false),
        ([150.0, 0.0], false),
    ];
    assert_eq!(p.len(), want.len(), "{p:?}");
    for (g, (v, arc)) in p.iter().zip(&want) {
        assert!(close(g.0[0], v[0]) && close(g.0[1], v[1]) && g.3 == *arc, "{g:?} vs {v:?}");
        // Machine X is the distance from the centre (as a diameter), C its angle.
        let r = (v[0] / 2.0).hypot(v[1]);
        assert!(close(g.1, 2.0 * r), "{g:?}");
    }
    // C: atan2(25, 30) after N130; once round the square CCW: 360° at N210 and N220.
    assert!(close(p[1].2, 25f64.atan2(30.0).to_degrees()), "{:?}", p[1]);
    assert!(close(p[3].2, 30f64.atan2(-25.0).to_degrees()), "{:?}", p[3]);
    assert!(close(p[9].2, 360.0) && close(p[10].2, 360.0), "{p:?}");
    // The arc N140's centre is the corner (X50, C25) less the radius: virtual (25, 25).
    let c = m.iter().find_map(|m| match &m.kind {
        MoveKind::Polar { center: Some(c), .. } => Some(*c),
        _ => None,
    });
    assert_eq!(c.map(|c| [(c[0] * 1e6).round() / 1e6, (c[1] * 1e6).round() / 1e6]), Some([25.0, 25.0]));
    // After G13.1, Z moves in the ZX plane again.
    let last = m.iter().filter_map(|m| m.kind.end()).next_back().unwrap();
    assert!(close(last.z, 100.0));
}

#[test]
fn figure_2_12_with_g42_offsets_the_square_outwards() {
    // Nose radius 0.4: in the polar plane the nose centre is offset (tip 0, §2.18.1 note).
    let m = run(&FIG_2_12.replace("G98\n", "G98 T0101\n"), Some("[1]\nr = 0.4\ntip = 3\n"));
    let p = polar(&m);
    // Start-up N120 ends where the offset lines of N120 (C = 0.4) and N130 (X = 30.4) meet.
    assert!(close(p[0].0[0], 60.8) && close(p[0].0[1], 0.4), "{:?}", p[0]);
    // N130 ends tangent to the arc: X30.4, C25; the arc's radius grows to 5.4.
    assert!(close(p[1].0[0], 60.8) && close(p[1].0[1], 25.0), "{:?}", p[1]);
    assert!(close(p[2].0[0], 50.0) && close(p[2].0[1], 30.4), "{:?}", p[2]);
    // N210 ends on the cancel block's offset line: (30.4, −0.4); the G40 block goes to X150.
    let n = p.len();
    assert!(close(p[n - 2].0[0], 60.8) && close(p[n - 2].0[1], -0.4), "{:?}", p[n - 2]);
    assert!(close(p[n - 1].0[0], 150.0) && close(p[n - 1].0[1], 0.0), "{:?}", p[n - 1]);
}

#[test]
fn polar_alarms() {
    let pre = "G98 G00 X150 C0 Z0\nG12.1\n";
    // Note 4: G00 (modal or written) is not allowed.
    assert_eq!(alarm(&format!("{pre}G00 X60\nM30\n")).number, 10);
    assert_eq!(alarm("G98 G00 X150 C0 Z0\nG12.1\nX60\nM30\n").number, 10);
    assert_eq!(alarm(&format!("{pre}G01 X60 F100\nG50 X0\nM30\n")).number, 10);
    // Note 6: R only.
    assert_eq!(alarm(&format!("{pre}G01 X60 F100\nG03 X50 C10 I-5\nM30\n")).number, 22);
    // Note 8: not in G41/G42.
    assert_eq!(alarm("G98 G00 X150 C0 Z0\nG42 G01 X140 F100\nG12.1\nM30\n").number, 37);
    // Alone in its block.
    let a = alarm("G98 G00 X150 C0 Z0\nG12.1 X60\nM30\n");
    assert_eq!((a.number, a.pos.as_ref().map(|p| (p.line, p.col))), (10, Some((2, 1))), "{a}");
    // Note 9: through the centre, or too close at this F for the C axis' speed.
    assert_eq!(alarm(&format!("{pre}G01 X-60 F200\nM30\n")).number, cncgw::alarm::VALUE_RANGE);
    // A spindle of 10 rpm max = 3600°/min = 62.8 rad/min: F200 needs d ≥ 3.18 mm.
    let text = EMBEDDED_LATHE.replace("max_speed = 6000.0", "max_speed = 10.0");
    assert!(text.contains("max_speed = 10.0"));
    {
        let cfg = MachineConfig::from_toml("c.toml", &text).unwrap_or_else(|e| panic!("{e}"));
        // (10, 0) → (10, 5) → (−10, 5) keeps ≥ 5 mm from the centre: 2292°/min, allowed.
        let ok = format!("{pre}G01 X20 F200\nC5\nX-20\n");
        assert!(interp(&format!("{ok}M30\n"), &cfg, None).all(|m| m.is_ok()));
        // (−10, 5) → (10, −2) passes 1.42 mm from it: 8100°/min, refused.
        let a = alarm_cfg(&format!("{ok}X20 C-2\nM30\n"), &cfg);
        assert_eq!(a.number, cncgw::alarm::VALUE_RANGE, "{a}");
        assert_eq!(a.pos.as_ref().map(|p| p.line), Some(6), "{a}");
    }
}

fn polygons(m: &[Move]) -> Vec<Option<PolygonCmd>> {
    m.iter()
        .filter_map(|m| match &m.kind {
            MoveKind::Polygon(p) => Some(*p),
            _ => None,
        })
        .collect()
}

#[test]
fn polygon_ex3() {
    let src = "T0101 G98\nG51.2 P1 Q2 R60 S1000\nG0 X50 Z2\nG01 W-10 F200\nG01 U2\nG0 Z2\nG50.2\nG51.2 P1 Q3 R180 S1000\nG01 X50 Z2\n\
G01 W-10 F200\nG01 U2\nG0 Z2\nG50.2\nM30\n";
    let m = run(src, None);
    let p = polygons(&m);
    assert_eq!(p.len(), 4);
    assert_eq!(p[0], Some(PolygonCmd { p: 1, q: 2, phase: 60.0, rpm: 1000.0, tool_rpm: 2000.0 }));
    assert_eq!(p[1], None);
    assert_eq!(p[2], Some(PolygonCmd { p: 1, q: 3, phase: 180.0, rpm: 1000.0, tool_rpm: 3000.0 }));
    assert_eq!(p[3], None);
}

#[test]
fn polygon_clamp_and_alarms() {
    let text = POLYGON_LATHE.replace("721 = 5000", "721 = 2500");
    let cfg = MachineConfig::from_toml("p.toml", &text).expect("config");
    assert!(text.contains("721 = 2500"));
    let m: Vec<Move> = interp("G51.2 P1 Q3 S1000\nM30\n", &cfg, None).map(|m| m.unwrap()).collect();
    // Note 3: S × Q / P = 3000 rpm clamped to No.721.
    assert_eq!(polygons(&m)[0].map(|p| p.tool_rpm), Some(2500.0));
    assert_eq!(alarm_cfg("G51.2 P0 Q2 S1000\nM30\n", &cfg).number, cncgw::alarm::VALUE_RANGE);
    assert_eq!(alarm_cfg("G51.2 P1 Q2 R360 S1000\nM30\n", &cfg).number, cncgw::alarm::VALUE_RANGE);
    assert_eq!(alarm_cfg("G51.2 P1 Q2 S1000 X20\nM30\n", &cfg).number, 10);
    assert_eq!(alarm_cfg("G51.2 P1 Q2 S1000\nG0 C90\nM30\n", &cfg).number, 9);
}

/// A machine without a tool spindle refuses G51.2 (and G50.2) while interpreting, before
/// any motion, saying what the config lacks.
#[test]
fn polygon_without_a_tool_spindle_is_refused() {
    let cfg = MachineConfig::from_toml("lathe.toml", EMBEDDED_LATHE).expect("config");
    let a = alarm_cfg("G98\nM03 S500\nG51.2 P1 Q2 S1000\nG0 X50\nM30\n", &cfg);
    assert_eq!(a.number, cncgw::alarm::NO_TOOL_SPINDLE, "{a}");
    assert!(a.message.contains("tool spindle") && a.message.contains("role = \"tool_spindle\""), "{a}");
    assert_eq!(a.pos.as_ref().map(|p| p.line), Some(3), "{a}");
}
