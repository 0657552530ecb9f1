use super::*;
use crate::canon::MoveKind as K;

fn cfg() -> MachineConfig {
    MachineConfig::embedded()
}

fn run(src: &str) -> Vec<Move> {
    let it = Interpreter::from_source("t.nc", src, &cfg()).unwrap_or_else(|e| panic!("{e:?}"));
    it.map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect()
}

fn run_err(src: &str) -> Alarm {
    let it = Interpreter::from_source("t.nc", src, &cfg()).unwrap_or_else(|e| panic!("{e:?}"));
    for m in it {
        if let Err(a) = m {
            return a;
        }
    }
    panic!("no alarm")
}

fn static_errs(src: &str) -> Vec<Alarm> {
    match Interpreter::from_source("t.nc", src, &cfg()) {
        Err(e) => e,
        Ok(_) => panic!("expected static errors"),
    }
}

fn close(a: Pos, b: Pos) -> bool {
    (a.x - b.x).abs() < 1e-9 && (a.z - b.z).abs() < 1e-9 && (a.y - b.y).abs() < 1e-9 && (a.c - b.c).abs() < 1e-9
}

#[test]
fn small_program_exact_moves() {
    let m = run("%\nO0001\nN1 G21 (metric)\nN2 G99 G00 X40 Z5;\nN3 M03 S800\nG01 Z-20. F0.2\nU10 W-5\nG98 F300 X60\nM30\n%\n");
    let kinds: Vec<&str> = m.iter().map(|m| m.kind.name()).collect();
    assert_eq!(kinds, ["rapid", "spindle", "feed", "feed", "feed", "end"]);
    assert_eq!(m[0].kind, K::Rapid { end: Pos::xz(20.0, 5.0) });
    assert!(m[0].exact_stop);
    assert_eq!(m[0].src.line, 4);
    assert_eq!(m[1].kind, K::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm: 800.0, css: None, max_rpm: None }));
    assert_eq!(m[2].kind, K::Feed { end: Pos::xz(20.0, -20.0), feed: Feed::PerRev(0.2) });
    assert!(!m[2].exact_stop);
    // U is a diameter increment: +10 → radius +5.
    assert_eq!(m[3].kind, K::Feed { end: Pos::xz(25.0, -25.0), feed: Feed::PerRev(0.2) });
    assert_eq!(m[4].kind, K::Feed { end: Pos::xz(30.0, -25.0), feed: Feed::PerMin(300.0) });
    assert_eq!(m[5].kind, K::End { code: 30 });
    assert_eq!(m[4].work_offset, Pos::ZERO);
}

#[test]
fn manual_arc_example_fig_2_6() {
    // Manual §2.3, figure 2.6.
    let m = run(
        "N001 G0 X40 Z5\nN002 M03 S200\nN003 G01 X0 Z0 F900\nN005 G03 U24 W-24 R15\nN006 G02 X26 Z-31 R5\nN007 G01 Z-40;\nN008 X40 Z5;\nN009 M30;\n",
    );
    let arcs: Vec<_> = m.iter().filter(|m| m.kind.name() == "arc").collect();
    assert_eq!(arcs.len(), 2);
    let K::Arc { end, center, cw, plane, .. } = &arcs[0].kind else { panic!() };
    assert!(close(*end, Pos::xz(12.0, -24.0)));
    assert!(close(*center, Pos::xz(0.0, -15.0)), "{center:?}");
    assert!(!cw);
    assert_eq!(*plane, Plane::Zx);
    let K::Arc { end, center, cw, .. } = &arcs[1].kind else { panic!() };
    assert!(close(*end, Pos::xz(13.0, -31.0)));
    assert!(*cw);
    // Centre 5 mm from both ends.
    let r1 = (center.x - 12.0).hypot(center.z + 24.0);
    let r2 = (center.x - 13.0).hypot(center.z + 31.0);
    assert!((r1 - 5.0).abs() < 1e-9 && (r2 - 5.0).abs() < 1e-9);
}

#[test]
fn arc_with_i_k_and_negative_r() {
    // Manual §2.3: G02 X50 Z30 I25 from X30 Z50 (I is a radius value).
    let m = run("G99 G00 X30 Z50\nG02 X50 Z30 I25 F0.1\nG00 X0 Z0\nG02 X0 Z-20 R-10\nM30");
    let K::Arc { center, .. } = &m[1].kind else { panic!("{:?}", m[1]) };
    assert!(close(*center, Pos::xz(40.0, 50.0)));
    // R<0: >180° arc. From (0,0) to (0,-20) with |R|=10 the centre is the midpoint either way.
    let K::Arc { center, .. } = &m[3].kind else { panic!() };
    assert!(close(*center, Pos::xz(0.0, -10.0)));
    // R<0 with a shorter chord puts the centre on the other side than R>0.
    let a = run("G99 G00 X0 Z0\nG02 X0 Z-10 R10 F0.1\nM30");
    let b = run("G99 G00 X0 Z0\nG02 X0 Z-10 R-10 F0.1\nM30");
    let (K::Arc { center: ca, .. }, K::Arc { center: cb, .. }) = (&a[1].kind, &b[1].kind) else { panic!() };
    assert!((ca.x + cb.x).abs() < 1e-9 && ca.x.abs() > 1.0, "{ca:?} {cb:?}");
}

