//! Machine configuration (`config/*.toml`), validated on load.
//!
//! Every validation error names the key path and what is allowed, e.g.
//! `axes.z.max_speed: must be > 0, got -3`.

use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::Path;

/// The configuration compiled into the binary: the default lathe with emulated drives.
pub const EMBEDDED_LATHE: &str = include_str!("../config/lathe.toml");

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: cannot read: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{file}: {message}")]
    Parse { file: String, message: String },
    #[error("{file}: {}", errors.join("\n  "))]
    Invalid { file: String, errors: Vec<String> },
}

impl ConfigError {
    /// Alarm number for configuration errors.
    pub const ALARM: u32 = crate::alarm::CONFIG;
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineConfig {
    pub machine: Machine,
    pub bus: Bus,
    /// Axes by name: `x`, `z`, `y`, `c`/`s1`… Iteration order is by name.
    pub axes: BTreeMap<String, AxisConfig>,
    /// The manuals' parameter table, keyed by parameter number (`5200 = 0`).
    #[serde(default)]
    pub parameters: BTreeMap<String, toml::Value>,
    /// Modbus links by name (`[modbus.line1]`); an axis with `modbus = "line1"` is on it.
    #[serde(default)]
    pub modbus: BTreeMap<String, ModbusLink>,
    /// Real-time setup of the cycle thread (`[rt]`); `cncgw run --rt-priority/--mlock/--cpu`
    /// override it.
    #[serde(default)]
    pub rt: RtConfig,
    /// Discrete I/O: devices, M codes, turret, safety inputs (`[io]`, see `crate::io`).
    #[serde(default)]
    pub io: crate::io::IoConfig,
    /// The read-only OPC UA server of `cncgw run` (`[opcua]`); absent or `enabled = false`:
    /// no socket is opened.
    #[serde(default)]
    pub opcua: OpcUaConfig,
}

/// `[rt]`: real-time setup of the cycle thread on a real PC. All optional; absent = normal
/// scheduling, no memory locking, no pinning. A request the system refuses is a warning when
/// `cncgw run` starts (see `control::rt`), not an error: the controller runs, with more jitter.
#[derive(Clone, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct RtConfig {
    /// SCHED_FIFO priority of the cycle thread, 1–99.
    #[serde(default)]
    pub priority: Option<i32>,
    /// Lock all memory (mlockall) so that no page fault delays a cycle.
    #[serde(default)]
    pub mlock: bool,
    /// Pin the cycle thread to this CPU (e.g. one isolated with `isolcpus=`).
    #[serde(default)]
    pub cpu: Option<usize>,
    /// Longest single sleep of the cycle thread's wait, µs (absent = one sleep to the
    /// deadline). Short steps keep a virtual CPU from being descheduled by its host while idle
    /// (`cncgw_bus::WakeStrategy`); each step is a wake-up.
    #[serde(default)]
    pub max_sleep_us: Option<u64>,
    /// Busy-wait the last this many µs of each wait (absent = never spin). Only where the
    /// cycle thread has a core to itself: spinning on a shared core starves the others.
    #[serde(default)]
    pub spin_us: Option<u64>,
    /// Hold /dev/cpu_dma_latency at 0 while running (the PM QoS request that keeps a PC's
    /// CPUs out of deep C-states, whose exit latency delays wake-ups).
    #[serde(default)]
    pub cpu_dma_latency: bool,
    /// Timer slack of the cycle thread in ns (prctl PR_SET_TIMERSLACK; Linux's default is
    /// 50 µs for normal threads, none for SCHED_FIFO ones). Absent = leave it.
    #[serde(default)]
    pub timer_slack_ns: Option<u64>,
}

#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum LinkTransport {
    /// Modbus TCP: one connection per link, kept open and re-opened when it drops.
    Tcp,
    /// Modbus RTU on a serial line (RS-485).
    Rtu,
}

#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Parity {
    #[default]
    None,
    Even,
    Odd,
}

/// One Modbus link: a TCP connection or an RS-485 line, carrying one or more drives (each
/// axis's `node` is its unit id on the link).
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModbusLink {
    pub transport: LinkTransport,
    /// TCP: `host:port`.
    #[serde(default)]
    pub address: Option<String>,
    /// RTU: the serial device (`/dev/ttyUSB0`, `/dev/pts/3`).
    #[serde(default)]
    pub device: Option<String>,
    #[serde(default = "default_baud")]
    pub baud: u32,
    #[serde(default)]
    pub parity: Parity,
    #[serde(default = "default_stop_bits")]
    pub stop_bits: u8,
    /// How long a drive takes to answer after a request, ms (RTU cycle computation).
    #[serde(default = "default_turnaround")]
    pub turnaround_ms: f64,
    /// A transaction without an answer after this long is a timeout, ms.
    #[serde(default = "default_modbus_timeout")]
    pub timeout_ms: u32,
    /// Use function 23 (read/write multiple registers) for the cyclic exchange of a CiA 402
    /// drive: one transaction per drive per cycle instead of two. Not every drive has it.
    #[serde(default)]
    pub fc23: bool,
    /// A longer link cycle than the computed one, ms (never shorter: it is checked).
    #[serde(default)]
    pub cycle_ms: Option<f64>,
}

impl ModbusLink {
    /// "Modbus TCP 127.0.0.1:5020", "Modbus RTU /dev/ttyUSB0 115200 baud".
    pub fn describe(&self) -> String {
        match self.transport {
            LinkTransport::Tcp => format!("Modbus TCP {}", self.address.as_deref().unwrap_or("?")),
            LinkTransport::Rtu => format!("Modbus RTU {} {} baud", self.device.as_deref().unwrap_or("?"), self.baud),
        }
    }

    /// The longest transaction timeout that rides through one lost answer: the drive's next
    /// reading comes a timeout and up to two cycles (`cycle_ms`, the machine's: a link cycle
    /// is never shorter) after the last one, and must come within `feedback_timeout_ms`.
    /// None when even that cannot hold.
    pub fn most_timeout_ms(&self, feedback_timeout_ms: f64, cycle_ms: f64) -> Option<f64> {
        let c = self.cycle_ms.unwrap_or(0.0).max(cycle_ms);
        Some((feedback_timeout_ms - 2.0 * c).floor()).filter(|m| *m >= 1.0)
    }
}

