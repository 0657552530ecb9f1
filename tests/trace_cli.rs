//! `cncgw run --trace FILE.csv` and `cncgw trace plot FILE.csv -o FILE.svg`.

use cncgw::control::trace::TraceData;
use std::process::Command;

#[test]
fn run_writes_a_trace_of_every_cycle_and_plot_draws_it() {
    let dir = std::env::temp_dir().join(format!("cncgw-trace-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("p.nc");
    // A thread pass, so the sync error column has something in it.
    std::fs::write(&prog, "G21\nG98\nM03 S800\nG00 X30 Z5\nG32 Z-15 F1.5\nG00 X40\nZ5\nM05\nM30\n").unwrap();
    let csv = dir.join("t.csv");
    let out = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["run", "--json", "--trace"])
        .arg(&csv)
        .arg(&prog)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    let d = TraceData::parse(&std::fs::read_to_string(&csv).unwrap()).unwrap();
    for c in ["t_s", "line", "x_cmd", "x_act", "x_ferr", "z_cmd", "z_act", "z_ferr", "s1_cmd", "s1_act", "spindle_rpm", "sync_err_um"] {
        assert!(d.column(c).is_some(), "column {c} in {:?}", d.columns);
    }
    let t = d.column("t_s").unwrap();
    // One row per cycle, 2 ms apart.
    assert_eq!(t.len() as u64, v["cycles"].as_u64().unwrap());
    assert!(t.windows(2).all(|w| (w[1] - w[0] - 0.002).abs() < 1e-6));
    // X is a radius: X30 → 15 mm at the thread.
    let x = d.column("x_cmd").unwrap();
    let lines = d.column("line").unwrap();
    let k = lines.iter().position(|l| *l == 5.0).unwrap();
    assert!((x[k] - 15.0).abs() < 1e-9, "x_cmd {} on the thread", x[k]);
    let rpm = d.column("spindle_rpm").unwrap();
    assert!((rpm[k] - 800.0).abs() < 5.0, "spindle {} rpm on the thread", rpm[k]);
    let sync = d.column("sync_err_um").unwrap();
    assert!(sync.iter().any(|e| *e != 0.0), "the thread's sync error is traced");
    assert!(sync.iter().all(|e| e.abs() < 20.0));
    let svg = dir.join("t.svg");
    let st = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["trace", "plot"])
        .arg(&csv)
        .arg("-o")
        .arg(&svg)
        .status()
        .unwrap();
    assert!(st.success());
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.starts_with("<svg") && text.contains("<polyline") && text.contains("sync error"));
    // A file that is not a trace is an error, not a panic.
    let st = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["trace", "plot"])
        .arg(&prog)
        .arg("-o")
        .arg(&svg)
        .status()
        .unwrap();
    assert_eq!(st.code(), Some(2));
    let _ = std::fs::remove_dir_all(&dir);
}