#[test]
fn arc_radius_mismatch_and_missing_centre() {
    let a = run_err("G99 G00 X30 Z50\nG02 X50 Z30 I20 F0.1\nM30");
    assert_eq!(a.number, crate::alarm::ARC_RADIUS);
    assert_eq!(a.pos.as_ref().unwrap().line, 2);
    let a = run_err("G99 G00 X30 Z50\nG02 X50 Z30 F0.1\nM30");
    assert_eq!(a.number, 22);
    let a = run_err("G99 G00 X0 Z0\nG02 X0 Z-30 R10 F0.1\nM30");
    assert_eq!(a.number, crate::alarm::ARC_RADIUS);
}

#[test]
fn no_feed_rate_is_alarm_11() {
    let a = run_err("G00 X10 Z0\nG01 Z-10\nM30");
    assert_eq!(a.number, crate::alarm::FEED_ZERO);
    assert_eq!(a.pos.unwrap().line, 2);
    // G98/G99 keep separate F values (§2.20 note 4): F under G99 does not carry to G98.
    let a = run_err("G99 G01 X10 F0.2\nG98 Z-5\nM30");
    assert_eq!(a.number, crate::alarm::FEED_ZERO);
}

#[test]
fn dwell_p_ms_x_seconds() {
    let m = run("G04 P500\nG04 X1.5\nG04 U2\nG04\nM30");
    let d: Vec<f64> = m.iter().filter_map(|m| if let K::Dwell { seconds } = m.kind { Some(seconds) } else { None }).collect();
    assert_eq!(d, [0.5, 1.5, 2.0, 0.0]);
    let e = static_errs("G04 P1.5\nM30");
    assert_eq!(e[0].number, 7);
}

#[test]
fn inch_input_converts_to_mm() {
    let m = run("G20\nG98 G01 X2. Z-1. F10\nM30");
    assert_eq!(m[0].kind, K::Feed { end: Pos::xz(25.4, -25.4), feed: Feed::PerMin(254.0) });
}

/// 004 §2.9 note 2: a unit *switch* only at the start and alone; a unit code that switches
/// nothing is accepted anywhere (the CAM header `G21 G40 G99` on a metric machine).
#[test]
fn unit_switch_rules() {
    // A switch that is not alone.
    let a = run_err("G20 X1\nM30");
    assert_eq!((a.number, a.pos.as_ref().unwrap().line), (10, 1), "{a}");
    assert!(a.message.contains("alone"), "{a}");
    // A switch in the middle of the program (it used to feed to X25.4 here).
    let a = run_err("G98 G01 X1 Z0 F100\nG20\nX1\nM30");
    assert_eq!((a.number, a.pos.as_ref().unwrap().line), (10, 2), "{a}");
    assert!(a.message.contains("middle of the program"), "{a}");
    // A metric header on a metric machine: switches nothing, accepted with other codes, and
    // again later in the program.
    let m = run("%\nO0001 (header)\nG21 G40 G99\nG98 G01 X10 Z-1 F100\nG21\nG21 X12\nM30\n%\n");
    assert_eq!(m[0].kind, K::Feed { end: Pos::xz(5.0, -1.0), feed: Feed::PerMin(100.0) });
    assert_eq!(m[1].kind, K::Feed { end: Pos::xz(6.0, -1.0), feed: Feed::PerMin(100.0) });
    // Back to mm right after a switch to inch, both at the start and alone: allowed.
    let m = run("G20\nG21\nG98 G01 X10 Z-1 F100\nM30");
    assert_eq!(m[0].kind, K::Feed { end: Pos::xz(5.0, -1.0), feed: Feed::PerMin(100.0) });
}

#[test]
fn power_on_modes_from_parameters() {
    // lathe.toml: No.5153 = 1 (G01), No.5154 = 1 (G99).
    let m = run("X10 Z-1 F0.1\nM30");
    assert_eq!(m[0].kind, K::Feed { end: Pos::xz(5.0, -1.0), feed: Feed::PerRev(0.1) });
    let mut c = cfg();
    c.parameters.insert("5153".into(), toml::Value::Integer(0));
    c.parameters.insert("5154".into(), toml::Value::Integer(0));
    let m: Vec<Move> = Interpreter::from_source("t", "X10 Z-1\nM30", &c).unwrap().map(|m| m.unwrap()).collect();
    assert_eq!(m[0].kind, K::Rapid { end: Pos::xz(5.0, -1.0) });
}

#[test]
fn no_decimal_point_rule_no_3401() {
    assert_eq!(run("G00 X10 Z-5\nM30")[0].kind, K::Rapid { end: Pos::xz(5.0, -5.0) });
    let mut c = cfg();
    c.parameters.insert("3401".into(), toml::Value::Integer(0));
    let m: Vec<Move> = Interpreter::from_source("t", "G00 X10 Z-5.\nM30", &c).unwrap().map(|m| m.unwrap()).collect();
    assert_eq!(m[0].kind, K::Rapid { end: Pos::xz(0.005, -5.0) });
}

