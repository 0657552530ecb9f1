//! `cncgw plan` JSON lines (docs/PLAN_FORMAT.md): valid JSON, sorted keys, exact values.

use cncgw::canon::{CycleTag, Feed, Move, MoveKind, Pos, SrcPos};
use cncgw::config::MachineConfig;
use cncgw::interp::{plan, Interpreter};
use serde_json::{json, Value};

fn keys_sorted(line: &str) -> Vec<String> {
    // serde_json's Map is ordered by key, so compare the raw key order with the sorted one.
    let v: Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{line}: {e}"));
    let keys: Vec<String> = v.as_object().expect("object").keys().cloned().collect();
    // Drop the nested `center` object's keys.
    let flat = match line.find("\"center\":{") {
        Some(i) => {
            let j = line[i..].find('}').map(|j| i + j + 1).unwrap_or(line.len());
            format!("{}\"center\":0{}", &line[..i], &line[j..])
        }
        None => line.to_string(),
    };
    let raw: Vec<String> = flat.split("\":").filter_map(|p| p.rsplit('"').next().map(str::to_string)).filter(|k| keys.contains(k)).collect();
    raw
}

#[test]
fn every_move_of_the_examples_is_valid_json_with_sorted_keys() {
    let cfg = MachineConfig::embedded();
    for file in ["examples/first_part.nc", "examples/macro_grooves.nc"] {
        let it = Interpreter::from_file(std::path::Path::new(file), &cfg).expect("valid example");
        let mut n = 0;
        for m in it {
            let line = plan::move_to_json(&m.expect("runs"));
            let v: Value = serde_json::from_str(&line).unwrap_or_else(|e| panic!("{line}: {e}"));
            assert_eq!(v["file"], file);
            assert!(v["line"].as_u64().is_some_and(|l| l > 0), "{line}");
            let mut sorted = keys_sorted(&line);
            let raw = sorted.clone();
            sorted.sort();
            assert_eq!(raw, sorted, "{line}");
            n += 1;
        }
        assert!(n > 10, "{file}: {n} moves");
    }
}

#[test]
fn exact_values_and_escaping() {
    let src = SrcPos::new("dir\\a \"b\".nc".into(), 7, 1);
    let off = Pos { x: 10.0, z: -100.0, y: 0.0, c: 0.0 };
    let mk = |kind| Move { src: src.clone(), kind, exact_stop: false, work_offset: off, tag: None };
    let arc = mk(MoveKind::Arc {
        end: Pos { x: 30.0, z: -120.0, y: 0.0, c: 45.5 },
        center: Pos::xz(20.0, -110.0),
        cw: false,
        plane: cncgw::canon::Plane::Zx,
        feed: Feed::PerMin(250.0),
    });
    let v: Value = serde_json::from_str(&plan::move_to_json(&arc)).expect("json");
    assert_eq!(
        v,
        json!({"file": "dir\\a \"b\".nc", "line": 7, "kind": "arc", "x": 40.0, "z": -20.0, "c": 45.5,
               "feed": 250.0, "cw": false, "center": {"x": 20.0, "z": -10.0}})
    );
    let mut t = mk(MoveKind::Thread { end: Pos::xz(10.0, -130.0), lead: 1.5, start_angle: 0.0, continuous: false, lead_inc: 0.0 });
    t.tag = Some(CycleTag { cycle: "G76".into(), step: 3 });
    let v: Value = serde_json::from_str(&plan::move_to_json(&t)).expect("json");
    assert_eq!(v["lead"], 1.5);
    assert_eq!((v["cycle"].as_str(), v["step"].as_u64()), (Some("G76"), Some(3)));
    assert_eq!((v["x"].as_f64(), v["z"].as_f64()), (Some(0.0), Some(-30.0)));
    let e = plan::move_to_json(&mk(MoveKind::End { code: 30 }));
    assert_eq!(e, r#"{"code":"M30","file":"dir\\a \"b\".nc","kind":"end","line":7}"#);
    let aux = plan::move_to_json(&mk(MoveKind::Aux { letter: 'T', value: 101.0 }));
    assert!(aux.starts_with(r#"{"code":"T0101","#), "{aux}");
    // Float noise is rounded away, non-finite numbers are null (valid JSON).
    let d = plan::move_to_json(&mk(MoveKind::Dwell { seconds: 0.30000000000000004 }));
    assert!(d.contains(r#""dwell_s":0.3"#), "{d}");
    let bad = plan::move_to_json(&mk(MoveKind::Dwell { seconds: f64::NAN }));
    assert!(serde_json::from_str::<Value>(&bad).expect("json")["dwell_s"].is_null(), "{bad}");
}

#[test]
fn numbers_print_like_the_shortest_round_trip_form() {
    let src = SrcPos::new("t.nc".into(), 1, 1);
    for v in [0.0, 20.05, -0.025, 54.0, 0.0001, -123456.7891, 1e9 + 0.5, 0.1 + 0.2, 1e14, 3.0e16, -7.25] {
        let m = Move { src: src.clone(), kind: MoveKind::Dwell { seconds: v }, exact_stop: false, work_offset: Pos::ZERO, tag: None };
        let j = plan::move_to_json(&m);
        let rounded = (v * 1e4).round() / 1e4;
        let want = format!("{:?}", if rounded == 0.0 { 0.0 } else { rounded });
        assert!(j.contains(&format!("\"dwell_s\":{want},")), "{v}: {j} (want {want})");
    }
}

/// docs/PLAN_FORMAT.md's thread fields (issue 20.6): a G32 chain's later blocks are
/// `continuous` and repeat the chain's first Q; G34's lead increment is `lead_inc`; every key
/// stays in alphabetical order.
#[test]
fn thread_chain_fields() {
    let cfg = MachineConfig::embedded();
    let src = "G0 X30 Z5\nM3 S500\nG32 Z-10 F1.5 Q90\nX34 Z-12\nG34 Z-30 F2 K0.1\nM30\n";
    let lines: Vec<Value> = Interpreter::from_source("t.nc", src, &cfg)
        .unwrap()
        .map(|m| {
            let line = plan::move_to_json(&m.unwrap());
            let mut sorted = keys_sorted(&line);
            let raw = sorted.clone();
            sorted.sort();
            assert_eq!(raw, sorted, "{line}");
            serde_json::from_str(&line).unwrap()
        })
        .filter(|v: &Value| v["kind"] == "thread")
        .collect();
    assert_eq!(lines.len(), 3);
    assert!(lines[0].get("continuous").is_none() && lines[0].get("lead_inc").is_none(), "{}", lines[0]);
    for v in &lines[1..] {
        assert_eq!((v["continuous"].as_bool(), v["start_angle"].as_f64()), (Some(true), Some(90.0)), "{v}");
    }
    assert_eq!((lines[2]["lead"].as_f64(), lines[2]["lead_inc"].as_f64()), (Some(2.0), Some(0.1)));
}
