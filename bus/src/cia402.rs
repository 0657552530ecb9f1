//! CiA 402 (IEC 61800-7-201) drive profile words: the power state machine as decoded from
//! the statusword (master side) and as driven by the controlword (device side), and the
//! modes of operation. Shared by the master (CANopen and Modbus drives) and `sim-drives`.

/// The CiA 402 power drive system states (Figure 10 of CiA 402-2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum State {
    NotReadyToSwitchOn,
    SwitchOnDisabled,
    ReadyToSwitchOn,
    SwitchedOn,
    OperationEnabled,
    QuickStopActive,
    FaultReactionActive,
    Fault,
}

pub mod sw {
    pub const READY_TO_SWITCH_ON: u16 = 1 << 0;
    pub const SWITCHED_ON: u16 = 1 << 1;
    pub const OPERATION_ENABLED: u16 = 1 << 2;
    pub const FAULT: u16 = 1 << 3;
    pub const VOLTAGE_ENABLED: u16 = 1 << 4;
    pub const QUICK_STOP: u16 = 1 << 5;
    pub const SWITCH_ON_DISABLED: u16 = 1 << 6;
    pub const WARNING: u16 = 1 << 7;
    pub const REMOTE: u16 = 1 << 9;
    pub const TARGET_REACHED: u16 = 1 << 10;
    pub const INTERNAL_LIMIT: u16 = 1 << 11;
    /// CSP/CSV: drive follows the command value. PP: set-point acknowledge. Homing: attained.
    pub const OMS12: u16 = 1 << 12;
    /// CSP/PP: following error. Homing: homing error.
    pub const OMS13: u16 = 1 << 13;
}

pub mod cw {
    pub const SWITCH_ON: u16 = 1 << 0;
    pub const ENABLE_VOLTAGE: u16 = 1 << 1;
    pub const QUICK_STOP: u16 = 1 << 2;
    pub const ENABLE_OPERATION: u16 = 1 << 3;
    /// PP: new set-point. Homing: start.
    pub const OMS4: u16 = 1 << 4;
    pub const OMS5: u16 = 1 << 5;
    pub const OMS6: u16 = 1 << 6;
    pub const FAULT_RESET: u16 = 1 << 7;
    pub const HALT: u16 = 1 << 8;

    pub const SHUTDOWN: u16 = 0x0006;
    pub const SWITCH_ON_CMD: u16 = 0x0007;
    pub const ENABLE_OPERATION_CMD: u16 = 0x000F;
    pub const DISABLE_VOLTAGE: u16 = 0x0000;
    pub const QUICK_STOP_CMD: u16 = 0x0002;
    pub const DISABLE_OPERATION: u16 = 0x0007;
    pub const FAULT_RESET_CMD: u16 = 0x0080;
}

impl State {
    /// Decode the state from a statusword (CiA 402-2 Table 30).
    pub fn from_statusword(s: u16) -> State {
        if s & 0x4F == 0x00 {
            State::NotReadyToSwitchOn
        } else if s & 0x4F == 0x40 {
            State::SwitchOnDisabled
        } else if s & 0x6F == 0x21 {
            State::ReadyToSwitchOn
        } else if s & 0x6F == 0x23 {
            State::SwitchedOn
        } else if s & 0x6F == 0x27 {
            State::OperationEnabled
        } else if s & 0x6F == 0x07 {
            State::QuickStopActive
        } else if s & 0x4F == 0x0F {
            State::FaultReactionActive
        } else if s & 0x4F == 0x08 {
            State::Fault
        } else {
            // Undefined bit patterns: treat as not ready, the safe reading.
            State::NotReadyToSwitchOn
        }
    }

