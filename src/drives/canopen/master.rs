//! CANopen master for CiA 402 drives: start-up (boot-up, identity, configuration, PDO
//! mapping, NMT start), cyclic PDO exchange with SYNC, the CiA 402 power state machine
//! from the master's side, heartbeat and EMCY consumers.
//!
//! Alarm numbers (ours; the manuals have none for the bus): 2001 node did not boot,
//! 2002 not a CiA 402 device, 2003 SDO failure during configuration, 2010 EMCY / drive
//! fault (with 0x603F and 0x1001 read and decoded), 2011 heartbeat lost, 2012 fault reset failed, 2013 enable timed out,
//! 2004 EDS unreadable or disagreeing, 2005 mode missing / not confirmed / left while
//! running, 2006 position scaling or polarity disagrees with the config, 2007 another master
//! or SYNC producer on the bus, 2008 start-up list entry refused or read back otherwise, 2009
//! fixed PDO mapping that cannot carry the cycle, 2014 node left operational, 2015 stale feedback, 2016 profile
//! move failed, 2017 homing failed, 2018 TPDO of the wrong length, 2020 bus error.

mod bus_check;
mod can_state;
mod drive_check;
mod explain;
mod ext_sync;
mod fixed_pdo;
mod io401;
mod ip_mode;
mod life;
mod mode_track;
mod restore;
mod startup_list;
mod torque;

pub use drive_check::{check_scaling, DriveProbe, Scaling, ALARM_FOREIGN, ALARM_MODE, ALARM_SCALING};
pub use explain::{mode_short, supported_modes_text};
pub use fixed_pdo::ALARM_MAPPING;
pub use mode_track::MODE_TIMEOUT_MS;
pub use startup_list::{check_list_against_eds, ALARM_STARTUP_LIST};

use super::sdo_client::{SdoClient, SdoError};
use crate::config::{AxisKind, CyclicMode, MachineConfig, Polarity, StartupSdo};
use crate::drives::{AxisFeedback, DriveBus};
use crate::Alarm;
use cncgw_bus::canopen::emcy::{error_register_text, error_text, Emcy};
use cncgw_bus::canopen::nmt::{decode_heartbeat, NmtCommand, NmtState};
use cncgw_bus::canopen::pdo::{get_i32, get_u16, put_u16, MapEntry};
use cncgw_bus::canopen::sdo::abort;
use cncgw_bus::canopen::{cob, od, sync_frame};
use cncgw_bus::cia402::{cw, mode, sw, EnableProgress, Enabler, HomingProgress, State};
use cncgw_bus::{CanBus, CanFrame, Clock};

/// The master's own node id for its heartbeat (consumed by the drives through 0x1016).
pub const MASTER_NODE_ID: u8 = 0x7F;
/// An object start-up writes: index, sub, bytes.
type ObjWrite = (u16, u8, usize);
/// An object start-up maps: index, sub, bits, into an RPDO (else a TPDO).
type ObjMap = (u16, u8, u8, bool);

/// RPDO1: controlword + target position (or target velocity), bytes.
pub const RPDO1_LEN: usize = 6;
/// TPDO1: statusword + position actual + modes of operation display, bytes (6 when the
/// drive cannot map 0x6061: see `mode_track`).
pub const TPDO1_LEN: usize = 7;
/// Consecutive TPDO1s of the wrong length before alarm 2018 (one is a glitch the feedback
/// timeout covers; three in a row is a mapping the drive did not take).
const BAD_LEN_ALARM: u32 = 3;

/// The cyclic frames of `drives` CANopen drives in CSP, for the bus-load figure: one
/// `RPDO1_LEN` and one `TPDO1_LEN` frame each, and the SYNC.
pub fn cyclic_frames(drives: usize) -> Vec<usize> {
    cncgw_bus::busload::csp_frames(drives, RPDO1_LEN, TPDO1_LEN)
}

/// [`cyclic_frames`] and each CiA 401 module's (`(node, inputs, outputs)`, bits as
/// `io::Resolved::canopen_modules` gives them): its outputs (RPDO1, every cycle) and inputs
/// (TPDO1, every SYNC), a byte per 8 bits (`io401`).
pub fn cyclic_frames_io(drives: usize, modules: &[(u8, u8, u8)]) -> Vec<usize> {
    let mut v = cyclic_frames(drives);
    for (_, i, o) in modules {
        v.push(io401::pdo_bytes(*o) as usize);
        v.push(io401::pdo_bytes(*i) as usize);
    }
    v
}

/// The torque reads (`NodeSpec` per drive in order) in a frame list that starts with
/// [`cyclic_frames`]' RPDO, TPDO per drive: friction feed-forward (`NodeSpec::friction`)
/// carries 0x60B2 in RPDO1 too and reads the torque all the time; a spindle reads it all the
/// time where its drive gives its max torque 0x6072 (`torque`; not known before start-up:
/// counted) — an SDO request and its answer, 8 bytes each, one every other cycle (a new read
/// starts the cycle after an answer).
pub fn add_torque_frames<'a>(frames: &mut Vec<usize>, specs: impl Iterator<Item = &'a NodeSpec>) {
    for (i, s) in specs.enumerate() {
        if s.friction {
            frames[2 * i] = RPDO1_LEN + 2;
        }
        if s.friction || s.spindle {
            frames.push(8);
        }
    }
}

fn le_u32(d: &[u8]) -> u32 {
    let mut b = [0u8; 4];
    let n = d.len().min(4);
    b[..n].copy_from_slice(&d[..n]);
    u32::from_le_bytes(b)
}

/// Cycles until a statusword reflects a controlword sent in the first of them.
const FRESH_STATUS_CYCLES: u32 = 3;
/// How often SDO waits look at the bus.
const POLL_NS: u64 = 200_000;
/// 0x1029:1 = 0: a communication error takes the drive to pre-operational (`configure_error_behaviour`).
const ERROR_BEHAVIOUR_PRE_OPERATIONAL: u8 = 0;
/// Aborts of a 0x1029:1 write that mean the drive's reaction is fixed (read-only, or 0 not
/// among its choices): a fact to log, not a reason to refuse the drive.
const FIXED_ERROR_BEHAVIOUR: [u32; 4] = [abort::READ_ONLY, abort::UNSUPPORTED_ACCESS, abort::INVALID_VALUE, abort::VALUE_TOO_LOW];

/// One drive as the configuration describes it.
#[derive(Clone, Debug)]
pub struct NodeSpec {
    pub axis: String,
    pub node: u8,
    pub spindle: bool,
    pub counts_per_unit: f64,
    /// Following-error window (0x6065) in machine units.
    pub following_error: f64,
    pub min: Option<f64>,
    pub max: Option<f64>,
    /// EDS file of the drive (`axes.NAME.eds`), checked at start-up.
    pub eds: Option<String>,
    /// RPDO1 / TPDO1 COB-IDs and transmission types (config; default 0x200/0x180 + node, 1).
    pub rpdo_cob: u16,
    pub tpdo_cob: u16,
    pub rpdo_tx: u8,
    pub tpdo_tx: u8,
    /// Axis travel per motor revolution (`axes.NAME.travel_per_rev`), checked against the
    /// drive's factor group at start-up.
    pub travel_per_rev: Option<f64>,
    /// The drive's position polarity (`axes.NAME.polarity`), checked against 0x607E.
    pub polarity: Polarity,
    /// Interpolated position (`axes.NAME.mode = "ip"`) instead of CSP.
    pub ip: bool,
    /// The start-up list (`[[axes.NAME.sdo]]`).
    pub sdo: Vec<StartupSdo>,
    /// Friction feed-forward through 0x60B2 (`axes.NAME.friction_compensation`; CSP feed
    /// axes only): RPDO1 carries the torque offset and 0x6077 is read every cycle.
    pub friction: bool,
}

impl NodeSpec {
    /// The drives of a machine, in the config's axis order.
    pub fn from_config(cfg: &MachineConfig) -> Vec<NodeSpec> {
        cfg.axes
            .iter()
            .filter(|(_, a)| a.modbus.is_none())
            .map(|(name, a)| NodeSpec {
                axis: name.clone(),
                node: a.node,
                spindle: a.kind == AxisKind::Spindle,
                counts_per_unit: a.counts_per_unit,
                following_error: a.following_error,
                min: a.min,
                max: a.max,
                eds: a.eds.clone(),
                rpdo_cob: a.pdo_cob_ids().0,
                tpdo_cob: a.pdo_cob_ids().1,
                rpdo_tx: a.rpdo_transmission,
                tpdo_tx: a.tpdo_transmission,
                travel_per_rev: a.travel_per_rev,
                polarity: a.polarity,
                ip: a.mode == CyclicMode::Ip,
                sdo: a.sdo.clone(),
                friction: a.friction_compensation && a.kind != AxisKind::Spindle && a.mode != CyclicMode::Ip,
            })
            .collect()
    }

    /// The cyclic position mode: interpolated position (7) or CSP (8).
    pub fn position_mode(&self) -> i8 {
        if self.ip {
            mode::INTERPOLATED_POSITION
        } else {
            mode::CYCLIC_SYNC_POSITION
        }
    }

    /// Where the cyclic position set-point goes: 0x60C1:1 in IP, 0x607A in CSP.
    pub fn target_object(&self) -> (u16, u8) {
        if self.ip {
            (od::INTERPOLATION_DATA, 1)
        } else {
            (od::TARGET_POSITION, 0)
        }
    }
}

/// Identity read at start-up (0x1000, 0x1018, 0x1008). `None`: the drive did not give it
/// (absent, or the read aborted) — never shown as 0.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodeInfo {
    pub node: u8,
    pub device_type: u32,
    pub vendor: Option<u32>,
    pub product: Option<u32>,
    pub revision: Option<u32>,
    pub serial: Option<u32>,
    pub name: String,
}

/// "0x00000CA7", or "unreadable" for an identity entry the drive did not give.
pub fn hex_or_unreadable(v: Option<u32>) -> String {
    v.map_or_else(|| "unreadable".to_string(), |v| format!("0x{v:08X}"))
}

/// A drive fault being diagnosed: 0x603F and 0x1001 are read (SDO, without blocking the
/// cycle) before alarm 2010 is raised. Every axis is quick-stopped when it starts.
struct Diag {
    node: usize,
    /// What was seen first: the EMCY or the state the drive fell into.
    seen: String,
    reading: u16,
    code: Option<Result<u16, String>>,
    register: Option<Result<u8, String>>,
}

struct Node {
    spec: NodeSpec,
    sdo: SdoClient,
    booted: bool,
    nmt: Option<NmtState>,
    last_hb_ns: u64,
    status: u16,
    raw_pos: i32,
    unwrapped: i64,
    have_fb: bool,
    /// Clock time of the last TPDO1.
    fb_ns: u64,
    /// SYNCs sent since the last TPDO1: a drive's silence is SYNCs it did not answer (a
    /// stall of the controller itself sends none, and is the watchdog's).
    syncs_unanswered: u32,
    target: i64,
    controlword: u16,
    enabled: bool,
    reset_attempts: u32,
    last_emcy: Option<Emcy>,
    info: NodeInfo,
    /// Cyclic synchronous velocity (a spindle in speed mode): RPDO1 carries 0x60FF.
    csv: bool,
    /// Consecutive TPDO1s whose statusword is not Operation Enabled (a fault without an EMCY
    /// counts from the second: one frame with a flipped bit is not a fault).
    not_enabled: u32,
    /// 0x60FF, counts/s.
    target_vel: i32,
    /// The mode asked for and the mode the drive shows (0x6061).
    mode: mode_track::ModeTrack,
    /// Torque actual 0x6077 of a spindle drive, polled by SDO while running (`torque`).
    torque: torque::TorquePoll,
    /// TPDO1's length since start-up mapped it (`None`: not configured by this master; any
    /// frame of at least 6 bytes is taken).
    tpdo_len: Option<u8>,
    /// TPDO1s of another length: in a row, in all, and the last length seen.
    bad_len: u32,
    bad_len_total: u64,
    bad_len_last: u8,
    /// Node guarding by the master (a drive without a heartbeat consumer).
    guarding: Option<life::Guarding>,
    /// IP: consecutive TPDO1s in Operation Enabled without statusword bit 12 (ip mode active).
    ip_inactive: u32,
    /// IP: consecutive RPDO1s sent with controlword bit 4 (enable ip mode) set.
    ip_sent: u32,
    /// Where the values sit in RPDO1 and TPDO1 (the master's own mapping, or a drive's
    /// fixed one: `fixed_pdo`).
    rpdo_at: fixed_pdo::RpdoLayout,
    tpdo_at: fixed_pdo::TpdoLayout,
    /// How start-up set the drive up, for the log line and `cncgw scan`-like reports.
    chosen: Chosen,
    /// Friction feed-forward (`NodeSpec::friction`, on once RPDO1 carries 0x60B2), the
    /// set-point as asked (counts, unrounded) and the torque offset sent with it (‰).
    friction: Option<crate::drives::friction::FrictionComp>,
    target_exact: f64,
    torque_offset: i16,
    /// Why the drive's position can no longer be trusted since start-up (a boot-up message
    /// the master did not cause, an encoder EMCY): its reference is lost (`reference`).
    position_lost: Option<String>,
}

/// What start-up chose for a drive and why, logged once per drive.
#[derive(Clone, Debug, Default)]
struct Chosen {
    mapping: String,
    error_control: String,
}