#[test]
fn spindle_css_and_max_speed() {
    let m = run("G00 X100 Z0\nG50 S2000\nG96 S300 M03\nS200\nG97 S500\nM05\nM30");
    let sp: Vec<SpindleCmd> = m.iter().filter_map(|m| if let K::Spindle(s) = m.kind { Some(s) } else { None }).collect();
    assert_eq!(sp.len(), 4, "{sp:?}");
    assert_eq!(sp[0].css, Some(300.0));
    assert_eq!(sp[0].max_rpm, Some(2000.0));
    assert!((sp[0].rpm - 300_000.0 / (std::f64::consts::PI * 100.0)).abs() < 1e-6);
    assert_eq!(sp[1].css, Some(200.0));
    assert_eq!((sp[2].css, sp[2].rpm, sp[2].dir), (None, 500.0, SpindleDir::Cw));
    assert_eq!(sp[3].dir, SpindleDir::Stop);
    // S with the spindle stopped changes no motion.
    assert_eq!(run("S500\nM30").len(), 1);
}

#[test]
fn aux_stop_and_order_in_block() {
    let m = run("G00 X50 Z5 M08 T0101\nG01 Z-1 F.1 M05 M09\nM01\nM00\nM30");
    let k: Vec<String> = m.iter().map(plan::move_to_text).map(|s| s.split_once(' ').unwrap().1.to_string()).collect();
    assert_eq!(k[0], "aux M08");
    assert_eq!(k[1], "aux T0101");
    assert!(k[2].starts_with("rapid"));
    assert!(k[3].starts_with("feed"));
    assert!(k[4].starts_with("spindle M05"));
    assert_eq!(k[5], "aux M09");
    assert_eq!(m[6].kind, K::Stop { optional: true });
    assert_eq!(m[7].kind, K::Stop { optional: false });
}

#[test]
fn end_stops_the_stream() {
    let mut it = Interpreter::from_source("t", "G00 X1\nM30\nG00 X2\n", &cfg()).unwrap();
    assert!(it.next_move().unwrap().is_some());
    assert_eq!(it.next_move().unwrap().unwrap().kind, K::End { code: 30 });
    assert!(it.next_move().unwrap().is_none());
    assert!(it.next_move().unwrap().is_none());
    // End of text without M30.
    assert_eq!(run("G00 X1\n").len(), 1);
}

#[test]
fn syntax_error_position_and_block() {
    let src = "O0001\nG21\nG99\nG00 X50 Z5\nM03 S500\nG01 Z0 F0.1\nG01 @10\nX40\nG00 X100\nM30\n";
    let e = static_errs(src);
    assert_eq!(e.len(), 1);
    let s = e[0].to_string();
    assert!(s.starts_with("t.nc:7:5: alarm 0009: "), "{s}");
    assert!(s.ends_with("\n    G01 @10"), "{s}");
}

#[test]
fn all_static_errors_reported_before_running() {
    let src = "G00 X10\nG01 Z\nG01 X1 Z1 F.1\nG200 X1\nG04 P2.5\nG00 G01 X1\nM30\n";
    let e = static_errs(src);
    let got: Vec<(u32, u32)> = e.iter().map(|a| (a.pos.as_ref().unwrap().line, a.number)).collect();
    assert_eq!(got, [(2, 5), (4, 10), (5, 7), (6, 10)]);
}

/// The first pass skips the static check of a block shaped like the last checked one (same
/// letters, same G/M/T/L/D values): a block that differs only in a value the checks read is
/// still checked, every error found with its line.
#[test]
fn repeated_block_shapes_are_still_checked() {
    let src = "G01 X1 Z1 F100\nG01 X2 Z2 F100\nG01 X3 Z3 F200\nG00 G01 X1\nG00 G01 X2\n\
               T0101 X1\nT0101 X2\nT1.5 X3\nM03 S100\nM03 S200\nM03.5 S200\nG07 X1 Z1 F100\n\
               G01 X1 Y1\nG01 X1 U1\nG04 P2\nG04 P2.5\nG01 X1 Z1 F100\nG20\nM30\n";
    let e = static_errs(src);
    let got: Vec<(u32, u32)> = e.iter().map(|a| (a.pos.as_ref().unwrap().line, a.number)).collect();
    assert_eq!(got, [(4, 10), (5, 10), (8, 7), (11, 7), (12, 10), (13, 9), (14, 9), (16, 7)]);
}

#[test]
fn unsupported_codes_are_rejected() {
    // Every code of table 1.1 is implemented now; codes outside it are refused statically.
    for g in ["G05", "G12.2"] {
        let e = static_errs(&format!("{g}\nM30"));
        assert_eq!(e[0].number, 10, "{g}");
        assert!(e[0].message.contains("not a G code of this control"), "{}", e[0].message);
    }
}

