//! The machine's I/O in the cycle loop (configuration: `crate::io`): every cycle the inputs
//! of every device are read, the safety inputs checked, a pending M/T code's completion
//! (FIN) decided, and the outputs handed to the devices. Fixed-size images, no allocation
//! after [`IoRun::new`]; an alarm's message is made only when it is raised.
//!
//! What stops the machine:
//! - the E-stop input open: the panel's E-stop path (`CycleLoop::estop`): every drive quick
//!   stop in this cycle, alarm 2400;
//! - the door input open: controlled stop along the path, alarm 2601;
//! - the chuck input open while the spindle is commanded to turn, or after the clamp code's
//!   confirmation until an unclamp code: controlled stop, alarm 2602;
//! - a code not confirmed within its timeout: controlled stop (nothing after the code ran),
//!   alarm 2600;
//! - a device that went silent: alarm 2603 (the CANopen master's, or a Modbus unit's here);
//! - a chuck unclamp code while M03/M04 is in force: refused before its outputs switch,
//!   controlled stop, alarm 2604. An unclamp code reached while the spindle still coasts
//!   down after M05 waits (within its timeout) until the spindle stands, then switches. The
//!   interlock a lathe's ladder has on the unclamp valve (Fanuc 0i-TF: the chuck's M code is
//!   the machine builder's; the standard ladder unclamps only at spindle zero speed). No
//!   interlock on the axes: motion takes an auxiliary code only after the move before it has
//!   ended (no blending across it), so no axis is commanded to move while M10/M11 switch.
//!
//! An input that has not been read yet (a device still starting) reads as open: a safety
//! input must be seen closed.

use crate::drives::modbus::io::ModbusIo;
use crate::drives::DriveBus;
use crate::io::{Action, Bit, Bits, DeviceKind, Resolved, MAX_DEVICES};
use crate::Alarm;

/// A spindle slower than this (rpm, measured) for [`STILL_MS`] stands: the chuck may be
/// unclamped. (Not the first zero crossing: a position-controlled spindle overshoots by a
/// few rpm as it stops.)
const STILL_RPM: f64 = 1.0;
const STILL_MS: f64 = 50.0;

/// What the cycle loop must do about the inputs of this cycle.
#[derive(Debug)]
pub enum IoStop {
    /// Quick stop every drive, as the panel's E-stop: the input's name.
    Estop(String),
    /// Controlled stop with this alarm.
    Halt(Alarm),
    /// A device failed: quick stop with this alarm.
    Device(Alarm),
}

