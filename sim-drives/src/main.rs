//! `sim-drives`: emulated CiA 402 amplifiers on a real (or virtual) CAN bus, in real time.
//!
//!     sim-drives --bus vcan0                 # the drives of config/lathe.toml
//!     sim-drives --bus can0 --config my.toml # drives from a sim-drives or machine config
//!     sim-drives --print-default-config      # commented TOML to start from
//!     sim-drives --socketcand 127.0.0.1:29536 # a virtual bus `can0` for socketcand clients
//!     sim-drives --bus vcan0 --log bus.log   # also write a candump log

use clap::Parser;
use sim_drives::SimConfig;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Parser)]
#[command(name = "sim-drives", version, about = "Emulated CiA 402 servo and spindle amplifiers on CANopen, in real time (SocketCAN or a socketcand server)")]
struct Args {
    /// CAN interface to serve, e.g. vcan0 or can0 (ignored with --socketcand).
    #[arg(long, default_value = "vcan0")]
    bus: String,
    /// Host a virtual bus as a socketcand-protocol server on this address instead of
    /// using a CAN interface, e.g. 127.0.0.1:29536. Clients join with
    /// `socketcand://127.0.0.1:29536/can0` (cncgw) or python-can's `socketcand` interface.
    #[arg(long, value_name = "ADDR:PORT")]
    socketcand: Option<String>,
    /// Name of the bus the socketcand server hosts (what clients `< open >`).
    #[arg(long, default_value = "can0", value_name = "NAME")]
    socketcand_bus: String,
    /// Inject a fault: NODE:NAME[=VALUE][@MS], repeatable. NAME: raise=CODE,
    /// encoder-lost, undervoltage, overcurrent, jam-mnm=N, heartbeat-stop,
    /// silent-ms[=N] (none: for good), pdo-drop-permille=N, tpdo-delay-us=N; @MS: that
    /// long after the start (default at once). Same effect as the SDO write to 0x2100.
    #[arg(long = "fault", value_name = "SPEC")]
    faults: Vec<String>,
    /// Write every frame on the bus to FILE in candump's log-file format.
    #[arg(long, value_name = "FILE")]
    log: Option<std::path::PathBuf>,
    /// A sim-drives config (as --print-default-config prints) or a cncgw machine config
    /// (its [axes.*] tables). Default: the drives of config/lathe.toml.
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Print the default configuration as commented TOML and exit.
    #[arg(long)]
    print_default_config: bool,
    /// More logging (-v: debug, -vv: trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count)]
    verbose: u8,
}

fn load(path: &std::path::Path) -> Result<SimConfig, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: cannot read: {e}", path.display()))?;
    // A machine config has [axes.*]; a sim-drives config has [[drive]].
    let is_machine = text.lines().any(|l| l.trim_start().starts_with("[axes."));
    let r = if is_machine { SimConfig::from_machine_toml(&text) } else { SimConfig::from_toml(&text) };
    r.map_err(|e| format!("{}: {e}", path.display()))
}

fn main() -> ExitCode {
    let args = Args::parse();
    if args.print_default_config {
        print!("{}", SimConfig::default_lathe().to_commented_toml());
        return ExitCode::SUCCESS;
    }
    let level = match args.verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();

    let cfg = match &args.config {
        Some(p) => match load(p) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("sim-drives: {e}");
                return ExitCode::from(2);
            }
        },
        None => SimConfig::default_lathe(),
    };
    let mut faults = Vec::new();
    for spec in &args.faults {
        match sim_drives::parse_fault(spec) {
            Ok(f) if cfg.drives.iter().any(|d| d.node == f.node) => faults.push(f),
            Ok(f) => {
                eprintln!("sim-drives: --fault {spec}: no drive with node {} in the configuration", f.node);
                return ExitCode::from(2);
            }
            Err(e) => {
                eprintln!("sim-drives: {e}");
                return ExitCode::from(2);
            }
        }
    }
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [2, 15] {
        // SIGINT, SIGTERM. The action only stores to an atomic: async-signal-safe.
        let s = stop.clone();
        // SAFETY: the handler does nothing but an atomic store.
        if let Err(e) = unsafe { signal_hook_registry::register(sig, move || s.store(true, Ordering::Relaxed)) } {
            eprintln!("sim-drives: cannot install signal handler {sig}: {e}");
            return ExitCode::FAILURE;
        }
    }
    let opened: Result<(Box<dyn cncgw_bus::CanBus>, String), cncgw_bus::BusError> = match &args.socketcand {
        Some(addr) => sim_drives::socketcand::SocketcandServer::bind(addr, &args.socketcand_bus)
            .map(|s| (Box::new(s) as Box<dyn cncgw_bus::CanBus>, args.socketcand_bus.clone())),
        None => cncgw_bus::transport::socketcan::SocketCan::open(&args.bus).map(|b| (Box::new(b) as Box<dyn cncgw_bus::CanBus>, args.bus.clone())),
    };
    let (mut bus, iface) = match opened {
        Ok(b) => b,
        Err(e) => {
            eprintln!("sim-drives: {e}");
            return ExitCode::FAILURE;
        }
    };
    if let Some(path) = &args.log {
        match std::fs::File::create(path) {
            Ok(f) => bus = Box::new(sim_drives::buslog::LoggedBus::new(bus, &iface, Box::new(std::io::BufWriter::new(f)))),
            Err(e) => {
                eprintln!("sim-drives: --log {}: cannot create: {e}", path.display());
                return ExitCode::FAILURE;
            }
        }
    }
    match sim_drives::run_realtime_with_faults(bus, cfg, stop, faults) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sim-drives: {e}");
            ExitCode::FAILURE
        }
    }
}