    /// The state bits of the statusword for this state (bits 0–3, 5, 6); voltage-enabled
    /// (bit 4) is added by the caller when the DC link is up.
    pub fn statusword_bits(self) -> u16 {
        match self {
            State::NotReadyToSwitchOn => 0x00,
            State::SwitchOnDisabled => 0x40,
            State::ReadyToSwitchOn => 0x21,
            State::SwitchedOn => 0x23,
            State::OperationEnabled => 0x27,
            State::QuickStopActive => 0x07,
            State::FaultReactionActive => 0x0F,
            State::Fault => 0x08,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            State::NotReadyToSwitchOn => "Not Ready to Switch On",
            State::SwitchOnDisabled => "Switch On Disabled",
            State::ReadyToSwitchOn => "Ready to Switch On",
            State::SwitchedOn => "Switched On",
            State::OperationEnabled => "Operation Enabled",
            State::QuickStopActive => "Quick Stop Active",
            State::FaultReactionActive => "Fault Reaction Active",
            State::Fault => "Fault",
        }
    }

    /// Master side: the controlword that moves the drive one step towards `target`
    /// (Operation Enabled, or back down for disable), per the transitions of Figure 10.
    /// Fault reset is not included: it needs a rising edge of bit 7 (see `fault_reset`).
    pub fn controlword_towards(self, target: State) -> u16 {
        use State::*;
        match target {
            OperationEnabled => match self {
                SwitchOnDisabled | NotReadyToSwitchOn => cw::SHUTDOWN,     // 2
                ReadyToSwitchOn => cw::SWITCH_ON_CMD,                      // 3
                SwitchedOn | OperationEnabled => cw::ENABLE_OPERATION_CMD, // 4
                QuickStopActive => cw::DISABLE_VOLTAGE,                    // 12
                FaultReactionActive | Fault => cw::DISABLE_VOLTAGE,
            },
            SwitchedOn => match self {
                OperationEnabled => cw::DISABLE_OPERATION, // 5
                ReadyToSwitchOn | SwitchedOn => cw::SWITCH_ON_CMD,
                _ => cw::SHUTDOWN,
            },
            ReadyToSwitchOn => cw::SHUTDOWN,
            QuickStopActive => cw::QUICK_STOP_CMD,
            _ => cw::DISABLE_VOLTAGE,
        }
    }
}

/// What a drive does on quick stop (0x605A, CiA 402-2 §8.4.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QuickStopOption {
    /// 0: disable drive function (coast).
    Disable,
    /// 1/5: slow-down ramp; 1 then Switch On Disabled, 5 stays in Quick Stop Active.
    SlowDownRamp { stay: bool },
    /// 2/6: quick-stop ramp.
    QuickStopRamp { stay: bool },
    /// 3/7: current limit.
    CurrentLimit { stay: bool },
    /// 4/8: voltage limit.
    VoltageLimit { stay: bool },
}

impl QuickStopOption {
    pub fn from_code(c: i16) -> Option<Self> {
        Some(match c {
            0 => Self::Disable,
            1 => Self::SlowDownRamp { stay: false },
            2 => Self::QuickStopRamp { stay: false },
            3 => Self::CurrentLimit { stay: false },
            4 => Self::VoltageLimit { stay: false },
            5 => Self::SlowDownRamp { stay: true },
            6 => Self::QuickStopRamp { stay: true },
            7 => Self::CurrentLimit { stay: true },
            8 => Self::VoltageLimit { stay: true },
            _ => return None,
        })
    }
    pub fn stays_in_quick_stop(self) -> bool {
        matches!(
            self,
            Self::SlowDownRamp { stay: true }
                | Self::QuickStopRamp { stay: true }
                | Self::CurrentLimit { stay: true }
                | Self::VoltageLimit { stay: true }
        )
    }
}

