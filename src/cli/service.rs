//! Service commands that change a drive's state or move an axis: `drive enable|disable|
//! fault-reset|home`, `jog`; and the bus tools `buslog` and `monitor`.
//!
//! Anything that can set a motor in motion (enable, home, jog, tap-test) on a real bus —
//! anything but `inproc` — needs `--yes`, or the operator's typed `yes` on a terminal; it is
//! refused before the bus is opened (as `sdo write` does).

use super::diag::sdo_error_text;
use super::exit;
use super::OrSetup;
use super::{load_config, open_service_bus, open_service_bus_with, MachineArgs, ServiceBus, Session};
pub use crate::drives::access::PowerGoal;
use crate::drives::access::{self, DriveAccess, DriveStatus, ObjType};
use crate::drives::DriveBus;
use cncgw_bus::canopen::emcy::error_text;
use cncgw_bus::canopen::od;
use cncgw_bus::cia402::{mode, State};
use cncgw_bus::{BusError, CanBus, CanFrame};
use std::io::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

const MS: u64 = 1_000_000;

/// The bus(es) the command will use, in words — `--bus`, else the config's CANopen interface
/// (if an axis is on it) and its Modbus links ("Modbus link tcp (Modbus TCP 10.0.0.9:502)")
/// — and whether that is the embedded emulated bus alone (nothing real can move).
fn effective_bus(machine: &MachineArgs) -> Result<(String, bool), String> {
    if let Some(b) = &machine.bus {
        return Ok((b.clone(), matches!(machine.bus_kind(), Ok(Some(super::BusKind::Inproc)))));
    }
    let (c, _) = load_config(machine.config.as_deref())?;
    let mut on: Vec<String> = Vec::new();
    if c.has_canopen() {
        on.push(c.bus.interface.clone());
    }
    for (name, l) in &c.modbus {
        if c.axes.values().any(|a| a.modbus.as_deref() == Some(name.as_str())) {
            on.push(format!("Modbus link {name} ({})", l.describe()));
        }
    }
    let embedded = (on.is_empty() || (on.len() == 1 && c.has_canopen())) && machine.on_embedded_bus(&c);
    Ok((if on.is_empty() { c.bus.interface } else { on.join(" and ") }, embedded))
}

/// On a real bus, `what` goes ahead only with `--yes` or, on a terminal, after the operator
/// types `yes`; without a terminal it is refused. Err = the exit code (message printed).
pub(crate) fn confirm_motion(machine: &MachineArgs, yes: bool, what: &str) -> Result<(), i32> {
    use std::io::{BufRead, IsTerminal};
    let (bus, embedded) = effective_bus(machine).map_err(|e| {
        eprintln!("error: {e}");
        exit::SETUP
    })?;
    if embedded || yes {
        return Ok(());
    }
    if std::io::stdin().is_terminal() && std::io::stderr().is_terminal() {
        eprint!("{what} can set a motor in motion on {bus}. Is the axis free to move and nobody near it? Type yes to go on: ");
        let _ = std::io::stderr().flush();
        let mut answer = String::new();
        let _ = std::io::stdin().lock().read_line(&mut answer);
        if answer.trim().eq_ignore_ascii_case("yes") {
            return Ok(());
        }
        eprintln!("not confirmed: nothing was moved");
        return Err(exit::INPUT);
    }
    eprintln!("error: {what} can set a motor in motion on {bus}; make sure the axis is free to move and nobody is near it, then repeat with --yes");
    Err(exit::INPUT)
}

/// Read a signed integer object of `n` bytes (sign-extended).
fn read_int(s: &mut Session, node: u8, index: u16, n: usize) -> Result<i64, String> {
    let d = s.master.sdo_upload(&mut *s.clock, node, index, 0).map_err(|e| sdo_error_text(&e))?;
    if d.len() < n || n == 0 || n > 8 {
        return Err(format!("0x{index:04X} answered {} byte(s), expected {n}", d.len()));
    }
    let mut b = [0u8; 8];
    b[..n].copy_from_slice(&d[..n]);
    let shift = 64 - 8 * n as u32;
    Ok(((u64::from_le_bytes(b) << shift) as i64) >> shift)
}

fn read_statusword(s: &mut Session, node: u8) -> Result<u16, String> {
    read_int(s, node, od::STATUSWORD, 2)
        .map(|v| v as u16)
        .map_err(|e| format!("node {node}: reading the statusword 0x6041 failed: {e}; is it a CiA 402 drive? `cncgw scan` shows what answers"))
}

/// The drive's error code 0x603F in words, for messages.
fn error_code_text(s: &mut Session, node: u8) -> String {
    match read_int(s, node, od::ERROR_CODE, 2) {
        Ok(c) => format!("0x603F error code 0x{:04X} {}", c as u16, error_text(c as u16)),
        Err(e) => format!("0x603F unreadable ({e})"),
    }
}

/// Walk `node` towards `goal` over SDO (0x6041 read, 0x6040 written): `drives::access`'s
/// walk, the same for every bus. Returns (state before, state reached).
pub fn power_walk(s: &mut Session, node: u8, goal: PowerGoal, timeout_ms: u64) -> Result<(State, State), String> {
    access::power_walk(&mut SdoDrive::new(s, node), goal, timeout_ms)
}

