//! A socketcand-protocol server hosting one virtual CAN bus: any socketcand client (cncgw's
//! `socketcand://` transport, python-can's `socketcand` interface, …) joins it over TCP.
//!
//! It is a `CanBus` for `run_realtime`, so the drives' code does not know it is there:
//! frames a client sends reach the drives (through a bounded channel) and every other
//! client; frames the drives send reach every client. The wire format is the codec of
//! `cncgw_bus::socketcand`, the same one the client transport uses.
//!
//! Per connection: `< hi >`; `< open NAME >` → `< ok >` (or `< error … >` for another bus
//! name); `< rawmode >` → `< ok >`; only then frames. Every message is written on its own
//! (TCP_NODELAY), and frames start `JOIN_SETTLE` after the rawmode `< ok >` or with the
//! client's first frame, whichever comes first: python-can reads the `< ok >` with one
//! `recv` and compares it whole, so a frame in the same segment would fail its handshake;
//! a client that sends has read it (cncgw's master resets the nodes at once and must see
//! their boot-up messages 1–3 ms later). A client joining a bus misses what was sent before.

use cncgw_bus::socketcand::{format, Msg, Splitter};
use cncgw_bus::{BusError, CanBus, CanFrame};
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Frames from clients waiting for the drives (a CAN controller's FIFO, generously).
const RX_CAP: usize = 4096;
/// Quiet time after the rawmode `< ok >` before frames are forwarded (see module doc).
const JOIN_SETTLE: Duration = Duration::from_millis(20);
/// A client that cannot take a frame for this long is disconnected (it would stall the bus).
const WRITE_TIMEOUT: Duration = Duration::from_millis(200);

struct Client {
    id: u64,
    stream: TcpStream,
    /// Frames flow once this instant has passed (set by `< rawmode >`).
    raw_from: Option<Instant>,
}

struct Shared {
    bus: String,
    clients: Mutex<Vec<Client>>,
    stop: AtomicBool,
    /// Frames lost because the drives' channel was full, not yet reported.
    dropped: AtomicU64,
}

impl Shared {
    /// Send `frame` (received at `t_us`) to every client in raw mode except `from`.
    /// A client whose socket fails or blocks too long is dropped.
    fn broadcast(&self, frame: &CanFrame, t_us: u64, from: Option<u64>) {
        let text = format(&Msg::Frame(*frame, t_us));
        let now = Instant::now();
        let mut clients = self.clients.lock().unwrap_or_else(|e| e.into_inner());
        clients.retain_mut(|c| {
            if Some(c.id) == from || c.raw_from.is_none_or(|t| now < t) {
                return true;
            }
            match c.stream.write_all(text.as_bytes()) {
                Ok(()) => true,
                Err(e) => {
                    tracing::warn!(bus = %self.bus, client = c.id, "socketcand client dropped: {e}");
                    let _ = c.stream.shutdown(Shutdown::Both);
                    false
                }
            }
        });
    }

    fn reply(&self, id: u64, m: &Msg) -> bool {
        let mut clients = self.clients.lock().unwrap_or_else(|e| e.into_inner());
        match clients.iter_mut().find(|c| c.id == id) {
            Some(c) => c.stream.write_all(format(m).as_bytes()).is_ok(),
            None => false,
        }
    }

    fn set_raw(&self, id: u64) {
        let mut clients = self.clients.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(c) = clients.iter_mut().find(|c| c.id == id) {
            c.raw_from = Some(Instant::now() + JOIN_SETTLE);
        }
    }

    /// The client has spoken: it has read the handshake, frames may flow to it at once.
    fn join_now(&self, id: u64) {
        let now = Instant::now();
        let mut clients = self.clients.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(c) = clients.iter_mut().find(|c| c.id == id) {
            if c.raw_from.is_some_and(|t| t > now) {
                c.raw_from = Some(now);
            }
        }
    }

    fn remove(&self, id: u64) {
        self.clients.lock().unwrap_or_else(|e| e.into_inner()).retain(|c| c.id != id);
    }
}

/// Wall-clock time in microseconds since the Unix epoch (socketcand's frame timestamps).
pub fn unix_us() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_micros() as u64).unwrap_or(0)
}

/// The server; as a `CanBus` it is the drives' side of the virtual bus.
pub struct SocketcandServer {
    shared: Arc<Shared>,
    rx: mpsc::Receiver<CanFrame>,
    addr: SocketAddr,
    name: String,
}

impl SocketcandServer {
    /// Listen on `addr` (e.g. `127.0.0.1:29536`; port 0 picks a free one) hosting the bus
    /// `bus_name` (what clients `< open >`).
    pub fn bind(addr: &str, bus_name: &str) -> Result<SocketcandServer, BusError> {
        let name = format!("socketcand-server://{addr}/{bus_name}");
        let listener = TcpListener::bind(addr).map_err(|e| BusError::Open {
            bus: name.clone(),
            reason: format!("cannot listen on {addr}: {e} (is another sim-drives running there? pick another port)"),
        })?;
        let local = listener.local_addr().map_err(|e| BusError::Open { bus: name.clone(), reason: e.to_string() })?;
        let shared =
            Arc::new(Shared { bus: bus_name.to_string(), clients: Mutex::new(Vec::new()), stop: AtomicBool::new(false), dropped: AtomicU64::new(0) });
        let (tx, rx) = mpsc::sync_channel(RX_CAP);
        let sh = shared.clone();
        std::thread::Builder::new()
            .name("socketcand-accept".into())
            .spawn(move || accept_loop(listener, sh, tx))
            .map_err(|e| BusError::Open { bus: name.clone(), reason: e.to_string() })?;
        let name = format!("socketcand-server://{local}/{bus_name}");
        tracing::info!("socketcand server on {local}, bus {bus_name}");
        Ok(SocketcandServer { shared, rx, addr: local, name })
    }