impl Node {
    fn new(spec: NodeSpec, sdo_timeout_ms: u32) -> Self {
        Node {
            sdo: SdoClient::new(spec.node, sdo_timeout_ms),
            spec,
            booted: false,
            position_lost: None,
            nmt: None,
            last_hb_ns: 0,
            status: 0,
            raw_pos: 0,
            unwrapped: 0,
            have_fb: false,
            fb_ns: 0,
            syncs_unanswered: 0,
            target: 0,
            controlword: 0,
            enabled: false,
            reset_attempts: 0,
            last_emcy: None,
            info: NodeInfo::default(),
            csv: false,
            target_vel: 0,
            not_enabled: 0,
            mode: mode_track::ModeTrack::default(),
            torque: torque::TorquePoll::default(),
            tpdo_len: None,
            bad_len: 0,
            bad_len_total: 0,
            bad_len_last: 0,
            guarding: None,
            ip_inactive: 0,
            ip_sent: 0,
            rpdo_at: fixed_pdo::RpdoLayout::default(),
            tpdo_at: fixed_pdo::TpdoLayout::default(),
            chosen: Chosen::default(),
            friction: None,
            target_exact: 0.0,
            torque_offset: 0,
        }
    }
}

pub struct CanOpenMaster<B: CanBus> {
    bus: B,
    nodes: Vec<Node>,
    cycle_ns: u64,
    cycle_ms: f64,
    hb_ms: u16,
    next_hb_ns: u64,
    boot_timeout_ms: u32,
    bitrate: u32,
    feedback_timeout_ns: u64,
    cycles: u64,
    /// Clock time of the last `receive`.
    now_ns: u64,
    enable_cycles: u64,
    running: bool,
    /// The master heartbeat runs from the first configured consumer on.
    hb_started: bool,
    diag: Option<Diag>,
    /// `isolate_faults`: a fault quick-stops only the faulted drive.
    isolate: bool,
    /// The drive isolated in its fault reaction (see `DriveBus::faulted`).
    faulted: Option<usize>,
    /// While start-up may still fail: the values its writes replaced (see `restore`).
    undo: Option<Vec<restore::Undo>>,
    /// The NMT state of each node before start-up reset it.
    found: Vec<Option<NmtState>>,
    /// CiA 401 I/O modules on this bus (`io401`).
    io: Vec<io401::IoModule>,
    /// `bus.sync = "external"`: the SYNC the cycle runs on comes from elsewhere.
    ext_sync: ext_sync::ExtSync,
    /// The CAN controller's state as last reported (see `can_state`).
    ctrl_seen: cncgw_bus::can_error::ControllerStatus,
}

/// Who a blocking SDO transfer is with: drive `i` or I/O module `k`.
#[derive(Clone, Copy)]
enum Peer {
    Drive(usize),
    Io(usize),
}