/// Device side: the state after the drive sees controlword `cw` (previous controlword
/// `prev` for the fault-reset edge). `FaultReactionActive` → `Fault` and quick stop →
/// Switch On Disabled after the ramp are timed by the device, not here.
pub fn device_transition(state: State, cw: u16, prev: u16) -> State {
    use State::*;
    let masked = cw & 0x8F;
    let shutdown = cw & 0x87 == 0x06;
    let switch_on = cw & 0x8F == 0x07;
    let enable_op = cw & 0x8F == 0x0F;
    let disable_voltage = cw & 0x82 == 0x00;
    let quick_stop = cw & 0x86 == 0x02;
    let _ = masked;
    match state {
        NotReadyToSwitchOn => state, // the device leaves it by itself (transition 1)
        SwitchOnDisabled => {
            if shutdown {
                ReadyToSwitchOn // 2
            } else {
                state
            }
        }
        ReadyToSwitchOn => {
            if enable_op {
                // 3 then 4 in one step, as most drives accept 0x0F here.
                OperationEnabled
            } else if switch_on {
                SwitchedOn // 3
            } else if disable_voltage || quick_stop {
                SwitchOnDisabled // 7
            } else {
                state
            }
        }
        SwitchedOn => {
            if enable_op {
                OperationEnabled // 4
            } else if shutdown {
                ReadyToSwitchOn // 6
            } else if disable_voltage || quick_stop {
                SwitchOnDisabled // 10
            } else {
                state
            }
        }
        OperationEnabled => {
            if switch_on {
                SwitchedOn // 5
            } else if shutdown {
                ReadyToSwitchOn // 8
            } else if disable_voltage {
                SwitchOnDisabled // 9
            } else if quick_stop {
                QuickStopActive // 11
            } else {
                state
            }
        }
        QuickStopActive => {
            if enable_op && cw & cw::QUICK_STOP != 0 {
                OperationEnabled // 16 (only where the quick-stop option stays)
            } else if disable_voltage {
                SwitchOnDisabled // 12
            } else {
                state
            }
        }
        FaultReactionActive => state,
        Fault => {
            if cw & cw::FAULT_RESET != 0 && prev & cw::FAULT_RESET == 0 {
                SwitchOnDisabled // 15, on the rising edge only
            } else {
                state
            }
        }
    }
}

/// Master side: walks one drive to Operation Enabled, one controlword per cycle. A drive in
/// Fault gets a fault reset on a rising edge of bit 7, and the walk waits for the
/// statusword to leave Fault before going on (python canopen's BaseNode402 has a FIXME
/// there). Shared by the CANopen and the Modbus CiA 402 layers.
#[derive(Clone, Copy, Debug, Default)]
pub struct Enabler {
    /// The controlword to send this cycle.
    pub controlword: u16,
    /// Fault resets tried since the last enable.
    pub reset_attempts: u32,
}

/// What `Enabler::step` found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EnableProgress {
    Enabled,
    Walking,
    /// In Fault after this many resets: the cause persists.
    ResetFailed,
}

impl Enabler {
    /// Fault resets before giving up.
    pub const MAX_RESETS: u32 = 5;

    /// Next controlword for the drive's `statusword`.
    pub fn step(&mut self, statusword: u16) -> EnableProgress {
        let st = State::from_statusword(statusword);
        match st {
            State::OperationEnabled => {
                self.controlword = cw::ENABLE_OPERATION_CMD;
                EnableProgress::Enabled
            }
            State::Fault | State::FaultReactionActive => {
                if self.controlword & cw::FAULT_RESET != 0 {
                    self.controlword = 0; // prepare the next rising edge
                } else {
                    self.reset_attempts += 1;
                    if self.reset_attempts > Self::MAX_RESETS {
                        return EnableProgress::ResetFailed;
                    }
                    self.controlword = cw::FAULT_RESET_CMD;
                }
                EnableProgress::Walking
            }
            _ => {
                self.controlword = st.controlword_towards(State::OperationEnabled);
                EnableProgress::Walking
            }
        }
    }
}

