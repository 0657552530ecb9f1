//! The emulated drives as Modbus servers, over TCP or RTU (a serial line or one end of a
//! pseudo-terminal pair). The frame codec and server loop are tokio-modbus's — the same
//! codec the cncgw master uses as client; what is ours is the register maps of
//! `cncgw_bus::modbus` on top of the drives of `Core` (physics, CiA 402 state machine).
//!
//! Unit id = node id. Time runs in real time: the drives are integrated up to the wall
//! clock before every request and by a 1 ms ticker thread between requests.
//!
//! ```no_run
//! use std::sync::{atomic::AtomicBool, Arc};
//! let stop = Arc::new(AtomicBool::new(false));
//! let srv = sim_drives::modbus::serve_tcp("127.0.0.1:0".parse().unwrap(), sim_drives::SimConfig::default_lathe(), stop.clone()).unwrap();
//! println!("units 1, 2, 3 on {}", srv.local_addr().unwrap());
//! stop.store(true, std::sync::atomic::Ordering::Relaxed);
//! srv.join().unwrap();
//! ```

mod pr;
mod world;

pub use world::{COMM_TIMEOUT_CODE, MAX_READ, MAX_RW_WRITE, MAX_WRITE};

use crate::{FaultAt, SimConfig, SimDrive};
use std::io;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use tokio_modbus::server::Service;
use tokio_modbus::{ExceptionCode, Response, SlaveRequest};
use world::World;

/// Parity of an RTU line.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Parity {
    #[default]
    None,
    Even,
    Odd,
}

impl std::str::FromStr for Parity {
    type Err = String;
    fn from_str(s: &str) -> Result<Parity, String> {
        match s {
            "none" | "N" | "n" => Ok(Parity::None),
            "even" | "E" | "e" => Ok(Parity::Even),
            "odd" | "O" | "o" => Ok(Parity::Odd),
            _ => Err(format!("parity {s:?}: expected none, even or odd")),
        }
    }
}

/// Settings of an RTU line (8 data bits always, as Modbus RTU requires).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RtuLine {
    pub baud: u32,
    pub parity: Parity,
    /// 1 or 2.
    pub stop_bits: u8,
}

impl Default for RtuLine {
    fn default() -> Self {
        RtuLine { baud: 115_200, parity: Parity::None, stop_bits: 1 }
    }
}

impl RtuLine {
    /// Character and frame timing of this line (cncgw-bus' model).
    pub fn timing(&self) -> cncgw_bus::modbus::SerialTiming {
        cncgw_bus::modbus::SerialTiming { baud: self.baud, parity: self.parity != Parity::None, stop_bits: self.stop_bits }
    }
}

/// The drives and the instant their time 0 is.
struct Shared {
    world: Mutex<World>,
    start: Instant,
}

impl Shared {
    /// The world, integrated up to now.
    fn now(&self) -> MutexGuard<'_, World> {
        // A panic elsewhere while holding the lock leaves the drives usable: take them.
        let mut w = self.world.lock().unwrap_or_else(|e| e.into_inner());
        let t = self.start.elapsed().as_nanos().min(u64::MAX as u128) as u64;
        w.advance(t);
        w
    }
}

/// tokio-modbus service: one request at a time against the shared drives.
#[derive(Clone)]
struct Svc {
    shared: Arc<Shared>,
    rtu: bool,
}

impl Service for Svc {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = std::pin::Pin<Box<dyn std::future::Future<Output = Result<Option<Response>, ExceptionCode>> + Send>>;

    fn call(&self, req: SlaveRequest<'static>) -> Self::Future {
        let (r, delay) = self.shared.now().request(req.slave, &req.request, self.rtu);
        Box::pin(async move {
            // A late answer (quirk): the line or connection carries nothing else meanwhile.
            if !delay.is_zero() {
                tokio::time::sleep(delay).await;
            }
            r
        })
    }
}

/// A running Modbus server (TCP or RTU). It stops when the `stop` flag given to
/// `serve_tcp`/`serve_rtu` is set; `join` then waits for its threads.
pub struct ModbusServer {
    addr: Option<SocketAddr>,
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<io::Result<()>>>,
}

