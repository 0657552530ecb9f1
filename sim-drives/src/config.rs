//! Configuration of the emulated drives: identity, scaling and physics per node.
//!
//! Two sources: a cncgw machine config (only `[axes.*]` kind, node and counts_per_unit are
//! read; physics get realistic defaults per kind) or a sim-drives TOML file (what
//! `--print-default-config` prints), where every physical parameter can be overridden.

use cncgw_bus::modbus::{Cia402Map, PrMap, Profile, WordOrder};
use serde::Deserialize;
use std::collections::BTreeMap;

/// The default machine, compiled in.
pub const LATHE_TOML: &str = include_str!("../../config/lathe.toml");

/// Ball-screw lead assumed for linear axes (mm per motor revolution, direct drive).
pub const DEFAULT_SCREW_LEAD_MM: f64 = 10.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DriveKind {
    /// A feed-axis servo on a ball screw; position units are counts of the motor encoder.
    Linear,
    /// A spindle amplifier (Cs-capable): heavier, softer position loop.
    Spindle,
}

impl DriveKind {
    pub fn name(self) -> &'static str {
        match self {
            DriveKind::Linear => "linear",
            DriveKind::Spindle => "spindle",
        }
    }
}

/// Mechanics and control loop of one drive. Motor-side units: kg·m², N·m, rad/s.
#[derive(Clone, Debug, PartialEq)]
pub struct Physics {
    /// Motor rotor inertia, kg·m².
    pub motor_inertia: f64,
    /// Load inertia reflected to the motor shaft, kg·m².
    pub load_inertia: f64,
    /// Peak torque of the amplifier/motor pair, N·m.
    pub torque_limit: f64,
    /// Coulomb (dry) friction torque, N·m.
    pub coulomb_friction: f64,
    /// Viscous friction, N·m per rad/s.
    pub viscous_friction: f64,
    /// Position loop gain Kv, 1/s.
    pub kv: f64,
    /// Velocity feed-forward gain (1.0 = 100 %). Real drives run slightly below 100 %.
    pub velocity_ff: f64,
    /// Velocity loop proportional gain, N·m per rad/s.
    pub vel_kp: f64,
    /// Velocity loop integral time, ms.
    pub vel_ti_ms: f64,
    /// Maximum motor speed, rpm (velocity command clamp).
    pub max_speed_rpm: f64,
    /// Current (torque) loop time constant, ms: the torque lags its command by this.
    pub current_loop_tc_ms: f64,
    /// Resolution of the motor encoder the speed is estimated from, bits per revolution.
    pub speed_encoder_bits: u32,
    /// Speed estimate low-pass filter time constant, ms.
    pub speed_filter_ms: f64,
    /// What real drives have and the plain model lacks; each 0 = off (the defaults).
    pub extra: Extra,
}

/// Properties of real drives beyond the rigid single-inertia model (`[drive.physics]`
/// keys; 0 = off).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Extra {
    /// SYNCs between a CSP set-point's arrival and the drive acting on it (buffering in the
    /// drive, beyond the one interpolation period every drive has).
    pub transport_delay_cycles: u32,
    /// Lines × 4 of the position encoder per motor revolution when coarser than the
    /// position unit: the position loop and the reported actual position see it quantised.
    pub encoder_counts_per_rev: u32,
    /// Compliance between motor and load (a belt, a long screw), N·m/rad at the motor; the
    /// load inertia then sits behind it with the friction and the process load.
    pub load_stiffness: f64,
    /// Damping of that compliance, N·m·s/rad.
    pub load_damping: f64,
    /// Lost motion between motor and load, degrees of the motor.
    pub backlash_deg: f64,
}

impl Physics {
    pub fn inertia(&self) -> f64 {
        self.motor_inertia + self.load_inertia
    }

    /// Defaults per kind: a 1 kW-class feed servo on a 10 mm screw; a 7.5 kW spindle motor
    /// with chuck and part — ~100× the inertia and a softer position loop, as on real lathes.
    pub fn default_for(kind: DriveKind) -> Physics {
        match kind {
            DriveKind::Linear => {
                let j = 1.6e-4 + 2.4e-4;
                Physics {
                    motor_inertia: 1.6e-4,
                    load_inertia: 2.4e-4,
                    torque_limit: 9.5,
                    coulomb_friction: 0.15,
                    viscous_friction: 2.0e-4,
                    kv: 50.0,
                    velocity_ff: 0.995,
                    // Velocity loop bandwidth ≈ 150 Hz.
                    vel_kp: j * 2.0 * std::f64::consts::PI * 150.0,
                    vel_ti_ms: 5.0,
                    max_speed_rpm: 3000.0,
                    // Current loop ≈ 1 kHz.
                    current_loop_tc_ms: 0.15,
                    // A 20-bit motor encoder, speed filtered at ≈ 800 Hz.
                    speed_encoder_bits: 20,
                    speed_filter_ms: 0.2,
                    extra: Extra::default(),
                }
            }
            DriveKind::Spindle => {
                let j = 0.02 + 0.03;
                Physics {
                    motor_inertia: 0.02,
                    load_inertia: 0.03,
                    torque_limit: 70.0,
                    coulomb_friction: 1.0,
                    viscous_friction: 5.0e-3,
                    kv: 20.0,
                    velocity_ff: 0.998,
                    // Velocity loop bandwidth ≈ 40 Hz.
                    vel_kp: j * 2.0 * std::f64::consts::PI * 40.0,
                    vel_ti_ms: 20.0,
                    max_speed_rpm: 8000.0,
                    // A bigger motor, a slower current loop (≈ 400 Hz).
                    current_loop_tc_ms: 0.4,
                    speed_encoder_bits: 20,
                    speed_filter_ms: 0.5,
                    extra: Extra::default(),
                }
            }
        }
    }
}

/// How a drive differs from the plain emulated one, imitating commercial drives that
/// trouble a master at start-up (issue 27): `[drive.shape]` in a sim-drives config. The
/// default is the plain drive (boots in no mode, switches modes at once, positions in encoder
/// increments, every object present, SYNC consumer).
#[derive(Clone, Debug, PartialEq)]
pub struct Shape {
    /// 0x6060 / 0x6061 after power-on: 0 = no mode; 1 = profile position, as many drives boot.
    pub boot_mode: i8,
    /// A mode written to 0x6060 shows in 0x6061 (and takes effect) only after this many ms…
    pub mode_switch_ms: f64,
    /// …and this many SYNCs (both, when both are set).
    pub mode_switch_syncs: u32,
    /// Modes of operation the drive has: what 0x6060 accepts and 0x6502 lists.
    pub modes: Vec<i8>,
    /// Whether 0x6502 (supported drive modes) exists.
    pub supported_modes_object: bool,
    /// Whether the factor group 0x608F / 0x6091 / 0x6092 and the polarity 0x607E exist.
    pub factor_group: bool,
    /// 0x6092:1 feed constant: position units per shaft revolution (0 = `counts_per_rev` ×
    /// gear ratio, i.e. positions in encoder increments). E.g. 10000 on a 10 mm screw: 1 µm.
    pub feed_constant: u32,
    /// 0x6091 gear ratio: motor revolutions (sub 1) per shaft revolution (sub 2).
    pub gear_ratio: [u32; 2],
    /// 0x607E at power-on: bit 7 inverts positions, bit 6 velocities.
    pub polarity: u8,
    /// A drive that scales its feedback differently from its target: 0x6064 reports this
    /// many times the position in 0x607A's units (1 = consistent). Hidden from the factor
    /// group; the master's last line of defence must find it while running.
    pub feedback_factor: f64,
    /// The drive produces SYNC itself (0x1005 bit 30 at power-on), every `sync_period_us`
    /// (0x1006 at power-on) while pre-operational or operational.
    pub sync_producer: bool,
    pub sync_period_us: u32,
    /// Whether 0x1016 (heartbeat consumer) exists.
    pub heartbeat_consumer: bool,
    /// Whether node guarding exists: 0x100C guard time, 0x100D life time factor, answers to
    /// remote frames on 0x700 + node, life guarding per 0x6007.
    pub node_guarding: bool,
    /// Whether 0x6007 (abort connection option) exists; without it a lost master faults
    /// the drive, as most drives do.
    pub abort_connection_object: bool,
    /// Whether 0x1029 (error behaviour, CiA 301) exists; without it a communication error
    /// leaves the NMT state as it is.
    pub error_behaviour_object: bool,
    /// Whether 0x6061 may be mapped into a PDO (a restricted mapping when false).
    pub mode_display_pdo: bool,
    /// Fixed PDO mapping: the mapping objects (0x1600…, 0x1A00…) are read-only and keep
    /// their power-on contents (RPDO1 controlword + 0x607A, TPDO1 statusword + 0x6064);
    /// COB-IDs and transmission types stay writable.
    pub fixed_pdo: bool,
    /// Whether the objects CiA 402 makes optional and a master only prefers exist: 0x605A
    /// quick stop option, 0x605B/0x605C/0x605E stop reactions, 0x607D software limits.
    pub optional_402_objects: bool,
    /// Sub-indices of 0x1018 the drive has (4: vendor, product, revision, serial; 0: none,
    /// a vendor-id read aborts).
    pub identity_subs: u8,
}

