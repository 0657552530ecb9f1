//! CANopen (CiA 301) codecs: NMT, heartbeat, SDO, PDO, SYNC, EMCY. Pure functions and
//! plain types; no I/O, no clocks.

pub mod eds;
pub mod emcy;
pub mod nmt;
pub mod pdo;
pub mod sdo;

/// Predefined connection set (CiA 301 §7.3.5).
pub mod cob {
    pub const NMT: u16 = 0x000;
    pub const SYNC: u16 = 0x080;
    pub const EMCY_BASE: u16 = 0x080;
    pub const TPDO1: u16 = 0x180;
    pub const RPDO1: u16 = 0x200;
    pub const TPDO2: u16 = 0x280;
    pub const RPDO2: u16 = 0x300;
    pub const TPDO3: u16 = 0x380;
    pub const RPDO3: u16 = 0x400;
    pub const TPDO4: u16 = 0x480;
    pub const RPDO4: u16 = 0x500;
    /// Server → client (SDO upload/download responses).
    pub const SDO_TX: u16 = 0x580;
    /// Client → server (SDO requests).
    pub const SDO_RX: u16 = 0x600;
    pub const HEARTBEAT: u16 = 0x700;

    /// The function code part of a COB-ID and the node id, for the predefined set.
    pub fn split(cob: u16) -> (u16, u8) {
        (cob & 0x780, (cob & 0x7F) as u8)
    }
}

/// The SYNC frame: empty, or with a 1-byte counter (1…240, CiA 301 §7.2.5.3).
pub fn sync_frame(counter: Option<u8>) -> crate::CanFrame {
    match counter {
        Some(c) => crate::CanFrame::new(cob::SYNC, &[c]),
        None => crate::CanFrame::new(cob::SYNC, &[]),
    }
}

/// Object dictionary indices used by master and emulator.
pub mod od {
    pub const DEVICE_TYPE: u16 = 0x1000;
    pub const ERROR_REGISTER: u16 = 0x1001;
    pub const COB_ID_SYNC: u16 = 0x1005;
    pub const COMM_CYCLE_PERIOD: u16 = 0x1006;
    pub const DEVICE_NAME: u16 = 0x1008;
    /// Node guarding: guard time (ms) and life time factor (CiA 301 §7.2.8.3.1).
    pub const GUARD_TIME: u16 = 0x100C;
    pub const LIFE_TIME_FACTOR: u16 = 0x100D;
    pub const HW_VERSION: u16 = 0x1009;
    pub const SW_VERSION: u16 = 0x100A;
    pub const COB_ID_EMCY: u16 = 0x1014;
    pub const CONSUMER_HEARTBEAT: u16 = 0x1016;
    pub const PRODUCER_HEARTBEAT: u16 = 0x1017;
    pub const IDENTITY: u16 = 0x1018;
    /// Error behaviour (CiA 301 §7.5.2.32): sub 1, the NMT state a communication error
    /// (heartbeat or life guarding event, bus-off) takes the node to: 0 pre-operational
    /// (if it was operational), 1 no change, 2 stopped.
    pub const ERROR_BEHAVIOUR: u16 = 0x1029;
    pub const RPDO_COMM: u16 = 0x1400;
    pub const RPDO_MAP: u16 = 0x1600;
    pub const TPDO_COMM: u16 = 0x1800;
    pub const TPDO_MAP: u16 = 0x1A00;
    pub const ABORT_CONNECTION: u16 = 0x6007;
    pub const ERROR_CODE: u16 = 0x603F;
    pub const CONTROLWORD: u16 = 0x6040;
    pub const STATUSWORD: u16 = 0x6041;
    pub const QUICK_STOP_OPTION: u16 = 0x605A;
    pub const SHUTDOWN_OPTION: u16 = 0x605B;
    pub const DISABLE_OPERATION_OPTION: u16 = 0x605C;
    pub const FAULT_REACTION_OPTION: u16 = 0x605E;
    pub const MODES_OF_OPERATION: u16 = 0x6060;
    pub const MODES_DISPLAY: u16 = 0x6061;
    /// Position actual internal value, in encoder increments (not scaled by the factor group).
    pub const POSITION_ACTUAL_INTERNAL: u16 = 0x6063;
    pub const POSITION_ACTUAL: u16 = 0x6064;
    pub const FOLLOWING_ERROR_WINDOW: u16 = 0x6065;
    pub const FOLLOWING_ERROR_TIMEOUT: u16 = 0x6066;
    pub const VELOCITY_ACTUAL: u16 = 0x606C;
    pub const TARGET_POSITION: u16 = 0x607A;
    /// Torque actual value, per mille of the rated torque (0x6076).
    pub const TORQUE_ACTUAL: u16 = 0x6077;
    /// Max torque, per mille of the rated torque (CiA 402 §6.9, optional): the drive's torque
    /// limit.
    pub const MAX_TORQUE: u16 = 0x6072;
    /// CSP's torque offset, per mille of the rated torque: added to the drive's torque command.
    pub const TORQUE_OFFSET: u16 = 0x60B2;
    pub const SOFTWARE_LIMIT: u16 = 0x607D;
    /// Polarity: bit 7 inverts positions (demand and actual), bit 6 velocities.
    pub const POLARITY: u16 = 0x607E;
    /// Factor group (CiA 402-2 §6.3): position encoder resolution (sub 1 increments per
    /// sub 2 motor revolutions), gear ratio (sub 1 motor revolutions per sub 2 shaft
    /// revolutions), feed constant (sub 1 feed in position units per sub 2 shaft revolutions).
    pub const ENCODER_RESOLUTION: u16 = 0x608F;
    pub const GEAR_RATIO: u16 = 0x6091;
    pub const FEED_CONSTANT: u16 = 0x6092;
    pub const HOMING_METHOD: u16 = 0x6098;
    pub const HOMING_SPEEDS: u16 = 0x6099;
    pub const HOMING_ACCEL: u16 = 0x609A;
    /// Interpolation sub-mode select (IP): 0 = linear.
    pub const INTERPOLATION_SUB_MODE: u16 = 0x60C0;
    /// Interpolation data record (IP): sub 1 = the position set-point.
    pub const INTERPOLATION_DATA: u16 = 0x60C1;
    pub const INTERPOLATION_PERIOD: u16 = 0x60C2;
    /// Interpolation data configuration (IP): sub 6 = buffer clear (0 clear, 1 enable).
    pub const INTERPOLATION_BUFFER: u16 = 0x60C4;
    pub const FOLLOWING_ERROR_ACTUAL: u16 = 0x60F4;
    pub const TARGET_VELOCITY: u16 = 0x60FF;
    pub const SUPPORTED_MODES: u16 = 0x6502;
}
