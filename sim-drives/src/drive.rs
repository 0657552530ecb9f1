//! One emulated CiA 402 amplifier on CANopen: NMT slave, SDO server, PDOs, SYNC consumer,
//! heartbeat producer and consumer, EMCY producer, the 402 device state machine and the
//! servo (see `servo`). Time is passed in (ns); the world decides when things happen.

use crate::config::{DriveConfig, DriveKind};
use crate::od::{Access, DType, Od, Value};
use crate::servo::{Command, Servo};
use cncgw_bus::canopen::emcy::Emcy;
use cncgw_bus::canopen::nmt::{decode_heartbeat, heartbeat_frame, NmtCommand, NmtState};
use cncgw_bus::canopen::pdo::MapEntry;
use cncgw_bus::canopen::sdo::{abort, SdoRequest, SdoResponse};
use cncgw_bus::canopen::{cob, od as ix};
use cncgw_bus::cia402::{cw, device_transition, mode, sw, QuickStopOption, State};
use cncgw_bus::CanFrame;
use std::collections::{BTreeMap, VecDeque};

mod block;
pub mod profile;
mod shape;

const MS: u64 = 1_000_000;
const N_RPDO: u16 = 2;
const N_TPDO: u16 = 2;
/// Manufacturer-specific write-only object (an access code, as many drives have).
pub const ACCESS_CODE: u16 = 0x2000;
/// Manufacturer-specific DOMAIN (read-write, up to `USER_DATA_LEN` bytes, empty after a
/// reset): where a commissioning tool keeps its notes or a parameter image. The large
/// object that block transfers are tested and measured with.
pub const USER_DATA: u16 = 0x2200;
pub const USER_DATA_LEN: usize = 4096;
/// Manufacturer-specific record: faults injected at run time (README, "Fault injection").
pub const SIM_FAULTS: u16 = 0x2100;
/// Manufacturer-specific U8: in CSP, how many SYNCs in a row without a new target (a lost
/// RPDO) the set-point goes on with the last increment before it holds (real CSP drives with
/// interpolation bridge a lost set-point so; 0 = hold at once).
pub const CSP_EXTRAPOLATE: u16 = 0x2102;
/// Manufacturer-specific parameters a start-up list (`[[axes.NAME.sdo]]`) writes, like a
/// vendor's gains and delays: 0x2003 U16 brake release delay (ms, 0…2000), 0x2005 I32
/// velocity loop gain, 0x2006 U16 current limit in 0.1 A that the drive keeps in whole
/// amperes (a written 1234 reads back 1230: what a read-back after writing must catch),
/// 0x2004 U8 encoder type, read-only (a refused write).
pub const VENDOR_BRAKE_DELAY: u16 = 0x2003;
pub const VENDOR_ENCODER_TYPE: u16 = 0x2004;
pub const VENDOR_VELOCITY_GAIN: u16 = 0x2005;
pub const VENDOR_CURRENT_LIMIT: u16 = 0x2006;
/// Default of `CSP_EXTRAPOLATE`: bridges up to 3 lost set-points (6 ms at 2 ms).
pub const CSP_EXTRAPOLATE_DEFAULT: i64 = 3;
/// Sub-indices of `SIM_FAULTS`.
pub mod fault_sub {
    /// U16: write an error code to raise that fault now (reads back the last one).
    pub const RAISE: u8 = 1;
    /// U8 0/1: encoder lost: fault 0x7305, 0x6064 frozen; reset refused while 1.
    pub const ENCODER_LOST: u8 = 2;
    /// U8 0/1: DC-link undervoltage: fault 0x3220, statusword bit 4 off; reset refused while 1.
    pub const UNDERVOLTAGE: u8 = 3;
    /// U8: write 1 to trip on overcurrent (0x2310) now; reads 0.
    pub const OVERCURRENT: u8 = 4;
    /// U32: extra dry friction on the motor shaft, mN·m (a jammed slide → following error).
    pub const JAM_MNM: u8 = 5;
    /// U8 0/1: the heartbeat producer stops (the node otherwise alive).
    pub const HEARTBEAT_MUTED: u8 = 6;
    /// U32: the node falls silent (deaf and mute) for this many ms after the SDO answer;
    /// 0xFFFFFFFF = until the process restarts. Reads 0.
    pub const SILENT_MS: u8 = 7;
    /// U16 0–1000: each RPDO received and each TPDO sent is lost with this probability (‰).
    pub const PDO_DROP_PERMILLE: u8 = 8;
    /// U32 0–1000000: TPDOs leave this many µs after their SYNC or event.
    pub const TPDO_DELAY_US: u8 = 9;
    /// U8: write 1 to switch the IP buffer off (0x60C4:6 = 0), as a drive does on a buffer
    /// underrun: statusword bit 12 "ip mode active" drops; reads 0.
    pub const IP_DISABLE: u8 = 10;
    /// U8 0/1: a SYNC-producing drive (0x1005 bit 30) stops producing SYNC (the node
    /// otherwise alive): an external SYNC lost.
    pub const SYNC_MUTED: u8 = 11;
}
const POSITION_DEMAND: u16 = 0x6062;
const POSITION_WINDOW: u16 = 0x6067;
const TORQUE_ACTUAL: u16 = ix::TORQUE_ACTUAL;
/// CSP's torque offset: a controller's friction or gravity feed-forward.
const TORQUE_OFFSET: u16 = ix::TORQUE_OFFSET;
const PROFILE_DECEL: u16 = 0x6084;
const QUICK_STOP_DECEL: u16 = 0x6085;
const FAULT_REACTION: u16 = ix::FAULT_REACTION_OPTION;
/// Shutdown option code (transition 8) and disable operation option code (transition 5):
/// 0 = switch the power stage off at once (the motor coasts), 1 = slow down on the profile
/// deceleration (0x6084) first. Real drives differ in the default; ours coasts, like the
/// drives that left a spindle free-wheeling before the master began to configure them.
const SHUTDOWN_OPTION: u16 = ix::SHUTDOWN_OPTION;
const DISABLE_OPTION: u16 = ix::DISABLE_OPERATION_OPTION;
/// A stop that has not finished after this long is finished by switching the power off
/// (a jammed axis must not keep a quick stop alive forever).
const STOP_TIMEOUT: u64 = 5_000 * MS;
/// Rated torque as a fraction of the peak torque (servo motors: peak ≈ 3 × rated).
const RATED_OF_PEAK: f64 = 1.0 / 3.0;
/// I²t budget: 3 s at peak torque ((3² − 1) × 3 s) before the overload trips.
const I2T_LIMIT: f64 = 24.0;