enum Sdo<'a> {
    Up(u16, u8),
    Down(u16, u8, &'a [u8]),
    BlockUp(u16, u8),
    BlockDown(u16, u8, &'a [u8]),
}

impl<B: CanBus> CanOpenMaster<B> {
    pub fn new(bus: B, cfg: &MachineConfig) -> Self {
        let timeout = cfg.bus.sdo_timeout_ms;
        let nodes = NodeSpec::from_config(cfg).into_iter().map(|spec| Node::new(spec, timeout)).collect();
        CanOpenMaster {
            bus,
            nodes,
            cycle_ns: cfg.cycle_ns(),
            cycle_ms: cfg.machine.cycle_ms,
            hb_ms: cfg.bus.heartbeat_ms,
            next_hb_ns: 0,
            boot_timeout_ms: timeout.max(100) * 4,
            bitrate: cfg.bus.bitrate,
            feedback_timeout_ns: (cfg.bus.feedback_timeout_ms * 1e6) as u64,
            now_ns: 0,
            cycles: 0,
            enable_cycles: 0,
            running: false,
            hb_started: false,
            diag: None,
            isolate: false,
            faulted: None,
            undo: None,
            found: Vec::new(),
            io: cfg.io.resolve().unwrap_or_default().canopen_modules().into_iter().map(|(n, i, o)| io401::IoModule::new(n, i, o, timeout)).collect(),
            ext_sync: ext_sync::ExtSync::from_config(cfg),
            ctrl_seen: Default::default(),
        }
    }

    /// Worst-case bus load of the cyclic traffic (one 6-byte RPDO and TPDO per drive, each
    /// I/O module's outputs and inputs, and the SYNC every cycle), 0…1.
    pub fn bus_load(&self, bitrate: u32) -> f64 {
        cncgw_bus::busload::load(&self.frames(), self.cycle_ns as f64 * 1e-9, bitrate)
    }

    fn frames(&self) -> Vec<usize> {
        let mut v = cyclic_frames(self.nodes.len());
        add_torque_frames(&mut v, self.nodes.iter().map(|n| &n.spec));
        v.extend(self.io.iter().flat_map(|m| m.pdo_lens()));
        v
    }

    /// Refuse a cycle the bus cannot carry (over 80 % worst-case load), naming one that fits.
    pub fn check_bus_load(&self, bitrate: u32) -> Result<f64, Alarm> {
        let load = self.bus_load(bitrate);
        if load > 0.8 {
            let fits = cncgw_bus::busload::shortest_cycle_s(&self.frames(), bitrate, 0.8);
            let io = if self.io.is_empty() { String::new() } else { format!(" and {} I/O modules", self.io.len()) };
            let ff = self.nodes.iter().filter(|n| n.spec.friction).count();
            let ff = if ff == 0 { String::new() } else { format!(", or friction_compensation off on {ff} axes (each reads its torque every cycle)") };
            return Err(Alarm::new(
                crate::alarm::BUS_LOAD,
                format!(
                    "bus load {:.0} % at {} ms cycle and {} bit/s for {} drives{io} is over 80 %; use machine.cycle_ms = {} or more (or a higher bitrate{ff})",
                    load * 100.0,
                    self.cycle_ms,
                    bitrate,
                    self.nodes.len(),
                    fits * 1000.0
                ),
            ));
        }
        Ok(load)
    }

    /// What start-up would refuse before it touches a drive, checked without a bus
    /// (`cncgw config check`): the bus load, and each axis' EDS (`axes.NAME.eds`) against what
    /// start-up writes and maps. One line per problem.
    pub fn offline_check(&self, bitrate: u32) -> Vec<String> {
        let mut out = Vec::new();
        if let Err(a) = self.check_bus_load(bitrate) {
            out.push(format!("alarm {:04}: {}", a.number, a.message));
        }
        for n in &self.nodes {
            let Some(path) = &n.spec.eds else { continue };
            match cncgw_bus::canopen::eds::Eds::load(std::path::Path::new(path)) {
                Ok(eds) => {
                    for b in self.check_eds(n.spec.node, &eds) {
                        out.push(format!("axes.{}.eds: {b}", n.spec.axis));
                    }
                }
                Err(e) => out.push(format!("axes.{}.eds: {e} (a relative path is from the working directory)", n.spec.axis)),
            }
        }
        out
    }

    /// Read `index:sub` of `node` over SDO (service tools, diagnostics).
    pub fn sdo_read(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8) -> Result<Vec<u8>, Alarm> {
        let i =
            self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::SDO_CONFIG, format!("node {node} is not in the machine configuration")))?;
        self.sdo(clock, i, Sdo::Up(index, sub))
            .map_err(|e| self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("reading 0x{index:04X}:{sub:02X} failed: {e}")))
    }

    /// Write `data` to `index:sub` of `node` over SDO.
    pub fn sdo_write(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8, data: &[u8]) -> Result<(), Alarm> {
        let i =
            self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::SDO_CONFIG, format!("node {node} is not in the machine configuration")))?;
        self.write(clock, i, index, sub, data)
    }

    pub fn infos(&self) -> Vec<NodeInfo> {
        self.nodes.iter().map(|n| n.info.clone()).collect()
    }

    pub fn bus_name(&self) -> &str {
        self.bus.name()
    }

    // ---- Diagnostics (service tools): no configuration is written, nothing is enabled. ----

    /// Add `node` for diagnostics if the configuration does not name it (SDO and NMT to
    /// any node id). Its axis name is "-" and it has no scaling.
    pub fn ensure_node(&mut self, node: u8) {
        if self.index_of(node).is_some() {
            return;
        }
        let spec = NodeSpec {
            axis: "-".into(),
            node,
            spindle: false,
            counts_per_unit: 1.0,
            following_error: 0.0,
            min: None,
            max: None,
            eds: None,
            rpdo_cob: cob::RPDO1 + node as u16,
            tpdo_cob: cob::TPDO1 + node as u16,
            rpdo_tx: 1,
            tpdo_tx: 1,
            travel_per_rev: None,
            polarity: Polarity::Normal,
            ip: false,
            sdo: Vec::new(),
            friction: false,
        };
        let timeout = self.boot_timeout_ms / 4;
        self.nodes.push(Node::new(spec, timeout.max(1)));
    }

    /// Node ids, in configuration order (then those added by `ensure_node`).
    pub fn node_ids(&self) -> Vec<u8> {
        self.nodes.iter().map(|n| n.spec.node).collect()
    }

    /// The configuration's description of `node`, if it is a configured drive.
    pub fn node_spec(&self, node: u8) -> Option<&NodeSpec> {
        self.nodes.iter().find(|n| n.spec.node == node && n.spec.axis != "-").map(|n| &n.spec)
    }

    /// Listen to the bus for `ms` of clock time, noting boot-ups, heartbeats and EMCYs.
    pub fn listen(&mut self, clock: &mut dyn Clock, ms: u64) {
        self.settle(clock, ms);
    }

    /// Listen until every node has sent its boot-up message or `ms` pass. True if all did.
    pub fn wait_boot(&mut self, clock: &mut dyn Clock, ms: u64) -> bool {
        let end = clock.now_ns() + ms * 1_000_000;
        while !self.nodes.iter().all(|n| n.booted) {
            if clock.now_ns() >= end {
                return false;
            }
            self.settle(clock, 1);
        }
        true
    }

    /// The NMT state `node` last reported (heartbeat; `BootUp` = its boot-up message, after
    /// which it is pre-operational). None if nothing was heard since the last NMT command.
    pub fn nmt_state(&self, node: u8) -> Option<NmtState> {
        self.index_of(node).and_then(|i| self.nodes[i].nmt)
    }

    /// Whether a boot-up message from `node` was heard.
    pub fn booted(&self, node: u8) -> bool {
        self.index_of(node).is_some_and(|i| self.nodes[i].booted)
    }

    /// The last EMCY heard from `node` (None also after an "error reset" EMCY).
    pub fn last_emcy(&self, node: u8) -> Option<Emcy> {
        self.index_of(node).and_then(|i| self.nodes[i].last_emcy)
    }

    /// Send an NMT command to `node` (0 = every node). The states heard before it are
    /// forgotten; after a reset, the boot-up is awaited afresh (`wait_boot`).
    pub fn nmt_command(&mut self, node: u8, cmd: NmtCommand) -> Result<(), Alarm> {
        self.send(&cmd.frame(node))?;
        let reset = matches!(cmd, NmtCommand::ResetNode | NmtCommand::ResetCommunication);
        for n in self.nodes.iter_mut().filter(|n| node == 0 || n.spec.node == node) {
            n.nmt = None;
            if reset {
                n.booted = false;
            }
        }
        Ok(())
    }

    /// One SDO upload with the protocol error kept (abort code, timeout) for service tools.
    pub fn sdo_upload(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8) -> Result<Vec<u8>, SdoError> {
        let i = self.index_of(node).ok_or(SdoError::Protocol("node not known to the master (call ensure_node)"))?;
        self.sdo(clock, i, Sdo::Up(index, sub))
    }

    /// One SDO download with the protocol error kept.
    pub fn sdo_download(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8, data: &[u8]) -> Result<(), SdoError> {
        let i = self.index_of(node).ok_or(SdoError::Protocol("node not known to the master (call ensure_node)"))?;
        self.sdo(clock, i, Sdo::Down(index, sub, data)).map(|_| ())
    }

    /// Read a large object (DOMAIN, long strings) of `node` with an SDO block upload
    /// (CRC checked when the drive offers it). Far fewer round trips than `sdo_upload`.
    pub fn sdo_block_upload(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8) -> Result<Vec<u8>, SdoError> {
        let i = self.index_of(node).ok_or(SdoError::Protocol("node not known to the master (call ensure_node)"))?;
        self.sdo(clock, i, Sdo::BlockUp(index, sub))
    }

    /// Write a large object of `node` with an SDO block download.
    pub fn sdo_block_download(&mut self, clock: &mut dyn Clock, node: u8, index: u16, sub: u8, data: &[u8]) -> Result<(), SdoError> {
        let i = self.index_of(node).ok_or(SdoError::Protocol("node not known to the master (call ensure_node)"))?;
        self.sdo(clock, i, Sdo::BlockDown(index, sub, data)).map(|_| ())
    }

    /// Read the identity (0x1000, 0x1018:1…4, 0x1008) of `node` without checking or
    /// configuring anything. Entries the drive does not give stay `None` / empty.
    pub fn read_identity(&mut self, clock: &mut dyn Clock, node: u8) -> Result<NodeInfo, SdoError> {
        let i = self.index_of(node).ok_or(SdoError::Protocol("node not known to the master (call ensure_node)"))?;
        let device_type = self.read_u32(clock, i, od::DEVICE_TYPE, 0)?;
        let mut info = NodeInfo { node, device_type, ..NodeInfo::default() };
        info.vendor = self.read_u32(clock, i, od::IDENTITY, 1).ok();
        info.product = self.read_u32(clock, i, od::IDENTITY, 2).ok();
        info.revision = self.read_u32(clock, i, od::IDENTITY, 3).ok();
        info.serial = self.read_u32(clock, i, od::IDENTITY, 4).ok();
        if let Ok(name) = self.sdo(clock, i, Sdo::Up(od::DEVICE_NAME, 0)) {
            info.name = String::from_utf8_lossy(&name).trim_end_matches('\0').trim().to_string();
        }
        Ok(info)
    }

    fn node_alarm(&self, i: usize, number: u32, msg: impl std::fmt::Display) -> Alarm {
        let n = &self.nodes[i];
        Alarm::new(number, format!("node {} (axis {}): {msg}", n.spec.node, n.spec.axis))
    }

    fn bus_alarm(&self, e: impl std::fmt::Display) -> Alarm {
        Alarm::new(crate::alarm::CAN_BUS, format!("{e}"))
    }

    fn send(&mut self, f: &CanFrame) -> Result<(), Alarm> {
        self.bus.send(f).map_err(|e| Alarm::new(crate::alarm::CAN_BUS, e.to_string()))
    }

    fn index_of(&self, node: u8) -> Option<usize> {
        self.nodes.iter().position(|n| n.spec.node == node)
    }

    /// Node indices in node-id order (the order start-up configures them and names them in
    /// alarms; the axis order stays the configuration's).
    fn by_node_id(&self) -> Vec<usize> {
        let mut v: Vec<usize> = (0..self.nodes.len()).collect();
        v.sort_by_key(|&i| self.nodes[i].spec.node);
        v
    }

    /// TPDO1s of the wrong length `node` sent since start-up (counted, not used).
    pub fn pdo_length_errors(&self, node: u8) -> u64 {
        self.index_of(node).map_or(0, |i| self.nodes[i].bad_len_total)
    }

    /// The mode `node` last showed in 0x6061 (TPDO1 or SDO poll), once start-up asked for one.
    pub fn mode_display(&self, node: u8) -> Option<i8> {
        self.index_of(node).and_then(|i| self.nodes[i].mode.shown)
    }

    /// Whether the master guards `node` (node guarding) instead of consuming its heartbeat.
    pub fn guarded(&self, node: u8) -> bool {
        self.index_of(node).is_some_and(|i| self.nodes[i].guarding.is_some())
    }

    /// Handle a frame that is not the answer being waited for: boot-ups, heartbeats,
    /// EMCY and TPDOs.
    fn on_background(&mut self, f: &CanFrame, now_ns: u64) {
        if self.on_sync_heard(f, now_ns) || (!self.io.is_empty() && self.io_frame(f, now_ns)) {
            return;
        }
        let (func, node) = cob::split(f.cob_id());
        // TPDO1 by its configured COB-ID first (it need not be 0x180 + node).
        let by_tpdo = self.nodes.iter().position(|n| n.spec.tpdo_cob == f.cob_id());
        let Some(i) = by_tpdo.or_else(|| self.index_of(node)) else { return };
        if by_tpdo.is_none() && func == cob::TPDO1 {
            return; // another node's default TPDO COB-ID, not configured here
        }
        if let Some((_, st)) = decode_heartbeat(f).filter(|_| by_tpdo.is_none()) {
            let n = &mut self.nodes[i];
            if st == NmtState::BootUp {
                // A second boot-up with no reset of ours in between: the drive rebooted
                // (power, watchdog, its own reset) and its position starts afresh.
                if n.booted && n.position_lost.is_none() {
                    n.position_lost = Some("it sent a boot-up message (0x700 + id, 0x00): it rebooted".into());
                }
                n.booted = true;
                n.have_fb = false;
            }
            n.nmt = Some(st);
            n.last_hb_ns = now_ns;
            return;
        }
        if let Some((_, e)) = Emcy::decode(f).filter(|_| by_tpdo.is_none()) {
            if (0x7300..=0x73FF).contains(&e.code) && self.nodes[i].position_lost.is_none() {
                // CiA 402 0x73xx: sensor (encoder) fault: the position is lost.
                self.nodes[i].position_lost = Some(format!("EMCY 0x{:04X} {}: an encoder fault", e.code, error_text(e.code)));
            }
            self.nodes[i].last_emcy = if e.code == 0 { None } else { Some(e) };
            if e.code != 0 {
                tracing::warn!(node, code = format!("0x{:04X}", e.code), "EMCY: {}", error_text(e.code));
            }
            return;
        }
        if by_tpdo.is_some() {
            let n = &mut self.nodes[i];
            let good = match n.tpdo_len {
                Some(len) => f.len == len,
                None => f.len >= 6,
            };
            if !good {
                // Not processed, but counted: a persistent wrong length is alarm 2018 in
                // `receive`, naming both lengths.
                n.bad_len = n.bad_len.saturating_add(1);
                n.bad_len_total += 1;
                n.bad_len_last = f.len;
                return;
            }
            n.bad_len = 0;
            let at = n.tpdo_at;
            if let Some(mo) = at.mode.filter(|&mo| n.mode.in_pdo && (f.len as usize) > mo) {
                // As the statusword: one frame with a flipped bit is not a mode change.
                let m = f.data[mo] as i8;
                if n.mode.shown != Some(m) && n.mode.confirmed && n.mode.odd_frames == 0 {
                    n.mode.odd_frames = 1;
                } else {
                    n.mode.odd_frames = 0;
                    n.mode.shown = Some(m);
                }
            }
            let raw = get_i32(&f.data, at.pos);
            if n.have_fb && raw.wrapping_sub(n.raw_pos).unsigned_abs() >= 1 << 30 {
                // No axis moves 2^30 counts between two TPDOs: a corrupt frame (a flipped top
                // bit would otherwise shift the unwrapped position by 2^32 for good). Dropped;
                // the feedback ages by a cycle.
                tracing::warn!(node = n.spec.node, "implausible position in TPDO1 ignored");
                return;
            }
            n.status = get_u16(&f.data, at.status);
            n.not_enabled = if State::from_statusword(n.status) == State::OperationEnabled { 0 } else { n.not_enabled.saturating_add(1) };
            self.note_ip_status(i);
            let n = &mut self.nodes[i];
            if n.have_fb {
                // INTEGER32 positions wrap; a spindle passes 2^31 counts within minutes.
                n.unwrapped += raw.wrapping_sub(n.raw_pos) as i64;
            } else {
                n.unwrapped = raw as i64;
            }
            n.raw_pos = raw;
            n.have_fb = true;
            if let Some(f) = n.friction.as_mut() {
                f.observe_actual(n.unwrapped);
            }
            n.fb_ns = now_ns;
            n.syncs_unanswered = 0;
        }
    }

    /// One SDO transfer with node `i`, waiting with `clock`. Retries once on timeout.
    fn sdo(&mut self, clock: &mut dyn Clock, i: usize, req: Sdo<'_>) -> Result<Vec<u8>, SdoError> {
        self.settle_background_sdo(clock, i);
        self.transfer(clock, Peer::Drive(i), req)
    }

    /// The SDO client of `peer` and its node id.
    fn peer_sdo(&mut self, peer: Peer) -> (&mut SdoClient, u8) {
        match peer {
            Peer::Drive(i) => {
                let n = &mut self.nodes[i];
                (&mut n.sdo, n.spec.node)
            }
            Peer::Io(k) => self.io[k].sdo_channel(),
        }
    }

    /// One SDO transfer with `peer`, waiting with `clock`, the rest of the bus served in the
    /// background. Retries once on timeout.
    fn transfer(&mut self, clock: &mut dyn Clock, peer: Peer, req: Sdo<'_>) -> Result<Vec<u8>, SdoError> {
        let mut tries = 0;
        loop {
            tries += 1;
            let now = clock.now_ns();
            let (c, _) = self.peer_sdo(peer);
            let f = match req {
                Sdo::Up(ix, sub) => c.start_upload(ix, sub, now),
                Sdo::Down(ix, sub, d) => c.start_download(ix, sub, d, now),
                Sdo::BlockUp(ix, sub) => c.start_block_upload(ix, sub, now),
                Sdo::BlockDown(ix, sub, d) => c.start_block_download(ix, sub, d, now),
            };
            if self.bus.send(&f).is_err() {
                return Err(SdoError::Protocol("cannot send on the bus"));
            }
            let r = loop {
                self.pump_sdo(clock, peer);
                if let Some(r) = self.peer_sdo(peer).0.take_result() {
                    break r;
                }
            };
            match r {
                Err(SdoError::Timeout { .. }) if tries < 2 => continue,
                r => return r,
            }
        }
    }

    /// Wait one poll step and serve `peer`'s SDO channel (the rest of the bus in the
    /// background), for a blocking transfer.
    fn pump_sdo(&mut self, clock: &mut dyn Clock, peer: Peer) {
        let t = clock.now_ns() + POLL_NS;
        clock.wait_until(t);
        let now = clock.now_ns();
        while let Ok(Some(fr)) = self.bus.try_recv() {
            let (func, node) = cob::split(fr.cob_id());
            let (c, id) = self.peer_sdo(peer);
            if func == cob::SDO_TX && node == id {
                for out in c.on_frame(&fr, now) {
                    let _ = self.bus.send(&out);
                }
            } else {
                self.on_background(&fr, now);
            }
        }
        if let Some(out) = self.peer_sdo(peer).0.poll(now) {
            let _ = self.bus.send(&out);
        }
        let _ = self.tick_life(now);
    }

    /// A background read still in flight on node `i`'s SDO channel (the mode or torque poll
    /// of the cycle) is let finish first and its answer dropped: a transfer started over it
    /// would take that answer for its own ("unexpected SDO response").
    fn settle_background_sdo(&mut self, clock: &mut dyn Clock, i: usize) {
        while self.nodes[i].sdo.busy() {
            self.pump_sdo(clock, Peer::Drive(i));
        }
        let n = &mut self.nodes[i];
        let _ = n.sdo.take_expedited();
        n.torque.polling = false;
        n.mode.polling = false;
    }

    fn read_u32(&mut self, clock: &mut dyn Clock, i: usize, ix: u16, sub: u8) -> Result<u32, SdoError> {
        self.sdo(clock, i, Sdo::Up(ix, sub)).map(|v| le_u32(&v))
    }

    /// Write an object; during start-up its old value is kept first (`restore`). Errors
    /// are alarm 2003 with the abort explained for this object (`explain`).
    fn write(&mut self, clock: &mut dyn Clock, i: usize, ix: u16, sub: u8, data: &[u8]) -> Result<(), Alarm> {
        self.try_write(clock, i, ix, sub, data).map_err(|e| self.write_alarm(i, ix, sub, data, &e))
    }

    /// `write` keeping the SDO error (for writes whose absence has a fallback).
    fn try_write(&mut self, clock: &mut dyn Clock, i: usize, ix: u16, sub: u8, data: &[u8]) -> Result<(), SdoError> {
        if self.undo.is_some() {
            self.keep_for_undo(clock, i, ix, sub);
        }
        self.sdo(clock, i, Sdo::Down(ix, sub, data)).map(|_| ())
    }

    fn write_alarm(&self, i: usize, ix: u16, sub: u8, data: &[u8], e: &SdoError) -> Alarm {
        let value = if data.len() <= 4 { format!(" = {}", le_u32(data)) } else { String::new() };
        let why = match e {
            SdoError::Abort { code } => explain::explain_write(ix, sub, *code, data),
            _ => None,
        };
        match why {
            Some(w) => self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("{w} (writing 0x{ix:04X}:{sub:02X}{value} was refused: {e})")),
            None => self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("writing 0x{ix:04X}:{sub:02X}{value} failed: {e}")),
        }
    }

    /// Drain the bus for `ms` milliseconds of clock time, handling background frames.
    fn settle(&mut self, clock: &mut dyn Clock, ms: u64) {
        let end = clock.now_ns() + ms * 1_000_000;
        while clock.now_ns() < end {
            let t = clock.now_ns() + POLL_NS;
            clock.wait_until(t);
            let now = clock.now_ns();
            while let Ok(Some(f)) = self.bus.try_recv() {
                self.on_background(&f, now);
            }
            let _ = self.tick_life(now);
        }
    }

    /// After the NMT reset: every node's boot-up, or alarm 2001 naming the first (by node
    /// id) that did not boot.
    fn wait_all_booted(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        let deadline = clock.now_ns() + self.boot_timeout_ms as u64 * 1_000_000;
        while !self.nodes.iter().all(|n| n.booted) {
            if clock.now_ns() >= deadline {
                let i = self.by_node_id().into_iter().find(|&i| !self.nodes[i].booted).unwrap_or(0);
                return Err(self.node_alarm(
                    i,
                    crate::alarm::CANOPEN_BOOT,
                    format!(
                        "no boot-up message within {} ms after NMT reset communication; check power, wiring, bitrate and the node id",
                        self.boot_timeout_ms
                    ),
                ));
            }
            self.settle(clock, 1);
        }
        Ok(())
    }

    /// NMT start, then run the cycle (SYNC, nothing enabled) until every drive shows the
    /// mode asked for in 0x6061.
    fn start_and_confirm_modes(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        self.send(&NmtCommand::Start.frame(0))?;
        // States heard before the start are stale; the next heartbeat tells.
        for n in &mut self.nodes {
            n.nmt = None;
        }
        self.settle(clock, 1);
        let all = self.by_node_id();
        self.wait_modes(clock, &all)
    }

    /// Configure node `i` for the cycle: its EDS, identity, the checks that must pass before
    /// anything moves (SYNC producer, mode, scaling), the cycle, the mode, the limits, the
    /// PDOs and error control. Each step in its own function (other start-up writes slot in
    /// as further steps).
    fn configure_node(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        self.check_node_eds(i)?;
        self.identify_node(clock, i)?;
        if self.ext_sync.on {
            self.note_sync_producer(clock, i);
        } else {
            self.check_not_sync_producer(clock, i)?;
        }
        let want = self.nodes[i].spec.position_mode();
        self.check_supported_mode(clock, i, want)?;
        let scaling = self.check_node_scaling(clock, i)?;
        self.write_cycle_period(clock, i)?;
        if self.nodes[i].spec.ip {
            self.configure_ip(clock, i)?;
        }
        // The mode it booted in, for the start-up line (a drive in PP is switched below and
        // confirmed through 0x6061 before it is enabled).
        let booted_in = self.read_u32(clock, i, od::MODES_DISPLAY, 0).ok().map(|v| v as u8 as i8);
        self.nodes[i].mode.want = want;
        self.nodes[i].mode.confirmed = false;
        self.write(clock, i, od::MODES_OF_OPERATION, 0, &[want as u8])?;
        let spec = self.nodes[i].spec.clone();
        let win = (spec.following_error * spec.counts_per_unit).round().clamp(1.0, u32::MAX as f64) as u32;
        self.write(clock, i, od::FOLLOWING_ERROR_WINDOW, 0, &win.to_le_bytes())?;
        if spec.spindle {
            // Optional (CiA 402): a drive without it is not judged on its torque margin.
            self.nodes[i].torque.max = self.read_u32(clock, i, od::MAX_TORQUE, 0).ok().map(|v| v as u16).filter(|v| *v > 0);
        }
        // Quick stop: decelerate on the quick-stop ramp, then Switch On Disabled.
        self.prefer_write(
            clock,
            i,
            od::QUICK_STOP_OPTION,
            0,
            &2i16.to_le_bytes(),
            "quick stop option 0x605A: a quick stop does what its manual says",
        )?;
        self.configure_stop_reactions(clock, i)?;
        if let (Some(lo), Some(hi), false) = (spec.min, spec.max, spec.spindle) {
            let lo = (lo * spec.counts_per_unit).floor() as i32;
            let hi = (hi * spec.counts_per_unit).ceil() as i32;
            let what = "software position limits 0x607D: the travel is limited by this controller's limits alone";
            if self.prefer_write(clock, i, od::SOFTWARE_LIMIT, 1, &lo.to_le_bytes(), what)? {
                self.write(clock, i, od::SOFTWARE_LIMIT, 2, &hi.to_le_bytes())?;
            }
        }
        self.map_cyclic_pdos(clock, i)?;
        self.configure_error_control(clock, i)?;
        self.write_startup_list(clock, i)?;
        let n = &self.nodes[i];
        let booted = match booted_in {
            Some(b) if b != want && b != 0 => {
                format!(", booted in {} and switched by 0x6060 (confirmed by 0x6061 before enabling)", explain::mode_words(b))
            }
            _ => String::new(),
        };
        tracing::info!(
            node = n.spec.node,
            axis = %n.spec.axis,
            "start-up: mode {} ({}){booted}; mapping: {}; error control: {}; units: {}{}",
            explain::mode_short(want),
            if n.spec.ip { format!("axes.{}.mode = \"ip\"", n.spec.axis) } else { "the default".into() },
            n.chosen.mapping,
            n.chosen.error_control,
            scaling.unit_text(),
            if n.spec.sdo.is_empty() { String::new() } else { format!("; start-up list: {} object(s) read back equal", n.spec.sdo.len()) }
        );
        Ok(())
    }

    /// Write an object the master only prefers (CiA 402 makes it optional and the master has
    /// its own safeguard): a drive without it gets a warning saying what that means, not a
    /// refusal; other failures are alarms as for `write`. Ok(true) if written.
    #[allow(clippy::too_many_arguments)]
    fn prefer_write(&mut self, clock: &mut dyn Clock, i: usize, ix: u16, sub: u8, data: &[u8], without: &str) -> Result<bool, Alarm> {
        match self.try_write(clock, i, ix, sub, data) {
            Ok(()) => Ok(true),
            Err(SdoError::Abort { code }) if explain::is_absent(code) => {
                tracing::warn!(node = self.nodes[i].spec.node, axis = %self.nodes[i].spec.axis, "warning: the drive has no {without}");
                Ok(false)
            }
            Err(e) => Err(self.write_alarm(i, ix, sub, data, &e)),
        }
    }

    /// The drive's own data sheet must allow what start-up writes (before anything is written).
    fn check_node_eds(&mut self, i: usize) -> Result<(), Alarm> {
        let node = self.nodes[i].spec.node;
        let Some(path) = self.nodes[i].spec.eds.clone() else { return Ok(()) };
        let eds = cncgw_bus::canopen::eds::Eds::load(std::path::Path::new(&path)).map_err(|e| {
            self.node_alarm(
                i,
                crate::alarm::EDS,
                format!("EDS: {e} (axes.{}.eds; a relative path is from the working directory)", self.nodes[i].spec.axis),
            )
        })?;
        let bad = self.check_eds(node, &eds);
        if !bad.is_empty() {
            return Err(self.node_alarm(
                i,
                crate::alarm::EDS,
                format!("the configuration does not fit the drive's EDS ({} problem(s)): {}", bad.len(), bad.join("; ")),
            ));
        }
        Ok(())
    }

    /// Device type (must be CiA 402), identity and name of node `i`.
    fn identify_node(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let node = self.nodes[i].spec.node;
        let dt = self
            .read_u32(clock, i, od::DEVICE_TYPE, 0)
            .map_err(|e| self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("reading the device type 0x1000 failed: {e}")))?;
        if dt & 0xFFFF != 402 {
            return Err(self.node_alarm(
                i,
                crate::alarm::DEVICE_TYPE,
                format!("device type 0x1000 = 0x{dt:08X} is not a CiA 402 drive (low word must be 402 = 0x0192); check the node id"),
            ));
        }
        let mut info = NodeInfo { node, device_type: dt, ..NodeInfo::default() };
        // The vendor id is mandatory in CiA 301, but only logged here: a drive that will not
        // give it is not refused for that.
        info.vendor = match self.read_u32(clock, i, od::IDENTITY, 1) {
            Ok(v) => Some(v),
            Err(e) => {
                tracing::warn!(node, "the vendor id 0x1018:01 is unreadable ({e})");
                None
            }
        };
        // Product, revision, serial are optional in CiA 301.
        info.product = self.read_u32(clock, i, od::IDENTITY, 2).ok();
        info.revision = self.read_u32(clock, i, od::IDENTITY, 3).ok();
        info.serial = self.read_u32(clock, i, od::IDENTITY, 4).ok();
        if let Ok(name) = self.sdo(clock, i, Sdo::Up(od::DEVICE_NAME, 0)) {
            info.name = String::from_utf8_lossy(&name).trim_end_matches('\0').trim().to_string();
        }
        tracing::info!(
            node,
            axis = %self.nodes[i].spec.axis,
            "CiA 402 drive \"{}\" vendor {} product {} rev {} serial {}",
            info.name,
            hex_or_unreadable(info.vendor),
            hex_or_unreadable(info.product),
            hex_or_unreadable(info.revision),
            info.serial.map_or("unreadable".into(), |s| s.to_string())
        );
        self.nodes[i].info = info;
        Ok(())
    }

    /// 0x1006 (optional for a SYNC consumer, CiA 301) and 0x60C2 (required in CSP).
    fn write_cycle_period(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let cycle_us = (self.cycle_ms * 1000.0).round() as u32;
        match self.try_write(clock, i, od::COMM_CYCLE_PERIOD, 0, &cycle_us.to_le_bytes()) {
            Ok(()) => {}
            Err(SdoError::Abort { code }) if explain::is_absent(code) => {
                tracing::info!(
                    node = self.nodes[i].spec.node,
                    "no 0x1006 (communication cycle period): the drive takes the period from 0x60C2 and the SYNCs"
                );
            }
            Err(e) => return Err(self.write_alarm(i, od::COMM_CYCLE_PERIOD, 0, &cycle_us.to_le_bytes(), &e)),
        }
        let (val, idx) = interpolation_period(self.cycle_ms);
        self.write(clock, i, od::INTERPOLATION_PERIOD, 1, &[val])?;
        self.write(clock, i, od::INTERPOLATION_PERIOD, 2, &[idx as u8])
    }

    /// RPDO1 = controlword + target position; TPDO1 = statusword + position actual + mode
    /// display (or, where the drive cannot map 0x6061, without it: the mode is then polled).
    fn map_cyclic_pdos(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let spec = self.nodes[i].spec.clone();
        let (tix, tsub) = spec.target_object();
        let rpdo = [MapEntry::new(od::CONTROLWORD, 0, 16), MapEntry::new(tix, tsub, 32), MapEntry::new(od::TORQUE_OFFSET, 0, 16)];
        let tpdo = [MapEntry::new(od::STATUSWORD, 0, 16), MapEntry::new(od::POSITION_ACTUAL, 0, 32), MapEntry::new(od::MODES_DISPLAY, 0, 8)];
        self.nodes[i].rpdo_at = fixed_pdo::RpdoLayout::default();
        self.nodes[i].tpdo_at = fixed_pdo::TpdoLayout::default();
        self.nodes[i].friction = None;
        if let Some(text) = self.map_friction_rpdo(clock, i, &rpdo) {
            return self.map_tpdo1(clock, i, &tpdo, text);
        }
        let rpdo = &rpdo[..2];
        let rpdo_text = match self.try_map_pdo(clock, i, od::RPDO_COMM, od::RPDO_MAP, spec.rpdo_cob, spec.rpdo_tx, rpdo) {
            Ok(()) => format!("remapped RPDO1 0x{:03X} = controlword + 0x{tix:04X}:{tsub:02X}", spec.rpdo_cob),
            Err(e) if Self::fixed_fallback(od::RPDO_MAP, &e) => self.use_fixed_rpdo(clock, i, &e.3)?,
            Err((ix, sub, data, e)) => return Err(self.write_alarm(i, ix, sub, &data, &e)),
        };
        self.map_tpdo1(clock, i, &tpdo, rpdo_text)
    }

    /// With friction compensation asked for: RPDO1 = controlword + target + torque offset.
    /// `None` when not asked for, or the drive refused it (said, and mapped without).
    fn map_friction_rpdo(&mut self, clock: &mut dyn Clock, i: usize, rpdo: &[MapEntry; 3]) -> Option<String> {
        let spec = &self.nodes[i].spec;
        if !spec.friction {
            return None;
        }
        let (node, cob, tx) = (spec.node, spec.rpdo_cob, spec.rpdo_tx);
        let (tix, tsub) = spec.target_object();
        match self.try_map_pdo(clock, i, od::RPDO_COMM, od::RPDO_MAP, cob, tx, rpdo) {
            Ok(()) => {
                let n = &mut self.nodes[i];
                n.rpdo_at = fixed_pdo::RpdoLayout::with_torque_offset();
                n.friction = Some(Default::default());
                Some(format!("remapped RPDO1 0x{cob:03X} = controlword + 0x{tix:04X}:{tsub:02X} + torque offset 0x60B2 (friction feed-forward)"))
            }
            Err(e) => {
                tracing::warn!(node, "friction compensation off: the drive does not take the torque offset 0x60B2 in RPDO1 ({})", e.3);
                None
            }
        }
    }

    /// TPDO1 = statusword + position actual + mode display (without it where the drive
    /// cannot map 0x6061), or the drive's fixed one; then the start-up line.
    fn map_tpdo1(&mut self, clock: &mut dyn Clock, i: usize, tpdo: &[MapEntry; 3], rpdo_text: String) -> Result<(), Alarm> {
        let spec = self.nodes[i].spec.clone();
        let refused_third = |e: &(u16, u8, [u8; 4], SdoError)| {
            e.0 == od::TPDO_MAP
                && matches!(e.1, 0 | 3)
                && matches!(e.3, SdoError::Abort { code } if matches!(code, abort::NOT_MAPPABLE | abort::PDO_TOO_LONG | abort::PARAM_INCOMPATIBLE | abort::INVALID_VALUE | abort::NO_SUBINDEX))
        };
        let (tc, tt) = (spec.tpdo_cob, spec.tpdo_tx);
        let tpdo_text = match self.try_map_pdo(clock, i, od::TPDO_COMM, od::TPDO_MAP, tc, tt, tpdo) {
            Ok(()) => self.remapped_tpdo(i, true),
            Err(e) if refused_third(&e) => match self.try_map_pdo(clock, i, od::TPDO_COMM, od::TPDO_MAP, tc, tt, &tpdo[..2]) {
                Ok(()) => {
                    tracing::warn!(
                        node = spec.node,
                        "the drive cannot map 0x6061 (mode display) into TPDO1 ({}): its mode is read by SDO every {} ms instead",
                        e.3,
                        mode_track::POLL_EVERY_NS / 1_000_000
                    );
                    self.remapped_tpdo(i, false)
                }
                Err(e2) if Self::fixed_fallback(od::TPDO_MAP, &e2) => self.use_fixed_tpdo(clock, i, &e2.3)?,
                Err((ix, sub, data, e2)) => return Err(self.write_alarm(i, ix, sub, &data, &e2)),
            },
            Err(e) if Self::fixed_fallback(od::TPDO_MAP, &e) => self.use_fixed_tpdo(clock, i, &e.3)?,
            Err((ix, sub, data, e)) => return Err(self.write_alarm(i, ix, sub, &data, &e)),
        };
        let n = &mut self.nodes[i];
        n.bad_len = 0;
        n.chosen.mapping = format!("{rpdo_text}, {tpdo_text}");
        Ok(())
    }

    /// TPDO1 mapped by the master (with 0x6061 or without): its length and the line's text.
    fn remapped_tpdo(&mut self, i: usize, in_pdo: bool) -> String {
        let n = &mut self.nodes[i];
        n.mode.in_pdo = in_pdo;
        n.tpdo_len = Some(if in_pdo { TPDO1_LEN } else { TPDO1_LEN - 1 } as u8);
        format!(
            "remapped TPDO1 0x{:03X} = statusword + position actual{}",
            n.spec.tpdo_cob,
            if in_pdo { " + mode display" } else { " (0x6061 not mappable: polled by SDO)" }
        )
    }

    /// Error control both ways: the drive's heartbeat (0x1017) and ours consumed by it
    /// (0x1016, 3 periods) with 0x6007 = 1, so that it faults and stops by itself if the
    /// controller dies. A drive without 0x1016 is guarded instead (`guard_node`).
    fn configure_error_control(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        if self.hb_ms == 0 {
            self.nodes[i].chosen.error_control = "none (bus.heartbeat_ms = 0, unsafe_no_heartbeat)".into();
            return Ok(());
        }
        let absent = |r: &Result<(), SdoError>| matches!(r, Err(SdoError::Abort { code }) if explain::is_absent(*code));
        let hb = self.hb_ms.to_le_bytes();
        let producer = self.try_write(clock, i, od::PRODUCER_HEARTBEAT, 0, &hb);
        if let (Err(e), false) = (&producer, absent(&producer)) {
            return Err(self.write_alarm(i, od::PRODUCER_HEARTBEAT, 0, &hb, e));
        }
        if producer.is_ok() {
            // Monitoring of this producer starts now: its first heartbeat is one period away.
            self.nodes[i].last_hb_ns = clock.now_ns().max(1);
        }
        if !self.hb_started {
            self.hb_started = true;
            self.next_hb_ns = clock.now_ns();
        }
        let consumer = (((MASTER_NODE_ID as u32) << 16) | (self.hb_ms as u32 * 3).min(0xFFFF)).to_le_bytes();
        let consumed = self.try_write(clock, i, od::CONSUMER_HEARTBEAT, 1, &consumer);
        if let (Err(e), false) = (&consumed, absent(&consumed)) {
            return Err(self.write_alarm(i, od::CONSUMER_HEARTBEAT, 1, &consumer, e));
        }
        if producer.is_err() || consumed.is_err() {
            self.guard_node(clock, i, producer.is_ok())?;
        } else {
            self.nodes[i].chosen.error_control =
                format!("heartbeat both ways (0x1017 = {} ms, 0x1016 consumes the master's at {} ms)", self.hb_ms, self.hb_ms as u32 * 3);
        }
        let opt = 1i16.to_le_bytes();
        match self.try_write(clock, i, od::ABORT_CONNECTION, 0, &opt) {
            Ok(()) => {}
            Err(SdoError::Abort { code }) if explain::is_absent(code) => {
                tracing::warn!(
                    node = self.nodes[i].spec.node,
                    "no 0x6007 (abort connection option): on a lost master the drive does what its manual says"
                );
            }
            Err(e) => return Err(self.write_alarm(i, od::ABORT_CONNECTION, 0, &opt, &e)),
        }
        self.configure_error_behaviour(clock, i)
    }

    /// 0x1029:1 (error behaviour, CiA 301) = 0: on a communication error (our heartbeat or
    /// guarding lost, bus-off) the drive leaves operational for pre-operational. Why 0 and
    /// not 1 (no change) or 2 (stopped): operational would go on taking PDOs — a set-point a
    /// dying or restarting controller still sends, or a stale one — after 0x6007 has stopped
    /// the motor; stopped takes no SDO, so the restarted controller could not read the
    /// drive's fault (0x603F) before it resets communication. Pre-operational takes no PDOs
    /// and still answers SDOs; it is also CiA 301's default, so the write only undoes a
    /// vendor or earlier setting. Absent (many drives) or read-only (a fixed reaction): said
    /// in the log, not refused.
    fn configure_error_behaviour(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        let value = [ERROR_BEHAVIOUR_PRE_OPERATIONAL];
        match self.try_write(clock, i, od::ERROR_BEHAVIOUR, 1, &value) {
            Ok(()) => {
                self.nodes[i].chosen.error_control.push_str("; 0x1029:1 = 0 (pre-operational on a communication error)");
                Ok(())
            }
            Err(SdoError::Abort { code }) if explain::is_absent(code) || FIXED_ERROR_BEHAVIOUR.contains(&code) => {
                tracing::info!(
                    node = self.nodes[i].spec.node,
                    "0x1029:1 (error behaviour) not set (abort 0x{code:08X}): on a communication error the drive's NMT state does what its manual says"
                );
                Ok(())
            }
            Err(e) => Err(self.write_alarm(i, od::ERROR_BEHAVIOUR, 1, &value, &e)),
        }
    }

    /// Node guarding for a drive without a heartbeat consumer (or producer): guard time
    /// 0x100C = `heartbeat_ms`, life time factor 0x100D = 3, requests from the master every
    /// guard time. Without guarding either (or over a transport without remote frames) a
    /// warning: the drive will not stop by itself if the controller dies.
    fn guard_node(&mut self, clock: &mut dyn Clock, i: usize, heartbeat_set: bool) -> Result<(), Alarm> {
        let (node, axis) = (self.nodes[i].spec.node, self.nodes[i].spec.axis.clone());
        let has_guarding = self.read_u32(clock, i, od::GUARD_TIME, 0).is_ok() && self.read_u32(clock, i, od::LIFE_TIME_FACTOR, 0).is_ok();
        if !has_guarding || !self.bus.remote_frames() {
            let why = if has_guarding {
                format!("{} carries no remote frames for node guarding", self.bus.name())
            } else {
                "nor node guarding (0x100C/0x100D)".to_string()
            };
            tracing::warn!(node, axis = %axis, "WARNING: the drive has no heartbeat consumer (0x1016) {why}: it will not stop by itself if this controller dies; use its own watchdog (SYNC or PDO timeout) if it has one");
            self.nodes[i].chosen.error_control = format!("none: no 0x1016 {why} (warning)");
            return Ok(());
        }
        if heartbeat_set {
            // Heartbeat and guarding exclude each other (CiA 301): 0x1017 back to 0.
            self.write(clock, i, od::PRODUCER_HEARTBEAT, 0, &0u16.to_le_bytes())?;
        }
        self.write(clock, i, od::GUARD_TIME, 0, &self.hb_ms.to_le_bytes())?;
        self.write(clock, i, od::LIFE_TIME_FACTOR, 0, &[3])?;
        self.start_guarding(i, self.hb_ms, clock.now_ns());
        self.nodes[i].chosen.error_control =
            format!("node guarding (no 0x1016 heartbeat consumer): 0x100C = {} ms, 0x100D = 3, remote frames every {} ms", self.hb_ms, self.hb_ms);
        tracing::warn!(
            node,
            axis = %axis,
            "the drive has no heartbeat consumer (0x1016): node guarding instead (0x100C = {} ms, 0x100D = 3); it stops by itself {} ms after this controller stops guarding it",
            self.hb_ms,
            self.hb_ms as u32 * 3
        );
        Ok(())
    }

    /// A drive left alone must brake too, whatever stops it: shutdown (0x605B) and disable
    /// operation (0x605C) slow down on the profile deceleration before the power stage goes
    /// off (1), a fault reaction (0x605E) brakes on the quick-stop ramp (2). Many drives
    /// default to switching off at once (the motor coasts). A drive without one of these
    /// objects is told in the log, not refused: it is optional in CiA 402.
    fn configure_stop_reactions(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        for (ix, v, what) in [
            (od::SHUTDOWN_OPTION, 1i16, "shutdown option 0x605B"),
            (od::DISABLE_OPERATION_OPTION, 1, "disable operation option 0x605C"),
            (od::FAULT_REACTION_OPTION, 2, "fault reaction option 0x605E"),
        ] {
            match self.try_write(clock, i, ix, 0, &v.to_le_bytes()) {
                Ok(()) => {}
                Err(SdoError::Abort { code }) if code == abort::NO_OBJECT || code == abort::NO_SUBINDEX => tracing::warn!(
                    node = self.nodes[i].spec.node,
                    "the drive has no {what}: how it stops when switched off or faulted is its own default"
                ),
                Err(e) => return Err(self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("writing the {what} failed: {e}"))),
            }
        }
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn map_pdo(&mut self, clock: &mut dyn Clock, i: usize, comm: u16, map: u16, cob_id: u16, tx_type: u8, entries: &[MapEntry]) -> Result<(), Alarm> {
        self.try_map_pdo(clock, i, comm, map, cob_id, tx_type, entries).map_err(|(ix, sub, data, e)| self.write_alarm(i, ix, sub, &data, &e))
    }

    /// Map a PDO in the order real drives demand: invalidate, zero count, entries, count,
    /// transmission type, validate. Err: the write that failed (index, sub, value) and why.
    #[allow(clippy::too_many_arguments)]
    fn try_map_pdo(
        &mut self,
        clock: &mut dyn Clock,
        i: usize,
        comm: u16,
        map: u16,
        cob_id: u16,
        tx_type: u8,
        entries: &[MapEntry],
    ) -> Result<(), (u16, u8, [u8; 4], SdoError)> {
        if cncgw_bus::canopen::pdo::mapped_len(entries).is_none() {
            return Err((map, 0, [0; 4], SdoError::Protocol("PDO mapping longer than 8 bytes")));
        }
        let mut w = |m: &mut Self, ix: u16, sub: u8, data: &[u8]| {
            m.try_write(clock, i, ix, sub, data).map_err(|e| {
                let mut d = [0u8; 4];
                d[..data.len().min(4)].copy_from_slice(&data[..data.len().min(4)]);
                (ix, sub, d, e)
            })
        };
        w(self, comm, 1, &(0x8000_0000u32 | cob_id as u32).to_le_bytes())?;
        w(self, map, 0, &[0])?;
        for (k, e) in entries.iter().enumerate() {
            w(self, map, k as u8 + 1, &e.encode().to_le_bytes())?;
        }
        w(self, map, 0, &[entries.len() as u8])?;
        w(self, comm, 2, &[tx_type])?; // 1: synchronous, every SYNC
        w(self, comm, 1, &(cob_id as u32).to_le_bytes())
    }

    /// Node `i` faulted. Isolating (`isolate_faults`, the first fault): only it gets quick
    /// stop, the others keep following their targets for the controlled stop above.
    /// Otherwise quick-stop every axis now (the others must not go on along a path one axis
    /// has left).
    fn fault_reaction(&mut self, i: usize) {
        if self.isolate && self.faulted.is_none_or(|f| f == i) {
            self.faulted = Some(i);
            self.nodes[i].controlword = cw::QUICK_STOP_CMD;
            return;
        }
        self.faulted = None;
        for n in &mut self.nodes {
            if n.enabled {
                n.controlword = cw::QUICK_STOP_CMD;
            }
        }
    }

    /// An alarm about node `i` found by `receive` (heartbeat, NMT state, stale feedback): its
    /// fault reaction, then the alarm.
    fn node_fault(&mut self, i: usize, number: u32, msg: impl std::fmt::Display) -> Alarm {
        self.fault_reaction(i);
        self.node_alarm(i, number, msg)
    }

    /// A drive faulted: the fault reaction (`fault_reaction`), and start reading 0x603F from
    /// the faulted one.
    fn start_diag(&mut self, i: usize, seen: String, now_ns: u64) -> Result<(), Alarm> {
        tracing::warn!(node = self.nodes[i].spec.node, "{seen}: quick stop, reading 0x603F and 0x1001");
        self.fault_reaction(i);
        // (The diagnosis takes the SDO channel: a torque read under way is given up.)
        self.nodes[i].torque.polling = false;
        let f = self.nodes[i].sdo.start_upload(od::ERROR_CODE, 0, now_ns);
        self.send(&f)?;
        self.diag = Some(Diag { node: i, seen, reading: od::ERROR_CODE, code: None, register: None });
        Ok(())
    }

    /// Advance the diagnosis; the finished alarm 2010 once both objects are read or failed.
    fn step_diag(&mut self, now_ns: u64) -> Result<Option<Alarm>, Alarm> {
        let Some(d) = self.diag.as_mut() else { return Ok(None) };
        let i = d.node;
        let sdo = &mut self.nodes[i].sdo;
        let mut out = sdo.poll(now_ns);
        let Some(r) = sdo.take_result() else {
            if let Some(f) = out.take() {
                self.send(&f)?;
            }
            return Ok(None);
        };
        let r = r.map_err(|e| e.to_string());
        if d.reading == od::ERROR_CODE {
            d.code = Some(r.map(|v| u16::from_le_bytes([v.first().copied().unwrap_or(0), v.get(1).copied().unwrap_or(0)])));
            d.reading = od::ERROR_REGISTER;
            let f = sdo.start_upload(od::ERROR_REGISTER, 0, now_ns);
            if let Some(a) = out {
                self.send(&a)?;
            }
            self.send(&f)?;
            return Ok(None);
        }
        d.register = Some(r.map(|v| v.first().copied().unwrap_or(0)));
        if let Some(a) = out {
            self.send(&a)?;
        }
        let Some(d) = self.diag.take() else { return Ok(None) };
        let code = match d.code {
            Some(Ok(0)) => "0x603F error code 0x0000 (the drive gives no code)".to_string(),
            Some(Ok(c)) => format!("0x603F error code 0x{c:04X} {}", error_text(c)),
            Some(Err(e)) => format!("0x603F unreadable ({e})"),
            None => "0x603F not read".to_string(),
        };
        let reg = match d.register {
            Some(Ok(r)) => format!("0x1001 error register 0x{r:02X} {}", error_register_text(r)),
            Some(Err(e)) => format!("0x1001 unreadable ({e})"),
            None => "0x1001 not read".to_string(),
        };
        Ok(Some(self.node_alarm(i, crate::alarm::DRIVE_FAULT, format!("{}; {code}; {reg}; clear the cause, then reset", d.seen))))
    }

    // ---- Profile position and homing: synchronous, clock-driven (like `startup`). ----

    /// Run the cycle (receive → `step` → transmit every `cycle_ms`) until `step` says done
    /// or `max_ns` of clock time pass. Ok(false) on the time limit.
    fn run_cycles(&mut self, clock: &mut dyn Clock, max_ns: u64, mut step: impl FnMut(&mut Self) -> Result<bool, Alarm>) -> Result<bool, Alarm> {
        let mut next = clock.now_ns();
        let end = next + max_ns;
        while next < end {
            next += self.cycle_ns;
            clock.wait_until(next);
            let now = clock.now_ns();
            self.receive(now)?;
            let done = step(self)?;
            self.transmit(now)?;
            if done {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// Enable every drive (holding position) if the cycle is not running yet.
    fn ensure_enabled(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        if !self.running {
            self.enable_cycles = 0;
            self.run_cycles(clock, 6_000_000_000, |m| m.enable_step())?;
        }
        Ok(())
    }

    fn counts(&self, i: usize, units: f64, what: &str, number: u32) -> Result<u32, Alarm> {
        let c = (units * self.nodes[i].spec.counts_per_unit).abs().round();
        if !c.is_finite() || c < 1.0 || c > u32::MAX as f64 {
            return Err(self.node_alarm(i, number, format!("{what} {units} is out of range (must give 1 to 2^32-1 counts)")));
        }
        Ok(c as u32)
    }

    /// Back to cyclic synchronous position, holding where the drive is.
    /// Back to CSP holding `hold` (counts) — the profile move's target, so that the position
    /// loop settles onto it rather than wherever inside the position window the drive said
    /// "reached" — or, without one (homing: a new reference), the actual position.
    fn back_to_csp(&mut self, clock: &mut dyn Clock, i: usize, hold: Option<i64>) -> Result<(), Alarm> {
        let n = &mut self.nodes[i];
        n.controlword = cw::ENABLE_OPERATION_CMD;
        n.target = hold.unwrap_or(n.unwrapped);
        let m = n.spec.position_mode();
        self.change_mode(clock, i, m)?;
        // One cycle so the target the drive latches is the held one.
        self.run_cycles(clock, self.cycle_ns, |_| Ok(true))?;
        if let Some(t) = hold {
            // Then let the position loop settle into the position window (0x6067, 10 counts
            // on the emulated drive; 0.2 s at most).
            self.run_cycles(clock, 200_000_000, |m| Ok((m.nodes[i].unwrapped - t).abs() <= 10))?;
        }
        Ok(())
    }

    /// Move `node` to `target` (machine units, absolute) in the drive's profile position
    /// mode (1): trapezoid of `velocity` (units/s) and `accel` (units/s², also the
    /// deceleration), computed by the drive. Enables the drives first if needed, returns
    /// when the drive reports the target reached (0x6041 bit 10), and leaves the drive in
    /// cyclic synchronous position holding there. The other drives hold their positions.
    pub fn profile_move(&mut self, clock: &mut dyn Clock, node: u8, target: f64, velocity: f64, accel: f64) -> Result<(), Alarm> {
        let i =
            self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::PROFILE_MOVE, format!("node {node} is not in the machine configuration")))?;
        let v = self.counts(i, velocity, "profile velocity", crate::alarm::PROFILE_MOVE)?;
        let a = self.counts(i, accel, "profile acceleration", crate::alarm::PROFILE_MOVE)?;
        let t = (target * self.nodes[i].spec.counts_per_unit).round();
        if !t.is_finite() || t.abs() > i32::MAX as f64 {
            return Err(self.node_alarm(i, crate::alarm::PROFILE_MOVE, format!("target {target} is out of the drive's INTEGER32 range")));
        }
        self.write(clock, i, 0x6081, 0, &v.to_le_bytes())?;
        self.write(clock, i, 0x6083, 0, &a.to_le_bytes())?;
        self.write(clock, i, 0x6084, 0, &a.to_le_bytes())?;
        self.ensure_enabled(clock)?;
        self.change_mode(clock, i, mode::PROFILE_POSITION)?;
        if self.nodes[i].spec.target_object() != (od::TARGET_POSITION, 0) {
            // RPDO1 carries 0x60C1:1 (IP), not the profile target 0x607A: written by SDO
            // before the set-point handshake takes it.
            self.write(clock, i, od::TARGET_POSITION, 0, &(t as i32).to_le_bytes())?;
        }
        let dist = (t - self.nodes[i].unwrapped as f64).abs();
        let est_s = dist / v as f64 + 2.0 * v as f64 / a as f64;
        let max_ns = ((2.0 * est_s + 2.0) * 1e9) as u64;
        self.nodes[i].target = t as i64;
        // Set-point handshake: bit 4 up until the drive acknowledges (bit 12), then down;
        // the move is over when bit 12 is down again and bit 10 (target reached) is up.
        self.nodes[i].controlword = cw::ENABLE_OPERATION_CMD | cw::OMS4 | cw::OMS5;
        // A controlword sent in cycle k acts after SYNC k; the statusword sampled at SYNC k+1
        // is read in cycle k+2: statuswords before that are stale (and in CSP bit 12 is set).
        let mut k = 0;
        let acked = self.run_cycles(clock, 500_000_000, |m| {
            k += 1;
            Ok(k >= FRESH_STATUS_CYCLES && m.nodes[i].status & sw::OMS12 != 0)
        })?;
        if !acked {
            return Err(self.node_alarm(
                i,
                crate::alarm::PROFILE_MOVE,
                "profile position set-point not acknowledged (0x6041 bit 12) within 500 ms; does the drive support mode 1?",
            ));
        }
        self.nodes[i].controlword = cw::ENABLE_OPERATION_CMD;
        let mut k = 0;
        let reached = self.run_cycles(clock, max_ns, |m| {
            k += 1;
            let s = m.nodes[i].status;
            Ok(k >= FRESH_STATUS_CYCLES && s & sw::OMS12 == 0 && s & sw::TARGET_REACHED != 0)
        })?;
        if !reached {
            return Err(self.node_alarm(
                i,
                crate::alarm::PROFILE_MOVE,
                format!(
                    "profile move to {target} not finished within {:.1} s (position {:.4}); check the axis for a jam",
                    max_ns as f64 * 1e-9,
                    self.nodes[i].unwrapped as f64 / self.nodes[i].spec.counts_per_unit
                ),
            ));
        }
        // Only a target the drive is already near: never a jump.
        let window = (self.nodes[i].spec.following_error * self.nodes[i].spec.counts_per_unit).abs();
        let near = (t - self.nodes[i].unwrapped as f64).abs() <= window.max(1.0);
        self.back_to_csp(clock, i, near.then_some(t as i64))
    }

    /// Home `node` in the drive's homing mode (6) with `method` (0x6098; e.g. 35/37 = the
    /// present position, 17/18 = the negative/positive limit switch), `switch_speed` and
    /// `zero_speed` (0x6099:1/2, units/s) and `accel` (0x609A, units/s²). Enables the
    /// drives first if needed, waits up to `timeout_ms` for "homing attained" (0x6041 bits
    /// 12 and 10), and leaves the drive in cyclic synchronous position holding there.
    #[allow(clippy::too_many_arguments)]
    pub fn home(
        &mut self,
        clock: &mut dyn Clock,
        node: u8,
        method: i8,
        switch_speed: f64,
        zero_speed: f64,
        accel: f64,
        timeout_ms: u64,
    ) -> Result<(), Alarm> {
        let i = self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::HOMING, format!("node {node} is not in the machine configuration")))?;
        let fast = self.counts(i, switch_speed, "homing switch-search speed", crate::alarm::HOMING)?;
        let slow = self.counts(i, zero_speed, "homing zero-search speed", crate::alarm::HOMING)?;
        let a = self.counts(i, accel, "homing acceleration", crate::alarm::HOMING)?;
        self.write(clock, i, od::HOMING_METHOD, 0, &[method as u8]).map_err(|e| {
            Alarm::new(
                crate::alarm::HOMING,
                format!("{}; homing method {method} is probably not supported by this drive (see 0x6098 in its manual)", e.message),
            )
        })?;
        self.write(clock, i, od::HOMING_SPEEDS, 1, &fast.to_le_bytes())?;
        self.write(clock, i, od::HOMING_SPEEDS, 2, &slow.to_le_bytes())?;
        self.write(clock, i, od::HOMING_ACCEL, 0, &a.to_le_bytes())?;
        self.ensure_enabled(clock)?;
        self.change_mode(clock, i, mode::HOMING)?;
        self.nodes[i].controlword = HomingProgress::START;
        // Bits 13/12/10 of a fresh statusword (see profile_move).
        let mut k = 0;
        let mut error = false;
        let done = self.run_cycles(clock, timeout_ms * 1_000_000, |m| {
            k += 1;
            if k < FRESH_STATUS_CYCLES {
                return Ok(false);
            }
            let p = HomingProgress::of(m.nodes[i].status);
            error = p == HomingProgress::Error;
            Ok(p != HomingProgress::Homing)
        })?;
        self.nodes[i].controlword = cw::ENABLE_OPERATION_CMD;
        if error {
            let _ = self.back_to_csp(clock, i, None);
            return Err(self.node_alarm(
                i,
                crate::alarm::HOMING,
                format!("homing method {method} failed (0x6041 bit 13 homing error); check the switch and its wiring"),
            ));
        }
        if !done {
            let _ = self.back_to_csp(clock, i, None);
            return Err(self.node_alarm(i, crate::alarm::HOMING, format!("homing method {method} not finished within {timeout_ms} ms")));
        }
        self.back_to_csp(clock, i, None)
    }

    // ---- Cyclic synchronous velocity (a spindle in speed mode) ----

    /// Put `node` in cyclic synchronous velocity (9): RPDO1 remapped to controlword +
    /// target velocity 0x60FF (the CiA 301 way), mode 9, target velocity 0. From then on
    /// `set_velocity` sets what each cycle sends; the position feedback goes on as before.
    pub fn velocity_mode(&mut self, clock: &mut dyn Clock, node: u8) -> Result<(), Alarm> {
        let i =
            self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::SDO_CONFIG, format!("node {node} is not in the machine configuration")))?;
        if self.nodes[i].csv {
            return Ok(());
        }
        self.nodes[i].target_vel = 0;
        let rpdo = [MapEntry::new(od::CONTROLWORD, 0, 16), MapEntry::new(od::TARGET_VELOCITY, 0, 32)];
        let (rc, rt) = (self.nodes[i].spec.rpdo_cob, self.nodes[i].spec.rpdo_tx);
        self.map_pdo(clock, i, od::RPDO_COMM, od::RPDO_MAP, rc, rt, &rpdo)?;
        self.nodes[i].csv = true;
        self.change_mode(clock, i, mode::CYCLIC_SYNC_VELOCITY)
    }

    /// Target velocity of a node in `velocity_mode`, machine units/s (degrees/s for a
    /// spindle), sent from the next `transmit` on. Ignored in position mode.
    pub fn set_velocity(&mut self, node: u8, units_per_s: f64) {
        if let Some(i) = self.index_of(node) {
            let n = &mut self.nodes[i];
            let c = (units_per_s * n.spec.counts_per_unit).round();
            if c.is_finite() {
                n.target_vel = c.clamp(i32::MIN as f64, i32::MAX as f64) as i32;
            }
        }
    }

    /// Back from `velocity_mode` to cyclic synchronous position: the target velocity goes to
    /// 0 and the master waits (up to `timeout_ms`) for the drive to report it reached
    /// (statusword bit 10), then mode 8, RPDO1 back to 0x607A, holding where the spindle stopped.
    pub fn position_mode(&mut self, clock: &mut dyn Clock, node: u8, timeout_ms: u64) -> Result<(), Alarm> {
        let i =
            self.index_of(node).ok_or_else(|| Alarm::new(crate::alarm::SDO_CONFIG, format!("node {node} is not in the machine configuration")))?;
        if !self.nodes[i].csv {
            return Ok(());
        }
        self.nodes[i].target_vel = 0;
        if self.running {
            // At rest (bit 10 at target velocity 0) for 50 ms: a spindle's velocity loop
            // overshoots through zero, and position control would have to catch that up.
            let (mut k, mut still) = (0, 0u64);
            let need = (50_000_000 / self.cycle_ns.max(1)).max(1);
            let stopped = self.run_cycles(clock, timeout_ms * 1_000_000, |m| {
                k += 1;
                let at_rest = k >= FRESH_STATUS_CYCLES && m.nodes[i].status & sw::TARGET_REACHED != 0;
                still = if at_rest { still + 1 } else { 0 };
                Ok(still >= need)
            })?;
            if !stopped {
                return Err(self.node_alarm(
                    i,
                    crate::alarm::DRIVE_FAULT,
                    format!("did not stop within {timeout_ms} ms for the change to position mode"),
                ));
            }
        }
        // RPDO1 back to 0x607A before the mode: a drive in CSP must never latch a stale
        // 0x607A (the one from before the speed mode) for lack of a fresh one.
        self.nodes[i].target = self.nodes[i].unwrapped;
        let (tix, tsub) = self.nodes[i].spec.target_object();
        let rpdo = [MapEntry::new(od::CONTROLWORD, 0, 16), MapEntry::new(tix, tsub, 32)];
        let (rc, rt) = (self.nodes[i].spec.rpdo_cob, self.nodes[i].spec.rpdo_tx);
        self.map_pdo(clock, i, od::RPDO_COMM, od::RPDO_MAP, rc, rt, &rpdo)?;
        self.nodes[i].csv = false;
        let m = self.nodes[i].spec.position_mode();
        self.change_mode(clock, i, m)?;
        self.nodes[i].target = self.nodes[i].unwrapped;
        Ok(())
    }

    // ---- EDS checks ----

    /// The objects start-up writes to `node` (index, sub, bytes) and maps (index, sub,
    /// bits, into an RPDO?). Kept next to `configure_node`, which must write the same.
    fn startup_objects(&self, i: usize) -> (Vec<ObjWrite>, Vec<ObjMap>) {
        let spec = &self.nodes[i].spec;
        let mut w = vec![
            (od::INTERPOLATION_PERIOD, 1, 1),
            (od::INTERPOLATION_PERIOD, 2, 1),
            (od::MODES_OF_OPERATION, 0, 1),
            (od::FOLLOWING_ERROR_WINDOW, 0, 4),
        ];
        for (comm, map) in [(od::RPDO_COMM, od::RPDO_MAP), (od::TPDO_COMM, od::TPDO_MAP)] {
            w.extend([(comm, 1, 4), (comm, 2, 1), (map, 0, 1), (map, 1, 4), (map, 2, 4)]);
        }
        let (tix, tsub) = spec.target_object();
        let maps = vec![(od::CONTROLWORD, 0, 16, true), (tix, tsub, 32, true), (od::STATUSWORD, 0, 16, false), (od::POSITION_ACTUAL, 0, 32, false)];
        (w, maps)
    }

    /// Objects start-up writes where the drive has them (a fallback where it does not):
    /// 0x1006, error control (heartbeat, or node guarding), 0x6007. Checked against an
    /// EDS only where the EDS lists them.
    fn optional_startup_objects(&self, i: usize) -> Vec<ObjWrite> {
        let mut w =
            vec![(od::COMM_CYCLE_PERIOD, 0, 4), (od::SHUTDOWN_OPTION, 0, 2), (od::DISABLE_OPERATION_OPTION, 0, 2), (od::FAULT_REACTION_OPTION, 0, 2)];
        if self.nodes[i].spec.ip {
            w.extend([(od::INTERPOLATION_SUB_MODE, 0, 2), (od::INTERPOLATION_BUFFER, 6, 1)]);
        }
        // Preferred, with a warning where absent (`prefer_write`).
        w.push((od::QUICK_STOP_OPTION, 0, 2));
        let spec = &self.nodes[i].spec;
        if spec.min.is_some() && spec.max.is_some() && !spec.spindle {
            w.extend([(od::SOFTWARE_LIMIT, 1, 4), (od::SOFTWARE_LIMIT, 2, 4)]);
        }
        if self.hb_ms > 0 {
            w.extend([
                (od::PRODUCER_HEARTBEAT, 0, 2),
                (od::CONSUMER_HEARTBEAT, 1, 4),
                (od::GUARD_TIME, 0, 2),
                (od::LIFE_TIME_FACTOR, 0, 1),
                (od::ABORT_CONNECTION, 0, 2),
                (od::ERROR_BEHAVIOUR, 1, 1),
            ]);
        }
        w
    }

    /// Check what start-up writes to and maps on `node` against its EDS: every object
    /// exists, is writable with that size, and is PDO-mappable where mapped. One line per
    /// disagreement, naming the file and line. Empty = all good.
    pub fn check_eds(&self, node: u8, eds: &cncgw_bus::canopen::eds::Eds) -> Vec<String> {
        let Some(i) = self.index_of(node) else {
            return vec![format!("node {node} is not in the machine configuration")];
        };
        let (writes, maps) = self.startup_objects(i);
        let mut out: Vec<String> = writes.iter().filter_map(|&(ix, sub, len)| eds.check_write(ix, sub, len).err()).collect();
        let optional = self.optional_startup_objects(i);
        out.extend(
            optional.iter().filter(|&&(ix, sub, _)| eds.get(ix, sub).is_some()).filter_map(|&(ix, sub, len)| eds.check_write(ix, sub, len).err()),
        );
        out.extend(maps.iter().filter_map(|&(ix, sub, bits, rpdo)| eds.check_map(ix, sub, bits, rpdo).err()));
        out.extend(check_list_against_eds(&self.nodes[i].spec.axis, &self.nodes[i].spec.sdo, eds));
        for (ix, sub) in [(od::DEVICE_TYPE, 0u8), (od::IDENTITY, 1)] {
            if eds.get(ix, sub).is_none() {
                out.push(format!("{}: 0x{ix:04X}:{sub:02X}, read at start-up, is not in the EDS", eds.file));
            }
        }
        out
    }

    /// Check a live drive's object dictionary against an EDS over SDO (`cncgw od check`):
    /// every object the file lists must exist, readable ones must read with the size of
    /// their type, write-only ones must refuse a read, and read-only ones must refuse a
    /// write (of the value just read, so nothing changes if the drive accepts it). PDO
    /// mappability cannot be seen without mapping and is not checked here (`check_eds`
    /// checks it for the objects start-up maps). One line per disagreement.
    pub fn check_od(&mut self, clock: &mut dyn Clock, node: u8, eds: &cncgw_bus::canopen::eds::Eds) -> Vec<String> {
        use cncgw_bus::canopen::eds::EdsAccess;
        use cncgw_bus::canopen::sdo::abort;
        self.ensure_node(node);
        let mut out = Vec::new();
        let entries: Vec<_> = eds.entries.values().cloned().collect();
        for e in entries {
            let at = eds.describe(e.index, e.sub).unwrap_or_default();
            let r = self.sdo_upload(clock, node, e.index, e.sub);
            match (r, e.access) {
                (Err(SdoError::Abort { code: abort::WRITE_ONLY }), EdsAccess::Wo) => {}
                (Ok(_), EdsAccess::Wo) => out.push(format!("{at}: AccessType=wo but node {node} lets it be read")),
                (Err(SdoError::Abort { code }), _) if code == abort::NO_OBJECT || code == abort::NO_SUBINDEX => out.push(format!(
                    "{at}: node {node} does not have 0x{:04X}:{:02X} ({})",
                    e.index,
                    e.sub,
                    cncgw_bus::canopen::sdo::abort_text(code)
                )),
                (Err(err), _) => out.push(format!("{at}: reading it from node {node} failed: {err}")),
                (Ok(v), access) => {
                    if let Some(n) = e.size() {
                        if v.len() != n {
                            out.push(format!(
                                "{at}: DataType {} is {n} bytes but node {node} answers {} bytes",
                                cncgw_bus::canopen::eds::data_type_name(e.data_type),
                                v.len()
                            ));
                            continue;
                        }
                        if matches!(access, EdsAccess::Ro | EdsAccess::Const) {
                            match self.sdo_download(clock, node, e.index, e.sub, &v) {
                                Err(SdoError::Abort { code: abort::READ_ONLY }) => {}
                                Ok(()) => out.push(format!("{at}: AccessType={} but node {node} accepts writes", access.name())),
                                Err(err) => out.push(format!(
                                    "{at}: AccessType={}: a write should abort 0x06010002 (read only), node {node} says: {err}",
                                    access.name()
                                )),
                            }
                        }
                    }
                }
            }
        }
        out
    }

    fn target_raw(&self, i: usize) -> i32 {
        self.nodes[i].target as i32 // wrapping to INTEGER32, as the drive does
    }
}

