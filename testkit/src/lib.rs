//! What cncgw's integration tests share (a dev-dependency only): running `cncgw` with a
//! state directory of its own (tests never touch the user's real one), the workspace's other
//! binaries, per-test scratch directories, child processes killed when a test ends, and the
//! socat pseudo-terminal pair the Modbus RTU tests run over.
//!
//! The paths cargo gives an integration test (`CARGO_BIN_EXE_cncgw`, `CARGO_TARGET_TMPDIR`)
//! exist only while that test crate compiles, so the macros below expand there.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

/// A child process, killed and reaped when dropped (also on a failed assertion).
pub struct Kill(pub Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A finished command: exit code (−1 if killed by a signal) and its output as text.
#[derive(Debug)]
pub struct Out {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

impl From<Output> for Out {
    fn from(o: Output) -> Out {
        Out {
            code: o.status.code().unwrap_or(-1),
            stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
            stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        }
    }
}

/// The state directory of this test process under `root` (the test crate's
/// `CARGO_TARGET_TMPDIR`, see [`state_dir!`]): never the user's (`CNCGW_STATE_DIR`), and inside
/// the build's target directory, not left behind in the system's /tmp (one per test process).
pub fn state_dir_in(root: &str) -> PathBuf {
    Path::new(root).join(format!("state_{}", std::process::id()))
}

/// The state directory of the calling test process ([`state_dir_in`]).
#[macro_export]
macro_rules! state_dir {
    () => {
        $crate::state_dir_in(env!("CARGO_TARGET_TMPDIR"))
    };
}

/// `cncgw` as a test runs it: [`cli!`] makes one for the test crate's binary.
#[derive(Clone, Debug)]
pub struct Cli {
    bin: PathBuf,
    state: PathBuf,
    dir: Option<PathBuf>,
}

impl Cli {
    /// `bin` with its power-off state in `state` (a test's own, see [`state_dir!`]).
    pub fn new(bin: impl Into<PathBuf>, state: impl Into<PathBuf>) -> Cli {
        Cli { bin: bin.into(), state: state.into(), dir: None }
    }

    /// Keep the power-off state here instead.
    pub fn state(mut self, dir: impl Into<PathBuf>) -> Cli {
        self.state = dir.into();
        self
    }

    /// Run in this working directory.
    pub fn dir(mut self, dir: impl Into<PathBuf>) -> Cli {
        self.dir = Some(dir.into());
        self
    }

    /// The command, not started (to add stdin, env, or spawn it).
    pub fn command<S: AsRef<std::ffi::OsStr>>(&self, args: &[S]) -> Command {
        let mut c = Command::new(&self.bin);
        c.env("CNCGW_STATE_DIR", &self.state).args(args);
        if let Some(d) = &self.dir {
            c.current_dir(d);
        }
        c
    }

    pub fn output<S: AsRef<std::ffi::OsStr>>(&self, args: &[S]) -> Output {
        self.command(args).output().unwrap_or_else(|e| panic!("cannot run {}: {e}", self.bin.display()))
    }

    pub fn run<S: AsRef<std::ffi::OsStr>>(&self, args: &[S]) -> Out {
        self.output(args).into()
    }
}

/// `cncgw` of the calling test crate, with this process's state directory.
#[macro_export]
macro_rules! cli {
    () => {
        $crate::Cli::new(env!("CARGO_BIN_EXE_cncgw"), $crate::state_dir!())
    };
}

/// A binary of the workspace (sim-drives is another package; its binary lands beside ours).
#[macro_export]
macro_rules! bin {
    ($name:expr) => {
        $crate::sibling(env!("CARGO_BIN_EXE_cncgw"), $name)
    };
}

/// `name` in the calling test binary's scratch directory (`test`: the binary's name).
#[macro_export]
macro_rules! tmp {
    ($test:expr, $name:expr) => {
        $crate::scratch(env!("CARGO_TARGET_TMPDIR"), $test, $name)
    };
}

/// `name` beside the binary `bin`, which must have been built.
pub fn sibling(bin: &str, name: &str) -> PathBuf {
    let b = Path::new(bin).parent().map(|p| p.join(name)).unwrap_or_else(|| PathBuf::from(name));
    assert!(b.exists(), "{} missing: cargo build --workspace --bins", b.display());
    b
}

/// `root/TEST_PID/name`, the directory made.
pub fn scratch(root: &str, test: &str, name: &str) -> PathBuf {
    let d = Path::new(root).join(format!("{test}_{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
    d.join(name)
}

/// Whether `tool` (socat, mbpoll) is on PATH for the Modbus tests. Missing: a failure
/// (install it with `scripts/install-test-deps.sh`), unless `CNCGW_SKIP_MODBUS_TOOLS=1`
/// outside CI, which skips the test and says so.
pub fn have_tool(tool: &str) -> bool {
    let found = Command::new("sh").args(["-c", &format!("command -v {tool}")]).stdout(Stdio::null()).status().is_ok_and(|s| s.success());
    if found {
        return true;
    }
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_MODBUS_TOOLS").as_deref() == Ok("1") && !ci {
        eprintln!("{tool} missing, CNCGW_SKIP_MODBUS_TOOLS=1: test skipped on request");
        return false;
    }
    panic!(
        "`{tool}` is not installed: run `scripts/install-test-deps.sh` (installs socat and mbpoll){}",
        if ci { "; CI=true: the Modbus tool tests never skip" } else { ", or set CNCGW_SKIP_MODBUS_TOOLS=1 to skip these tests on purpose" }
    );
}

/// [`have_tool`] for socat (the RTU tests' serial line pair).
pub fn have_socat() -> bool {
    have_tool("socat")
}

/// A pair of connected pseudo-terminals (a null-modem serial line) from socat, alive while
/// the returned [`Kill`] is.
pub fn pty_pair() -> (Kill, String, String) {
    let mut c = Command::new("socat")
        .args(["-d", "-d", "pty,raw,echo=0", "pty,raw,echo=0"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start socat");
    let err = c.stderr.take().expect("socat's stderr");
    let k = Kill(c);
    let mut lines = BufReader::new(err).lines();
    let mut ptys = Vec::new();
    while ptys.len() < 2 {
        let l = lines.next().expect("socat named no pty").expect("socat's stderr");
        if let Some(p) = l.split("PTY is ").nth(1) {
            ptys.push(p.trim().to_string());
        }
    }
    // Keep draining socat's messages so that it never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines.by_ref() {});
    (k, ptys[0].clone(), ptys[1].clone())
}

/// A detached tmux server of its own (Debian's tmux; `send-keys` types, `capture-pane` reads
/// the screen) with one session running a shell command: a terminal driven as a person
/// drives it. Killed when dropped.
pub struct Tmux {
    socket: String,
    session: String,
}

impl Tmux {
    /// A `width`×`height` terminal running `sh`; `name` keeps servers of parallel tests apart.
    pub fn start(name: &str, (width, height): (u16, u16), sh: &str) -> Tmux {
        let t = Tmux { socket: format!("cncgw-{name}-{}", std::process::id()), session: name.to_string() };
        t.cmd(&["new-session", "-d", "-s", name, "-x", &width.to_string(), "-y", &height.to_string(), sh]);
        t
    }

    /// A tmux command on this server; its output.
    pub fn cmd(&self, args: &[&str]) -> String {
        let o = Command::new("tmux").args(["-L", &self.socket]).args(args).output().expect("tmux is not installed: run scripts/install-test-deps.sh");
        assert!(o.status.success(), "tmux {args:?}: {}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    }

    /// The screen and up to `history` lines above it.
    pub fn screen_with(&self, history: u32) -> String {
        self.cmd(&["capture-pane", "-p", "-S", &format!("-{history}"), "-t", &self.session])
    }

    /// The visible screen.
    pub fn screen(&self) -> String {
        self.cmd(&["capture-pane", "-p", "-t", &self.session])
    }

    /// Keys as tmux names them (`h`, `C-c`, `Enter`).
    pub fn keys(&self, k: &str) {
        self.cmd(&["send-keys", "-t", &self.session, k]);
    }

    /// A line of text, then Enter.
    pub fn line(&self, text: &str) {
        self.cmd(&["send-keys", "-t", &self.session, "-l", text]);
        self.keys("Enter");
    }

    /// Wait up to `secs` for `read()` (a screen) to satisfy `f`; that screen.
    pub fn wait_until(&self, what: &str, secs: u64, read: impl Fn(&Tmux) -> String, f: impl Fn(&str) -> bool) -> String {
        let t0 = std::time::Instant::now();
        loop {
            let s = read(self);
            if f(&s) {
                return s;
            }
            assert!(t0.elapsed() < std::time::Duration::from_secs(secs), "waited {secs} s for {what}; the screen:\n{s}");
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = Command::new("tmux").args(["-L", &self.socket, "kill-server"]).output();
    }
}
