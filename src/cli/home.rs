//! `cncgw home [AXIS|all]`: reference return of the axes that have `homing = { … }` in the
//! configuration, in the drives' CiA 402 homing mode (6) — over CANopen through the master's
//! homing walk (0x6098 method, 0x607C offset, 0x6099 speeds, 0x609A acceleration, controlword
//! bit 4, statusword bits 10/12/13), over Modbus through `mbus::home_unit` — the same work as
//! `cncgw drive home NODE`, with the parameters from the configuration. An axis is written
//! referenced (`reference`) only once its drive reported homing attained; the axes about to
//! be homed lose their old reference first (an interrupted homing leaves them unreferenced).
//!
//! The reference file is part of the machine's state: every read-change-write of it holds
//! the state lock (`lock::state`, as `run` and `mdi` do for the whole run), so a `home` and
//! a run — or two `home`s, or a `drive home` and an `nmt reset-node` — of the same machine
//! never interleave their updates (one would write back a table read before the other's
//! change: a reference kept that was lost, or one lost that was won). `home` holds it from
//! before the first motion to the last write; a run holding it refuses `home`.

use super::exit;
use super::service::{confirm_motion, HomeArgs};
use super::MachineArgs;
use super::OrSetup;
use crate::config::{AxisConfig, MachineConfig};
use crate::drives::DriveBus;
use crate::reference::ReferenceFile;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
pub struct HomeCmd {
    /// The axis to home (x, z, …), or `all` (default): every axis with a homing method, in
    /// the configuration's order.
    #[arg(default_value = "all")]
    pub axis: String,
    /// Confirm the motion on a real bus.
    #[arg(long)]
    pub yes: bool,
    /// The state directory (the reference is kept there). Default: $CNCGW_STATE_DIR, else
    /// $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    #[command(flatten)]
    pub machine: MachineArgs,
}

/// The reference file of this machine on this bus, in `dir` (default state dir when None).
pub fn reference_file(cfg: &MachineConfig, machine: &MachineArgs, dir: Option<&Path>) -> Option<ReferenceFile> {
    state_place(cfg, machine, dir).map(|s| s.reference())
}

fn state_place(cfg: &MachineConfig, machine: &MachineArgs, dir: Option<&Path>) -> Option<crate::persist::StatePlace> {
    let root = dir.map(Path::to_path_buf).or_else(crate::persist::default_state_dir)?;
    Some(crate::persist::StatePlace::new(&root, &cfg.machine.name, &super::run::run_place(cfg, machine)))
}

/// The reference file with the machine's state lock held (see the module's doc); `wait`:
/// retry that long while another process holds it (a service command's short update).
fn locked_reference(
    cfg: &MachineConfig,
    machine: &MachineArgs,
    dir: Option<&Path>,
    wait: std::time::Duration,
) -> Option<Result<(ReferenceFile, super::lock::Lock), crate::Alarm>> {
    let st = state_place(cfg, machine, dir)?;
    let t0 = std::time::Instant::now();
    loop {
        match super::lock::state(&st.dir, &st.key) {
            Ok(l) => return Some(Ok((st.reference(), l))),
            Err(a) if t0.elapsed() >= wait => return Some(Err(a)),
            Err(_) => std::thread::sleep(std::time::Duration::from_millis(50)),
        }
    }
}

/// `homing` of an axis as `drive home`'s arguments.
pub fn home_args(a: &AxisConfig) -> Option<HomeArgs> {
    let h = a.homing.as_ref()?;
    Some(HomeArgs { method: h.method, switch_speed: h.speed, zero_speed: h.zero_speed, offset: h.offset, timeout: h.timeout_s.unwrap_or(30.0) })
}

/// The axes `which` names, each with its homing; Err = exit code (message printed).
fn select(cfg: &MachineConfig, which: &str) -> Result<Vec<(String, AxisConfig)>, i32> {
    let which = which.to_ascii_lowercase();
    if which == "all" {
        let v: Vec<_> = cfg.axes.iter().filter(|(_, a)| a.homing.is_some()).map(|(n, a)| (n.clone(), a.clone())).collect();
        if v.is_empty() {
            eprintln!("error: no axis of the configuration has a homing method: give one `homing = {{ method = 35, offset = 0.0 }}` in [axes.NAME] (or `absolute = true` for an absolute encoder)");
            return Err(exit::INPUT);
        }
        return Ok(v);
    }
    let Some(a) = cfg.axes.get(&which) else {
        let names: Vec<&str> = cfg.axes.keys().map(String::as_str).collect();
        eprintln!("error: no axis {which} in the configuration (axes: {})", names.join(", "));
        return Err(exit::INPUT);
    };
    if a.absolute {
        println!("axis {}: absolute encoder, referenced at power-on; nothing to home", which.to_uppercase());
        return Ok(Vec::new());
    }
    if a.homing.is_none() {
        eprintln!("error: axis {which} has no homing method: give it `homing = {{ method = 35, offset = 0.0 }}` in [axes.{which}] (35 = the present position is home)");
        return Err(exit::INPUT);
    }
    Ok(vec![(which, a.clone())])
}

