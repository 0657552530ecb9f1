//! `DriveAccess`: one drive's CiA 402 objects, read and written one at a time, whatever
//! carries them — SDO on a CANopen bus (SocketCAN, socketcand, the embedded emulator), or a
//! Modbus drive's holding registers through its `cia402_map` (the PR map: its status
//! register as a statusword, servo on and alarm reset as the controlword). The service
//! commands (`drive enable|disable|fault-reset`) walk a drive here once, for every bus.

use cncgw_bus::canopen::od;
use cncgw_bus::cia402::{DisableProgress, Disabler, EnableProgress, Enabler, FaultResetter, ResetProgress, State};

/// The type of an object as it is read or written (sign extension, size on the wire).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObjType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
}

impl ObjType {
    /// Size in bytes (SDO); Modbus carries 1 and 2 byte objects in one register, 4 in two.
    pub fn bytes(self) -> usize {
        match self {
            ObjType::I8 | ObjType::U8 => 1,
            ObjType::I16 | ObjType::U16 => 2,
            ObjType::I32 | ObjType::U32 => 4,
        }
    }

    pub fn signed(self) -> bool {
        matches!(self, ObjType::I8 | ObjType::I16 | ObjType::I32)
    }

    /// `raw`'s low `bytes()` bytes as this type's value (sign-extended when signed).
    pub fn extend(self, raw: u64) -> i64 {
        let shift = 64 - 8 * self.bytes() as u32;
        if self.signed() {
            ((raw << shift) as i64) >> shift
        } else {
            ((raw << shift) >> shift) as i64
        }
    }
}

/// One drive's objects over whatever bus it is on. Errors are messages that name the drive.
pub trait DriveAccess {
    /// How the drive is addressed in messages: "node" (CANopen) or "unit" (Modbus).
    fn noun(&self) -> &'static str;
    /// Node id or unit id.
    fn id(&self) -> u8;
    /// The drive in messages, with its axis and bus where known: "node 1 (axis x)",
    /// "unit 2 (axis z) on Modbus TCP 127.0.0.1:5020".
    fn label(&self) -> String;
    /// The drive's axis in the configuration: (name, counts per machine unit, a spindle).
    fn axis(&self) -> Option<(String, f64, bool)>;
    fn read(&mut self, index: u16, sub: u8, ty: ObjType) -> Result<i64, String>;
    fn write(&mut self, index: u16, sub: u8, ty: ObjType, value: i64) -> Result<(), String>;
    fn statusword(&mut self) -> Result<u16, String> {
        self.read(od::STATUSWORD, 0, ObjType::U16).map(|v| v as u16)
    }
    fn controlword(&mut self, c: u16) -> Result<(), String> {
        self.write(od::CONTROLWORD, 0, ObjType::U16, c as i64)
    }
    /// The drive's error code (0x603F, or a PR drive's alarm code) in words, for messages.
    fn error_text(&mut self) -> String;
    /// The drive's own clock: simulated time on the emulated bus, else the wall clock.
    fn now_ns(&mut self) -> u64;
    fn wait_ns(&mut self, ns: u64);
    /// Before a drive that is not enabled is enabled (Modbus: its communication watchdog off,
    /// as no cyclic writes will follow).
    fn before_enable(&mut self) -> Result<(), String> {
        Ok(())
    }
    /// What the status register is when it is not a CiA 402 statusword (a PR drive's), for
    /// the messages: (what it is called, value).
    fn status_register(&mut self) -> Option<(&'static str, u16)> {
        None
    }
}

