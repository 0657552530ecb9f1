//! The interactive `cncgw run` driven as a person drives it: in a terminal (Debian's tmux,
//! detached; `send-keys` types, `capture-pane` reads the screen), on the embedded emulated
//! machine paced to the wall clock. Start, feed hold, cycle start, single block, reset.
//!
//! Real time: serialized in .config/nextest.toml. tmux comes from
//! scripts/install-test-deps.sh.

use std::time::{Duration, Instant};
use testkit::Tmux;

/// Wait (up to 20 s) for the screen to satisfy `f`; the screen.
fn wait_for(t: &Tmux, what: &str, f: impl Fn(&str) -> bool) -> String {
    t.wait_until(what, 20, Tmux::screen, f)
}

/// Z on the status line `X    20.000 Z   -26.040  F …`.
fn z_of(screen: &str) -> Option<f64> {
    let l = screen.lines().find(|l| l.trim_start().starts_with('X') && l.contains(" Z"))?;
    let mut t = l.split_whitespace();
    t.find(|w| *w == "Z")?;
    t.next()?.parse().ok()
}

#[test]
fn interactive_run_feed_hold_resume_reset_in_tmux() {
    let dir = std::env::temp_dir().join(format!("cncgw_cli_tmux_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // 100 mm at 600 mm/min: 10 s of feed, paced to the wall clock.
    std::fs::write(dir.join("long.nc"), "G21\nG98\nG0 X20 Z2\nG1 Z-100 F600\nG1 X40\nG0 Z2\nM30\n").unwrap();
    let sh =
        format!("cd {d} && {bin} run long.nc --state-dir {d}/state; echo EXIT=$?; sleep 60", d = dir.display(), bin = env!("CARGO_BIN_EXE_cncgw"));
    // An 80 × 24 terminal (issue 19.11: the status used to need 119 columns and repeated down
    // the screen).
    let t = Tmux::start("run", (80, 24), &sh);

    // It runs: the help line, the block in execution, Z going down.
    let s = wait_for(&t, "the feed block", |s| s.contains("G1 Z-100 F600") && z_of(s).is_some_and(|z| z < -2.0));
    assert!(s.contains("h:hold s:start b:single"), "{s}");
    std::thread::sleep(Duration::from_millis(500));
    let s = t.screen();
    assert_eq!(s.matches("h:hold s:start").count(), 1, "the panel is redrawn in place, not down the screen:\n{s}");
    assert!(s.lines().all(|l| l.chars().count() <= 80), "{s}");
    assert!(s.contains("line    4/7"), "{s}");
    assert!(!s.contains("HELD"), "{s}");

    // Feed hold: HELD on screen and Z stands still.
    t.keys("h");
    wait_for(&t, "HELD", |s| s.contains("HELD"));
    // HELD shows from the start of the deceleration: wait (up to 3 s) for Z to stand.
    let mut z_held = z_of(&t.screen()).unwrap();
    let t0 = Instant::now();
    loop {
        std::thread::sleep(Duration::from_millis(200));
        let z = z_of(&t.screen()).unwrap();
        if z == z_held {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(3), "Z still moving 3 s after feed hold: {z}");
        z_held = z;
    }
    std::thread::sleep(Duration::from_millis(800));
    let s = t.screen();
    assert!(s.contains("HELD"), "{s}");
    assert_eq!(z_of(&s), Some(z_held), "Z moved while held:\n{s}");
    assert!(z_held > -100.0, "held at the end of the block? {z_held}");

    // Cycle start: it moves on, down from where it stood.
    t.keys("s");
    let s = wait_for(&t, "the move to go on", |s| !s.contains("HELD") && z_of(s).is_some_and(|z| z < z_held - 1.0));
    assert!(s.contains("line    4/7"), "{s}");

    // Rapid override down two of Fanuc's steps, spindle override up one: on the status line.
    t.keys("ff>");
    wait_for(&t, "the overrides", |s| s.contains("rapid 25%") && s.contains("spindle 110%"));

    // Single block on and off shows on the status line.
    t.keys("b");
    wait_for(&t, "SINGLE BLOCK", |s| s.contains("SINGLE BLOCK"));
    t.keys("b");
    wait_for(&t, "single block off", |s| !s.contains("SINGLE BLOCK"));

    // Reset: a controlled stop, alarm 2401 in words, exit code 3, terminal restored.
    t.keys("r");
    let s = wait_for(&t, "the end of the run", |s| s.contains("EXIT="));
    assert!(s.contains("alarm 2401: reset by the operator at line 4"), "{s}");
    assert!(s.contains("EXIT=3"), "{s}");
    let z_end = z_of(&s).unwrap();
    assert!(z_end > -100.0 && z_end < z_held - 1.0, "{z_end}");
    // The summary shows where Z stopped (mm, with its unit), near the last status: the status
    // line is refreshed every few tenths of a second and the stop still brakes after it.
    let row: Vec<&str> = s.lines().find(|l| l.starts_with("z ")).expect("summary row of z").split_whitespace().collect();
    assert_eq!(row[4], "mm", "{row:?}");
    let z_stop = row[3].parse::<f64>().unwrap();
    assert!((z_stop - z_end).abs() < 1.0, "Z stopped at {z_stop}, last shown {z_end}");
    // The shell echoes typed keys again (the terminal left raw mode).
    t.keys("echo-check");
    wait_for(&t, "the echo of typed keys", |s| s.contains("echo-check"));
}

/// Ctrl-C on an interactive run is reset (a controlled stop, not a kill): alarm 2401, exit
/// code 3, and the terminal is back in its normal mode.
#[test]
fn ctrl_c_is_reset_and_restores_the_terminal() {
    let dir = std::env::temp_dir().join(format!("cncgw_cli_tmux_c_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("long.nc"), "G21\nG98\nG0 X20 Z2\nG1 Z-100 F600\nM30\n").unwrap();
    let sh = format!(
        "cd {d} && {bin} run long.nc --state-dir {d}/state; echo EXIT=$?; stty -a | tr ' ;' '\\n\\n' | grep -x -e icanon -e echo -e -icanon -e -echo; sleep 60",
        d = dir.display(),
        bin = env!("CARGO_BIN_EXE_cncgw")
    );
    let t = Tmux::start("run-c", (160, 30), &sh);
    wait_for(&t, "the feed block", |s| s.contains("G1 Z-100 F600") && z_of(s).is_some_and(|z| z < -2.0));
    t.keys("C-c");
    // The end of the run and stty's report after it (two lines: icanon or -icanon, echo or -echo).
    let s = wait_for(&t, "the end of the run and stty", |s| {
        s.find("EXIT=").is_some_and(|i| s[i..].lines().filter(|l| matches!(l.trim(), "icanon" | "-icanon" | "echo" | "-echo")).count() == 2)
    });
    assert!(s.contains("alarm 2401: reset by the operator at line 4"), "{s}");
    assert!(s.contains("EXIT=3"), "{s}");
    // stty reports the restored modes: canonical input and echo on (no "-icanon"/"-echo").
    let after = &s[s.find("EXIT=3").unwrap()..];
    assert!(after.lines().any(|l| l.trim() == "icanon") && after.lines().any(|l| l.trim() == "echo"), "{after}");
}
