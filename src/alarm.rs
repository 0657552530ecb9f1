//! Alarms: every failure a user can cause or meet is a numbered alarm with a message that
//! says what to do and, where there is one, the source position and block text.
//!
//! Numbers: the manuals' numbers where they give one (e.g. 3605). Where they are silent we
//! use Fanuc 0i-TF numbers (PS0010 "improper G-code" → 10, …) and our own ranges:
//! 1000–1099 configuration, 1100 state files, 2000–2199 CANopen / drives, 2200–2299 Modbus,
//! 2300–2399 sync and motion, 2400–2499 controller (watchdog, E-stop), 2500–2599 program
//! limits and restart, 3000 user alarms, 5010 end of record.
//!
//! [`CATALOGUE`] is the one list of the numbers the controller raises (the interpreter's own
//! Fanuc program-error numbers, raised where the program is parsed and decoded, stay in
//! `interp/`); every module names its alarms from here, and the table in
//! docs/ARCHITECTURE.md is generated from it ([`markdown_table`]).

use crate::canon::SrcPos;
use std::fmt;

#[derive(Clone, Debug, PartialEq)]
pub struct Alarm {
    pub number: u32,
    pub message: String,
    pub pos: Option<SrcPos>,
    /// The offending block's text, for program errors.
    pub block: Option<String>,
}

impl Alarm {
    pub fn new(number: u32, message: impl Into<String>) -> Self {
        Alarm { number, message: message.into(), pos: None, block: None }
    }
    pub fn at(mut self, pos: SrcPos) -> Self {
        self.pos = Some(pos);
        self
    }
    pub fn with_block(mut self, block: impl Into<String>) -> Self {
        self.block = Some(block.into());
        self
    }
}

impl fmt::Display for Alarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(p) = &self.pos {
            write!(f, "{p}: ")?;
        }
        write!(f, "alarm {:04}: {}", self.number, self.message)?;
        if let Some(b) = &self.block {
            let col = self.pos.as_ref().map_or(1, |p| p.col as usize);
            write!(f, "\n    {}", echo(b.trim_end(), col))?;
        }
        Ok(())
    }
}

/// At most this many characters of a block are echoed in an alarm.
pub const ECHO_CHARS: usize = 120;

/// The block as an alarm shows it: non-printing characters escaped (`\x00`), and a block
/// longer than [`ECHO_CHARS`] cut to a window around the alarm's column, the cuts marked
/// with how much was left out (a 2 MB line must not flood the terminal or the log).
pub fn echo(block: &str, col: usize) -> String {
    let n = block.chars().count();
    let start = if n <= ECHO_CHARS { 0 } else { col.saturating_sub(1 + ECHO_CHARS / 2).min(n - ECHO_CHARS) };
    let end = (start + ECHO_CHARS).min(n);
    let mut out = String::new();
    if start > 0 {
        out.push_str(&format!("[{start} characters cut] …"));
    }
    for ch in block.chars().skip(start).take(end - start) {
        if ch == '\t' {
            out.push(' ');
        } else if ch.is_control() {
            out.extend(ch.escape_default());
        } else {
            out.push(ch);
        }
    }
    if end < n {
        out.push_str(&format!("… [{} characters cut]", n - end));
    }
    out
}

impl std::error::Error for Alarm {}

/// One catalogue entry: what a service engineer looks up by number.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Entry {
    pub number: u32,
    pub name: &'static str,
    /// The range the number belongs to.
    pub group: &'static str,
    /// One line: what the alarm means.
    pub doc: &'static str,
}