/// One drive's state as `drive status` and `monitor` show it: the statusword and what the
/// drive has of the rest (absent or unreadable objects are `None`).
#[derive(Clone, Debug, Default)]
pub struct DriveStatus {
    pub statusword: u16,
    /// The status register as read, where it is no CiA 402 statusword (a PR drive's).
    pub status_register: Option<(&'static str, u16)>,
    pub mode: Option<i8>,
    pub position: Option<i64>,
    pub velocity: Option<i64>,
    pub following_error: Option<i64>,
    pub error_code: Option<u16>,
    /// 0x60FD: bit 0 negative, bit 1 positive limit switch, bit 2 home switch.
    pub digital_inputs: Option<u32>,
}

impl DriveStatus {
    pub fn state(&self) -> State {
        State::from_statusword(self.statusword)
    }
}

/// Read `d`'s status: the statusword (an error when it does not answer), then the rest.
pub fn read_status(d: &mut dyn DriveAccess) -> Result<DriveStatus, String> {
    let statusword = d.statusword()?;
    let status_register = d.status_register();
    let mut int = |ix: u16, ty: ObjType| d.read(ix, 0, ty).ok();
    Ok(DriveStatus {
        statusword,
        status_register,
        mode: int(od::MODES_DISPLAY, ObjType::I8).map(|m| m as i8),
        position: int(od::POSITION_ACTUAL, ObjType::I32),
        velocity: int(od::VELOCITY_ACTUAL, ObjType::I32),
        following_error: int(od::FOLLOWING_ERROR_ACTUAL, ObjType::I32),
        error_code: int(od::ERROR_CODE, ObjType::U16).map(|e| e as u16),
        digital_inputs: int(0x60FD, ObjType::U32).map(|v| v as u32),
    })
}

/// What `drive enable|disable|fault-reset` walks towards.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PowerGoal {
    /// Operation Enabled (fault resets included, as the master's own walk does).
    Enable,
    /// Switch On Disabled: no torque (disable voltage, CiA 402 transitions 7, 9, 10, 12).
    Disable,
    /// Out of Fault (rising edge of controlword bit 7), to Switch On Disabled.
    FaultReset,
}

/// Step period of the walks.
const STEP_NS: u64 = 10_000_000;