#[test]
fn work_offsets_g50_g52_g54() {
    let m = run("G00 X100 Z50\nG50 X200 Z100\nG00 X150 Z80\nG52 Z-10\nG00 Z0\nG52 Z0\nM30");
    // G50: current machine (50, 50) reads X200 Z100 → offset x = 50 − 100 = −50, z = −50.
    assert_eq!(m[1].kind, K::Rapid { end: Pos::xz(25.0, 30.0) });
    assert_eq!(m[1].work_offset, Pos::xz(-50.0, -50.0));
    assert_eq!(m[2].kind, K::Rapid { end: Pos::xz(25.0, -60.0) });
    let mut it = Interpreter::from_source("t", "G55 G00 X10 Z0\nG54 X10\nM30", &cfg()).unwrap();
    let mut t = [Pos::ZERO; 6];
    t[1] = Pos::xz(1.0, -100.0);
    it.set_work_offsets(t);
    let m: Vec<Move> = it.map(|m| m.unwrap()).collect();
    assert_eq!(m[0].kind, K::Rapid { end: Pos::xz(6.0, -100.0) });
    assert_eq!(m[0].work_offset, Pos::xz(1.0, -100.0));
    assert_eq!(m[1].kind, K::Rapid { end: Pos::xz(5.0, -100.0) });
}

#[test]
fn start_position_and_incremental() {
    let mut it = Interpreter::from_source("t", "G00 U-10 W-5\nM30", &cfg()).unwrap();
    it.set_start_position(Pos::xz(100.0, 5.0));
    let m = it.next_move().unwrap().unwrap();
    assert_eq!(m.kind, K::Rapid { end: Pos::xz(95.0, 0.0) });
}

#[test]
fn g09_and_g61_exact_stop() {
    let m = run("G99 F.1\nG01 X10\nG09 G01 X12\nG61\nG01 X14\nG64\nG01 X16\nG61 X18\nX20\nM30");
    let e: Vec<bool> = m.iter().filter(|m| m.kind.name() == "feed").map(|m| m.exact_stop).collect();
    // §2.14 item 5: G61 in a moving block takes effect from the next block.
    assert_eq!(e, [false, true, true, false, false, true]);
}

#[test]
fn plan_json_fields() {
    let m = run("G99 G00 X40 Z5\nM03 S800\nG01 Z-20 F0.2\nG02 X60 Z-30 R10\nG04 P500\nM08\nM30");
    let j: Vec<serde_json::Value> = m.iter().map(|m| serde_json::from_str(&plan::move_to_json(m)).unwrap()).collect();
    assert_eq!(j[0]["kind"], "rapid");
    assert_eq!(j[0]["x"], 40.0);
    assert_eq!(j[0]["z"], 5.0);
    assert_eq!(j[0]["line"], 1);
    assert_eq!(j[0]["file"], "t.nc");
    assert!(j[0].get("c").is_none());
    assert_eq!(j[1]["kind"], "spindle");
    assert_eq!(j[1]["rpm"], 800.0);
    assert_eq!(j[2]["feed_per_rev"], 0.2);
    assert_eq!(j[3]["kind"], "arc");
    assert_eq!(j[3]["cw"], true);
    assert_eq!(j[3]["x"], 60.0);
    // CW from (X40 Z-20) to (X60 Z-30) in the ZX plane: centre at X60 Z-20.
    assert_eq!(j[3]["center"]["x"], 60.0);
    assert_eq!(j[3]["center"]["z"], -20.0);
    assert_eq!(j[4]["dwell_s"], 0.5);
    assert_eq!(j[5]["code"], "M08");
    assert_eq!(j[6]["kind"], "end");
    assert_eq!(j[6]["code"], "M30");
    // Workpiece coordinates with an offset.
    let m = run("G00 X100 Z50\nG50 X200 Z100\nG00 X150\nM30");
    let j: serde_json::Value = serde_json::from_str(&plan::move_to_json(&m[1])).unwrap();
    assert_eq!((j["x"].as_f64(), j["z"].as_f64()), (Some(150.0), Some(100.0)));
}

#[test]
fn example_first_part_runs() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/first_part.nc");
    let it = Interpreter::from_file(&path, &cfg()).unwrap_or_else(|e| panic!("{}", e[0]));
    let m: Vec<Move> = it.map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect();
    assert_eq!(m.last().unwrap().kind, K::End { code: 30 });
    let c = cfg();
    let (xa, za) = (&c.axes["x"], &c.axes["z"]);
    let mut t = 0.0;
    let mut p = Pos::ZERO;
    let mut rpm: f64 = 0.0;
    let mut css = None;
    for mv in &m {
        if let Some(e) = mv.kind.end() {
            // The brief: X is a diameter 0…290 (radius 0…145 within the axis limit).
            assert!(e.x >= 0.0 && e.x >= xa.min.unwrap() && e.x <= xa.max.unwrap(), "{}", plan::move_to_text(mv));
            assert!(e.z >= za.min.unwrap() && e.z <= za.max.unwrap(), "{}", plan::move_to_text(mv));
        }
        match &mv.kind {
            K::Spindle(s) => {
                rpm = s.rpm;
                css = s.css.map(|v| (v, s.max_rpm.unwrap_or(f64::INFINITY)));
            }
            K::Feed { end, feed } | K::Arc { end, feed, .. } => {
                // An arc is at most π/2 times its chord (half circle).
                let k = if matches!(mv.kind, K::Arc { .. }) { 1.6 } else { 1.0 };
                let len = (end.x - p.x).hypot(end.z - p.z) * k;
                let r = match css {
                    Some((v, mx)) => (v * 1000.0 / (std::f64::consts::PI * 2.0 * end.x.max(p.x).max(1.0))).min(mx),
                    None => rpm,
                };
                let fm = match feed {
                    Feed::PerMin(f) => *f,
                    Feed::PerRev(f) => f * r,
                };
                assert!(fm > 0.0);
                t += len / fm * 60.0;
            }
            K::Dwell { seconds } => t += seconds,
            K::Rapid { end } => t += (end.x - p.x).abs().max((end.z - p.z).abs()) / 8000.0 * 60.0,
            _ => {}
        }
        if let Some(e) = mv.kind.end() {
            p = e;
        }
    }
    assert!(t < 60.0, "machining time estimate {t:.1} s");
    // The documented end point.
    assert_eq!(p, Pos::xz(50.0, 5.0));
}

