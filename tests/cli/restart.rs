//! Program restart (issue 24.4) on the embedded machine: `run --restart-seq/--restart-at`
//! scans to the block without motion, brings the axes there X first, starts the spindle and
//! goes on with the program's modal state; refusals say why and move nothing.

use std::path::Path;
use std::process::{Command, Output};

fn cncgw(state: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", state).args(args).output().unwrap()
}

/// Rows of a trace: (line, x_cmd radius, z_cmd, spindle_rpm, t_s).
fn trace(path: &Path) -> Vec<(u32, f64, f64, f64, f64)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let (l, x, z, s, t) = (col("line"), col("x_cmd"), col("z_cmd"), col("spindle_rpm"), col("t_s"));
    lines
        .map(|r| {
            let v: Vec<&str> = r.split(',').collect();
            (v[l].parse().unwrap(), v[x].parse().unwrap(), v[z].parse().unwrap(), v[s].parse().unwrap(), v[t].parse().unwrap())
        })
        .collect()
}

const PROG: &str = "G21 G98\nG0 X40 Z2 M3 S800\nG1 Z-10 F600\n#100=5\nG0 X50\nN60 G1 U-[#100*2]\nZ-20\nM30\n";

#[test]
fn restart_goes_there_x_first_starts_the_spindle_and_keeps_the_modal_state() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let prog = dir.path().join("r.nc");
    std::fs::write(&prog, PROG).unwrap();
    let csv = dir.path().join("r.csv");
    for how in [["--restart-seq", "60"], ["--restart-at", "6"]] {
        let o = cncgw(&state, &["run", "--batch", "--trace", csv.to_str().unwrap(), how[0], how[1], prog.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        assert_eq!(o.status.code(), Some(0), "{err}");
        assert!(err.contains("restart at line 6 (N60 G1 U-[#100*2])") && err.contains("in this order: X 50.0000 → Z -10.0000"), "{err}");
        assert!(err.contains("then the spindle: M03 S800"), "{err}");
        let rows = trace(&csv);
        // Nothing of lines 1–5 ran: the first motion is the restart's own.
        assert!(rows.iter().all(|r| r.0 >= 6), "a scanned block moved");
        // X away first: Z does not move before X has reached the restart diameter.
        let first_z = rows.iter().position(|r| r.2 != 0.0).unwrap();
        assert!((rows[first_z].1 - 25.0).abs() < 1e-9, "Z moved at X {}", rows[first_z].1);
        // The spindle starts once the axes are there, before the block cuts.
        let cut = rows.iter().position(|r| r.1 < 25.0 - 1e-9).unwrap();
        assert!(rows[..cut].iter().all(|r| r.3.abs() < 1.0), "the spindle turned during the approach");
        assert!(rows.iter().filter(|r| r.0 == 7).all(|r| (r.3 - 800.0).abs() < 8.0), "the spindle is at S800 for the next block");
        // Modal G01 F600 and #100 = 5 from the scanned blocks: N60 cuts to X40, line 7 takes
        // 10 mm at 600 mm/min (1 s plus its ramps).
        let l7: Vec<_> = rows.iter().filter(|r| r.0 == 7).collect();
        let dt = l7.last().unwrap().4 - l7[0].4;
        assert!((1.0..1.2).contains(&dt), "line 7 took {dt} s");
        let end = rows.last().unwrap();
        assert!((end.1 - 20.0).abs() < 1e-9 && (end.2 - -20.0).abs() < 1e-9, "ends at X40 Z-20: {end:?}");
    }
}

#[test]
fn refused_restarts_say_why_and_move_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    let cases = [
        ("G21 G97 S500 M3\nG0 X30 Z5\nG32 Z-10 F1.5\nZ-20\nG0 X40\nM30\n", "4", "a thread cannot be picked up"),
        (
            "G21 G98 M3 S500\nG0 X50 Z2\nG71 U1 R0.5\nG71 P10 Q20 U0.2 W0.1 F200\nN10 G0 X20\nG1 Z-10\nN20 X50\nG0 X60 Z5\nM30\n",
            "6",
            "finishing contour of the cycle at line 4",
        ),
        (PROG, "60", "no such line"),
    ];
    for (text, line, why) in cases {
        let prog = dir.path().join("p.nc");
        std::fs::write(&prog, text).unwrap();
        let csv = dir.path().join("p.csv");
        let o = cncgw(&state, &["run", "--batch", "--trace", csv.to_str().unwrap(), "--restart-at", line, prog.to_str().unwrap()]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains("alarm 2520") && err.contains(why) && err.contains("nothing was moved"), "{err}");
        assert!(!csv.exists(), "the drives were not even started");
    }
    let o = cncgw(&state, &["run", "--restart-at", "3", "--restart-seq", "5", "x.nc"]);
    assert_eq!(o.status.code(), Some(2), "one restart point or the other");
}

#[test]
fn restart_uses_the_stored_offsets_as_the_run_does() {
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().join("state");
    for set in [["T01", "--x", "-4", "--z", "-3"], ["G54", "--z", "-10", "", ""]] {
        let args: Vec<&str> = ["offsets", "set"].into_iter().chain(set.into_iter().filter(|a| !a.is_empty())).collect();
        assert!(cncgw(&state, &args).status.success());
    }
    let prog = dir.path().join("o.nc");
    std::fs::write(&prog, "G21 G98 T0101\nG0 X40 Z2\nG1 Z-10 F3000\nN40 G0 X50\nZ5\nM30\n").unwrap();
    let o = cncgw(&state, &["run", "--batch", "--json", "--restart-seq", "40", prog.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    // Before N40 the tool stands at work X40 Z-10: machine X 40 − 4 = 36, Z −10 − 3 − 10 = −23.
    assert!(err.contains("to X 36.0000 Z -23.0000 (machine; work X 40.0000 Z -10.0000"), "{err}");
    let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let at = |n: &str| s["axes"].as_array().unwrap().iter().find(|a| a["axis"] == n).unwrap()["final_actual"].as_f64().unwrap();
    assert!((at("x") - 46.0).abs() < 2e-3 && (at("z") - -8.0).abs() < 1e-3, "{s}");
}