impl ModbusServer {
    /// The bound TCP address (the real port when 0 was asked); `None` for RTU.
    pub fn local_addr(&self) -> Option<SocketAddr> {
        self.addr
    }

    /// Unit ids served (= node ids).
    pub fn units(&self) -> Vec<u8> {
        self.shared.now().nodes()
    }

    /// Look at a drive as it is now (state, position, error code …), for tests.
    pub fn with_drive<R>(&self, node: u8, f: impl FnOnce(&SimDrive) -> R) -> Option<R> {
        let w = self.shared.now();
        w.drive(node).map(f)
    }

    /// Wait until the server has stopped (set the stop flag first). The first error of its
    /// threads, if any.
    pub fn join(self) -> io::Result<()> {
        let mut r = Ok(());
        for t in self.threads {
            let x = t.join().unwrap_or_else(|_| Err(io::Error::other("Modbus server thread panicked")));
            if r.is_ok() {
                r = x;
            }
        }
        r
    }
}

fn invalid(e: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, e)
}

fn start_ticker(shared: Arc<Shared>, stop: Arc<AtomicBool>) -> io::Result<JoinHandle<io::Result<()>>> {
    std::thread::Builder::new().name("modbus-physics".into()).spawn(move || {
        // Between requests the drives still move, time out and fault: integrate every ms.
        while !stop.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(1));
            drop(shared.now());
        }
        Ok(())
    })
}

