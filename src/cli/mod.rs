//! The `cncgw` command line.

pub mod run;

use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(name = "cncgw", version, about = "CNC lathe controller core and fieldbus gateway (CANopen CiA 402)", long_about = None)]
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
    /// as `vcan0` or `can0`, or `socketcand://HOST:PORT/IFACE`. Default: the config's
    /// bus.interface.
    #[arg(long, value_name = "BUS")]
    pub bus: Option<String>,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a part program on the machine.
    ///
    /// Example: `cncgw run examples/first_part.nc` (embedded emulated drives), or
    /// `cncgw run --bus vcan0 examples/first_part.nc` against `sim-drives --bus vcan0`.
    Run {
        /// The part program.
        program: PathBuf,
        #[command(flatten)]
        machine: MachineArgs,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Print the canonical moves of a program without running anything.
    ///
    /// Example: `cncgw plan examples/first_part.nc --format text`
    Plan {
        program: PathBuf,
        #[arg(long, short = 'c', value_name = "FILE")]
        config: Option<PathBuf>,
        /// Output format: one JSON object per line, or text.
        #[arg(long, default_value = "jsonl", value_parser = ["jsonl", "text"])]
        format: String,
    },
    /// Configuration commands.
    #[command(subcommand)]
    Config(ConfigCmd),
}

#[derive(Subcommand, Debug)]
pub enum ConfigCmd {
    /// Validate a machine configuration and print what it describes.
    Check {
        /// The file (default: the embedded config/lathe.toml).
        file: Option<PathBuf>,
    },
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
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).try_init();
}

/// Entry point; returns the process exit code.
pub fn main() -> i32 {
    let cli = Cli::parse();
    init_tracing(cli.verbose);
    match cli.cmd {
        Command::Run { program, machine, json } => run::run(&program, &machine, json),
        Command::Plan { program, config, format } => plan(&program, config.as_deref(), &format),
        Command::Config(ConfigCmd::Check { file }) => config_check(file.as_deref()),
    }
}

fn plan(program: &std::path::Path, config: Option<&std::path::Path>, format: &str) -> i32 {
    use std::io::Write;
    let (cfg, _) = match load_config(config) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return 2;
        }
    };
    let interp = match crate::interp::Interpreter::from_file(program, &cfg) {
        Ok(i) => i,
        Err(alarms) => {
            for a in &alarms {
                eprintln!("{a}");
            }
            return 2;
        }
    };
    let out = std::io::stdout();
    let mut out = std::io::BufWriter::new(out.lock());
    for m in interp {
        match m {
            Ok(m) => {
                let line = if format == "text" { crate::interp::plan::move_to_text(&m) } else { crate::interp::plan::move_to_json(&m) };
                if writeln!(out, "{line}").is_err() {
                    return 0; // stdout closed (e.g. piped into head)
                }
            }
            Err(a) => {
                let _ = out.flush();
                eprintln!("{a}");
                return 2;
            }
        }
    }
    0
}

fn config_check(file: Option<&std::path::Path>) -> i32 {
    match load_config(file) {
        Ok((cfg, _)) => {
            println!("{}: ok — {}", file.map(|p| p.display().to_string()).unwrap_or_else(|| "embedded config/lathe.toml".into()), cfg.machine.name);
            println!("  cycle {} ms, bus {} at {} bit/s", cfg.machine.cycle_ms, cfg.bus.interface, cfg.bus.bitrate);
            let frames = crate::bus::busload::csp_frames(cfg.axes.len(), 6);
            let load = crate::bus::busload::load(&frames, cfg.cycle_s(), cfg.bus.bitrate);
            println!(
                "  worst-case CANopen bus load {:.1} % ({} drives, one 6-byte RPDO and TPDO each + SYNC per cycle){}",
                load * 100.0,
                cfg.axes.len(),
                if load > 0.8 { " — OVER 80 %: lengthen the cycle" } else { "" }
            );
            for (name, a) in &cfg.axes {
                println!(
                    "  axis {name}: {:?} node {} {} counts/unit, max speed {}, max accel {}",
                    a.kind, a.node, a.counts_per_unit, a.max_speed, a.max_accel
                );
            }
            0
        }
        Err(e) => {
            eprintln!("error: {e}");
            2
        }
    }
}