impl IoStop {
    /// The alarm when a safety input is already open before the program starts.
    pub fn refused(self) -> Alarm {
        match self {
            IoStop::Estop(name) => Alarm::new(
                crate::alarm::ESTOP,
                format!("the E-stop input {name} is open: the program did not start and every drive was sent quick stop; close the E-stop chain, then start again"),
            ),
            IoStop::Halt(mut a) | IoStop::Device(mut a) => {
                a.message = format!("before the start: {}", a.message.replace(" at line 0", ""));
                a
            }
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum Code {
    M(u16),
    T(u32),
}

/// An auxiliary code waiting for its completion.
#[derive(Clone, Copy, Debug)]
struct Pending {
    code: Code,
    action: Action,
    /// Outputs switched off at FIN (the turret's strobe).
    after: Bits,
    cycles_left: u64,
    line: u32,
    /// Its outputs are switched (an unclamp code waits for the spindle to stand first).
    armed: bool,
}

enum Device {
    Can(u8),
    Modbus(ModbusIo),
}

pub struct IoRun {
    cfg: Resolved,
    devices: Vec<Device>,
    out: [u32; MAX_DEVICES],
    inp: [u32; MAX_DEVICES],
    seen: [bool; MAX_DEVICES],
    pending: Option<Pending>,
    /// The clamp code was confirmed and no unclamp code came since.
    clamped: bool,
    /// Cycles the spindle has stood (measured) while an unclamp code waits.
    still: u32,
    cycle_ms: f64,
}

impl IoRun {
    /// The I/O of `cfg` (None when it has no `[io]` devices). Starts the Modbus units' poll
    /// threads.
    pub fn new(cfg: &crate::config::MachineConfig) -> Result<Option<IoRun>, Alarm> {
        let r = cfg.io.resolve().map_err(|e| Alarm::new(crate::alarm::CONFIG, e.join("; ")))?;
        if r.is_empty() {
            return Ok(None);
        }
        let mut devices = Vec::with_capacity(r.devices.len());
        for (name, kind, ins, outs) in &r.devices {
            devices.push(match kind {
                DeviceKind::Cia401 { node } => Device::Can(*node),
                DeviceKind::ModbusTcp { .. } => Device::Modbus(ModbusIo::start(name, kind, *ins, *outs)?),
            });
        }
        Ok(Some(IoRun {
            cfg: r,
            devices,
            out: [0; MAX_DEVICES],
            inp: [0; MAX_DEVICES],
            seen: [false; MAX_DEVICES],
            pending: None,
            clamped: false,
            still: 0,
            cycle_ms: cfg.machine.cycle_ms,
        }))
    }

    fn get(&self, b: Bit) -> bool {
        self.seen[b.dev as usize] && self.inp[b.dev as usize] >> b.bit & 1 == 1
    }

    fn put(&mut self, b: Bit, on: bool) {
        let w = &mut self.out[b.dev as usize];
        if on {
            *w |= 1 << b.bit;
        } else {
            *w &= !(1 << b.bit);
        }
    }

    /// Read every device's inputs (after the bus's `receive`). Err: a device failed.
    pub fn read(&mut self, drives: &dyn DriveBus) -> Result<(), Alarm> {
        for (k, d) in self.devices.iter().enumerate() {
            let v = match d {
                Device::Can(node) => drives.io_inputs(*node),
                Device::Modbus(m) => m.inputs()?,
            };
            if let Some(v) = v {
                self.inp[k] = v;
                self.seen[k] = true;
            }
        }
        Ok(())
    }

    /// Hand the outputs to the devices (before the bus's `transmit`).
    pub fn write(&self, drives: &mut dyn DriveBus) {
        for (k, d) in self.devices.iter().enumerate() {
            match d {
                Device::Can(node) => drives.set_io_outputs(*node, self.out[k]),
                Device::Modbus(m) => m.set_outputs(self.out[k]),
            }
        }
    }

    /// The safety inputs as read (for the panel's display).
    pub fn safety_inputs(&self) -> super::panel::SafetyInputs {
        let read = |x: &Option<(Bit, String)>| x.as_ref().map(|(b, _)| self.get(*b));
        super::panel::SafetyInputs { estop: read(&self.cfg.estop), door: read(&self.cfg.door), chuck: read(&self.cfg.chuck) }
    }

    /// The E-stop input is open (read by the stop loops, which have no other I/O).
    pub fn estop_open(&self) -> bool {
        self.cfg.estop.as_ref().is_some_and(|(b, _)| !self.get(*b))
    }

    /// The safety inputs this cycle (`spindle_on`: the spindle is commanded to turn).
    pub fn check_safety(&self, spindle_on: bool, line: u32) -> Option<IoStop> {
        if let Some((_, name)) = self.cfg.estop.as_ref().filter(|(b, _)| !self.get(*b)) {
            return Some(IoStop::Estop(name.clone()));
        }
        if let Some((_, name)) = self.cfg.door.as_ref().filter(|(b, _)| !self.get(*b)) {
            return Some(IoStop::Halt(Alarm::new(
                crate::alarm::IO_DOOR_OPEN,
                format!("door open at line {line} (input {name}): the axes and the spindle were stopped under control and the program ended; close the door, then start the program again from a safe block"),
            )));
        }
        if let Some((_, name)) = self.cfg.chuck.as_ref().filter(|(b, _)| !self.get(*b) && (spindle_on || self.clamped)) {
            let why = if spindle_on { "while the spindle was commanded to turn" } else { "after the clamp was confirmed" };
            return Some(IoStop::Halt(Alarm::new(
                crate::alarm::IO_CHUCK_UNCLAMPED,
                format!("chuck not clamped at line {line} (input {name} opened {why}): stopped under control, the program ended; check the workpiece, the chuck pressure and its switch before anything turns again"),
            )));
        }
        None
    }

    /// A code that unclamps the chuck: M11 (manual 004 §3.1: 卡盘松开), one that waits for
    /// the chuck input to drop, or one that clears an output the clamp code (M10) sets.
    fn unclamps(&self, m: u16, a: &Action) -> bool {
        let chuck_in = self.cfg.chuck.as_ref().map(|(b, _)| *b);
        let clamp_outs = self.cfg.m.iter().find(|(n, _)| *n == 10).map(|(_, a)| a.set).unwrap_or_default();
        m == 11 || a.wait_off.iter().any(|b| Some(*b) == chuck_in) || a.clear.iter().any(|b| clamp_outs.iter().any(|c| c == b))
    }

    /// The code reached by execution (`Event::Aux`): switch its outputs; Ok(true) when the
    /// program must wait for its completion (`Motion::wait_fin`). `turning`: M03/M04 in
    /// force; `rpm`: the spindle's measured speed. Err: an unclamp code refused (nothing
    /// switched).
    pub fn on_aux(&mut self, letter: char, value: f64, line: u32, turning: bool, rpm: f64) -> Result<bool, Alarm> {
        let (code, action, after) = match letter {
            'M' => {
                let m = value as u16;
                let Some(a) = self.cfg.m.iter().find(|(n, _)| *n == m).map(|(_, a)| *a) else { return Ok(false) };
                if self.unclamps(m, &a) {
                    if turning {
                        return Err(Alarm::new(
                            crate::alarm::IO_UNCLAMP_TURNING,
                            format!("M{m:02} (chuck unclamp) at line {line} while the spindle is commanded to turn (M03/M04): refused, the chuck stayed clamped and the machine was stopped under control; program M05 before M{m:02} (the unclamp waits for the spindle to stand), then start again from a safe block"),
                        ));
                    }
                    // Switched once the spindle has stood for STILL_MS (after M05 it may
                    // still coast down).
                    self.still = u32::from(rpm.abs() <= STILL_RPM);
                    let cycles_left = (a.timeout_ms as f64 / self.cycle_ms).ceil() as u64;
                    self.pending = Some(Pending { code: Code::M(m), action: a, after: Bits::default(), cycles_left, line, armed: false });
                    return Ok(true);
                }
                (Code::M(m), a, Bits::default())
            }
            'T' => {
                let Some(t) = self.cfg.turret else { return Ok(false) };
                let station = value as u32 / 100;
                let mut a = Action { timeout_ms: t.timeout_ms, ..Action::default() };
                for (k, b) in t.code.iter().enumerate() {
                    self.put(*b, station >> k & 1 == 1);
                }
                a.set.at[0] = t.strobe;
                a.set.n = 1;
                a.wait_on.at[0] = t.in_position;
                a.wait_on.n = 1;
                let mut after = Bits::default();
                after.at[0] = t.strobe;
                after.n = 1;
                (Code::T(station), a, after)
            }
            _ => return Ok(false),
        };
        self.switch(&action);
        if !action.waits() {
            return Ok(false);
        }
        let cycles_left = (action.timeout_ms as f64 / self.cycle_ms).ceil() as u64;
        self.pending = Some(Pending { code, action, after, cycles_left, line, armed: true });
        Ok(true)
    }

    /// Switch a code's outputs.
    fn switch(&mut self, action: &Action) {
        for b in action.set.iter() {
            self.put(*b, true);
        }
        for b in action.clear.iter() {
            self.put(*b, false);
        }
        // An unclamp code: the chuck is no longer held to be clamped.
        if self.cfg.chuck.as_ref().is_some_and(|(c, _)| action.wait_off.iter().any(|b| b == c)) {
            self.clamped = false;
        }
    }

    /// The program's end (M02/M30): the coolant off, as a Fanuc 0i-TF's standard ladder does
    /// (manual 004 §2.19's example: "M30; 程序结束, 关主轴、冷却液"; the spindle stop is
    /// motion's): M09's outputs are switched as M09 would (without its FIN wait — nothing
    /// follows), or, without an `[io.m.9]`, the outputs M08 sets are cleared. Other outputs
    /// (the chuck) keep their state: the part stays clamped.
    pub fn on_end(&mut self) {
        let code = |n: u16| self.cfg.m.iter().find(|(m, _)| *m == n).map(|(_, a)| *a);
        match (code(9), code(8)) {
            (Some(m9), _) => {
                for b in m9.set.iter() {
                    self.put(*b, true);
                }
                for b in m9.clear.iter() {
                    self.put(*b, false);
                }
            }
            (None, Some(m8)) => {
                for b in m8.set.iter() {
                    self.put(*b, false);
                }
            }
            (None, None) => {}
        }
    }

    /// Every device has answered at least once.
    pub fn all_seen(&self) -> bool {
        self.seen[..self.devices.len()].iter().all(|s| *s)
    }

    /// Wait (wall time) for every Modbus unit's first answer.
    pub fn wait_modbus(&self, ms: u64) -> Result<(), Alarm> {
        for d in &self.devices {
            if let Device::Modbus(m) = d {
                m.wait_first(ms)?;
            }
        }
        Ok(())
    }

    /// A code is waiting for its completion.
    pub fn pending(&self) -> bool {
        self.pending.is_some()
    }

    /// One cycle of the pending code (`rpm`: the spindle's measured speed): `Ok(true)` at FIN
    /// (call `Motion::wait_fin(false)`), Err: not confirmed in time.
    pub fn step_fin(&mut self, rpm: f64) -> Result<bool, Alarm> {
        let Some(mut p) = self.pending else { return Ok(false) };
        if !p.armed {
            self.still = if rpm.abs() <= STILL_RPM { self.still + 1 } else { 0 };
            if self.still as f64 * self.cycle_ms >= STILL_MS {
                self.switch(&p.action);
                p.armed = true;
                // The confirmation's own timeout starts with its valve.
                p.cycles_left = (p.action.timeout_ms as f64 / self.cycle_ms).ceil() as u64;
            }
        }
        let done = p.armed && p.action.wait_on.iter().all(|b| self.get(*b)) && p.action.wait_off.iter().all(|b| !self.get(*b));
        if done {
            for b in p.after.iter() {
                self.put(*b, false);
            }
            if self.cfg.chuck.as_ref().is_some_and(|(c, _)| p.action.wait_on.iter().any(|b| b == c)) {
                self.clamped = true;
            }
            self.pending = None;
            return Ok(true);
        }
        if p.cycles_left == 0 {
            self.pending = None;
            return Err(self.timeout_alarm(&p));
        }
        p.cycles_left -= 1;
        self.pending = Some(p);
        Ok(false)
    }

    fn timeout_alarm(&self, p: &Pending) -> Alarm {
        let missing: Vec<String> = p
            .action
            .wait_on
            .iter()
            .filter(|b| !self.get(**b))
            .map(|b| format!("{} on", self.cfg.input_name(*b)))
            .chain(p.action.wait_off.iter().filter(|b| self.get(**b)).map(|b| format!("{} off", self.cfg.input_name(*b))))
            .collect();
        let missing = if p.armed { missing } else { vec!["the spindle to stand before the unclamp".to_string()] };
        let what = match p.code {
            Code::M(m) => format!("M{m:02}"),
            Code::T(t) => format!("T{t:02} (turret index)"),
        };
        Alarm::new(
            crate::alarm::IO_FIN_TIMEOUT,
            format!(
                "{what} at line {} was not confirmed within {} ms (waiting for {}): no later block ran and the machine was stopped under control; check the device and its switch, then start again from this block",
                p.line,
                p.action.timeout_ms,
                missing.join(", ")
            ),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(extra: &str) -> IoRun {
        let text = format!(
            "{}\n[io.devices.m]\ncanopen_node = 10\n[io.inputs]\nestop = \"m.0\"\ndoor = \"m.1\"\nclamped = \"m.2\"\n[io.outputs]\ncoolant = \"m.0\"\nclamp = \"m.1\"\n{extra}",
            crate::config::EMBEDDED_LATHE
        );
        let cfg = crate::config::MachineConfig::from_toml("t", &text).unwrap();
        IoRun::new(&cfg).unwrap().unwrap()
    }

    #[test]
    fn a_clamp_code_waits_for_its_input_then_times_out() {
        let mut io = run("[io.m.10]\nset = [\"clamp\"]\nwait_on = [\"clamped\"]\ntimeout_ms = 10\n[io.safety]\nchuck = \"clamped\"");
        assert!(io.on_aux('M', 10.0, 7, false, 0.0).unwrap());
        assert_eq!(io.out[0], 0b10);
        io.seen[0] = true;
        for _ in 0..5 {
            assert!(!io.step_fin(0.0).unwrap());
        }
        let a = io.step_fin(0.0).unwrap_err();
        assert_eq!(a.number, crate::alarm::IO_FIN_TIMEOUT);
        assert!(a.message.contains("M10 at line 7") && a.message.contains("clamped on"), "{}", a.message);
        // Confirmed: FIN, and from then on the chuck input is watched.
        assert!(io.on_aux('M', 10.0, 8, false, 0.0).unwrap());
        io.inp[0] = 0b100;
        assert!(io.step_fin(0.0).unwrap());
        assert!(io.check_safety(false, 9).is_none());
        io.inp[0] = 0;
        assert!(matches!(io.check_safety(false, 9), Some(IoStop::Halt(a)) if a.number == crate::alarm::IO_CHUCK_UNCLAMPED));
    }

    #[test]
    fn an_unread_estop_input_is_open() {
        let mut io = run("[io.safety]\nestop = \"estop\"\ndoor = \"door\"");
        assert!(matches!(io.check_safety(false, 1), Some(IoStop::Estop(n)) if n == "estop"));
        io.seen[0] = true;
        io.inp[0] = 0b01;
        assert!(matches!(io.check_safety(false, 1), Some(IoStop::Halt(a)) if a.number == crate::alarm::IO_DOOR_OPEN));
        io.inp[0] = 0b11;
        assert!(io.check_safety(true, 1).is_none());
    }
}