fn default_baud() -> u32 {
    115_200
}
fn default_stop_bits() -> u8 {
    1
}
fn default_turnaround() -> f64 {
    1.0
}
fn default_modbus_timeout() -> u32 {
    100
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Machine {
    pub name: String,
    /// Bus cycle in milliseconds (0.25 … 100).
    pub cycle_ms: f64,
    /// Spindle–axis sync error (threading, rigid tapping, G92.1) at which motion alarms and
    /// stops spindle and axes together, µm along the thread (1 … 10000).
    #[serde(default = "default_sync_error_limit")]
    pub sync_error_limit_um: f64,
    /// Cycle watchdog (alarm 2402): this many cycles in a row that woke a whole period late
    /// stop the machine (CODESYS' task watchdog "sensitivity"); 0 = off. Default 5.
    #[serde(default = "default_watchdog_overruns")]
    pub watchdog_overruns: u32,
    /// Cycle watchdog: one wake-up this many periods late stops the machine at once (the
    /// drives bridge a late SYNC for about 10 periods, the loop catches up at most 50);
    /// 1 … 50, default 25.
    #[serde(default = "default_watchdog_missed")]
    pub watchdog_missed_cycles: u32,
    /// The spindle that turns the tool of the SINUMERIK drilling cycles that orient or tap
    /// (CYCLE84 POSS and its tap, CYCLE86's oriented stop), as SINUMERIK's master spindle
    /// (SETMS) says which: `work` (default; the tool stands still, the work spindle turns and
    /// is oriented as C) or `tool` (a driven tool; needs an axis with role = "tool_spindle").
    #[serde(default)]
    pub drilling_spindle: DrillingSpindle,
    /// Refuse motion (`run`, `mdi`) while an axis that has a `homing` method is not
    /// referenced (alarm 224, "home it with `cncgw home X`"). Default true.
    ///
    /// As a Fanuc 0i-TF: No.1005#0 ZRNx = 0 (its default) raises PS0224 "zero return not
    /// finished" for a move command on an axis not yet referenced since power-on; ZRNx = 1
    /// lets it move. An axis with an absolute encoder (No.1815#5 APCx) is referenced at power-on.
    /// Here the check applies to the axes that declare `homing = { … }`: an axis with neither
    /// `homing` nor `absolute` has no reference to manage (the embedded default machine and
    /// the earlier configurations, whose positions are taken as valid from power-on).
    #[serde(default = "default_true")]
    pub require_reference: bool,
    /// Take-up before a thread pass, mm along the thread (0 … 5; 0 = none; default 0.3).
    /// Where the long axis last moved against the thread's direction — a G92/G76/G78 pass
    /// returns to its start so — the axes first creep this far along the thread (at most a
    /// quarter of it) at 2 mm/s and stop; the lead-in then starts from there, on the same
    /// synchronous line (the phase is unchanged; the incomplete lead-in grows by as much).
    /// A slide behind a belt stands in its dry friction while the motor winds the belt back
    /// the other way, and breaks away where the lead-in is already fast: the belt rings at
    /// the thread's start, and a lightly damped one still rings where the thread is measured
    /// (0.26–0.36° of phase spread between S500 and S1500; with the take-up 0.05–0.10°).
    /// It costs some 0.24 s a pass. Fanuc's threading cycles have no such step: the nearest is
    /// the machine tool builder's practice of approaching a thread's start in the cutting
    /// direction (single-direction positioning, G60, for backlash).
    #[serde(default = "default_thread_take_up")]
    pub thread_take_up_mm: f64,
}

fn default_thread_take_up() -> f64 {
    0.3
}

fn default_true() -> bool {
    true
}

/// Which spindle turns the tool of a drilling cycle (see [`Machine::drilling_spindle`]).
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum DrillingSpindle {
    #[default]
    Work,
    Tool,
}

fn default_watchdog_overruns() -> u32 {
    5
}
fn default_watchdog_missed() -> u32 {
    25
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bus {
    /// `inproc` (embedded emulated drives), `vcan0`, `can0`, … Overridden by `--bus`.
    pub interface: String,
    /// CAN bitrate in bit/s, for the bus-load check.
    #[serde(default = "default_bitrate")]
    pub bitrate: u32,
    /// How long to wait for each node's boot-up / first SDO answer, ms.
    #[serde(default = "default_sdo_timeout")]
    pub sdo_timeout_ms: u32,
    /// Master heartbeat producer period (ms) that the drives consume via 0x1016 (or guard
    /// by node guarding): a drive that stops hearing it faults and stops by itself when the
    /// controller dies. 0 = off, refused unless `unsafe_no_heartbeat = true`.
    #[serde(default = "default_heartbeat")]
    pub heartbeat_ms: u16,
    /// Allow `heartbeat_ms = 0`: the drives then go on with their last set-point if the
    /// controller dies (only for a bench without mechanics).
    #[serde(default)]
    pub unsafe_no_heartbeat: bool,
    /// A drive whose position feedback (TPDO) is older than this while running raises
    /// alarm 2015 and stops the machine, ms.
    #[serde(default = "default_feedback_timeout")]
    pub feedback_timeout_ms: f64,
    /// Who produces SYNC: this master (the default), or a device elsewhere on the bus (a
    /// drive with 0x1005 bit 30, a separate SYNC producer). `external`: the cycle runs on the
    /// SYNC received and the master sends none.
    #[serde(default)]
    pub sync: SyncSource,
    /// `sync = "external"`: no SYNC for more than this many cycles is alarm 2022 (the axes are
    /// stopped under control).
    #[serde(default = "default_sync_loss_cycles")]
    pub sync_loss_cycles: u32,
}

/// `bus.sync`: where the SYNC the cycle runs on comes from.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum SyncSource {
    /// This master produces SYNC every cycle.
    #[default]
    Master,
    /// Another device produces SYNC; the master consumes it and runs its cycle on it.
    External,
}

fn default_sync_loss_cycles() -> u32 {
    5
}

fn default_feedback_timeout() -> f64 {
    20.0
}

fn default_sync_error_limit() -> f64 {
    // A tenth of a millimetre: well beyond what locked drives show, well within what spoils
    // a thread flank.
    100.0
}

fn default_bitrate() -> u32 {
    1_000_000
}
fn default_sdo_timeout() -> u32 {
    500
}
fn default_heartbeat() -> u16 {
    100
}

#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum AxisKind {
    /// A feed axis in mm (X is held as a radius).
    Linear,
    /// A spindle, usable as a Cs position axis, in degrees.
    Spindle,
}

/// The drive's position polarity the machine was commissioned with (CiA 402 0x607E bit 7;
/// for a spindle bit 6, speed, too). Start-up refuses a drive whose 0x607E says otherwise:
/// the axis would move against the programmed direction. Like a Fanuc's No.2022 (motor
/// direction 111 / −111) it is a fact of the machine, set once at commissioning.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Polarity {
    #[default]
    Normal,
    Inverted,
}