/// A CANopen drive's objects by SDO (SocketCAN, socketcand or the embedded emulator).
pub struct SdoDrive<'a> {
    pub s: &'a mut Session,
    pub node: u8,
}

impl<'a> SdoDrive<'a> {
    pub fn new(s: &'a mut Session, node: u8) -> SdoDrive<'a> {
        s.master.ensure_node(node);
        SdoDrive { s, node }
    }
}

impl DriveAccess for SdoDrive<'_> {
    fn noun(&self) -> &'static str {
        "node"
    }
    fn id(&self) -> u8 {
        self.node
    }
    fn label(&self) -> String {
        let axis = self.s.master.node_spec(self.node).map(|n| format!(" (axis {})", n.axis)).unwrap_or_default();
        format!("node {}{axis}", self.node)
    }
    fn axis(&self) -> Option<(String, f64, bool)> {
        self.s.master.node_spec(self.node).map(|n| (n.axis.clone(), n.counts_per_unit, n.spindle))
    }
    fn read(&mut self, index: u16, sub: u8, ty: ObjType) -> Result<i64, String> {
        let n = ty.bytes();
        let d = self.s.master.sdo_upload(&mut *self.s.clock, self.node, index, sub).map_err(|e| sdo_error_text(&e))?;
        if d.len() < n {
            return Err(format!("0x{index:04X} answered {} byte(s), expected {n}", d.len()));
        }
        let mut b = [0u8; 8];
        b[..n].copy_from_slice(&d[..n]);
        Ok(ty.extend(u64::from_le_bytes(b)))
    }
    fn write(&mut self, index: u16, sub: u8, ty: ObjType, value: i64) -> Result<(), String> {
        let b = value.to_le_bytes();
        self.s.master.sdo_download(&mut *self.s.clock, self.node, index, sub, &b[..ty.bytes()]).map_err(|e| sdo_error_text(&e))
    }
    fn statusword(&mut self) -> Result<u16, String> {
        read_statusword(self.s, self.node)
    }
    fn controlword(&mut self, c: u16) -> Result<(), String> {
        self.write(od::CONTROLWORD, 0, ObjType::U16, c as i64)
            .map_err(|e| format!("node {}: writing the controlword 0x6040 = 0x{c:04X} failed: {e}", self.node))
    }
    fn error_text(&mut self) -> String {
        error_code_text(self.s, self.node)
    }
    fn now_ns(&mut self) -> u64 {
        self.s.clock.now_ns()
    }
    fn wait_ns(&mut self, t: u64) {
        self.s.clock.wait_until(t)
    }
}