impl Default for Shape {
    fn default() -> Self {
        Shape {
            boot_mode: 0,
            mode_switch_ms: 0.0,
            mode_switch_syncs: 0,
            modes: vec![1, 6, 8, 9],
            supported_modes_object: true,
            factor_group: true,
            feed_constant: 0,
            gear_ratio: [1, 1],
            polarity: 0,
            feedback_factor: 1.0,
            sync_producer: false,
            sync_period_us: 2000,
            heartbeat_consumer: true,
            node_guarding: true,
            abort_connection_object: true,
            error_behaviour_object: true,
            mode_display_pdo: true,
            fixed_pdo: false,
            optional_402_objects: true,
            identity_subs: 4,
        }
    }
}

impl Shape {
    /// Modes the emulated drive implements (and so may list).
    pub const IMPLEMENTED_MODES: [i8; 5] = [1, 6, 7, 8, 9];

    /// The named shapes of `[[drive]] profile = "…"` (issue 21), each imitating a kind of
    /// commercial drive; `[drive.shape]` keys change them further.
    pub const PROFILES: [&'static str; 6] = ["plain", "ip-only", "pp-boot", "no-1016", "fixed-pdo", "user-units"];

    /// The shape of a named profile: "ip-only" has interpolated position (7) but no CSP
    /// (0x6060 = 8 aborts 0x06090030); "pp-boot" boots into profile position and takes a new
    /// mode only 200 SYNCs after it was asked for; "no-1016" has no heartbeat consumer but
    /// node guarding; "fixed-pdo" has a read-only PDO mapping that cannot carry 0x6061;
    /// "user-units" counts positions in user units, 10000 per shaft revolution (0x6092:1 =
    /// 10000: µm on a 10 mm screw), not encoder increments.
    pub fn profile(name: &str) -> Option<Shape> {
        let mut s = Shape::default();
        match name {
            "plain" => {}
            "ip-only" => s.modes = vec![1, 6, 7],
            "pp-boot" => {
                s.boot_mode = 1;
                s.mode_switch_syncs = 200;
            }
            "no-1016" => s.heartbeat_consumer = false,
            "fixed-pdo" => s.fixed_pdo = true,
            "user-units" => s.feed_constant = 10_000,
            _ => return None,
        }
        Some(s)
    }

    /// 0x6502: bit m−1 for each standard mode m (1…10).
    pub fn supported_modes_bits(&self) -> u32 {
        self.modes.iter().filter(|&&m| (1..=10).contains(&m)).fold(0, |b, &m| b | 1 << (m - 1))
    }

    fn check(&self, k: &str, errs: &mut Vec<String>) {
        for &m in &self.modes {
            if !Self::IMPLEMENTED_MODES.contains(&m) {
                errs.push(format!("{k}: shape.modes: mode {m} is not emulated (modes: 1 PP, 6 homing, 7 IP, 8 CSP, 9 CSV)"));
            }
        }
        if !Self::IMPLEMENTED_MODES.contains(&self.boot_mode) && self.boot_mode != 0 {
            errs.push(format!("{k}: shape.boot_mode must be 0, 1, 6, 7, 8 or 9, got {}", self.boot_mode));
        }
        if !(self.mode_switch_ms.is_finite() && (0.0..=60_000.0).contains(&self.mode_switch_ms)) {
            errs.push(format!("{k}: shape.mode_switch_ms must be 0…60000, got {}", self.mode_switch_ms));
        }
        if self.gear_ratio.contains(&0) {
            errs.push(format!("{k}: shape.gear_ratio: both numbers must be > 0"));
        }
        if !(self.feedback_factor.is_finite() && self.feedback_factor != 0.0) {
            errs.push(format!("{k}: shape.feedback_factor must be a non-zero number, got {}", self.feedback_factor));
        }
        if self.identity_subs > 4 {
            errs.push(format!("{k}: shape.identity_subs must be 0…4, got {}", self.identity_subs));
        }
        if self.sync_producer && !(100..=1_000_000).contains(&self.sync_period_us) {
            errs.push(format!("{k}: shape.sync_period_us must be 100…1000000, got {}", self.sync_period_us));
        }
    }
}

/// How a Modbus drive differs from the plain emulated one, imitating drives cncgw's authors
/// did not write (issue 22): `[drive.modbus_quirks]` in a sim-drives config, all off by
/// default (`ModbusQuirks::realistic()` switches the ones a vendor's drive typically has on).
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModbusQuirks {
    /// 0x607A written at any time is the drive's target: entering Operation Enabled in CSP it
    /// goes to whatever the register holds (the plain drive takes only targets written while
    /// enabled, which hides a master that enables with a stale target).
    pub latch_any_time: bool,
    /// The motor's position at power-on, counts (an absolute encoder away from 0).
    pub power_up_counts: i64,
    /// Every Nth request to this unit is answered with exception 0x06 (server device busy)
    /// and not executed; 0 = never.
    pub busy_every: u32,
    /// After this many requests every request is answered with exception 0x04 (server
    /// device failure) and not executed: a drive that breaks while running; 0 = never.
    pub refuse_after: u32,
    /// After this many requests every request is answered `late_ms` late (a drive whose
    /// answers slow down while running); 0 = never.
    pub late_after: u32,
    /// Every Nth request is answered `late_ms` late; 0 = never.
    pub late_every: u32,
    pub late_ms: u32,
    /// The first N requests (start-up) are answered `slow_first_ms` late.
    pub slow_first: u32,
    pub slow_first_ms: u32,
    /// The drive interpolates only over whole multiples of this many ms: a written
    /// interpolation period is rounded up to one (and reads back so); 0 = any.
    pub interpolation_grid_ms: u16,
}

impl ModbusQuirks {
    /// What a drive built from cncgw's docs by someone else did (issue 22): latches targets
    /// at any time, powers up away from 0.
    pub fn realistic(power_up_counts: i64) -> ModbusQuirks {
        ModbusQuirks { latch_any_time: true, power_up_counts, ..ModbusQuirks::default() }
    }

