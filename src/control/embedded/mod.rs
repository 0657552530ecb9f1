//! The embedded machine: sim-drives' emulated CANopen drives on an in-process bus, in
//! simulated time (`--bus inproc`, the default of the shipped config), and the measurement
//! harnesses built on it. The only module of the core that names `sim_drives`; a build
//! without the `embedded` feature (`cargo build --no-default-features`) leaves the
//! emulator out and `--bus inproc` is refused.

pub mod matrix;
pub mod measure;

use cncgw_bus::transport::inproc::InprocBus;

/// The emulated drives of `cfg` (or of the sim-drives config `sim`) on a fresh in-process
/// bus: the master's endpoint and the emulator, which is the run's (simulated) clock.
pub fn open(cfg: &crate::config::MachineConfig, cfg_text: &str, sim: Option<&std::path::Path>) -> Result<super::BusClock, String> {
    let sim_cfg = emulated_drives(cfg, cfg_text, sim)?;
    let wire = InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim_cfg);
    // The machine's CiA 401 I/O modules, emulated as `[io.devices.*.emulate]` says.
    for m in sim_drives::io401::from_machine_toml(cfg_text).map_err(|e| format!("emulated I/O: {e}"))?.0 {
        world.add_io_module(m);
    }
    Ok((Box::new(wire.endpoint()), Box::new(world)))
}

/// The emulated drives of the embedded machine: sim-drives' defaults for the machine's
/// CANopen axes, or the sim-drives configuration `sim` (another drive model), which must
/// have the machine's CANopen nodes with the same kinds and counts per unit.
pub fn emulated_drives(cfg: &crate::config::MachineConfig, cfg_text: &str, sim: Option<&std::path::Path>) -> Result<sim_drives::SimConfig, String> {
    let Some(path) = sim else {
        return sim_drives::SimConfig::from_machine_toml_bus(cfg_text, Some(false)).map_err(|e| format!("emulated drives: {e}"));
    };
    let text = std::fs::read_to_string(path).map_err(|e| format!("--sim-config {}: {e}", path.display()))?;
    let sim_cfg = sim_drives::SimConfig::from_toml(&text).map_err(|e| format!("--sim-config {}: {e}", path.display()))?;
    let mut errs = Vec::new();
    for (name, a) in cfg.axes.iter().filter(|(_, a)| a.modbus.is_none()) {
        let kind = match a.kind {
            crate::config::AxisKind::Linear => sim_drives::DriveKind::Linear,
            crate::config::AxisKind::Spindle => sim_drives::DriveKind::Spindle,
        };
        match sim_cfg.drives.iter().find(|d| d.node == a.node) {
            None => errs.push(format!("axis {name} is node {} in the machine, and no drive of the emulated ones has that node", a.node)),
            Some(d) if d.kind != kind => {
                errs.push(format!("axis {name} (node {}) is {:?} in the machine, {} in the emulated drives", a.node, a.kind, d.kind.name()))
            }
            // A drive with a `[drive.shape]` is there to try start-up's own checks (its
            // scaling against counts_per_unit is alarm 2006, with the value that matches):
            // its scaling is not refused here.
            Some(d)
                if d.shape == sim_drives::config::Shape::default()
                    && (d.counts_per_unit - a.counts_per_unit).abs() > 1e-9 * a.counts_per_unit.abs().max(1.0) =>
            {
                errs.push(format!(
                    "axis {name} (node {}): counts_per_unit {} in the machine, {} in the emulated drives",
                    a.node, a.counts_per_unit, d.counts_per_unit
                ))
            }
            Some(_) => {}
        }
    }
    for d in &sim_cfg.drives {
        if !cfg.axes.values().any(|a| a.modbus.is_none() && a.node == d.node) {
            errs.push(format!("emulated drive node {} ({}) is not an axis of the machine", d.node, d.axis));
        }
    }
    if errs.is_empty() {
        Ok(sim_cfg)
    } else {
        Err(format!("--sim-config {} does not fit the machine: {}", path.display(), errs.join("; ")))
    }
}
