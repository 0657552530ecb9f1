//! `sim-drives`: emulated CiA 402 amplifiers on a real (or virtual) CAN bus, in real time.
//!
//!     sim-drives --bus vcan0                 # the drives of config/lathe.toml
//!     sim-drives --bus can0 --config my.toml # drives from a sim-drives or machine config
//!     sim-drives --print-default-config      # commented TOML to start from
//!     sim-drives --socketcand 127.0.0.1:29536 # a virtual bus `can0` for socketcand clients
//!     sim-drives --bus vcan0 --log bus.log   # also write a candump log
//!     sim-drives --modbus-tcp 127.0.0.1:5020  # the drives as Modbus TCP units (id = node)
//!     sim-drives --modbus-rtu /dev/pts/5 --baud 115200 --parity none --stop-bits 1
//!     sim-drives --config config/lathe-modbus.toml --modbus-tcp 127.0.0.1:5020 [--modbus-link tcp]

use clap::Parser;
use sim_drives::SimConfig;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(Parser)]
#[command(
    name = "sim-drives",
    version,
    about = "Emulated CiA 402 servo and spindle amplifiers on CANopen, in real time (SocketCAN or a socketcand server)"
)]
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
    /// silent-ms[=N] (none: for good), pdo-drop-permille=N, tpdo-delay-us=N, ip-disable
    /// (an IP drive's buffer off: statusword bit 12 drops); @MS: that
    /// long after the start (default at once). Same effect as the SDO write to 0x2100.
    #[arg(long = "fault", value_name = "SPEC")]
    faults: Vec<String>,
    /// Serve the drives over Modbus TCP on this address instead of CAN (unit id = node id;
    /// register map per drive: `modbus_profile` of the config, default cia402).
    #[arg(long, value_name = "ADDR:PORT", conflicts_with_all = ["socketcand", "modbus_rtu", "log"])]
    modbus_tcp: Option<String>,
    /// Serve the drives over Modbus RTU on this serial device instead of CAN, e.g.
    /// /dev/ttyUSB0 or one end of `socat -d -d pty,raw,echo=0 pty,raw,echo=0`.
    #[arg(long, value_name = "DEVICE", conflicts_with_all = ["socketcand", "log"])]
    modbus_rtu: Option<String>,
    /// With a cncgw machine config: serve only the axes on this Modbus link (their
    /// `modbus = "LINK"`). Default: every axis on some Modbus link.
    #[arg(long, value_name = "LINK")]
    modbus_link: Option<String>,
    /// RTU baud rate.
    #[arg(long, default_value_t = 115_200, value_name = "BAUD", requires = "modbus_rtu")]
    baud: u32,
    /// RTU parity: none, even or odd.
    #[arg(long, default_value = "none", value_name = "none|even|odd", requires = "modbus_rtu")]
    parity: sim_drives::modbus::Parity,
    /// RTU stop bits: 1 or 2.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2), requires = "modbus_rtu")]
    stop_bits: u8,
    /// Write every frame on the bus to FILE in candump's log-file format.
    #[arg(long, value_name = "FILE")]
    log: Option<std::path::PathBuf>,
    /// A sim-drives config (as --print-default-config prints) or a cncgw machine config
    /// (its [axes.*] tables). Default: the drives of config/lathe.toml.
    #[arg(long)]
    config: Option<std::path::PathBuf>,
    /// Also serve the Modbus TCP I/O units of the --config machine config (`[io.devices.*]
    /// modbus = "ADDR:PORT"`, wired as its `emulate` table says), each on its address.
    #[arg(long, requires = "config")]
    modbus_io: bool,
    /// Print the default configuration as commented TOML and exit.
    #[arg(long)]
    print_default_config: bool,
    /// More logging (-v: debug, -vv: trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count)]
    verbose: u8,
}

fn load(path: &std::path::Path) -> Result<SimConfig, String> {
    // Each server below takes the drives of its bus (a mixed machine has both).
    SimConfig::from_file(path)
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
    // The drives of this bus: a mixed machine's Modbus axes are not on the CAN bus, and each
    // Modbus link is its own server.
    let cfg = if args.modbus_tcp.is_some() || args.modbus_rtu.is_some() {
        match cfg.modbus_drives(args.modbus_link.as_deref()) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("sim-drives: --modbus-link: {e}");
                return ExitCode::from(2);
            }
        }
    } else if args.modbus_link.is_some() {
        eprintln!("sim-drives: --modbus-link needs --modbus-tcp or --modbus-rtu");
        return ExitCode::from(2);
    } else {
        cfg.canopen_drives()
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
    let mut io_servers = Vec::new();
    if args.modbus_io {
        let units = args
            .config
            .as_deref()
            .map(|p| std::fs::read_to_string(p).map_err(|e| e.to_string()).and_then(|t| sim_drives::io401::from_machine_toml(&t)));
        for (addr, _unit, emu) in units.and_then(|r| r.ok()).map(|r| r.1).unwrap_or_default() {
            match sim_drives::modbus_io::serve(&addr, emu, stop.clone()) {
                Ok(s) => io_servers.push(s),
                Err(e) => {
                    eprintln!("sim-drives: --modbus-io {addr}: {e}");
                    return ExitCode::FAILURE;
                }
            }
        }
    }
    if args.modbus_tcp.is_some() || args.modbus_rtu.is_some() {
        return serve_modbus(&args, cfg, faults, stop);
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
    // A machine config's CiA 401 I/O modules ([io.devices.*] canopen_node) on the same bus.
    let io = match args
        .config
        .as_deref()
        .map(|p| std::fs::read_to_string(p).map_err(|e| e.to_string()).and_then(|t| sim_drives::io401::from_machine_toml(&t)))
    {
        Some(Ok((can, _))) => can,
        Some(Err(e)) => {
            eprintln!("sim-drives: {e}");
            return ExitCode::from(2);
        }
        None => Vec::new(),
    };
    match sim_drives::run_realtime_with_io(bus, cfg, stop, faults, io) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("sim-drives: {e}");
            ExitCode::FAILURE
        }
    }
}

/// `--modbus-tcp` / `--modbus-rtu`: serve until SIGINT/SIGTERM.
fn serve_modbus(args: &Args, cfg: SimConfig, faults: Vec<sim_drives::FaultAt>, stop: Arc<AtomicBool>) -> ExitCode {
    let started = if let Some(addr) = &args.modbus_tcp {
        match std::net::ToSocketAddrs::to_socket_addrs(addr.as_str()).map(|mut a| a.next()) {
            Ok(Some(a)) => sim_drives::modbus::serve_tcp_with_faults(a, cfg, faults, stop),
            Ok(None) | Err(_) => {
                eprintln!("sim-drives: --modbus-tcp {addr}: not an address (expected e.g. 127.0.0.1:5020)");
                return ExitCode::from(2);
            }
        }
    } else if let Some(dev) = &args.modbus_rtu {
        let line = sim_drives::modbus::RtuLine { baud: args.baud, parity: args.parity, stop_bits: args.stop_bits };
        sim_drives::modbus::serve_rtu_with_faults(dev, line, cfg, faults, stop)
    } else {
        return ExitCode::from(2);
    };
    let server = match started {
        Ok(s) => s,
        Err(e) => {
            eprintln!("sim-drives: {e}");
            return ExitCode::FAILURE;
        }
    };
    match server.join() {
        Ok(()) => {
            tracing::info!("sim-drives: Modbus server stopped");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("sim-drives: {e}");
            ExitCode::FAILURE
        }
    }
}
