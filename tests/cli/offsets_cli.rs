//! Offsets kept in the state directory (issue 24.1): `cncgw offsets set|list|import|export`,
//! refusal of bad values, atomic stores, and `run`, `plan` and `preview` following the same
//! path for the same stored table.

use std::path::Path;
use std::process::{Command, Output};

fn cncgw(state: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", state).args(args).output().unwrap()
}

fn ok(o: &Output) -> String {
    assert!(o.status.success(), "exit {:?}\n{}\n{}", o.status.code(), String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn json(state: &Path) -> serde_json::Value {
    serde_json::from_str(&ok(&cncgw(state, &["offsets", "list", "--json"]))).unwrap()
}

fn files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    v.sort();
    v
}

#[test]
fn set_list_json_import_export_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    // Nothing stored: the list says so and every system reads zero.
    let empty = ok(&cncgw(&state, &["offsets", "list"]));
    assert!(empty.contains("none stored"), "{empty}");
    ok(&cncgw(&state, &["offsets", "set", "T01", "--x", "-152.3", "--z", "-310.45", "--wear-x", "0.02", "--r", "0.8", "--tip", "3"]));
    // +INPUT on the wear, the geometry kept.
    ok(&cncgw(&state, &["offsets", "set", "t1", "--wear-x", "0.01", "--add"]));
    ok(&cncgw(&state, &["offsets", "set", "T12", "--wear-z", "-0.05"]));
    ok(&cncgw(&state, &["offsets", "set", "G54", "--z", "-312.5", "--x", "1.5"]));
    ok(&cncgw(&state, &["offsets", "set", "ext", "--z", "-0.25"]));
    let v = json(&state);
    let t1 = &v["tools"]["1"];
    assert_eq!((t1["x"].as_f64(), t1["z"].as_f64(), t1["r"].as_f64(), t1["tip"].as_u64()), (Some(-152.3), Some(-310.45), Some(0.8), Some(3)));
    assert!((t1["wear_x"].as_f64().unwrap() - 0.03).abs() < 1e-12, "{v}");
    assert_eq!(v["tools"]["12"]["wear_z"].as_f64(), Some(-0.05));
    assert_eq!(v["tools"].as_object().unwrap().len(), 2);
    assert_eq!((v["work"]["G54"]["x"].as_f64(), v["work"]["G54"]["z"].as_f64()), (Some(1.5), Some(-312.5)), "X as entered (diameter)");
    assert_eq!(v["work"]["EXT"]["z"].as_f64(), Some(-0.25));
    assert_eq!(v["work"]["G55"]["z"].as_f64(), Some(0.0));
    let text = ok(&cncgw(&state, &["offsets", "list"]));
    assert!(text.contains("T01") && text.contains("-152.3000") && text.contains("T12") && text.contains("-312.5000"), "{text}");

    // Export, then import into another state directory: the same tables.
    let tools = dir.path().join("tools.toml");
    let work = dir.path().join("work.toml");
    ok(&cncgw(&state, &["offsets", "export", tools.to_str().unwrap()]));
    ok(&cncgw(&state, &["offsets", "export", "--work", work.to_str().unwrap()]));
    let other = dir.path().join("other");
    ok(&cncgw(&other, &["offsets", "import", tools.to_str().unwrap()]));
    ok(&cncgw(&other, &["offsets", "import", "--work", work.to_str().unwrap()]));
    let w = json(&other);
    assert_eq!(w["tools"], v["tools"]);
    assert_eq!(w["work"], v["work"]);
    // The export is a tool table `--tools` reads (docs/TOOL_TABLE.md); the shipped example imports.
    let prog = dir.path().join("t.nc");
    std::fs::write(&prog, "T0101\nG0 X10 Z1\nT1212\nG0 X20\nM30\n").unwrap();
    ok(&cncgw(&dir.path().join("none"), &["plan", "--no-machine", "--tools", tools.to_str().unwrap(), prog.to_str().unwrap()]));
    let example = dir.path().join("ex");
    let out = ok(&cncgw(&example, &["offsets", "import", "config/tools.toml"]));
    assert!(out.contains("3 tool offset(s)"), "{out}");
    assert_eq!(json(&example)["tools"]["2"]["r"].as_f64(), Some(0.4));
}