fn xs(m: &[Move]) -> Vec<f64> {
    m.iter().filter_map(|m| m.kind.end()).map(|p| (p.x * 2.0 * 1e6).round() / 1e6).collect()
}

#[test]
fn macro_variables_and_while_loop() {
    // Three passes at dia 40, 36, 32 via WHILE; null word ignored; computed address values.
    let src = "#1=40\n#2=3\nG99 F0.2\nWHILE [#2 GT 0] DO 1\nG00 X#1 Z2 Y#30\nG01 Z-[10*#2]\n#1=#1-4\n#2=#2-1\nEND 1\nM30\n";
    let m = run(src);
    assert_eq!(xs(&m), [40.0, 40.0, 36.0, 36.0, 32.0, 32.0]);
    let z: Vec<f64> = m.iter().filter_map(|m| m.kind.end()).map(|p| p.z).collect();
    assert_eq!(z, [2.0, -30.0, 2.0, -20.0, 2.0, -10.0]);
}

#[test]
fn if_goto_and_if_then() {
    let src = "#1=0\nN10 #1=#1+1\nIF [#1 LT 3] GOTO 10\nIF [#1 EQ 3] THEN #2=50\nG00 X#2\nGOTO 99\nG00 X1\nN99 M30\n";
    let m = run(src);
    assert_eq!(xs(&m), [50.0]);
    assert_eq!(m.last().unwrap().kind, K::End { code: 30 });
}

#[test]
fn macro_runtime_error_stops_at_its_block() {
    let mut it = Interpreter::from_source("t.nc", "G00 X10\n#1=0\n#2=5/#1\nG00 X20\nM30\n", &cfg()).unwrap();
    assert!(it.next_move().unwrap().is_some());
    let a = it.next_move().unwrap_err();
    assert_eq!(a.number, 112);
    assert_eq!(a.pos.as_ref().unwrap().line, 3);
    assert_eq!(a.block.as_deref(), Some("#2=5/#1"));
}

#[test]
fn static_loop_and_label_errors() {
    let e = static_errs("WHILE [1 EQ 1] DO 1\nG00 X1\nM30\n");
    assert_eq!(e[0].number, 124);
    let e = static_errs("DO 1\nDO 2\nEND 1\nEND 2\nM30\n");
    assert_eq!(e[0].number, 126);
    let e = static_errs("GOTO 50\nM30\n");
    assert_eq!(e[0].number, 78);
    let e = static_errs("G00 X1 #1=2\nM30\n");
    assert_eq!(e[0].number, 127);
}

#[test]
fn subprograms_m98_m99() {
    let src = "O0001\nG00 X100 Z5\nM98 P0010\nM98 P30010\nM98 P10 L2\nM30\nO0010\nG00 U-2\nM99\n";
    let m = run(src);
    assert_eq!(xs(&m), [100.0, 98.0, 96.0, 94.0, 92.0, 90.0, 88.0]);
    // M99 P returns to a label in the caller.
    let m = run("O1\nM98 P2\nG00 X1\nN50 G00 X2\nM30\nO2\nM99 P50\n");
    assert_eq!(xs(&m), [2.0]);
    // 12 levels of nesting are allowed, 13 are not.
    let chain = |levels: u32| {
        let mut s = String::from("O1\nM98 P2\nM30\n");
        for p in 2..=levels + 1 {
            s.push_str(&format!("O{p}\n{}M99\n", if p <= levels { format!("M98 P{}\n", p + 1) } else { "G00 X1\n".into() }));
        }
        s
    };
    assert_eq!(xs(&run(&chain(12))), [1.0]);
    assert_eq!(run_err(&chain(13)).number, 77);
    // Missing program, self call, nesting.
    assert_eq!(static_errs("O1\nM98 P7\nM30\n")[0].number, 76);
    assert_eq!(run_err("O1\n#1=7\nM98 P#1\nM30\n").number, 76);
    assert_eq!(run_err("O1\nM98 P2\nM30\nO2\nM98 P2\nM99\n").number, 76);
    assert_eq!(run_err("O1\nM98 P2\nM30\nO2\nM98 P3\nM99\nO3\nM98 P2\nM99\n").number, 77);
}