/// What a drive is for, where its kind alone does not say.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum AxisRole {
    /// The tool spindle of polygon turning (G51.2), synchronised to the work spindle. Not
    /// the work spindle: M03/M04, threads, taps and C use the other spindle.
    ToolSpindle,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisConfig {
    pub kind: AxisKind,
    /// A special role (`role = "tool_spindle"`); absent for the usual axes and the work spindle.
    #[serde(default)]
    pub role: Option<AxisRole>,
    /// CANopen node id (1…127), or the Modbus unit id (1…247) when `modbus` names a link.
    pub node: u8,
    /// The `[modbus.NAME]` link this drive is on; absent: the CANopen bus.
    #[serde(default)]
    pub modbus: Option<String>,
    /// Register map of a Modbus drive: `cia402` (CiA 402 objects in holding registers) or
    /// `pr` (position-register block).
    #[serde(default)]
    pub modbus_profile: cncgw_bus::modbus::Profile,
    /// Register addresses of a `cia402` Modbus drive, where they differ from the defaults.
    #[serde(default)]
    pub cia402_map: Option<cncgw_bus::modbus::Cia402Map>,
    /// Register addresses of a `pr` Modbus drive, where they differ from the defaults.
    #[serde(default)]
    pub pr_map: Option<cncgw_bus::modbus::PrMap>,
    /// Position counts per mm (linear) or per degree (spindle).
    pub counts_per_unit: f64,
    /// Software travel limits in machine coordinates (mm; X as radius). Not used for spindles.
    #[serde(default)]
    pub min: Option<f64>,
    #[serde(default)]
    pub max: Option<f64>,
    /// Maximum speed: mm/min for linear axes, rpm for spindles.
    pub max_speed: f64,
    /// Maximum acceleration: mm/s² for linear axes, rpm/s for spindles.
    pub max_accel: f64,
    /// Jerk limit of the path-speed profile (S-curve), mm/s³; linear axes only (the spindle
    /// ramp and the spindle-synchronised moves keep their own laws). Absent or 0: no jerk
    /// limit, the trapezoid of before.
    ///
    /// Default: off, as on a Fanuc 0i-TF, whose bell-shaped acceleration is off until set
    /// (No.1772 = 0). Its bell-shaped acc/dec *before* interpolation ramps the acceleration
    /// over the time No.1772 (ms), i.e. jerk = max_accel / T; that is what this limits, and
    /// when `jerk` is absent `[parameters] 1772 = T` sets it for every axis that way. (Its
    /// filter *after* interpolation, No.1769, is not mapped: a filter on the setpoints
    /// delays them and rounds corners off the programmed path.) A sensible start on a lathe
    /// slide: T = 32 ms, e.g. 2000 mm/s² / 0.032 s = 62 500 mm/s³; smaller is gentler.
    #[serde(default)]
    pub jerk: Option<f64>,
    /// Axis travel per motor revolution: mm (linear) or degrees (spindle: 360 / gear ratio).
    /// With it start-up checks `counts_per_unit` exactly against the drive's factor group
    /// (0x608F, 0x6091, 0x6092): the drive's position units per motor revolution must be
    /// `counts_per_unit × travel_per_rev`. Without it the drive's positions must be encoder
    /// increments (factor group 1:1), the meaning of `counts_per_unit` by default. As
    /// SINUMERIK's leadscrew pitch and gear (MD31030, MD31050/31060) against the drive's
    /// encoder resolution.
    #[serde(default)]
    pub travel_per_rev: Option<f64>,
    /// The drive's position polarity (0x607E), checked at start-up: "normal" (default) or
    /// "inverted".
    #[serde(default)]
    pub polarity: Polarity,
    /// Following-error window written to 0x6065 (mm or degrees).
    #[serde(default = "default_ferr")]
    pub following_error: f64,
    /// In-position width (mm): an axis that stands within it of the program's end point has
    /// reached it (`cncgw run` exits 0; the summary still shows the counts it stands off).
    /// Default 0.01 mm, SINUMERIK 828D's exact-stop fine window (MD36010 STOP_LIMIT_FINE);
    /// Fanuc's No.1826 is the same check. A drive with high dry friction closes its last
    /// counts slowly through its integral action: 2–3 counts (0.2–0.3 µm) after 2 s on four-fold
    /// friction, which a check to the count called not at the end point.
    #[serde(default = "default_in_position")]
    pub in_position: f64,
    /// Optional EDS file describing the drive.
    #[serde(default)]
    pub eds: Option<String>,
    /// CANopen RPDO1 COB-ID (controlword + target); default 0x200 + node.
    #[serde(default)]
    pub rpdo_cob_id: Option<u16>,
    /// CANopen TPDO1 COB-ID (statusword + position actual); default 0x180 + node.
    #[serde(default)]
    pub tpdo_cob_id: Option<u16>,
    /// RPDO1 transmission type (0x1400:2): 0–240 synchronous (acts at the next SYNC), 254/255
    /// event-driven (acts on arrival). Default 1.
    #[serde(default = "default_tx_type")]
    pub rpdo_transmission: u8,
    /// TPDO1 transmission type (0x1800:2): n = 1–240 sends after every n-th SYNC. Default 1.
    #[serde(default = "default_tx_type")]
    pub tpdo_transmission: u8,
    /// SYNCs this drive goes on along its last set-point increment when a SYNC comes late
    /// (interpolating CiA 402 drives extrapolate; many hold their last target instead). Absent
    /// or 0: it holds — the safe assumption; check the drive's manual before setting more.
    /// After a late cycle the controller catches the path up by at most the smallest of these
    /// over the drives and holds the path's time base back by the rest, so that no set-point
    /// steps by more than one cycle's travel (0 … 50).
    #[serde(default)]
    pub late_sync_extrapolation: u32,
    /// Friction feed-forward (CANopen CSP feed axes): the master sends the friction the axis
    /// needs in the drive's torque offset 0x60B2 with each set-point, learnt from its torque
    /// actual 0x6077 while it moves (`drives::friction`), so that the slide does not stick
    /// where it starts or reverses. A drive that cannot map 0x60B2 into RPDO1 runs without
    /// (said at start-up). Default off.
    #[serde(default)]
    pub friction_compensation: bool,
    /// The drive's response as `cncgw identify` measured it (commissioning); `config check`
    /// warns when the following-error window is below what it lags at maximum speed.
    #[serde(default)]
    pub response: Option<DriveResponse>,
    /// The amplifier's overload rating as its manual states it: `overload_pct` % of its rated
    /// torque for `overload_s` seconds (default 300 % for 3 s, a common servo and spindle
    /// amplifier's I²t). A spindle's acceleration is capped before its amplifier would trip
    /// (`sync::overload`, from the drive's torque actual 0x6077).
    #[serde(default = "default_overload_pct")]
    pub overload_pct: f64,
    #[serde(default = "default_overload_s")]
    pub overload_s: f64,
    /// The cyclic position mode of a CANopen drive: `"csp"` (8, default) or `"ip"`
    /// (interpolated position, 7, linear sub-mode) for drives without CSP.
    #[serde(default)]
    pub mode: CyclicMode,
    /// Start-up list (`[[axes.NAME.sdo]]`): vendor parameters written in pre-operational after
    /// the standard configuration and read back, in this order (CiA 306-3's concise DCF).
    #[serde(default)]
    pub sdo: Vec<StartupSdo>,
    /// How the axis finds its reference point (`cncgw home X`): CiA 402 homing mode 6.
    #[serde(default)]
    pub homing: Option<Homing>,
    /// An absolute encoder: the axis is referenced at power-on and is never homed.
    #[serde(default)]
    pub absolute: bool,
    /// How sim-drives emulates the drive's surroundings, e.g. `[axes.z.emulate] switches =
    /// { negative = -20000 }` (cncgw itself ignores it; see sim-drives' README).
    #[serde(default)]
    pub emulate: Option<toml::Value>,
}

/// `axes.NAME.homing = { method = 35, offset = 0.0, speed = 600, zero_speed = 60 }`: the
/// CiA 402 homing of the axis (0x6098 method, 0x607C home offset, 0x6099 speeds, 0x609A
/// acceleration).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Homing {
    /// 0x6098: 35/37 the present position, 17/18 the negative/positive limit switch,
    /// 1–14 switches with the index pulse, 33/34 the index pulse alone (the drive's manual
    /// says which it has).
    pub method: i8,
    /// 0x607C: the machine position the home point gets (mm, X as a radius; degrees).
    #[serde(default)]
    pub offset: f64,
    /// 0x6099:1, searching the switch: mm/min (rpm for a spindle). Default max_speed / 20.
    #[serde(default)]
    pub speed: Option<f64>,
    /// 0x6099:2, searching zero (leaving the switch, to the index): default max_speed / 100.
    #[serde(default)]
    pub zero_speed: Option<f64>,
    /// 0x609A: mm/s² (rpm/s); default the axis's max_accel.
    #[serde(default)]
    pub accel: Option<f64>,
    /// Give up after this many seconds (default 30).
    #[serde(default)]
    pub timeout_s: Option<f64>,
}

/// The homing methods CiA 402 defines (0x6098): 1–35 and 37 (36 is reserved; 0 = none).
pub fn homing_method_defined(m: i8) -> bool {
    matches!(m, 1..=35 | 37)
}

/// `axes.NAME.mode`: how a CANopen drive takes its cyclic position set-points.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum CyclicMode {
    /// Cyclic synchronous position (CiA 402 mode 8): targets in 0x607A.
    #[default]
    Csp,
    /// Interpolated position (mode 7): targets in 0x60C1:1, enabled by controlword bit 4.
    Ip,
}

/// The CiA 301 type of a start-up list entry.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum SdoType {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
}

impl SdoType {
    pub fn size(self) -> usize {
        match self {
            SdoType::U8 | SdoType::I8 => 1,
            SdoType::U16 | SdoType::I16 => 2,
            SdoType::U32 | SdoType::I32 => 4,
        }
    }

    pub fn signed(self) -> bool {
        matches!(self, SdoType::I8 | SdoType::I16 | SdoType::I32)
    }

    /// The values the type holds.
    pub fn range(self) -> (i64, i64) {
        let bits = self.size() as u32 * 8;
        if self.signed() {
            (-(1i64 << (bits - 1)), (1i64 << (bits - 1)) - 1)
        } else {
            (0, (1i64 << bits) - 1)
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            SdoType::U8 => "u8",
            SdoType::I8 => "i8",
            SdoType::U16 => "u16",
            SdoType::I16 => "i16",
            SdoType::U32 => "u32",
            SdoType::I32 => "i32",
        }
    }

    /// A value read back (little-endian, `size` bytes) as a number of this type.
    pub fn decode(self, b: &[u8]) -> i64 {
        let mut a = [0u8; 8];
        let n = b.len().min(self.size());
        a[..n].copy_from_slice(&b[..n]);
        let u = u64::from_le_bytes(a) as i64;
        if self.signed() {
            let shift = 64 - self.size() as u32 * 8;
            (u << shift) >> shift
        } else {
            u
        }
    }
}

/// One `[[axes.NAME.sdo]]` entry: `index = 0x2003, sub = 0, value = 1200, type = "u16"`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StartupSdo {
    pub index: u16,
    #[serde(default)]
    pub sub: u8,
    pub value: i64,
    #[serde(rename = "type")]
    pub ty: SdoType,
}

impl StartupSdo {
    /// The bytes written (little-endian, the type's size).
    pub fn bytes(&self) -> Vec<u8> {
        self.value.to_le_bytes()[..self.ty.size()].to_vec()
    }

    /// "0x2003:00 = 1200 (u16)".
    pub fn describe(&self) -> String {
        format!("0x{:04X}:{:02X} = {} ({})", self.index, self.sub, self.value, self.ty.name())
    }

    /// Objects start-up configures itself (PDOs, error control, mode, controlword): a
    /// start-up list entry would be overwritten or would break the cycle.
    pub fn owned_by_startup(&self) -> bool {
        matches!(self.index, 0x1005 | 0x1006 | 0x100C | 0x100D | 0x1016 | 0x1017 | 0x1400..=0x1BFF | 0x6040 | 0x6060 | 0x607A | 0x60C1 | 0x60C2)
    }
}

