//! The operator panel on a terminal: single keys without Enter (raw mode through termios),
//! pressed onto a [`Panel`] the cycle loop reads every cycle, and a status display redrawn
//! in place.
//!
//! Keys (as on a Fanuc 0i-TF's machine operator panel, one key per button):
//! `h` feed hold, `s` cycle start, `b` single block on/off, `o` optional stop (M01) on/off,
//! `+`/`-` feed override ±10 % (0–200 %), `r` reset, `e` E-stop, Ctrl-C = reset.
//!
//! The terminal is restored on every way out: `RawMode` restores it when dropped (normal
//! end, alarm, panic unwinding); Ctrl-C arrives as a key (ISIG is off) and presses reset, so
//! the run ends through its controlled stop and the guard; SIGTERM and SIGHUP stop it as
//! reset does too (`catch_termination`).

use crate::control::cycle::Progress;
use crate::control::panel::Panel;
use crate::motion::{AX_X, AX_Z};
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};

/// The terminal in raw-ish mode (no line buffering, no echo, no signals from keys) while
/// alive; the saved settings come back on drop.
pub struct RawMode {
    saved: libc::termios,
}

impl RawMode {
    /// Switch stdin to single keys. Err if stdin is not a terminal.
    pub fn enter() -> std::io::Result<RawMode> {
        // SAFETY: tcgetattr/tcsetattr on fd 0 with a termios we own; zeroed is a valid
        // termios bit pattern and is overwritten by tcgetattr.
        unsafe {
            let mut t: libc::termios = std::mem::zeroed();
            if libc::tcgetattr(0, &mut t) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            let saved = t;
            // Output processing (OPOST) stays on, so '\n' still returns the carriage.
            t.c_lflag &= !(libc::ICANON | libc::ECHO | libc::ISIG | libc::IEXTEN);
            t.c_iflag &= !(libc::IXON | libc::ICRNL);
            t.c_cc[libc::VMIN] = 1;
            t.c_cc[libc::VTIME] = 0;
            if libc::tcsetattr(0, libc::TCSANOW, &t) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(RawMode { saved })
        }
    }
}

impl Drop for RawMode {
    fn drop(&mut self) {
        // SAFETY: restores the settings read in `enter` on the same fd.
        unsafe {
            libc::tcsetattr(0, libc::TCSANOW, &self.saved);
        }
    }
}

/// What a key does to the panel. Returns false for keys without a meaning.
pub fn press(panel: &Panel, key: u8) -> bool {
    match key {
        b'h' | b'H' => panel.press_feed_hold(),
        b's' | b'S' => panel.press_cycle_start(),
        b'b' | b'B' => panel.set_single_block(!panel.single_block()),
        b'o' | b'O' => {
            let on = OPTIONAL_STOP.fetch_xor(true, Ordering::Relaxed);
            panel.set_optional_stop(!on);
        }
        b'+' | b'=' => panel.set_feed_override((panel.feed_override() + 10).min(200)),
        b'-' | b'_' => panel.set_feed_override(panel.feed_override().saturating_sub(10)),
        // Rapid override as a Fanuc panel's four steps, down and up: 100, 50, 25 %, F0.
        b'f' => panel.set_rapid_override(rapid_step(panel.rapid_override(), false)),
        b'F' => panel.set_rapid_override(rapid_step(panel.rapid_override(), true)),
        // Spindle override in 10 % steps, 50–120 % (the panel clamps).
        b'>' | b'.' => panel.set_spindle_override(panel.spindle_override() + 10),
        b'<' | b',' => panel.set_spindle_override(panel.spindle_override().saturating_sub(10)),
        b'r' | b'R' | 0x03 => panel.press_reset(),
        b'e' | b'E' => panel.set_estop(true),
        _ => return false,
    }
    true
}

/// The rapid override's next step (Fanuc's F0, 25, 50, 100 %), up or down.
fn rapid_step(now: u32, up: bool) -> u32 {
    const STEPS: [u32; 4] = [0, 25, 50, 100];
    let i = STEPS.iter().rposition(|&s| s <= now).unwrap_or(0);
    if up {
        STEPS[(i + 1).min(3)]
    } else {
        STEPS[i.saturating_sub(1)]
    }
}

