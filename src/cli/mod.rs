//! The `cncgw` command line.

pub mod diag;
pub mod exit;
pub mod home;
pub mod identify;
pub mod iomon;
pub mod lock;
pub mod manpages;
pub mod mapcheck;
pub mod mbus;
pub mod mdi;
pub mod offsets;
pub mod plan;
pub mod preview;
pub mod restart;
pub mod run;
pub mod service;
pub mod taptest;
pub mod term;

use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "cncgw",
    version,
    about = "CNC lathe controller core and fieldbus gateway (CANopen CiA 402, Modbus RTU/TCP)",
    long_about = None,
    after_help = exit::table()
)]
pub struct Cli {
    /// More log output (-v info, -vv debug); RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    #[command(subcommand)]
    pub cmd: Command,
}

/// Options every command that touches the machine takes.
#[derive(clap::Args, Debug, Clone)]
pub struct MachineArgs {
    /// Machine configuration (TOML). Default: the embedded config/lathe.toml.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Bus: `inproc` (embedded emulated drives, simulated time), a SocketCAN interface such
    /// as `vcan0` or `can0`, `socketcand://HOST:PORT/IFACE`, or a Modbus link for every axis:
    /// `modbus-tcp://HOST:PORT`, `modbus-rtu:///dev/ttyUSB0?baud=115200&parity=none`.
    /// Default: the config's bus.interface (and its Modbus links).
    #[arg(long, value_name = "BUS")]
    pub bus: Option<String>,
    /// With `--bus inproc`: the emulated drives' own configuration (a sim-drives file, as
    /// `sim-drives --print-default-config` prints; e.g. one of tests/drive_models/) instead of
    /// sim-drives' defaults for the machine's axes; its `[drive.shape]` makes them behave like
    /// commercial drives (boot mode, user units, SYNC producer, no 0x1016, …). Its node ids
    /// and kinds must be the machine's, and its counts per unit too unless a drive is shaped.
    #[arg(long, value_name = "FILE")]
    pub sim_config: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a part program on the machine.
    ///
    /// On a terminal the run is interactive: single keys
    /// press the operator panel — h feed hold, s cycle start, b single block on/off, o
    /// optional stop, +/- feed override, r reset (alarm 2401), e E-stop (alarm 2400),
    /// Ctrl-C = reset — and the status line shows the block, position, F, S, sync error and
    /// HELD / SINGLE BLOCK; on the embedded emulated machine its simulated time is then paced
    /// to the wall clock. Without a terminal (or with --batch) it runs straight through and
    /// M00/M01 go on. Exit code 0 ok, 1 not at the end point, 2 program error, 3 alarm, 4
    /// setup.
    ///
    /// Example: `cncgw run examples/first_part.nc` (embedded emulated drives), or
    /// `cncgw run --bus vcan0 examples/first_part.nc` against `sim-drives --bus vcan0`.
    Run {
        /// The part program; `-` reads it from standard input.
        program: PathBuf,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
        /// Where the machine's power-off state lives (common variables #401–#600). Default:
        /// $CNCGW_STATE_DIR, else $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
        #[arg(long, value_name = "DIR")]
        state_dir: Option<PathBuf>,
        /// Record every cycle to this CSV file: t_s, line, NAME_cmd/NAME_act/NAME_ferr per
        /// drive (mm, X as a radius; the spindle in degrees) and NAME_age (SYNC cycles the
        /// actual is old: 0 fresh, more after a late frame), spindle_rpm, sync_err_um. After
        /// an alarm, reset or a drive fault it goes on until the drives stand still (NAME_ferr
        /// 0 there).
        #[arg(long, value_name = "FILE.csv")]
        trace: Option<PathBuf>,
        /// Stop with alarm 2501 (a controlled stop) after this many blocks: a program that
        /// loops without end (DO without WHILE). 0 = no budget, for a main program that
        /// repeats on purpose with M99 (bar feeder).
        #[arg(long, value_name = "N", default_value_t = crate::interp::DEFAULT_BLOCK_BUDGET)]
        max_blocks: u64,
        /// Tool offset table (docs/TOOL_TABLE.md, e.g. config/tools.toml): geometry, wear,
        /// nose radius and tip per offset number for the T codes. Default: the table stored
        /// with `cncgw offsets` (none stored: all zero).
        #[arg(long, value_name = "FILE")]
        tools: Option<PathBuf>,
        #[command(flatten)]
        rt: run::RtArgs,
        #[command(flatten)]
        op: run::OperatorArgs,
        #[command(flatten)]
        restart: restart::RestartArgs,
    },
    /// Run a rigid tap in the air and report its spindle–Z sync error (commissioning).
    ///
    /// Runs a rigid tap in the air on the configured machine (what a service engineer does at
    /// commissioning) and reports the spindle–Z sync error from the drives' actual positions —
    /// max and RMS over the whole tap and through entry, reversal and exit — with the
    /// following errors of spindle and Z, and draws it (SVG; the trace is kept as CSV next to
    /// it). The tap starts `--clearance` above the present Z (X stays) and goes `--depth`
    /// down: leave that much free air below the tool. `--dry`: plan and check only, nothing
    /// moves. Needs --yes (or a typed yes on a terminal) on a real bus. Exit code 0 = within
    /// machine.sync_error_limit_um, 1 = over it, 2 = cannot be done as asked, 3 = alarm.
    ///
    /// Example: `cncgw tap-test --lead 1.5 --depth 30 --rpm 3000`,
    /// `cncgw tap-test --lead 1.5 --depth 30 --rpm 3000 --dry --bus can0`,
    /// `cncgw tap-test --lead 1 --depth 20 --rpm 2000 --bus can0 --yes --json -o tap.svg`
    TapTest {
        #[command(flatten)]
        tap: taptest::TapArgs,
        #[command(flatten)]
        machine: MachineArgs,
        #[command(flatten)]
        op: run::OperatorArgs,
    },
    /// Identify an axis' drive response and propose its following-error window.
    ///
    /// Commissioning: moves the axis a little (in the air; --yes on a
    /// real bus), fit its response and print it as `[axes.NAME.response]` with the
    /// following-error window it asks for.
    ///
    /// Example: `cncgw identify z`, `cncgw identify s1 --bus can0 --yes --json`
    Identify {
        #[command(flatten)]
        args: identify::IdentifyArgs,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Trace files written by `cncgw run --trace`.
    #[command(subcommand)]
    Trace(TraceCmd),
    /// Print the canonical moves of a program without running anything.
    ///
    /// The moves go to stdout (docs/PLAN_FORMAT.md); then, on stderr, a summary (moves,
    /// extents) and the checks `run` makes before motion — travel, G22, feeds, threads and
    /// taps against the axes — from machine zero, unless `--no-machine`. Exit code 2 for a
    /// program error, 3 when the machine would refuse the program.
    ///
    /// Example: `cncgw plan examples/first_part.nc --format text`,
    /// `cncgw plan part.nc --tools config/tools.toml --no-machine`
    Plan(plan::PlanArgs),
    /// Draw the toolpath of a program as an SVG, without running anything.
    ///
    /// The Z–X plane in workpiece coordinates (X as a radius, one scale on both axes) with mm
    /// ticks and the work zero; rapids dashed, feeds solid, threads and each cycle in their
    /// own colour, a legend of only the kinds the program has; the stock with `--stock`, the
    /// tool nose circle along G41/G42 paths with `--tools`. A name ending in .png is
    /// rendered through rsvg-convert (librsvg2-bin). Exit code 2 after an alarm (the path up
    /// to it is drawn).
    ///
    /// Example: `cncgw preview examples/first_part.nc -o part.svg --stock 60x80+1`
    Preview {
        /// The part program (Type A G code or SINUMERIK cycles).
        program: PathBuf,
        /// The picture to write: SVG, or PNG for a name ending in .png (needs rsvg-convert).
        #[arg(long, short = 'o', value_name = "FILE")]
        out: PathBuf,
        /// Machine configuration (TOML). Default: the embedded config/lathe.toml.
        #[arg(long, short = 'c', value_name = "FILE")]
        config: Option<PathBuf>,
        /// Picture width in pixels.
        #[arg(long, default_value_t = 1000)]
        width: u32,
        /// Tool offset table (docs/TOOL_TABLE.md, e.g. config/tools.toml): offsets and nose radii for T codes
        /// and G41/G42. Default: the table stored with `cncgw offsets` (none stored: all zero).
        #[arg(long, value_name = "FILE")]
        tools: Option<PathBuf>,
        /// The bar to draw under the path: diameter × length in mm, the face stock after a +
        /// (from Z = face down), e.g. `--stock 60x80` or `--stock 60x80+1`.
        #[arg(long, value_name = "DxL[+F]")]
        stock: Option<preview::Stock>,
        /// Where the stored offsets are (`cncgw offsets`; as for `run`). Default:
        /// $CNCGW_STATE_DIR, else $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
        #[arg(long, value_name = "DIR")]
        state_dir: Option<PathBuf>,
    },
    /// Configuration commands.
    #[command(subcommand)]
    Config(ConfigCmd),
    /// List every node of the configuration with its identity and state.
    ///
    /// Per node: node id, vendor, product, revision, serial
    /// (0x1018), device type (0x1000), name (0x1008), NMT state, heartbeat period (0x1017).
    /// Read-only.
    ///
    /// Example: `cncgw scan` (embedded emulated drives), `cncgw scan --bus can0 --json`
    Scan {
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Read or write one object of a node's object dictionary over SDO.
    #[command(subcommand)]
    Sdo(SdoCmd),
    /// Send an NMT command to one node or to all, and report the state the nodes answer with.
    ///
    /// Example: `cncgw nmt preop all`, `cncgw nmt reset-comm 2 --bus vcan0`
    Nmt {
        /// start | stop | preop | reset | reset-comm
        #[arg(value_enum)]
        command: diag::NmtArg,
        /// Node id 1…127 (decimal or 0x…) or `all`.
        #[arg(value_parser = diag::parse_target, value_name = "NODE|all")]
        target: u8,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// CiA 402 drive commands.
    #[command(subcommand)]
    Drive(DriveCmd),
    /// Reference return: home the axes with their configured homing (`homing = { … }`).
    ///
    /// Each axis is homed in its drive's CiA 402 homing mode (6) with the method, offset and
    /// speeds of its `homing` table, and kept referenced in the state directory until its
    /// drive reboots or loses its position. `run` refuses to move an axis that needs a
    /// reference and has none (alarm 224). Needs --yes on a real bus.
    ///
    /// Example: `cncgw home`, `cncgw home x`, `cncgw home all --bus can0 --yes`
    Home(home::HomeCmd),
    /// Move one axis to a position or by a distance (service).
    ///
    /// In the drive's profile position mode (1), to an absolute position or
    /// by a distance, in machine units (mm, X as a radius; degrees for a spindle). All the
    /// configured drives are started and enabled (holding) for the move, and disabled after
    /// it; prints the position read back from the drive. Refused outside axes.NAME.min/max.
    /// Needs --yes on a real bus.
    ///
    /// Example: `cncgw jog z --to -20`, `cncgw jog x --by 2.5 --speed 500`,
    /// `cncgw jog z --by -1 --bus can0 --yes`
    Jog {
        /// The axis name of the configuration (x, z, s1, …).
        axis: String,
        /// Absolute target position.
        #[arg(long, allow_hyphen_values = true, conflicts_with = "by", required_unless_present = "by", value_name = "POS")]
        to: Option<f64>,
        /// Distance from the present position.
        #[arg(long, allow_hyphen_values = true, value_name = "DIST")]
        by: Option<f64>,
        /// Speed in mm/min (rpm for a spindle). Default: 1/10 of the axis's max_speed.
        #[arg(long)]
        speed: Option<f64>,
        /// Confirm the move on a real bus.
        #[arg(long)]
        yes: bool,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Record every frame on the bus to a candump log file.
    ///
    /// Every frame on the bus goes to FILE in candump's log format
    /// (`(1700000000.123456) can0 181#2700E8030000`), replayable with `canplayer`. Passive:
    /// sends nothing. On `inproc` the emulated drives boot while it logs.
    ///
    /// Example: `cncgw buslog --bus can0 -o run.log --seconds 60`
    Buslog {
        /// The log file to write.
        #[arg(long, short = 'o', value_name = "FILE")]
        out: PathBuf,
        /// Stop after N seconds. Default: until interrupted (5 s of simulated time on inproc).
        #[arg(long, value_name = "N")]
        seconds: Option<f64>,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Show every configured drive's state, position and following error, live.
    ///
    /// A table of every configured drive, read over SDO (or the Modbus registers of its
    /// map): statusword and CiA 402 state, mode
    /// (0x6061), position, velocity and following error in machine units, and the bus load
    /// this tool sees. Refreshed in place on a terminal, one table after another otherwise.
    /// Read-only.
    ///
    /// Example: `cncgw monitor --bus can0`, `cncgw monitor --once`, `cncgw monitor --once --json`
    Monitor {
        /// Stop after N seconds. Default: until interrupted (5 s of simulated time on inproc).
        #[arg(long, value_name = "N")]
        seconds: Option<f64>,
        /// Print one table and exit.
        #[arg(long)]
        once: bool,
        /// Refresh period in milliseconds.
        #[arg(long, default_value_t = 500, value_name = "MS")]
        interval_ms: u64,
        /// Print one JSON object per refresh (JSON lines) instead of the table.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Object dictionary commands.
    #[command(subcommand)]
    Od(OdCmd),
    /// Show the machine's alarm history (every alarm `run` met, newest last).
    ///
    /// Alarms are kept per machine and place (as the machine's state: `--config`, `--bus`) in
    /// the state directory, one line each with time, number, message, program and line.
    ///
    /// `--list` prints the catalogue instead: every alarm number the controller raises, its
    /// name and meaning (no machine or state needed).
    ///
    /// Example: `cncgw alarms`, `cncgw alarms --since 8h`, `cncgw alarms --bus can0 --json`,
    /// `cncgw alarms --list`
    Alarms {
        #[command(flatten)]
        machine: MachineArgs,
        /// Where the machine's state lives (as for `run`). Default: $CNCGW_STATE_DIR, else
        /// $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
        #[arg(long, value_name = "DIR")]
        state_dir: Option<PathBuf>,
        /// Only alarms since then: a duration back from now (`30min`, `8h`, `2days`) or a time
        /// (`2026-11-25T06:00:00Z`).
        #[arg(long, value_name = "WHEN")]
        since: Option<String>,
        /// Print JSON (an array of {time, number, message, file, line, program}; with `--list`
        /// of {number, name, group, doc}).
        #[arg(long)]
        json: bool,
        /// Print the alarm catalogue (number, name, meaning) instead of the history.
        #[arg(long, conflicts_with = "since")]
        list: bool,
    },
    /// Print the Argon2 hash of an OPC UA user's password, for `[[opcua.users]] password_hash`.
    ///
    /// The password is read from the first line of standard input (not an argument: it
    /// would stay in the shell's history and the process list). Each run salts anew.
    ///
    /// Example: `printf '%s\n' "$PW" | cncgw opcua-hash`
    #[command(name = "opcua-hash")]
    OpcuaHash,
    /// MDI: type blocks on the live machine, each Enter runs one.
    ///
    /// One block per line from standard input (a terminal or a pipe); the modal state (G codes,
    /// F, S, T, offsets, macro variables) is kept between blocks and the drives stay enabled.
    /// Each block is checked as `run` checks a program before motion: a refused block moves
    /// nothing and the session goes on. M02/M30 or the end of input (Ctrl-D) ends it; Ctrl-C
    /// stops the machine. Exit codes as for `run`.
    ///
    /// Example: `cncgw mdi`, `printf 'G98 G0 X20 Z2\nG1 Z-5 F300\n' | cncgw mdi`
    Mdi(mdi::MdiArgs),
    /// The offset pages kept in the state directory: tool offsets and work offsets.
    ///
    /// Tool offsets T01–T99 (geometry X/Z, wear X/Z, nose radius, tip) and work offsets
    /// G54–G59 with EXT (the external offset), per machine (--config's name). `run`, `plan`
    /// and `preview` use them when no --tools FILE is given.
    ///
    /// Example: `cncgw offsets list`, `cncgw offsets set T01 --wear-x 0.02 --add`,
    /// `cncgw offsets set G54 --z -312.5`, `cncgw offsets import config/tools.toml`
    #[command(subcommand)]
    Offsets(offsets::OffsetsCmd),
    /// Print a shell completion script.
    ///
    /// Example: `cncgw completions bash > /etc/bash_completion.d/cncgw`
    Completions {
        /// bash | zsh | fish | elvish | powershell
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
    /// Print the manual page (roff), or write one page per command into a directory.
    ///
    /// Example: `cncgw man > cncgw.1 && man -l cncgw.1`,
    /// `cncgw man --dir /usr/local/share/man/man1`
    Man {
        /// Write cncgw.1, cncgw-run.1, cncgw-sdo-read.1, … (every command and subcommand)
        /// into this directory instead of printing the top page.
        #[arg(long, value_name = "DIR")]
        dir: Option<PathBuf>,
    },
}

#[derive(Subcommand, Debug)]
pub enum TraceCmd {
    /// Draw positions, following errors, spindle speed and sync error over time as SVG.
    ///
    /// One panel per thing the run did: positions (command dashed dark over the actual) and
    /// following errors of the feed axes that moved, the spindle speed if it turned, the sync
    /// error if a move was synchronised; legends right of the data. A name ending in .png
    /// is rendered through rsvg-convert (librsvg2-bin).
    ///
    /// Example: `cncgw trace plot run.csv -o run.svg`
    Plot {
        /// A trace CSV from `cncgw run --trace`.
        file: PathBuf,
        /// The picture to write: SVG, or PNG for a name ending in .png (needs rsvg-convert).
        #[arg(short = 'o', long, value_name = "FILE.svg")]
        out: PathBuf,
    },
}

#[derive(Subcommand, Debug)]
pub enum SdoCmd {
    /// Read INDEX:SUB of NODE. Without --type the value is shown by its length (1, 2, 4 bytes
    /// as unsigned numbers, printable bytes as text, else hex bytes). Exit code 1 on an abort.
    ///
    /// Example: `cncgw sdo read 1 0x6041 0 --type u16`, `cncgw sdo read 1 0x1008 0 --type str`,
    /// `cncgw sdo read 2 0x2000 1 --type domain -o blob.bin`
    Read {
        /// Node id 1…127 (decimal or 0x…).
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        /// Object index, e.g. 0x6041.
        #[arg(value_parser = diag::parse_index)]
        index: u16,
        /// Sub-index, e.g. 0 or 0x01.
        #[arg(value_parser = diag::parse_sub)]
        sub: u8,
        /// How to show the value.
        #[arg(long, short = 't', value_enum)]
        r#type: Option<diag::SdoType>,
        /// Also save the raw bytes to FILE (for domains).
        #[arg(long, short = 'o', value_name = "FILE")]
        out: Option<PathBuf>,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Write VALUE as TYPE to INDEX:SUB of NODE. Numbers in decimal or 0x… hex; a domain
    /// VALUE is a file whose bytes are written. Objects that can set a motor in motion
    /// (0x6040, 0x6060, 0x607A, 0x60FF, …) need --yes on a real bus. Exit code 1 on an abort.
    ///
    /// Example: `cncgw sdo write 1 0x1017 0 u16 100`, `cncgw sdo write 3 0x6065 0 u32 0x2000`
    Write {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        /// Object index, e.g. 0x1017.
        #[arg(value_parser = diag::parse_index)]
        index: u16,
        /// Sub-index, e.g. 0 or 0x01.
        #[arg(value_parser = diag::parse_sub)]
        sub: u8,
        /// u8 | u16 | u32 | i8 | i16 | i32 | f32 | str | domain
        #[arg(value_enum)]
        r#type: diag::SdoType,
        /// The value: a number (decimal or 0x…), a string for str, a file for domain.
        #[arg(allow_hyphen_values = true)]
        value: String,
        /// Confirm a write that can move a motor on a real bus.
        #[arg(long)]
        yes: bool,
        #[command(flatten)]
        machine: MachineArgs,
    },
}

#[derive(Subcommand, Debug)]
pub enum OdCmd {
    /// Print NODE's object dictionary as the drive reports it (read-only): with --eds every
    /// object of the file, read over SDO, shown by its DataType and checked against the file
    /// (present, the type's size, write-only not readable); without, the CiA 301 identity
    /// and communication objects and the CiA 402 objects. Exit code 1 on a disagreement or
    /// a failed read.
    ///
    /// Example: `cncgw od dump 1`, `cncgw od dump 1 --eds tests/python/sim_drive.eds --json`
    Dump {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        /// The EDS file.
        #[arg(long, value_name = "FILE")]
        eds: Option<PathBuf>,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Check NODE's object dictionary against an EDS file (CiA 306): every object of the
    /// file must exist on the node, read with its type's size, and refuse writes if read-only
    /// (the value just read is written back, so nothing changes), or reads if write-only;
    /// for a configured drive, also what start-up writes and maps (type, access, PDO
    /// mapping). Prints one line per disagreement naming the file and line. Exit code 1 if
    /// there is any.
    ///
    /// Example: `cncgw od check 1 --eds tests/python/sim_drive.eds`
    Check {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        /// The EDS file.
        #[arg(long, value_name = "FILE")]
        eds: PathBuf,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand, Debug)]
pub enum DriveCmd {
    /// Show a drive's state: statusword bit by bit, CiA 402 state, mode (0x6061), position
    /// (0x6064), velocity (0x606C), following error (0x60F4), error code (0x603F) and the last
    /// EMCY heard, all in words. Read-only. Exit code 1 when the drive is in fault.
    ///
    /// Example: `cncgw drive status 1`, `cncgw drive status 3 --bus can0 --json`
    Status {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Walk a drive through the CiA 402 state machine to Operation Enabled (CANopen: over
    /// SDO, 0x6041 read and 0x6040 written; Modbus: the statusword and controlword registers
    /// of the drive's map; a fault is reset on the way) and report the state reached. The
    /// drive holds its position. Needs --yes on a real bus.
    ///
    /// Example: `cncgw drive enable 1`, `cncgw drive enable 2 --bus can0 --yes`,
    /// `cncgw drive enable 2 --bus modbus-tcp://192.168.1.20:502 --config M.toml --yes`
    Enable {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        /// Confirm on a real bus.
        #[arg(long)]
        yes: bool,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Take the torque off a drive: to Switch On Disabled (disable voltage) and report the
    /// state reached. Exit code 1 if the drive is in fault.
    ///
    /// Example: `cncgw drive disable 1 --bus can0`
    Disable {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Reset a drive's fault (rising edge of controlword bit 7) and report the state
    /// reached; exit code 1 with the error code 0x603F in words if the fault persists.
    ///
    /// Example: `cncgw drive fault-reset 3 --bus can0`
    FaultReset {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        #[command(flatten)]
        machine: MachineArgs,
    },
    /// Home a drive in its homing mode (6); the configured drives are started and enabled
    /// for it and disabled after it. Prints the position read back. Needs --yes on a real
    /// bus.
    ///
    /// Example: `cncgw drive home 1 --method 37 --offset 150`,
    /// `cncgw drive home 2 --method 18 --switch-speed 600 --bus can0 --yes`
    Home {
        /// Node id: CANopen 1…127 or Modbus unit 1…247 (decimal or 0x…), as in the configuration.
        #[arg(value_parser = diag::parse_node)]
        node: u8,
        #[command(flatten)]
        home: service::HomeArgs,
        /// Confirm on a real bus.
        #[arg(long)]
        yes: bool,
        #[command(flatten)]
        machine: MachineArgs,
    },
}

/// An open bus with its clock and a CANopen master that has not configured anything.
pub struct Session {
    pub cfg: crate::config::MachineConfig,
    pub master: crate::drives::canopen::CanOpenMaster<Box<dyn cncgw_bus::CanBus>>,
    /// The emulated drives (`inproc`) or the wall clock.
    pub clock: Box<dyn cncgw_bus::Clock>,
    /// The bus as given (`inproc`, `vcan0`, …).
    pub bus: String,
    /// The bus in words, for messages.
    pub what: String,
    pub simulated: bool,
}

/// A `--bus` value (or `bus.interface`), parsed once: what kind of bus it names.
#[derive(Clone, Debug)]
pub enum BusKind {
    /// The embedded emulated drives, in simulated time.
    Inproc,
    /// No CANopen bus (every drive on a Modbus link).
    None,
    /// A SocketCAN interface (can0, vcan0).
    SocketCan(String),
    /// A socketcand server: address and the interface on that host.
    Socketcand { addr: String, iface: String },
    /// `modbus-tcp://…` / `modbus-rtu://…`: every axis on that link (see `mbus`).
    Modbus(ModbusBus),
}

/// A `modbus-tcp://…` / `modbus-rtu://…` bus: the link it names, and which of the URL's
/// parameters were given (the others stay the configuration's, `mbus::apply_bus`).
#[derive(Clone, Debug)]
pub struct ModbusBus {
    pub link: crate::config::ModbusLink,
    pub given: Vec<String>,
}

impl BusKind {
    /// Parse `bus`, or say what is wrong with it before anything tries to open it: `inproc`,
    /// `none`, a SocketCAN interface name (1–15 characters, no `/`, `:` or white space),
    /// `socketcand://HOST:PORT/IFACE`, `modbus-tcp://…`, `modbus-rtu://…`.
    pub fn parse(bus: &str) -> Result<BusKind, String> {
        let schemes = "inproc, a SocketCAN interface (can0, vcan0), socketcand://HOST:PORT/IFACE, modbus-tcp://HOST:PORT, modbus-rtu://DEVICE?baud=…";
        if let Some((scheme, _)) = bus.split_once("://") {
            return match scheme {
                "socketcand" => match cncgw_bus::transport::socketcand::parse_url(bus) {
                    Some((addr, iface)) => Ok(BusKind::Socketcand { addr, iface }),
                    None => Err(format!(
                        "--bus {bus}: a socketcand bus is socketcand://HOST:PORT/IFACE, e.g. socketcand://192.168.1.20:29536/can0 (host, port and the interface on that host)"
                    )),
                },
                "modbus-tcp" | "modbus-rtu" => match mbus::parse_bus_url(bus) {
                    Some(link) => {
                        let given = bus.split_once('?').map(|(_, q)| q.split('&').map(|kv| kv.split('=').next().unwrap_or("").to_string()).collect());
                        Ok(BusKind::Modbus(ModbusBus { link: link?, given: given.unwrap_or_default() }))
                    }
                    None => Err(format!("--bus {bus}: unknown kind of bus `{scheme}://`; one of: {schemes}")),
                },
                _ => Err(format!("--bus {bus}: unknown kind of bus `{scheme}://`; one of: {schemes}")),
            };
        }
        match bus {
            "inproc" => return Ok(BusKind::Inproc),
            "none" => return Ok(BusKind::None),
            _ => {}
        }
        let bad = bus.is_empty() || bus.len() > 15 || bus.chars().any(|c| c == '/' || c == ':' || c.is_whitespace());
        if bad {
            return Err(format!(
                "--bus {bus}: not a SocketCAN interface name (1–15 characters without `/`, `:` or spaces, e.g. can0) nor any other kind of bus; one of: {schemes}"
            ));
        }
        Ok(BusKind::SocketCan(bus.to_string()))
    }
}

impl MachineArgs {
    /// `--bus` parsed ([`BusKind::parse`]); None without one (the configuration's bus).
    pub fn bus_kind(&self) -> Result<Option<BusKind>, String> {
        self.bus.as_deref().map(BusKind::parse).transpose()
    }

    /// The bus this command runs on — `--bus`, else the configuration's `bus.interface` —
    /// is the embedded emulated one (nothing real can move).
    pub fn on_embedded_bus(&self, cfg: &crate::config::MachineConfig) -> bool {
        let bus = self.bus.as_deref().unwrap_or(&cfg.bus.interface);
        matches!(BusKind::parse(bus), Ok(BusKind::Inproc))
    }
}

/// What is wrong with a `--bus` value, before anything tries to open it ([`BusKind::parse`]).
pub fn check_bus_value(bus: &str) -> Result<(), String> {
    BusKind::parse(bus).map(|_| ())
}

/// The bus named by `bus` (default: the config's bus.interface) with its clock: the bus
/// endpoint, the clock, the bus as given, and the bus in words. `inproc` builds the
/// emulated drives from `cfg_text`.
#[allow(clippy::type_complexity)]
pub fn open_raw(
    cfg: &crate::config::MachineConfig,
    cfg_text: &str,
    bus: Option<&str>,
    sim: Option<&std::path::Path>,
) -> Result<(Box<dyn cncgw_bus::CanBus>, Box<dyn cncgw_bus::Clock>, String, String), String> {
    let (ep, clock, bus, what) = open_plain(cfg, cfg_text, bus, sim)?;
    if cfg.bus.sync == crate::config::SyncSource::External {
        // The cycle runs on the SYNC another device produces (issue 21 item 6).
        let (ep, clock) = cncgw_bus::sync_source::external_sync(ep, clock, cfg.cycle_ns());
        return Ok((Box::new(ep), Box::new(clock), bus, format!("{what}, cycle on the external SYNC")));
    }
    Ok((ep, clock, bus, what))
}

#[allow(clippy::type_complexity)]
fn open_plain(
    cfg: &crate::config::MachineConfig,
    cfg_text: &str,
    bus: Option<&str>,
    sim: Option<&std::path::Path>,
) -> Result<(Box<dyn cncgw_bus::CanBus>, Box<dyn cncgw_bus::Clock>, String, String), String> {
    use cncgw_bus::transport::socketcand::Socketcand;
    let bus = bus.map(str::to_string).unwrap_or_else(|| cfg.bus.interface.clone());
    let real = || -> Box<dyn cncgw_bus::Clock> { Box::new(cncgw_bus::RealClock::new()) };
    match BusKind::parse(&bus)? {
        BusKind::Modbus(_) => Err(format!(
            "{bus} is a Modbus bus: this is a CANopen command (Modbus drives: scan, drive status|enable|disable|fault-reset|home, monitor, jog, run, tap-test)"
        )),
        BusKind::None => Err("the configuration has no CANopen bus (bus.interface = \"none\"): give one with --bus, or use a Modbus command".into()),
        BusKind::Inproc => {
            embedded_bus(cfg, cfg_text, sim).map(|(ep, clock)| (ep, clock, bus, "inproc (embedded emulated drives, simulated time)".into()))
        }
        BusKind::Socketcand { addr, iface } => {
            let sock = Socketcand::connect(&addr, &iface).map_err(|e| format!("{e}; is socketcand running at {addr}?"))?;
            let what = format!("{bus} (socketcand over TCP, real time)");
            Ok((Box::new(sock), real(), bus, what))
        }
        BusKind::SocketCan(iface) => {
            let sock = cncgw_bus::transport::socketcan::SocketCan::open(&iface).map_err(|e| {
                if e.to_string().contains("no SocketCAN") {
                    e.to_string()
                } else {
                    format!("{e}; or use --bus inproc for the embedded emulated drives")
                }
            })?;
            let what = format!("{bus} (SocketCAN, real time)");
            Ok((Box::new(sock), real(), bus, what))
        }
    }
}

#[cfg(feature = "embedded")]
fn embedded_bus(cfg: &crate::config::MachineConfig, text: &str, sim: Option<&std::path::Path>) -> Result<crate::control::BusClock, String> {
    crate::control::embedded::open(cfg, text, sim)
}

#[cfg(not(feature = "embedded"))]
fn embedded_bus(_: &crate::config::MachineConfig, _: &str, _: Option<&std::path::Path>) -> Result<crate::control::BusClock, String> {
    Err("this cncgw was built without the embedded emulated drives (cargo feature `embedded`): give the machine's bus with --bus (can0, socketcand://HOST:PORT/can0, modbus-tcp://HOST:PORT)".into())
}

/// Open the bus named by `bus` (default: the config's bus.interface) with its clock, and a
/// master for `cfg` on it. `inproc` builds the emulated drives from `cfg_text` (or `sim`).
#[allow(clippy::type_complexity)]
pub fn open_bus(
    cfg: &crate::config::MachineConfig,
    cfg_text: &str,
    bus: Option<&str>,
    sim: Option<&std::path::Path>,
) -> Result<(crate::drives::canopen::CanOpenMaster<Box<dyn cncgw_bus::CanBus>>, Box<dyn cncgw_bus::Clock>, String, String), String> {
    let (ep, clock, bus, what) = open_raw(cfg, cfg_text, bus, sim)?;
    Ok((crate::drives::canopen::CanOpenMaster::new(ep, cfg), clock, bus, what))
}

/// `--config` + `--bus` → an open session. On the emulated bus the drives boot first (a real
/// bus's nodes booted long ago).
pub fn open_session(m: &MachineArgs) -> Result<Session, String> {
    open_session_with(m, |b| b)
}

/// `open_session` with the bus endpoint passed through `wrap` first (frame counting…).
pub fn open_session_with(m: &MachineArgs, wrap: impl FnOnce(Box<dyn cncgw_bus::CanBus>) -> Box<dyn cncgw_bus::CanBus>) -> Result<Session, String> {
    let (cfg, text) = load_config(m.config.as_deref())?;
    let (ep, mut clock, bus, what) = open_raw(&cfg, &text, m.bus.as_deref(), m.sim_config.as_deref())?;
    let mut master = crate::drives::canopen::CanOpenMaster::new(wrap(ep), &cfg);
    let simulated = clock.is_simulated();
    if simulated && !master.wait_boot(&mut *clock, 5000) {
        return Err("the emulated drives did not boot within 5 s; check the [axes] of the config".into());
    }
    Ok(Session { cfg, master, clock, bus, what, simulated })
}

/// The bus a service command talks to: every drive on Modbus (the configuration's links or
/// `--bus modbus-…`), or an open CANopen session. One per command, matched at once: its
/// size does not matter.
#[allow(clippy::large_enum_variant)]
pub enum ServiceBus {
    Modbus(crate::config::MachineConfig),
    CanOpen(Session),
}

/// `open_session`, the error printed: Err is the exit code.
pub fn open_or_exit(m: &MachineArgs) -> Result<Session, i32> {
    open_session(m).or_setup()
}

/// The machine's bus for a service command; an error is printed, Err is the exit code.
pub fn open_service_bus(m: &MachineArgs) -> Result<ServiceBus, i32> {
    open_service_bus_with(m, |b| b)
}

/// `open_service_bus` with a CANopen endpoint passed through `wrap` (`open_session_with`).
pub fn open_service_bus_with(
    m: &MachineArgs,
    wrap: impl FnOnce(Box<dyn cncgw_bus::CanBus>) -> Box<dyn cncgw_bus::CanBus>,
) -> Result<ServiceBus, i32> {
    if let Some(cfg) = mbus::modbus_machine(m).or_setup()? {
        return Ok(ServiceBus::Modbus(cfg));
    }
    open_session_with(m, wrap).map(ServiceBus::CanOpen).or_setup()
}

/// The offset tables of a run, plan, preview or MDI (`offsets::resolve`); an alarm is
/// printed, Err is its exit code: a state directory that cannot be read is the set-up's
/// fault, a bad --tools file the input's.
pub fn resolve_tables(state_root: Option<&std::path::Path>, machine: &str, tools: Option<&std::path::Path>) -> Result<crate::offsets::Tables, i32> {
    crate::offsets::resolve(state_root, machine, tools).map_err(|a| {
        eprintln!("{a}");
        if a.number == crate::persist::STATE_ALARM {
            exit::SETUP
        } else {
            exit::INPUT
        }
    })
}

/// A bus, configuration or file that could not be opened: said, and its exit code.
fn setup_failed(e: &dyn std::fmt::Display) -> i32 {
    eprintln!("error: {e}");
    exit::SETUP
}

/// A set-up step's result for a command: its error said (`error: …`), Err the exit code.
pub trait OrSetup<T> {
    fn or_setup(self) -> Result<T, i32>;
}

impl<T, E: std::fmt::Display> OrSetup<T> for Result<T, E> {
    fn or_setup(self) -> Result<T, i32> {
        self.map_err(|e| setup_failed(&e))
    }
}

#[derive(Subcommand, Debug)]
pub enum ConfigCmd {
    /// Validate a machine configuration and print what it describes.
    ///
    /// Example: `cncgw config check config/lathe.toml`, `cncgw config check --json`,
    /// `cncgw config check config/lathe-modbus.toml --bus modbus-tcp://192.168.1.10:502`
    Check {
        /// The file (default: the embedded config/lathe.toml).
        file: Option<PathBuf>,
        /// Print JSON.
        #[arg(long)]
        json: bool,
        /// A live Modbus link (`modbus-tcp://HOST:PORT`, `modbus-rtu://DEVICE?baud=…`): every
        /// axis is put on it and every register of its map is read and each writable one
        /// written back (nothing moves); each one that fails is listed (docs/MODBUS_MAPS.md).
        #[arg(long)]
        bus: Option<String>,
    },
}

/// `--config` with `--bus` applied: a `modbus-tcp://…` / `modbus-rtu://…` bus puts every
/// axis on that link (see `mbus`). Other buses are opened by `open_raw`.
pub fn machine_config(m: &MachineArgs) -> Result<(crate::config::MachineConfig, String), String> {
    let (mut cfg, text) = load_config(m.config.as_deref())?;
    mbus::apply_bus(&mut cfg, m.bus_kind()?.as_ref());
    Ok((cfg, text))
}

/// Load the machine config and its text (the emulator builds its drives from the same text).
pub fn load_config(path: Option<&std::path::Path>) -> Result<(crate::config::MachineConfig, String), String> {
    match path {
        None => Ok((crate::config::MachineConfig::embedded(), crate::config::EMBEDDED_LATHE.to_string())),
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| format!("{}: cannot read: {e}", p.display()))?;
            let cfg = crate::config::MachineConfig::from_toml(&p.display().to_string(), &text).map_err(|e| e.to_string())?;
            Ok((cfg, text))
        }
    }
}

fn init_tracing(verbose: u8) {
    let default = match verbose {
        0 => "warn",
        1 => "info",
        _ => "debug",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    // Colour only for a person at a terminal: not into files, pipes or the journal, and never
    // with NO_COLOR set (no-color.org).
    use std::io::IsTerminal;
    let ansi = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(ansi).try_init();
}

/// A read-only command whose output goes to a pipe closed early (`cncgw drive status 1 |
/// head`) ends quietly, as Unix tools do, instead of panicking in `println!`: the default
/// SIGPIPE action. Never for a command that moves or holds drives (run, jog, enable …): it
/// must stop them under control whatever happens to its output.
fn quiet_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: sets a signal's disposition to its default; no handler runs our code.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// `cncgw opcua-hash`: the password on standard input's first line → its PHC string.
fn opcua_hash() -> i32 {
    let mut line = String::new();
    if let Err(e) = std::io::stdin().read_line(&mut line) {
        eprintln!("error: cannot read the password from standard input: {e}");
        return exit::SETUP;
    }
    let pw = line.trim_end_matches(['\r', '\n']);
    if pw.is_empty() {
        eprintln!("error: give the password on standard input (an empty password is refused)");
        return exit::INPUT;
    }
    #[cfg(feature = "opcua")]
    match crate::opcua::hash_password(pw) {
        Ok(h) => {
            println!("{h}");
            exit::OK
        }
        Err(e) => {
            eprintln!("error: {e}");
            exit::SETUP
        }
    }
    #[cfg(not(feature = "opcua"))]
    {
        eprintln!("error: this cncgw was built without the OPC UA server (cargo feature `opcua`)");
        exit::SETUP
    }
}

/// Entry point; returns the process exit code.
pub fn main() -> i32 {
    let cli = Cli::parse();
    init_tracing(cli.verbose);
    if matches!(
        cli.cmd,
        Command::Scan { .. }
            | Command::Drive(DriveCmd::Status { .. })
            | Command::Monitor { .. }
            | Command::Config(ConfigCmd::Check { .. })
            | Command::Plan { .. }
            | Command::Offsets(offsets::OffsetsCmd::List { .. })
            | Command::Alarms { .. }
            | Command::Sdo(SdoCmd::Read { .. })
            | Command::Od(_)
            | Command::Completions { .. }
            | Command::Man { .. }
    ) {
        quiet_on_closed_pipe();
    }
    match cli.cmd {
        Command::Run { program, machine, json, state_dir, trace, max_blocks, tools, rt, op, restart } => {
            let files = run::RunFiles { state_dir: state_dir.as_deref(), trace: trace.as_deref(), tools: tools.as_deref(), restart: restart.at() };
            run::run(&program, &machine, json, files, max_blocks, &rt, &op)
        }
        Command::TapTest { tap, machine, op } => taptest::tap_test(&machine, &tap, &op),
        Command::Identify { args, machine } => identify::run(&machine, &args),
        Command::Trace(TraceCmd::Plot { file, out }) => run::trace_plot(&file, &out),
        Command::Plan(args) => plan::plan(&args),
        Command::Preview { program, out, config, width, tools, stock, state_dir } => {
            preview::preview(&program, config.as_deref(), tools.as_deref(), state_dir.as_deref(), &out, width, stock)
        }
        Command::Config(ConfigCmd::Check { file, json, bus }) => config_check(file.as_deref(), json, bus.as_deref()),
        Command::Scan { machine, json } => diag::scan(&machine, json),
        Command::Sdo(SdoCmd::Read { node, index, sub, r#type, out, machine, json }) => {
            diag::sdo_read(&machine, node, index, sub, r#type, out.as_deref(), json)
        }
        Command::Sdo(SdoCmd::Write { node, index, sub, r#type, value, yes, machine }) => {
            diag::sdo_write(&machine, node, index, sub, r#type, &value, yes)
        }
        Command::Nmt { command, target, machine, json } => diag::nmt(&machine, command, target, json),
        Command::Drive(DriveCmd::Status { node, machine, json }) => diag::drive_status(&machine, node, json),
        Command::Drive(DriveCmd::Enable { node, yes, machine }) => service::drive_power(&machine, node, service::PowerGoal::Enable, yes),
        Command::Drive(DriveCmd::Disable { node, machine }) => service::drive_power(&machine, node, service::PowerGoal::Disable, false),
        Command::Drive(DriveCmd::FaultReset { node, machine }) => service::drive_power(&machine, node, service::PowerGoal::FaultReset, false),
        Command::Drive(DriveCmd::Home { node, home, yes, machine }) => service::drive_home(&machine, node, &home, yes),
        Command::Home(c) => home::home(&c),
        Command::Jog { axis, to, by, speed, yes, machine } => service::jog(&machine, &axis, to, by, speed, yes),
        Command::Buslog { out, seconds, machine } => service::buslog(&machine, &out, seconds),
        Command::Monitor { seconds, once, interval_ms, json, machine } => service::monitor(&machine, seconds, once, interval_ms, json),
        Command::Od(OdCmd::Dump { node, eds, machine, json }) => diag::od_dump(&machine, node, eds.as_deref(), json),
        Command::Od(OdCmd::Check { node, eds, machine, json }) => diag::od_check(&machine, node, &eds, json),
        Command::Alarms { list: true, json, .. } => alarm_catalogue(json),
        Command::Alarms { machine, state_dir, since, json, list: false } => alarms(&machine, state_dir.as_deref(), since.as_deref(), json),
        Command::Offsets(cmd) => offsets::main(cmd),
        Command::Mdi(a) => mdi::mdi(&a),
        Command::OpcuaHash => opcua_hash(),
        Command::Completions { shell } => {
            use clap::CommandFactory;
            clap_complete::generate(shell, &mut Cli::command(), "cncgw", &mut std::io::stdout());
            0
        }
        Command::Man { dir } => {
            let r = match &dir {
                Some(d) => manpages::write_all(d).map(|files| println!("{} manual pages written to {}", files.len(), d.display())),
                None => manpages::print_top(&mut std::io::stdout()),
            };
            match r {
                Ok(()) => exit::OK,
                Err(e) => {
                    eprintln!("error: cannot write the manual pages: {e}");
                    exit::SETUP
                }
            }
        }
    }
}

/// `cncgw alarms`: the alarm history of the machine and place `machine` names.
/// `cncgw alarms --list`: the catalogue, grouped by range, for looking a number up.
fn alarm_catalogue(json: bool) -> i32 {
    if json {
        println!("{}", serde_json::to_string_pretty(crate::alarm::CATALOGUE).unwrap_or_default());
        return exit::OK;
    }
    let mut group = "";
    for e in crate::alarm::CATALOGUE {
        if e.group != group {
            if !group.is_empty() {
                println!();
            }
            group = e.group;
            println!("{group}");
        }
        println!("{:>5}  {:<24} {}", e.number, e.name, e.doc);
    }
    exit::OK
}

fn alarms(machine: &MachineArgs, state_dir: Option<&std::path::Path>, since: Option<&str>, json: bool) -> i32 {
    let (cfg, _) = match machine_config(machine).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    let since = match since.map(parse_since).transpose() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: --since: {e}");
            return exit::INPUT;
        }
    };
    let Some(dir) = state_dir.map(std::path::Path::to_path_buf).or_else(crate::persist::default_state_dir) else {
        eprintln!("error: no state directory: give --state-dir or set CNCGW_STATE_DIR");
        return exit::SETUP;
    };
    let place = crate::persist::StatePlace::new(&dir, &cfg.machine.name, &run::run_place(&cfg, machine));
    let history = place.alarm_history();
    let records = match history.read(since) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {}: {e}", history.path.display());
            return exit::SETUP;
        }
    };
    if json {
        println!("{}", serde_json::to_string_pretty(&records).unwrap_or_default());
    } else if records.is_empty() {
        let when = if since.is_some() { " in that time" } else { "" };
        println!("no alarms recorded for {}{when} ({})", cfg.machine.name, history.path.display());
    } else {
        for r in &records {
            let at = match (&r.file, r.line) {
                (Some(f), Some(l)) => format!("{f}:{l}"),
                _ => r.program.clone(),
            };
            println!("{}  {:04}  {at}  {}", r.time, r.number, r.message);
        }
    }
    exit::OK
}

/// `--since`: a duration back from now (humantime: `8h`, `30min`) or an RFC 3339 time.
fn parse_since(s: &str) -> Result<std::time::SystemTime, String> {
    if let Ok(t) = humantime::parse_rfc3339_weak(s) {
        return Ok(t);
    }
    let d = humantime::parse_duration(s).map_err(|e| format!("`{s}` is neither a duration (8h, 30min) nor a time (2026-11-25T06:00:00Z): {e}"))?;
    std::time::SystemTime::now().checked_sub(d).ok_or_else(|| format!("`{s}` reaches back before 1970"))
}

/// One axis in `config check`'s words and units: kind, where it is, scale, speed and
/// acceleration in the units the configuration takes them in, the travel (X as a radius there).
fn axis_line(name: &str, a: &crate::config::AxisConfig) -> String {
    use crate::config::AxisKind;
    let (kind, unit, speed, accel) = match a.kind {
        AxisKind::Spindle => ("spindle", "degree", "rpm", "rpm/s"),
        AxisKind::Linear => ("linear axis", "mm", "mm/min", "mm/s²"),
    };
    let at = match &a.modbus {
        Some(l) => {
            let profile = format!("{:?}", a.modbus_profile).to_lowercase().replace("cia402", "CiA 402");
            format!("Modbus link {l} unit {} ({profile} register map)", a.node)
        }
        None => format!("CANopen node {}", a.node),
    };
    let travel = match (a.kind, a.min, a.max) {
        (AxisKind::Spindle, ..) => String::new(),
        (_, None, None) => ", no travel limits".to_string(),
        (_, lo, hi) => {
            let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v}"));
            let radius = if name == "x" { " (radius)" } else { "" };
            format!(", travel {} … {} mm{radius}", f(lo), f(hi))
        }
    };
    format!(
        "  axis {name}: {kind} on {at}, {} counts/{unit}, max speed {} {speed}, max accel {} {accel}{travel}",
        a.counts_per_unit, a.max_speed, a.max_accel
    )
}

/// Following-error windows below what an axis' identified response (`[axes.NAME.response]`)
/// lags at its maximum speed and acceleration: the drive would fault at full speed.
fn response_warnings(cfg: &crate::config::MachineConfig) -> Vec<String> {
    let mut out = Vec::new();
    for (name, a) in &cfg.axes {
        let Some(r) = a.response else { continue };
        let resp = crate::sync::identify::Response {
            delay_cycles: r.delay_cycles.max(0.0).floor() as u32,
            delay_fraction: r.delay_cycles.max(0.0).fract(),
            feed_forward: r.feed_forward,
            time_constant_s: r.time_constant_ms * 1e-3,
            vaf: 1.0,
            samples: 0,
            velocity_lag: 0.0,
            accel_lag: r.accel_lag_ms2 * 1e-6,
        };
        let resp = crate::sync::identify::Response { velocity_lag: resp.velocity_lag_model(cfg.cycle_s()), ..resp };
        // (The configured response carries the model; its lag is the model's.)
        let need = identify::proposed_window(cfg, name, &resp);
        if a.following_error < need {
            out.push(format!(
                "axes.{name}.following_error = {} is below 3 × the lag its response predicts at max_speed and max_accel; set at least {need:.4}",
                a.following_error
            ));
        }
    }
    out
}

/// `config check --bus modbus-…`: every axis on that link, and its map tried on the drives.
fn config_check_live(
    mut cfg: crate::config::MachineConfig,
    bus: Option<&str>,
) -> Result<(crate::config::MachineConfig, Option<Vec<mapcheck::AxisCheck>>), String> {
    let Some(b) = bus else { return Ok((cfg, None)) };
    if !mbus::apply_bus(&mut cfg, Some(&BusKind::parse(b)?)) {
        return Err(format!("config check --bus {b}: only a Modbus link (modbus-tcp://HOST:PORT, modbus-rtu://DEVICE) is checked live"));
    }
    let live = mapcheck::check_live(&cfg);
    Ok((cfg, Some(live)))
}

fn config_check(file: Option<&std::path::Path>, json: bool, bus: Option<&str>) -> i32 {
    let name = file.map(|p| p.display().to_string()).unwrap_or_else(|| "embedded config/lathe.toml".into());
    if let Some(Err(e)) = file.map(std::fs::metadata) {
        eprintln!("error: cannot read {name}: {e}");
        return exit::INPUT;
    }
    let cfg = match load_config(file) {
        Ok((cfg, _)) => cfg,
        Err(e) => {
            if json {
                println!("{}", serde_json::json!({"file": name, "ok": false, "error": e}));
            } else {
                eprintln!("error: {e}");
            }
            return exit::NOT_MET;
        }
    };
    let (cfg, live) = match config_check_live(cfg, bus) {
        Ok(v) => v,
        Err(e) => {
            eprintln!("error: {e}");
            return exit::INPUT;
        }
    };
    // Everything `run` would refuse before it touches a drive, checked here too.
    let problems = if cfg.has_canopen() {
        crate::drives::canopen::CanOpenMaster::new(cncgw_bus::transport::inproc::InprocBus::new().endpoint(), &cfg).offline_check(cfg.bus.bitrate)
    } else {
        Vec::new()
    };
    let mut warnings = response_warnings(&cfg);
    warnings.extend(mapcheck::map_warnings(&cfg));
    let mut text = Vec::new();
    if problems.is_empty() {
        text.push(format!("{name}: ok — {}", cfg.machine.name));
    } else {
        text.push(format!("{name}: run would refuse it ({} problem(s)) — {}", problems.len(), cfg.machine.name));
        text.extend(problems.iter().map(|p| format!("  {p}")));
    }
    text.extend(warnings.iter().map(|w| format!("  warning: {w}")));
    if cfg.has_canopen() {
        text.push(format!("  cycle {} ms, CANopen bus {} at {} bit/s", cfg.machine.cycle_ms, cfg.bus.interface, cfg.bus.bitrate));
    } else {
        text.push(format!("  cycle {} ms, no CANopen bus (every drive on a Modbus link)", cfg.machine.cycle_ms));
    }
    let n_can = cfg.axes.values().filter(|a| a.modbus.is_none()).count();
    let mut can_load = None;
    if n_can > 0 {
        let modules = cfg.io.resolve().unwrap_or_default().canopen_modules();
        let mut frames = crate::drives::canopen::master::cyclic_frames_io(n_can, &modules);
        let specs = crate::drives::canopen::master::NodeSpec::from_config(&cfg);
        let ff = specs.iter().filter(|s| s.friction).count();
        let sp = specs.iter().filter(|s| s.spindle && !s.friction).count();
        crate::drives::canopen::master::add_torque_frames(&mut frames, specs.iter());
        let load = crate::bus::busload::load(&frames, cfg.cycle_s(), cfg.bus.bitrate);
        can_load = Some(load);
        text.push(format!(
            "  worst-case CANopen bus load {:.1} % ({} drives, one 6-byte RPDO and TPDO each + SYNC per cycle{}{}{}){}",
            load * 100.0,
            n_can,
            if ff == 0 { String::new() } else { format!(", {ff} with friction feed-forward (8-byte RPDO, a torque read)") },
            if sp == 0 { String::new() } else { format!(", {sp} spindle torque read") },
            if modules.is_empty() { String::new() } else { format!(", {} CiA 401 I/O module(s)' outputs and inputs", modules.len()) },
            if load > 0.8 { " — OVER 80 %: lengthen the cycle" } else { "" }
        ));
    }
    let mut links = Vec::new();
    for pl in crate::drives::modbus::ModbusDrives::new(&cfg).planned_links() {
        let (lname, what, tx, rtu) = (pl.name, pl.what, pl.transactions, pl.rtu);
        let link_cycle_ms = rtu.map(|r| r.1);
        match rtu {
            Some((s, c)) => text.push(format!(
                "  Modbus link {lname}: {what}, {tx} transactions per cycle take {:.2} ms on the line → link cycle {c} ms (with {:.0} % margin)",
                s * 1e3,
                (crate::drives::modbus::link::RTU_MARGIN - 1.0) * 100.0
            )),
            None => text
                .push(format!("  Modbus link {lname}: {what}, {tx} transactions per cycle; the cycle is measured from the round trip at start-up")),
        }
        links.push(serde_json::json!({
            "link": lname, "what": what, "transactions_per_cycle": tx,
            "line_time_ms": rtu.map(|r| r.0 * 1e3), "link_cycle_ms": link_cycle_ms,
        }));
    }
    let mut axes = Vec::new();
    for (aname, a) in &cfg.axes {
        text.push(axis_line(aname, a));
        axes.push(serde_json::json!({
            "axis": aname, "kind": format!("{:?}", a.kind).to_lowercase(), "node": a.node,
            "modbus_link": a.modbus, "counts_per_unit": a.counts_per_unit,
            "min": a.min, "max": a.max, "max_speed": a.max_speed, "max_accel": a.max_accel,
            "position_unit": if a.kind == crate::config::AxisKind::Spindle { "deg" } else { "mm" },
            "speed_unit": if a.kind == crate::config::AxisKind::Spindle { "rpm" } else { "mm/min" },
            "accel_unit": if a.kind == crate::config::AxisKind::Spindle { "rpm/s" } else { "mm/s²" },
        }));
    }
    if json {
        println!(
            "{}",
            serde_json::json!({
                "file": name, "ok": problems.is_empty(), "problems": problems, "warnings": warnings, "machine": cfg.machine.name, "cycle_ms": cfg.machine.cycle_ms,
                "bus": cfg.bus.interface, "bitrate": cfg.bus.bitrate, "canopen_bus_load": can_load,
                "canopen_drives": n_can, "modbus_links": links, "axes": axes,
                "live": live.as_ref().map(|l| l.iter().map(mapcheck::AxisCheck::json).collect::<Vec<_>>()),
            })
        );
    } else {
        for l in text {
            println!("{l}");
        }
        for l in live.iter().flatten().flat_map(mapcheck::AxisCheck::lines) {
            println!("  {l}");
        }
    }
    let live_failed = live.iter().flatten().any(|a| a.error.is_some() || !a.findings.is_empty());
    if live_failed && !json {
        println!("  the live drives do not have the registers listed above: run would stop at start-up; fix the maps (docs/MODBUS_MAPS.md)");
    }
    if live_failed {
        exit::NOT_MET
    } else if problems.is_empty() {
        exit::OK
    } else {
        exit::NOT_MET
    }
}

#[cfg(test)]
mod tests {
    use super::response_warnings;
    use crate::config::{MachineConfig, EMBEDDED_LATHE};

    /// A spindle drive with full feed-forward (no lag at constant speed) that lags a·τ² while
    /// it accelerates (τ 40 ms: 1600 ms², 57.6° at the lathe's 6000 rpm/s): a 150° window is
    /// below 3 × that, 180° is not; without `accel_lag_ms2` nothing is predicted.
    #[test]
    fn a_window_below_the_lag_while_accelerating_is_warned() {
        let warned = |window: &str, accel: &str| {
            let text = EMBEDDED_LATHE.replace("following_error = 180.0 ", &format!("following_error = {window} "));
            let text = format!("{text}\n[axes.s1.response]\ndelay_cycles = 3.0\nfeed_forward = 1.0\ntime_constant_ms = 80.0\n{accel}");
            let cfg = MachineConfig::from_toml("t.toml", &text).unwrap();
            response_warnings(&cfg).iter().any(|w| w.starts_with("axes.s1.following_error"))
        };
        assert!(warned("150.0", "accel_lag_ms2 = 1600.0\n"));
        assert!(!warned("180.0", "accel_lag_ms2 = 1600.0\n"));
        assert!(!warned("150.0", ""));
    }
}