/// Master side: walks one drive to Switch On Disabled (no torque: disable voltage, CiA 402
/// transitions 7, 9, 10, 12), one controlword per step. A drive in Fault has no torque
/// either, but is not taken out of it: that is `FaultResetter`'s (a disable must not clear
/// an alarm the operator has not seen).
#[derive(Clone, Copy, Debug, Default)]
pub struct Disabler {
    /// The controlword to send this step.
    pub controlword: u16,
}

/// What `Disabler::step` found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DisableProgress {
    Disabled,
    Walking,
    /// In Fault (or its reaction): no torque, and left there.
    InFault,
}

impl Disabler {
    /// Next controlword for the drive's `statusword`.
    pub fn step(&mut self, statusword: u16) -> DisableProgress {
        self.controlword = cw::DISABLE_VOLTAGE;
        match State::from_statusword(statusword) {
            State::SwitchOnDisabled | State::NotReadyToSwitchOn => DisableProgress::Disabled,
            State::Fault | State::FaultReactionActive => DisableProgress::InFault,
            _ => DisableProgress::Walking,
        }
    }
}

/// Master side: takes one drive out of Fault to Switch On Disabled. Every step in Fault
/// sends a whole rising edge of bit 7 (low, then high: the controlword the drive holds may
/// have bit 7 high already); once out of it, bit 7 goes back down so that the next reset
/// is an edge again.
#[derive(Clone, Copy, Debug, Default)]
pub struct FaultResetter {
    /// Resets sent.
    pub resets: u32,
}

/// What `FaultResetter::step` found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ResetProgress {
    /// Not (or no longer) in Fault.
    Cleared,
    Walking,
}

impl FaultResetter {
    /// The controlwords to send this step, in order, for the drive's `statusword`.
    pub fn step(&mut self, statusword: u16) -> (ResetProgress, &'static [u16]) {
        match State::from_statusword(statusword) {
            State::Fault | State::FaultReactionActive => {
                self.resets += 1;
                (ResetProgress::Walking, &[cw::DISABLE_VOLTAGE, cw::FAULT_RESET_CMD])
            }
            _ if self.resets > 0 => (ResetProgress::Cleared, &[cw::DISABLE_VOLTAGE]),
            _ => (ResetProgress::Cleared, &[]),
        }
    }
}

/// What a drive's statusword says of a homing under way (mode 6, controlword bit 4 up):
/// bit 13 is a homing error, bits 12 (homing attained) and 10 (target reached) together its
/// end. Shared by the CANopen master's cyclic homing and the Modbus drives' homing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HomingProgress {
    Homing,
    Attained,
    /// Bit 13: before attained, as a drive may show both.
    Error,
}

impl HomingProgress {
    /// The controlword that starts the homing (and holds it): enable operation with bit 4.
    pub const START: u16 = cw::ENABLE_OPERATION_CMD | cw::OMS4;

    pub fn of(statusword: u16) -> HomingProgress {
        if statusword & sw::OMS13 != 0 {
            HomingProgress::Error
        } else if statusword & sw::OMS12 != 0 && statusword & sw::TARGET_REACHED != 0 {
            HomingProgress::Attained
        } else {
            HomingProgress::Homing
        }
    }
}

/// Modes of operation (0x6060 / 0x6061).
pub mod mode {
    pub const PROFILE_POSITION: i8 = 1;
    pub const PROFILE_VELOCITY: i8 = 3;
    pub const HOMING: i8 = 6;
    /// Interpolated position (IP): targets in 0x60C1:1, controlword bit 4 "enable ip",
    /// statusword bit 12 "ip mode active".
    pub const INTERPOLATED_POSITION: i8 = 7;
    pub const CYCLIC_SYNC_POSITION: i8 = 8;
    pub const CYCLIC_SYNC_VELOCITY: i8 = 9;
    pub const CYCLIC_SYNC_TORQUE: i8 = 10;