/// `cncgw drive enable|disable|fault-reset NODE`: the same walk for every bus.
pub fn drive_power(machine: &MachineArgs, node: u8, goal: PowerGoal, yes: bool) -> i32 {
    let _bus_lock = match super::lock::for_writing(machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    if goal == PowerGoal::Enable {
        if let Err(c) = confirm_motion(machine, yes, &format!("enabling node {node}")) {
            return c;
        }
    }
    let mut s = match open_service_bus(machine) {
        Ok(ServiceBus::Modbus(cfg)) => {
            return match super::mbus::ModbusDrive::open(&cfg, node) {
                Ok(mut d) => power_report(&mut d, goal),
                Err(code) => code,
            }
        }
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let simulated = s.simulated;
    let code = power_report(&mut SdoDrive::new(&mut s, node), goal);
    if code == exit::OK && simulated {
        println!("  (embedded emulated drives: they start fresh with every command)");
    }
    code
}

/// Walk `d` to `goal` and say what happened.
fn power_report(d: &mut dyn DriveAccess, goal: PowerGoal) -> i32 {
    match access::power_walk(d, goal, 2000) {
        Ok((from, to)) => {
            let sw = match d.status_register() {
                Some((what, v)) => format!(" ({what} 0x{v:04X})"),
                None => d.statusword().map(|w| format!(" (statusword 0x{w:04X})")).unwrap_or_default(),
            };
            let label = d.label();
            if from == to {
                let why = if goal == PowerGoal::FaultReset { "not in fault, nothing to reset" } else { "already there" };
                println!("{label}: {}{sw}; {why}", to.name());
            } else {
                println!("{label}: {} → {}{sw}", from.name(), to.name());
            }
            if goal == PowerGoal::Enable {
                match d.read(od::MODES_DISPLAY, 0, ObjType::I8) {
                    Ok(m) => println!("  mode {m} ({}): the drive holds its position until it gets a set-point", mode::name(m as i8)),
                    Err(_) if d.status_register().is_some() => println!("  servo on: the drive holds its position until a PR block is triggered"),
                    Err(_) => {}
                }
                if d.noun() == "unit" {
                    println!("  communication watchdog off: the controller sets it again when it starts");
                }
            }
            exit::OK
        }
        Err(e) => {
            eprintln!("error: {e}");
            exit::NOT_MET
        }
    }
}

// ---------------------------------------------------------------- home and jog

/// Speeds on the command line are per minute for linear axes (mm/min, like F) and rpm for a
/// spindle; the master takes units/s (mm/s, degrees/s).
fn per_s(spindle: bool, v: f64) -> f64 {
    if spindle {
        v * 6.0
    } else {
        v / 60.0
    }
}

/// Start the configured drives (configuration, NMT start), run `f`, read back the node's
/// position (machine units) and shut down in order (drives disabled, heartbeat released).
fn with_started(s: &mut Session, node: u8, f: impl FnOnce(&mut Session) -> Result<(), crate::Alarm>) -> Result<f64, String> {
    let cpu = s.master.node_spec(node).map(|n| n.counts_per_unit).unwrap_or(1.0);
    if let Err(a) = DriveBus::startup(&mut s.master, &mut *s.clock) {
        // Drives configured before the failure must not go on expecting our heartbeat.
        DriveBus::shutdown(&mut s.master, &mut *s.clock);
        return Err(a.to_string());
    }
    let r = f(s);
    let pos = read_int(s, node, od::POSITION_ACTUAL, 4);
    DriveBus::shutdown(&mut s.master, &mut *s.clock);
    r.map_err(|a| a.to_string())?;
    pos.map(|c| c as f64 / cpu).map_err(|e| format!("node {node}: reading the position 0x6064 failed: {e}"))
}

/// The homing methods CiA 402 defines (the drive refuses those it has not: 0x6098's abort).
pub fn parse_method(s: &str) -> Result<i8, String> {
    match s.trim().parse::<i8>() {
        Ok(m) if crate::config::homing_method_defined(m) => Ok(m),
        _ => Err(format!(
            "homing method {s} is not a CiA 402 method: 35 or 37 (here), 17 / 18 (negative / positive limit switch), 1–14 (switches and index pulse), 33 / 34 (index pulse); the drive's manual says which it has"
        )),
    }
}

/// Homing parameters of `cncgw drive home`.
#[derive(clap::Args, Debug, Clone)]
pub struct HomeArgs {
    /// Homing method (0x6098): 35 or 37 = the present position becomes home, 17 / 18 =
    /// search the negative / positive limit switch.
    #[arg(long, default_value_t = 35, value_parser = parse_method)]
    pub method: i8,
    /// Speed searching the switch (0x6099:1): mm/min (rpm for a spindle). Default: 1/20 of
    /// the axis's max_speed.
    #[arg(long, value_name = "SPEED")]
    pub switch_speed: Option<f64>,
    /// Speed leaving the switch (0x6099:2). Default: 1/100 of max_speed.
    #[arg(long, value_name = "SPEED")]
    pub zero_speed: Option<f64>,
    /// Home offset (0x607C) in machine units: the position the home point gets.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0.0)]
    pub offset: f64,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 30.0)]
    pub timeout: f64,
}