    /// The address actually bound (useful with port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Clients that completed the handshake (in raw mode).
    pub fn clients(&self) -> usize {
        self.shared.clients.lock().unwrap_or_else(|e| e.into_inner()).iter().filter(|c| c.raw_from.is_some()).count()
    }

    fn take_dropped(&self) -> Result<(), BusError> {
        match self.shared.dropped.swap(0, Ordering::Relaxed) {
            0 => Ok(()),
            n => Err(BusError::Overflow { bus: self.name.clone(), dropped: n }),
        }
    }
}

fn accept_loop(listener: TcpListener, sh: Arc<Shared>, tx: mpsc::SyncSender<CanFrame>) {
    let mut next_id = 1u64;
    for conn in listener.incoming() {
        if sh.stop.load(Ordering::Relaxed) {
            return;
        }
        let stream = match conn {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!("socketcand accept: {e}");
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
        };
        let id = next_id;
        next_id += 1;
        let peer = stream.peer_addr().map(|a| a.to_string()).unwrap_or_default();
        let setup = (|| {
            stream.set_nodelay(true)?;
            stream.set_write_timeout(Some(WRITE_TIMEOUT))?;
            let reader = stream.try_clone()?;
            let mut w = stream.try_clone()?;
            w.write_all(format(&Msg::Hi).as_bytes())?;
            Ok::<_, std::io::Error>(reader)
        })();
        let reader = match setup {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!("socketcand client {peer}: {e}");
                continue;
            }
        };
        tracing::info!(client = id, "socketcand client connected from {peer}");
        sh.clients.lock().unwrap_or_else(|e| e.into_inner()).push(Client { id, stream, raw_from: None });
        let (sh2, tx2) = (sh.clone(), tx.clone());
        if let Err(e) = std::thread::Builder::new().name(format!("socketcand-client-{id}")).spawn(move || client_loop(id, reader, sh2, tx2)) {
            tracing::warn!("socketcand client {peer}: cannot start its thread: {e}");
            sh.remove(id);
        }
    }
}

fn client_loop(id: u64, mut reader: TcpStream, sh: Arc<Shared>, tx: mpsc::SyncSender<CanFrame>) {
    let mut sp = Splitter::default();
    let mut buf = [0u8; 4096];
    let (mut opened, mut raw) = (false, false);
    loop {
        let n = match reader.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        sp.push(&buf[..n]);
        while let Some(m) = sp.next_msg() {
            let ok = match m {
                Msg::Open(ref bus) if !opened => {
                    if *bus == sh.bus {
                        opened = true;
                        sh.reply(id, &Msg::Ok)
                    } else {
                        sh.reply(id, &Msg::Error(format!("could not open bus {bus}: this server hosts {}", sh.bus)))
                    }
                }
                Msg::RawMode if opened && !raw => {
                    raw = true;
                    let ok = sh.reply(id, &Msg::Ok);
                    sh.set_raw(id);
                    ok
                }
                Msg::Send(f) if raw => {
                    let t = unix_us();
                    sh.join_now(id);
                    match tx.try_send(f) {
                        Ok(()) => {}
                        Err(mpsc::TrySendError::Full(_)) => {
                            sh.dropped.fetch_add(1, Ordering::Relaxed);
                        }
                        Err(mpsc::TrySendError::Disconnected(_)) => return sh.remove(id),
                    }
                    sh.broadcast(&f, t, Some(id));
                    true
                }
                Msg::Send(_) | Msg::RawMode | Msg::Open(_) => {
                    sh.reply(id, &Msg::Error("wrong state: send < open BUS > then < rawmode > first".into()))
                }
                other => {
                    tracing::debug!(client = id, "socketcand: ignored {other:?}");
                    true
                }
            };
            if !ok {
                break;
            }
        }
    }
    tracing::info!(client = id, "socketcand client disconnected");
    sh.remove(id);
}

impl CanBus for SocketcandServer {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.shared.broadcast(frame, unix_us(), None);
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        self.take_dropped()?;
        match self.rx.try_recv() {
            Ok(f) => Ok(Some(f)),
            Err(mpsc::TryRecvError::Empty) => Ok(None),
            Err(mpsc::TryRecvError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        self.take_dropped()?;
        match self.rx.recv_timeout(timeout) {
            Ok(f) => Ok(Some(f)),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn name(&self) -> &str {
        &self.name
    }
    fn remote_frames(&self) -> bool {
        false
    }
}

impl Drop for SocketcandServer {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        // Wake the accept loop so it sees the flag, and close every client.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(100));
        for c in self.shared.clients.lock().unwrap_or_else(|e| e.into_inner()).drain(..) {
            let _ = c.stream.shutdown(Shutdown::Both);
        }
    }
}
