//! Machine configuration (`config/*.toml`), validated on load.
//!
//! Every validation error names the key path and what is allowed, e.g.
//! `axes.z.max_speed: must be > 0, got -3`.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;

/// The configuration compiled into the binary: the default lathe with emulated drives.
pub const EMBEDDED_LATHE: &str = include_str!("../config/lathe.toml");

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: cannot read: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{file}: {message}")]
    Parse { file: String, message: String },
    #[error("{file}: {}", errors.join("\n  "))]
    Invalid { file: String, errors: Vec<String> },
}

impl ConfigError {
    /// Alarm number for configuration errors.
    pub const ALARM: u32 = 1000;
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineConfig {
    pub machine: Machine,
    pub bus: Bus,
    /// Axes by name: `x`, `z`, `y`, `c`/`s1`… Iteration order is by name.
    pub axes: BTreeMap<String, AxisConfig>,
    /// The manuals' parameter table, keyed by parameter number (`5200 = 0`).
    #[serde(default)]
    pub parameters: BTreeMap<String, toml::Value>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Machine {
    pub name: String,
    /// Bus cycle in milliseconds (0.25 … 100).
    pub cycle_ms: f64,
    /// Spindle–axis sync error (threading, rigid tapping, G92.1) at which motion alarms and
    /// stops spindle and axes together, µm along the thread (1 … 10000).
    #[serde(default = "default_sync_error_limit")]
    pub sync_error_limit_um: f64,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bus {
    /// `inproc` (embedded emulated drives), `vcan0`, `can0`, … Overridden by `--bus`.
    pub interface: String,
    /// CAN bitrate in bit/s, for the bus-load check.
    #[serde(default = "default_bitrate")]
    pub bitrate: u32,
    /// How long to wait for each node's boot-up / first SDO answer, ms.
    #[serde(default = "default_sdo_timeout")]
    pub sdo_timeout_ms: u32,
    /// Master heartbeat producer period (ms) that the drives consume via 0x1016; 0 = off.
    #[serde(default = "default_heartbeat")]
    pub heartbeat_ms: u16,
    /// A drive whose position feedback (TPDO) is older than this while running raises
    /// alarm 2015 and stops the machine, ms.
    #[serde(default = "default_feedback_timeout")]
    pub feedback_timeout_ms: f64,
}

fn default_feedback_timeout() -> f64 {
    20.0
}

fn default_sync_error_limit() -> f64 {
    // A tenth of a millimetre: well beyond what locked drives show, well within what spoils
    // a thread flank.
    100.0
}

fn default_bitrate() -> u32 {
    1_000_000
}
fn default_sdo_timeout() -> u32 {
    500
}
fn default_heartbeat() -> u16 {
    100
}

#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum AxisKind {
    /// A feed axis in mm (X is held as a radius).
    Linear,
    /// A spindle, usable as a Cs position axis, in degrees.
    Spindle,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisConfig {
    pub kind: AxisKind,
    /// CANopen node id (1…127).
    pub node: u8,
    /// Position counts per mm (linear) or per degree (spindle).
    pub counts_per_unit: f64,
    /// Software travel limits in machine coordinates (mm; X as radius). Not used for spindles.
    #[serde(default)]
    pub min: Option<f64>,
    #[serde(default)]
    pub max: Option<f64>,
    /// Maximum speed: mm/min for linear axes, rpm for spindles.
    pub max_speed: f64,
    /// Maximum acceleration: mm/s² for linear axes, rpm/s for spindles.
    pub max_accel: f64,
    /// Following-error window written to 0x6065 (mm or degrees).
    #[serde(default = "default_ferr")]
    pub following_error: f64,
    /// Optional EDS file describing the drive.
    #[serde(default)]
    pub eds: Option<String>,
}

fn default_ferr() -> f64 {
    1.0
}

impl MachineConfig {
    /// Load and validate a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Io { path: path.display().to_string(), source })?;
        Self::from_toml(&path.display().to_string(), &text)
    }

    /// The embedded default machine.
    pub fn embedded() -> Self {
        Self::from_toml("<embedded config/lathe.toml>", EMBEDDED_LATHE)
            .expect("embedded config/lathe.toml is validated by the test suite")
    }

    /// Parse and validate TOML text; `file` names it in errors.
    pub fn from_toml(file: &str, text: &str) -> Result<Self, ConfigError> {
        let cfg: MachineConfig = toml::from_str(text)
            .map_err(|e| ConfigError::Parse { file: file.into(), message: e.to_string() })?;
        let errors = cfg.validate();
        if errors.is_empty() {
            Ok(cfg)
        } else {
            Err(ConfigError::Invalid { file: file.into(), errors })
        }
    }

    /// Every problem, each as `key.path: what is allowed, got value`.
    pub fn validate(&self) -> Vec<String> {
        let mut e = Vec::new();
        let c = self.machine.cycle_ms;
        if !(c.is_finite() && (0.25..=100.0).contains(&c)) {
            e.push(format!("machine.cycle_ms: must be between 0.25 and 100, got {c}"));
        }
        let sl = self.machine.sync_error_limit_um;
        if !(sl.is_finite() && (1.0..=10_000.0).contains(&sl)) {
            e.push(format!("machine.sync_error_limit_um: must be between 1 and 10000, got {sl}"));
        }
        if self.bus.interface.trim().is_empty() {
            e.push("bus.interface: must name an interface (inproc, vcan0, can0, …), got \"\"".into());
        }
        if !(10_000..=1_000_000).contains(&self.bus.bitrate) {
            e.push(format!("bus.bitrate: must be between 10000 and 1000000, got {}", self.bus.bitrate));
        }
        let ft = self.bus.feedback_timeout_ms;
        if !(ft.is_finite() && ft >= 2.0 * c && ft <= 1000.0) {
            e.push(format!("bus.feedback_timeout_ms: must be between two cycles ({}) and 1000, got {ft}", 2.0 * c));
        }
        if self.bus.sdo_timeout_ms == 0 {
            e.push("bus.sdo_timeout_ms: must be > 0, got 0".into());
        }
        if self.axes.is_empty() {
            e.push("axes: at least one axis is required".into());
        }
        let mut nodes: BTreeMap<u8, &str> = BTreeMap::new();
        for (name, a) in &self.axes {
            let p = format!("axes.{name}");
            if !name.chars().all(|ch| ch.is_ascii_alphanumeric()) || name.is_empty() {
                e.push(format!("{p}: axis names are letters and digits (x, z, c, s1), got {name:?}"));
            }
            if !(1..=127).contains(&a.node) {
                e.push(format!("{p}.node: must be a CANopen node id 1..=127, got {}", a.node));
            } else if let Some(other) = nodes.insert(a.node, name) {
                e.push(format!("{p}.node: node {} is already used by axes.{other}", a.node));
            }
            positive(&mut e, &format!("{p}.counts_per_unit"), a.counts_per_unit);
            positive(&mut e, &format!("{p}.max_speed"), a.max_speed);
            positive(&mut e, &format!("{p}.max_accel"), a.max_accel);
            positive(&mut e, &format!("{p}.following_error"), a.following_error);
            if a.kind == AxisKind::Linear {
                match (a.min, a.max) {
                    (Some(lo), Some(hi)) if !(lo.is_finite() && hi.is_finite() && lo < hi) => {
                        e.push(format!("{p}.max: must be > {p}.min ({lo}), got {hi}"))
                    }
                    (Some(_), Some(_)) => {}
                    _ => e.push(format!("{p}.min/{p}.max: a linear axis needs both travel limits (mm)")),
                }
            }
            // Counts must fit i32 over the whole travel (CiA 402 positions are INTEGER32).
            if let (Some(lo), Some(hi)) = (a.min, a.max) {
                let m = lo.abs().max(hi.abs()) * a.counts_per_unit;
                if m > i32::MAX as f64 {
                    e.push(format!(
                        "{p}.counts_per_unit: travel ±{} × {} counts overflows INTEGER32; lower the resolution",
                        lo.abs().max(hi.abs()),
                        a.counts_per_unit
                    ));
                }
            }
        }
        for (k, v) in &self.parameters {
            if k.parse::<u32>().is_err() {
                e.push(format!("parameters.{k}: parameter keys are the manuals' numbers (e.g. 5200), got {k:?}"));
            }
            // Per-axis parameters (No.1240 reference point …) are tables `{ x = 0.0, z = 0.0 }`.
            let per_axis = v.as_table().is_some_and(|t| t.values().all(|a| a.is_integer() || a.is_float()));
            if !(v.is_integer() || v.is_float() || v.is_bool() || per_axis) {
                e.push(format!("parameters.{k}: must be a number (or {{ x = …, z = … }} per axis), got {v}"));
            }
        }
        e
    }

    pub fn cycle_s(&self) -> f64 {
        self.machine.cycle_ms / 1000.0
    }

    /// A numeric parameter by its manual number.
    pub fn param(&self, no: u32) -> Option<f64> {
        match self.parameters.get(&no.to_string())? {
            toml::Value::Integer(i) => Some(*i as f64),
            toml::Value::Float(f) => Some(*f),
            toml::Value::Boolean(b) => Some(*b as u8 as f64),
            _ => None,
        }
    }

    /// Axis `axis` (`x`, `z`, `y`, `c`) of a per-axis parameter written as a table, e.g.
    /// `1240 = { x = 0.0, z = 0.0 }` → `param_axis(1240, "z")`.
    pub fn param_axis(&self, no: u32, axis: &str) -> Option<f64> {
        match self.parameters.get(&no.to_string())?.as_table()?.get(axis)? {
            toml::Value::Integer(i) => Some(*i as f64),
            toml::Value::Float(f) => Some(*f),
            _ => None,
        }
    }

    /// Bit `bit` of an integer parameter (No.5200#6 → `param_bit(5200, 6)`).
    pub fn param_bit(&self, no: u32, bit: u8) -> bool {
        self.param(no).map(|v| (v as i64 >> bit) & 1 == 1).unwrap_or(false)
    }

    /// The spindle axis, if any.
    pub fn spindle(&self) -> Option<(&str, &AxisConfig)> {
        self.axes.iter().find(|(_, a)| a.kind == AxisKind::Spindle).map(|(n, a)| (n.as_str(), a))
    }
}

fn positive(e: &mut Vec<String>, path: &str, v: f64) {
    if !(v.is_finite() && v > 0.0) {
        e.push(format!("{path}: must be > 0, got {v}"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_config_is_valid() {
        let c = MachineConfig::from_toml("lathe.toml", EMBEDDED_LATHE).unwrap();
        assert_eq!(c.machine.cycle_ms, 2.0);
        assert_eq!(c.axes["x"].node, 1);
        assert_eq!(c.axes["z"].node, 2);
        assert_eq!(c.axes["s1"].node, 3);
        assert!(c.param(5200).is_some());
    }

    #[test]
    fn negative_speed_is_reported_with_key_path() {
        let t = EMBEDDED_LATHE.replace("max_speed = 12000.0 # z", "max_speed = -3 # z");
        assert_ne!(t, EMBEDDED_LATHE, "test must edit the z axis");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.max_speed: must be > 0, got -3"), "{err}");
    }

    #[test]
    fn unknown_key_is_a_parse_error() {
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nbogus = 1");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("bogus"), "{err}");
    }

    #[test]
    fn sync_error_limit_defaults_and_is_validated() {
        let c = MachineConfig::from_toml("lathe.toml", EMBEDDED_LATHE).unwrap();
        assert_eq!(c.machine.sync_error_limit_um, 100.0);
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nsync_error_limit_um = 25");
        assert_eq!(MachineConfig::from_toml("t.toml", &t).unwrap().machine.sync_error_limit_um, 25.0);
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nsync_error_limit_um = 0.0");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("machine.sync_error_limit_um: must be between 1 and 10000, got 0"), "{err}");
    }

    #[test]
    fn duplicate_node_is_reported() {
        let t = EMBEDDED_LATHE.replace("node = 2", "node = 1");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.node: node 1 is already used by axes.x"), "{err}");
    }
}