/// `[axes.NAME.response]`: what `cncgw identify NAME` prints.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DriveResponse {
    /// Cycles (with a fraction) from a set-point to the first change of the actual position
    /// read back.
    pub delay_cycles: f64,
    /// Share of a speed change that follows at once.
    pub feed_forward: f64,
    /// Time constant of the rest, ms.
    pub time_constant_ms: f64,
    /// The drive's own lag per unit of acceleration, ms² (a·τ² of a second-order drive with
    /// full feed-forward, which lags nothing at constant speed). Absent: 0.
    #[serde(default)]
    pub accel_lag_ms2: f64,
}

fn default_tx_type() -> u8 {
    1
}

/// COB-IDs that CiA 301 reserves (NMT, SYNC/EMCY/TIME, SDO, NMT error control, LSS): no PDO
/// may use them.
pub fn restricted_cob_id(id: u16) -> bool {
    matches!(id, 0x000..=0x07F | 0x101..=0x180 | 0x581..=0x5FF | 0x601..=0x67F | 0x6E0..=0x6FF | 0x701..=0x7FF) || id > 0x7FF
}

impl AxisConfig {
    /// The jerk limit in mm/s³ (0 = none): `jerk`, else `max_accel` over No.1772 (`p1772`,
    /// ms) when that is set, else 0.
    pub fn jerk_limit(&self, p1772: Option<f64>) -> f64 {
        match (self.jerk, p1772) {
            (Some(j), _) if j.is_finite() && j > 0.0 => j,
            (Some(_), _) => 0.0,
            (None, Some(t)) if t.is_finite() && t > 0.0 => self.max_accel / (t / 1000.0),
            _ => 0.0,
        }
    }

    /// `max_speed` in the axis' position units per second: mm/s from mm/min, degrees/s from
    /// rpm.
    pub fn max_speed_units_s(&self) -> f64 {
        match self.kind {
            AxisKind::Spindle => self.max_speed * 6.0,
            AxisKind::Linear => self.max_speed / 60.0,
        }
    }

    /// `max_accel` in the axis' position units per second²: mm/s², degrees/s² from rpm/s.
    pub fn max_accel_units_s2(&self) -> f64 {
        match self.kind {
            AxisKind::Spindle => self.max_accel * 6.0,
            AxisKind::Linear => self.max_accel,
        }
    }

    /// (RPDO1, TPDO1) COB-IDs of a CANopen drive.
    pub fn pdo_cob_ids(&self) -> (u16, u16) {
        (self.rpdo_cob_id.unwrap_or(0x200 + self.node as u16), self.tpdo_cob_id.unwrap_or(0x180 + self.node as u16))
    }
}

fn default_ferr() -> f64 {
    1.0
}

fn default_in_position() -> f64 {
    0.01
}

fn default_overload_pct() -> f64 {
    300.0
}

fn default_overload_s() -> f64 {
    3.0
}