/// Walk `d` towards `goal`, one step per 10 ms, giving up after `timeout_ms`. Returns
/// (state before, state reached).
pub fn power_walk(d: &mut dyn DriveAccess, goal: PowerGoal, timeout_ms: u64) -> Result<(State, State), String> {
    let (noun, id) = (d.noun(), d.id());
    let first = State::from_statusword(d.statusword()?);
    if goal == PowerGoal::Enable && first != State::OperationEnabled {
        d.before_enable()?;
        // A stale target position (0x607A) would be jumped to in a position mode the moment
        // the drive enables: make it the present position. Drives without 0x607A skip this.
        if let Ok(p) = d.read(od::POSITION_ACTUAL, 0, ObjType::I32) {
            let _ = d.write(od::TARGET_POSITION, 0, ObjType::I32, p);
        }
    }
    let end = d.now_ns() + timeout_ms * 1_000_000;
    let (mut enabler, mut disabler, mut resetter) = (Enabler::default(), Disabler::default(), FaultResetter::default());
    loop {
        let sw = d.statusword()?;
        let st = State::from_statusword(sw);
        let words: &[u16] = match goal {
            PowerGoal::Enable => match enabler.step(sw) {
                EnableProgress::Enabled => return Ok((first, st)),
                EnableProgress::ResetFailed => {
                    return Err(format!(
                        "{noun} {id} stays in Fault after {} fault resets: {}; clear the cause first",
                        Enabler::MAX_RESETS,
                        d.error_text()
                    ))
                }
                EnableProgress::Walking => &[enabler.controlword],
            },
            PowerGoal::Disable => match disabler.step(sw) {
                DisableProgress::Disabled => return Ok((first, st)),
                DisableProgress::InFault => {
                    return Err(format!(
                        "{noun} {id} is in {} (no torque): {}; `cncgw drive fault-reset {id}` clears it once the cause is gone",
                        st.name(),
                        d.error_text()
                    ))
                }
                DisableProgress::Walking => &[disabler.controlword],
            },
            PowerGoal::FaultReset => match resetter.step(sw) {
                (ResetProgress::Cleared, down) => {
                    for &c in down {
                        d.controlword(c)?;
                    }
                    return Ok((first, st));
                }
                (ResetProgress::Walking, edge) => edge,
            },
        };
        if d.now_ns() >= end {
            return Err(match goal {
                PowerGoal::FaultReset => format!("{noun} {id} still in {} after a fault reset: the cause persists: {}", st.name(), d.error_text()),
                _ => format!("{noun} {id} stuck in {} for {timeout_ms} ms; `cncgw drive status {id}` shows why", st.name()),
            });
        }
        for &c in words {
            d.controlword(c)?;
        }
        let t = d.now_ns() + STEP_NS;
        d.wait_ns(t);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cncgw_bus::cia402::device_transition;

    /// A drive that follows its controlword as CiA 402 says (one transition per write).
    struct Model {
        state: State,
        writes: Vec<u16>,
        t: u64,
        stuck_fault: bool,
    }

    impl DriveAccess for Model {
        fn noun(&self) -> &'static str {
            "node"
        }
        fn id(&self) -> u8 {
            1
        }
        fn label(&self) -> String {
            "node 1".into()
        }
        fn axis(&self) -> Option<(String, f64, bool)> {
            None
        }
        fn read(&mut self, index: u16, _: u8, _: ObjType) -> Result<i64, String> {
            match index {
                od::STATUSWORD => Ok(self.state.statusword_bits() as i64),
                _ => Err("no such object".into()),
            }
        }
        fn write(&mut self, index: u16, _: u8, _: ObjType, v: i64) -> Result<(), String> {
            if index == od::CONTROLWORD {
                let prev = self.writes.last().copied().unwrap_or(0);
                self.writes.push(v as u16);
                let next = device_transition(self.state, v as u16, prev);
                if !(self.stuck_fault && self.state == State::Fault) {
                    self.state = next;
                }
            }
            Ok(())
        }
        fn error_text(&mut self) -> String {
            "error code 0x2310".into()
        }
        fn now_ns(&mut self) -> u64 {
            self.t
        }
        fn wait_ns(&mut self, t: u64) {
            self.t = t;
        }
    }

    fn model(state: State) -> Model {
        Model { state, writes: Vec::new(), t: 0, stuck_fault: false }
    }

    #[test]
    fn walks_to_each_goal() {
        let mut m = model(State::SwitchOnDisabled);
        assert_eq!(power_walk(&mut m, PowerGoal::Enable, 2000).unwrap(), (State::SwitchOnDisabled, State::OperationEnabled));
        assert_eq!(power_walk(&mut m, PowerGoal::Disable, 2000).unwrap(), (State::OperationEnabled, State::SwitchOnDisabled));
        let mut m = model(State::Fault);
        assert!(power_walk(&mut m, PowerGoal::Disable, 2000).unwrap_err().contains("node 1 is in Fault (no torque): error code 0x2310"));
        assert_eq!(power_walk(&mut m, PowerGoal::FaultReset, 2000).unwrap(), (State::Fault, State::SwitchOnDisabled));
        // The edge, then bit 7 down again.
        assert_eq!(m.writes, [0x0000, 0x0080, 0x0000]);
    }

    #[test]
    fn a_fault_that_stays_is_said() {
        let mut m = model(State::Fault);
        m.stuck_fault = true;
        let e = power_walk(&mut m, PowerGoal::FaultReset, 100).unwrap_err();
        assert!(e.starts_with("node 1 still in Fault after a fault reset: the cause persists"), "{e}");
        let e = power_walk(&mut m, PowerGoal::Enable, 2000).unwrap_err();
        assert!(e.contains("stays in Fault after 5 fault resets"), "{e}");
    }

    #[test]
    fn types_extend() {
        assert_eq!(ObjType::I8.extend(0xFF), -1);
        assert_eq!(ObjType::U8.extend(0x1FF), 255);
        assert_eq!(ObjType::I32.extend(0xFFFF_FFFE), -2);
        assert_eq!(ObjType::U16.extend(0xFFFF_8000), 0x8000);
    }
}