    fn to_toml(&self) -> String {
        format!(
            "[drive.modbus_quirks]\nlatch_any_time = {}\npower_up_counts = {}\nbusy_every = {}\nrefuse_after = {}\nlate_after = {}\nlate_every = {}\nlate_ms = {}\nslow_first = {}\nslow_first_ms = {}\ninterpolation_grid_ms = {}\n",
            self.latch_any_time,
            self.power_up_counts,
            self.busy_every,
            self.refuse_after,
            self.late_after,
            self.late_every,
            self.late_ms,
            self.slow_first,
            self.slow_first_ms,
            self.interpolation_grid_ms
        )
    }
}

/// The drive's emulated limit switches, home switch and index pulse as it powers on
/// (`profile::SIM_SWITCHES`, 0x2101; physical counts, the power-on coordinate; absent: not
/// fitted). The switches show in 0x60FD bits 0/1 — over CANopen, and over Modbus in the
/// CiA 402 map's `digital_inputs` — and homing methods 1–30 use them.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct Switches {
    /// Negative limit switch: active at or below this position.
    pub negative: Option<i32>,
    /// Positive limit switch: active at or above.
    pub positive: Option<i32>,
    /// Home switch: active at or above.
    pub home: Option<i32>,
    /// Counts between index pulses (default 10 000).
    pub index_period: Option<u32>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DriveConfig {
    pub node: u8,
    pub kind: DriveKind,
    /// Axis name (from the machine config), for logs.
    pub axis: String,
    /// 0x1008 manufacturer device name.
    pub device_name: String,
    /// 0x1018 identity.
    pub vendor_id: u32,
    pub product_code: u32,
    pub revision: u32,
    pub serial: u32,
    /// Encoder counts per motor revolution (the position unit of every 402 object).
    pub counts_per_rev: u32,
    /// Counts per machine unit (mm or degree), for defaults in machine units.
    pub counts_per_unit: f64,
    /// Time from power-on (or reset) to the boot-up message, ms.
    pub boot_delay_ms: f64,
    /// 0x6065 default, counts.
    pub following_error_window: u32,
    /// 0x6066 default, ms.
    pub following_error_timeout_ms: u16,
    /// 0x6085 quick-stop deceleration default, counts/s².
    pub quick_stop_decel: u32,
    /// 0x6084 profile deceleration default (halt, slow-down ramp), counts/s².
    pub profile_decel: u32,
    pub physics: Physics,
    /// Register map served over Modbus (`sim-drives --modbus-tcp/--modbus-rtu`); the unit
    /// id is `node`.
    pub modbus_profile: Profile,
    /// Addresses of the CiA 402 profile (`[drive.cia402_map]`, any subset of keys).
    pub cia402_map: Cia402Map,
    /// Addresses of the PR profile (`[drive.pr_map]`).
    pub pr_map: PrMap,
    /// The machine config's `modbus = "LINK"` of this axis: the drive is on that Modbus link,
    /// not on CANopen (`None`: CANopen, or a sim-drives config that does not say).
    pub modbus_link: Option<String>,
    /// SYNC periods the drive goes on along its last set-point increment when a SYNC comes
    /// late, before it holds (0: it holds its target at once, as many real drives do).
    pub late_sync_extrapolation: u32,
    /// How the drive differs from the plain emulated one (`[drive.shape]`).
    pub shape: Shape,
    /// How its Modbus server differs from the plain one (`[drive.modbus_quirks]`).
    pub modbus_quirks: ModbusQuirks,
    /// Its switches (`[drive.switches]`; in a machine config `[axes.NAME.emulate.switches]`).
    pub switches: Switches,
}

/// sim-drives' own default of `late_sync_extrapolation` (its configuration format): 10
/// periods, as interpolating drives bridge a late SYNC.
pub const LATE_SYNC_EXTRAPOLATION: u32 = 10;

impl DriveConfig {
    /// Defaults for one node of `kind` with `counts_per_unit` counts per mm (linear) or per
    /// degree (spindle).
    pub fn new(node: u8, kind: DriveKind, axis: &str, counts_per_unit: f64) -> DriveConfig {
        let (counts_per_rev, window_units, qs_units_s2, prof_units_s2, product, name) = match kind {
            // Window 1 mm; quick stop 5 m/s², profile 2 m/s².
            DriveKind::Linear => (counts_per_unit * DEFAULT_SCREW_LEAD_MM, 1.0, 5000.0, 2000.0, 0x0402_0001, "SIM-SERVO"),
            // Window 10°; quick stop 50 rev/s², profile 20 rev/s².
            DriveKind::Spindle => (counts_per_unit * 360.0, 10.0, 50.0 * 360.0, 20.0 * 360.0, 0x0402_0002, "SIM-SPINDLE"),
        };
        let clamp_u32 = |x: f64| x.round().clamp(1.0, u32::MAX as f64) as u32;
        DriveConfig {
            node,
            kind,
            axis: axis.to_string(),
            device_name: format!("{name} {}", axis.to_uppercase()),
            vendor_id: 0x0000_0CA7,
            product_code: product,
            revision: 0x0001_0003,
            serial: 0x5100_0000 + node as u32,
            counts_per_rev: clamp_u32(counts_per_rev),
            counts_per_unit,
            // Nodes come up a little apart, as real ones do.
            boot_delay_ms: 1.0 + node as f64 * 0.5,
            following_error_window: clamp_u32(window_units * counts_per_unit),
            following_error_timeout_ms: 10,
            quick_stop_decel: clamp_u32(qs_units_s2 * counts_per_unit),
            profile_decel: clamp_u32(prof_units_s2 * counts_per_unit),
            physics: Physics::default_for(kind),
            modbus_profile: Profile::Cia402,
            cia402_map: Cia402Map::default(),
            pr_map: PrMap::default(),
            modbus_link: None,
            late_sync_extrapolation: LATE_SYNC_EXTRAPOLATION,
            shape: Shape::default(),
            modbus_quirks: ModbusQuirks::default(),
            switches: Switches::default(),
        }
    }

    /// 0x6092:1 as the drive powers on (see `Shape::feed_constant`).
    pub fn feed_constant(&self) -> u32 {
        match self.shape.feed_constant {
            0 => (self.counts_per_rev as u64 * self.shape.gear_ratio[1] as u64 / self.shape.gear_ratio[0].max(1) as u64).clamp(1, u32::MAX as u64)
                as u32,
            f => f,
        }
    }

    /// Encoder increments per position unit of the factor group at power-on (1 = positions in
    /// increments).
    pub fn increments_per_unit(&self) -> f64 {
        let [motor, shaft] = self.shape.gear_ratio;
        self.counts_per_rev as f64 * motor as f64 / shaft.max(1) as f64 / self.feed_constant() as f64
    }
}

impl DriveConfig {
    /// The Modbus registers of this drive's profile: (name, first address, registers).
    pub fn modbus_registers(&self) -> Vec<(&'static str, u16, u16)> {
        // Optional registers set to "none" are not served (reads and writes of them are
        // answered 0x02, as a drive without them does).
        let regs = match self.modbus_profile {
            Profile::Cia402 => self.cia402_map.registers(),
            Profile::Pr => self.pr_map.registers(),
        };
        regs.into_iter().map(|r| (r.name, r.addr, r.len)).collect()
    }