#[test]
fn g65_macro_call_with_arguments_and_locals() {
    let src = "O1\n#1=7\nG65 P9000 X40 Z-10 F0.1\nG00 X#1\nM30\nO9000\n#1=99\nG99 G01 X#24 Z#26 F#9\nM99\n";
    let m = run(src);
    assert_eq!(m[0].kind, K::Feed { end: Pos::xz(20.0, -10.0), feed: Feed::PerRev(0.1) });
    // The caller's #1 is untouched by the macro's local #1.
    assert_eq!(m[1].kind, K::Rapid { end: Pos::xz(3.5, -10.0) });
}

#[test]
fn block_skip() {
    let src = "G00 X10\n/G00 X20\nM30\n";
    assert_eq!(xs(&run(src)), [10.0, 20.0]);
    let mut it = Interpreter::from_source("t", src, &cfg()).unwrap();
    it.set_block_skip(true);
    let m: Vec<Move> = it.map(|m| m.unwrap()).collect();
    assert_eq!(xs(&m), [10.0]);
}

#[test]
fn endless_loop_without_motion_is_an_alarm() {
    let mut it = Interpreter::from_source("t", "N1 #1=#1+1\nGOTO 1\n", &cfg()).unwrap();
    assert_eq!(it.next_move().unwrap_err().number, ENDLESS_LOOP_ALARM);
}

#[test]
fn g28_returns_through_intermediate_point() {
    let m = run("G00 X100 Z-50\nG28 U0 W10\nM30");
    assert_eq!(m[1].kind, K::Rapid { end: Pos::xz(50.0, -40.0) });
    assert_eq!(m[2].kind, K::Rapid { end: Pos::xz(0.0, 0.0) });
    let m = run("G00 X100 Z-50\nG28 X80\nM30");
    assert_eq!(m[2].kind, K::Rapid { end: Pos::xz(0.0, -50.0) });
}

#[test]
fn ellipse_and_parabola_emit_feed_chains() {
    let m = run("G99 G00 X43.14 Z0\nG02.1 U20.68 W-50.0 A48 B25 Q60000 F0.1\nM30");
    let feeds: Vec<&Move> = m.iter().filter(|m| m.kind.name() == "feed").collect();
    assert!(feeds.len() > 20);
    assert_eq!(feeds.last().unwrap().kind.end().map(|p| ((p.x * 2.0 * 1e6).round() / 1e6, p.z)), Some((63.82, -50.0)));
    assert!(feeds.iter().all(|m| m.src.line == 2));
    // Manual §2.5 example.
    let m = run("G98 G00 X0 Z0\nG01 X30 F200\nG3.2 X60 Z-40 P10\nG01 X90 Z-60\nM30");
    let n = m.iter().filter(|m| m.src.line == 3).count();
    assert!(n > 10);
    assert_eq!(m.iter().rev().nth(1).unwrap().kind, K::Feed { end: Pos::xz(45.0, -60.0), feed: Feed::PerMin(200.0) });
    assert_eq!(run_err("G98 G00 X0 Z0\nG02.1 X10 Z-5 B2 F100\nM30").number, 9);
}

#[test]
fn chamfer_and_corner_r_are_inserted() {
    // Along Z at dia 40 to Z-10, chamfer 2 to the face going up to dia 60.
    let m = run("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nX60\nM30");
    let e: Vec<Pos> = m.iter().filter_map(|m| m.kind.end()).collect();
    assert_eq!(e, [Pos::xz(20.0, 0.0), Pos::xz(20.0, -8.0), Pos::xz(22.0, -10.0), Pos::xz(30.0, -10.0)]);
    assert_eq!(m[2].src.line, 2, "the inserted chamfer belongs to the ,C block");
    // Corner R: an arc tangent to both moves, clockwise for this right turn.
    let m = run("G99 G00 X40 Z0\nG01 Z-10 ,R2 F0.1\nX60\nM30");
    let K::Arc { end, center, cw, .. } = m[2].kind else { panic!("{:?}", m[2]) };
    assert!(close(end, Pos::xz(22.0, -10.0)) && close(center, Pos::xz(22.0, -8.0)) && cw);
    // One G04 may stand between; its dwell follows the inserted block.
    let m = run("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nG04 P100\nX60\nM30");
    let k: Vec<&str> = m.iter().map(|m| m.kind.name()).collect();
    assert_eq!(k, ["rapid", "feed", "feed", "dwell", "feed", "end"]);
}

#[test]
fn chamfer_alarms() {
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nM08\nX60\nM30").number, 51);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nG00 X60\nM30").number, 52);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nG18\nX60\nM30").number, 51);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nG04 P1\nG04 P1\nX60\nM30").number, 51);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nX42\nM30").number, 55);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\nM30").number, 51);
    assert_eq!(run_err("G99 G00 X40 Z0\nG01 Z-10 ,C2 F0.1\n").number, 51);
}

