//! Reference (home) state of the axes, kept in the state directory per machine and bus
//! (`MACHINE@PLACE.reference.toml`, written atomically as `persist` writes every state file).
//!
//! "State is never wrong": an axis is written referenced only after its drive reported
//! "homing attained", and the entry is dropped — and the file rewritten — as soon as
//! anything says the drive's position may have changed behind the controller's back:
//! - the bus saw the drive reboot (a boot-up message 0x700 + id, 0x00, it did not cause) or
//!   an encoder fault (EMCY 0x73xx) — `DriveBus::position_lost`;
//! - `cncgw nmt reset-node` was sent to it;
//! - at the start of a run the drive stands elsewhere than where the last session left it
//!   (a drive powered off and on while no controller watched: an incremental encoder counts
//!   afresh from power-on);
//! - the controller's host was restarted since (its boot id changed): a machine's control
//!   and drives share the main switch, and a Fanuc loses the reference at power-off too.
//!
//! Axes with `absolute = true` are referenced at start; axes with neither `homing` nor
//! `absolute` have no reference to manage (see `config::Machine::require_reference`).
//!
//! Manual 004 §2.10 note 4 (stroke limits take effect after reference return) and G28/G30
//! (to the reference points of parameters 1240–1243, machine coordinates): both rest on the
//! machine coordinates the homing sets — `homing.offset` is the machine position the home
//! point gets, as a Fanuc's reference return sets No.1240 there. Since `run` and `mdi`
//! refuse to start while an axis needing a reference has none (alarm 224; a Fanuc refuses
//! a move command with PS0224, G28 itself excepted: here G28 is not a homing, the drive's
//! homing mode is, so it is refused too), the travel limits, G22 and G28/G30 only ever act
//! on referenced coordinates.

use crate::config::MachineConfig;
use crate::Alarm;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// One referenced axis.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Entry {
    /// The drive (CANopen node or Modbus unit) that was homed.
    pub node: u8,
    /// The homing method it was homed with (0x6098).
    pub method: i8,
    /// When, seconds since the Unix epoch.
    pub homed_at: u64,
    /// Where the last session left the axis (machine units): the check at the next start.
    pub position: f64,
    /// The host's boot id when homed (Linux /proc/sys/kernel/random/boot_id).
    #[serde(default)]
    pub host_boot: String,
}

/// Every referenced axis by name.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Table {
    #[serde(default)]
    pub axes: BTreeMap<String, Entry>,
}

/// This host's boot id (empty where there is none).
pub fn host_boot() -> String {
    std::fs::read_to_string("/proc/sys/kernel/random/boot_id").map(|s| s.trim().to_string()).unwrap_or_default()
}

fn unix_now() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

/// The axes whose motion needs a reference: those with a `homing` method, unless
/// `machine.require_reference = false`.
pub fn required(cfg: &MachineConfig) -> Vec<String> {
    if !cfg.machine.require_reference {
        return Vec::new();
    }
    cfg.axes.iter().filter(|(_, a)| a.homing.is_some() && !a.absolute).map(|(n, _)| n.clone()).collect()
}

impl Table {
    /// Record `axis` homed now, standing at `position`.
    pub fn set_homed(&mut self, axis: &str, node: u8, method: i8, position: f64) {
        let e = Entry { node, method, homed_at: unix_now(), position, host_boot: host_boot() };
        self.axes.insert(axis.to_string(), e);
    }

    /// Drop `axis`'s reference; the reason is returned as a note when it had one.
    pub fn lose(&mut self, axis: &str, why: &str) -> Option<String> {
        self.axes.remove(axis).map(|_| format!("axis {} lost its reference: {why}; home it again with `cncgw home {axis}`", axis.to_uppercase()))
    }

    /// Whether `axis` is referenced (absolute axes always are).
    pub fn referenced(&self, cfg: &MachineConfig, axis: &str) -> bool {
        cfg.axes.get(axis).is_some_and(|a| a.absolute) || self.axes.contains_key(axis)
    }

    /// At start: drop every entry whose axis stands elsewhere than the last session left it
    /// (by more than `tol(axis)`), or that was homed before the host last booted. `here` gives
    /// the axis's actual position now. Returns what was dropped, in words.
    pub fn check_start(&mut self, here: &[(String, f64, f64)]) -> Vec<String> {
        let boot = host_boot();
        let mut notes = Vec::new();
        for (axis, pos, tol) in here {
            let Some(e) = self.axes.get(axis) else { continue };
            let why = if !boot.is_empty() && !e.host_boot.is_empty() && e.host_boot != boot {
                Some("the controller was restarted since it was homed (the machine was powered off)".to_string())
            } else if (pos - e.position).abs() > *tol {
                Some(format!(
                    "its drive reports {pos:.4} where the last session left it at {:.4} (the drive was reset or powered off and on)",
                    e.position
                ))
            } else {
                None
            };
            if let Some(w) = why {
                notes.extend(self.lose(axis, &w));
            }
        }
        notes
    }