/// 0x60C2 interpolation period as value × 10^index s, value ≤ 255.
/// EMCY codes that report a problem the drive rides through without faulting: 0x8210 / 0x8220
/// PDO length (the PDO was not processed; one late or lost set-point is bridged by the
/// drive's interpolation). Logged, not a fault: a drive that does fault on them shows it in
/// its statusword a cycle later.
fn emcy_is_warning(code: u16) -> bool {
    matches!(code, 0x8210 | 0x8220)
}

fn interpolation_period(cycle_ms: f64) -> (u8, i8) {
    let mut v = cycle_ms;
    let mut idx: i8 = -3;
    while (v - v.round()).abs() > 1e-9 && idx > -6 {
        v *= 10.0;
        idx -= 1;
    }
    (v.round().clamp(1.0, 255.0) as u8, idx)
}

impl<B: CanBus> DriveBus for CanOpenMaster<B> {
    fn startup(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        let load = self.check_bus_load(self.bitrate)?;
        tracing::info!(
            "bus {}: worst-case load {:.1} % ({} drives, {} ms cycle, {} bit/s)",
            self.bus.name(),
            load * 100.0,
            self.nodes.len(),
            self.cycle_ms,
            self.bitrate
        );
        // Nothing is sent before the bus was heard free of another master.
        self.found = self.check_bus_free(clock)?;
        // Reset communication so every node reports a boot-up and starts from its default
        // communication parameters; then wait for all of them. Pre-operational first: a
        // reset straight from operational is a lost connection to some drives (0x6007).
        self.send(&NmtCommand::EnterPreOperational.frame(0))?;
        self.nmt_command(0, NmtCommand::ResetCommunication)?;
        self.undo = Some(Vec::new());
        let r = self.wait_all_booted(clock).and_then(|_| {
            for i in self.by_node_id() {
                self.configure_node(clock, i)?;
            }
            self.start_io_modules(clock)?;
            self.start_and_confirm_modes(clock)
        });
        if let Err(a) = r {
            let found = std::mem::take(&mut self.found);
            self.restore(clock, &found);
            return Err(a);
        }
        Ok(())
    }