    /// The served map must not overlap itself nor run past register 65535.
    fn check_modbus_map(&self) -> Result<(), String> {
        let map = if self.modbus_profile == Profile::Cia402 { "cia402_map" } else { "pr_map" };
        let mut regs = self.modbus_registers();
        regs.sort_by_key(|r| r.1);
        for r in &regs {
            if r.1 as u32 + r.2 as u32 > 0x1_0000 {
                return Err(format!("{map}.{} = {}: its {} registers run past address 65535", r.0, r.1, r.2));
            }
        }
        for w in regs.windows(2) {
            if w[0].1 as u32 + w[0].2 as u32 > w[1].1 as u32 {
                return Err(format!(
                    "{map}.{} = {} overlaps {map}.{} = {} ({} registers): give each its own addresses",
                    w[1].0, w[1].1, w[0].0, w[0].1, w[0].2
                ));
            }
        }
        Ok(())
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct SimConfig {
    pub drives: Vec<DriveConfig>,
    /// Control/physics step, µs (≤ 100). Control loops run at this rate.
    pub step_us: u32,
}

impl SimConfig {
    /// The drives of a cncgw machine config: its `[axes.*]` tables (kind, node,
    /// counts_per_unit; other keys ignored), with default physics per kind.
    pub fn from_machine_toml(text: &str) -> Result<SimConfig, String> {
        Self::from_machine_toml_all(text)
    }

    /// The drives of a cncgw machine config on one bus: `Some(false)` its CANopen axes,
    /// `Some(true)` its Modbus axes (every link), `None` the CANopen axes, or the Modbus
    /// ones if it has no CANopen axis.
    pub fn from_machine_toml_bus(text: &str, modbus: Option<bool>) -> Result<SimConfig, String> {
        let all = Self::from_machine_toml_all(text)?;
        let has_can = all.drives.iter().any(|d| d.modbus_link.is_none());
        if modbus.unwrap_or(!has_can) {
            all.modbus_drives(None)
        } else {
            Ok(all.canopen_drives())
        }
    }

    /// Every drive of a cncgw machine config, each with its Modbus link if it has one.
    fn from_machine_toml_all(text: &str) -> Result<SimConfig, String> {
        #[derive(Deserialize)]
        struct Axis {
            kind: DriveKind,
            node: u8,
            counts_per_unit: f64,
            // A drive on Modbus: the link, and the same keys as in a sim-drives [[drive]].
            modbus: Option<String>,
            modbus_profile: Option<Profile>,
            cia402_map: Option<Cia402Map>,
            pr_map: Option<PrMap>,
            // The drive behaves as the machine says it does (absent: it holds, as cncgw
            // assumes).
            #[serde(default)]
            late_sync_extrapolation: u32,
            // How sim-drives emulates the drive's surroundings (cncgw ignores it).
            emulate: Option<AxisEmulate>,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct AxisEmulate {
            #[serde(default)]
            switches: Switches,
        }
        #[derive(Deserialize)]
        struct Machine {
            #[serde(default)]
            axes: BTreeMap<String, Axis>,
        }
        // Parse only what we need: other tables and keys are the master's business.
        let m: Machine = toml::from_str(text).map_err(|e| format!("machine config: {e}"))?;
        let mut drives = Vec::new();
        for (name, a) in &m.axes {
            let mut d = DriveConfig::new(a.node, a.kind, name, a.counts_per_unit);
            d.modbus_profile = a.modbus_profile.unwrap_or_default();
            d.cia402_map = a.cia402_map.unwrap_or_default();
            d.pr_map = a.pr_map.unwrap_or_default();
            d.modbus_link = a.modbus.clone();
            d.late_sync_extrapolation = a.late_sync_extrapolation;
            d.switches = a.emulate.as_ref().map(|e| e.switches).unwrap_or_default();
            drives.push(d);
        }
        let cfg = SimConfig { drives, step_us: 50 };
        cfg.validate()?;
        Ok(cfg)
    }

    /// The drives on the CANopen bus: those without a Modbus link.
    pub fn canopen_drives(&self) -> SimConfig {
        SimConfig { drives: self.drives.iter().filter(|d| d.modbus_link.is_none()).cloned().collect(), step_us: self.step_us }
    }

    /// The drives a Modbus server serves: those on `link`; without a link name, every drive
    /// on some Modbus link — or all drives when none names a link (a sim-drives config, or a
    /// CANopen machine served over Modbus as it is). Err: no drive on that link.
    pub fn modbus_drives(&self, link: Option<&str>) -> Result<SimConfig, String> {
        let any_link = self.drives.iter().any(|d| d.modbus_link.is_some());
        let drives: Vec<DriveConfig> = self
            .drives
            .iter()
            .filter(|d| match link {
                Some(l) => d.modbus_link.as_deref() == Some(l),
                None => !any_link || d.modbus_link.is_some(),
            })
            .cloned()
            .collect();
        if let Some(l) = link {
            if drives.is_empty() {
                let mut links: Vec<&str> = self.drives.iter().filter_map(|d| d.modbus_link.as_deref()).collect();
                links.sort();
                links.dedup();
                return Err(format!(
                    "no drive is on Modbus link {l:?} (links in the config: {})",
                    if links.is_empty() { "none".into() } else { links.join(", ") }
                ));
            }
        }
        Ok(SimConfig { drives, step_us: self.step_us })
    }

    /// A sim-drives config (what `--print-default-config` prints) or a cncgw machine config
    /// (its `[axes.*]`), from a file.
    pub fn from_file(path: &std::path::Path) -> Result<SimConfig, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
        // A machine config has [axes.*]; a sim-drives config has [[drive]].
        let is_machine = text.lines().any(|l| l.trim_start().starts_with("[axes."));
        let r = if is_machine { SimConfig::from_machine_toml(&text) } else { SimConfig::from_toml(&text) };
        r.map_err(|e| format!("{}: {e}", path.display()))
    }

    /// The drives of the default machine (config/lathe.toml).
    pub fn default_lathe() -> SimConfig {
        // The embedded file is checked by a test; fall back to an empty bus rather than panic.
        SimConfig::from_machine_toml(LATHE_TOML).unwrap_or(SimConfig { drives: Vec::new(), step_us: 50 })
    }

    /// Parse a sim-drives TOML file (the format `--print-default-config` prints).
    pub fn from_toml(text: &str) -> Result<SimConfig, String> {
        let raw: RawSim = toml::from_str(text).map_err(|e| format!("sim-drives config: {e}"))?;
        let mut drives = Vec::new();
        for (i, d) in raw.drive.iter().enumerate() {
            let cpu = d.counts_per_unit.unwrap_or(match d.kind {
                DriveKind::Linear => 10000.0,
                DriveKind::Spindle => 1000.0,
            });
            let axis = d.axis.clone().unwrap_or_else(|| format!("n{}", d.node));
            let mut c = DriveConfig::new(d.node, d.kind, &axis, cpu);
            macro_rules! set {
                ($field:ident) => {
                    if let Some(v) = d.$field.clone() {
                        c.$field = v;
                    }
                };
            }
            set!(device_name);
            set!(vendor_id);
            set!(product_code);
            set!(revision);
            set!(serial);
            set!(counts_per_rev);
            set!(boot_delay_ms);
            set!(following_error_window);
            set!(following_error_timeout_ms);
            set!(quick_stop_decel);
            set!(profile_decel);
            set!(modbus_profile);
            set!(cia402_map);
            set!(pr_map);
            set!(modbus_quirks);
            set!(switches);
            if d.modbus_link.is_some() {
                c.modbus_link = d.modbus_link.clone();
            }
            if let Some(n) = d.late_sync_extrapolation {
                c.late_sync_extrapolation = n;
            }
            if let Some(p) = &d.physics {
                let q = &mut c.physics;
                macro_rules! setp {
                    ($field:ident) => {
                        if let Some(v) = p.$field {
                            q.$field = v;
                        }
                    };
                }
                setp!(motor_inertia);
                setp!(load_inertia);
                setp!(torque_limit);
                setp!(coulomb_friction);
                setp!(viscous_friction);
                setp!(kv);
                setp!(velocity_ff);
                setp!(vel_kp);
                setp!(vel_ti_ms);
                setp!(max_speed_rpm);
                setp!(current_loop_tc_ms);
                setp!(speed_encoder_bits);
                setp!(speed_filter_ms);
                let e = &mut c.physics.extra;
                if let Some(v) = p.transport_delay_cycles {
                    e.transport_delay_cycles = v;
                }
                if let Some(v) = p.encoder_counts_per_rev {
                    e.encoder_counts_per_rev = v;
                }
                if let Some(v) = p.load_stiffness {
                    e.load_stiffness = v;
                }
                if let Some(v) = p.load_damping {
                    e.load_damping = v;
                }
                if let Some(v) = p.backlash_deg {
                    e.backlash_deg = v;
                }
            }
            if let Some(name) = &d.profile {
                c.shape = Shape::profile(name).ok_or_else(|| {
                    format!("sim-drives config: drive node {}: profile = {name:?}: unknown; one of {}", d.node, Shape::PROFILES.join(", "))
                })?;
            }
            if let Some(sh) = &d.shape {
                let q = &mut c.shape;
                macro_rules! sets {
                    ($field:ident) => {
                        if let Some(v) = sh.$field.clone() {
                            q.$field = v;
                        }
                    };
                }
                sets!(boot_mode);
                sets!(mode_switch_ms);
                sets!(mode_switch_syncs);
                sets!(modes);
                sets!(supported_modes_object);
                sets!(factor_group);
                sets!(feed_constant);
                sets!(gear_ratio);
                sets!(polarity);
                sets!(feedback_factor);
                sets!(sync_producer);
                sets!(sync_period_us);
                sets!(heartbeat_consumer);
                sets!(node_guarding);
                sets!(abort_connection_object);
                sets!(error_behaviour_object);
                sets!(mode_display_pdo);
                sets!(fixed_pdo);
                sets!(optional_402_objects);
                sets!(identity_subs);
            }
            let _ = i;
            drives.push(c);
        }
        let cfg = SimConfig { drives, step_us: raw.step_us.unwrap_or(50) };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Every problem, each naming the key and what is allowed.
    pub fn validate(&self) -> Result<(), String> {
        let mut errs = Vec::new();
        if self.step_us == 0 || self.step_us > 100 {
            errs.push(format!("step_us: must be 1…100, got {}", self.step_us));
        }
        // Ids are unique per bus: the CANopen bus, and each Modbus link.
        let mut seen = std::collections::BTreeSet::new();
        for d in &self.drives {
            let k = format!("drive node {}", d.node);
            match &d.modbus_link {
                None if d.node == 0 || d.node > 127 => errs.push(format!("{k}: node must be 1…127")),
                Some(l) if d.node == 0 || d.node > 247 => errs.push(format!("{k}: unit id on Modbus link {l:?} must be 1…247")),
                _ => {}
            }
            if !seen.insert((d.modbus_link.clone(), d.node)) {
                errs.push(match &d.modbus_link {
                    None => format!("{k}: node id used twice"),
                    Some(l) => format!("{k}: unit id used twice on Modbus link {l:?}"),
                });
            }
            if !(d.counts_per_unit.is_finite() && d.counts_per_unit > 0.0) {
                errs.push(format!("{k}: counts_per_unit must be > 0, got {}", d.counts_per_unit));
            }
            if d.counts_per_rev == 0 {
                errs.push(format!("{k}: counts_per_rev must be > 0"));
            }
            if !(d.boot_delay_ms.is_finite() && (0.0..=10_000.0).contains(&d.boot_delay_ms)) {
                errs.push(format!("{k}: boot_delay_ms must be 0…10000, got {}", d.boot_delay_ms));
            }
            if d.device_name.len() > 64 {
                errs.push(format!("{k}: device_name longer than 64 bytes"));
            }
            let p = &d.physics;
            let positive = [
                ("motor_inertia", p.motor_inertia),
                ("torque_limit", p.torque_limit),
                ("kv", p.kv),
                ("vel_kp", p.vel_kp),
                ("vel_ti_ms", p.vel_ti_ms),
                ("max_speed_rpm", p.max_speed_rpm),
            ];
            for (n, v) in positive {
                if !(v.is_finite() && v > 0.0) {
                    errs.push(format!("{k}: physics.{n} must be > 0, got {v}"));
                }
            }
            let non_negative = [
                ("load_inertia", p.load_inertia),
                ("coulomb_friction", p.coulomb_friction),
                ("viscous_friction", p.viscous_friction),
                ("current_loop_tc_ms", p.current_loop_tc_ms),
                ("speed_filter_ms", p.speed_filter_ms),
            ];
            for (n, v) in non_negative {
                if !(v.is_finite() && v >= 0.0) {
                    errs.push(format!("{k}: physics.{n} must be ≥ 0, got {v}"));
                }
            }
            if !(p.velocity_ff.is_finite() && (0.0..=1.5).contains(&p.velocity_ff)) {
                errs.push(format!("{k}: physics.velocity_ff must be 0…1.5, got {}", p.velocity_ff));
            }
            if !(8..=32).contains(&p.speed_encoder_bits) {
                errs.push(format!("{k}: physics.speed_encoder_bits must be 8…32, got {}", p.speed_encoder_bits));
            }
            let x = p.extra;
            for (n, v) in [("load_stiffness", x.load_stiffness), ("load_damping", x.load_damping), ("backlash_deg", x.backlash_deg)] {
                if !(v.is_finite() && v >= 0.0) {
                    errs.push(format!("{k}: physics.{n} must be ≥ 0, got {v}"));
                }
            }
            if x.transport_delay_cycles > 8 {
                errs.push(format!("{k}: physics.transport_delay_cycles must be 0…8, got {}", x.transport_delay_cycles));
            }
            if x.encoder_counts_per_rev > d.counts_per_rev {
                errs.push(format!(
                    "{k}: physics.encoder_counts_per_rev ({}) must not be finer than counts_per_rev ({})",
                    x.encoder_counts_per_rev, d.counts_per_rev
                ));
            }
            if x.load_stiffness > 0.0 && p.load_inertia <= 0.0 {
                errs.push(format!("{k}: physics.load_stiffness needs a load_inertia > 0 behind it"));
            }
            if p.coulomb_friction >= p.torque_limit {
                errs.push(format!("{k}: physics.coulomb_friction must be below torque_limit (the motor could never move)"));
            }
            if let Err(e) = d.check_modbus_map() {
                errs.push(format!("{k}: {e}"));
            }
            d.shape.check(&k, &mut errs);
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(errs.join("\n"))
        }
    }

    /// A commented TOML that `from_toml` reads back to this configuration.
    pub fn to_commented_toml(&self) -> String {
        let mut s = String::new();
        s.push_str("# sim-drives configuration: emulated CiA 402 amplifiers on CANopen.\n");
        s.push_str("# Position units are encoder counts of the motor; times in ms unless named.\n");
        s.push_str("# Any key of a [[drive]] or [drive.physics] may be left out: it then takes the\n");
        s.push_str("# default for the drive's kind (linear: feed servo on a 10 mm ball screw;\n");
        s.push_str("# spindle: heavy spindle motor with a softer position loop).\n");
        s.push_str("# [drive.shape] imitates commercial drives (all keys optional; the plain drive when absent):\n");
        s.push_str("#   boot_mode = 1            # 0x6061 at power-on (1 = profile position)\n");
        s.push_str("#   mode_switch_ms = 300.0   # a new 0x6060 shows in 0x6061 only after this long…\n");
        s.push_str("#   mode_switch_syncs = 50   # …and this many SYNCs\n");
        s.push_str("#   modes = [1, 6, 8, 9]     # modes 0x6060 accepts and 0x6502 lists (1 PP, 6 homing, 7 IP, 8 CSP, 9 CSV)\n");
        s.push_str("#   supported_modes_object = false  # no 0x6502\n");
        s.push_str("#   factor_group = false     # no 0x608F/0x6091/0x6092/0x607E\n");
        s.push_str("#   feed_constant = 10000    # 0x6092:1 position units per shaft rev (0: increments); 10000 on a 10 mm screw = 1 µm\n");
        s.push_str("#   gear_ratio = [1, 1]      # 0x6091 motor revs : shaft revs\n");
        s.push_str("#   polarity = 0x80          # 0x607E (bit 7 inverts positions, bit 6 velocities)\n");
        s.push_str("#   feedback_factor = 10.0   # 0x6064 reports this × the position in 0x607A's units (a hidden scaling)\n");
        s.push_str("#   sync_producer = true     # produces SYNC itself (0x1005 bit 30) every sync_period_us (0x1006)\n");
        s.push_str("#   sync_period_us = 2000\n");
        s.push_str("#   heartbeat_consumer = false  # no 0x1016\n");
        s.push_str("#   node_guarding = false    # no 0x100C/0x100D (no answers to guarding requests)\n");
        s.push_str("#   abort_connection_object = false  # no 0x6007 (a lost master faults the drive)\n");
        s.push_str("#   error_behaviour_object = false  # no 0x1029 (a communication error leaves the NMT state as it is)\n");
        s.push_str("#   mode_display_pdo = false # 0x6061 cannot be mapped into a PDO\n");
        s.push_str("#   fixed_pdo = true         # PDO mapping read-only (RPDO1 controlword + 0x607A, TPDO1 statusword + 0x6064)\n");
        s.push_str("#   optional_402_objects = false  # no 0x605A/0x605B/0x605C/0x605E/0x607D/0x6072\n");
        s.push_str("#   identity_subs = 0        # 0x1018 sub-indices present (4 = vendor…serial; 0: a vendor-id read aborts)\n");
        s.push_str("# profile = \"ip-only\" | \"pp-boot\" | \"no-1016\" | \"fixed-pdo\" | \"user-units\" in a [[drive]] starts from that shape\n");
        s.push_str("# (IP but no CSP; boots in PP, switches 200 SYNCs late; no 0x1016; fixed PDO map; 10000 units/rev); [drive.shape] keys change it further.\n\n");
        s.push_str(&format!("step_us = {}                 # control loop / physics step, µs (≤ 100)\n", self.step_us));
        for d in &self.drives {
            let p = &d.physics;
            s.push_str("\n[[drive]]\n");
            s.push_str(&format!("node = {}\n", d.node));
            s.push_str(&format!("kind = \"{}\"            # linear | spindle\n", d.kind.name()));
            s.push_str(&format!("axis = \"{}\"\n", d.axis));
            s.push_str(&format!("counts_per_unit = {:?}  # counts per mm (linear) or per degree (spindle)\n", d.counts_per_unit));
            s.push_str(&format!("counts_per_rev = {}      # encoder counts per motor revolution\n", d.counts_per_rev));
            s.push_str(&format!("device_name = \"{}\"     # 0x1008\n", d.device_name));
            s.push_str(&format!("vendor_id = 0x{:08X}        # 0x1018 sub 1\n", d.vendor_id));
            s.push_str(&format!("product_code = 0x{:08X}     # 0x1018 sub 2\n", d.product_code));
            s.push_str(&format!("revision = 0x{:08X}         # 0x1018 sub 3\n", d.revision));
            s.push_str(&format!("serial = 0x{:08X}           # 0x1018 sub 4\n", d.serial));
            s.push_str(&format!("boot_delay_ms = {:?}         # power-on/reset to boot-up message\n", d.boot_delay_ms));
            s.push_str(&format!("following_error_window = {}   # 0x6065, counts\n", d.following_error_window));
            s.push_str(&format!("following_error_timeout_ms = {}  # 0x6066\n", d.following_error_timeout_ms));
            s.push_str(&format!("quick_stop_decel = {}   # 0x6085, counts/s²\n", d.quick_stop_decel));
            s.push_str(&format!("profile_decel = {}      # 0x6084, counts/s² (halt, slow-down ramp)\n", d.profile_decel));
            let profile = match d.modbus_profile {
                Profile::Cia402 => "cia402",
                Profile::Pr => "pr",
            };
            s.push_str(&format!("modbus_profile = \"{profile}\"  # cia402 | pr (register map over Modbus; unit id = node)\n"));
            if let Some(l) = &d.modbus_link {
                s.push_str(&format!("modbus_link = \"{l}\"     # the machine's Modbus link this drive is on\n"));
            }
            s.push_str(&format!(
                "late_sync_extrapolation = {}   # SYNC periods it goes on over a late SYNC before it holds (0: holds at once)\n",
                d.late_sync_extrapolation
            ));
            s.push_str("# Register addresses: [drive.cia402_map] / [drive.pr_map] (keys as in cncgw-bus' Cia402Map / PrMap)\n");
            if d.shape != Shape::default() {
                let h = &d.shape;
                let modes: Vec<String> = h.modes.iter().map(|m| m.to_string()).collect();
                s.push_str("[drive.shape]\n");
                s.push_str(&format!(
                    "boot_mode = {}\nmode_switch_ms = {:?}\nmode_switch_syncs = {}\nmodes = [{}]\n",
                    h.boot_mode,
                    h.mode_switch_ms,
                    h.mode_switch_syncs,
                    modes.join(", ")
                ));
                s.push_str(&format!(
                    "supported_modes_object = {}\nfactor_group = {}\nfeed_constant = {}\n",
                    h.supported_modes_object, h.factor_group, h.feed_constant
                ));
                s.push_str(&format!(
                    "gear_ratio = [{}, {}]\npolarity = 0x{:02X}\nfeedback_factor = {:?}\n",
                    h.gear_ratio[0], h.gear_ratio[1], h.polarity, h.feedback_factor
                ));
                s.push_str(&format!(
                    "sync_producer = {}\nsync_period_us = {}\nheartbeat_consumer = {}\n",
                    h.sync_producer, h.sync_period_us, h.heartbeat_consumer
                ));
                s.push_str(&format!(
                    "node_guarding = {}\nabort_connection_object = {}\nerror_behaviour_object = {}\n",
                    h.node_guarding, h.abort_connection_object, h.error_behaviour_object
                ));
                s.push_str(&format!(
                    "mode_display_pdo = {}\nfixed_pdo = {}\noptional_402_objects = {}\nidentity_subs = {}\n",
                    h.mode_display_pdo, h.fixed_pdo, h.optional_402_objects, h.identity_subs
                ));
            }
            if d.modbus_quirks != ModbusQuirks::default() {
                s.push_str(&d.modbus_quirks.to_toml());
            }
            if d.switches != Switches::default() {
                let w = &d.switches;
                s.push_str("[drive.switches]\n");
                for (k, v) in [
                    ("negative", w.negative.map(i64::from)),
                    ("positive", w.positive.map(i64::from)),
                    ("home", w.home.map(i64::from)),
                    ("index_period", w.index_period.map(i64::from)),
                ] {
                    if let Some(v) = v {
                        s.push_str(&format!("{k} = {v}\n"));
                    }
                }
            }
            s.push_str("[drive.physics]\n");
            s.push_str(&format!("motor_inertia = {:?}     # kg·m²\n", p.motor_inertia));
            s.push_str(&format!("load_inertia = {:?}      # kg·m², reflected to the motor\n", p.load_inertia));
            s.push_str(&format!("torque_limit = {:?}      # N·m, peak\n", p.torque_limit));
            s.push_str(&format!("coulomb_friction = {:?}  # N·m\n", p.coulomb_friction));
            s.push_str(&format!("viscous_friction = {:?}  # N·m per rad/s\n", p.viscous_friction));
            s.push_str(&format!("kv = {:?}                # position loop gain, 1/s\n", p.kv));
            s.push_str(&format!("velocity_ff = {:?}       # velocity feed-forward, 1.0 = 100 %\n", p.velocity_ff));
            s.push_str(&format!("vel_kp = {:?}            # velocity loop P, N·m per rad/s\n", p.vel_kp));
            s.push_str(&format!("vel_ti_ms = {:?}         # velocity loop integral time\n", p.vel_ti_ms));
            s.push_str(&format!("max_speed_rpm = {:?}\n", p.max_speed_rpm));
            s.push_str(&format!("current_loop_tc_ms = {:?}  # torque lag behind its command\n", p.current_loop_tc_ms));
            s.push_str(&format!("speed_encoder_bits = {}     # motor encoder the speed is estimated from\n", p.speed_encoder_bits));
            s.push_str(&format!("speed_filter_ms = {:?}     # speed estimate low-pass\n", p.speed_filter_ms));
            let x = p.extra;
            s.push_str(&format!("transport_delay_cycles = {}  # SYNCs a set-point waits in the drive (0 = off)\n", x.transport_delay_cycles));
            s.push_str(&format!("encoder_counts_per_rev = {}  # coarser position encoder, lines × 4 per rev (0 = off)\n", x.encoder_counts_per_rev));
            s.push_str(&format!("load_stiffness = {:?}        # motor–load compliance, N·m/rad (0 = rigid)\n", x.load_stiffness));
            s.push_str(&format!("load_damping = {:?}          # its damping, N·m·s/rad\n", x.load_damping));
            s.push_str(&format!("backlash_deg = {:?}          # lost motion motor–load, motor degrees (0 = none)\n", x.backlash_deg));
            // Register maps only where they differ from the built-in ones.
            let order = |o: WordOrder| match o {
                WordOrder::HighFirst => "high_first",
                WordOrder::LowFirst => "low_first",
            };
            if d.cia402_map != Cia402Map::default() {
                let m = &d.cia402_map;
                s.push_str("[drive.cia402_map]\n");
                for (k, v) in [
                    ("controlword", Some(m.controlword)),
                    ("target_position", Some(m.target_position)),
                    ("target_velocity", Some(m.target_velocity)),
                    ("mode", Some(m.mode)),
                    ("statusword", Some(m.statusword)),
                    ("mode_display", Some(m.mode_display)),
                    ("position_actual", Some(m.position_actual)),
                    ("velocity_actual", Some(m.velocity_actual)),
                    ("error_code", m.error_code),
                    ("interpolation_ms", m.interpolation_ms),
                    ("following_error_window", Some(m.following_error_window)),
                    ("comm_timeout_ms", m.comm_timeout_ms),
                    ("homing_method", m.homing_method),
                    ("home_offset", m.home_offset),
                    ("homing_switch_speed", m.homing_switch_speed),
                    ("homing_zero_speed", m.homing_zero_speed),
                    ("homing_accel", m.homing_accel),
                    ("digital_inputs", m.digital_inputs),
                ] {
                    s.push_str(&format!("{k} = {}\n", v.map_or("\"none\"".to_string(), |v| v.to_string())));
                }
                s.push_str(&format!("word_order = \"{}\"\nreads = \"{}\"\n", order(m.word_order), m.reads.name()));
            }
            if d.pr_map != PrMap::default() {
                let m = &d.pr_map;
                s.push_str("[drive.pr_map]\n");
                for (k, v) in [
                    ("block", Some(m.block)),
                    ("trigger", Some(m.trigger)),
                    ("trigger_value", Some(m.trigger_value)),
                    ("servo_on", Some(m.servo_on)),
                    ("status", Some(m.status)),
                    ("position_actual", Some(m.position_actual)),
                    ("alarm_code", m.alarm_code),
                    ("alarm_reset", Some(m.alarm_reset)),
                    ("comm_timeout_ms", m.comm_timeout_ms),
                ] {
                    s.push_str(&format!("{k} = {}\n", v.map_or("\"none\"".to_string(), |v| format!("0x{v:04X}"))));
                }
                s.push_str(&format!("counts_per_rev = {}\n", m.counts_per_rev));
                s.push_str(&format!("word_order = \"{}\"\nreads = \"{}\"\n", order(m.word_order), m.reads.name()));
            }
        }
        s
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSim {
    step_us: Option<u32>,
    #[serde(default)]
    drive: Vec<RawDrive>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDrive {
    node: u8,
    kind: DriveKind,
    axis: Option<String>,
    counts_per_unit: Option<f64>,
    counts_per_rev: Option<u32>,
    device_name: Option<String>,
    vendor_id: Option<u32>,
    product_code: Option<u32>,
    revision: Option<u32>,
    serial: Option<u32>,
    boot_delay_ms: Option<f64>,
    following_error_window: Option<u32>,
    following_error_timeout_ms: Option<u16>,
    quick_stop_decel: Option<u32>,
    profile_decel: Option<u32>,
    physics: Option<RawPhysics>,
    modbus_profile: Option<Profile>,
    cia402_map: Option<Cia402Map>,
    pr_map: Option<PrMap>,
    modbus_link: Option<String>,
    late_sync_extrapolation: Option<u32>,
    shape: Option<RawShape>,
    /// A named shape (`Shape::profile`), before `shape`'s keys.
    profile: Option<String>,
    modbus_quirks: Option<ModbusQuirks>,
    switches: Option<Switches>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawShape {
    boot_mode: Option<i8>,
    mode_switch_ms: Option<f64>,
    mode_switch_syncs: Option<u32>,
    modes: Option<Vec<i8>>,
    supported_modes_object: Option<bool>,
    factor_group: Option<bool>,
    feed_constant: Option<u32>,
    gear_ratio: Option<[u32; 2]>,
    polarity: Option<u8>,
    feedback_factor: Option<f64>,
    sync_producer: Option<bool>,
    sync_period_us: Option<u32>,
    heartbeat_consumer: Option<bool>,
    node_guarding: Option<bool>,
    abort_connection_object: Option<bool>,
    error_behaviour_object: Option<bool>,
    mode_display_pdo: Option<bool>,
    fixed_pdo: Option<bool>,
    optional_402_objects: Option<bool>,
    identity_subs: Option<u8>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPhysics {
    motor_inertia: Option<f64>,
    load_inertia: Option<f64>,
    torque_limit: Option<f64>,
    coulomb_friction: Option<f64>,
    viscous_friction: Option<f64>,
    kv: Option<f64>,
    velocity_ff: Option<f64>,
    vel_kp: Option<f64>,
    vel_ti_ms: Option<f64>,
    max_speed_rpm: Option<f64>,
    current_loop_tc_ms: Option<f64>,
    speed_encoder_bits: Option<u32>,
    speed_filter_ms: Option<f64>,
    transport_delay_cycles: Option<u32>,
    encoder_counts_per_rev: Option<u32>,
    load_stiffness: Option<f64>,
    load_damping: Option<f64>,
    backlash_deg: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_lathe_has_x_z_and_spindle() {
        let c = SimConfig::from_machine_toml(LATHE_TOML).unwrap();
        assert_eq!(c, SimConfig::default_lathe());
        let nodes: Vec<(u8, DriveKind)> = c.drives.iter().map(|d| (d.node, d.kind)).collect();
        assert_eq!(nodes, vec![(3, DriveKind::Spindle), (1, DriveKind::Linear), (2, DriveKind::Linear)]);
        let x = c.drives.iter().find(|d| d.node == 1).unwrap();
        assert_eq!(x.counts_per_rev, 100_000);
        let s = c.drives.iter().find(|d| d.node == 3).unwrap();
        assert_eq!(s.counts_per_rev, 360_000);
        // Mismatched like a real machine: the spindle is much heavier and softer.
        assert!(s.physics.inertia() > 5.0 * x.physics.inertia());
        assert!(s.physics.kv < x.physics.kv);
    }

    #[test]
    fn modbus_quirks_read_back_and_unknown_ones_are_refused() {
        let mut c = SimConfig::default_lathe();
        c.drives[1].modbus_quirks = ModbusQuirks { busy_every: 7, late_every: 300, late_ms: 25, ..ModbusQuirks::realistic(16_000) };
        assert_eq!(SimConfig::from_toml(&c.to_commented_toml()).unwrap(), c);
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.modbus_quirks]\nbusy = 3\n").unwrap_err();
        assert!(e.contains("busy"), "{e}");
    }

    #[test]
    fn printed_default_reads_back_identically() {
        let c = SimConfig::default_lathe();
        let text = c.to_commented_toml();
        assert_eq!(SimConfig::from_toml(&text).unwrap(), c);
    }

    #[test]
    fn bad_configs_are_refused_with_the_key() {
        let e = SimConfig::from_toml("[[drive]]\nnode = 0\nkind = \"linear\"\n").unwrap_err();
        assert!(e.contains("node must be 1…127"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.physics]\nkv = -1.0\n").unwrap_err();
        assert!(e.contains("physics.kv"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"rotary\"\n").unwrap_err();
        assert!(e.contains("sim-drives config"), "{e}");
        let e = SimConfig::from_machine_toml("[axes.x]\nkind = \"linear\"\nnode = 1\n").unwrap_err();
        assert!(e.contains("counts_per_unit"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.cia402_map]\nmode = 2\n").unwrap_err();
        assert!(e.contains("cia402_map.mode = 2 overlaps cia402_map.target_position"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\nmodbus_profile = \"pr\"\n[drive.pr_map]\nblock = 65530\n").unwrap_err();
        assert!(e.contains("pr_map.block = 65530"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\nmodbus_profile = \"rtu\"\n").unwrap_err();
        assert!(e.contains("modbus_profile"), "{e}");
    }

    #[test]
    fn shapes_read_back_and_bad_ones_are_refused() {
        let c = SimConfig::from_toml(
            "[[drive]]\nnode = 1\nkind = \"linear\"\ncounts_per_unit = 10000.0\n[drive.shape]\nboot_mode = 1\nmode_switch_ms = 300.0\nmode_switch_syncs = 20\n\
             feed_constant = 10000\nsync_producer = true\nheartbeat_consumer = false\nmodes = [1, 6]\npolarity = 0x80\n",
        )
        .unwrap();
        let sh = &c.drives[0].shape;
        assert_eq!((sh.boot_mode, sh.mode_switch_syncs, sh.feed_constant, sh.polarity), (1, 20, 10000, 0x80));
        assert!(sh.sync_producer && !sh.heartbeat_consumer && sh.node_guarding);
        assert_eq!(sh.supported_modes_bits(), 0x21);
        // 100000 increments per revolution, 10000 units per revolution: 10 increments per µm.
        assert_eq!(c.drives[0].increments_per_unit(), 10.0);
        assert_eq!(SimConfig::default_lathe().drives[0].increments_per_unit(), 1.0);
        assert_eq!(SimConfig::from_toml(&c.to_commented_toml()).unwrap(), c);
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.shape]\nmodes = [4]\n").unwrap_err();
        assert!(e.contains("shape.modes: mode 4 is not emulated"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.shape]\nfeedback_factor = 0.0\n").unwrap_err();
        assert!(e.contains("shape.feedback_factor"), "{e}");
        let e = SimConfig::from_toml("[[drive]]\nnode = 1\nkind = \"linear\"\n[drive.shape]\nboot_mod = 1\n").unwrap_err();
        assert!(e.contains("boot_mod"), "{e}");
    }

    #[test]
    fn modbus_profile_and_map_overrides() {
        let c = SimConfig::from_toml(
            "[[drive]]\nnode = 4\nkind = \"linear\"\nmodbus_profile = \"pr\"\n[drive.pr_map]\ntrigger = 0x100\nword_order = \"low_first\"\n\
             [[drive]]\nnode = 5\nkind = \"spindle\"\n",
        )
        .unwrap();
        assert_eq!(c.drives[0].modbus_profile, Profile::Pr);
        assert_eq!(c.drives[0].pr_map.trigger, 0x100);
        assert_eq!(c.drives[0].pr_map.block, PrMap::default().block);
        assert_eq!(c.drives[0].pr_map.word_order, cncgw_bus::modbus::WordOrder::LowFirst);
        assert_eq!(c.drives[1].modbus_profile, Profile::Cia402);
        assert_eq!(c.drives[1].cia402_map, Cia402Map::default());
        // A machine config's axes take the same keys.
        let m = SimConfig::from_machine_toml(
            "[axes.w]\nkind = \"linear\"\nnode = 7\ncounts_per_unit = 1000.0\nmodbus_profile = \"pr\"\n[axes.w.pr_map]\nservo_on = 0x100\n",
        )
        .unwrap();
        assert_eq!((m.drives[0].modbus_profile, m.drives[0].pr_map.servo_on), (Profile::Pr, 0x100));
        // A mixed machine: ids are per bus; each server takes its own drives.
        let mixed = SimConfig::from_machine_toml(
            "[axes.x]\nkind = \"linear\"\nnode = 1\ncounts_per_unit = 1000.0\n\
             [axes.w]\nkind = \"linear\"\nnode = 1\ncounts_per_unit = 1000.0\nmodbus = \"line\"\n\
             [axes.t]\nkind = \"linear\"\nnode = 200\ncounts_per_unit = 1000.0\nmodbus = \"tcp\"\n",
        )
        .unwrap();
        let axes = |c: &SimConfig| c.drives.iter().map(|d| d.axis.clone()).collect::<Vec<_>>();
        assert_eq!(axes(&mixed.canopen_drives()), ["x"]);
        assert_eq!(axes(&mixed.modbus_drives(Some("line")).unwrap()), ["w"]);
        assert_eq!(axes(&mixed.modbus_drives(None).unwrap()), ["t", "w"]);
        let e = mixed.modbus_drives(Some("rs485")).unwrap_err();
        assert!(e.contains("links in the config: line, tcp"), "{e}");
        assert_eq!(axes(&SimConfig::default_lathe().modbus_drives(None).unwrap()).len(), 3);
        assert_eq!(SimConfig::from_toml(&mixed.to_commented_toml()).unwrap(), mixed);
        let e = SimConfig::from_machine_toml(
            "[axes.a]\nkind = \"linear\"\nnode = 3\ncounts_per_unit = 1.0\nmodbus = \"l\"\n[axes.b]\nkind = \"linear\"\nnode = 3\ncounts_per_unit = 1.0\nmodbus = \"l\"\n",
        )
        .unwrap_err();
        assert!(e.contains("unit id used twice on Modbus link \"l\""), "{e}");
        // The printed form reads back to the same profiles and maps.
        let mut c = c;
        c.drives[1].cia402_map.statusword = 300;
        c.drives[1].cia402_map.word_order = cncgw_bus::modbus::WordOrder::LowFirst;
        c.drives[0].pr_map.counts_per_rev = c.drives[0].counts_per_rev;
        assert_eq!(SimConfig::from_toml(&c.to_commented_toml()).unwrap(), c);
    }
}