impl MachineConfig {
    /// Load and validate a TOML file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io { path: path.display().to_string(), source })?;
        Self::from_toml(&path.display().to_string(), &text)
    }

    /// The embedded default machine.
    pub fn embedded() -> Self {
        Self::from_toml("<embedded config/lathe.toml>", EMBEDDED_LATHE).expect("embedded config/lathe.toml is validated by the test suite")
    }

    /// Parse and validate TOML text; `file` names it in errors.
    pub fn from_toml(file: &str, text: &str) -> Result<Self, ConfigError> {
        let cfg: MachineConfig = toml::from_str(text).map_err(|e| ConfigError::Parse { file: file.into(), message: e.to_string() })?;
        let errors = cfg.validate();
        if errors.is_empty() {
            Ok(cfg)
        } else {
            Err(ConfigError::Invalid { file: file.into(), errors })
        }
    }

    /// Every problem, each as `key.path: what is allowed, got value`.
    pub fn validate(&self) -> Vec<String> {
        let mut e = Vec::new();
        self.validate_machine(&mut e);
        self.validate_axes(&mut e);
        self.validate_links(&mut e);
        self.validate_parameters(&mut e);
        self.validate_io(&mut e);
        self.opcua.validate(&mut e);
        e
    }

    /// `[io]`: see `crate::io`; a CiA 401 module's node id is not a drive's.
    fn validate_io(&self, e: &mut Vec<String>) {
        match self.io.resolve() {
            Ok(r) => {
                for (node, _, _) in r.canopen_modules() {
                    if let Some((name, _)) = self.axes.iter().find(|(_, a)| a.modbus.is_none() && a.node == node) {
                        e.push(format!("io.devices: CANopen node {node} is axis {name}'s drive"));
                    }
                }
            }
            Err(mut x) => e.append(&mut x),
        }
    }

    /// The machine, bus, [rt] and parameter-range keys.
    fn validate_machine(&self, e: &mut Vec<String>) {
        let c = self.machine.cycle_ms;
        for (k, v) in &self.parameters {
            e.extend(crate::params::check(k, v));
        }
        if self.bus.heartbeat_ms == 0 && !self.bus.unsafe_no_heartbeat && self.has_canopen() {
            e.push(
                "bus.heartbeat_ms: 0 switches off the drives' watch on the controller — killed, it would leave them enabled on their last set-point; set 50 … 1000, or `unsafe_no_heartbeat = true` for a bench without mechanics"
                    .into(),
            );
        }
        if !(c.is_finite() && (0.25..=100.0).contains(&c)) {
            e.push(format!("machine.cycle_ms: must be between 0.25 and 100, got {c}"));
        }
        if self.machine.drilling_spindle == DrillingSpindle::Tool && self.tool_spindle().is_none() {
            e.push("machine.drilling_spindle = \"tool\" needs an axis with role = \"tool_spindle\" (the driven tool's spindle)".into());
        }
        let sl = self.machine.sync_error_limit_um;
        if !(sl.is_finite() && (1.0..=10_000.0).contains(&sl)) {
            e.push(format!("machine.sync_error_limit_um: must be between 1 and 10000, got {sl}"));
        }
        let tu = self.machine.thread_take_up_mm;
        if !(tu.is_finite() && (0.0..=5.0).contains(&tu)) {
            e.push(format!("machine.thread_take_up_mm: must be between 0 (none) and 5, got {tu}"));
        }
        if self.machine.watchdog_overruns > 100_000 {
            e.push(format!("machine.watchdog_overruns: must be between 0 (off) and 100000, got {}", self.machine.watchdog_overruns));
        }
        for (n, a) in &self.axes {
            if a.late_sync_extrapolation > 50 {
                e.push(format!("axes.{n}.late_sync_extrapolation: must be between 0 (the drive holds) and 50, got {}", a.late_sync_extrapolation));
            }
        }
        if !(1..=50).contains(&self.machine.watchdog_missed_cycles) {
            e.push(format!(
                "machine.watchdog_missed_cycles: must be between 1 and 50 (the most cycles the loop catches up), got {}",
                self.machine.watchdog_missed_cycles
            ));
        }
        if self.bus.interface.trim().is_empty() {
            e.push("bus.interface: must name an interface (inproc, vcan0, can0, …), got \"\"".into());
        }
        if !(10_000..=1_000_000).contains(&self.bus.bitrate) {
            e.push(format!("bus.bitrate: must be between 10000 and 1000000, got {}", self.bus.bitrate));
        }
        let ft = self.bus.feedback_timeout_ms;
        if !(ft.is_finite() && ft >= 2.0 * c && ft <= 1000.0) {
            e.push(format!("bus.feedback_timeout_ms: must be between two cycles ({}) and 1000, got {ft}", 2.0 * c));
        }
        if self.bus.sdo_timeout_ms == 0 {
            e.push("bus.sdo_timeout_ms: must be > 0, got 0".into());
        }
        if !(2..=1000).contains(&self.bus.sync_loss_cycles) {
            e.push(format!("bus.sync_loss_cycles: must be 2…1000, got {}", self.bus.sync_loss_cycles));
        }
        if self.axes.is_empty() {
            e.push("axes: at least one axis is required".into());
        }
        if let Some(p) = self.rt.priority.filter(|p| !(1..=99).contains(p)) {
            e.push(format!("rt.priority: SCHED_FIFO priorities are 1–99, got {p}"));
        }
        if let Some(m) = self.rt.max_sleep_us.filter(|m| !(10..=1_000_000).contains(m)) {
            e.push(format!("rt.max_sleep_us: the longest sleep step must be 10–1000000 µs (leave it out for one sleep to the deadline), got {m}"));
        }
        if let Some(s) = self.rt.spin_us.filter(|&s| s as f64 >= c * 1000.0) {
            e.push(format!("rt.spin_us: the spin margin must be shorter than the cycle ({} µs), got {s}", c * 1000.0));
        }
        if let Some(t) = self.rt.timer_slack_ns.filter(|&t| t == 0 || t > 1_000_000) {
            e.push(format!("rt.timer_slack_ns: must be 1–1000000 ns, got {t}"));
        }
        if let Some(t) = self.param(1772).filter(|t| !(t.is_finite() && *t >= 0.0)) {
            e.push(format!("parameters.1772: the acceleration change time must be ≥ 0 ms, got {t}"));
        }
    }

    /// Every axis, node ids and PDO COB-IDs unique per bus, at most one tool spindle.
    fn validate_axes(&self, e: &mut Vec<String>) {
        // Node ids are unique per bus: the CANopen bus, and each Modbus link.
        let mut nodes: BTreeMap<(Option<&str>, u8), &str> = BTreeMap::new();
        let mut cobs: BTreeMap<u16, String> = BTreeMap::new();
        for (name, a) in &self.axes {
            self.validate_axis(name, a, &mut nodes, &mut cobs, e);
        }
        let tools: Vec<&str> = self.axes.iter().filter(|(_, a)| a.role == Some(AxisRole::ToolSpindle)).map(|(n, _)| n.as_str()).collect();
        if tools.len() > 1 {
            e.push(format!("axes: at most one axis may have role = \"tool_spindle\", got {}", tools.join(", ")));
        }
        if !tools.is_empty() && self.spindle().is_none() {
            e.push(format!("axes.{}.role: a tool spindle needs a work spindle (another axis with kind = \"spindle\")", tools[0]));
        }
    }

    /// One axis; `nodes` and `cobs` collect the ids taken so far.
    fn validate_axis<'a>(
        &self,
        name: &'a str,
        a: &'a AxisConfig,
        nodes: &mut BTreeMap<(Option<&'a str>, u8), &'a str>,
        cobs: &mut BTreeMap<u16, String>,
        e: &mut Vec<String>,
    ) {
        let p = format!("axes.{name}");
        if !name.chars().all(|ch| ch.is_ascii_alphanumeric()) || name.is_empty() {
            e.push(format!("{p}: axis names are letters and digits (x, z, c, s1), got {name:?}"));
        }
        match &a.modbus {
            None if !(1..=127).contains(&a.node) => e.push(format!("{p}.node: must be a CANopen node id 1..=127, got {}", a.node)),
            Some(l) if !(1..=247).contains(&a.node) => e.push(format!("{p}.node: must be a Modbus unit id 1..=247 on link {l:?}, got {}", a.node)),
            Some(l) if !self.modbus.contains_key(l) => {
                let known: Vec<&str> = self.modbus.keys().map(String::as_str).collect();
                e.push(format!(
                    "{p}.modbus: no [modbus.{l}] link is configured (links: {})",
                    if known.is_empty() { "none".into() } else { known.join(", ") }
                ))
            }
            bus => {
                if let Some(other) = nodes.insert((bus.as_deref(), a.node), name) {
                    let on = bus.as_deref().map(|l| format!(" on Modbus link {l:?}")).unwrap_or_default();
                    e.push(format!("{p}.node: node {}{on} is already used by axes.{other}", a.node));
                }
            }
        }
        if a.modbus.is_none() {
            let (r, t) = a.pdo_cob_ids();
            for (key, id) in [("rpdo_cob_id", r), ("tpdo_cob_id", t)] {
                if restricted_cob_id(id) {
                    e.push(format!("{p}.{key}: 0x{id:03X} is reserved by CiA 301 (NMT, SYNC, EMCY, SDO, heartbeat); use 0x181–0x57F"));
                } else if let Some(other) = cobs.insert(id, format!("{p}.{key}")) {
                    e.push(format!("{p}.{key}: 0x{id:03X} is already used by {other}"));
                }
            }
            if !(a.rpdo_transmission <= 240 || a.rpdo_transmission >= 254) {
                e.push(format!("{p}.rpdo_transmission: must be 0–240 (synchronous) or 254/255 (event), got {}", a.rpdo_transmission));
            }
            if !(1..=240).contains(&a.tpdo_transmission) {
                e.push(format!("{p}.tpdo_transmission: must be 1–240 (every n-th SYNC), got {}", a.tpdo_transmission));
            }
        }
        if a.modbus.is_none() && (a.cia402_map.is_some() || a.pr_map.is_some()) {
            e.push(format!("{p}: cia402_map / pr_map apply to Modbus drives; set {p}.modbus to the link"));
        }
        if let Some(h) = &a.homing {
            if a.absolute {
                e.push(format!("{p}: homing and absolute = true exclude each other (an absolute encoder is referenced at power-on)"));
            }
            if !homing_method_defined(h.method) {
                e.push(format!("{p}.homing.method: CiA 402 homing methods are 1–35 and 37, got {}", h.method));
            }
            for (k, v) in [("speed", h.speed), ("zero_speed", h.zero_speed), ("accel", h.accel), ("timeout_s", h.timeout_s)] {
                if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
                    e.push(format!("{p}.homing.{k}: must be > 0, got {v}"));
                }
            }
            if !h.offset.is_finite() || (h.offset * a.counts_per_unit).abs() > i32::MAX as f64 {
                e.push(format!("{p}.homing.offset: must fit the drive's INTEGER32 home offset, got {}", h.offset));
            }
        }
        if a.role == Some(AxisRole::ToolSpindle) && a.kind != AxisKind::Spindle {
            e.push(format!("{p}.role: \"tool_spindle\" needs kind = \"spindle\""));
        }
        for (k, x) in a.sdo.iter().enumerate() {
            let (lo, hi) = x.ty.range();
            if !(lo..=hi).contains(&x.value) {
                e.push(format!("{p}.sdo[{k}]: value {} does not fit type {} ({lo} … {hi})", x.value, x.ty.name()));
            }
            if x.owned_by_startup() {
                e.push(format!(
                    "{p}.sdo[{k}]: 0x{:04X} is configured by start-up itself (PDOs, error control, mode, SYNC, interpolation period); use the axis keys for it",
                    x.index
                ));
            }
            if a.modbus.is_some() {
                e.push(format!(
                    "{p}.sdo: start-up lists are for CANopen drives; this axis is on Modbus link {:?}",
                    a.modbus.as_deref().unwrap_or("")
                ));
            }
        }
        positive(e, &format!("{p}.counts_per_unit"), a.counts_per_unit);
        positive(e, &format!("{p}.max_speed"), a.max_speed);
        positive(e, &format!("{p}.max_accel"), a.max_accel);
        if let Some(j) = a.jerk.filter(|j| !(j.is_finite() && *j >= 0.0)) {
            e.push(format!("{p}.jerk: must be ≥ 0 mm/s³ (0 = no jerk limit), got {j}"));
        }
        positive(e, &format!("{p}.following_error"), a.following_error);
        positive(e, &format!("{p}.in_position"), a.in_position);
        if !(a.overload_pct.is_finite() && a.overload_pct > 100.0) {
            e.push(format!("{p}.overload_pct: the peak torque the amplifier allows, % of its rated torque, must be > 100, got {}", a.overload_pct));
        }
        positive(e, &format!("{p}.overload_s"), a.overload_s);
        if let Some(t) = a.travel_per_rev {
            positive(e, &format!("{p}.travel_per_rev"), t);
        }
        if a.kind == AxisKind::Linear {
            match (a.min, a.max) {
                (Some(lo), Some(hi)) if !(lo.is_finite() && hi.is_finite() && lo < hi) => {
                    e.push(format!("{p}.max: must be > {p}.min ({lo}), got {hi}"))
                }
                (Some(_), Some(_)) => {}
                _ => e.push(format!("{p}.min/{p}.max: a linear axis needs both travel limits (mm)")),
            }
        }
        // Counts must fit i32 over the whole travel (CiA 402 positions are INTEGER32).
        if let (Some(lo), Some(hi)) = (a.min, a.max) {
            let m = lo.abs().max(hi.abs()) * a.counts_per_unit;
            if m > i32::MAX as f64 {
                e.push(format!(
                    "{p}.counts_per_unit: travel ±{} × {} counts overflows INTEGER32; lower the resolution",
                    lo.abs().max(hi.abs()),
                    a.counts_per_unit
                ));
            }
        }
    }

    /// The Modbus links.
    fn validate_links(&self, e: &mut Vec<String>) {
        let c = self.machine.cycle_ms;
        for (name, l) in &self.modbus {
            let p = format!("modbus.{name}");
            match l.transport {
                LinkTransport::Tcp => match &l.address {
                    Some(a)
                        if a.parse::<std::net::SocketAddr>().is_ok()
                            || a.rsplit_once(':').is_some_and(|(h, port)| !h.is_empty() && port.parse::<u16>().is_ok()) => {}
                    Some(a) => e.push(format!("{p}.address: must be host:port, got {a:?}")),
                    None => e.push(format!("{p}.address: a tcp link needs host:port (e.g. \"192.168.1.20:502\")")),
                },
                LinkTransport::Rtu => {
                    if l.device.as_deref().is_none_or(|d| d.trim().is_empty()) {
                        e.push(format!("{p}.device: an rtu link needs the serial device (e.g. \"/dev/ttyUSB0\")"));
                    }
                    if !(1200..=4_000_000).contains(&l.baud) {
                        e.push(format!("{p}.baud: must be between 1200 and 4000000, got {}", l.baud));
                    }
                    if !(1..=2).contains(&l.stop_bits) {
                        e.push(format!("{p}.stop_bits: must be 1 or 2, got {}", l.stop_bits));
                    }
                }
            }
            if !(l.turnaround_ms.is_finite() && (0.0..=1000.0).contains(&l.turnaround_ms)) {
                e.push(format!("{p}.turnaround_ms: must be between 0 and 1000, got {}", l.turnaround_ms));
            }
            if !(1..=10_000).contains(&l.timeout_ms) {
                e.push(format!("{p}.timeout_ms: must be between 1 and 10000, got {}", l.timeout_ms));
            } else if let Some(most) = l.most_timeout_ms(self.bus.feedback_timeout_ms, c).filter(|&m| (l.timeout_ms as f64) > m) {
                e.push(format!(
                    "{p}.timeout_ms = {}: one answer that does not come holds the drive's next reading back by the timeout and a cycle, past bus.feedback_timeout_ms = {}: every lost answer would be alarm 2015; make timeout_ms at most {most:.0} (or raise the feedback timeout)",
                    l.timeout_ms, self.bus.feedback_timeout_ms
                ));
            }
            if let Some(c) = l.cycle_ms {
                if !(c.is_finite() && (0.25..=1000.0).contains(&c)) {
                    e.push(format!("{p}.cycle_ms: must be between 0.25 and 1000, got {c}"));
                }
            }
            if !self.axes.values().any(|a| a.modbus.as_deref() == Some(name.as_str())) {
                e.push(format!("{p}: no axis uses this link (set modbus = {name:?} on an axis, or remove it)"));
            }
        }
    }

    /// `[parameters]` keys and value shapes.
    fn validate_parameters(&self, e: &mut Vec<String>) {
        for (k, v) in &self.parameters {
            if k.parse::<u32>().is_err() {
                e.push(format!("parameters.{k}: parameter keys are the manuals' numbers (e.g. 5200), got {k:?}"));
            }
            // Per-axis parameters (No.1240 reference point …) are tables `{ x = 0.0, z = 0.0 }`.
            let per_axis = v.as_table().is_some_and(|t| t.values().all(|a| a.is_integer() || a.is_float()));
            if !(v.is_integer() || v.is_float() || v.is_bool() || per_axis) {
                e.push(format!("parameters.{k}: must be a number (or {{ x = …, z = … }} per axis), got {v}"));
            }
        }
    }

    pub fn cycle_s(&self) -> f64 {
        self.machine.cycle_ms / 1000.0
    }

    /// The cycle period in ns, as the cycle loop and the drives' SYNC period take it (the one
    /// conversion of `machine.cycle_ms`).
    pub fn cycle_ns(&self) -> u64 {
        (self.machine.cycle_ms * 1e6).round() as u64
    }

    /// A numeric parameter by its manual number.
    pub fn param(&self, no: u32) -> Option<f64> {
        match self.parameters.get(&no.to_string())? {
            toml::Value::Integer(i) => Some(*i as f64),
            toml::Value::Float(f) => Some(*f),
            toml::Value::Boolean(b) => Some(*b as u8 as f64),
            _ => None,
        }
    }

    /// Axis `axis` (`x`, `z`, `y`, `c`) of a per-axis parameter written as a table, e.g.
    /// `1240 = { x = 0.0, z = 0.0 }` → `param_axis(1240, "z")`.
    pub fn param_axis(&self, no: u32, axis: &str) -> Option<f64> {
        match self.parameters.get(&no.to_string())?.as_table()?.get(axis)? {
            toml::Value::Integer(i) => Some(*i as f64),
            toml::Value::Float(f) => Some(*f),
            _ => None,
        }
    }

    /// Bit `bit` of an integer parameter (No.5200#6 → `param_bit(5200, 6)`).
    pub fn param_bit(&self, no: u32, bit: u8) -> bool {
        self.param(no).map(|v| (v as i64 >> bit) & 1 == 1).unwrap_or(false)
    }

    /// Whether any axis is on the CANopen bus.
    pub fn has_canopen(&self) -> bool {
        self.axes.values().any(|a| a.modbus.is_none())
    }

    /// The (work) spindle axis, if any: the first spindle that is not the tool spindle.
    pub fn spindle(&self) -> Option<(&str, &AxisConfig)> {
        self.axes.iter().find(|(_, a)| is_work_spindle(a)).map(|(n, a)| (n.as_str(), a))
    }

    /// How many cycles every drive bridges a late SYNC by extrapolating (the least of the
    /// axes' `late_sync_extrapolation`; 0: at least one holds its target).
    pub fn late_sync_extrapolation(&self) -> u32 {
        self.axes.values().map(|a| a.late_sync_extrapolation).min().unwrap_or(0)
    }

    /// The work spindle's index in configuration order (the bus's drive order).
    pub fn spindle_index(&self) -> Option<usize> {
        self.axes.values().position(is_work_spindle)
    }

    /// The tool spindle of polygon turning (`role = "tool_spindle"`): its index in
    /// configuration order and its config.
    pub fn tool_spindle(&self) -> Option<(usize, &AxisConfig)> {
        self.axes.values().enumerate().find(|(_, a)| a.role == Some(AxisRole::ToolSpindle))
    }
}