    fn abandon_startup(&mut self, clock: &mut dyn Clock) {
        if self.undo.is_some() {
            let found = std::mem::take(&mut self.found);
            self.restore(clock, &found);
        }
    }

    fn receive(&mut self, now_ns: u64) -> Result<(), Alarm> {
        self.cycles += 1;
        self.now_ns = now_ns;
        loop {
            match self.bus.try_recv() {
                Ok(Some(f)) => {
                    let (func, node) = cob::split(f.cob_id());
                    match self.index_of(node) {
                        Some(i) if func == cob::SDO_TX && self.nodes[i].sdo.busy() => {
                            for out in self.nodes[i].sdo.on_frame(&f, now_ns) {
                                self.send(&out)?;
                            }
                        }
                        _ => self.on_background(&f, now_ns),
                    }
                }
                Ok(None) => break,
                Err(e) => return Err(self.bus_alarm(e)),
            }
        }
        if let Some(a) = self.step_diag(now_ns)? {
            return Err(a);
        }
        self.check_sync_loss(now_ns)?;
        self.watch_controller()?;
        self.poll_modes(now_ns)?;
        self.poll_torque(now_ns)?;
        self.check_io(now_ns)?;
        for i in 0..self.nodes.len() {
            if self.running && self.faulted == Some(i) {
                // Isolated in its fault reaction: already reported.
                continue;
            }
            let n = &self.nodes[i];
            if self.running && self.diag.is_none() {
                let st = State::from_statusword(n.status);
                // A PDO-length EMCY is a warning (CiA 301: the PDO was not processed, the
                // drive goes on); a drive that faults on it says so in its statusword.
                let seen = if let Some(e) = n.last_emcy.filter(|e| !emcy_is_warning(e.code)) {
                    Some(format!("drive fault EMCY 0x{:04X} {} (error register 0x{:02X})", e.code, error_text(e.code), e.register))
                } else if n.have_fb && st != State::OperationEnabled && n.not_enabled >= 2 {
                    Some(format!("drive left Operation Enabled: now {}", st.name()))
                } else {
                    None
                };
                if let Some(seen) = seen {
                    self.start_diag(i, seen, now_ns)?;
                    if let Some(a) = self.step_diag(now_ns)? {
                        return Err(a);
                    }
                    continue;
                }
            }
            if let Some(a) = self.check_tpdo_and_mode(i) {
                return Err(a);
            }
            if self.running && self.nodes[i].ip_inactive >= ip_mode::IP_INACTIVE_ALARM {
                let st = self.nodes[i].status;
                return Err(self.node_fault(
                    i,
                    ALARM_MODE,
                    format!("statusword bit 12 (ip mode active) dropped while running (statusword 0x{st:04X}): the drive stopped taking set-points; its set-points were stopped. Check the drive's fault log and IP buffer settings"),
                ));
            }
            let n = &self.nodes[i];
            if self.running && matches!(n.nmt, Some(s) if s != NmtState::Operational) {
                return Err(self.node_fault(i, crate::alarm::NODE_LEFT_OPERATIONAL, "node left NMT operational (reset or stopped by someone else?)"));
            }
            if self.hb_ms > 0 && n.last_hb_ns > 0 && now_ns.saturating_sub(n.last_hb_ns) > 3 * self.hb_ms as u64 * 1_000_000 {
                return Err(self.node_fault(
                    i,
                    crate::alarm::HEARTBEAT_LOST,
                    format!(
                        "heartbeat lost (none for {} ms); check the cable and the drive's power",
                        now_ns.saturating_sub(n.last_hb_ns) / 1_000_000
                    ),
                ));
            }
            // Stale by time *and* by SYNCs left unanswered: after the cycle thread was late,
            // a cycle follows at once and a drive cannot have answered yet, and a stall of the
            // controller (no SYNC sent) is not the drive's silence.
            let age = now_ns.saturating_sub(n.fb_ns);
            let timeout_syncs = (self.feedback_timeout_ns / self.cycle_ns.max(1)).max(1) as u32;
            if self.running && age > self.feedback_timeout_ns && n.syncs_unanswered > timeout_syncs {
                return Err(self.node_fault(
                    i,
                    crate::alarm::STALE_FEEDBACK,
                    format!(
                        "no position feedback (TPDO1) for {:.1} ms: the drive answered none of the last {} SYNCs; check the drive's PDO configuration (TPDO1 mapping and transmission type) and the bus",
                        age as f64 * 1e-6,
                        n.syncs_unanswered
                    ),
                ));
            }
        }
        Ok(())
    }

