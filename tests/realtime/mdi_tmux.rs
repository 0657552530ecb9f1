//! `cncgw mdi` on a terminal, as an operator types it (Debian's tmux, detached: `send-keys`
//! types, `capture-pane` reads the screen), on the embedded machine paced to the wall clock:
//! the prompt, a block per Enter with the modal state kept, a refused block, M30 ends.
//!
//! Real time: serialized in .config/nextest.toml.

use std::time::{Duration, Instant};
use testkit::Tmux;

/// The screen with its scrollback (the session's whole dialogue), within 30 s.
fn wait_for(t: &Tmux, what: &str, f: impl Fn(&str) -> bool) -> String {
    t.wait_until(what, 30, |t| t.screen_with(200), f)
}

#[test]
fn mdi_on_a_terminal_block_by_block() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display();
    let sh = format!("cd {d} && {bin} mdi --state-dir {d}/state; echo EXIT=$?; sleep 60", bin = env!("CARGO_BIN_EXE_cncgw"));
    let t = Tmux::start("mdi", (100, 40), &sh);
    let prompts = |n: usize| move |s: &str| s.matches("MDI>").count() >= n;
    let s = wait_for(&t, "the prompt", prompts(1));
    assert!(s.contains("one block per line, Enter runs it"), "{s}");
    t.line("G21 G98 G0 X20 Z2");
    wait_for(&t, "the second prompt", prompts(2));
    t.line("G1 Z-5 F3000");
    wait_for(&t, "the third prompt", prompts(3));
    // Beyond X's travel: refused, nothing moves, the session goes on.
    t.line("X900");
    let s = wait_for(&t, "the refusal", |s| s.contains("the block was not run") && s.matches("MDI>").count() >= 4);
    assert!(s.contains("refused before any motion"), "{s}");
    // Modal G01 and F3000 from the blocks before.
    t.line("U4");
    wait_for(&t, "the fifth prompt", prompts(5));
    t.line("M30");
    let s = wait_for(&t, "the end", |s| s.contains("EXIT="));
    assert!(s.contains("EXIT=0"), "{s}");
    let row = |axis: &str| s.lines().find(|l| l.split_whitespace().next() == Some(axis)).unwrap_or_else(|| panic!("{s}")).to_string();
    // Final actual (third column pair) X 24 (diameter), Z −5.
    assert!(row("x").contains("24.0000 mm") && row("z").contains("-5.0000 mm"), "{s}");
}

#[test]
fn ctrl_c_stops_a_block_and_ends_the_session_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display();
    let sh = format!("cd {d} && {bin} mdi --state-dir {d}/state; echo EXIT=$?; sleep 60", bin = env!("CARGO_BIN_EXE_cncgw"));
    let t = Tmux::start("mdi-c", (100, 40), &sh);
    wait_for(&t, "the prompt", |s| s.contains("MDI>"));
    t.line("#500=7");
    wait_for(&t, "the second prompt", |s| s.matches("MDI>").count() >= 2);
    // 100 mm at 600 mm/min: 10 s, paced to the wall clock.
    t.line("G21 G98 G1 Z-100 F600");
    wait_for(&t, "the third prompt", |s| s.matches("MDI>").count() >= 3);
    std::thread::sleep(Duration::from_millis(500));
    let t0 = Instant::now();
    t.keys("C-c");
    // The machine stops under control and the session ends without another line typed
    // (the input thread, waiting for one, is not waited for).
    let s = wait_for(&t, "the end", |s| s.contains("EXIT="));
    assert!(s.contains("EXIT=3"), "{s}");
    assert!(t0.elapsed() < Duration::from_secs(5), "it took {:?}", t0.elapsed());
    let z: f64 = s.lines().find(|l| l.split_whitespace().next() == Some("z")).and_then(|l| l.split_whitespace().nth(3)).unwrap().parse().unwrap();
    assert!(z > -50.0 && z < 0.0, "stopped on the way: Z {z}\n{s}");
    // #500 (kept through power-off) was stored although the session ended on a stop.
    let vars = std::fs::read_dir(dir.path().join("state"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_string_lossy().ends_with(".common-vars.toml"))
        .unwrap();
    assert!(std::fs::read_to_string(vars).unwrap().contains("\"#500\" = 7.0"));
}
