//! `cncgw mdi` on a terminal, as an operator types it (Debian's tmux, detached: `send-keys`
//! types, `capture-pane` reads the screen), on the embedded machine paced to the wall clock:
//! the prompt, a block per Enter with the modal state kept, a refused block, M30 ends.
//!
//! Real time: serialized in .config/nextest.toml.

use std::process::Command;
use std::time::{Duration, Instant};

struct Tmux {
    socket: String,
}

impl Tmux {
    fn cmd(&self, args: &[&str]) -> String {
        let o = Command::new("tmux").args(["-L", &self.socket]).args(args).output().expect("tmux is not installed: run scripts/install-test-deps.sh");
        assert!(o.status.success(), "tmux {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    }
    fn screen(&self) -> String {
        self.cmd(&["capture-pane", "-p", "-S", "-200", "-t", "mdi"])
    }
    fn line(&self, text: &str) {
        self.cmd(&["send-keys", "-t", "mdi", "-l", text]);
        self.cmd(&["send-keys", "-t", "mdi", "Enter"]);
    }
    fn wait_for(&self, what: &str, f: impl Fn(&str) -> bool) -> String {
        let t0 = Instant::now();
        loop {
            let s = self.screen();
            if f(&s) {
                return s;
            }
            assert!(t0.elapsed() < Duration::from_secs(30), "waited 30 s for {what}; the screen:\n{s}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = Command::new("tmux").args(["-L", &self.socket, "kill-server"]).output();
    }
}

#[test]
fn mdi_on_a_terminal_block_by_block() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().display();
    let sh = format!("cd {d} && {bin} mdi --state-dir {d}/state; echo EXIT=$?; sleep 60", bin = env!("CARGO_BIN_EXE_cncgw"));
    let t = Tmux { socket: format!("cncgw-mdi-{}", std::process::id()) };
    t.cmd(&["new-session", "-d", "-s", "mdi", "-x", "100", "-y", "40", &sh]);
    let prompts = |n: usize| move |s: &str| s.matches("MDI>").count() >= n;
    let s = t.wait_for("the prompt", prompts(1));
    assert!(s.contains("one block per line, Enter runs it"), "{s}");
    t.line("G21 G98 G0 X20 Z2");
    t.wait_for("the second prompt", prompts(2));
    t.line("G1 Z-5 F3000");
    t.wait_for("the third prompt", prompts(3));
    // Beyond X's travel: refused, nothing moves, the session goes on.
    t.line("X900");
    let s = t.wait_for("the refusal", |s| s.contains("the block was not run") && s.matches("MDI>").count() >= 4);
    assert!(s.contains("refused before any motion"), "{s}");
    // Modal G01 and F3000 from the blocks before.
    t.line("U4");
    t.wait_for("the fifth prompt", prompts(5));
    t.line("M30");
    let s = t.wait_for("the end", |s| s.contains("EXIT="));
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
    let t = Tmux { socket: format!("cncgw-mdi-c-{}", std::process::id()) };
    t.cmd(&["new-session", "-d", "-s", "mdi", "-x", "100", "-y", "40", &sh]);
    t.wait_for("the prompt", |s| s.contains("MDI>"));
    t.line("#500=7");
    t.wait_for("the second prompt", |s| s.matches("MDI>").count() >= 2);
    // 100 mm at 600 mm/min: 10 s, paced to the wall clock.
    t.line("G21 G98 G1 Z-100 F600");
    t.wait_for("the third prompt", |s| s.matches("MDI>").count() >= 3);
    std::thread::sleep(Duration::from_millis(500));
    let t0 = Instant::now();
    t.cmd(&["send-keys", "-t", "mdi", "C-c"]);
    // The machine stops under control and the session ends without another line typed
    // (the input thread, waiting for one, is not waited for).
    let s = t.wait_for("the end", |s| s.contains("EXIT="));
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
