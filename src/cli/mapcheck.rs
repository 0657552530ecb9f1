//! `cncgw config check --bus modbus-…`: every register of each Modbus axis's map tried on
//! the live drive (docs/MODBUS_MAPS.md). A map that looks right on paper but names a
//! register the drive does not have made `run` stop with 0x02 at start-up while `config
//! check` said ok (issue 22); this reads each register and writes back each writable one
//! (with the value read, or a value that starts nothing), and reports what fails.

use super::mbus::Client;
use crate::config::{AxisConfig, MachineConfig};
use crate::drives::modbus::plan::DrivePlan;
use cncgw_bus::modbus::{MapRegister, Profile};

/// One register that failed.
pub struct Finding {
    pub axis: String,
    pub unit: u8,
    pub register: MapRegister,
    /// "cannot read: …" / "cannot write: …".
    pub what: String,
}

impl Finding {
    pub fn line(&self, map: &str) -> String {
        let r = &self.register;
        let hint = if r.optional {
            format!(" — optional: if the drive has no such register, set {} = \"none\" in [axes.{}.{map}_map]", r.name, self.axis)
        } else {
            String::new()
        };
        format!(
            "axis {} (unit {}): {} (register {} = 0x{:04X}, {} register{}): {}{hint}",
            self.axis,
            self.unit,
            r.name,
            r.addr,
            r.addr,
            r.len,
            if r.len == 1 { "" } else { "s" },
            self.what
        )
    }
}

/// The result for one axis.
pub struct AxisCheck {
    pub axis: String,
    pub unit: u8,
    pub map: &'static str,
    pub link: String,
    pub read: usize,
    pub written: usize,
    pub findings: Vec<Finding>,
    /// The link could not be opened.
    pub error: Option<String>,
}

impl AxisCheck {
    pub fn lines(&self) -> Vec<String> {
        if let Some(e) = &self.error {
            return vec![format!("live: axis {} (unit {}): {e}", self.axis, self.unit)];
        }
        let mut v = vec![format!(
            "live: axis {} (unit {}, {} map) on {}: {} register(s) read, {} written back{}",
            self.axis,
            self.unit,
            self.map,
            self.link,
            self.read,
            self.written,
            if self.findings.is_empty() { ", none failed".to_string() } else { format!(", {} failed:", self.findings.len()) }
        )];
        v.extend(self.findings.iter().map(|f| format!("  {}", f.line(self.map))));
        v
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "axis": self.axis, "unit": self.unit, "map": self.map, "link": self.link, "error": self.error,
            "read": self.read, "written": self.written,
            "failed": self.findings.iter().map(|f| serde_json::json!({
                "register": f.register.name, "address": f.register.addr, "len": f.register.len,
                "optional": f.register.optional, "what": f.what,
            })).collect::<Vec<_>>(),
        })
    }
}

fn registers(a: &AxisConfig) -> (&'static str, Vec<MapRegister>) {
    match a.modbus_profile {
        Profile::Cia402 => ("cia402", a.cia402_map.unwrap_or_default().registers()),
        Profile::Pr => ("pr", a.pr_map.unwrap_or_default().registers()),
    }
}

/// The value written back to `r`: what was read, except where writing it could start
/// something — the PR trigger and the alarm reset get 0 (no move, no reset), the CiA 402
/// mode the cyclic synchronous position mode `run` sets anyway (a drive may refuse its
/// power-on mode 0).
fn write_back(r: &MapRegister, read: Option<&[u16]>) -> Option<Vec<u16>> {
    match r.name {
        "trigger" | "alarm_reset" => Some(vec![0; r.len as usize]),
        "mode" => Some(vec![cncgw_bus::cia402::mode::CYCLIC_SYNC_POSITION as u16]),
        _ => read.map(<[u16]>::to_vec),
    }
}

/// Try every register of one axis.
fn check_axis(c: &mut Client, name: &str, a: &AxisConfig) -> AxisCheck {
    let (map, regs) = registers(a);
    let mut out = AxisCheck { axis: name.into(), unit: a.node, map, link: c.what.clone(), read: 0, written: 0, findings: Vec::new(), error: None };
    for r in regs {
        let finding = |what: String| Finding { axis: name.into(), unit: a.node, register: r, what };
        // The alarm reset is a command register: many drives cannot read it.
        let read = if r.name == "alarm_reset" { Ok(None) } else { c.read(a.node, r.addr, r.len).map(Some) };
        let read = match read {
            Ok(v) => {
                out.read += v.is_some() as usize;
                v
            }
            Err(e) => {
                // One line per register: a register that cannot be read is not written
                // either (cncgw writes back only what it read).
                let also = if r.writable { "; so not written back" } else { "" };
                out.findings.push(finding(format!("cannot read: {e}{also}")));
                continue;
            }
        };
        if !r.writable {
            continue;
        }
        if let Some(words) = write_back(&r, read.as_deref()) {
            match c.write(a.node, r.addr, &words) {
                Ok(()) => out.written += 1,
                Err(e) => out.findings.push(finding(format!("cannot write: {e}"))),
            }
        }
    }
    out
}