#[test]
fn bad_values_are_refused_and_nothing_is_stored() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    ok(&cncgw(&state, &["offsets", "set", "T01", "--x", "-100", "--r", "0.4"]));
    ok(&cncgw(&state, &["offsets", "set", "G54", "--z", "-300"]));
    let tools_file = state.join(files(&state).into_iter().find(|n| n.ends_with(".tools.toml")).unwrap());
    let before: Vec<Vec<u8>> = files(&state).iter().filter(|n| n.ends_with(".toml")).map(|n| std::fs::read(state.join(n)).unwrap()).collect();
    assert_eq!(before.len(), 2, "{:?}", files(&state));
    let cases: &[(&[&str], &str)] = &[
        (&["T01", "--r", "-0.4"], "nose radius must be >= 0"),
        (&["T01", "--tip", "12"], "tip is a whole number 0–9"),
        (&["T01", "--x", "nan"], "must be finite"),
        (&["T01", "--wear-z", "inf"], "must be finite"),
        (&["T100", "--x", "1"], "T01…T99"),
        (&["T0", "--x", "1"], "T01…T99"),
        (&["G54", "--wear-x", "0.1"], "for tool offsets"),
        (&["T01", "--c", "1"], "for work offsets"),
        (&["G60", "--z", "1"], "G54…G59 or EXT"),
        (&["G54", "--x", "-inf"], "must be finite"),
    ];
    for (args, want) in cases {
        let mut a = vec!["offsets", "set"];
        a.extend_from_slice(args);
        let o = cncgw(&state, &a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(want) && err.contains("nothing was stored"), "{args:?}: {err}");
    }
    // An import with one bad section stores nothing (and names the key).
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[1]\nx = -90.0\n[2]\nx = -80.0\nradius = 0.4\n").unwrap();
    let o = cncgw(&state, &["offsets", "import", bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("2.radius"), "{}", String::from_utf8_lossy(&o.stderr));
    let after: Vec<Vec<u8>> = files(&state).iter().filter(|n| n.ends_with(".toml")).map(|n| std::fs::read(state.join(n)).unwrap()).collect();
    assert_eq!(before, after, "the stored files are untouched");
    // A damaged stored file is an alarm that says how to fix it, and nothing moves.
    std::fs::write(&tools_file, "[1]\nx = -100.0\nr = ").unwrap();
    let o = cncgw(&state, &["offsets", "list"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("alarm 1100") && err.contains("offsets import"), "{err}");
    let prog = dir.path().join("p.nc");
    std::fs::write(&prog, "G0 X20 Z2\nM30\n").unwrap();
    let o = cncgw(&state, &["run", "--batch", prog.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.code() == Some(4) && err.contains("nothing was moved"), "{err}");
}

#[test]
fn stores_are_atomic_and_concurrent_edits_are_not_lost() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    // Eight editors at once: each store is a whole file (the others read it to modify it) and
    // the lock serialises read-modify-write, so every one of them is kept.
    let kids: Vec<_> = (1..=8)
        .map(|n| {
            Command::new(env!("CARGO_BIN_EXE_cncgw"))
                .env("CNCGW_STATE_DIR", &state)
                .args(["offsets", "set", &format!("T{n:02}"), "--x", &format!("-{n}.5")])
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for k in kids {
        ok(&k.wait_with_output().unwrap());
    }
    let v = json(&state);
    assert_eq!(v["tools"].as_object().unwrap().len(), 8, "{v}");
    for (k, t) in v["tools"].as_object().unwrap() {
        assert_eq!(t["x"].as_f64(), Some(-(k.parse::<f64>().unwrap() + 0.5)));
    }
    let names = files(&state);
    assert!(names.iter().all(|n| !n.ends_with(".tmp")), "no temporary file is left: {names:?}");
}

/// Offsets that show in the path: T01 geometry and wear, G54 and EXT.
fn store_offsets(state: &Path) {
    ok(&cncgw(state, &["offsets", "set", "T01", "--x", "-4", "--z", "-3", "--wear-x", "0.2", "--wear-z", "-0.1", "--r", "0.8", "--tip", "3"]));
    ok(&cncgw(state, &["offsets", "set", "G54", "--z", "-10"]));
    ok(&cncgw(state, &["offsets", "set", "EXT", "--x", "2", "--z", "-1"]));
}

#[test]
fn run_plan_and_preview_take_the_stored_tables() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    store_offsets(&state);
    let prog = dir.path().join("part.nc");
    std::fs::write(&prog, "G21 G98\nT0101\nG0 X20 Z5\nG1 Z-5 F300\nM30\n").unwrap();
    let p = prog.to_str().unwrap();
    let o = cncgw(&state, &["run", "--batch", "--json", p]);
    let s: serde_json::Value = serde_json::from_str(&ok(&o)).unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("tool offsets stored in"), "{}", String::from_utf8_lossy(&o.stderr));
    let axis = |n: &str| s["axes"].as_array().unwrap().iter().find(|a| a["axis"] == n).unwrap()["final_actual"].as_f64().unwrap();
    // Machine X (diameter) = 20 + geometry −4 + wear 0.2 + EXT 2; Z = −5 − 3 − 0.1 − 10 − 1.
    assert!((axis("x") - 18.2).abs() < 2e-3, "{s}");
    assert!((axis("z") - -19.1).abs() < 1e-3, "{s}");

    // preview with the stored table draws exactly what preview --tools with the same table
    // draws; with no table at all the nose radius path differs.
    let cprog = dir.path().join("comp.nc");
    std::fs::write(&cprog, "G21 G98\nT0101\nG0 X30 Z5\nG42 G1 X20 Z0 F200\nG1 Z-10\nX30 Z-15\nG40 G0 X40 Z5\nM30\n").unwrap();
    let cp = cprog.to_str().unwrap();
    let table = dir.path().join("t.toml");
    ok(&cncgw(&state, &["offsets", "export", table.to_str().unwrap()]));
    let svg = |st: &Path, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let mut a = vec!["preview", cp, "-o", out.to_str().unwrap()];
        a.extend_from_slice(extra);
        let o = cncgw(st, &a);
        ok(&o);
        (std::fs::read_to_string(out).unwrap(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (stored, said) = svg(&state, &[], "stored.svg");
    assert!(said.contains("stored in"), "{said}");
    let (file, said) = svg(&state, &["--tools", table.to_str().unwrap()], "file.svg");
    assert!(said.contains("(--tools)"), "{said}");
    let (none, _) = svg(&dir.path().join("empty"), &[], "none.svg");
    assert!(stored == file, "preview from the stored table and from --tools with the same table differ");
    assert!(stored != none, "the offsets (nose radius 0.8, G54, EXT) do not show in the path");
    // plan prints the same moves from the stored table as from --tools FILE.
    let plan_stored = ok(&cncgw(&state, &["plan", "--no-machine", cp]));
    let plan_file = ok(&cncgw(&state, &["plan", "--no-machine", "--tools", table.to_str().unwrap(), cp]));
    let plan_none = ok(&cncgw(&dir.path().join("empty"), &["plan", "--no-machine", cp]));
    assert!(plan_stored != plan_none, "the nose radius shows in the planned moves");
    assert_eq!(plan_stored, plan_file);
    // An explicit --tools wins over the stored table: an empty table means no offset.
    let zero = dir.path().join("zero.toml");
    std::fs::write(&zero, "[1]\n").unwrap();
    let o = cncgw(&state, &["run", "--batch", "--json", "--tools", zero.to_str().unwrap(), p]);
    let s: serde_json::Value = serde_json::from_str(&ok(&o)).unwrap();
    let axis = |n: &str| s["axes"].as_array().unwrap().iter().find(|a| a["axis"] == n).unwrap()["final_actual"].as_f64().unwrap();
    assert!((axis("x") - 22.0).abs() < 2e-3 && (axis("z") - -16.0).abs() < 1e-3, "only G54 + EXT: {s}");
}