    fn feedback(&self, axis: usize) -> AxisFeedback {
        let n = &self.nodes[axis];
        AxisFeedback {
            pos: n.unwrapped as f64 / n.spec.counts_per_unit,
            counts: n.unwrapped,
            statusword: n.status,
            age_cycles: (self.now_ns.saturating_sub(n.fb_ns) / self.cycle_ns.max(1)) as u32,
            demand_counts: None,
            sampled_ns: None,
        }
    }

    fn set_target(&mut self, axis: usize, pos: f64) {
        let n = &mut self.nodes[axis];
        let exact = pos * n.spec.counts_per_unit;
        let c = exact.round();
        if c.is_finite() {
            n.target = c as i64;
            n.target_exact = exact;
        }
    }

    fn target_counts(&self, axis: usize) -> i64 {
        self.nodes[axis].target
    }

    fn transmit(&mut self, now_ns: u64) -> Result<(), Alarm> {
        for i in 0..self.nodes.len() {
            let n = &self.nodes[i];
            // A drive that does not show the mode asked for (changing modes, or not yet
            // enabled) gets no set-point it could take: the position it is at, speed 0.
            let hold = !n.mode.ok() || (!n.enabled && n.have_fb);
            let t = match (n.csv, hold) {
                (true, true) => 0i32.to_le_bytes(),
                (true, false) => n.target_vel.to_le_bytes(),
                (false, true) => (n.unwrapped as i32).to_le_bytes(),
                (false, false) => self.target_raw(i).to_le_bytes(),
            };
            let c = self.cyclic_controlword(i);
            let n = &mut self.nodes[i];
            // The set-point as asked where it is the one sent (a target set in counts — a hold,
            // back to CSP after a profile move — has no finer value).
            let exact = if n.target_exact.round() as i64 == n.target { n.target_exact } else { n.target as f64 };
            let csp = n.mode.want == mode::CYCLIC_SYNC_POSITION;
            n.torque_offset = match n.friction.as_mut() {
                Some(f) if !hold && !n.csv && csp => f.offset(exact),
                Some(f) => {
                    f.reset_motion();
                    0
                }
                None => 0,
            };
            let n = &self.nodes[i];
            let mut d = [0u8; 8];
            for &(slot, off) in &n.rpdo_at.slots {
                match slot {
                    fixed_pdo::Slot::Controlword => put_u16(&mut d, off, c),
                    fixed_pdo::Slot::Target => d[off..off + 4].copy_from_slice(&t),
                    fixed_pdo::Slot::Mode => d[off] = n.mode.want as u8,
                    // 0 unless friction feed-forward runs (`torque_offset` is set only then).
                    fixed_pdo::Slot::TorqueOffset => put_u16(&mut d, off, n.torque_offset as u16),
                    fixed_pdo::Slot::Zero => {}
                }
            }
            let f = CanFrame::new(n.spec.rpdo_cob, &d[..n.rpdo_at.len]);
            self.send(&f)?;
            let n = &mut self.nodes[i];
            n.ip_sent = if c & cw::OMS4 != 0 && n.spec.ip { n.ip_sent.saturating_add(1) } else { 0 };
        }
        self.transmit_io()?;
        // An external SYNC (bus.sync): the set-points act on the producer's next SYNC.
        if !self.ext_sync.on {
            self.send(&sync_frame(None))?;
            for n in &mut self.nodes {
                n.syncs_unanswered = n.syncs_unanswered.saturating_add(1);
            }
        }
        self.tick_life(now_ns)
    }