/// Every Modbus axis of `cfg`, on its link, in link and axis order.
pub fn check_live(cfg: &MachineConfig) -> Vec<AxisCheck> {
    let mut out = Vec::new();
    for (lname, link) in &cfg.modbus {
        let axes: Vec<_> = cfg.axes.iter().filter(|(_, a)| a.modbus.as_deref() == Some(lname.as_str())).collect();
        if axes.is_empty() {
            continue;
        }
        let mut client = match Client::connect(link) {
            Ok(c) => Some(c),
            Err(e) => {
                let e = format!("Modbus link {lname}: cannot open {}: {e}", link.describe());
                out.extend(axes.iter().map(|(n, a)| AxisCheck {
                    axis: (*n).clone(),
                    unit: a.node,
                    map: registers(a).0,
                    link: link.describe(),
                    read: 0,
                    written: 0,
                    findings: Vec::new(),
                    error: Some(e.clone()),
                }));
                None
            }
        };
        if let Some(c) = client.as_mut() {
            out.extend(axes.iter().map(|(n, a)| check_axis(c, n, a)));
        }
    }
    out
}

/// What the maps of `cfg` leave out (optional registers set to `"none"`), as `run` warns,
/// and a PR map whose `counts_per_rev` disagrees with the axis's scaling
/// (`travel_per_rev × counts_per_unit`, where given): the block's speeds would be off.
pub fn map_warnings(cfg: &MachineConfig) -> Vec<String> {
    let mut w = Vec::new();
    for (n, a) in cfg.axes.iter().filter(|(_, a)| a.modbus.is_some()) {
        let pr = a.pr_map.unwrap_or_default();
        w.extend(DrivePlan::new(n, a.node, a.modbus_profile, a.cia402_map.unwrap_or_default(), pr, false, 1).map_warnings());
        // A homing the map cannot carry: `cncgw home` refuses it (alarm 2017), said here first.
        if let (Profile::Cia402, Some(h)) = (a.modbus_profile, super::home::home_args(a)) {
            let missing = super::mbus::homing_missing(&a.cia402_map.unwrap_or_default(), &h, a.homing.as_ref().and_then(|c| c.accel));
            if !missing.is_empty() {
                w.push(format!(
                    "axis {n}: its homing (method {}) needs the {}, which its cia402_map does not have (\"none\" or not named): `cncgw home` refuses it (alarm 2017)",
                    h.method,
                    missing.join(", ")
                ));
            }
        }
        if let (Profile::Pr, Some(t)) = (a.modbus_profile, a.travel_per_rev) {
            let per_rev = t * a.counts_per_unit;
            if (per_rev / pr.counts_per_rev.max(1) as f64 - 1.0).abs() > 1e-3 {
                w.push(format!(
                    "axis {n}: pr_map.counts_per_rev = {} but travel_per_rev × counts_per_unit = {per_rev:.0}: the PR block's speeds would be off by {:.3}×; set counts_per_rev = {per_rev:.0}",
                    pr.counts_per_rev,
                    per_rev / pr.counts_per_rev.max(1) as f64
                ));
            }
        }
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn map_warnings_name_what_the_map_leaves_out_and_a_pr_scale_that_disagrees() {
        let text = include_str!("../../config/lathe-modbus.toml").replace(
            "node = 1                    # Modbus unit id",
            "node = 1\nmodbus_profile = \"pr\"\ntravel_per_rev = 5.0\npr_map = { comm_timeout_ms = \"none\" }",
        );
        let cfg = MachineConfig::from_toml("t", &text).unwrap();
        let w = map_warnings(&cfg);
        assert!(w.iter().any(|l| l.starts_with("axis x: the register map has no communication watchdog register")), "{w:?}");
        assert!(w.iter().any(|l| l.contains("axis x: pr_map.counts_per_rev = 100000 but travel_per_rev × counts_per_unit = 50000")), "{w:?}");
        assert_eq!(w.len(), 2, "{w:?}");
    }

    #[test]
    fn write_back_starts_nothing() {
        let m = cncgw_bus::modbus::PrMap::default().registers();
        let get = |n: &str| *m.iter().find(|r| r.name == n).unwrap();
        // The trigger and the alarm reset get 0 whatever was read: no move, no reset.
        assert_eq!(write_back(&get("trigger"), Some(&[0x10])), Some(vec![0]));
        assert_eq!(write_back(&get("alarm_reset"), None), Some(vec![0]));
        // The block goes back as it was read; nothing read, nothing written.
        assert_eq!(write_back(&get("block"), Some(&[1, 0, 5, 60, 100, 100, 0])), Some(vec![1, 0, 5, 60, 100, 100, 0]));
        assert_eq!(write_back(&get("servo_on"), None), None);
    }
}