/// `cncgw drive home NODE`.
pub fn drive_home(machine: &MachineArgs, node: u8, h: &HomeArgs, yes: bool) -> i32 {
    let _bus_lock = match super::lock::for_writing(machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    if let Err(c) = confirm_motion(machine, yes, &format!("homing node {node}")) {
        return c;
    }
    let mut s = match open_service_bus(machine) {
        Ok(ServiceBus::Modbus(cfg)) => return super::mbus::drive_home(&cfg, node, h),
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let Some(spec) = s.master.node_spec(node).cloned() else {
        eprintln!("error: node {node} is not a drive of the configuration; homing needs its scaling (`cncgw config check` lists the axes)");
        return exit::INPUT;
    };
    if let Err(e) = home_params(&s, node, h) {
        eprintln!("error: {e}");
        return exit::INPUT;
    }
    let method = h.method;
    let r = with_started(&mut s, node, |s| home_node(s, node, h).map_err(|e| crate::Alarm::new(crate::alarm::HOMING, e)));
    match r {
        Ok(pos) => {
            println!(
                "node {node} (axis {}): homed with method {method}; position now {pos:.4} {}",
                spec.axis,
                if spec.spindle { "deg" } else { "mm" }
            );
            super::home::record_drive_home(machine, &spec.axis, node, method, pos);
            exit::OK
        }
        Err(e) => {
            eprintln!("error: {e}");
            exit::NOT_MET
        }
    }
}

/// A homing in the drive's units, the same figures on every bus: switch and zero speed
/// (units/s; degrees/s for a spindle), acceleration (units/s², degrees/s²), home offset
/// (counts). Speeds default to max_speed / 20 and / 100, the acceleration to
/// `homing.accel`, else max_accel.
pub struct HomingFigures {
    pub switch_speed: f64,
    pub zero_speed: f64,
    pub accel: f64,
    pub offset: i32,
}

/// `h` on axis `ax` as its `HomingFigures`; Err: the offset is out of the drive's range.
pub fn homing_figures(ax: &crate::config::AxisConfig, h: &HomeArgs) -> Result<HomingFigures, String> {
    let spindle = ax.kind == crate::config::AxisKind::Spindle;
    let accel = ax.homing.as_ref().and_then(|c| c.accel).unwrap_or(ax.max_accel);
    let offset = (h.offset * ax.counts_per_unit).round();
    if !offset.is_finite() || offset.abs() > i32::MAX as f64 {
        return Err(format!("home offset {} is out of the drive's range", h.offset));
    }
    Ok(HomingFigures {
        switch_speed: per_s(spindle, h.switch_speed.unwrap_or(ax.max_speed / 20.0)),
        zero_speed: per_s(spindle, h.zero_speed.unwrap_or(ax.max_speed / 100.0)),
        accel: if spindle { accel * 6.0 } else { accel },
        offset: offset as i32,
    })
}

/// `--timeout` (seconds) in ms, checked.
pub fn home_timeout_ms(h: &HomeArgs) -> Result<u64, String> {
    if !(h.timeout.is_finite() && h.timeout > 0.0) {
        return Err("--timeout must be a positive number of seconds".into());
    }
    Ok((h.timeout * 1000.0) as u64)
}

/// The homing of `node` in the master's units and its timeout (ms).
fn home_params(s: &Session, node: u8, h: &HomeArgs) -> Result<(HomingFigures, u64), String> {
    let spec = s.master.node_spec(node).ok_or_else(|| format!("node {node} is not a drive of the configuration"))?;
    let ax = s.cfg.axes.get(&spec.axis).ok_or_else(|| format!("axis {} is not in the configuration", spec.axis))?;
    let f = homing_figures(ax, h)?;
    Ok((f, home_timeout_ms(h)?))
}

/// Home `node` of a started session (0x607C written, then the master's homing walk).
pub fn home_node(s: &mut Session, node: u8, h: &HomeArgs) -> Result<(), String> {
    let (f, timeout_ms) = home_params(s, node, h)?;
    s.master.sdo_write(&mut *s.clock, node, 0x607C, 0, &f.offset.to_le_bytes()).map_err(|a| a.to_string())?;
    s.master.home(&mut *s.clock, node, h.method, f.switch_speed, f.zero_speed, f.accel, timeout_ms).map_err(|a| a.to_string())
}

/// `cncgw jog AXIS --to POS | --by DIST`.
pub fn jog(machine: &MachineArgs, axis: &str, to: Option<f64>, by: Option<f64>, speed: Option<f64>, yes: bool) -> i32 {
    let _bus_lock = match super::lock::for_writing(machine) {
        Ok(l) => l,
        Err(code) => return code,
    };
    if let Err(c) = confirm_motion(machine, yes, &format!("jogging axis {axis}")) {
        return c;
    }
    let mut s = match open_service_bus(machine) {
        Ok(ServiceBus::Modbus(cfg)) => return jog_program(machine, &cfg, axis, to, by, speed),
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let Some(ax) = s.cfg.axes.get(axis).cloned() else {
        let names: Vec<&str> = s.cfg.axes.keys().map(String::as_str).collect();
        eprintln!("error: no axis `{axis}` in the configuration (axes: {})", names.join(", "));
        return exit::INPUT;
    };
    if ax.modbus.is_some() {
        match super::machine_config(machine) {
            Ok((cfg, _)) => return jog_program(machine, &cfg, axis, to, by, speed),
            Err(e) => {
                eprintln!("error: {e}");
                return exit::SETUP;
            }
        }
    }
    let node = ax.node;
    let Some(spec) = s.master.node_spec(node).cloned() else {
        eprintln!("error: axis {axis} (node {node}) is not a CANopen drive of the configuration");
        return exit::SETUP;
    };
    let unit = if spec.spindle { "deg" } else { "mm" };
    let speed = speed.unwrap_or(ax.max_speed / 10.0);
    if !(speed.is_finite() && speed > 0.0 && speed <= ax.max_speed) {
        eprintln!("error: --speed {speed} must be above 0 and at most the axis's max_speed {}", ax.max_speed);
        return exit::INPUT;
    }
    let start = match read_int(&mut s, node, od::POSITION_ACTUAL, 4) {
        Ok(c) => c as f64 / spec.counts_per_unit,
        Err(e) => {
            eprintln!("error: node {node}: reading the position 0x6064 failed: {e}");
            return exit::NOT_MET;
        }
    };
    let target = match (to, by) {
        (Some(t), None) => t,
        (None, Some(d)) => start + d,
        _ => {
            eprintln!("error: give exactly one of --to POS and --by DIST");
            return exit::INPUT;
        }
    };
    if !target.is_finite() {
        eprintln!("error: the target is not a number");
        return exit::INPUT;
    }
    if !spec.spindle {
        if let (Some(lo), Some(hi)) = (spec.min, spec.max) {
            if target < lo || target > hi {
                eprintln!("error: {target} {unit} is outside axis {axis}'s travel {lo} … {hi} {unit} (axes.{axis}.min/max)");
                return exit::INPUT;
            }
        }
    }
    let v = per_s(spec.spindle, speed);
    let a = if spec.spindle { ax.max_accel * 6.0 } else { ax.max_accel };
    match with_started(&mut s, node, |s| s.master.profile_move(&mut *s.clock, node, target, v, a)) {
        Ok(pos) => {
            println!("axis {axis} (node {node}): {start:.4} → {pos:.4} {unit} (target {target:.4})");
            exit::OK
        }
        Err(e) => {
            eprintln!("error: {e}");
            exit::NOT_MET
        }
    }
}

/// Jog through the controller itself: a one-block program (`G98 G1 X|Z… F…`) run by the
/// cycle loop on the machine's drives — how an axis on a Modbus link moves (Modbus has no
/// profile position mode the master could hand the move to). Linear axes only.
fn jog_program(machine: &MachineArgs, cfg: &crate::config::MachineConfig, axis: &str, to: Option<f64>, by: Option<f64>, speed: Option<f64>) -> i32 {
    use crate::canon::Pos;
    let Some(ax) = cfg.axes.get(axis).cloned() else {
        let names: Vec<&str> = cfg.axes.keys().map(String::as_str).collect();
        eprintln!("error: no axis `{axis}` in the configuration (axes: {})", names.join(", "));
        return exit::INPUT;
    };
    if !matches!(axis, "x" | "z") || ax.kind != crate::config::AxisKind::Linear {
        eprintln!("error: axis {axis}: a jog through the controller moves X or Z; turn a spindle with a program (M03 S…)");
        return exit::INPUT;
    }
    let speed = speed.unwrap_or(ax.max_speed / 10.0);
    if !(speed.is_finite() && speed > 0.0 && speed <= ax.max_speed) {
        eprintln!("error: --speed {speed} must be above 0 and at most the axis's max_speed {}", ax.max_speed);
        return exit::INPUT;
    }
    let from = std::cell::Cell::new(None::<f64>);
    let target = std::cell::Cell::new(None::<f64>);
    let job = super::run::Job {
        name: format!("jog {axis}"),
        source: String::new(),
        first: None,
        make: Box::new(|start: Pos| {
            let here = if axis == "x" { start.x } else { start.z };
            from.set(Some(here));
            let t = match (to, by) {
                (Some(t), None) => t,
                (None, Some(d)) => here + d,
                _ => f64::NAN,
            };
            let bad = |m: String| Err(vec![crate::Alarm::new(super::taptest::ALARM_TAP_PLAN, m)]);
            if !t.is_finite() {
                return bad("give exactly one of --to POS and --by DIST".into());
            }
            if ax.min.is_some_and(|lo| t < lo) || ax.max.is_some_and(|hi| t > hi) {
                return bad(format!("{t} mm is outside axis {axis}'s travel {:?} … {:?} mm (axes.{axis}.min/max)", ax.min, ax.max));
            }
            target.set(Some(t));
            let word = if axis == "x" { format!("X{:.4}", t * 2.0) } else { format!("Z{t:.4}") };
            crate::interp::Interpreter::from_source("jog.nc", &format!("G21\nG98\nG1 {word} F{speed}\nM30\n"), cfg)
        }),
        feed: None,
    };
    let opts = super::run::ExecOpts { print_summary: false, ..Default::default() };
    let (code, _, summary) = super::run::run_job(cfg, "", machine, job, &opts);
    let end = summary.axes.iter().find(|a| a.name == axis).map(|a| a.final_actual_counts as f64 / a.counts_per_unit);
    match (code, from.get(), target.get(), end) {
        (0, Some(f), Some(t), Some(e)) => {
            println!("axis {axis} (unit {}): {f:.4} → {e:.4} mm (target {t:.4})", ax.node);
            exit::OK
        }
        (0, ..) => exit::NOT_MET,
        (c, ..) => c,
    }
}

// ---------------------------------------------------------------- buslog

/// Seconds an `inproc` log or monitor lasts without `--seconds` (simulated time has no
/// operator to press Ctrl-C at the right moment).
const INPROC_DEFAULT_S: f64 = 5.0;

fn unix_us() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_micros() as u64).unwrap_or(0)
}

/// `cncgw buslog -o FILE [--seconds N]`: every frame on the bus, candump log format.
pub fn buslog(machine: &MachineArgs, out: &std::path::Path, seconds: Option<f64>) -> i32 {
    if let Some(n) = seconds {
        if !(n.is_finite() && n > 0.0) {
            eprintln!("error: --seconds must be a positive number");
            return exit::INPUT;
        }
    }
    let (cfg, text) = match load_config(machine.config.as_deref()).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    let (mut bus, mut clock, name, what) = match super::open_raw(&cfg, &text, machine.bus.as_deref(), machine.sim_config.as_deref()).or_setup() {
        Ok(b) => b,
        Err(code) => return code,
    };
    let file = match std::fs::File::create(out) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("error: {}: cannot create: {e}", out.display());
            return exit::SETUP;
        }
    };
    let mut w = std::io::BufWriter::new(file);
    let simulated = clock.is_simulated();
    // candump's interface column: the SocketCAN name, or the socketcand interface.
    let iface = if simulated {
        "inproc".to_string()
    } else {
        cncgw_bus::transport::socketcand::parse_url(&name).map(|(_, i)| i).unwrap_or_else(|| name.clone())
    };
    let seconds = seconds.or(simulated.then_some(INPROC_DEFAULT_S));
    let t0 = clock.now_ns();
    let unix0 = unix_us();
    let end = seconds.map(|s| t0 + (s * 1e9) as u64);
    eprintln!(
        "logging {what} to {}{}",
        out.display(),
        match seconds {
            Some(s) => format!(" for {s} s"),
            None => " until interrupted (Ctrl-C)".into(),
        }
    );
    let mut frames = 0u64;
    let mut last_flush = clock.now_ns();
    loop {
        let now = clock.now_ns();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        let got = if simulated {
            match bus.try_recv() {
                Ok(None) => {
                    // Nothing pending: let the emulated drives run 1 ms.
                    clock.wait_until(now + MS);
                    continue;
                }
                r => r,
            }
        } else {
            let left = end.map(|e| e.saturating_sub(now)).unwrap_or(u64::MAX).min(100 * MS);
            bus.recv_timeout(Duration::from_nanos(left))
        };
        let f = match got {
            Ok(Some(f)) => f,
            Ok(None) => {
                // Idle bus: what is buffered goes to the file (Ctrl-C loses nothing old).
                if !simulated {
                    if let Err(e) = w.flush() {
                        eprintln!("error: {}: cannot write: {e}", out.display());
                        return exit::SETUP;
                    }
                }
                continue;
            }
            Err(e) => {
                let _ = w.flush();
                eprintln!("error: reading {name}: {e}");
                return exit::SETUP;
            }
        };
        let t_us = unix0 + (clock.now_ns() - t0) / 1000;
        let line = cncgw_bus::frame::candump_line(t_us, &iface, &f);
        let mut r = writeln!(w, "{line}");
        // Flush now and then so a log cut short by Ctrl-C keeps (almost) everything.
        if r.is_ok() && !simulated && clock.now_ns() - last_flush > 100 * MS {
            last_flush = clock.now_ns();
            r = w.flush();
        }
        if let Err(e) = r {
            eprintln!("error: {}: cannot write: {e}", out.display());
            return exit::SETUP;
        }
        frames += 1;
    }
    if let Err(e) = w.flush() {
        eprintln!("error: {}: cannot write: {e}", out.display());
        return exit::SETUP;
    }
    println!("{frames} frame(s) logged to {}", out.display());
    exit::OK
}