async fn stopped(stop: Arc<AtomicBool>) {
    while !stop.load(Ordering::Relaxed) {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

fn runtime() -> io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread().enable_all().build()
}

/// Serve the drives of `cfg` over Modbus TCP on `addr` (port 0: any free port; see
/// `ModbusServer::local_addr`) until `stop` is set. Returns once the socket is bound.
pub fn serve_tcp(addr: SocketAddr, cfg: SimConfig, stop: Arc<AtomicBool>) -> io::Result<ModbusServer> {
    serve_tcp_with_faults(addr, cfg, Vec::new(), stop)
}

/// `serve_tcp`, injecting `faults` at their times after the start (`--fault`).
pub fn serve_tcp_with_faults(addr: SocketAddr, cfg: SimConfig, faults: Vec<FaultAt>, stop: Arc<AtomicBool>) -> io::Result<ModbusServer> {
    let world = World::new(cfg, faults).map_err(invalid)?;
    let listener = std::net::TcpListener::bind(addr)?;
    listener.set_nonblocking(true)?;
    let local = listener.local_addr()?;
    let shared = Arc::new(Shared { world: Mutex::new(world), start: Instant::now() });
    tracing::info!("sim-drives: Modbus TCP on {local}, units {:?}", shared.now().nodes());
    let mut threads = vec![start_ticker(shared.clone(), stop.clone())?];
    let sh = shared.clone();
    threads.push(std::thread::Builder::new().name("modbus-tcp".into()).spawn(move || {
        runtime()?.block_on(async move {
            let listener = tokio::net::TcpListener::from_std(listener)?;
            let server = tokio_modbus::server::tcp::Server::new(listener);
            let on_connected = move |stream: tokio::net::TcpStream, peer: SocketAddr| {
                let svc = Svc { shared: sh.clone(), rtu: false };
                async move {
                    tracing::debug!("Modbus TCP client {peer}");
                    // Each response leaves at once (one request in flight per client).
                    stream.set_nodelay(true)?;
                    Ok(Some((svc, stream)))
                }
            };
            let on_error = |e: io::Error| tracing::debug!("Modbus TCP connection ended: {e}");
            server.serve_until(&on_connected, on_error, stopped(stop)).await.map(|_| ())
        })
    })?);
    Ok(ModbusServer { addr: Some(local), shared, threads })
}

fn open_serial(path: &str, line: RtuLine) -> io::Result<tokio_serial::SerialStream> {
    let parity = match line.parity {
        Parity::None => tokio_serial::Parity::None,
        Parity::Even => tokio_serial::Parity::Even,
        Parity::Odd => tokio_serial::Parity::Odd,
    };
    let stop_bits = match line.stop_bits {
        1 => tokio_serial::StopBits::One,
        2 => tokio_serial::StopBits::Two,
        n => return Err(invalid(format!("stop bits {n}: expected 1 or 2"))),
    };
    let b = tokio_serial::new(path, line.baud).data_bits(tokio_serial::DataBits::Eight).parity(parity).stop_bits(stop_bits);
    tokio_serial::SerialStream::open(&b).map_err(|e| io::Error::other(format!("{path}: {e}")))
}

/// Serve the drives of `cfg` over Modbus RTU on the serial device `path` (a UART, or one end
/// of a `socat pty,raw,echo=0 pty,raw,echo=0` pair) until `stop` is set. Requests for unit
/// ids not configured get no answer, as on a real RS-485 line. Returns once the device is
/// open.
pub fn serve_rtu(path: &str, line: RtuLine, cfg: SimConfig, stop: Arc<AtomicBool>) -> io::Result<ModbusServer> {
    serve_rtu_with_faults(path, line, cfg, Vec::new(), stop)
}

/// `serve_rtu`, injecting `faults` at their times after the start (`--fault`).
pub fn serve_rtu_with_faults(path: &str, line: RtuLine, cfg: SimConfig, faults: Vec<FaultAt>, stop: Arc<AtomicBool>) -> io::Result<ModbusServer> {
    if line.baud == 0 {
        return Err(invalid("baud rate 0".into()));
    }
    let world = World::new(cfg, faults).map_err(invalid)?;
    let shared = Arc::new(Shared { world: Mutex::new(world), start: Instant::now() });
    let (tx, rx) = std::sync::mpsc::channel::<io::Result<()>>();
    let sh = shared.clone();
    let st = stop.clone();
    let shown = path.to_string();
    let path = path.to_string();
    let server = std::thread::Builder::new().name("modbus-rtu".into()).spawn(move || {
        let rt = match runtime() {
            Ok(rt) => rt,
            Err(e) => {
                let _ = tx.send(Err(io::Error::new(e.kind(), e.to_string())));
                return Err(e);
            }
        };
        rt.block_on(async move {
            // The stream registers with this runtime's reactor: open it here.
            let mut serial = match open_serial(&path, line) {
                Ok(s) => {
                    let _ = tx.send(Ok(()));
                    s
                }
                Err(e) => {
                    let _ = tx.send(Err(io::Error::new(e.kind(), e.to_string())));
                    return Err(e);
                }
            };
            loop {
                let svc = Svc { shared: sh.clone(), rtu: true };
                let r = tokio_modbus::server::rtu::Server::new(serial).serve_until(svc, stopped(st.clone())).await;
                match r {
                    Ok(tokio_modbus::server::Terminated::Aborted) => return Ok(()),
                    // tokio-modbus' loop ends on a frame it cannot decode or when the line
                    // closes; a real drive keeps listening: reopen the line.
                    Ok(tokio_modbus::server::Terminated::Finished) => tracing::debug!("{path}: line closed; reopening"),
                    Err(e) => tracing::warn!("{path}: {e}; reopening the line"),
                }
                loop {
                    if st.load(Ordering::Relaxed) {
                        return Ok(());
                    }
                    tokio::time::sleep(Duration::from_millis(20)).await;
                    match open_serial(&path, line) {
                        Ok(s) => {
                            serial = s;
                            break;
                        }
                        Err(e) => tracing::debug!("{path}: {e}"),
                    }
                }
            }
        })
    })?;
    match rx.recv() {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            let _ = server.join();
            return Err(e);
        }
        Err(_) => return Err(io::Error::other("Modbus RTU server thread ended before opening the line")),
    }
    tracing::info!(
        "sim-drives: Modbus RTU on {} ({} baud, parity {:?}, {} stop bits), units {:?}",
        shown,
        line.baud,
        line.parity,
        line.stop_bits,
        shared.now().nodes()
    );
    let threads = vec![start_ticker(shared.clone(), stop)?, server];
    Ok(ModbusServer { addr: None, shared, threads })
}
