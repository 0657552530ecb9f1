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