// ---------------------------------------------------------------- monitor

/// A bus endpoint that counts the bits of every frame it sends or receives (bus load).
struct CountingBus {
    inner: Box<dyn CanBus>,
    bits: Arc<AtomicU64>,
}

impl CountingBus {
    fn count(&self, f: &CanFrame) {
        self.bits.fetch_add(cncgw_bus::busload::frame_bits(f.data().len()) as u64, Ordering::Relaxed);
    }
}

impl CanBus for CountingBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let r = self.inner.send(frame);
        if r.is_ok() {
            self.count(frame);
        }
        r
    }
    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        let r = self.inner.try_recv();
        if let Ok(Some(f)) = &r {
            self.count(f);
        }
        r
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        let r = self.inner.recv_timeout(timeout);
        if let Ok(Some(f)) = &r {
            self.count(f);
        }
        r
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn remote_frames(&self) -> bool {
        self.inner.remote_frames()
    }
    fn controller(&self) -> Option<cncgw_bus::can_error::ControllerStatus> {
        self.inner.controller()
    }
}

/// One drive's row of the monitor, read through `DriveAccess`: the same for every bus.
pub(super) struct MonitorRow {
    node: u8,
    axis: String,
    /// A spindle (degrees, rpm) rather than a feed axis (mm, mm/min).
    spindle: bool,
    cpu: f64,
    /// The drive's status, or why it did not answer.
    st: Result<DriveStatus, String>,
}