#[derive(Clone, Debug)]
enum SdoState {
    Idle,
    Upload { index: u16, sub: u8, data: Vec<u8>, pos: usize, toggle: bool },
    Download { index: u16, sub: u8, size: Option<u32>, buf: Vec<u8>, toggle: bool },
    BlockDown(block::Down),
    BlockUp(block::Up),
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum StopWhy {
    Halt,
    QuickStop,
    FaultReaction,
    /// Shutdown or disable operation with a slow-down option (0x605B / 0x605C = 1): ramp to
    /// rest in Operation Enabled, then take the transition to this state.
    Disable(State),
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Brake {
    /// Ramp the demand down at this deceleration (counts/s²).
    Ramp(f64),
    /// Command zero speed; the torque limit decides the deceleration.
    TorqueLimit,
}

#[derive(Clone, Copy, Debug)]
struct Stop {
    why: StopWhy,
    brake: Brake,
    /// Demand speed (counts/s) and position (counts) of the ramp.
    v: f64,
    pos: f64,
    started: u64,
}

/// Copies of objects the control tick reads (the dictionary is a map; the tick runs at
/// 20 kHz). Refreshed by `recache` after every write from the bus and every reset.
#[derive(Clone, Copy, Debug, Default)]
struct Hot {
    /// 0x1016: (producer node, timeout ns) per entry; node 0 = unused.
    consumers: [(u8, u64); 2],
    /// Some TPDO is event-driven (254/255) and valid.
    event_tpdo: bool,
    mode: i8,
    ferr_window: i64,
    ferr_timeout: u64,
    /// 0x1005 COB-ID and the RPDO COB-IDs (0x1400+i:1, raw): every frame is matched
    /// against them, by every drive.
    sync_cob: u16,
    rpdo_cob: [u32; N_RPDO as usize],
    // Injected conditions (0x2100).
    encoder_lost: bool,
    undervoltage: bool,
    hb_muted: bool,
    pdo_drop_permille: u32,
    tpdo_delay: u64,
    /// Factor group: encoder increments per position unit; 0x607E bit 7 as ±1.
    inc_per_unit: f64,
    pos_sign: f64,
}

/// An emulated drive. Read its state with the accessors; inject faults with the `inject_*`
/// and `set_*` methods.
pub struct SimDrive {
    cfg: DriveConfig,
    od: Od,
    nmt: NmtState,
    /// Boot-up message due (power-on or NMT reset).
    boot_at: Option<u64>,
    state: State,
    prev_cw: u16,
    servo: Servo,
    step_s: f64,
    // Motion.
    demand: f64,
    vff: f64,
    seg_start: f64,
    seg_end: f64,
    seg_t0: u64,
    seg_len: u64,
    /// Set-point velocity of the current segment, counts/s.
    seg_v: f64,
    /// Last latched target (raw) and its unwrapped value; `None` = next target is taken
    /// relative to the actual position.
    target_ref: Option<(i32, f64)>,
    /// A target position was written (RPDO or SDO) since the last SYNC.
    target_fresh: bool,
    /// SYNCs in a row without a new target (see `CSP_EXTRAPOLATE`).
    csp_missed: u32,
    target_vel: f64,
    stop: Option<Stop>,
    limit_active: bool,
    // SYNC and PDOs.
    last_sync: Option<u64>,
    sync_period: u64,
    tpdo_count: [u32; N_TPDO as usize],
    tpdo_last: [Option<Vec<u8>>; N_TPDO as usize],
    tpdo_last_t: [u64; N_TPDO as usize],
    rpdo_buf: [Option<Vec<u8>>; N_RPDO as usize],
    rpdo_len_error: bool,
    // Heartbeat.
    hb_next: Option<u64>,
    /// Last heartbeat seen per producer node (monitoring is armed once one is seen).
    hb_seen: BTreeMap<u8, u64>,
    // Following error.
    ferr_since: Option<u64>,
    ferr_flag: bool,
    /// Motor thermal (I²t) load: ∫((τ/τ_rated)² − 1) dt, ≥ 0; trips at `I2T_LIMIT`.
    i2t: f64,
    sdo: SdoState,
    silent: bool,
    /// End of a timed silence (`u64::MAX`: none planned).
    silent_until: u64,
    /// A silence to start once the present output (the SDO answer that asked) is out.
    silence_pending: Option<u64>,
    /// 0x6064 held at the instant the encoder was lost.
    encoder_frozen: Option<i64>,
    /// TPDOs waiting for their injected delay: (due, frame).
    delayed: VecDeque<(u64, CanFrame)>,
    /// CSP set-points waiting in the drive (`Extra::transport_delay_cycles`): (raw, fresh,
    /// torque offset 0x60B2).
    transport: VecDeque<(i32, bool, i16)>,
    /// The torque offset (0x60B2, per mille of the rated torque) of the set-point being
    /// followed: it acts with its target, after the same transport delay.
    torque_offset: i16,
    /// PDO-loss draws (xorshift64; seeded by the node id, so runs are reproducible).
    rng: u64,
    /// Objects read every control tick, copied out of the dictionary after each write.
    hot: Hot,
    /// Profile position and homing (modes 1 and 6).
    prof: profile::Prof,
    /// A mode written to 0x6060 that does not show yet (`Shape::mode_switch_ms`).
    pending_mode: Option<shape::PendingMode>,
    /// Next SYNC this drive produces (0x1005 bit 30).
    own_sync_next: Option<u64>,
    /// Node guarding (slave side).
    guarding: shape::Guarding,
    /// Modes (bit m) the drive has been in Operation Enabled in, and NMT resets received:
    /// what a test asks afterwards ("never enabled before the mode", "nothing was reset").
    enabled_modes: u32,
    nmt_resets: u32,
    out: Vec<CanFrame>,
}

fn error_register_bits(code: u16) -> u8 {
    let class = match code >> 12 {
        0x2 => 0x02,
        0x3 => 0x04,
        0x4 => 0x08,
        0x8 if code >> 8 == 0x81 || code >> 8 == 0x82 => 0x10,
        0x8 => 0x20,
        0xF => 0x80,
        _ => 0x00,
    };
    0x01 | class
}

fn restricted_cob(id: u32) -> bool {
    matches!(id, 0x000..=0x07F | 0x101..=0x180 | 0x581..=0x5FF | 0x601..=0x67F | 0x6E0..=0x6FF | 0x701..=0x7FF)
}

fn build_od(c: &DriveConfig) -> Od {
    use Access::*;
    use DType::*;
    let n = c.node as i64;
    let mut od = Od::new();
    od.add(ix::DEVICE_TYPE, 0, U32, Const, false, 0x0002_0192);
    od.add(ix::ERROR_REGISTER, 0, U8, Ro, true, 0);
    let sh = &c.shape;
    od.add(ix::COB_ID_SYNC, 0, U32, Rw, false, if sh.sync_producer { 0x4000_0080 } else { 0x80 });
    od.add(ix::COMM_CYCLE_PERIOD, 0, U32, Rw, false, if sh.sync_producer { sh.sync_period_us as i64 } else { 0 });
    od.add_str(ix::DEVICE_NAME, 0, Const, &c.device_name);
    od.add_str(ix::HW_VERSION, 0, Const, "1.0");
    od.add_str(ix::SW_VERSION, 0, Const, concat!("sim-drives ", env!("CARGO_PKG_VERSION")));
    od.add(ix::COB_ID_EMCY, 0, U32, Rw, false, 0x80 + n);
    if sh.node_guarding {
        od.add(ix::GUARD_TIME, 0, U16, Rw, false, 0);
        od.add(ix::LIFE_TIME_FACTOR, 0, U8, Rw, false, 0);
    }
    if sh.heartbeat_consumer {
        od.add(ix::CONSUMER_HEARTBEAT, 0, U8, Const, false, 2);
        od.add(ix::CONSUMER_HEARTBEAT, 1, U32, Rw, false, 0);
        od.add(ix::CONSUMER_HEARTBEAT, 2, U32, Rw, false, 0);
    }
    od.add(ix::PRODUCER_HEARTBEAT, 0, U16, Rw, false, 0);
    let ids = c.shape.identity_subs.min(4);
    od.add(ix::IDENTITY, 0, U8, Const, false, ids as i64);
    for (s, v) in [c.vendor_id, c.product_code, c.revision, c.serial].into_iter().enumerate().take(ids as usize) {
        od.add(ix::IDENTITY, s as u8 + 1, U32, Const, false, v as i64);
    }
    // RPDO1: controlword + target position, valid; RPDO2: controlword + target velocity,
    // invalid until the master enables it (CSV spindles).
    let rpdo = [
        (0x200 + n, vec![MapEntry::new(ix::CONTROLWORD, 0, 16), MapEntry::new(ix::TARGET_POSITION, 0, 32)]),
        (0x8000_0000 | (0x300 + n), vec![MapEntry::new(ix::CONTROLWORD, 0, 16), MapEntry::new(ix::TARGET_VELOCITY, 0, 32)]),
    ];
    for (i, (cobid, map)) in rpdo.iter().enumerate() {
        let i = i as u16;
        od.add(ix::RPDO_COMM + i, 0, U8, Const, false, 2);
        od.add(ix::RPDO_COMM + i, 1, U32, Rw, false, *cobid);
        od.add(ix::RPDO_COMM + i, 2, U8, Rw, false, 1);
        od.add_range(ix::RPDO_MAP + i, 0, U8, Rw, false, map.len() as i64, 0, 8);
        for s in 1..=8u8 {
            let v = map.get(s as usize - 1).map(|e| e.encode() as i64).unwrap_or(0);
            od.add(ix::RPDO_MAP + i, s, U32, Rw, false, v);
        }
    }
    let tpdo = [
        (0x180 + n, vec![MapEntry::new(ix::STATUSWORD, 0, 16), MapEntry::new(ix::POSITION_ACTUAL, 0, 32)]),
        (0x8000_0000 | (0x280 + n), vec![MapEntry::new(ix::STATUSWORD, 0, 16), MapEntry::new(ix::VELOCITY_ACTUAL, 0, 32)]),
    ];
    for (i, (cobid, map)) in tpdo.iter().enumerate() {
        let i = i as u16;
        // Sub 4 is reserved in CiA 301 and absent here, as on real devices.
        od.add(ix::TPDO_COMM + i, 0, U8, Const, false, 5);
        od.add(ix::TPDO_COMM + i, 1, U32, Rw, false, *cobid);
        od.add(ix::TPDO_COMM + i, 2, U8, Rw, false, 1);
        od.add(ix::TPDO_COMM + i, 3, U16, Rw, false, 0);
        od.add(ix::TPDO_COMM + i, 5, U16, Rw, false, 0);
        od.add_range(ix::TPDO_MAP + i, 0, U8, Rw, false, map.len() as i64, 0, 8);
        for s in 1..=8u8 {
            let v = map.get(s as usize - 1).map(|e| e.encode() as i64).unwrap_or(0);
            od.add(ix::TPDO_MAP + i, s, U32, Rw, false, v);
        }
    }
    od.add(ACCESS_CODE, 0, U32, Wo, false, 0);
    od.add_domain(USER_DATA, 0, Rw, USER_DATA_LEN);
    {
        use fault_sub::*;
        od.add(SIM_FAULTS, 0, U8, Const, false, 11);
        od.add(SIM_FAULTS, RAISE, U16, Rw, false, 0);
        od.add_range(SIM_FAULTS, ENCODER_LOST, U8, Rw, false, 0, 0, 1);
        od.add_range(SIM_FAULTS, UNDERVOLTAGE, U8, Rw, false, 0, 0, 1);
        od.add_range(SIM_FAULTS, OVERCURRENT, U8, Rw, false, 0, 0, 1);
        od.add(SIM_FAULTS, JAM_MNM, U32, Rw, false, 0);
        od.add_range(SIM_FAULTS, HEARTBEAT_MUTED, U8, Rw, false, 0, 0, 1);
        od.add(SIM_FAULTS, SILENT_MS, U32, Rw, false, 0);
        od.add_range(SIM_FAULTS, PDO_DROP_PERMILLE, U16, Rw, false, 0, 0, 1000);
        od.add_range(SIM_FAULTS, TPDO_DELAY_US, U32, Rw, false, 0, 0, 1_000_000);
        od.add_range(SIM_FAULTS, IP_DISABLE, U8, Rw, false, 0, 0, 1);
        od.add_range(SIM_FAULTS, SYNC_MUTED, U8, Rw, false, 0, 0, 1);
    }
    if sh.abort_connection_object {
        od.add_range(ix::ABORT_CONNECTION, 0, I16, Rw, false, 1, 0, 3);
    }
    if sh.error_behaviour_object {
        // Sub 1, a communication error's NMT reaction: 0 pre-operational (CiA 301's default),
        // 1 no change, 2 stopped. Shipped as 1, as a vendor may, so that a master's start-up
        // write is seen (the master writes 0).
        od.add(ix::ERROR_BEHAVIOUR, 0, U8, Const, false, 1);
        od.add_range(ix::ERROR_BEHAVIOUR, 1, U8, Rw, false, 1, 0, 2);
    }
    od.add(ix::ERROR_CODE, 0, U16, Ro, true, 0);
    od.add(ix::CONTROLWORD, 0, U16, Rw, true, 0);
    od.add(ix::STATUSWORD, 0, U16, Ro, true, 0);
    if sh.optional_402_objects {
        od.add_range(ix::QUICK_STOP_OPTION, 0, I16, Rw, false, 2, 0, 8);
        od.add_range(FAULT_REACTION, 0, I16, Rw, false, 2, 0, 4);
        od.add_range(SHUTDOWN_OPTION, 0, I16, Rw, false, 0, 0, 1);
        od.add_range(DISABLE_OPTION, 0, I16, Rw, false, 0, 0, 1);
    }
    od.add(ix::MODES_OF_OPERATION, 0, I8, Rw, true, sh.boot_mode as i64);
    od.add(ix::MODES_DISPLAY, 0, I8, Ro, sh.mode_display_pdo, sh.boot_mode as i64);
    od.add(POSITION_DEMAND, 0, I32, Ro, true, 0);
    od.add(ix::POSITION_ACTUAL, 0, I32, Ro, true, 0);
    // Position objects are in position units (the factor group below).
    let per_unit = c.increments_per_unit();
    let window = (c.following_error_window as f64 / per_unit).round().clamp(1.0, u32::MAX as f64) as i64;
    od.add(ix::FOLLOWING_ERROR_WINDOW, 0, U32, Rw, false, window);
    od.add(ix::FOLLOWING_ERROR_TIMEOUT, 0, U16, Rw, false, c.following_error_timeout_ms as i64);
    od.add(POSITION_WINDOW, 0, U32, Rw, false, 10);
    od.add(ix::VELOCITY_ACTUAL, 0, I32, Ro, true, 0);
    od.add(TORQUE_ACTUAL, 0, I16, Ro, true, 0);
    od.add(TORQUE_OFFSET, 0, I16, Rw, true, 0);
    od.add(ix::TARGET_POSITION, 0, I32, Rw, true, 0);
    od.add(CSP_EXTRAPOLATE, 0, U8, Rw, false, CSP_EXTRAPOLATE_DEFAULT);
    if sh.optional_402_objects {
        od.add(ix::SOFTWARE_LIMIT, 0, U8, Const, false, 2);
        od.add(ix::SOFTWARE_LIMIT, 1, I32, Rw, false, i32::MIN as i64);
        od.add(ix::SOFTWARE_LIMIT, 2, I32, Rw, false, i32::MAX as i64);
        // The torque limit the physics' peak torque is, in the unit of 0x6077.
        od.add(ix::MAX_TORQUE, 0, U16, Ro, false, (1000.0 / RATED_OF_PEAK).round() as i64);
    }
    od.add_range(PROFILE_DECEL, 0, U32, Rw, false, c.profile_decel as i64, 1, u32::MAX as i64);
    od.add_range(QUICK_STOP_DECEL, 0, U32, Rw, false, c.quick_stop_decel as i64, 1, u32::MAX as i64);
    od.add(ix::INTERPOLATION_PERIOD, 0, U8, Const, false, 2);
    od.add(ix::INTERPOLATION_PERIOD, 1, U8, Rw, false, 0);
    od.add_range(ix::INTERPOLATION_PERIOD, 2, I8, Rw, false, -3, -6, 0);
    od.add(ix::FOLLOWING_ERROR_ACTUAL, 0, I32, Ro, true, 0);
    od.add(ix::TARGET_VELOCITY, 0, I32, Rw, true, 0);
    // Profile position and homing (drive/profile.rs).
    {
        use profile::*;
        let rev = c.counts_per_rev as i64;
        od.add(HOME_OFFSET, 0, I32, Rw, false, 0);
        od.add(PROFILE_VELOCITY, 0, U32, Rw, true, 5 * rev);
        od.add_range(PROFILE_ACCEL, 0, U32, Rw, false, c.profile_decel as i64, 1, u32::MAX as i64);
        od.add_range(ix::HOMING_METHOD, 0, I8, Rw, false, 0, -128, 127);
        od.add(ix::HOMING_SPEEDS, 0, U8, Const, false, 2);
        od.add_range(ix::HOMING_SPEEDS, 1, U32, Rw, false, rev, 1, u32::MAX as i64);
        od.add_range(ix::HOMING_SPEEDS, 2, U32, Rw, false, (rev / 10).max(1), 1, u32::MAX as i64);
        od.add_range(ix::HOMING_ACCEL, 0, U32, Rw, false, c.profile_decel as i64, 1, u32::MAX as i64);
        od.add(DIGITAL_INPUTS, 0, U32, Ro, true, 0);
        od.add(SIM_SWITCHES, 0, U8, Const, false, 4);
        let sw = &c.switches;
        od.add(SIM_SWITCHES, 1, I32, Rw, false, sw.negative.unwrap_or(i32::MIN) as i64);
        od.add(SIM_SWITCHES, 2, I32, Rw, false, sw.positive.unwrap_or(i32::MAX) as i64);
        od.add(SIM_SWITCHES, 3, I32, Rw, false, sw.home.unwrap_or(i32::MAX) as i64);
        od.add(SIM_SWITCHES, 4, U32, Rw, false, sw.index_period.unwrap_or(10_000) as i64);
    }
    // Supported modes: bit m−1 for mode m (default PP, homing, CSP, CSV = 0x1A1).
    if sh.supported_modes_object {
        od.add(ix::SUPPORTED_MODES, 0, U32, Const, false, sh.supported_modes_bits() as i64);
    }
    if sh.factor_group {
        od.add_range(ix::POLARITY, 0, U8, Rw, false, sh.polarity as i64, 0, 0xC0);
        od.add(ix::ENCODER_RESOLUTION, 0, U8, Const, false, 2);
        od.add(ix::ENCODER_RESOLUTION, 1, U32, Ro, false, c.counts_per_rev as i64);
        od.add(ix::ENCODER_RESOLUTION, 2, U32, Ro, false, 1);
        od.add(ix::GEAR_RATIO, 0, U8, Const, false, 2);
        od.add_range(ix::GEAR_RATIO, 1, U32, Rw, false, sh.gear_ratio[0] as i64, 1, u32::MAX as i64);
        od.add_range(ix::GEAR_RATIO, 2, U32, Rw, false, sh.gear_ratio[1] as i64, 1, u32::MAX as i64);
        od.add(ix::FEED_CONSTANT, 0, U8, Const, false, 2);
        od.add_range(ix::FEED_CONSTANT, 1, U32, Rw, false, c.feed_constant() as i64, 1, u32::MAX as i64);
        od.add_range(ix::FEED_CONSTANT, 2, U32, Rw, false, 1, 1, u32::MAX as i64);
    }
    // Interpolated position (mode 7), where the drive has it: linear sub-mode only, one
    // set-point record 0x60C1:1, a one-record buffer 0x60C4 (sub 6 clears and enables it).
    if sh.modes.contains(&mode::INTERPOLATED_POSITION) {
        od.add_range(ix::INTERPOLATION_SUB_MODE, 0, I16, Rw, false, 0, 0, 0);
        od.add(ix::INTERPOLATION_DATA, 0, U8, Const, false, 1);
        od.add(ix::INTERPOLATION_DATA, 1, I32, Rw, true, 0);
        od.add(ix::INTERPOLATION_BUFFER, 0, U8, Const, false, 6);
        od.add(ix::INTERPOLATION_BUFFER, 1, U32, Ro, false, 1);
        od.add(ix::INTERPOLATION_BUFFER, 2, U32, Ro, false, 1);
        od.add_range(ix::INTERPOLATION_BUFFER, 3, U8, Rw, false, 0, 0, 1);
        od.add_range(ix::INTERPOLATION_BUFFER, 4, U16, Rw, false, 0, 0, 0);
        od.add_range(ix::INTERPOLATION_BUFFER, 5, U8, Wo, false, 4, 4, 4);
        od.add_range(ix::INTERPOLATION_BUFFER, 6, U8, Wo, false, 1, 0, 1);
    }
    od.add_range(VENDOR_BRAKE_DELAY, 0, U16, Rw, false, 0, 0, 2000);
    od.add(VENDOR_ENCODER_TYPE, 0, U8, Ro, false, 3);
    od.add(VENDOR_VELOCITY_GAIN, 0, I32, Rw, false, 100);
    od.add_range(VENDOR_CURRENT_LIMIT, 0, U16, Rw, false, 100, 0, 5000);
    if sh.fixed_pdo {
        // The power-on mapping above, read-only: remapping aborts 0x06010002.
        for i in 0..N_RPDO {
            for s in 0..=8u8 {
                od.make_read_only(ix::RPDO_MAP + i, s);
            }
        }
        for i in 0..N_TPDO {
            for s in 0..=8u8 {
                od.make_read_only(ix::TPDO_MAP + i, s);
            }
        }
    }
    od
}

impl SimDrive {
    pub fn new(cfg: DriveConfig, step_us: u32) -> SimDrive {
        let od = build_od(&cfg);
        let servo = Servo::new(cfg.physics.clone(), cfg.counts_per_rev);
        let boot = (cfg.boot_delay_ms * MS as f64).round() as u64;
        let mut d = SimDrive {
            od,
            nmt: NmtState::BootUp,
            boot_at: Some(boot),
            state: State::NotReadyToSwitchOn,
            prev_cw: 0,
            servo,
            step_s: step_us as f64 * 1e-6,
            demand: 0.0,
            vff: 0.0,
            seg_start: 0.0,
            seg_end: 0.0,
            seg_t0: 0,
            seg_len: 0,
            seg_v: 0.0,
            target_ref: None,
            target_fresh: false,
            csp_missed: 0,
            target_vel: 0.0,
            stop: None,
            limit_active: false,
            last_sync: None,
            sync_period: 0,
            tpdo_count: [0; N_TPDO as usize],
            tpdo_last: [None, None],
            tpdo_last_t: [0; N_TPDO as usize],
            rpdo_buf: [None, None],
            rpdo_len_error: false,
            hb_next: None,
            hb_seen: BTreeMap::new(),
            ferr_since: None,
            ferr_flag: false,
            i2t: 0.0,
            sdo: SdoState::Idle,
            silent: false,
            silent_until: u64::MAX,
            silence_pending: None,
            encoder_frozen: None,
            delayed: VecDeque::new(),
            transport: VecDeque::new(),
            torque_offset: 0,
            rng: 0x9E37_79B9_7F4A_7C15 ^ cfg.node as u64,
            hot: Hot::default(),
            prof: profile::Prof::default(),
            pending_mode: None,
            own_sync_next: None,
            guarding: shape::Guarding::default(),
            enabled_modes: 0,
            nmt_resets: 0,
            out: Vec::new(),
            cfg,
        };
        d.recache();
        d
    }

    fn recache(&mut self) {
        let mut h = Hot::default();
        for s in 1..=2u8 {
            let v = self.od.int(ix::CONSUMER_HEARTBEAT, s) as u32;
            let (node, ms) = (((v >> 16) & 0xFF) as u8, (v & 0xFFFF) as u64);
            if node != 0 && ms != 0 {
                h.consumers[s as usize - 1] = (node, ms * MS);
            }
        }
        h.event_tpdo = (0..N_TPDO).any(|i| self.pdo_valid(ix::TPDO_COMM + i) && self.od.int(ix::TPDO_COMM + i, 2) >= 254);
        h.mode = self.od.int(ix::MODES_DISPLAY, 0) as i8;
        h.ferr_window = self.od.int(ix::FOLLOWING_ERROR_WINDOW, 0);
        h.ferr_timeout = self.od.int(ix::FOLLOWING_ERROR_TIMEOUT, 0) as u64 * MS;
        h.sync_cob = (self.od.int(ix::COB_ID_SYNC, 0) & 0x7FF) as u16;
        for i in 0..N_RPDO {
            h.rpdo_cob[i as usize] = self.od.int(ix::RPDO_COMM + i, 1) as u32;
        }
        h.encoder_lost = self.od.int(SIM_FAULTS, fault_sub::ENCODER_LOST) != 0;
        h.undervoltage = self.od.int(SIM_FAULTS, fault_sub::UNDERVOLTAGE) != 0;
        h.hb_muted = self.od.int(SIM_FAULTS, fault_sub::HEARTBEAT_MUTED) != 0;
        h.pdo_drop_permille = self.od.int(SIM_FAULTS, fault_sub::PDO_DROP_PERMILLE) as u32;
        h.tpdo_delay = self.od.int(SIM_FAULTS, fault_sub::TPDO_DELAY_US) as u64 * 1000;
        h.inc_per_unit = if self.cfg.shape.factor_group { shape::increments_per_unit(&self.od) } else { self.cfg.increments_per_unit() };
        h.pos_sign = if self.od.int(ix::POLARITY, 0) & 0x80 != 0 { -1.0 } else { 1.0 };
        self.hot = h;
    }

    // ---- accessors -------------------------------------------------------------------

    pub fn node(&self) -> u8 {
        self.cfg.node
    }
    pub fn config(&self) -> &DriveConfig {
        &self.cfg
    }
    pub fn kind(&self) -> DriveKind {
        self.cfg.kind
    }
    /// NMT state; `BootUp` while initialising (before the boot-up message).
    pub fn nmt_state(&self) -> NmtState {
        self.nmt
    }
    pub fn state(&self) -> State {
        self.state
    }
    /// 0x6064: encoder position in position units (whole counts with the default factor
    /// group), wrapping like the INTEGER32 object.
    pub fn position_actual(&self) -> i32 {
        let inc = self.encoder_frozen.unwrap_or_else(|| self.servo.position_counts());
        if self.hot.inc_per_unit == 1.0 && self.hot.pos_sign == 1.0 && self.cfg.shape.feedback_factor == 1.0 {
            return inc as i32;
        }
        (self.inc_to_user(inc as f64) * self.cfg.shape.feedback_factor).round() as i64 as i32
    }
    /// Unwrapped encoder position (counts), for tests.
    pub fn position_unwrapped(&self) -> i64 {
        self.servo.position_counts()
    }
    /// 0x60F4: position demand − actual, counts.
    pub fn following_error(&self) -> i32 {
        self.ferr()
    }
    /// 0x606C, counts/s: the drive's filtered speed estimate.
    pub fn velocity_actual(&self) -> i32 {
        self.servo.velocity_estimate_counts().round().clamp(i32::MIN as f64, i32::MAX as f64) as i32
    }
    pub fn mode_display(&self) -> i8 {
        self.hot.mode
    }
    /// The modes (bit m for mode m, 0…31) this drive has been in Operation Enabled in.
    pub fn enabled_modes(&self) -> u32 {
        self.enabled_modes
    }
    /// NMT reset node / reset communication commands received since power-on.
    pub fn nmt_resets(&self) -> u32 {
        self.nmt_resets
    }
    pub fn statusword(&self) -> u16 {
        self.compute_statusword()
    }
    /// 0x603F.
    pub fn error_code(&self) -> u16 {
        self.od.int(ix::ERROR_CODE, 0) as u16
    }
    /// Position demand (counts, unwrapped) the loop follows.
    pub fn position_demand(&self) -> f64 {
        self.demand
    }
    /// Motor torque, N·m.
    pub fn torque(&self) -> f64 {
        self.servo.torque()
    }
    /// The object dictionary (types, access, mappability; values as last refreshed).
    pub fn od(&self) -> &Od {
        &self.od
    }
    /// Read any object as the SDO server would (integers only; `None` if absent).
    pub fn object(&self, index: u16, sub: u8) -> Option<i64> {
        match self.od.get(index, sub).map(|e| &e.value) {
            Some(Value::Int(v)) => Some(*v),
            _ => None,
        }
    }

    // ---- fault injection -------------------------------------------------------------

    /// Raise a drive fault with this error code (e.g. 0x2310 overcurrent, 0x3210 DC-link
    /// overvoltage): EMCY, 0x603F, fault reaction, Fault.
    pub fn inject_fault(&mut self, code: u16, now: u64) {
        self.fault(code, now);
    }
    /// An external torque on the motor shaft (N·m): a crash, a jammed slide, a cutting load.
    pub fn set_load_torque(&mut self, nm: f64) {
        self.servo.load_torque = if nm.is_finite() { nm } else { 0.0 };
    }
    /// Extra dry friction on the motor shaft (N·m): a jammed slide or a crashed tool. 0 frees it.
    pub fn set_jam(&mut self, nm: f64) {
        self.servo.jam_friction = if nm.is_finite() { nm.max(0.0) } else { 0.0 };
    }
    /// Disconnect the node from the bus (it neither receives nor sends) or reconnect it.
    pub fn set_silent(&mut self, silent: bool) {
        self.silent = silent;
        self.silent_until = u64::MAX;
    }
    /// Whether the node is off the bus.
    pub fn is_silent(&self) -> bool {
        self.silent
    }
    /// Set an injected fault as an SDO write of `value` to 0x2100:`sub` would (see
    /// `fault_sub`), without a bus. Err: the SDO abort code.
    pub fn set_sim_fault(&mut self, sub: u8, value: u32, now: u64) -> Result<(), u32> {
        let size = self.od.get(SIM_FAULTS, sub).and_then(|e| e.dtype.size()).unwrap_or(4);
        self.write_object(SIM_FAULTS, sub, &value.to_le_bytes()[..size.min(4)], now)
    }
    /// A condition that makes a fault persist (fault reset refused): its error code.
    fn lasting_fault(&self) -> Option<u16> {
        if self.hot.encoder_lost {
            Some(0x7305)
        } else if self.hot.undervoltage {
            Some(0x3220)
        } else {
            None
        }
    }
    fn draw_drop(&mut self) -> bool {
        let p = self.hot.pdo_drop_permille;
        if p == 0 {
            return false;
        }
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.rng = x;
        (x % 1000) < p as u64
    }
    /// A TPDO leaves now, later (injected delay) or never (injected loss).
    fn emit_tpdo(&mut self, f: CanFrame, now: u64) {
        if self.draw_drop() {
            return;
        }
        if self.hot.tpdo_delay > 0 {
            self.delayed.push_back((now + self.hot.tpdo_delay, f));
        } else {
            self.out.push(f);
        }
    }
    /// Power-on encoder position (an absolute encoder's offset), counts.
    pub fn set_position(&mut self, counts: f64) {
        if counts.is_finite() {
            self.servo.set_position(counts);
            self.demand = counts;
        }
    }

    // ---- world interface -------------------------------------------------------------

    pub(crate) fn take_output(&mut self, into: &mut Vec<CanFrame>) {
        if self.silent {
            self.out.clear();
        } else {
            into.append(&mut self.out);
        }
        if let Some(until) = self.silence_pending.take() {
            self.silent = true;
            self.silent_until = until;
            self.delayed.clear();
        }
    }

    /// When the next SYNC is expected (last SYNC + the period estimate), once known.
    pub(crate) fn expected_sync(&self) -> Option<u64> {
        match (self.last_sync, self.sync_period) {
            (Some(l), p) if p > 0 && self.nmt == NmtState::Operational => Some(l + p),
            _ => None,
        }
    }

    /// The next time a timer of this drive fires (boot-up, heartbeat, heartbeat timeout).
    pub(crate) fn next_event(&self) -> Option<u64> {
        let mut t = self.boot_at;
        let mut take = |x: Option<u64>| {
            if let Some(x) = x {
                t = Some(t.map_or(x, |t: u64| t.min(x)));
            }
        };
        take(self.hb_next);
        take(self.next_own_sync());
        take(self.pending_mode_due());
        take(self.life_guard_due());
        take(self.delayed.front().map(|d| d.0));
        if self.silent_until != u64::MAX {
            take(Some(self.silent_until));
        }
        if self.nmt != NmtState::BootUp {
            for (node, timeout) in self.hot.consumers {
                if node != 0 {
                    take(self.hb_seen.get(&node).map(|&last| last + timeout));
                }
            }
        }
        t
    }

    /// Fire every timer due at `now`.
    pub(crate) fn on_time(&mut self, now: u64) {
        if self.silent && now >= self.silent_until {
            tracing::info!(node = self.cfg.node, "back on the bus after an injected silence");
            self.silent = false;
            self.silent_until = u64::MAX;
        }
        while self.delayed.front().is_some_and(|d| d.0 <= now) {
            if let Some((_, f)) = self.delayed.pop_front() {
                self.out.push(f);
            }
        }
        if let Some(b) = self.boot_at {
            if now >= b {
                self.boot(now);
            }
        }
        self.own_sync(now);
        self.step_pending_mode(now, false);
        self.check_life_guarding(now);
        if let Some(h) = self.hb_next {
            if now >= h {
                let period = self.od.int(ix::PRODUCER_HEARTBEAT, 0) as u64 * MS;
                if self.nmt != NmtState::BootUp && !self.hot.hb_muted {
                    self.out.push(heartbeat_frame(self.cfg.node, self.nmt));
                }
                self.hb_next = if period > 0 { Some(h + period * ((now - h) / period + 1)) } else { None };
            }
        }
        if self.nmt != NmtState::BootUp {
            for (node, timeout) in self.hot.consumers {
                if node == 0 {
                    continue;
                }
                if let Some(&last) = self.hb_seen.get(&node) {
                    if now >= last + timeout {
                        // Monitoring stops until the producer is heard again (CiA 301).
                        self.hb_seen.remove(&node);
                        tracing::warn!(node = self.cfg.node, producer = node, "heartbeat consumer timeout");
                        self.communication_error(0x8130, now);
                    }
                }
            }
        }
    }

    fn boot(&mut self, now: u64) {
        self.boot_at = None;
        self.set_nmt(NmtState::PreOperational);
        self.out.push(heartbeat_frame(self.cfg.node, NmtState::BootUp));
        if self.state == State::NotReadyToSwitchOn {
            // Self-test passed: transition 1.
            self.set_state(State::SwitchOnDisabled, now);
        }
        let period = self.od.int(ix::PRODUCER_HEARTBEAT, 0) as u64 * MS;
        self.hb_next = if period > 0 { Some(now + period) } else { None };
    }

    fn set_nmt(&mut self, s: NmtState) {
        if s != self.nmt {
            tracing::info!(node = self.cfg.node, "NMT {} → {}", self.nmt.name(), s.name());
            self.nmt = s;
            if s != NmtState::Operational {
                self.rpdo_buf = [None, None];
            }
        }
    }

    /// Integrate the mechanics over `dt` seconds.
    pub(crate) fn integrate(&mut self, dt: f64) {
        self.servo.integrate(dt);
    }

    // ---- frames ----------------------------------------------------------------------

    pub(crate) fn handle_frame(&mut self, f: &CanFrame, now: u64) {
        if self.silent || f.extended {
            return;
        }
        if f.rtr {
            self.remote_frame(f, now);
            return;
        }
        let id = f.cob_id();
        if let Some((c, node)) = NmtCommand::decode(f) {
            if node == 0 || node == self.cfg.node {
                self.nmt_command(c, now);
            }
            return;
        }
        if self.nmt == NmtState::BootUp {
            return; // initialising: deaf
        }
        if let Some((node, _)) = decode_heartbeat(f) {
            self.hb_seen.insert(node, now);
            return;
        }
        if id == self.hot.sync_cob {
            self.on_sync(now);
            return;
        }
        if id == cob::SDO_RX + self.cfg.node as u16 {
            if matches!(self.nmt, NmtState::PreOperational | NmtState::Operational) {
                self.sdo_request(f, now);
            }
            return;
        }
        if self.nmt == NmtState::Operational {
            for i in 0..N_RPDO {
                let c = self.hot.rpdo_cob[i as usize];
                if c & 0x8000_0000 == 0 && c & 0x7FF == id as u32 && !self.draw_drop() {
                    self.rpdo_received(i, f, now);
                }
            }
        }
    }

    fn nmt_command(&mut self, c: NmtCommand, now: u64) {
        if self.nmt == NmtState::BootUp && !matches!(c, NmtCommand::ResetNode | NmtCommand::ResetCommunication) {
            return;
        }
        if matches!(c, NmtCommand::ResetNode | NmtCommand::ResetCommunication) {
            self.nmt_resets += 1;
        }
        match c {
            NmtCommand::Start => self.set_nmt(NmtState::Operational),
            NmtCommand::Stop => {
                if self.nmt == NmtState::Operational {
                    self.abort_connection(0x8100, now);
                }
                self.set_nmt(NmtState::Stopped);
            }
            NmtCommand::EnterPreOperational => self.set_nmt(NmtState::PreOperational),
            NmtCommand::ResetNode => {
                // Reset application: every object to its default, power stage off. The
                // injected faults (0x2100) are hardware: they survive a reset.
                self.od.reset_range(0x0000, SIM_FAULTS - 1);
                self.od.reset_range(profile::SIM_SWITCHES + 1, 0xFFFF);
                self.recache();
                self.forget_homing();
                self.prev_cw = 0;
                self.stop = None;
                self.pending_mode = None;
                self.ferr_flag = false;
                self.ferr_since = None;
                self.set_state(State::NotReadyToSwitchOn, now);
                self.reset_comm(now);
            }
            NmtCommand::ResetCommunication => {
                if self.nmt == NmtState::Operational {
                    self.abort_connection(0x8100, now);
                }
                self.od.reset_range(0x1000, 0x1FFF);
                self.recache();
                self.reset_comm(now);
            }
        }
    }

    fn reset_comm(&mut self, now: u64) {
        self.set_nmt(NmtState::BootUp);
        self.sdo = SdoState::Idle;
        self.hb_next = None;
        self.hb_seen.clear();
        self.tpdo_count = [0; N_TPDO as usize];
        self.tpdo_last = [None, None];
        self.rpdo_buf = [None, None];
        self.delayed.clear();
        self.last_sync = None;
        self.own_sync_next = None;
        self.guarding = shape::Guarding::default();
        self.boot_at = Some(now + (self.cfg.boot_delay_ms * MS as f64).round() as u64);
    }

    fn emcy(&mut self, code: u16, register: u8) {
        let c = self.od.int(ix::COB_ID_EMCY, 0) as u32;
        if c & 0x8000_0000 != 0 || !matches!(self.nmt, NmtState::PreOperational | NmtState::Operational) {
            return;
        }
        let f = Emcy { code, register, vendor: [0; 5] }.frame(self.cfg.node);
        self.out.push(CanFrame::new((c & 0x7FF) as u16, f.data()));
    }

    // ---- SYNC and PDOs ---------------------------------------------------------------

    fn on_sync(&mut self, now: u64) {
        self.step_pending_mode(now, true);
        if let Some(last) = self.last_sync {
            if now > last {
                // A real drive locks onto the SYNC period with a slow loop: one short or
                // long interval (a master that caught up after a stall sends SYNCs back to
                // back) moves the estimate by at most 1/8 of a factor 2 — else the next
                // segment would be interpolated over microseconds at a huge speed.
                let dt = now - last;
                self.sync_period = if self.sync_period == 0 {
                    dt
                } else {
                    let p = self.sync_period;
                    let x = dt.clamp(p / 2, p.saturating_mul(2));
                    (p as i64 + (x as i64 - p as i64) / 8) as u64
                };
            }
        }
        self.last_sync = Some(now);
        if self.nmt != NmtState::Operational {
            return;
        }
        // Inputs are sampled at the SYNC instant, before this SYNC's outputs act.
        self.refresh_od();
        for i in 0..N_TPDO {
            let c = self.od.int(ix::TPDO_COMM + i, 1) as u32;
            let ty = self.od.int(ix::TPDO_COMM + i, 2);
            if c & 0x8000_0000 != 0 || ty > 240 {
                continue;
            }
            let data = self.tpdo_data(i);
            let k = i as usize;
            let send = if ty == 0 {
                self.tpdo_last[k].as_ref() != Some(&data)
            } else {
                self.tpdo_count[k] += 1;
                if self.tpdo_count[k] >= ty as u32 {
                    self.tpdo_count[k] = 0;
                    true
                } else {
                    false
                }
            };
            if send {
                self.emit_tpdo(CanFrame::new((c & 0x7FF) as u16, &data), now);
                self.tpdo_last[k] = Some(data);
                self.tpdo_last_t[k] = now;
            }
        }
        for i in 0..N_RPDO as usize {
            if let Some(d) = self.rpdo_buf[i].take() {
                self.apply_rpdo(i as u16, &d, now);
            }
        }
        self.latch_setpoints(now, true);
    }

    fn mapping(&self, map_index: u16) -> Vec<MapEntry> {
        let n = self.od.int(map_index, 0).clamp(0, 8) as u8;
        (1..=n).map(|s| MapEntry::decode(self.od.int(map_index, s) as u32)).collect()
    }

    fn tpdo_data(&self, i: u16) -> Vec<u8> {
        let mut d = Vec::with_capacity(8);
        for e in self.mapping(ix::TPDO_MAP + i) {
            let v = self.od.int(e.index, e.sub);
            let n = (e.bits / 8) as usize;
            d.extend_from_slice(&v.to_le_bytes()[..n.min(8)]);
        }
        d.truncate(8);
        d
    }

    fn rpdo_received(&mut self, i: u16, f: &CanFrame, now: u64) {
        let need: usize = self.mapping(ix::RPDO_MAP + i).iter().map(|e| (e.bits / 8) as usize).sum();
        let got = f.len as usize;
        if got < need {
            // Not processed (CiA 301): tell the master once per episode.
            if !self.rpdo_len_error {
                self.rpdo_len_error = true;
                self.emcy(0x8210, self.od.int(ix::ERROR_REGISTER, 0) as u8 | 0x11);
            }
            return;
        }
        self.rpdo_len_error = false;
        let ty = self.od.int(ix::RPDO_COMM + i, 2);
        if ty <= 240 {
            self.rpdo_buf[i as usize] = Some(f.data().to_vec());
        } else {
            self.apply_rpdo(i, f.data(), now);
        }
    }

    fn apply_rpdo(&mut self, i: u16, data: &[u8], now: u64) {
        let mut pos = 0usize;
        // A PDO is one set of values: all are stored before any acts (a controlword with
        // "new set-point" takes the target position of the same PDO).
        let mut written = Vec::with_capacity(4);
        for e in self.mapping(ix::RPDO_MAP + i) {
            let n = (e.bits / 8) as usize;
            if pos + n > data.len() {
                break;
            }
            if let Some(ent) = self.od.get(e.index, e.sub) {
                let v = ent.dtype.decode(&data[pos..pos + n]);
                // A PDO value a real drive would refuse by SDO is ignored.
                if self.object_rules(e.index, e.sub, v).is_ok() && v >= ent.min && v <= ent.max {
                    self.od.set(e.index, e.sub, v);
                    written.push((e.index, e.sub, v));
                }
            }
            pos += n;
        }
        if !written.is_empty() {
            self.recache();
        }
        for (index, sub, v) in written {
            self.after_write(index, sub, v, now);
        }
    }

    /// Event-driven TPDOs (254/255): on change (respecting the inhibit time) and on the
    /// event timer. Checked every control tick.
    fn event_tpdos(&mut self, now: u64) {
        if !self.hot.event_tpdo || self.nmt != NmtState::Operational {
            return;
        }
        let mut refreshed = false;
        for i in 0..N_TPDO {
            let c = self.od.int(ix::TPDO_COMM + i, 1) as u32;
            let ty = self.od.int(ix::TPDO_COMM + i, 2);
            if c & 0x8000_0000 != 0 || ty < 254 {
                continue;
            }
            if !refreshed {
                self.refresh_od();
                refreshed = true;
            }
            let k = i as usize;
            let inhibit = self.od.int(ix::TPDO_COMM + i, 3) as u64 * 100_000;
            let event = self.od.int(ix::TPDO_COMM + i, 5) as u64 * MS;
            let data = self.tpdo_data(i);
            let since = now.saturating_sub(self.tpdo_last_t[k]);
            let first = self.tpdo_last[k].is_none();
            let changed = self.tpdo_last[k].as_ref() != Some(&data);
            if first || (changed && since >= inhibit) || (event > 0 && since >= event) {
                self.emit_tpdo(CanFrame::new((c & 0x7FF) as u16, &data), now);
                self.tpdo_last[k] = Some(data);
                self.tpdo_last_t[k] = now;
            }
        }
    }

    // ---- SDO server ------------------------------------------------------------------

    fn sdo_send(&mut self, r: SdoResponse) {
        self.out.push(r.encode(self.cfg.node));
    }

    fn sdo_abort(&mut self, index: u16, sub: u8, code: u32) {
        self.sdo = SdoState::Idle;
        self.sdo_send(SdoResponse::Abort { index, sub, code });
    }

    fn sdo_request(&mut self, f: &CanFrame, now: u64) {
        if f.len == 8 && self.sdo_block(f, now) {
            return;
        }
        let Some(req) = SdoRequest::decode(f) else {
            if f.len == 8 {
                // Unknown command specifier.
                let index = u16::from_le_bytes([f.data[1], f.data[2]]);
                self.sdo_abort(index, f.data[3], abort::BAD_COMMAND);
            }
            return;
        };
        self.sdo_request_plain(req, now);
    }

    /// Expedited and segmented transfers.
    fn sdo_request_plain(&mut self, req: SdoRequest, now: u64) {
        match req {
            SdoRequest::InitiateUpload { index, sub } => {
                self.sdo = SdoState::Idle;
                self.refresh_od();
                match self.od.read_bytes(index, sub) {
                    Err(code) => self.sdo_abort(index, sub, code),
                    Ok(data) if !data.is_empty() && data.len() <= 4 => {
                        let mut d = [0u8; 4];
                        d[..data.len()].copy_from_slice(&data);
                        self.sdo_send(SdoResponse::InitiateUpload { index, sub, expedited: true, size: Some(data.len() as u32), data: d });
                    }
                    Ok(data) => {
                        let n = data.len() as u32;
                        self.sdo_send(SdoResponse::InitiateUpload { index, sub, expedited: false, size: Some(n), data: n.to_le_bytes() });
                        self.sdo = SdoState::Upload { index, sub, data, pos: 0, toggle: false };
                    }
                }
            }
            SdoRequest::UploadSegment { toggle } => {
                let SdoState::Upload { index, sub, data, pos, toggle: expect } = &mut self.sdo else {
                    self.sdo_abort(0, 0, abort::BAD_COMMAND);
                    return;
                };
                let (index, sub) = (*index, *sub);
                if toggle != *expect {
                    self.sdo_abort(index, sub, abort::TOGGLE);
                    return;
                }
                let n = (data.len() - *pos).min(7);
                let mut seg = [0u8; 7];
                seg[..n].copy_from_slice(&data[*pos..*pos + n]);
                *pos += n;
                let last = *pos >= data.len();
                *expect = !*expect;
                let r = SdoResponse::UploadSegment { toggle, len: n as u8, data: seg, last };
                if last {
                    self.sdo = SdoState::Idle;
                }
                self.sdo_send(r);
            }
            SdoRequest::InitiateDownload { index, sub, expedited, size, data } => {
                self.sdo = SdoState::Idle;
                if expedited {
                    let obj_size = self.od.get(index, sub).and_then(|e| e.dtype.size()).unwrap_or(4);
                    let n = size.map(|s| s as usize).unwrap_or(obj_size).clamp(1, 4);
                    match self.write_object(index, sub, &data[..n], now) {
                        Ok(()) => self.sdo_send(SdoResponse::InitiateDownload { index, sub }),
                        Err(code) => self.sdo_abort(index, sub, code),
                    }
                } else {
                    let e = match self.od.lookup(index, sub) {
                        Ok(e) => e,
                        Err(code) => return self.sdo_abort(index, sub, code),
                    };
                    if !e.access.writable() {
                        return self.sdo_abort(index, sub, abort::READ_ONLY);
                    }
                    if let (Some(n), Some(s)) = (e.dtype.size(), size) {
                        if s as usize > n {
                            return self.sdo_abort(index, sub, abort::TOO_LONG);
                        }
                        if (s as usize) < n {
                            return self.sdo_abort(index, sub, abort::TOO_SHORT);
                        }
                    }
                    self.sdo_send(SdoResponse::InitiateDownload { index, sub });
                    self.sdo = SdoState::Download { index, sub, size, buf: Vec::new(), toggle: false };
                }
            }
            SdoRequest::DownloadSegment { toggle, len, data, last } => {
                let SdoState::Download { index, sub, size, buf, toggle: expect } = &mut self.sdo else {
                    self.sdo_abort(0, 0, abort::BAD_COMMAND);
                    return;
                };
                let (index, sub, size) = (*index, *sub, *size);
                if toggle != *expect {
                    return self.sdo_abort(index, sub, abort::TOGGLE);
                }
                *expect = !*expect;
                buf.extend_from_slice(&data[..len.min(7) as usize]);
                if buf.len() > 1024.max(USER_DATA_LEN) {
                    return self.sdo_abort(index, sub, abort::OUT_OF_MEMORY);
                }
                if !last {
                    self.sdo_send(SdoResponse::DownloadSegment { toggle });
                    return;
                }
                let buf = std::mem::take(buf);
                self.sdo = SdoState::Idle;
                if size.is_some_and(|s| s as usize != buf.len()) {
                    // The initiate announced another length than the segments carried.
                    return self.sdo_abort(index, sub, abort::TYPE_MISMATCH);
                }
                match self.write_object(index, sub, &buf, now) {
                    Ok(()) => self.sdo_send(SdoResponse::DownloadSegment { toggle }),
                    Err(code) => self.sdo_abort(index, sub, code),
                }
            }
            SdoRequest::Abort { .. } => self.sdo = SdoState::Idle,
        }
    }

    /// An SDO download: generic checks, object rules, store, side effects.
    fn write_object(&mut self, index: u16, sub: u8, data: &[u8], now: u64) -> Result<(), u32> {
        let mut v = self.od.check_write(index, sub, data)?;
        if let (VENDOR_CURRENT_LIMIT, Value::Int(x)) = (index, &v) {
            v = Value::Int(x / 10 * 10); // kept in whole amperes
        }
        if let Value::Int(x) = v {
            self.object_rules(index, sub, x)?;
            self.od.store(index, sub, v);
            self.recache();
            self.after_write(index, sub, x, now);
        } else {
            self.od.store(index, sub, v);
        }
        Ok(())
    }

    fn pdo_valid(&self, comm: u16) -> bool {
        self.od.int(comm, 1) as u32 & 0x8000_0000 == 0
    }

    fn check_map_entry(&self, e: MapEntry, rpdo: bool) -> Result<u32, u32> {
        let obj = self.od.lookup(e.index, e.sub)?;
        let dir_ok = if rpdo { obj.access.writable() } else { obj.access.readable() };
        if !obj.pdo || !dir_ok {
            return Err(abort::NOT_MAPPABLE);
        }
        if obj.dtype.size().map(|n| n * 8) != Some(e.bits as usize) {
            return Err(abort::PARAM_INCOMPATIBLE);
        }
        Ok(e.bits as u32)
    }

    /// Object-specific rules, after the generic checks (CiA 301 PDO rules, CiA 402 ranges).
    fn object_rules(&self, index: u16, sub: u8, x: i64) -> Result<(), u32> {
        let rpdo_comm = ix::RPDO_COMM..ix::RPDO_COMM + N_RPDO;
        let tpdo_comm = ix::TPDO_COMM..ix::TPDO_COMM + N_TPDO;
        let rpdo_map = ix::RPDO_MAP..ix::RPDO_MAP + N_RPDO;
        let tpdo_map = ix::TPDO_MAP..ix::TPDO_MAP + N_TPDO;
        let is_rpdo = rpdo_comm.contains(&index) || rpdo_map.contains(&index);
        if rpdo_comm.contains(&index) || tpdo_comm.contains(&index) {
            match sub {
                1 => {
                    let x = x as u32;
                    if x & 0x2000_0000 != 0 || x & 0x1FFF_F800 != 0 {
                        return Err(abort::INVALID_VALUE); // 29-bit ids not supported
                    }
                    let cur = self.od.int(index, 1) as u32;
                    let new_valid = x & 0x8000_0000 == 0;
                    if new_valid && cur & 0x8000_0000 == 0 && cur & 0x7FF != x & 0x7FF {
                        return Err(abort::INVALID_VALUE); // change the id only while invalid
                    }
                    if new_valid && restricted_cob(x & 0x7FF) {
                        return Err(abort::INVALID_VALUE);
                    }
                }
                2 if !(0..=240).contains(&x) && x != 254 && x != 255 => {
                    return Err(abort::INVALID_VALUE);
                }
                3 if self.pdo_valid(index) => {
                    return Err(abort::INVALID_VALUE); // inhibit time only while invalid
                }
                _ => {}
            }
        } else if rpdo_map.contains(&index) || tpdo_map.contains(&index) {
            let comm = index - 0x200;
            if self.pdo_valid(comm) {
                return Err(abort::PARAM_INCOMPATIBLE);
            }
            if sub == 0 {
                let mut bits = 0u32;
                for s in 1..=(x.clamp(0, 8) as u8) {
                    let v = self.od.int(index, s) as u32;
                    if v == 0 {
                        return Err(abort::PARAM_INCOMPATIBLE);
                    }
                    bits += self.check_map_entry(MapEntry::decode(v), is_rpdo)?;
                }
                if bits > 64 {
                    return Err(abort::PDO_TOO_LONG);
                }
            } else {
                if self.od.int(index, 0) != 0 {
                    return Err(abort::PARAM_INCOMPATIBLE);
                }
                if x != 0 {
                    self.check_map_entry(MapEntry::decode(x as u32), is_rpdo)?;
                }
            }
        } else {
            match index {
                ix::CONSUMER_HEARTBEAT if sub > 0 => {
                    let node = (x >> 16) & 0xFF;
                    let ms = x & 0xFFFF;
                    if x as u32 & 0xFF00_0000 != 0 || node > 127 {
                        return Err(abort::INVALID_VALUE);
                    }
                    for s in 1..=2u8 {
                        let o = self.od.int(index, s);
                        if s != sub && node != 0 && ms != 0 && (o >> 16) & 0xFF == node && o & 0xFFFF != 0 {
                            return Err(abort::PARAM_INCOMPATIBLE); // one entry per producer
                        }
                    }
                }
                ix::COB_ID_SYNC if ((x & 0x4000_0000 != 0 && !self.cfg.shape.sync_producer) || x & 0x2000_0000 != 0) => {
                    return Err(abort::INVALID_VALUE); // not a SYNC producer; 11-bit only
                }
                ix::COB_ID_EMCY if x & 0x2000_0000 != 0 => {
                    return Err(abort::INVALID_VALUE);
                }
                ix::MODES_OF_OPERATION if !self.mode_allowed(x) => return Err(abort::INVALID_VALUE),
                ix::HOMING_METHOD if !profile::homing_method_supported(x) => return Err(abort::INVALID_VALUE),
                ix::SOFTWARE_LIMIT => {
                    let (lo, hi) = if sub == 1 { (x, self.od.int(index, 2)) } else { (self.od.int(index, 1), x) };
                    if lo > hi {
                        return Err(abort::MAX_LESS_THAN_MIN);
                    }
                }
                _ => {}
            }
        }
        Ok(())
    }

    fn after_write(&mut self, index: u16, sub: u8, x: i64, now: u64) {
        match index {
            ix::PRODUCER_HEARTBEAT => {
                self.hb_next = if x > 0 { Some(now + x as u64 * MS) } else { None };
            }
            ix::CONSUMER_HEARTBEAT if sub > 0 => {
                // Monitoring (re)starts with the next heartbeat of that producer.
                self.hb_seen.remove(&(((x >> 16) & 0xFF) as u8));
            }
            ix::CONTROLWORD => self.controlword(x as u16, now),
            ix::MODES_OF_OPERATION => self.request_mode(x as i8, now),
            ix::COB_ID_SYNC | ix::COMM_CYCLE_PERIOD => self.own_sync_next = None,
            ix::TARGET_POSITION | ix::INTERPOLATION_DATA => self.target_fresh = true,
            SIM_FAULTS => self.sim_fault_written(sub, x, now),
            _ => {}
        }
    }

    fn sim_fault_written(&mut self, sub: u8, x: i64, now: u64) {
        use fault_sub::*;
        match sub {
            RAISE if x != 0 => self.fault(x as u16, now),
            ENCODER_LOST => {
                if x != 0 {
                    self.encoder_frozen.get_or_insert(self.servo.position_counts());
                    self.fault(0x7305, now);
                } else if self.encoder_frozen.take().is_some() {
                    // The encoder reads the real position again; hold there.
                    self.rebase();
                }
            }
            UNDERVOLTAGE if x != 0 => self.fault(0x3220, now),
            OVERCURRENT if x != 0 => {
                self.od.set(SIM_FAULTS, OVERCURRENT, 0);
                self.fault(0x2310, now);
            }
            JAM_MNM => self.set_jam(x as f64 / 1000.0),
            IP_DISABLE if x != 0 => {
                self.od.set(SIM_FAULTS, IP_DISABLE, 0);
                if self.od.get(ix::INTERPOLATION_BUFFER, 6).is_some() {
                    tracing::warn!(node = self.cfg.node, "IP buffer switched off (injected): ip mode no longer active");
                    self.od.set(ix::INTERPOLATION_BUFFER, 6, 0);
                }
            }
            SILENT_MS if x != 0 => {
                self.od.set(SIM_FAULTS, SILENT_MS, 0);
                let until = if x as u32 == u32::MAX { u64::MAX } else { now + x as u64 * MS };
                tracing::warn!(node = self.cfg.node, "falls silent for {} ms (injected)", if until == u64::MAX { "∞".into() } else { x.to_string() });
                self.silence_pending = Some(until);
            }
            _ => {}
        }
    }

    /// Live values into the object dictionary (before an SDO upload or a TPDO).
    fn refresh_od(&mut self) {
        let sw = self.compute_statusword();
        self.od.set(ix::STATUSWORD, 0, sw as i64);
        self.od.set(ix::POSITION_ACTUAL, 0, self.position_actual() as i64);
        self.od.set(ix::VELOCITY_ACTUAL, 0, self.velocity_actual() as i64);
        self.od.set(ix::FOLLOWING_ERROR_ACTUAL, 0, self.ferr() as i64);
        self.od.set(profile::DIGITAL_INPUTS, 0, self.digital_inputs());
        self.od.set(POSITION_DEMAND, 0, self.inc_to_user(self.demand).round() as i64 as i32 as i64);
        let rated = self.servo.physics().torque_limit * RATED_OF_PEAK;
        let t = (self.servo.torque() / rated * 1000.0).round().clamp(-32768.0, 32767.0);
        self.od.set(TORQUE_ACTUAL, 0, t as i64);
    }

    // ---- CiA 402 -----------------------------------------------------------------------

    /// 0x60F4 in position units.
    fn ferr(&self) -> i32 {
        let d = self.demand.round() as i64 - self.servo.position_counts();
        let d = if self.hot.inc_per_unit == 1.0 && self.hot.pos_sign == 1.0 { d } else { self.inc_to_user(d as f64).round() as i64 };
        d.clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    fn compute_statusword(&self) -> u16 {
        let mut s = self.state.statusword_bits();
        if self.state != State::NotReadyToSwitchOn && !self.hot.undervoltage {
            s |= sw::VOLTAGE_ENABLED; // mains are on
        }
        s |= sw::REMOTE;
        if self.ferr_flag {
            s |= sw::OMS13;
        }
        if self.limit_active {
            s |= sw::INTERNAL_LIMIT;
        }
        let m = self.mode_display();
        match self.state {
            State::OperationEnabled => {
                let halt = self.prev_cw & cw::HALT != 0;
                if !halt && self.stop.is_none() && (m == mode::CYCLIC_SYNC_POSITION || m == mode::CYCLIC_SYNC_VELOCITY) {
                    s |= sw::OMS12; // following the command value
                }
                if !halt && self.stop.is_none() && m == mode::INTERPOLATED_POSITION && self.ip_active() {
                    s |= sw::OMS12; // ip mode active
                }
                let reached = if let Some(st) = self.stop {
                    st.v == 0.0 && self.servo.at_rest()
                } else if m == mode::PROFILE_POSITION || m == mode::HOMING {
                    s |= self.profile_status();
                    false
                } else if m == mode::CYCLIC_SYNC_VELOCITY {
                    // Velocity window: 1 rpm or 0.5 % of the target, whichever is larger.
                    let window = (self.cfg.counts_per_rev as f64 / 60.0).max(0.005 * self.target_vel.abs());
                    (self.servo.velocity_estimate_counts() - self.target_vel).abs() <= window
                } else {
                    let window = self.od.int(POSITION_WINDOW, 0) as f64 * self.hot.inc_per_unit;
                    self.demand == self.seg_end && (self.demand - self.servo.position_counts() as f64).abs() <= window
                };
                if reached {
                    s |= sw::TARGET_REACHED;
                }
            }
            State::QuickStopActive if self.stop.is_none_or(|st| st.v == 0.0 && self.servo.at_rest()) => {
                s |= sw::TARGET_REACHED;
            }
            _ => {}
        }
        s
    }

    fn set_mode(&mut self, m: i8) {
        let old = self.mode_display();
        if old != m {
            tracing::info!(node = self.cfg.node, "mode {} → {}", mode::name(old), mode::name(m));
            self.od.set(ix::MODES_DISPLAY, 0, m as i64);
            self.hot.mode = m;
            self.prof.mode_changed();
            self.rebase();
        }
    }

    /// Hold the present position: the next target is taken relative to it.
    fn rebase(&mut self) {
        let p = self.servo.position_counts() as f64;
        self.demand = p;
        self.seg_start = p;
        self.seg_end = p;
        self.seg_v = 0.0;
        self.vff = 0.0;
        self.target_ref = None;
        self.ferr_since = None;
        self.transport.clear();
        self.torque_offset = 0;
        self.prof.cancel();
    }

    fn controlword(&mut self, c: u16, now: u64) {
        let prev = self.prev_cw;
        self.prev_cw = c;
        let next = device_transition(self.state, c, prev);
        if self.state == State::QuickStopActive && next == State::OperationEnabled && !self.qs_option().stays_in_quick_stop() {
            return; // transition 16 only exists for the "stay in quick stop" options
        }
        if self.state == State::OperationEnabled && matches!(next, State::ReadyToSwitchOn | State::SwitchedOn) {
            let option = if next == State::ReadyToSwitchOn { SHUTDOWN_OPTION } else { DISABLE_OPTION };
            if self.od.int(option, 0) == 1 && !self.servo.at_rest() {
                if !matches!(self.stop, Some(Stop { why: StopWhy::Disable(_), .. })) {
                    self.start_stop(StopWhy::Disable(next), Brake::Ramp(self.od.int(PROFILE_DECEL, 0) as f64), now);
                }
                return;
            }
        }
        self.set_state(next, now);
        self.profile_controlword(prev, c);
    }

    fn qs_option(&self) -> QuickStopOption {
        QuickStopOption::from_code(self.od.int(ix::QUICK_STOP_OPTION, 0) as i16).unwrap_or(QuickStopOption::QuickStopRamp { stay: false })
    }

    fn start_stop(&mut self, why: StopWhy, brake: Brake, now: u64) {
        // Halt and quick stop ramp the demand down from where it is; a fault reaction
        // (the demand may be what went wrong) from where the motor is.
        let (pos, v) = if why != StopWhy::FaultReaction && self.state == State::OperationEnabled && self.mode_display() != mode::CYCLIC_SYNC_VELOCITY
        {
            (self.demand, self.vff)
        } else {
            (self.servo.position_counts() as f64, self.servo.velocity_counts())
        };
        self.stop = Some(Stop { why, brake, v, pos, started: now });
    }

    fn brake_for(&self, code: i64) -> Option<Brake> {
        let qs = self.od.int(QUICK_STOP_DECEL, 0) as f64;
        let prof = self.od.int(PROFILE_DECEL, 0) as f64;
        match code {
            0 => None,
            1 => Some(Brake::Ramp(prof)),
            2 => Some(Brake::Ramp(qs)),
            _ => Some(Brake::TorqueLimit),
        }
    }

    fn set_state(&mut self, new: State, now: u64) {
        let old = self.state;
        if new == old {
            return;
        }
        let mut new = new;
        match new {
            State::OperationEnabled => {
                // From below or (transition 16) from a finished quick stop: hold here.
                self.stop = None;
                self.rebase();
            }
            State::QuickStopActive => {
                let code = self.od.int(ix::QUICK_STOP_OPTION, 0);
                // 0x605A: 1/5 slow-down ramp, 2/6 quick-stop ramp, 3/7 and 4/8 at the limit.
                match self.brake_for(if code == 0 { 0 } else { ((code - 1) % 4) + 1 }) {
                    None => new = State::SwitchOnDisabled, // coast
                    Some(b) => self.start_stop(StopWhy::QuickStop, b, now),
                }
            }
            State::FaultReactionActive => match self.brake_for(self.od.int(FAULT_REACTION, 0)) {
                None => new = State::Fault,
                Some(b) if matches!(old, State::OperationEnabled | State::QuickStopActive) => self.start_stop(StopWhy::FaultReaction, b, now),
                Some(_) => new = State::Fault, // power stage was off: nothing to stop
            },
            State::SwitchOnDisabled if old == State::Fault && self.lasting_fault().is_some() => {
                // The cause is still there (encoder, DC link): the fault stays, and says so.
                let code = self.lasting_fault().unwrap_or(0);
                self.emcy(code, error_register_bits(code));
                return;
            }
            State::SwitchOnDisabled if old == State::Fault => {
                // Fault reset.
                self.od.set(ix::ERROR_CODE, 0, 0);
                self.od.set(ix::ERROR_REGISTER, 0, 0);
                self.ferr_flag = false;
                self.emcy(0x0000, 0);
            }
            _ => {}
        }
        if !matches!(new, State::OperationEnabled | State::QuickStopActive | State::FaultReactionActive) {
            self.stop = None;
        }
        if new != old {
            tracing::info!(node = self.cfg.node, "402 {} → {}", old.name(), new.name());
            self.state = new;
        }
    }

    fn fault(&mut self, code: u16, now: u64) {
        if matches!(self.state, State::Fault | State::FaultReactionActive) {
            return;
        }
        tracing::warn!(node = self.cfg.node, "fault 0x{code:04X}: {}", cncgw_bus::canopen::emcy::error_text(code));
        let reg = error_register_bits(code);
        self.od.set(ix::ERROR_CODE, 0, code as i64);
        self.od.set(ix::ERROR_REGISTER, 0, reg as i64);
        self.emcy(code, reg);
        self.set_state(State::FaultReactionActive, now);
    }

    /// A communication error (heartbeat consumer timeout, life guarding event): the power
    /// stage per 0x6007, then the NMT state per 0x1029:1 (CiA 301: only out of operational).
    pub(super) fn communication_error(&mut self, code: u16, now: u64) {
        self.abort_connection(code, now);
        if !self.cfg.shape.error_behaviour_object || self.nmt != NmtState::Operational {
            return;
        }
        match self.od.int(ix::ERROR_BEHAVIOUR, 1) {
            0 => self.set_nmt(NmtState::PreOperational),
            2 => self.set_nmt(NmtState::Stopped),
            _ => {}
        }
    }

    /// Loss of the connection to the master (heartbeat timeout, NMT stop or reset while
    /// operational): act per 0x6007.
    fn abort_connection(&mut self, code: u16, now: u64) {
        // Without 0x6007 the drive faults, as most drives do.
        let option = if self.cfg.shape.abort_connection_object { self.od.int(ix::ABORT_CONNECTION, 0) } else { 1 };
        match option {
            1 => self.fault(code, now),
            opt => {
                // The communication error is still signalled (CiA 301), without a fault.
                self.emcy(code, self.od.int(ix::ERROR_REGISTER, 0) as u8 | 0x11);
                let powered = matches!(self.state, State::OperationEnabled | State::QuickStopActive);
                if opt == 2 && powered {
                    self.set_state(State::SwitchOnDisabled, now);
                } else if opt == 3 && self.state == State::OperationEnabled {
                    self.set_state(State::QuickStopActive, now);
                }
            }
        }
    }

    /// At a SYNC: take the new targets (CSP: start the next interpolation segment).
    /// `sync`: at a SYNC (where a missing target means a lost RPDO); else a Modbus write.
    fn latch_setpoints(&mut self, now: u64, sync: bool) {
        let fresh = std::mem::take(&mut self.target_fresh) || !sync;
        if self.state != State::OperationEnabled || self.stop.is_some() {
            return;
        }
        match self.mode_display() {
            mode::CYCLIC_SYNC_VELOCITY => {
                self.target_vel = self.od.int(ix::TARGET_VELOCITY, 0) as f64;
            }
            mode::CYCLIC_SYNC_POSITION => self.latch_position(self.od.int(ix::TARGET_POSITION, 0) as i32, fresh, sync, now),
            mode::INTERPOLATED_POSITION if self.ip_active() => self.latch_position(self.od.int(ix::INTERPOLATION_DATA, 1) as i32, fresh, sync, now),
            // Interpolation not enabled (controlword bit 4 low, or the buffer cleared): the
            // drive holds where it is and takes no set-point.
            mode::INTERPOLATED_POSITION if self.target_ref.is_some() || self.seg_len > 0 => {
                self.rebase();
                self.seg_len = 0;
            }
            _ => {}
        }
    }

    /// IP: interpolation enabled by controlword bit 4, with the buffer enabled (0x60C4:6 = 1).
    fn ip_active(&self) -> bool {
        self.prev_cw & cw::OMS4 != 0 && self.od.get(ix::INTERPOLATION_BUFFER, 6).is_none_or(|_| self.od.int(ix::INTERPOLATION_BUFFER, 6) != 0)
    }

    /// CSP and IP at a SYNC: the next segment of linear interpolation towards `raw`
    /// (position units), one interpolation period long.
    fn latch_position(&mut self, raw: i32, fresh: bool, sync: bool, now: u64) {
        let (raw, fresh) = self.delayed_target(raw, fresh, sync);
        // No new target for this SYNC (its RPDO was lost): go on with the last
        // increment for up to `CSP_EXTRAPOLATE` SYNCs, then hold. A stop of one
        // period would be a velocity step and, on the next target, twice the
        // increment: a torque spike (10 % PDO loss tripped following error so).
        let missed = !fresh && self.seg_len > 0 && self.target_ref.is_some();
        self.csp_missed = if missed { self.csp_missed.saturating_add(1) } else { 0 };
        let mut t = if missed {
            if self.csp_missed as i64 <= self.od.int(CSP_EXTRAPOLATE, 0) {
                self.seg_end + self.seg_v * (self.seg_len as f64 * 1e-9)
            } else {
                self.seg_end
            }
        } else {
            // 0x607A is in position units; the loop runs in increments.
            let t = match self.target_ref {
                Some((r, u)) => u + self.user_to_inc(raw.wrapping_sub(r) as f64),
                None => {
                    let a = self.servo.position_counts();
                    let au = self.inc_to_user(a as f64).round() as i64 as i32;
                    a as f64 + self.user_to_inc(raw.wrapping_sub(au) as f64)
                }
            };
            self.target_ref = Some((raw, t));
            t
        };
        self.limit_active = false;
        if let Some((lo, hi)) = self.software_limits_inc() {
            let c = t.clamp(lo, hi);
            self.limit_active = c != t;
            t = c;
        }
        // Interpolate from where the demand is now to the new target over the
        // interpolation period (0x60C2, else the measured SYNC period).
        let ip = self.od.int(ix::INTERPOLATION_PERIOD, 1) as f64 * 10f64.powi(self.od.int(ix::INTERPOLATION_PERIOD, 2) as i32);
        let len = if ip > 0.0 {
            (ip * 1e9).round() as u64
        } else if self.sync_period > 0 {
            self.sync_period
        } else {
            let c = self.od.int(ix::COMM_CYCLE_PERIOD, 0) as u64 * 1000;
            if c > 0 {
                c
            } else {
                MS
            }
        };
        // The set-point runs on a line through the new target, reaching it one
        // interpolation period from now (a fixed one-period delay, as real drives
        // interpolate). A late SYNC or a master that caught up several cycles at once
        // then changes neither the velocity feed-forward nor the set-point by more
        // than the lateness.
        let len = len.max(1);
        let since = now.saturating_sub(self.seg_t0);
        let fresh = self.seg_len == 0 || since > self.seg_len * (1 + self.late_periods());
        // The velocity is the target difference over whole interpolation periods:
        // one normally (sub-period jitter of the SYNC does not modulate it — the
        // spindle's inertia turns every percent of feed-forward noise into torque),
        // n when the SYNC came n periods after the last one (a master that caught up
        // after missing cycles sends n periods' worth of travel at once).
        let v = if fresh {
            (t - self.demand) / (len as f64 * 1e-9)
        } else {
            let n = ((since as f64 / len as f64).round() as u64).clamp(1, 1 + self.late_periods());
            (t - self.seg_end) / ((n * len) as f64 * 1e-9)
        };
        self.seg_v = v;
        self.seg_start = t - v * (len as f64 * 1e-9);
        self.seg_end = t;
        self.seg_t0 = now;
        self.seg_len = len;
    }

    /// How many interpolation periods a late SYNC is bridged by extrapolating the set-point
    /// (`DriveConfig::late_sync_extrapolation`; sim-drives' default 10 = 20 ms at 2 ms: enough
    /// for a master on a non-real-time kernel — the vcan tier runs in a User-Mode Linux guest
    /// whose timers were measured 10–18 ms late at p99 under load). 0: hold at once.
    fn late_periods(&self) -> u64 {
        self.cfg.late_sync_extrapolation as u64
    }

    /// The CSP target this SYNC acts on: the one written `transport_delay_cycles` SYNCs ago
    /// (a drive that buffers its set-points), else the latest.
    fn delayed_target(&mut self, raw: i32, fresh: bool, sync: bool) -> (i32, bool) {
        let n = self.cfg.physics.extra.transport_delay_cycles as usize;
        let toff = self.od.int(TORQUE_OFFSET, 0) as i16;
        if n == 0 || !sync {
            self.torque_offset = toff;
            return (raw, fresh);
        }
        self.transport.push_back((raw, fresh, toff));
        while self.transport.len() > n + 1 {
            self.transport.pop_front();
        }
        let (raw, fresh, toff) = self.transport.front().copied().unwrap_or((raw, fresh, toff));
        self.torque_offset = toff;
        (raw, fresh)
    }

    /// One control tick at `now` (every `step_us`).
    pub(crate) fn tick(&mut self, now: u64) {
        let dt = self.step_s;
        let powered = matches!(self.state, State::OperationEnabled | State::QuickStopActive | State::FaultReactionActive);
        if !powered {
            self.servo.control(Command::Off, dt);
            self.rebase();
            self.limit_active = false;
            self.event_tpdos(now);
            return;
        }
        if self.state == State::OperationEnabled {
            self.enabled_modes |= 1u32.checked_shl(self.mode_display() as u32).unwrap_or(0);
            let halt = self.prev_cw & cw::HALT != 0;
            match self.stop {
                None if halt => self.start_stop(StopWhy::Halt, Brake::Ramp(self.od.int(PROFILE_DECEL, 0) as f64), now),
                Some(st) if st.why == StopWhy::Halt && !halt => {
                    self.stop = None;
                    self.rebase();
                }
                _ => {}
            }
        }
        let cmd = if let Some(st) = self.stop.as_mut() {
            match st.brake {
                Brake::Ramp(a) => {
                    let dv = a * dt;
                    let v0 = st.v;
                    st.v = if st.v.abs() <= dv { 0.0 } else { st.v - dv * st.v.signum() };
                    st.pos += 0.5 * (v0 + st.v) * dt;
                    self.demand = st.pos;
                    self.vff = st.v;
                    Command::Position { demand: st.pos, vff: st.v }
                }
                Brake::TorqueLimit => {
                    st.v = 0.0;
                    self.demand = self.servo.position_counts() as f64;
                    self.vff = 0.0;
                    Command::Velocity { v: 0.0 }
                }
            }
        } else if matches!(self.mode_display(), mode::PROFILE_POSITION | mode::HOMING) {
            self.profile_tick(dt)
        } else if self.mode_display() == mode::CYCLIC_SYNC_VELOCITY {
            self.demand = self.servo.position_counts() as f64;
            self.vff = self.target_vel;
            Command::Velocity { v: self.target_vel }
        } else {
            let el = now.saturating_sub(self.seg_t0);
            if el <= self.seg_len * (1 + self.late_periods()) {
                // Within the period this reaches the target; past it (a late SYNC) it goes
                // on at the same speed, as real drives extrapolate over a late or missing
                // SYNC instead of stopping the motor dead.
                self.demand = self.seg_end + self.seg_v * ((el as f64 - self.seg_len as f64) * 1e-9);
                self.vff = self.seg_v;
            } else {
                // No SYNC for several periods: the master is gone or stalled; hold.
                self.demand = self.seg_end + self.seg_v * ((self.seg_len * self.late_periods()) as f64 * 1e-9);
                self.vff = 0.0;
            }
            Command::Position { demand: self.demand, vff: self.vff }
        };
        // The torque offset acts only while the drive follows the master's set-points.
        let following = self.stop.is_none() && matches!(self.mode_display(), mode::CYCLIC_SYNC_POSITION | mode::INTERPOLATED_POSITION);
        let rated = self.servo.physics().torque_limit * RATED_OF_PEAK;
        self.servo.torque_offset = if following { self.torque_offset as f64 * 1e-3 * rated } else { 0.0 };
        self.servo.control(cmd, dt);

        // Motor overload (I²t): a jammed or overloaded axis trips like a real amplifier.
        let rated = self.servo.physics().torque_limit * RATED_OF_PEAK;
        let q = self.servo.torque() / rated;
        self.i2t = (self.i2t + (q * q - 1.0) * dt).max(0.0);
        if self.i2t >= I2T_LIMIT {
            self.i2t = 0.0;
            self.fault(0x2310, now);
            return;
        }

        // Following error monitoring (position control while enabled).
        if self.state == State::OperationEnabled && matches!(cmd, Command::Position { .. }) {
            let window = self.hot.ferr_window;
            if window != u32::MAX as i64 && (self.ferr() as i64).abs() > window {
                let since = *self.ferr_since.get_or_insert(now);
                let timeout = self.hot.ferr_timeout;
                if now - since >= timeout {
                    tracing::warn!(
                        node = self.cfg.node,
                        ferr = self.ferr(),
                        demand = self.demand,
                        actual = self.servo.position_counts(),
                        seg_start = self.seg_start,
                        seg_end = self.seg_end,
                        since_seg_ms = now.saturating_sub(self.seg_t0) as f64 * 1e-6,
                        window,
                        "following error over the window 0x6065 for 0x6066"
                    );
                    self.ferr_flag = true;
                    self.ferr_since = None;
                    self.fault(0x8611, now);
                }
            } else {
                self.ferr_since = None;
            }
        }

        // End of a stop ramp.
        if let Some(st) = self.stop {
            let done = st.v == 0.0 && self.servo.at_rest();
            if done || now.saturating_sub(st.started) >= STOP_TIMEOUT {
                match st.why {
                    StopWhy::Halt => {}
                    StopWhy::QuickStop => {
                        if !self.qs_option().stays_in_quick_stop() || !done {
                            self.set_state(State::SwitchOnDisabled, now);
                        }
                    }
                    StopWhy::FaultReaction => self.set_state(State::Fault, now),
                    StopWhy::Disable(st) => self.set_state(st, now),
                }
            }
        }
        self.event_tpdos(now);
    }
}

/// Hooks for the Modbus server (`crate::modbus`): its register writes go through the same
/// object checks, rules and side effects as SDO downloads, and a target write is latched at
/// once, as a SYNC would latch it (Modbus has no SYNC).
impl SimDrive {
    /// Write an integer object as an SDO download would. Err: the SDO abort code.
    pub(crate) fn modbus_write(&mut self, index: u16, sub: u8, value: i64, now: u64) -> Result<(), u32> {
        let size = self.od.get(index, sub).and_then(|e| e.dtype.size()).unwrap_or(4).min(8);
        self.write_object(index, sub, &value.to_le_bytes()[..size], now)
    }

    /// Latch the present targets now (CSP: start the next interpolation segment over the
    /// interpolation period 0x60C2; CSV: take the target velocity). Returns when to latch
    /// the same target again if this CSP segment started from a hold (no target for more
    /// than the extrapolation span): its velocity is a catch-up step, not the path's, and
    /// must not be extrapolated if the next target is late too (else each late target
    /// multiplies the error by the extrapolation span).
    pub(crate) fn modbus_latch(&mut self, now: u64) -> Option<u64> {
        let fresh = self.seg_len == 0 || now.saturating_sub(self.seg_t0) > self.seg_len * (1 + self.late_periods());
        let before = self.seg_t0;
        self.latch_setpoints(now, false);
        (fresh && self.seg_t0 == now && before != now).then(|| now + self.seg_len)
    }
}