/// `cncgw home`.
pub fn home(c: &HomeCmd) -> i32 {
    let (cfg, _) = match super::machine_config(&c.machine).or_setup() {
        Ok(x) => x,
        Err(code) => return code,
    };
    let axes = match select(&cfg, &c.axis) {
        Ok(v) if v.is_empty() => return exit::OK,
        Ok(v) => v,
        Err(code) => return code,
    };
    let _bus_lock = match super::lock::for_writing(&c.machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    // The state lock before anything moves: a run of this machine refuses the homing.
    let (file, _state_lock) = match locked_reference(&cfg, &c.machine, c.state_dir.as_deref(), std::time::Duration::ZERO) {
        Some(Ok(f)) => f,
        Some(Err(a)) => {
            eprintln!("{a}");
            eprintln!("nothing was moved");
            return exit::SETUP;
        }
        None => {
            eprintln!("error: no state directory (set $CNCGW_STATE_DIR or give --state-dir): the reference could not be kept");
            return exit::SETUP;
        }
    };
    let names: Vec<String> = axes.iter().map(|(n, _)| n.to_uppercase()).collect();
    if let Err(code) = confirm_motion(&c.machine, c.yes, &format!("homing axis {}", names.join(", "))) {
        return code;
    }
    // Homing moves the axes and resets their coordinates: the old reference is void from here.
    if let Err(a) = file.update(|t| {
        for (n, _) in &axes {
            t.axes.remove(n);
        }
    }) {
        eprintln!("{a}");
        return exit::SETUP;
    }
    let (bus_axes, modbus_axes): (Vec<_>, Vec<_>) = axes.into_iter().partition(|(_, a)| a.modbus.is_none());
    let mut homed: Vec<(String, u8, i8, f64)> = Vec::new();
    let mut failed = false;
    for (n, a) in &modbus_axes {
        let h = home_args(a).expect("selected axes have homing");
        match super::mbus::home_unit(&cfg, a.node, &h) {
            Ok(pos) => homed.push((n.clone(), a.node, h.method, pos)),
            Err(_) => failed = true,
        }
    }
    if !bus_axes.is_empty() {
        match home_canopen(&c.machine, &bus_axes, &mut homed) {
            Ok(ok) => failed |= !ok,
            Err(code) => return code,
        }
    }
    if let Err(a) = file.update(|t| {
        for (n, node, method, pos) in &homed {
            t.set_homed(n, *node, *method, *pos);
        }
    }) {
        eprintln!("{a}");
        return exit::SETUP;
    }
    for (n, _, method, pos) in &homed {
        println!("axis {}: referenced (homing method {method}), position {pos:.4}", n.to_uppercase());
    }
    if failed {
        exit::NOT_MET
    } else {
        exit::OK
    }
}

/// Home the CANopen axes in one session (start-up, each axis in turn, shutdown); the homed
/// ones are pushed to `homed`. Ok(false) when one failed (said); Err = exit code at setup.
fn home_canopen(machine: &MachineArgs, axes: &[(String, AxisConfig)], homed: &mut Vec<(String, u8, i8, f64)>) -> Result<bool, i32> {
    let mut s = super::open_session(machine).map_err(|e| {
        eprintln!("error: {e}");
        exit::SETUP
    })?;
    if let Err(a) = DriveBus::startup(&mut s.master, &mut *s.clock) {
        DriveBus::shutdown(&mut s.master, &mut *s.clock);
        eprintln!("{a}");
        return Err(exit::NOT_MET);
    }
    let mut ok = true;
    for (n, a) in axes {
        let h = home_args(a).expect("selected axes have homing");
        let r = super::service::home_node(&mut s, a.node, &h).and_then(|()| {
            let cpu = a.counts_per_unit;
            s.master
                .sdo_upload(&mut *s.clock, a.node, cncgw_bus::canopen::od::POSITION_ACTUAL, 0)
                .map_err(|e| format!("node {}: reading the position 0x6064 failed: {}", a.node, super::diag::sdo_error_text(&e)))
                .map(|d| i32::from_le_bytes([d[0], d[1], d[2], d[3]]) as f64 / cpu)
        });
        match r {
            Ok(pos) => homed.push((n.clone(), a.node, h.method, pos)),
            Err(e) => {
                eprintln!("error: axis {}: {e}", n.to_uppercase());
                ok = false;
                break;
            }
        }
    }
    DriveBus::shutdown(&mut s.master, &mut *s.clock);
    Ok(ok)
}

/// How long a service command waits for another process's short reference update.
const SERVICE_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// After `cncgw drive home NODE`: the axis of that drive is referenced (with the method the
/// command used), kept in the default state directory.
pub fn record_drive_home(machine: &MachineArgs, axis: &str, node: u8, method: i8, pos: f64) {
    let Ok((cfg, _)) = super::machine_config(machine) else { return };
    match locked_reference(&cfg, machine, None, SERVICE_WAIT) {
        Some(Ok((f, _lock))) => {
            if let Err(a) = f.update(|t| t.set_homed(axis, node, method, pos)) {
                eprintln!("warning: {a}");
            }
        }
        Some(Err(a)) => eprintln!("warning: axis {} homed but not recorded referenced: {a}", axis.to_uppercase()),
        None => {}
    }
}

/// After `cncgw nmt reset-node` to `node` (0 = every node): the drives restarted their
/// application, so the axes on them lose their reference.
pub fn record_reset(machine: &MachineArgs, node: u8) {
    let Ok((cfg, _)) = super::machine_config(machine) else { return };
    // The run that holds the state sees the boot-up itself and drops the reference at its end.
    let (f, _lock) = match locked_reference(&cfg, machine, None, SERVICE_WAIT) {
        Some(Ok(f)) => f,
        Some(Err(a)) => {
            eprintln!("warning: the reference of the reset drives could not be dropped now: {a}");
            return;
        }
        None => return,
    };
    let axes: Vec<String> = cfg.axes.iter().filter(|(_, a)| a.modbus.is_none() && (node == 0 || a.node == node)).map(|(n, _)| n.clone()).collect();
    let r = f.update(|t| {
        for a in &axes {
            if let Some(note) = t.lose(a, "NMT reset node restarted its drive") {
                eprintln!("cncgw: {note}");
            }
        }
    });
    if let Err(a) = r {
        eprintln!("warning: {a}");
    }
}