/// The panel has no getter for optional stop; the switch's position is kept here.
static OPTIONAL_STOP: AtomicBool = AtomicBool::new(false);
/// The number of the last termination signal (SIGTERM, SIGHUP, SIGINT in a batch run), 0 =
/// none; the cycle loop reads it every cycle and stops as on reset (`CycleLoop::set_signal`).
pub static SIGNAL: AtomicI32 = AtomicI32::new(0);

/// Read keys from stdin on a thread of their own and press them onto `panel`. The thread
/// ends at end of input; a thread still waiting for a key when the run is over simply ends
/// with the process.
pub fn spawn_key_reader(panel: Panel) {
    let _ = std::thread::Builder::new().name("keys".into()).spawn(move || {
        let mut b = [0u8; 16];
        loop {
            // SAFETY: read into a buffer we own, of its length.
            let n = unsafe { libc::read(0, b.as_mut_ptr().cast(), b.len()) };
            if n == 0 {
                return;
            }
            if n < 0 {
                if std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted {
                    continue;
                }
                return;
            }
            for &k in &b[..n as usize] {
                press(&panel, k);
            }
        }
    });
}

extern "C" fn on_terminate(sig: libc::c_int) {
    SIGNAL.store(sig, Ordering::Relaxed);
}

/// SIGTERM and SIGHUP (systemd stop, a CI timeout, a closed terminal) — and SIGINT where it
/// is a signal (a batch run; on the panel Ctrl-C is a key) — stop the run as reset does
/// instead of killing the process: spindle and axes come to rest under control, the summary
/// is printed, the trace completed, the terminal restored, exit code 3. (SIGKILL remains
/// the way to end the process at once; the drives then stop on the lost heartbeat.)
pub fn catch_termination(sigint: bool) {
    // SAFETY: the handler only stores to an atomic (async-signal-safe).
    unsafe {
        libc::signal(libc::SIGTERM, on_terminate as *const () as libc::sighandler_t);
        libc::signal(libc::SIGHUP, on_terminate as *const () as libc::sighandler_t);
        if sigint {
            libc::signal(libc::SIGINT, on_terminate as *const () as libc::sighandler_t);
        }
    }
}

/// The signal's name, for messages.
pub fn signal_name(sig: i32) -> &'static str {
    match sig {
        libc::SIGTERM => "SIGTERM",
        libc::SIGHUP => "SIGHUP",
        libc::SIGINT => "SIGINT",
        _ => "a signal",
    }
}

/// The interactive run's status, redrawn in place on stderr: the block in execution, the
/// position, F, S, sync error, overrides and the panel's state, with the keys underneath.
pub struct PanelDisplay {
    panel: Panel,
    lines: Vec<String>,
    shown: bool,
}

/// The help line under the status.
/// The keys, in 79 columns (an 80-column terminal cuts every line to its width).
pub const HELP: &str = "h:hold s:start b:single o:opt +/-:feed f/F:rapid <>:spindle r:reset e:E-stop";

impl PanelDisplay {
    pub fn new(panel: Panel, lines: &[&str]) -> Self {
        PanelDisplay { panel, lines: lines.iter().map(|l| l.trim().to_string()).collect(), shown: false }
    }

    /// The status text of one progress report (two lines, no newline at the end).
    pub fn status(&self, p: &Progress) -> String {
        let line = p.line;
        let block = line.checked_sub(1).and_then(|i| self.lines.get(i as usize)).map(String::as_str).unwrap_or("");
        let block: String = block.chars().take(60).collect();
        let mut state = String::new();
        if self.panel.is_held() {
            state.push_str("  HELD (s: start)");
        }
        if self.panel.single_block() {
            state.push_str("  SINGLE BLOCK");
        }
        if OPTIONAL_STOP.load(Ordering::Relaxed) {
            state.push_str("  OPT STOP");
        }
        // The [io.safety] inputs, after HELD (which must never be cut): an open one in
        // capitals.
        for label in self.panel.safety().labels() {
            state.push_str("  ");
            state.push_str(label);
        }
        let rapid = match self.panel.rapid_override() {
            0 => "F0".to_string(),
            r => format!("{r}%"),
        };
        // The overrides on the first line, the state on the second: on an 80-column terminal
        // every line is cut to its width, and HELD must never be what is cut.
        format!(
            "line {line:>4}/{}  feed {}% rapid {rapid} spindle {}%  {block}\nX{:>9.3} Z{:>9.3} F{:>5.0} S{:>5.0} sync{:>6.1} µm{state}",
            self.lines.len(),
            self.panel.feed_override(),
            self.panel.spindle_override(),
            p.pos[AX_X] * 2.0,
            p.pos[AX_Z],
            p.feed,
            p.spindle_rpm,
            p.sync_err_um,
        )
    }

