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

/// The state directory of this test process: never the user's (`CNCGW_STATE_DIR`).
pub fn state_dir() -> PathBuf {
    std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id()))
}

/// `cncgw` as a test runs it: [`cli!`] makes one for the test crate's binary.
#[derive(Clone, Debug)]
pub struct Cli {
    bin: PathBuf,
    state: PathBuf,
    dir: Option<PathBuf>,
}

impl Cli {
    pub fn new(bin: impl Into<PathBuf>) -> Cli {
        Cli { bin: bin.into(), state: state_dir(), dir: None }
    }

    /// Keep the power-off state here instead of [`state_dir`].
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
        $crate::Cli::new(env!("CARGO_BIN_EXE_cncgw"))
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

/// Whether socat is here for the RTU tests. Missing: a failure (install it with
/// `scripts/install-test-deps.sh`), unless `CNCGW_SKIP_MODBUS_TOOLS=1` outside CI, which
/// skips the test and says so.
pub fn have_socat() -> bool {
    let found = Command::new("sh").args(["-c", "command -v socat"]).stdout(Stdio::null()).status().is_ok_and(|s| s.success());
    if found {
        return true;
    }
    let ci = std::env::var("CI").as_deref() == Ok("true");
    if std::env::var("CNCGW_SKIP_MODBUS_TOOLS").as_deref() == Ok("1") && !ci {
        eprintln!("socat missing, CNCGW_SKIP_MODBUS_TOOLS=1: test skipped on request");
        return false;
    }
    panic!("`socat` is not installed: run `scripts/install-test-deps.sh`");
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