pub(super) fn monitor_read(d: &mut dyn DriveAccess) -> MonitorRow {
    let axis = d.axis();
    let (name, cpu, spindle) = axis.unwrap_or_else(|| ("-".into(), 1.0, false));
    MonitorRow { node: d.id(), axis: name, spindle, cpu, st: access::read_status(d) }
}

impl MonitorRow {
    /// Position, speed (rpm or mm/min: 360°/rev, 60 s/min) and following error in the
    /// operator's units (X as the drive counts it: a radius).
    fn figures(&self, st: &DriveStatus) -> (Option<f64>, Option<f64>, Option<f64>) {
        let units = |c: Option<i64>| c.map(|c| c as f64 / self.cpu);
        let vel = units(st.velocity).map(|v| if self.spindle { v / 6.0 } else { v * 60.0 });
        (units(st.position), vel, units(st.following_error))
    }
}

/// The monitor table's header, the drives addressed as `noun` ("node", "unit").
pub(super) fn monitor_header(noun: &str) -> String {
    format!(
        "{noun:>4} {:<5} {:<6} {:<22} {:<26} {:>8} {:>16} {:>16} {:>14}",
        "axis", "sw", "state", "mode", "error", "position", "speed", "follow. error"
    )
}

/// One drive's line of the monitor table.
pub(super) fn monitor_line(r: &MonitorRow) -> String {
    let (node, axis) = (r.node, &r.axis);
    let st = match &r.st {
        Ok(st) => st,
        Err(e) => return format!("{node:>4} {axis:<5} no answer: {e}"),
    };
    let (pos, vel, ferr) = r.figures(st);
    let (pu, vu) = if r.spindle { ("deg", "rpm") } else { ("mm", "mm/min") };
    let f = |v: Option<f64>, u: &str| v.map(|v| format!("{v:.4} {u}")).unwrap_or_else(|| "-".into());
    let mode = st.mode.map(|m| format!("{m} {}", mode::name(m))).unwrap_or_else(|| "-".into());
    let err = st.error_code.map(|e| format!("0x{e:04X}")).unwrap_or_else(|| "-".into());
    format!(
        "{node:>4} {axis:<5} 0x{:04X} {:<22} {mode:<26} {err:>8} {:>16} {:>16} {:>14}",
        st.statusword,
        st.state().name(),
        f(pos, pu),
        f(vel, vu),
        f(ferr, pu)
    )
}