    /// Redraw with `p` (called about every 50 ms of machine time).
    pub fn show(&mut self, p: &Progress) {
        let mut out = String::new();
        if self.shown {
            // Back to the first of the three lines drawn last time.
            out.push_str("\r\x1b[2A");
        }
        // Every line shorter than the terminal: one that wraps would push the redraw down
        // the screen (on 80 × 24 the status line repeated down it).
        let width = console::Term::stderr().size_checked().map_or(80, |(_, w)| w as usize).max(20) - 1;
        for l in self.status(p).lines().chain(std::iter::once(HELP)) {
            out.push_str("\r\x1b[2K");
            out.extend(l.chars().take(width));
            out.push('\n');
        }
        let mut e = std::io::stderr().lock();
        let _ = e.write_all(out.trim_end_matches('\n').as_bytes());
        let _ = e.flush();
        self.shown = true;
    }

    /// Leave the last status on screen and move below it.
    pub fn close(&mut self) {
        if self.shown {
            eprintln!();
        }
        self.shown = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_press_the_panel() {
        let p = Panel::new();
        let mut r = p.reader();
        assert!(press(&p, b'h'));
        assert!(r.poll().feed_hold);
        assert!(press(&p, b's'));
        assert!(r.poll().cycle_start);
        press(&p, b'b');
        assert!(p.single_block());
        press(&p, b'b');
        assert!(!p.single_block());
        press(&p, b'-');
        press(&p, b'-');
        assert_eq!(p.feed_override(), 80);
        for _ in 0..20 {
            press(&p, b'+');
        }
        assert_eq!(p.feed_override(), 200);
        // Rapid override down through Fanuc's steps to F0 and back up; spindle 50–120 %.
        for want in [50, 25, 0, 0] {
            press(&p, b'f');
            assert_eq!(p.rapid_override(), want);
        }
        for want in [25, 50, 100, 100] {
            press(&p, b'F');
            assert_eq!(p.rapid_override(), want);
        }
        for _ in 0..10 {
            press(&p, b'<');
        }
        assert_eq!(p.spindle_override(), 50);
        for _ in 0..10 {
            press(&p, b'>');
        }
        assert_eq!(p.spindle_override(), 120);
        let i = r.poll();
        assert_eq!((i.rapid_ovr, i.spindle_ovr), (1.0, 1.2), "the cycle loop reads them");
        press(&p, 0x03);
        assert!(r.poll().reset, "Ctrl-C presses reset");
        assert!(!press(&p, b'z'));
        press(&p, b'e');
        assert!(r.poll().estop);
    }

    #[test]
    fn status_shows_block_and_state() {
        let p = Panel::new();
        let src = ["G0 X10 Z2", "G1 Z-20 F0.2", "M30"];
        let d = PanelDisplay::new(p.clone(), &src);
        let r = p.reader();
        r.report(true, 2);
        p.set_single_block(true);
        let prog = Progress { line: 2, feed: 120.0, spindle_rpm: 800.0, sync_err_um: 1.5, ..Progress::default() };
        let s = d.status(&prog);
        assert!(s.contains("line    2/3  feed 100% rapid 100% spindle 100%  G1 Z-20 F0.2"), "{s}");
        assert!(s.contains("HELD") && s.contains("SINGLE BLOCK") && s.contains("S  800") && s.contains("sync   1.5 µm"), "{s}");
        r.report(false, 3);
        p.set_single_block(false);
        let s = d.status(&prog);
        assert!(!s.contains("HELD") && !s.contains("SINGLE"), "{s}");
        assert!(!s.contains("door") && !s.contains("E-stop"), "no [io.safety]: nothing shown: {s}");
        use crate::control::panel::SafetyInputs;
        r.report_safety(SafetyInputs { estop: Some(true), door: Some(false), chuck: Some(true) });
        let s = d.status(&prog);
        assert!(s.contains("E-stop ok  DOOR OPEN  chuck clamped"), "{s}");
        r.report_safety(SafetyInputs { estop: Some(false), door: None, chuck: Some(false) });
        let s = d.status(&prog);
        assert!(s.contains("E-STOP OPEN  CHUCK OPEN") && !s.contains("door"), "{s}");
    }
}