fn is_work_spindle(a: &AxisConfig) -> bool {
    a.kind == AxisKind::Spindle && a.role != Some(AxisRole::ToolSpindle)
}

fn positive(e: &mut Vec<String>, path: &str, v: f64) {
    if !(v.is_finite() && v > 0.0) {
        e.push(format!("{path}: must be > 0, got {v}"));
    }
}

/// `[opcua]`: the read-only OPC UA server of `cncgw run` (src/opcua/). Off unless
/// `enabled = true`; secure by default: Sign&Encrypt, users with passwords, no anonymous.
#[derive(Clone, Debug, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct OpcUaConfig {
    #[serde(default)]
    pub enabled: bool,
    /// The address the server binds and names in its endpoint URL.
    #[serde(default = "default_opcua_host")]
    pub host: String,
    /// TCP port; 4840 is OPC UA's registered port.
    #[serde(default = "default_opcua_port")]
    pub port: u16,
    /// Security policies offered, each with Sign&Encrypt: `basic256sha256` (default),
    /// `aes128sha256rsaoaep`, `aes256sha256rsapss`; `none` (no signing, no encryption) only
    /// on a loopback `host` with `allow_none_on_loopback = true`.
    #[serde(default = "default_opcua_policies")]
    pub security_policies: Vec<String>,
    /// Allow the `none` policy when the server is bound to loopback (a local dashboard).
    #[serde(default)]
    pub allow_none_on_loopback: bool,
    /// Accept clients without a user name (anonymous). Off by default.
    #[serde(default)]
    pub anonymous: bool,
    /// Users (`[[opcua.users]]`): `name` and either `password_hash`, an Argon2 PHC string
    /// (`cncgw opcua-hash` makes one), or an X.509 user certificate (`certificate`, a file, or
    /// `certificate_thumbprint`, its SHA-1).
    #[serde(default)]
    pub users: Vec<OpcUaUser>,
    /// After the run the server stays up this long so that subscribed clients receive the
    /// final state and the last alarm, ms (0 … 60000; default 1500).
    #[serde(default = "default_opcua_linger")]
    pub linger_ms: u32,
}

