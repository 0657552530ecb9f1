//! Common variables #401–#600 survive from one `cncgw run` to the next (manual 004 §2.24.1).

use std::process::Command;

fn run(program: &std::path::Path, state: &std::path::Path) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--json", "--state-dir"])
        .arg(state)
        .arg(program)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn common_variables_persist_between_runs() {
    let dir = std::env::temp_dir().join(format!("cncgw-state-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("count.nc");
    // Each run moves X to the diameter #500 holds, then counts the part.
    std::fs::write(&prog, "O1\nG00 U0 W0\n#500 = #500 + 2\nG00 X#500 Z0\n#1 = 7\nM30\n").unwrap();
    let state = dir.join("state");
    let end_x = |v: &serde_json::Value| v["axes"].as_array().unwrap().iter().find(|a| a["axis"] == "x").unwrap()["final_actual_counts"].as_i64().unwrap();
    let first = run(&prog, &state);
    // X2.0 diameter = 1 mm radius = 10 000 counts.
    assert!((end_x(&first) - 10_000).abs() <= 1, "{first}");
    let second = run(&prog, &state);
    assert!((end_x(&second) - 20_000).abs() <= 1, "{second}");
    let text = std::fs::read_to_string(state.join("cncgw-default-lathe-x-z-cs-spindle.common-vars.toml")).unwrap();
    assert!(text.contains("\"#500\" = 4.0"), "{text}");
    assert!(!text.contains("#1\""), "locals are not stored: {text}");
    let _ = std::fs::remove_dir_all(&dir);
}
