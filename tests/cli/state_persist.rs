//! Common variables #401–#600 survive from one `cncgw run` to the next (manual 004 §2.24.1);
//! the state is kept per machine and per place it runs (the embedded machine never shares a
//! real machine's), and under a lock: one run at a time (issue 19.5/19.6).

use std::process::Command;

fn run(program: &std::path::Path, state: &std::path::Path) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_cncgw")).args(["run", "--json", "--state-dir"]).arg(state).arg(program).output().unwrap();
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
    let end_x =
        |v: &serde_json::Value| v["axes"].as_array().unwrap().iter().find(|a| a["axis"] == "x").unwrap()["final_actual_counts"].as_i64().unwrap();
    let first = run(&prog, &state);
    // X2.0 diameter = 1 mm radius = 10 000 counts.
    assert!((end_x(&first) - 10_000).abs() <= 1, "{first}");
    let second = run(&prog, &state);
    assert!((end_x(&second) - 20_000).abs() <= 1, "{second}");
    let text = std::fs::read_to_string(state.join("cncgw-default-lathe-x-z-cs-spindle@inproc.common-vars.toml")).unwrap();
    assert!(text.contains("\"#500\" = 4.0"), "{text}");
    assert!(!text.contains("#1\""), "locals are not stored: {text}");
    let _ = std::fs::remove_dir_all(&dir);
}

fn run_raw(args: &[&str], state: &std::path::Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cncgw")).args(args).arg("--state-dir").arg(state).output().unwrap()
}

fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("cncgw-state-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

const FIRST_PART: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc");

#[test]
fn the_embedded_machine_never_reads_or_writes_a_real_machines_state() {
    let state = scratch("place");
    // A real machine (on can0) was interrupted in a tapped hole; so was one of the earlier
    // naming, one state for every place.
    let in_hole = "in_hole = true\naxis = \"Z\"\nr_plane = 2.0\ndirection_in = -1.0\nlead = -1.5\nrpm = 500.0\noverride_pct = 100.0\nposition = -10.0\nspindle_deg = 0.0\nline = 6\n";
    let real = state.join("cncgw-default-lathe-x-z-cs-spindle@can0.tap-state.toml");
    let old = state.join("cncgw-default-lathe-x-z-cs-spindle.tap-state.toml");
    // (Written without the check line: what matters is that the embedded run does not read them.)
    std::fs::write(&real, in_hole).unwrap();
    std::fs::write(&old, in_hole).unwrap();
    let o = run_raw(&["run", "--batch", FIRST_PART], &state);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("left alone"), "the old file is not taken by the embedded machine: {err}");
    assert_eq!(std::fs::read_to_string(&real).unwrap(), in_hole, "the real machine's state is untouched");
    assert_eq!(std::fs::read_to_string(&old).unwrap(), in_hole);
    assert!(state.join("cncgw-default-lathe-x-z-cs-spindle@inproc.common-vars.toml").exists());
    let _ = std::fs::remove_dir_all(&state);
}

#[test]
fn a_second_run_on_the_same_state_is_refused_and_names_the_first() {
    let state = scratch("lock");
    let _held = cncgw::cli::lock::state(&state, "cncgw-default-lathe-x-z-cs-spindle@inproc").unwrap();
    let o = run_raw(&["run", "--batch", FIRST_PART], &state);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(4), "{err}");
    assert!(err.contains("alarm 2405") && err.contains(&format!("pid {}", std::process::id())), "{err}");
    let _ = std::fs::remove_dir_all(&state);
}

#[test]
fn a_second_controller_on_the_same_bus_is_refused_before_it_touches_it() {
    let state = scratch("bus");
    // No socketcand listens there: the lock is checked before the bus is opened.
    let bus = format!("socketcand://127.0.0.1:9/lock{}", std::process::id());
    let _held = cncgw::cli::lock::bus(&bus).unwrap();
    let o = run_raw(&["run", "--batch", "--bus", &bus, FIRST_PART], &state);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(4), "{err}");
    assert!(err.contains("alarm 2404") && err.contains("in use by another cncgw"), "{err}");
    let _ = std::fs::remove_dir_all(&state);
}

#[test]
fn an_unwritable_state_directory_is_found_before_anything_moves() {
    let state = scratch("ro");
    let file = state.join("not-a-dir");
    std::fs::write(&file, "x").unwrap();
    let o = run_raw(&["run", "--batch", "--json", FIRST_PART], &file);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(4), "{err}");
    assert!(err.contains("cannot be written") && !err.contains("drives enabled"), "{err}");
    assert!(o.stdout.is_empty(), "nothing ran");
    let _ = std::fs::remove_dir_all(&state);
}