    fn enable_step(&mut self) -> Result<bool, Alarm> {
        self.enable_cycles += 1;
        let limit = (5_000_000_000 / self.cycle_ns.max(1)).max(100);
        let mut all = true;
        for i in 0..self.nodes.len() {
            let n = &mut self.nodes[i];
            if !n.have_fb || !n.mode.ok() {
                // Never enabled before it shows the mode asked for (start-up waited for it;
                // this holds it if the mode went away since).
                all = false;
                continue;
            }
            // Hold the actual position while enabling so that nothing jumps.
            if !n.enabled {
                n.target = n.unwrapped;
            }
            let mut en = Enabler { controlword: n.controlword, reset_attempts: n.reset_attempts };
            let progress = en.step(n.status);
            let was_reset = en.reset_attempts > n.reset_attempts;
            n.controlword = en.controlword;
            n.reset_attempts = en.reset_attempts;
            match progress {
                EnableProgress::Enabled => {
                    n.enabled = true;
                    // IP: enabled once the drive says "ip mode active" (bit 4 goes out
                    // from the next RPDO1 on).
                    if !self.ip_active(i) {
                        all = false;
                    }
                }
                EnableProgress::ResetFailed => {
                    let code = n.last_emcy.map(|e| e.code).unwrap_or(0);
                    return Err(self.node_alarm(
                        i,
                        crate::alarm::FAULT_RESET,
                        format!("fault reset did not clear the fault (last EMCY 0x{code:04X} {}); fix the cause on the drive", error_text(code)),
                    ));
                }
                EnableProgress::Walking => {
                    all = false;
                    n.enabled = false;
                    if was_reset {
                        tracing::warn!(node = n.spec.node, "drive in Fault: fault reset");
                        n.last_emcy = None;
                    }
                }
            }
        }
        if all {
            self.running = true;
            self.diag = None;
            self.faulted = None;
            // Start-up is over: nothing to leave as found any more.
            self.undo = None;
            for n in &mut self.nodes {
                n.last_emcy = None;
            }
        } else if self.enable_cycles > limit {
            let i = self.by_node_id().into_iter().find(|&i| !self.nodes[i].enabled).unwrap_or(0);
            let n = &self.nodes[i];
            let st = State::from_statusword(n.status);
            let why = if !n.mode.ok() {
                format!(
                    "; it does not show the mode asked for ({} asked, 0x6061 = {})",
                    explain::mode_words(n.mode.want),
                    n.mode.shown.map_or("unknown".into(), explain::mode_words)
                )
            } else if !n.have_fb {
                "; no position feedback (TPDO1) was received".to_string()
            } else if n.enabled && !self.ip_active(i) {
                format!(
                    "; it is Operation Enabled in interpolated position but statusword bit 12 (ip mode active) never came with controlword bit 4 (enable ip mode) set (statusword 0x{:04X}); check the drive's IP settings (sub-mode 0x60C0, buffer 0x60C4) in its manual",
                    n.status
                )
            } else {
                String::new()
            };
            return Err(self.node_alarm(
                i,
                crate::alarm::ENABLE_TIMEOUT,
                format!("did not reach Operation Enabled within 5 s (state {}){why}", st.name()),
            ));
        }
        Ok(all)
    }

