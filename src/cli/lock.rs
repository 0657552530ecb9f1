//! One controller per bus and per state: exclusive locks (`flock`) on lock files, released by
//! the kernel when the process ends however it ends.
//!
//! - The bus: `/run/lock/cncgw-bus-NAME.lock` (`/run/lock` is shared by every user on Debian,
//!   so a systemd service and a service engineer's terminal see the same lock; a temporary
//!   directory where it is not writable), NAME from the interface or URL. Taken by every
//!   command that moves or writes the drives or resets the bus (`run`, `tap-test`, `jog`,
//!   `drive enable|disable|fault-reset|home`, `nmt`, `sdo write`); the read-only ones (`scan`,
//!   `sdo read`, `drive status`, `monitor`, `od`, `buslog`) may watch a bus in use. The
//!   embedded emulated bus (`inproc`) is private to each run and takes none.
//! - The state: `STATE_DIR/MACHINE@PLACE.lock` beside the state files, so that two runs can
//!   never interleave their common-variable or tap-state updates.
//!
//! A refusal names the holder (its pid and command line, written into the file). The master
//! also listens on the wire for a foreign SYNC or master heartbeat before it resets the bus
//! (`drives::canopen::master::bus_check`): that catches a master on another computer.

use std::fs::File;
use std::io::{Read, Seek, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};

/// Alarm: another process holds the bus.
pub const BUS_IN_USE: u32 = crate::alarm::BUS_IN_USE;
/// Alarm: another process holds the machine's state.
pub const STATE_IN_USE: u32 = crate::alarm::STATE_IN_USE;

/// A lock held until dropped.
#[derive(Debug)]
pub struct Lock {
    _file: File,
    pub path: PathBuf,
}

/// The locks this process holds: a command that locks the bus and then runs a job (a Modbus
/// jog) must not be refused by itself.
static HELD: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

impl Drop for Lock {
    fn drop(&mut self) {
        if let Ok(mut h) = HELD.lock() {
            h.retain(|p| *p != self.path);
        }
    }
}

fn held_here(path: &Path) -> bool {
    HELD.lock().is_ok_and(|h| h.iter().any(|p| p == path))
}

/// The file-name form of a bus or place: letters, digits, `.` and `-` kept, the rest `_`.
pub fn slug(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '.' || c == '-' { c } else { '_' }).collect()
}

fn lock_dir() -> PathBuf {
    let run = Path::new("/run/lock");
    let writable = run.is_dir() && {
        let probe = run.join(format!(".cncgw-probe-{}", std::process::id()));
        let ok = File::create(&probe).is_ok();
        let _ = std::fs::remove_file(&probe);
        ok
    };
    if writable {
        run.to_path_buf()
    } else {
        std::env::temp_dir().join("cncgw-locks")
    }
}

/// Lock the bus named `bus` for a command that moves or writes the drives; `None` for the
/// private embedded bus.
pub fn bus(bus: &str) -> Result<Option<Lock>, crate::Alarm> {
    if bus == "inproc" {
        return Ok(None);
    }
    let dir = lock_dir();
    let path = dir.join(format!("cncgw-bus-{}.lock", slug(bus)));
    if held_here(&path) {
        return Ok(None);
    }
    acquire(&path).map(Some).map_err(|holder| {
        crate::Alarm::new(
            BUS_IN_USE,
            format!(
                "the bus {bus} is in use by another cncgw ({holder}; lock {}): only one controller may drive a bus; stop the other one first (read-only commands such as scan, drive status and monitor may watch it meanwhile)",
                path.display()
            ),
        )
    })
}

/// The bus lock of a service command that moves or writes the drives (`--bus`, else the
/// configuration's); `Err`: the exit code, the reason printed.
pub fn for_writing(machine: &super::MachineArgs) -> Result<Option<Lock>, i32> {
    let name = match &machine.bus {
        Some(b) => b.clone(),
        None => match super::load_config(machine.config.as_deref()) {
            Ok((cfg, _)) => super::run::run_place(&cfg, machine),
            Err(_) => return Ok(None), // the command itself reports the configuration
        },
    };
    bus(&name).map_err(|a| {
        eprintln!("{a}");
        super::exit::SETUP
    })
}

/// Lock the machine's state in `dir` (`key`: the state files' stem).
pub fn state(dir: &Path, key: &str) -> Result<Lock, crate::Alarm> {
    let path = dir.join(format!("{key}.lock"));
    acquire(&path).map_err(|holder| {
        crate::Alarm::new(
            STATE_IN_USE,
            format!(
                "the machine's state in {} is in use by another run ({holder}): two runs must not share it; wait for the other one or give this one its own --state-dir",
                dir.display()
            ),
        )
    })
}

/// Take the lock; `Err`: who holds it (or why it cannot be taken).
fn acquire(path: &Path) -> Result<Lock, String> {
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d).map_err(|e| format!("cannot create {}: {e}", d.display()))?;
    }
    let mut f =
        File::options().read(true).write(true).create(true).truncate(false).open(path).map_err(|e| format!("cannot open {}: {e}", path.display()))?;
    // SAFETY: flock on a descriptor we own; released when it is closed.
    let r = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if r != 0 {
        let mut holder = String::new();
        let _ = f.read_to_string(&mut holder);
        let holder = holder.trim();
        return Err(if holder.is_empty() { "a process that wrote no name".into() } else { holder.to_string() });
    }
    let me = format!("pid {}: {}", std::process::id(), std::env::args().collect::<Vec<_>>().join(" "));
    let _ = f.set_len(0);
    let _ = f.rewind();
    let _ = f.write_all(me.as_bytes());
    if let Ok(mut h) = HELD.lock() {
        h.push(path.to_path_buf());
    }
    Ok(Lock { _file: f, path: path.to_path_buf() })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_the_same_file_is_refused_and_names_the_first() {
        let dir = std::env::temp_dir().join(format!("cncgw-lock-test-{}", std::process::id()));
        let a = state(&dir, "m@inproc").unwrap();
        let e = state(&dir, "m@inproc").unwrap_err();
        assert_eq!(e.number, STATE_IN_USE);
        assert!(e.message.contains(&format!("pid {}", std::process::id())), "{e}");
        drop(a);
        assert!(state(&dir, "m@inproc").is_ok(), "released on drop");
        assert!(bus("inproc").unwrap().is_none());
        assert_eq!(slug("socketcand://127.0.0.1:5000/can0"), "socketcand___127.0.0.1_5000_can0");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