pub(super) fn monitor_json(r: &MonitorRow) -> serde_json::Value {
    match &r.st {
        Ok(st) => {
            let (pos, vel, ferr) = r.figures(st);
            serde_json::json!({
                "node": r.node, "axis": r.axis, "statusword": format!("0x{:04X}", st.statusword),
                "state": st.state().name(), "mode": st.mode, "mode_name": st.mode.map(mode::name),
                "position": pos, "velocity": vel, "following_error": ferr, "error": null,
                "error_code": st.error_code.map(|e| format!("0x{e:04X}")),
                "position_unit": if r.spindle { "deg" } else { "mm" }, "velocity_unit": if r.spindle { "rpm" } else { "mm/min" },
            })
        }
        Err(e) => serde_json::json!({"node": r.node, "axis": r.axis, "error": e}),
    }
}

/// Write one refresh: JSON lines, or the table redrawn in place on a terminal. `shown`: the
/// lines drawn last time (updated). False: stdout is closed.
pub(super) fn monitor_draw(out: &mut impl Write, lines: &[String], tty: bool, shown: &mut usize, once: bool) -> bool {
    let mut text = String::new();
    if tty && *shown > 0 {
        // Back to the top of the previous table and overwrite it.
        text.push_str(&format!("\x1b[{shown}A"));
    }
    for l in lines {
        if tty {
            text.push_str("\x1b[2K");
        }
        text.push_str(l);
        text.push('\n');
    }
    if !tty && !once {
        text.push('\n');
    }
    *shown = lines.len();
    out.write_all(text.as_bytes()).and_then(|_| out.flush()).is_ok()
}

/// The machine's I/O monitor of `cfg` (None: no `[io]`); Err = exit code (said).
pub(super) fn io_monitor(cfg: &crate::config::MachineConfig) -> Result<Option<super::iomon::IoMonitor>, i32> {
    super::iomon::IoMonitor::new(cfg).map_err(|e| {
        eprintln!("error: [io]: {e}");
        exit::SETUP
    })
}

/// One bus as the monitor sees it: its drives, each read through `DriveAccess`, its clock,
/// its lines under the table and its fields of the JSON object, and how it waits for the
/// next refresh. `monitor_loop` is the one refresh loop over it.
pub(super) trait MonitorBus {
    /// How the drives are addressed ("node", "unit").
    fn noun(&self) -> &'static str;
    fn now_ns(&mut self) -> u64;
    /// Before the first refresh.
    fn prepare(&mut self) {}
    /// Each drive's row.
    fn rows(&mut self) -> Vec<MonitorRow>;
    fn read_io(&mut self, m: &mut super::iomon::IoMonitor) -> super::iomon::IoRead;
    /// The lines under the drives' rows and this bus's fields of the JSON object; the
    /// refresh began at `tick`, its drives were read by `rows_done`, `now` is its end.
    fn status(&mut self, tick: u64, rows_done: u64, now: u64, n_rows: usize) -> (Vec<String>, serde_json::Map<String, serde_json::Value>);
    /// Until the next refresh, `interval_ns` after the one that began at `tick`.
    fn wait(&mut self, tick: u64, interval_ns: u64, tty: bool);
}

/// The monitor's refresh loop, the same for every bus: a table (or one JSON object per
/// refresh) every `interval_ms`, for `seconds` (None: until stdout closes) or `once`.
pub(super) fn monitor_loop(
    bus: &mut dyn MonitorBus,
    mut io: Option<super::iomon::IoMonitor>,
    seconds: Option<f64>,
    once: bool,
    interval_ms: u64,
    json: bool,
) -> i32 {
    use std::io::IsTerminal;
    let tty = std::io::stdout().is_terminal() && !json;
    let t0 = bus.now_ns();
    let end = seconds.map(|x| t0 + (x * 1e9) as u64);
    let interval = interval_ms.max(50) * MS;
    let mut shown = 0usize;
    let mut out = std::io::stdout();
    bus.prepare();
    loop {
        let tick = bus.now_ns();
        let rows = bus.rows();
        let rows_done = bus.now_ns();
        let io = io.as_mut().map(|m| {
            let r = bus.read_io(m);
            (m.json(&r), m.lines(&r))
        });
        let now = bus.now_ns();
        let (status, fields) = bus.status(tick, rows_done, now, rows.len());
        let lines = if json {
            let mut o = fields;
            o.insert("t_s".into(), ((now - t0) as f64 * 1e-9).into());
            o.insert("drives".into(), rows.iter().map(monitor_json).collect::<Vec<_>>().into());
            o.insert("io".into(), io.map(|(j, _)| j).unwrap_or(serde_json::Value::Null));
            vec![serde_json::Value::Object(o).to_string()]
        } else {
            let mut lines = vec![monitor_header(bus.noun())];
            lines.extend(rows.iter().map(monitor_line));
            lines.extend(status);
            lines.extend(io.into_iter().flat_map(|(_, l)| l));
            lines
        };
        // JSON: one object per refresh (JSON lines), never redrawn in place.
        if !monitor_draw(&mut out, &lines, tty, &mut shown, once || json) || once {
            return exit::OK; // stdout closed, or one table asked for
        }
        if end.is_some_and(|e| bus.now_ns() + interval > e) {
            return exit::OK;
        }
        bus.wait(tick, interval, tty);
    }
}