/// One `[[opcua.users]]` entry: a name and exactly one way to prove it.
#[derive(Clone, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct OpcUaUser {
    pub name: String,
    /// Argon2 PHC string (`$argon2id$v=19$m=…,t=…,p=…$salt$hash`); never the password itself.
    #[serde(default)]
    pub password_hash: Option<String>,
    /// The user's X.509 certificate (DER or PEM), which the client presents as its identity
    /// token (signed with its key); relative: to the configuration file's folder.
    #[serde(default)]
    pub certificate: Option<String>,
    /// The same, by the certificate's SHA-1 thumbprint (40 hex digits, `:` allowed: what
    /// `openssl x509 -noout -fingerprint -sha1` prints).
    #[serde(default)]
    pub certificate_thumbprint: Option<String>,
}

impl OpcUaUser {
    /// `certificate_thumbprint` as 20 bytes, if it is 40 hex digits (with or without `:`).
    pub fn thumbprint_bytes(&self) -> Option<[u8; 20]> {
        let hex: String = self.certificate_thumbprint.as_deref()?.chars().filter(|c| *c != ':').collect();
        let mut b = [0u8; 20];
        if hex.len() != 40 || !hex.is_ascii() {
            return None;
        }
        for (k, byte) in b.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&hex[2 * k..2 * k + 2], 16).ok()?;
        }
        Some(b)
    }
}

/// The security policies `[opcua] security_policies` accepts.
pub const OPCUA_POLICIES: [&str; 4] = ["basic256sha256", "aes128sha256rsaoaep", "aes256sha256rsapss", "none"];

impl Default for OpcUaConfig {
    fn default() -> Self {
        OpcUaConfig {
            enabled: false,
            host: default_opcua_host(),
            port: default_opcua_port(),
            security_policies: default_opcua_policies(),
            allow_none_on_loopback: false,
            anonymous: false,
            users: Vec::new(),
            linger_ms: default_opcua_linger(),
        }
    }
}

fn default_opcua_host() -> String {
    "127.0.0.1".into()
}
fn default_opcua_port() -> u16 {
    4840
}
fn default_opcua_policies() -> Vec<String> {
    vec!["basic256sha256".into()]
}
fn default_opcua_linger() -> u32 {
    1500
}

impl OpcUaConfig {
    /// `host` is a loopback address (127.0.0.0/8, ::1, `localhost`): only this machine can
    /// connect.
    pub fn is_loopback(&self) -> bool {
        self.host == "localhost" || self.host.parse::<std::net::IpAddr>().is_ok_and(|a| a.is_loopback())
    }

