//! MDI (issue 24.3) on the embedded machine: `cncgw mdi` with blocks piped on standard
//! input — modal state and macro variables kept between blocks, refused blocks move nothing
//! and the session goes on — and `cncgw run -`.

use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};

fn with_stdin(state: &Path, args: &[&str], input: &str) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", state)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    c.stdin.take().unwrap().write_all(input.as_bytes()).unwrap();
    c.wait_with_output().unwrap()
}

fn final_actual(o: &Output) -> (f64, f64) {
    let out = String::from_utf8_lossy(&o.stdout);
    let s: serde_json::Value = serde_json::from_str(out.trim()).unwrap_or_else(|e| panic!("{e}: {out}\n{}", String::from_utf8_lossy(&o.stderr)));
    let axis = |n: &str| s["axes"].as_array().unwrap().iter().find(|a| a["axis"] == n).unwrap()["final_actual"].as_f64().unwrap();
    (axis("x"), axis("z"))
}

#[test]
fn mdi_keeps_modal_state_and_refuses_bad_blocks_without_motion() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let blocks = [
        "G21 G98",
        "G0 X20 Z2",
        "G1 Z-5 F3000",      // G01 and F stay modal
        "G1 X900",           // beyond X's travel: refused before motion
        "G5.5",              // not a G code: refused
        "#3000=1(MDI TEST)", // a user alarm: refused, kept in the history
        "#100=4",            // a macro variable kept for the next block
        "U#100",             // modal G01 at F3000: X 20 → 24 (diameter)
        "W-[#100/2]",        // Z −5 → −7
    ];
    let input = blocks.join("\n") + "\n";
    let o = with_stdin(&state, &["mdi", "--json"], &input);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let (x, z) = final_actual(&o);
    assert!((x - 24.0).abs() < 2e-3 && (z - -7.0).abs() < 1e-3, "X{x} Z{z}\n{err}");
    assert_eq!(err.matches("the block was not run").count(), 3, "{err}");
    assert!(err.contains("refused before any motion"), "{err}");
    // The refused blocks are not part of the session: the blocks that ran are numbered on.
    assert!(err.contains("MDI 4: #100=4") && err.contains("MDI 6: W-[#100/2]"), "{err}");
    let h = Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", &state).args(["alarms", "--json"]).output().unwrap();
    let v: serde_json::Value = serde_json::from_slice(&h.stdout).unwrap();
    assert!(v.as_array().unwrap().iter().any(|r| r["number"] == 3001 && r["program"] == "MDI"), "{v}");
}

#[test]
fn mdi_ends_at_m30_and_common_variables_survive() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let o = with_stdin(&state, &["mdi", "--json"], "#500=12.5\nG0 X10 Z1\nM30\nG0 X40\n");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    let (x, _) = final_actual(&o);
    assert!((x - 10.0).abs() < 2e-3, "M30 ended the session before G0 X40: X{x}\n{err}");
    // #500 is kept through power-off: a program run later reads it.
    let prog = dir.path().join("p.nc");
    std::fs::write(&prog, "G0 X#500 Z1\nM30\n").unwrap();
    let o = with_stdin(&state, &["run", "--batch", "--json", prog.to_str().unwrap()], "");
    let (x, _) = final_actual(&o);
    assert!((x - 12.5).abs() < 2e-3, "X{x}");
}

#[test]
fn run_dash_takes_the_program_on_standard_input() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let prog = "G21 G98\nG0 X30 Z2\nG1 Z-8 F2000\nM30\n";
    let o = with_stdin(&state, &["run", "--batch", "--json", "-"], prog);
    assert_eq!(o.status.code(), Some(0), "{}", String::from_utf8_lossy(&o.stderr));
    let (x, z) = final_actual(&o);
    assert!((x - 30.0).abs() < 2e-3 && (z - -8.0).abs() < 1e-3);
    // A program error on standard input is reported at its line, nothing moves.
    let o = with_stdin(&state, &["run", "--batch", "-"], "G0 X30\nG5.5\nM30\n");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("<stdin>:2") && err.contains("nothing was moved"), "{err}");
}