/// The CANopen bus of the monitor: the drives by SDO, the bus load from the frames this
/// tool sent and heard.
struct CanMonitor {
    s: Session,
    nodes: Vec<u8>,
    bits: Arc<AtomicU64>,
    /// Start of the bus load's window.
    since: u64,
}

impl MonitorBus for CanMonitor {
    fn noun(&self) -> &'static str {
        "node"
    }
    fn now_ns(&mut self) -> u64 {
        self.s.clock.now_ns()
    }
    fn prepare(&mut self) {
        // Load over the previous period: the first table measures a short listen.
        self.bits.store(0, Ordering::Relaxed);
        self.since = self.s.clock.now_ns();
        self.s.master.listen(&mut *self.s.clock, 100);
    }
    fn rows(&mut self) -> Vec<MonitorRow> {
        let s = &mut self.s;
        self.nodes.iter().map(|&n| monitor_read(&mut SdoDrive::new(s, n))).collect()
    }
    fn read_io(&mut self, m: &mut super::iomon::IoMonitor) -> super::iomon::IoRead {
        let s = &mut self.s;
        m.read(Some(&mut |node, index, sub| sdo_byte(s, node, index, sub)))
    }
    fn status(&mut self, _: u64, _: u64, now: u64, _: usize) -> (Vec<String>, serde_json::Map<String, serde_json::Value>) {
        let s = &self.s;
        let bitrate = s.cfg.bus.bitrate.max(1);
        let dt = (now - self.since).max(1) as f64 * 1e-9;
        let load = self.bits.swap(0, Ordering::Relaxed) as f64 / (bitrate as f64 * dt);
        self.since = now;
        let mut lines =
            vec![format!("bus {} load {:.2} % ({bitrate} bit/s; frames sent and heard by this tool over the last {dt:.2} s)", s.bus, load * 100.0)];
        // The CAN controller's own state, as `ip -details -statistics link show` has it
        // (SocketCAN's error frames; the emulated bus and socketcand do not report it).
        if let Some(c) = s.master.controller() {
            lines.push(format!("CAN controller: {}", c.line()));
        }
        let fields = serde_json::json!({
            "bus": s.bus, "simulated": s.simulated, "bus_load": load, "bitrate": bitrate,
            "load_window_s": dt, "controller": s.master.controller(),
        });
        (lines, fields.as_object().cloned().unwrap_or_default())
    }
    fn wait(&mut self, _: u64, interval: u64, tty: bool) {
        if self.s.simulated && tty {
            // Simulated time runs as fast as the CPU: pace the display for a human.
            std::thread::sleep(Duration::from_nanos(interval));
        }
        self.s.master.listen(&mut *self.s.clock, interval / MS);
    }
}

/// `cncgw monitor`.
pub fn monitor(machine: &MachineArgs, seconds: Option<f64>, once: bool, interval_ms: u64, json: bool) -> i32 {
    if let Some(n) = seconds {
        if !(n.is_finite() && n > 0.0) {
            eprintln!("error: --seconds must be a positive number");
            return exit::INPUT;
        }
    }
    let bits = Arc::new(AtomicU64::new(0));
    let counter = bits.clone();
    let s = match open_service_bus_with(machine, move |inner| Box::new(CountingBus { inner, bits: counter })) {
        Ok(ServiceBus::Modbus(cfg)) => return super::mbus::monitor(&cfg, seconds, once, interval_ms, json),
        Ok(ServiceBus::CanOpen(s)) => s,
        Err(code) => return code,
    };
    let io = match io_monitor(&s.cfg) {
        Ok(m) => m,
        Err(code) => return code,
    };
    let mut nodes = s.master.node_ids();
    nodes.sort_unstable();
    let seconds = seconds.or(s.simulated.then_some(INPROC_DEFAULT_S));
    monitor_loop(&mut CanMonitor { s, nodes, bits, since: 0 }, io, seconds, once, interval_ms, json)
}

/// One byte of an object by SDO (a CiA 401 module's 8 inputs or outputs of a sub-index).
fn sdo_byte(s: &mut Session, node: u8, index: u16, sub: u8) -> Result<u8, String> {
    // A module is no drive of the master's: its SDO channel is opened here (the monitor's
    // drive list was taken before).
    s.master.ensure_node(node);
    let d = s.master.sdo_upload(&mut *s.clock, node, index, sub).map_err(|e| sdo_error_text(&e))?;
    d.first().copied().ok_or_else(|| format!("0x{index:04X}:{sub} answered no data"))
}