    fn quick_stop(&mut self) {
        self.running = false;
        for n in &mut self.nodes {
            n.controlword = cw::QUICK_STOP_CMD;
        }
    }

    fn shutdown(&mut self, clock: &mut dyn Clock) {
        self.running = false;
        for n in &mut self.nodes {
            n.controlword = cw::SHUTDOWN;
        }
        // Outputs off with torque (coolant, turret strobe); CiA 401 0x6206 decides what the
        // module does once the master is gone.
        for m in 0..self.io.len() {
            self.io[m].clear_outputs();
        }
        self.power_off_cycles(clock);
        // Stop the drives expecting our heartbeat before we go silent.
        for i in 0..self.nodes.len() {
            let _ = self.sdo(clock, i, Sdo::Down(od::CONSUMER_HEARTBEAT, 1, &0u32.to_le_bytes()));
        }
        self.stop_guarding(clock);
        let _ = self.send(&NmtCommand::EnterPreOperational.frame(0));
        self.settle(clock, 1);
    }

    fn axis_count(&self) -> usize {
        self.nodes.len()
    }

    fn position_lost(&self, axis: usize) -> Option<String> {
        self.nodes.get(axis).and_then(|n| n.position_lost.clone())
    }

    fn io_inputs(&self, node: u8) -> Option<u32> {
        self.io_inputs_of(node)
    }

    fn set_io_outputs(&mut self, node: u8, bits: u32) {
        self.set_io_outputs_of(node, bits)
    }

    fn isolate_faults(&mut self, on: bool) -> bool {
        self.isolate = on;
        true
    }

    fn faulted(&self) -> Option<usize> {
        self.faulted
    }

    fn axis_name(&self, axis: usize) -> &str {
        &self.nodes[axis].spec.axis
    }

    fn counts_per_unit(&self, axis: usize) -> f64 {
        self.nodes[axis].spec.counts_per_unit
    }

    fn following_window(&self, axis: usize) -> Option<f64> {
        Some(self.nodes[axis].spec.following_error).filter(|w| w.is_finite() && *w > 0.0)
    }

    fn torque_permille(&self, axis: usize) -> Option<i16> {
        self.nodes.get(axis).and_then(|n| n.torque.value)
    }

    fn max_torque_permille(&self, axis: usize) -> Option<u16> {
        self.nodes.get(axis).and_then(|n| n.torque.max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bus_load_is_checked_against_80_percent() {
        let bus = cncgw_bus::transport::inproc::InprocBus::new();
        let mut cfg = MachineConfig::embedded();
        for n in ["x", "z"] {
            cfg.axes.get_mut(n).unwrap().friction_compensation = true;
        }
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        // 3 × (6-byte RPDO + 7-byte TPDO) + SYNC = 775 bits every 2 ms; X and Z with friction
        // feed-forward: 8-byte RPDOs (+20 bits each) and a torque read (135 bits each); the
        // spindle's torque read (135 bits).
        assert!((m.bus_load(1_000_000) - 1220.0 / 2000.0).abs() < 1e-6, "{}", m.bus_load(1_000_000));
        cfg.machine.cycle_ms = 0.5;
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        let e = m.check_bus_load(1_000_000).unwrap_err();
        assert_eq!(e.number, crate::alarm::BUS_LOAD);
        assert!(e.message.contains("machine.cycle_ms = 1.75 or more") && e.message.contains("friction_compensation off on 2 axes"), "{}", e.message);
        for a in cfg.axes.values_mut() {
            a.friction_compensation = false;
        }
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        assert!(m.check_bus_load(1_000_000).unwrap_err().message.contains("machine.cycle_ms = 1.25 or more"));
    }

    /// A CiA 401 module's frames count: 16 inputs and 8 outputs add a 2-byte TPDO (75 bits)
    /// and a 1-byte RPDO (65 bits) per cycle to the drives' 1220 (910 without friction
    /// feed-forward).
    #[test]
    fn bus_load_counts_the_io_modules() {
        let bus = cncgw_bus::transport::inproc::InprocBus::new();
        let text = format!("{}\n[io.devices.io1]\ncanopen_node = 10\ninputs = 16\noutputs = 8\n", crate::config::EMBEDDED_LATHE);
        let mut cfg = MachineConfig::from_toml("io.toml", &text).unwrap();
        for n in ["x", "z"] {
            cfg.axes.get_mut(n).unwrap().friction_compensation = true;
        }
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        assert!((m.bus_load(1_000_000) - (1220.0 + 75.0 + 65.0) / 2000.0).abs() < 1e-6, "{}", m.bus_load(1_000_000));
        for a in cfg.axes.values_mut() {
            a.friction_compensation = false;
        }
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        let (mut want, mut got) = (cyclic_frames_io(3, &cfg.io.resolve().unwrap().canopen_modules()), m.frames());
        want.push(8);
        want.sort();
        got.sort();
        assert_eq!(want, got);
        cfg.machine.cycle_ms = 1.0;
        let m = CanOpenMaster::new(bus.endpoint(), &cfg);
        let e = m.check_bus_load(1_000_000).unwrap_err();
        assert!(e.message.contains("3 drives and 1 I/O modules") && e.message.contains("machine.cycle_ms = 1.5 or more"), "{}", e.message);
    }

    #[test]
    fn interpolation_period_encoding() {
        assert_eq!(interpolation_period(2.0), (2, -3));
        assert_eq!(interpolation_period(1.0), (1, -3));
        assert_eq!(interpolation_period(0.5), (5, -4));
        assert_eq!(interpolation_period(0.25), (25, -5));
    }
}