    /// Where the axes stand at the end of a session: the positions the next start checks.
    pub fn update_positions(&mut self, here: &[(String, f64, f64)]) {
        for (axis, pos, _) in here {
            if let Some(e) = self.axes.get_mut(axis) {
                e.position = *pos;
            }
        }
    }

    /// Alarm 224 for the first axis of `required` that is not referenced.
    pub fn check(&self, cfg: &MachineConfig, required: &[String]) -> Result<(), Alarm> {
        let missing: Vec<&String> = required.iter().filter(|a| !self.referenced(cfg, a)).collect();
        let Some(first) = missing.first() else { return Ok(()) };
        let names: Vec<String> = missing.iter().map(|a| a.to_uppercase()).collect();
        Err(Alarm::new(
            crate::alarm::NOT_REFERENCED,
            format!(
                "zero return not finished: axis {} {} not referenced; home {} with `cncgw home {}` (or `cncgw home all`) before moving (machine.require_reference = false moves without)",
                names.join(", "),
                if names.len() > 1 { "are" } else { "is" },
                if names.len() > 1 { "them" } else { "it" },
                first.as_str()
            ),
        ))
    }
}

/// The reference file of one machine on one place.
#[derive(Clone, Debug)]
pub struct ReferenceFile {
    pub path: PathBuf,
}

impl ReferenceFile {
    /// The table (empty when there is no file yet).
    pub fn load(&self) -> Result<Table, Alarm> {
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Table::default()),
            Err(e) => return Err(Alarm::new(crate::persist::STATE_ALARM, format!("{}: cannot be read ({e})", self.path.display()))),
        };
        toml::from_str(&text).map_err(|e| {
            Alarm::new(
                crate::persist::STATE_ALARM,
                format!("{}: not a reference table ({e}); delete it and home the axes again", self.path.display()),
            )
        })
    }

    pub fn save(&self, t: &Table) -> Result<(), Alarm> {
        let text = format!(
            "# Written by cncgw: the axes referenced (homed) on this machine and bus. Do not edit;\n# `cncgw home AXIS` writes it.\n{}",
            toml::to_string(t).unwrap_or_default()
        );
        crate::persist::atomic_write(&self.path, text.as_bytes())
            .map_err(|e| Alarm::new(crate::persist::STATE_ALARM, format!("{}: cannot be written ({e})", self.path.display())))
    }

    /// Load, change with `f`, save if it changed. The caller holds the machine's state lock
    /// (`cli::lock::state`): two processes' read-change-writes must not interleave.
    pub fn update(&self, f: impl FnOnce(&mut Table)) -> Result<Table, Alarm> {
        let mut t = self.load()?;
        let before = t.clone();
        f(&mut t);
        if t != before {
            self.save(&t)?;
        }
        Ok(t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(require: bool) -> MachineConfig {
        let mut c = MachineConfig::embedded();
        c.machine.require_reference = require;
        let x = c.axes.get_mut("x").unwrap();
        x.homing = Some(crate::config::Homing { method: 35, offset: 0.0, speed: None, zero_speed: None, accel: None, timeout_s: None });
        c
    }

    #[test]
    fn unreferenced_axis_is_alarm_224_naming_the_command() {
        let c = cfg(true);
        let req = required(&c);
        assert_eq!(req, vec!["x".to_string()]);
        let a = Table::default().check(&c, &req).unwrap_err();
        assert_eq!(a.number, crate::alarm::NOT_REFERENCED);
        assert!(a.message.contains("cncgw home x"), "{}", a.message);
        assert!(required(&cfg(false)).is_empty());
        let mut t = Table::default();
        t.set_homed("x", 1, 35, 10.0);
        assert!(t.check(&c, &req).is_ok());
    }

    #[test]
    fn a_moved_axis_loses_its_reference_at_start() {
        let mut t = Table::default();
        t.set_homed("x", 1, 35, 10.0);
        assert!(t.check_start(&[("x".into(), 10.0005, 0.001)]).is_empty());
        let notes = t.check_start(&[("x".into(), 0.0, 0.001)]);
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(t.axes.is_empty());
    }

    #[test]
    fn file_round_trips_and_missing_is_empty() {
        let dir = std::env::temp_dir().join(format!("cncgw-ref-{}", std::process::id()));
        let f = ReferenceFile { path: dir.join("m@inproc.reference.toml") };
        assert_eq!(f.load().unwrap(), Table::default());
        let t = f.update(|t| t.set_homed("z", 2, 17, -1.5)).unwrap();
        assert_eq!(f.load().unwrap(), t);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