/// Defines `pub const NAME: u32 = N;` for each entry and [`CATALOGUE`] from the same text,
/// so a number and its description cannot drift apart. Exactly one doc line per alarm.
macro_rules! catalogue {
    ($($group:literal { $(#[doc = $doc:literal] $name:ident = $number:literal;)* })*) => {
        $($(#[doc = $doc] pub const $name: u32 = $number;)*)*
        /// Every alarm number the controller raises, grouped by range, ascending.
        pub const CATALOGUE: &[Entry] = &[$($(Entry { number: $number, name: stringify!($name), group: $group, doc: $doc.trim_ascii() },)*)*];
    };
}

catalogue! {
    "Fanuc PS/OT numbers (motion, guard, cycles)" {
        /// PS0011: feed zero (a feed move without a positive F).
        FEED_ZERO = 11;
        /// PS0014: G34 lead change makes the lead ≤ 0 before the end of the thread.
        ILLEGAL_LEAD = 14;
        /// PS0020: arc radius out of tolerance (start and end radii differ).
        ARC_RADIUS = 20;
        /// PS0034: nose-radius compensation started or cancelled on an arc.
        NOSE_ARC_STARTUP = 34;
        /// PS0200: illegal S code in rigid tapping.
        RIGID_S = 200;
        /// PS0201: no feed rate in rigid tapping.
        RIGID_F = 201;
        /// PS0203: rigid tapping program error.
        RIGID_PROGRAM = 203;
        /// PS0204: illegal axis operation (a move between M29 and G84).
        RIGID_AXIS = 204;
        /// PS0224: an axis that needs a reference is not referenced (home it: `cncgw home X`).
        NOT_REFERENCED = 224;
        /// OT0500: + overtravel (soft limit 1).
        PLUS_OVERTRAVEL = 500;
        /// OT0501: − overtravel (soft limit 1).
        MINUS_OVERTRAVEL = 501;
        /// OT0502: + overtravel (stored stroke check 2, G22).
        PLUS_STROKE = 502;
        /// OT0503: − overtravel (stored stroke check 2, G22).
        MINUS_STROKE = 503;
    }
    "1000–1099 configuration" {
        /// The machine configuration is invalid or cannot be read (the message names the key).
        CONFIG = 1000;
    }
    "1100 state files" {
        /// A state file (offsets, tap state, alarm history) cannot be read or written.
        STATE_FILE = 1100;
    }
    "2000–2199 CANopen / drives" {
        /// No boot-up message from a drive after NMT reset communication.
        CANOPEN_BOOT = 2001;
        /// Device type 0x1000 is not a CiA 402 drive.
        DEVICE_TYPE = 2002;
        /// An SDO failed during configuration, or the node is not in the configuration.
        SDO_CONFIG = 2003;
        /// The configuration does not fit the drive's EDS, or the EDS cannot be read.
        EDS = 2004;
        /// The drive lacks the mode, did not confirm it (0x6061), or left it while running.
        DRIVE_MODE = 2005;
        /// The drive's position scaling or polarity disagrees with the axis config.
        DRIVE_SCALING = 2006;
        /// Another SYNC producer or master on the bus.
        FOREIGN_MASTER = 2007;
        /// A start-up list entry was refused or reads back another value.
        STARTUP_LIST = 2008;
        /// The drive's PDO mapping cannot be changed and does not carry what the cycle needs.
        FIXED_PDO = 2009;
        /// Drive fault (EMCY / 0x603F / error register), or a drive did not stop for a mode change.
        DRIVE_FAULT = 2010;
        /// Heartbeat of a drive lost.
        HEARTBEAT_LOST = 2011;
        /// Fault reset did not clear the drive's fault.
        FAULT_RESET = 2012;
        /// The drive did not reach Operation Enabled in time.
        ENABLE_TIMEOUT = 2013;
        /// The node left NMT operational.
        NODE_LEFT_OPERATIONAL = 2014;
        /// No position feedback within bus.feedback_timeout_ms.
        STALE_FEEDBACK = 2015;
        /// A profile-position move (service command) failed.
        PROFILE_MOVE = 2016;
        /// Homing failed or timed out.
        HOMING = 2017;
        /// TPDO1 of the wrong length (the drive did not take the mapping).
        TPDO_LENGTH = 2018;
        /// Position feedback disagrees with the commanded motion by a constant factor.
        FEEDBACK_SCALE = 2019;
        /// The CAN bus cannot be opened or written.
        CAN_BUS = 2020;
        /// The bus load at this cycle and bitrate is over 80 %.
        BUS_LOAD = 2021;
        /// `bus.sync = "external"`: no SYNC heard, or none for more than bus.sync_loss_cycles.
        SYNC_LOST = 2022;
        /// The CAN controller went bus-off (or its bus was lost): nothing can be sent.
        CAN_BUS_OFF = 2023;
    }
    "2200–2299 Modbus" {
        /// The Modbus link cannot be opened (connection refused, no serial device).
        MODBUS_LINK = 2200;
        /// A Modbus drive answered with an exception.
        MODBUS_EXCEPTION = 2201;
        /// A Modbus drive did not answer.
        MODBUS_TIMEOUT = 2202;
        /// A spindle-synchronised move needs a faster link than this Modbus link.
        MODBUS_SYNC_TOO_SLOW = 2203;
        /// A Modbus link falls behind, or its configured cycle is shorter than it can carry.
        MODBUS_CYCLE = 2204;
    }
    "2300–2399 sync and motion" {
        /// The look-ahead queue is full (caller must check `has_room`).
        QUEUE_FULL = 2300;
        /// End point outside the software travel limits, or on an axis that is not configured.
        TRAVEL = 2301;
        /// Feed per revolution (G99) while the spindle is stopped.
        PER_REV_SPINDLE_STOPPED = 2302;
        /// A value that is not a finite number, a negative dwell or speed, a degenerate arc.
        BAD_VALUE = 2303;
        /// A move kind this motion layer does not execute yet.
        UNSUPPORTED = 2304;
        /// A move pushed while a controlled stop is in progress.
        STOPPING = 2305;
        /// Thread lead × spindle speed is faster than the feed axes can go.
        THREAD_TOO_FAST = 2306;
        /// The measured spindle–axis sync error exceeded machine.sync_error_limit_um.
        SYNC_ERROR = 2307;
        /// G51.2/G50.2 on a machine without a tool spindle (Fanuc PS0218-class).
        NO_TOOL_SPINDLE = 2308;
        /// A measurement harness (emulated drives, trace) could not be set up.
        HARNESS = 2399;
    }
    "2400–2499 controller" {
        /// E-stop pressed: every drive was sent quick stop.
        ESTOP = 2400;
        /// Reset by the operator: controlled stop, the program ended.
        RESET = 2401;
        /// Too many cycle overruns (watchdog).
        WATCHDOG = 2402;
        /// The controller stalled inside a thread or rigid tap longer than the drives bridge.
        STALL_IN_SYNC = 2403;
        /// Another process holds the bus.
        BUS_IN_USE = 2404;
        /// Another process holds the machine's state.
        STATE_IN_USE = 2405;
        /// A thread of the controller (interpreter, state writer) could not be started.
        NO_THREAD = 2406;
        /// The tool is in a tapped hole (stored state) and the program does not start with G30 P99.
        TAP_IN_HOLE = 2410;
        /// The tap-state writer did not acknowledge a hole's entry state; the tap did not start.
        TAP_ACK_TIMEOUT = 2411;
        /// tap-test: the tap cannot be done from the position the drives report.
        TAP_PLAN = 2450;
        /// identify: the identification program cannot be made for this axis.
        IDENTIFY_PLAN = 2451;
    }
    "2500–2599 program limits and restart" {
        /// Too many blocks in a row without a move (taken as an endless loop).
        ENDLESS_LOOP = 2500;
        /// The program ran more blocks than its budget (--max-blocks).
        BLOCK_BUDGET = 2501;
        /// A cycle value outside the range the manual states.
        VALUE_RANGE = 2510;
        /// G30 P99 with no interrupted tap to return from.
        TAP_RETURN = 2511;
        /// The program cannot be restarted at that block.
        RESTART = 2520;
    }
    "2600–2699 machine I/O" {
        /// An M or T code was not confirmed (FIN) within its timeout: no later block ran.
        IO_FIN_TIMEOUT = 2600;
        /// The door-closed input opened while a program ran: controlled stop.
        IO_DOOR_OPEN = 2601;
        /// The chuck-clamped input dropped while the spindle turned or the chuck was clamped.
        IO_CHUCK_UNCLAMPED = 2602;
        /// An I/O device did not start, is not what the config says, or went silent.
        IO_DEVICE = 2603;
        /// A chuck unclamp code (M11) while the spindle was commanded to turn: refused, controlled stop.
        IO_UNCLAMP_TURNING = 2604;
    }
    "3000 user alarms, nose compensation" {
        /// `#3000 = k (MESSAGE)`: user alarm 3000 + k.
        USER_ALARM = 3000;
        /// Nose compensation (manual §2.18.4 note 2): G41 ↔ G42 without G40.
        NOSE_SWITCH = 3576;
        /// Nose compensation (manual §2.18.4 note 3): T code while compensating.
        NOSE_T_CODE = 3577;
        /// Nose compensation (manual §2.18.4): interference (overcut).
        NOSE_INTERFERENCE = 3605;
        /// Nose compensation (manual §2.18.4 note 1): corner angle under 0.1°.
        NOSE_CORNER_ANGLE = 3607;
    }
    "5010 end of record" {
        /// PS5010: the program's text ended before M02/M30 (or after the end-of-tape %).
        END_OF_RECORD = 5010;
    }
}

/// The catalogue as the markdown table docs/ARCHITECTURE.md carries.
pub fn markdown_table() -> String {
    let mut out = String::from("| Number | Name | Meaning |\n|---:|---|---|\n");
    let mut group = "";
    for e in CATALOGUE {
        if e.group != group {
            group = e.group;
            out.push_str(&format!("| | **{group}** | |\n"));
        }
        out.push_str(&format!("| {} | `{}` | {} |\n", e.number, e.name, e.doc.replace('|', "\\|")));
    }
    out
}

/// The catalogue entry of `number` (user alarms 3000 + k resolve to [`USER_ALARM`]).
pub fn lookup(number: u32) -> Option<&'static Entry> {
    let n = if (USER_ALARM..=USER_ALARM + 200).contains(&number) { USER_ALARM } else { number };
    CATALOGUE.iter().find(|e| e.number == n)
}

#[cfg(test)]
mod tests {
    use super::*;

    const BEGIN: &str = "<!-- alarm table: generated by `CNCGW_BLESS=1 cargo test -p cncgw --lib alarm` from src/alarm.rs -->";
    const END: &str = "<!-- end alarm table -->";

    #[test]
    fn catalogue_numbers_are_unique_and_ascending() {
        for w in CATALOGUE.windows(2) {
            assert!(
                w[0].number < w[1].number,
                "alarm {} ({}) then {} ({}): numbers must be unique and ascending",
                w[0].number,
                w[0].name,
                w[1].number,
                w[1].name
            );
        }
        let mut seen = std::collections::HashMap::new();
        for e in CATALOGUE {
            if let Some(other) = seen.insert(e.number, e.name) {
                panic!("alarm {} is both {other} and {}", e.number, e.name);
            }
            assert!(!e.doc.is_empty() && !e.doc.contains('\n'), "{}: one doc line", e.name);
        }
    }

    #[test]
    fn lookup_finds_user_alarms_and_misses_unknown_numbers() {
        assert_eq!(lookup(2400).map(|e| e.name), Some("ESTOP"));
        assert_eq!(lookup(3017).map(|e| e.name), Some("USER_ALARM"));
        assert_eq!(lookup(3201), None);
        assert_eq!(lookup(1), None);
    }

    /// The table in docs/ARCHITECTURE.md is the generated one; `CNCGW_BLESS=1` rewrites it.
    #[test]
    fn architecture_table_is_generated_from_the_catalogue() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/ARCHITECTURE.md");
        let text = std::fs::read_to_string(&path).unwrap();
        let (Some(b), Some(e)) = (text.find(BEGIN), text.find(END)) else { panic!("{}: markers `{BEGIN}` … `{END}` missing", path.display()) };
        let want = format!("{BEGIN}\n{}{END}", markdown_table());
        let have = &text[b..e + END.len()];
        if have == want {
            return;
        }
        if std::env::var_os("CNCGW_BLESS").is_some() {
            std::fs::write(&path, format!("{}{want}{}", &text[..b], &text[e + END.len()..])).unwrap();
        } else {
            panic!("docs/ARCHITECTURE.md's alarm table differs from src/alarm.rs: run `CNCGW_BLESS=1 cargo test -p cncgw --lib alarm`");
        }
    }
}
