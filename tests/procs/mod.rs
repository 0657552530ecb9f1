//! What the process-level tests share: a child that is killed when the test ends (also on a
//! failed assertion), the workspace's binaries, a per-run scratch directory.
#![allow(dead_code)]

use std::path::PathBuf;
use std::process::Child;

/// A child process, killed and reaped when dropped.
pub struct Kill(pub Child);
impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A binary of the workspace (sim-drives is another package; its binary lands beside ours).
pub fn bin(name: &str) -> PathBuf {
    let b = PathBuf::from(env!("CARGO_BIN_EXE_cncgw")).parent().unwrap().join(name);
    assert!(b.exists(), "{} missing: cargo build --workspace --bins", b.display());
    b
}

/// `name` in this test binary's scratch directory (`test`: the binary's name).
pub fn tmp(test: &str, name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("{test}_{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d.join(name)
}