    fn validate(&self, e: &mut Vec<String>) {
        if self.host.trim().is_empty() {
            e.push("opcua.host: must name an address to bind, got an empty string".into());
        }
        if self.port == 0 {
            e.push("opcua.port: must be 1 … 65535, got 0".into());
        }
        if self.security_policies.is_empty() {
            e.push(format!("opcua.security_policies: must name at least one of {}", OPCUA_POLICIES.join(", ")));
        }
        for p in &self.security_policies {
            if !OPCUA_POLICIES.contains(&p.as_str()) {
                e.push(format!("opcua.security_policies: unknown policy {p:?}; known: {}", OPCUA_POLICIES.join(", ")));
            }
        }
        if self.security_policies.iter().any(|p| p == "none") && !(self.is_loopback() && self.allow_none_on_loopback) {
            e.push(format!(
                "opcua.security_policies: \"none\" (unsigned, unencrypted) is allowed only on a loopback host with allow_none_on_loopback = true, got host {:?}{}",
                self.host,
                if self.is_loopback() { " without allow_none_on_loopback" } else { "" }
            ));
        }
        if self.enabled && !self.anonymous && self.users.is_empty() {
            e.push("opcua.users: no user could connect: add [[opcua.users]] (name, password_hash or certificate) or set anonymous = true".into());
        }
        for (i, u) in self.users.iter().enumerate() {
            if u.name.trim().is_empty() {
                e.push(format!("opcua.users[{i}].name: must not be empty"));
            }
            if self.users[..i].iter().any(|v| v.name == u.name) {
                e.push(format!("opcua.users[{i}].name: {:?} is given twice", u.name));
            }
            let ways = [u.password_hash.is_some(), u.certificate.is_some(), u.certificate_thumbprint.is_some()];
            if ways.iter().filter(|w| **w).count() != 1 {
                e.push(format!("opcua.users[{i}]: give exactly one of password_hash, certificate, certificate_thumbprint"));
            }
            // The full parse is the server's (feature `opcua`); here the form, so that a
            // password written in clear is refused by `config check` too.
            if let Some(h) = &u.password_hash {
                if !["$argon2id$", "$argon2i$", "$argon2d$"].iter().any(|p| h.starts_with(p)) || h.split('$').count() != 6 {
                    e.push(format!(
                        "opcua.users[{i}].password_hash: must be an Argon2 PHC string ($argon2id$v=19$m=…$salt$hash; `cncgw opcua-hash` makes one), not the password itself"
                    ));
                }
            }
            if u.certificate.as_deref().is_some_and(|c| c.trim().is_empty()) {
                e.push(format!("opcua.users[{i}].certificate: must name a certificate file"));
            }
            if u.certificate_thumbprint.is_some() && u.thumbprint_bytes().is_none() {
                e.push(format!("opcua.users[{i}].certificate_thumbprint: must be the certificate's SHA-1, 40 hex digits (\":\" allowed)"));
            }
        }
        if self.linger_ms > 60_000 {
            e.push(format!("opcua.linger_ms: must be 0 … 60000, got {}", self.linger_ms));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_config_is_valid() {
        let c = MachineConfig::from_toml("lathe.toml", EMBEDDED_LATHE).unwrap();
        assert_eq!(c.machine.cycle_ms, 2.0);
        assert_eq!(c.axes["x"].node, 1);
        assert_eq!(c.axes["z"].node, 2);
        assert_eq!(c.axes["s1"].node, 3);
        assert!(c.param(5200).is_some());
    }

    #[test]
    fn negative_speed_is_reported_with_key_path() {
        let t = EMBEDDED_LATHE.replace("max_speed = 12000.0 # z", "max_speed = -3 # z");
        assert_ne!(t, EMBEDDED_LATHE, "test must edit the z axis");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.max_speed: must be > 0, got -3"), "{err}");
    }

    #[test]
    fn unknown_key_is_a_parse_error() {
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nbogus = 1");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("bogus"), "{err}");
    }

    #[test]
    fn thread_take_up_defaults_and_is_validated() {
        let key = "thread_take_up_mm = 0.3";
        assert!(EMBEDDED_LATHE.contains(key));
        // Absent, the default.
        let c = MachineConfig::from_toml("t.toml", &EMBEDDED_LATHE.replace(key, "")).unwrap();
        assert_eq!(c.machine.thread_take_up_mm, 0.3);
        let t = EMBEDDED_LATHE.replace(key, "thread_take_up_mm = 0");
        assert_eq!(MachineConfig::from_toml("t.toml", &t).unwrap().machine.thread_take_up_mm, 0.0);
        for bad in ["-0.1", "6.0", "nan"] {
            let t = EMBEDDED_LATHE.replace(key, &format!("thread_take_up_mm = {bad}"));
            let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
            assert!(err.contains("machine.thread_take_up_mm: must be between 0 (none) and 5"), "{bad}: {err}");
        }
    }

    #[test]
    fn sync_error_limit_defaults_and_is_validated() {
        let c = MachineConfig::from_toml("lathe.toml", EMBEDDED_LATHE).unwrap();
        assert_eq!(c.machine.sync_error_limit_um, 100.0);
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nsync_error_limit_um = 25");
        assert_eq!(MachineConfig::from_toml("t.toml", &t).unwrap().machine.sync_error_limit_um, 25.0);
        let t = EMBEDDED_LATHE.replace("[machine]", "[machine]\nsync_error_limit_um = 0.0");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("machine.sync_error_limit_um: must be between 1 and 10000, got 0"), "{err}");
    }

    #[test]
    fn duplicate_node_is_reported() {
        let t = EMBEDDED_LATHE.replace("node = 2", "node = 1");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.node: node 1 is already used by axes.x"), "{err}");
    }

    const MODBUS_LATHE: &str = include_str!("../config/lathe-modbus.toml");

    #[test]
    fn modbus_lathe_is_valid_and_has_no_canopen_axis() {
        let c = MachineConfig::from_toml("lathe-modbus.toml", MODBUS_LATHE).unwrap();
        assert!(!c.has_canopen());
        assert_eq!(c.axes["z"].modbus.as_deref(), Some("tcp"));
        assert_eq!(c.modbus["tcp"].transport, LinkTransport::Tcp);
        assert!(MachineConfig::embedded().has_canopen());
    }

    #[test]
    fn modbus_errors_name_the_key() {
        let t = MODBUS_LATHE.replace("node = 2\nmodbus = \"tcp\"", "node = 2\nmodbus = \"rs485\"");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.modbus: no [modbus.rs485] link is configured (links: tcp)"), "{err}");
        let t = MODBUS_LATHE.replace("node = 2\n", "node = 1\n");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.node: node 1 on Modbus link \"tcp\" is already used by axes.x"), "{err}");
        let t = MODBUS_LATHE.replace("node = 3\n", "node = 250\n");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.s1.node: must be a Modbus unit id 1..=247"), "{err}");
        let t = MODBUS_LATHE.replace("address = \"127.0.0.1:5020\"", "address = \"drive-cabinet\"");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("modbus.tcp.address: must be host:port"), "{err}");
        let t = MODBUS_LATHE.replace("transport = \"tcp\"", "transport = \"rtu\"\nbaud = 300");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("modbus.tcp.device: an rtu link needs the serial device"), "{err}");
        assert!(err.contains("modbus.tcp.baud: must be between 1200 and 4000000, got 300"), "{err}");
        // Issue 22.7: a timeout as long as the feedback timeout makes every lost answer 2015.
        let t = MODBUS_LATHE.replace("timeout_ms = 20 ", "timeout_ms = 50 ");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("modbus.tcp.timeout_ms = 50: one answer that does not come"), "{err}");
        assert!(err.contains("every lost answer would be alarm 2015; make timeout_ms at most 46"), "{err}");
    }

    #[test]
    fn mixed_machine_allows_the_same_node_on_two_buses() {
        // Z on CANopen node 2 and a tailstock W on Modbus unit 2.
        let t = format!(
            "{EMBEDDED_LATHE}\n[modbus.line]\ntransport = \"rtu\"\ndevice = \"/dev/ttyUSB0\"\ntimeout_ms = 10\n\n[axes.w]\nkind = \"linear\"\nnode = 2\nmodbus = \"line\"\nmodbus_profile = \"pr\"\ncounts_per_unit = 1000.0\nmin = -500.0\nmax = 0.0\nmax_speed = 3000.0\nmax_accel = 500.0\n"
        );
        let c = MachineConfig::from_toml("mixed.toml", &t).unwrap();
        assert!(c.has_canopen());
        assert_eq!(c.axes["w"].modbus_profile, cncgw_bus::modbus::Profile::Pr);
    }

    const POLYGON_LATHE: &str = include_str!("../config/lathe-polygon.toml");

    #[test]
    fn polygon_lathe_has_a_tool_spindle_apart_from_the_work_spindle() {
        let c = MachineConfig::from_toml("lathe-polygon.toml", POLYGON_LATHE).unwrap();
        let (i, t) = c.tool_spindle().unwrap();
        assert_eq!((i, t.node), (1, 4));
        assert_eq!(c.spindle().map(|s| s.0), Some("s1"));
        assert_eq!(c.spindle_index(), Some(0));
        assert!(MachineConfig::embedded().tool_spindle().is_none());
        let t = POLYGON_LATHE.replace("kind = \"spindle\"\nrole", "kind = \"linear\"\nmin = 0.0\nmax = 1.0\nrole");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("role: \"tool_spindle\" needs kind = \"spindle\""), "{err}");
    }

    #[test]
    fn pdo_cob_ids_are_checked() {
        let t = EMBEDDED_LATHE.replace("node = 2\n", "node = 2\ntpdo_cob_id = 0x181\n");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.tpdo_cob_id: 0x181 is already used by axes.x.tpdo_cob_id"), "{err}");
        let t = EMBEDDED_LATHE.replace("node = 2\n", "node = 2\nrpdo_cob_id = 0x601\ntpdo_transmission = 0\n");
        let err = MachineConfig::from_toml("t.toml", &t).unwrap_err().to_string();
        assert!(err.contains("axes.z.rpdo_cob_id: 0x601 is reserved by CiA 301"), "{err}");
        assert!(err.contains("axes.z.tpdo_transmission: must be 1–240"), "{err}");
        let t = EMBEDDED_LATHE.replace("node = 2\n", "node = 2\nrpdo_cob_id = 0x222\ntpdo_cob_id = 0x1A2\n");
        let c = MachineConfig::from_toml("t.toml", &t).unwrap();
        assert_eq!(c.axes["z"].pdo_cob_ids(), (0x222, 0x1A2));
        assert_eq!(c.axes["x"].pdo_cob_ids(), (0x201, 0x181));
    }

    fn opcua(extra: &str) -> Result<MachineConfig, ConfigError> {
        MachineConfig::from_toml("m.toml", &format!("{EMBEDDED_LATHE}\n[opcua]\n{extra}"))
    }

    const HASH: &str = "$argon2id$v=19$m=19456,t=2,p=1$c2FsdHNhbHQ$ZmFrZWhhc2hmYWtlaGFzaGZha2VoYXNoZmFrZQ";

    #[test]
    fn opcua_is_off_by_default_and_secure_when_on() {
        let c = MachineConfig::embedded();
        assert!(!c.opcua.enabled);
        let c = opcua(&format!("enabled = true\nport = 4841\n[[opcua.users]]\nname = \"mes\"\npassword_hash = \"{HASH}\"")).unwrap();
        assert!(c.opcua.enabled && !c.opcua.anonymous && c.opcua.port == 4841);
        assert_eq!(c.opcua.security_policies, vec!["basic256sha256".to_string()]);
    }

    #[test]
    fn opcua_none_only_on_loopback_and_when_allowed() {
        let user = format!("[[opcua.users]]\nname = \"mes\"\npassword_hash = \"{HASH}\"");
        let e = opcua(&format!("enabled = true\nsecurity_policies = [\"none\"]\n{user}")).unwrap_err().to_string();
        assert!(
            e.contains("\"none\" (unsigned, unencrypted) is allowed only on a loopback host") && e.contains("without allow_none_on_loopback"),
            "{e}"
        );
        let e = opcua(&format!("enabled = true\nhost = \"0.0.0.0\"\nallow_none_on_loopback = true\nsecurity_policies = [\"none\"]\n{user}"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("got host \"0.0.0.0\""), "{e}");
        let c = opcua(&format!(
            "enabled = true\nhost = \"::1\"\nallow_none_on_loopback = true\nsecurity_policies = [\"none\", \"basic256sha256\"]\n{user}"
        ));
        assert!(c.is_ok(), "{c:?}");
    }

    #[test]
    fn opcua_users_need_hashes_and_someone_must_be_able_to_connect() {
        let e = opcua("enabled = true").unwrap_err().to_string();
        assert!(e.contains("opcua.users: no user could connect"), "{e}");
        assert!(opcua("enabled = true\nanonymous = true").is_ok());
        let e = opcua("enabled = true\n[[opcua.users]]\nname = \"mes\"\npassword_hash = \"secret\"").unwrap_err().to_string();
        assert!(e.contains("opcua.users[0].password_hash: must be an Argon2 PHC string"), "{e}");
        let cert = opcua("enabled = true\n[[opcua.users]]\nname = \"cell\"\ncertificate_thumbprint = \"3F:9A:00:11:22:33:44:55:66:77:88:99:aa:bb:cc:dd:ee:ff:01:02\"");
        assert_eq!(cert.unwrap().opcua.users[0].thumbprint_bytes().map(|b| (b[0], b[19])), Some((0x3f, 0x02)));
        assert!(opcua("enabled = true\n[[opcua.users]]\nname = \"cell\"\ncertificate = \"cell.der\"").is_ok());
        let e = opcua(&format!("enabled = true\n[[opcua.users]]\nname = \"cell\"\ncertificate = \"c.der\"\npassword_hash = \"{HASH}\""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("opcua.users[0]: give exactly one of"), "{e}");
        let e = opcua("enabled = true\n[[opcua.users]]\nname = \"cell\"").unwrap_err().to_string();
        assert!(e.contains("opcua.users[0]: give exactly one of"), "{e}");
        let e = opcua("enabled = true\n[[opcua.users]]\nname = \"cell\"\ncertificate_thumbprint = \"3f9a\"").unwrap_err().to_string();
        assert!(e.contains("certificate_thumbprint: must be the certificate's SHA-1"), "{e}");
        let e = opcua("enabled = true\nport = 0\nsecurity_policies = [\"basic128rsa15\"]\nanonymous = true").unwrap_err().to_string();
        assert!(e.contains("opcua.port: must be 1 … 65535") && e.contains("unknown policy \"basic128rsa15\""), "{e}");
    }
}