    pub fn name(m: i8) -> &'static str {
        match m {
            0 => "no mode",
            1 => "profile position",
            3 => "profile velocity",
            4 => "profile torque",
            6 => "homing",
            7 => "interpolated position",
            8 => "cyclic synchronous position",
            9 => "cyclic synchronous velocity",
            10 => "cyclic synchronous torque",
            _ => "manufacturer specific",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn homing_ends_on_attained_with_target_reached_and_an_error_comes_first() {
        let oe = State::OperationEnabled.statusword_bits();
        assert_eq!(HomingProgress::of(oe | sw::TARGET_REACHED), HomingProgress::Homing);
        assert_eq!(HomingProgress::of(oe | sw::OMS12), HomingProgress::Homing);
        assert_eq!(HomingProgress::of(oe | sw::OMS12 | sw::TARGET_REACHED), HomingProgress::Attained);
        assert_eq!(HomingProgress::of(oe | sw::OMS13 | sw::OMS12 | sw::TARGET_REACHED), HomingProgress::Error);
    }

    #[test]
    fn statusword_decodes_every_state_and_round_trips() {
        for s in [
            State::NotReadyToSwitchOn,
            State::SwitchOnDisabled,
            State::ReadyToSwitchOn,
            State::SwitchedOn,
            State::OperationEnabled,
            State::QuickStopActive,
            State::FaultReactionActive,
            State::Fault,
        ] {
            // With voltage enabled, remote and target reached set: still the same state.
            let word = s.statusword_bits() | sw::VOLTAGE_ENABLED | sw::REMOTE | sw::TARGET_REACHED;
            assert_eq!(State::from_statusword(word), s, "{word:#06x}");
        }
        assert_eq!(State::from_statusword(0x0237), State::OperationEnabled);
        assert_eq!(State::from_statusword(0x0250), State::SwitchOnDisabled);
        assert_eq!(State::from_statusword(0x0218), State::Fault);
    }

    #[test]
    fn master_walks_the_device_to_operation_enabled() {
        let mut s = State::SwitchOnDisabled;
        let mut prev = 0;
        for _ in 0..4 {
            let c = s.controlword_towards(State::OperationEnabled);
            s = device_transition(s, c, prev);
            prev = c;
        }
        assert_eq!(s, State::OperationEnabled);
    }

    #[test]
    fn enabler_resets_a_fault_on_an_edge_and_walks_on() {
        let mut s = State::Fault;
        let mut e = Enabler::default();
        let mut prev = 0;
        for _ in 0..8 {
            if e.step(s.statusword_bits()) == EnableProgress::Enabled {
                break;
            }
            s = device_transition(s, e.controlword, prev);
            prev = e.controlword;
        }
        assert_eq!(s, State::OperationEnabled);
        assert_eq!(e.reset_attempts, 1);
        // A fault that never clears gives up after MAX_RESETS edges.
        let mut e = Enabler::default();
        let mut p = EnableProgress::Walking;
        for _ in 0..20 {
            p = e.step(State::Fault.statusword_bits());
            if p == EnableProgress::ResetFailed {
                break;
            }
        }
        assert_eq!(p, EnableProgress::ResetFailed);
    }

    #[test]
    fn fault_reset_needs_a_rising_edge() {
        assert_eq!(device_transition(State::Fault, 0x80, 0x80), State::Fault);
        assert_eq!(device_transition(State::Fault, 0x80, 0x00), State::SwitchOnDisabled);
    }

    #[test]
    fn quick_stop_and_disable_from_operation_enabled() {
        assert_eq!(device_transition(State::OperationEnabled, cw::QUICK_STOP_CMD, 0x0F), State::QuickStopActive);
        assert_eq!(device_transition(State::OperationEnabled, cw::DISABLE_VOLTAGE, 0x0F), State::SwitchOnDisabled);
        assert_eq!(device_transition(State::OperationEnabled, cw::SHUTDOWN, 0x0F), State::ReadyToSwitchOn);
        assert_eq!(device_transition(State::OperationEnabled, cw::DISABLE_OPERATION, 0x0F), State::SwitchedOn);
    }
}