#[test]
fn subprograms_from_the_program_directory() {
    let dir = std::env::temp_dir().join(format!("cncgw-interp-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("O0100.nc"), "O0100\nG00 U-2\nM98 P200\nM99\n").unwrap();
    std::fs::write(dir.join("0200.nc"), "G00 W-1\nM99\n").unwrap();
    std::fs::write(dir.join("O0300.nc"), "O0300\nG01 X\nM99\n").unwrap();
    let main = dir.join("main.nc");
    std::fs::write(&main, "G00 X100 Z0\nM98 P100 L2\nM30\n").unwrap();
    let m: Vec<Move> = Interpreter::from_file(&main, &cfg()).unwrap().map(|m| m.unwrap()).collect();
    let e: Vec<Pos> = m.iter().filter_map(|m| m.kind.end()).collect();
    assert_eq!(e, [Pos::xz(50.0, 0.0), Pos::xz(49.0, 0.0), Pos::xz(49.0, -1.0), Pos::xz(48.0, -1.0), Pos::xz(48.0, -2.0)]);
    assert!(m[2].src.file.ends_with("0200.nc"), "{}", m[2].src.file);
    // A syntax error in a called file is found before running; a missing program too.
    std::fs::write(&main, "M98 P300\nM98 P400\nM30\n").unwrap();
    let errs = Interpreter::from_file(&main, &cfg()).err().expect("static errors");
    let mut got: Vec<(String, u32)> = errs.iter().map(|a| (a.pos.as_ref().unwrap().file.to_string(), a.number)).collect();
    got.sort();
    assert!(got.iter().any(|(f, n)| f.ends_with("O0300.nc") && *n == 5), "{got:?}");
    assert!(got.iter().any(|(f, n)| f.ends_with("main.nc") && *n == 76), "{got:?}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn work_offset_table_from_toml() {
    let t = parse_work_offsets("wo.toml", "[G54]\nx = 2.0\nz = -300\n[G56]\nz = -100.5\n").unwrap();
    assert_eq!(t[0], Pos::xz(1.0, -300.0));
    assert_eq!(t[2], Pos::xz(0.0, -100.5));
    assert_eq!(t[1], Pos::ZERO);
    let e = parse_work_offsets("wo.toml", "[G60]\nx = 1\n").unwrap_err();
    assert_eq!(e.number, crate::alarm::CONFIG);
    assert!(e.message.contains("G60"), "{}", e.message);
    assert!(parse_work_offsets("wo.toml", "[G54]\nq = 1\n").is_err());
    let mut it = Interpreter::from_source("t", "G54 G00 X20 Z0\nM30", &cfg()).unwrap();
    it.set_work_offsets(t);
    let m = it.next_move().unwrap().unwrap();
    assert_eq!(m.kind, K::Rapid { end: Pos::xz(11.0, -300.0) });
    let j: serde_json::Value = serde_json::from_str(&plan::move_to_json(&m)).unwrap();
    assert_eq!((j["x"].as_f64(), j["z"].as_f64()), (Some(20.0), Some(0.0)));
}

#[test]
fn macro_grooves_example() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/macro_grooves.nc");
    let it = Interpreter::from_file(&path, &cfg()).unwrap_or_else(|e| panic!("{}", e[0]));
    let m: Vec<Move> = it.map(|m| m.unwrap_or_else(|a| panic!("{a}"))).collect();
    let bottoms: Vec<(f64, f64)> =
        m.iter().filter_map(|m| if let K::Feed { end, .. } = m.kind { Some((end.x * 2.0, end.z)) } else { None }).collect();
    assert_eq!(bottoms, [(32.0, -10.0), (32.0, -20.0), (32.0, -30.0)]);
    assert_eq!(m.iter().filter(|m| m.kind.name() == "dwell").count(), 3);
    assert_eq!(m.iter().rev().find_map(|m| m.kind.end()), Some(Pos::xz(50.0, 5.0)));
    assert_eq!(m.last().unwrap().kind, K::End { code: 30 });
}

#[test]
fn full_circle_with_i_k_and_corner_r_into_an_arc() {
    // Same start and end with I/K: a full circle (end == start, centre given).
    let m = run("G99 G00 X20 Z0\nG02 X20 Z0 I-5 F0.1\nM30");
    let K::Arc { end, center, .. } = m[1].kind else { panic!() };
    assert_eq!(end, Pos::xz(10.0, 0.0));
    assert!(close(center, Pos::xz(5.0, 0.0)));
    // Same start and end with R: a 0° arc, nothing moves (§2.3 note 5).
    assert_eq!(run("G99 G00 X20 Z0\nG02 X20 Z0 R5 F0.1\nM30").len(), 2);
    // Corner R between a line along −Z and a CCW arc: the rounding arc is tangent to both.
    let m = run("G99 G00 X20 Z0\nG01 Z-10 ,R1 F0.1\nG03 X40 Z-20 R10\nM30");
    let K::Arc { end: t2, center: o, cw, .. } = m[2].kind else { panic!("{:?}", m[2]) };
    let K::Arc { center: c2, .. } = m[3].kind else { panic!() };
    let p1 = m[1].kind.end().unwrap();
    // Heading −Z then leaving the CCW arc towards +X is a right turn: the rounding is CW.
    assert!(cw);
    assert!(((p1.x - o.x).hypot(p1.z - o.z) - 1.0).abs() < 1e-9);
    assert!(((t2.x - o.x).hypot(t2.z - o.z) - 1.0).abs() < 1e-9);
    // Outside the arc of radius 10 and tangent to it: the rounding centre is 10 + 1 from its centre.
    assert!(((o.x - c2.x).hypot(o.z - c2.z) - 11.0).abs() < 1e-9);
    assert!((p1.x - 10.0).abs() < 1e-9 && p1.z > -10.0);
}

#[test]
fn common_variables_survive_between_runs() {
    let mut it = Interpreter::from_source("t", "#500=#500+1\n#1=5\nM30\n", &cfg()).unwrap();
    it.set_common_vars([(500, 41.0), (1, 3.0)].into_iter().collect());
    while it.next_move().unwrap().is_some() {}
    assert_eq!(it.common_vars().get(&500), Some(&42.0));
    assert_eq!(it.common_vars().get(&1), None, "locals are not common variables");
}

#[test]
fn static_errors_are_in_line_order() {
    let e = static_errs("GOTO 7\nG01 X\nM98 P9\nG01 Q\nM30\n");
    let lines: Vec<u32> = e.iter().map(|a| a.pos.as_ref().unwrap().line).collect();
    assert_eq!(lines, [1, 2, 3, 4]);
}

#[test]
fn m98_runs_after_the_blocks_motion() {
    let m = run("O1\nG00 X10 M98 P2\nM30\nO2\nG00 X20\nM99\n");
    assert_eq!(xs(&m), [10.0, 20.0]);
    assert_eq!(static_errs("G04 P100 M98 P2\nM30\nO2\nM99\n")[0].number, 9);
    assert_eq!(static_errs("O1\nM98 P2\nM30\nO2\nG00 X1 M99\n")[0].number, 9);
}

/// A file is read through a 64 KiB window with seeks for jumps: the same program from a file
/// and from memory gives the same moves and the same alarm, with lines longer than the
/// window, CRLF line ends, a last line without a line end, GOTO backwards, WHILE loops,
/// M99 P and M98 into another file, and jump targets far behind the window.
#[test]
fn a_file_streams_like_the_same_text_in_memory() {
    let dir = std::env::temp_dir().join(format!("cncgw-stream-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("O0007.nc"), "O0007\r\nG01 W-0.5\r\nM99 P40\r\n").unwrap();
    let long_comment = format!("({})", "x".repeat(150_000));
    let mut text = String::from("G98 G00 X100 Z0\r\nF500\r\n#1=0\r\n");
    text.push_str("N10 G01 U-1\r\n");
    text.push_str(&long_comment);
    text.push_str("\r\n#1=#1+1\r\nIF [#1 LT 3] GOTO 10\r\n");
    // Enough plain blocks that the loop below jumps back over several windows.
    for i in 0..8_000 {
        text.push_str(&format!("G01 X{}.5 Z-{}\r\n", 60 + i % 9, i % 50));
    }
    text.push_str("#2=0\r\nWHILE [#2 LT 2] DO1\r\nG01 W-1\r\nM98 P7\r\nN40 #2=#2+1\r\nEND1\r\n");
    text.push_str(&long_comment);
    text.push_str("\nG00 X200 Z100\nM30");
    let main = dir.join("main.nc");
    std::fs::write(&main, &text).unwrap();
    let from_file: Vec<Move> = Interpreter::from_file(&main, &cfg()).unwrap().map(|m| m.unwrap()).collect();
    let in_mem: Vec<Move> = Interpreter::with_program_dir("main.nc", &text, &cfg(), Some(&dir)).unwrap().map(|m| m.unwrap()).collect();
    let key = |m: &Move| (m.src.line, m.src.col, m.src.file.ends_with("O0007.nc"), format!("{:?}", m.kind));
    assert_eq!(from_file.iter().map(key).collect::<Vec<_>>(), in_mem.iter().map(key).collect::<Vec<_>>());
    assert_eq!(from_file.len(), 1 + 3 + 8_000 + 2 * 2 + 1 + 1, "G00, 3 U-1 moves, 8000 blocks, 2×(W-1, sub W-0.5), G00, M30");
    let last_feed = from_file.iter().rev().find(|m| matches!(m.kind, K::Rapid { .. })).unwrap();
    assert_eq!(last_feed.src.line as usize, text.lines().count() - 1);
    // A run-time alarm late in the file carries the same line and block text.
    let bad = text.replace("G00 X200 Z100", "#3=1/0");
    std::fs::write(&main, &bad).unwrap();
    let a1 = Interpreter::from_file(&main, &cfg()).unwrap().find_map(|m| m.err()).unwrap();
    let a2 = Interpreter::with_program_dir("main.nc", &bad, &cfg(), Some(&dir)).unwrap().find_map(|m| m.err()).unwrap();
    assert_eq!(
        (a1.number, a1.pos.as_ref().map(|p| (p.line, p.col)), a1.block.clone()),
        (a2.number, a2.pos.as_ref().map(|p| (p.line, p.col)), a2.block.clone())
    );
    assert_eq!(a1.block.as_deref(), Some("#3=1/0"));
    std::fs::remove_dir_all(&dir).ok();
}
