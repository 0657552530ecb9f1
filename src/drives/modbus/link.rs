//! One Modbus link (a TCP connection or an RS-485 line) on its own I/O thread.
//!
//! Modbus has no SYNC and an RTU line carries a few transactions per millisecond at best, so
//! the link runs its own cycle, decoupled from the machine's: every link cycle it writes each
//! drive's latest set-point and reads its feedback, and exchanges both with the cycle thread
//! through a mutex-protected slot (no allocation on the cycle thread). The link thread owns
//! a current-thread tokio runtime for tokio-modbus; it may allocate (tokio-modbus boxes its
//! futures), which is why it is not the cycle thread.

use super::line::Line;
use super::plan::{DrivePlan, Exchange};
use crate::config::{LinkTransport, ModbusLink, Parity};
use crate::Alarm;
use cncgw_bus::modbus::SerialTiming;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};
use tokio_modbus::client::{Context, Reader, Writer};
use tokio_modbus::prelude::SlaveContext;
use tokio_modbus::{ExceptionCode, Slave};

/// What the cycle thread wants of one drive.
#[derive(Clone, Copy, Debug, Default)]
pub struct Command {
    /// CiA 402 controlword (the `cia402` profile).
    pub controlword: u16,
    /// Servo on (the `pr` profile).
    pub servo_on: bool,
    /// Clear a latched alarm (the `pr` profile): written once per request.
    pub alarm_reset_seq: u32,
    /// Target position, counts (wrapping INTEGER32 on the wire), computed at `at`.
    pub target: i32,
    /// Set-point velocity at `at`, counts/s: the link extrapolates the target to the
    /// instant it writes it, so the drive sees a set-point that moves with its own clock
    /// rather than the machine cycle's samples re-sampled by the link's (which would hold
    /// still one period and jump the next).
    pub velocity: f64,
    pub at: Option<Instant>,
    /// Write the target register (CiA 402: also while enabling, holding the actual position,
    /// so that the drive has it before the controlword that enables it; off at shutdown).
    pub stream: bool,
    /// CiA 402 spindle in speed: cyclic synchronous velocity (mode 9), `velocity` written to
    /// the target velocity register every link cycle (`DriveBus::set_spindle_control`).
    pub speed_mode: bool,
    /// CiA 402: the following-error window to hold, counts (0: the one written at start-up).
    pub ferr_window: u32,
}

/// What the link read from one drive.
#[derive(Clone, Copy, Debug, Default)]
pub struct Reading {
    pub statusword: u16,
    pub position: i32,
    pub error_code: u16,
    /// The target the drive was interpolating towards before this cycle's write (its demand
    /// at the read, to within a link cycle): the reference for the following error.
    pub demand: i32,
    /// The controlword / servo-on state written just before this reading.
    pub command: Command,
    /// Increments with every reading.
    pub seq: u64,
    pub at: Option<Instant>,
}

#[derive(Debug, Default)]
pub struct Slot {
    pub command: Command,
    pub reading: Reading,
    /// The last failed transaction of this drive, in words (timeouts are not fatal at once:
    /// the feedback age is).
    pub last_error: Option<String>,
    /// An exception of this drive in the cyclic exchange was handed to the cycle thread
    /// (once: the link goes on serving the others while they stop).
    pub exception_reported: bool,
}

#[derive(Debug)]
pub enum LinkState {
    Starting,
    /// Exchanging every `cycle`.
    Running {
        cycle: Duration,
    },
    Failed(Alarm),
}

#[derive(Debug)]
pub struct Shared {
    pub slots: Vec<Slot>,
    pub state: LinkState,
    /// An alarm of the running link for the cycle thread (taken once): a drive refused the
    /// cyclic exchange. The link keeps exchanging with every drive so that the controlled
    /// stop reaches them all.
    pub alarm: Option<(Option<usize>, Alarm)>,
    pub stop: bool,
    /// Link cycles that took longer than the cycle.
    pub overruns: u64,
    /// Transactions done (answered or failed), failed, and link cycles run.
    pub transactions: u64,
    pub cycles: u64,
    pub failures: u64,
    /// Bytes of late answers dropped before a request (see `line`).
    pub stale_bytes: u64,
}

pub type SharedLink = Arc<(Mutex<Shared>, Condvar)>;

/// A link's static description.
pub struct LinkSpec {
    pub name: String,
    pub cfg: ModbusLink,
    pub drives: Vec<DrivePlan>,
    /// The machine cycle: the link cycle is never shorter.
    pub machine_cycle: Duration,
    /// SCHED_FIFO priority of the link thread (the cycle thread's `rt.priority` − 1: it feeds
    /// the cycle and must not be preempted by normal threads, nor preempt the cycle); None =
    /// normal scheduling.
    pub rt_priority: Option<i32>,
}

impl LinkSpec {
    pub fn serial_timing(&self) -> SerialTiming {
        SerialTiming { baud: self.cfg.baud, parity: self.cfg.parity != Parity::None, stop_bits: self.cfg.stop_bits }
    }

    /// RTU: the time one link cycle of every drive's exchange takes on the wire.
    pub fn rtu_cycle_s(&self) -> f64 {
        let t = self.serial_timing();
        let turn = self.cfg.turnaround_ms * 1e-3;
        self.drives
            .iter()
            .flat_map(|d| d.cyclic.iter())
            .map(|x| {
                let (rq, rs) = x.rtu_bytes();
                t.transaction_s(rq, rs, turn)
            })
            .sum()
    }

    /// RTU: the link cycle for the line time, in whole ms: `RTU_MARGIN` over it (the
    /// drives' turnaround is a configured guess, and a USB adapter or the scheduler adds to
    /// every transaction — a link computed without margin ran at 45.8 ms against the 41 ms
    /// told to the drives), never shorter than the machine cycle. What the margin does not
    /// cover the run-time check (`Behind`, alarm 2204) reports.
    pub fn rtu_link_cycle_ms(&self) -> f64 {
        (self.rtu_cycle_s() * RTU_MARGIN * 1e3).ceil().max((self.machine_cycle.as_secs_f64() * 1e3).ceil())
    }

    /// RTU: when each drive's exchange starts in a link cycle, from its start: the line
    /// time of the drives before it × `RTU_MARGIN` (the cycle has that margin over the
    /// whole line time, so the last drive still ends within it). TCP: none (0).
    pub fn rtu_write_offsets(&self) -> Vec<Duration> {
        if self.cfg.transport != LinkTransport::Rtu {
            return Vec::new();
        }
        let t = self.serial_timing();
        let turn = self.cfg.turnaround_ms * 1e-3;
        let mut at = 0.0;
        self.drives
            .iter()
            .map(|d| {
                let start = Duration::from_secs_f64(at * RTU_MARGIN);
                at += d
                    .cyclic
                    .iter()
                    .map(|x| {
                        let (rq, rs) = x.rtu_bytes();
                        t.transaction_s(rq, rs, turn)
                    })
                    .sum::<f64>();
                start
            })
            .collect()
    }

    pub fn transactions_per_cycle(&self) -> usize {
        self.drives.iter().map(|d| d.cyclic.len()).sum()
    }

    pub fn what(&self) -> String {
        self.cfg.describe()
    }
}

/// Start the link thread. It connects, configures every drive, measures or computes the
/// cycle, then exchanges every cycle until `stop`.
pub fn spawn(spec: LinkSpec) -> std::io::Result<(SharedLink, std::thread::JoinHandle<()>)> {
    let shared: SharedLink = Arc::new((
        Mutex::new(Shared {
            slots: spec.drives.iter().map(|_| Slot::default()).collect(),
            state: LinkState::Starting,
            alarm: None,
            stop: false,
            overruns: 0,
            transactions: 0,
            cycles: 0,
            failures: 0,
            stale_bytes: 0,
        }),
        Condvar::new(),
    ));
    let s2 = shared.clone();
    let h = std::thread::Builder::new().name(format!("modbus-{}", spec.name)).spawn(move || {
        if let Some(p) = spec.rt_priority {
            match cncgw_bus::rt::fifo_current_thread(p) {
                Ok(()) => tracing::info!(link = %spec.name, priority = p, "Modbus link thread at SCHED_FIFO"),
                Err(e) => tracing::warn!(link = %spec.name, priority = p, "Modbus link thread left at normal scheduling: {e}"),
            }
        }
        let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
            Ok(rt) => rt,
            Err(e) => {
                set_state(
                    &s2,
                    LinkState::Failed(Alarm::new(crate::alarm::MODBUS_LINK, format!("Modbus link {}: cannot start its runtime: {e}", spec.name))),
                );
                return;
            }
        };
        let mut io = LinkIo { spec, ctx: None, rt, last_end: None, line: None, stale_bytes: 0 };
        match io.start(&s2) {
            Ok(cycle) => {
                set_state(&s2, LinkState::Running { cycle });
                io.run(&s2, cycle);
            }
            Err(a) => set_state(&s2, LinkState::Failed(a)),
        }
        if let Some(mut ctx) = io.ctx.take() {
            let _ = io.rt.block_on(tokio_modbus::client::Client::disconnect(&mut ctx));
        }
    })?;
    Ok((shared, h))
}

fn set_state(s: &SharedLink, st: LinkState) {
    if let Ok(mut g) = s.0.lock() {
        g.state = st;
    }
    s.1.notify_all();
}

/// The run-time check of the link cycle: the drives interpolate each set-point over the
/// cycle they were told; a link whose exchanges take longer feeds them late, every cycle.
/// `BEHIND_CYCLES` cycles in a row longer than the cycle (one slow cycle is a hiccup, ridden
/// through by the drives' extrapolation) is alarm 2204 naming the figures, once.
#[derive(Default)]
struct Behind {
    in_a_row: u32,
    sum: Duration,
    longest: Duration,
    told: bool,
}

const BEHIND_CYCLES: u32 = 10;

impl Behind {
    fn took(&mut self, took: Duration, cycle: Duration, spec: &LinkSpec) -> Option<Alarm> {
        if took <= cycle {
            self.in_a_row = 0;
            self.sum = Duration::ZERO;
            self.longest = Duration::ZERO;
            return None;
        }
        self.in_a_row += 1;
        self.sum += took;
        self.longest = self.longest.max(took);
        if self.in_a_row < BEHIND_CYCLES || std::mem::replace(&mut self.told, true) {
            return None;
        }
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        let avg = ms(self.sum) / self.in_a_row as f64;
        Some(Alarm::new(
            crate::alarm::MODBUS_CYCLE,
            format!(
                "Modbus link {} falls behind its cycle: {} link cycles in a row took {avg:.1} ms on average (longest {:.1} ms) against the {:.0} ms the drives were told to interpolate over ({} transactions per cycle on {}); set cycle_ms = {:.0} in [modbus.{}] or find what slows the drives' answers",
                spec.name,
                self.in_a_row,
                ms(self.longest),
                ms(cycle),
                spec.transactions_per_cycle(),
                spec.what(),
                (ms(self.longest) * 1.25).ceil(),
                spec.name
            ),
        ))
    }
}

/// One try of a transaction.
enum Attempt {
    /// Busy or acknowledge: try again.
    Busy(String),
    Other(TxError),
}
use Attempt::{Busy, Other};

struct LinkIo {
    spec: LinkSpec,
    ctx: Option<Context>,
    rt: tokio::runtime::Runtime,
    /// End of the last RTU frame, for the inter-frame silence.
    last_end: Option<Instant>,
    /// The byte stream under `ctx`, to drop late answers from.
    line: Option<Line>,
    /// Bytes of late answers dropped so far.
    stale_bytes: u64,
}

/// A failed transaction.
enum TxError {
    /// The drive answered with an exception (after the retries of a busy one): the
    /// configuration or the drive is wrong.
    Exception(String),
    /// No answer in time or the connection failed: retried, then the feedback goes stale.
    Transport(String),
}

impl TxError {
    fn text(&self) -> &str {
        match self {
            TxError::Exception(s) | TxError::Transport(s) => s,
        }
    }
}

/// Times a transaction answered "busy" (0x06) or "acknowledge" (0x05: accepted, still
/// working) is sent again before it counts as failed. Modbus V1.1b3 §7: the client should
/// retransmit later; 3 tries a millisecond apart ride through a drive that is busy writing
/// its EEPROM for a moment without holding the link up for long.
const BUSY_RETRIES: u32 = 3;
const BUSY_PAUSE: Duration = Duration::from_millis(1);
/// The RTU link cycle over the computed line time (`LinkSpec::rtu_link_cycle_ms`).
pub const RTU_MARGIN: f64 = 1.10;
/// TCP: start-up rounds of round-trip measurement (at most), and the link cycle over the p99
/// round.
const TCP_ROUNDS: usize = 300;
pub const TCP_MARGIN: f64 = 1.25;
/// Tries after the first of a start-up transaction that got no (or a garbled) answer.
const STARTUP_RETRIES: u32 = 3;

/// A start-up transaction that failed: 2201 for an exception (the map or the drive is
/// wrong), 2202 for no answer.
fn startup_alarm(e: &TxError, doing: &str) -> Alarm {
    let (n, hint) = match e {
        TxError::Exception(_) => (
            crate::alarm::MODBUS_EXCEPTION,
            "; check the unit id, the profile and the register map (a register the drive does not have: `cncgw config check --bus …` lists them; optional ones can be \"none\" in the map, docs/MODBUS_MAPS.md)",
        ),
        TxError::Transport(_) => (crate::alarm::MODBUS_TIMEOUT, ""),
    };
    Alarm::new(n, format!("{doing}: {}{hint}", e.text()))
}

/// `exception 0x06 (Server device busy)`: the code and tokio-modbus' name for it.
pub fn exception_words(code: ExceptionCode) -> String {
    let c: u8 = code.into();
    format!("exception 0x{c:02X} ({code})")
}

impl LinkIo {
    fn connect(&mut self) -> Result<(), String> {
        let cfg = &self.spec.cfg;
        let timeout = Duration::from_millis(cfg.timeout_ms as u64);
        let line = match cfg.transport {
            LinkTransport::Tcp => {
                let addr = cfg.address.clone().unwrap_or_default();
                self.rt.block_on(async {
                    let sa = tokio::net::lookup_host(&addr)
                        .await
                        .map_err(|e| format!("{addr}: {e}"))?
                        .next()
                        .ok_or_else(|| format!("{addr}: no address"))?;
                    let stream = tokio::time::timeout(timeout.max(Duration::from_millis(500)), tokio::net::TcpStream::connect(sa))
                        .await
                        .map_err(|_| format!("{addr}: connection timed out"))?
                        .map_err(|e| format!("{addr}: {e}"))?;
                    let _ = stream.set_nodelay(true);
                    Ok::<_, String>(Line::tcp(stream))
                })?
            }
            LinkTransport::Rtu => {
                let dev = cfg.device.clone().unwrap_or_default();
                let parity = match cfg.parity {
                    Parity::None => tokio_serial::Parity::None,
                    Parity::Even => tokio_serial::Parity::Even,
                    Parity::Odd => tokio_serial::Parity::Odd,
                };
                let stop = if cfg.stop_bits == 2 { tokio_serial::StopBits::Two } else { tokio_serial::StopBits::One };
                let builder = tokio_serial::new(&dev, cfg.baud).parity(parity).stop_bits(stop).data_bits(tokio_serial::DataBits::Eight);
                let port = self.rt.block_on(async { tokio_serial::SerialStream::open(&builder) }).map_err(|e| format!("{dev}: {e}"))?;
                Line::serial(port)
            }
        };
        self.ctx = Some(match cfg.transport {
            LinkTransport::Tcp => tokio_modbus::client::tcp::attach(line.clone()),
            LinkTransport::Rtu => tokio_modbus::client::rtu::attach(line.clone()),
        });
        self.line = Some(line);
        Ok(())
    }

    /// RTU: keep the 3.5-character silence between the end of one frame and the next.
    fn silence(&mut self) {
        if self.spec.cfg.transport != LinkTransport::Rtu {
            return;
        }
        if let Some(end) = self.last_end {
            let gap = Duration::from_secs_f64(self.spec.serial_timing().t35_s());
            let due = end + gap;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
    }

    /// One transaction with drive `d`, sent again while the drive answers busy (up to
    /// `BUSY_RETRIES` times).
    fn exchange(&mut self, d: usize, x: &Exchange, write: &[u16]) -> Result<Vec<u16>, TxError> {
        let mut tries = 0;
        loop {
            match self.exchange_once(d, x, write) {
                Err(Busy(_)) if tries < BUSY_RETRIES => {
                    tries += 1;
                    std::thread::sleep(BUSY_PAUSE);
                }
                Err(Busy(m)) => return Err(TxError::Exception(format!("{m} ({} tries)", tries + 1))),
                Err(Other(e)) => return Err(e),
                Ok(v) => return Ok(v),
            }
        }
    }

    /// `exchange` at start-up, where nothing moves yet: a transaction without an answer (or
    /// with a late one's bytes in its place) is sent again, `STARTUP_RETRIES` times, before
    /// it is alarm 2202 — a drive still booting or one slow answer must not abort the start.
    fn exchange_at_startup(&mut self, d: usize, x: &Exchange, write: &[u16]) -> Result<Vec<u16>, TxError> {
        let mut tries = 0;
        loop {
            match self.exchange(d, x, write) {
                Err(TxError::Transport(m)) if tries < STARTUP_RETRIES => {
                    tries += 1;
                    tracing::debug!("{m}: try {} of {}", tries + 1, STARTUP_RETRIES + 1);
                    if self.ctx.is_none() {
                        self.connect().map_err(TxError::Transport)?;
                    }
                }
                Err(TxError::Transport(m)) => return Err(TxError::Transport(format!("{m} ({} tries)", tries + 1))),
                r => return r,
            }
        }
    }

    fn exchange_once(&mut self, d: usize, x: &Exchange, write: &[u16]) -> Result<Vec<u16>, Attempt> {
        self.silence();
        // A late answer to an earlier request must not be taken for this one's (line.rs).
        if let Some(n) = self.line.as_ref().map(Line::drain).filter(|&n| n > 0) {
            tracing::debug!(link = %self.spec.name, "dropped {n} bytes of a late answer before the next request");
            self.stale_bytes += n as u64;
        }
        let unit = self.spec.drives[d].unit;
        let timeout = Duration::from_millis(self.spec.cfg.timeout_ms as u64);
        let Some(ctx) = self.ctx.as_mut() else {
            return Err(Other(TxError::Transport("not connected".into())));
        };
        ctx.set_slave(Slave(unit));
        let r = self.rt.block_on(async {
            tokio::time::timeout(timeout, async {
                match *x {
                    Exchange::Read { addr, len } => ctx.read_holding_registers(addr, len).await,
                    Exchange::Write { addr, .. } => ctx.write_multiple_registers(addr, write).await.map(|r| r.map(|_| Vec::new())),
                    Exchange::WriteSingle { addr } => {
                        ctx.write_single_register(addr, write.first().copied().unwrap_or(0)).await.map(|r| r.map(|_| Vec::new()))
                    }
                    Exchange::ReadWrite { read_addr, read_len, write_addr, .. } => {
                        ctx.read_write_multiple_registers(read_addr, read_len, write_addr, write).await
                    }
                }
            })
            .await
        });
        self.last_end = Some(Instant::now());
        let name = &self.spec.drives[d].axis;
        let what = || format!("axis {name} (unit {unit}) on link {}: {}", self.spec.name, x.describe());
        match r {
            Err(_) => Err(Other(TxError::Transport(format!("{}: no answer within {} ms", what(), self.spec.cfg.timeout_ms)))),
            Ok(Err(e)) => {
                // A broken connection; or on TCP an answer out of step (a late one that
                // came after the drain, with the next one possibly buffered in the framing,
                // out of the drain's reach): reconnect — a new connection starts in step.
                if matches!(e, tokio_modbus::Error::Transport(_)) || self.spec.cfg.transport == LinkTransport::Tcp {
                    self.ctx = None;
                    self.line = None;
                }
                Err(Other(TxError::Transport(format!("{}: {e}", what()))))
            }
            Ok(Ok(Err(code @ (ExceptionCode::ServerDeviceBusy | ExceptionCode::Acknowledge)))) => {
                Err(Busy(format!("{}: {}", what(), exception_words(code))))
            }
            Ok(Ok(Err(code))) => Err(Other(TxError::Exception(format!("{}: {}", what(), exception_words(code))))),
            Ok(Ok(Ok(v))) => {
                if let Exchange::Read { len, .. } | Exchange::ReadWrite { read_len: len, .. } = *x {
                    if v.len() != len as usize {
                        return Err(Other(TxError::Transport(format!("{}: {} registers in the answer, {len} asked", what(), v.len()))));
                    }
                }
                Ok(v)
            }
        }
    }

    /// Connect, configure every drive, and find the cycle the link can carry.
    fn start(&mut self, s: &SharedLink) -> Result<Duration, Alarm> {
        self.connect()
            .map_err(|e| Alarm::new(crate::alarm::MODBUS_LINK, format!("Modbus link {}: cannot open {}: {e}", self.spec.name, self.spec.what())))?;
        for d in 0..self.spec.drives.len() {
            for w in self.spec.drives[d].map_warnings() {
                tracing::warn!(link = %self.spec.name, "{w}");
            }
            let writes = self.spec.drives[d].setup.clone();
            for (x, data) in writes {
                self.exchange_at_startup(d, &x, &data).map_err(|e| startup_alarm(&e, "configuring the drive failed"))?;
            }
        }
        // The cycle: RTU from the line's timing; TCP from the measured round trips.
        let (needed_ms, least_ms) = match self.spec.cfg.transport {
            LinkTransport::Rtu => {
                let c = self.spec.rtu_link_cycle_ms();
                (c, c)
            }
            LinkTransport::Tcp => self.measure_tcp_cycle()?,
        };
        let machine_ms = (self.spec.machine_cycle.as_secs_f64() * 1e3).ceil();
        // Whole milliseconds: the drives' interpolation period register is in ms.
        let mut cycle_ms = needed_ms.ceil().max(machine_ms);
        if let Some(c) = self.spec.cfg.cycle_ms {
            // A configured cycle the link cannot carry even typically is refused; one below
            // the measured tail with margin is the operator's choice, watched at run time
            // (alarm 2204 if the link falls behind it).
            if c < least_ms.ceil() {
                return Err(Alarm::new(
                    crate::alarm::MODBUS_CYCLE,
                    format!(
                        "Modbus link {}: cycle_ms = {c} is shorter than the {} ms its {} transactions per cycle need on {}; raise it or remove it",
                        self.spec.name,
                        least_ms.ceil(),
                        self.spec.transactions_per_cycle(),
                        self.spec.what()
                    ),
                ));
            }
            if c < cycle_ms {
                tracing::warn!(link = %self.spec.name, "cycle_ms = {c} is below the {cycle_ms} ms measured with margin: the run-time check (alarm 2204) watches it");
            }
            cycle_ms = c.ceil().max(machine_ms);
        }
        cycle_ms = self.tell_timing(cycle_ms)?;
        let cycle = Duration::from_secs_f64(cycle_ms * 1e-3);
        // First readings, so that the cycle thread starts from real positions.
        self.cycle_once(s, Instant::now());
        tracing::info!(link = %self.spec.name, "{}: link cycle {cycle_ms} ms ({} transactions per cycle)", self.spec.what(), self.spec.transactions_per_cycle());
        Ok(cycle)
    }

    /// TCP: the link cycle from start-up rounds of as many transactions as a link cycle has
    /// (the drives' feedback reads, in turn: reads move nothing): the p99 of the rounds'
    /// durations × `TCP_MARGIN`, and the least the link carries (the median round), ms. A
    /// cycle set by the tail of whole rounds, not by one sample (a single measurement came
    /// out 3–23 ms between starts on one loopback link) nor by one transaction's tail times
    /// the transactions (one descheduled transaction is not every one).
    fn measure_tcp_cycle(&mut self) -> Result<(f64, f64), Alarm> {
        let n = self.spec.drives.len();
        let tx = self.spec.transactions_per_cycle().max(1);
        let mut rounds = Vec::with_capacity(TCP_ROUNDS);
        let t_start = Instant::now();
        // At least 100 rounds (p99 is then the largest), up to TCP_ROUNDS within 0.5 s (p99
        // of 300 leaves out the 3 longest).
        while n > 0 && rounds.len() < TCP_ROUNDS && (rounds.len() < 100 || t_start.elapsed() < Duration::from_millis(500)) {
            let t0 = Instant::now();
            for k in 0..tx {
                let d = k % n;
                let x = self.spec.drives[d].feedback_read();
                self.exchange_at_startup(d, &x, &[]).map_err(|e| startup_alarm(&e, "reading the drive's feedback failed"))?;
            }
            rounds.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        if rounds.is_empty() {
            return Ok((0.0, 0.0));
        }
        rounds.sort_by(f64::total_cmp);
        let q = |p: usize| rounds[(rounds.len() * p / 100).min(rounds.len() - 1)];
        let (median, p90, p99, max) = (q(50), q(90), q(99), rounds[rounds.len() - 1]);
        let cycle = p99 * TCP_MARGIN;
        tracing::info!(
            link = %self.spec.name,
            "{} start-up rounds of {tx} transactions (a link cycle's): median {median:.2} ms, p90 {p90:.2} ms, p99 {p99:.2} ms, max {max:.2} ms; p99 × {TCP_MARGIN} = {cycle:.2} ms",
            rounds.len()
        );
        Ok((cycle, median))
    }

    /// Tell every drive its interpolation period (the link cycle) and the watchdog, and
    /// follow the drives: one that holds a longer interpolation period than written (it has
    /// a coarser grid or a minimum) sets the link's cycle — every drive is told again; one
    /// that holds a shorter one cannot interpolate over the link's cycle (alarm 2204).
    fn tell_timing(&mut self, mut cycle_ms: f64) -> Result<f64, Alarm> {
        for _pass in 0..3 {
            let mut longest = cycle_ms;
            for d in 0..self.spec.drives.len() {
                let writes = self.spec.drives[d].timing_writes(cycle_ms as u16, self.spec.cfg.timeout_ms);
                for (x, data) in writes {
                    self.exchange_at_startup(d, &x, &data).map_err(|e| startup_alarm(&e, "configuring the drive failed"))?;
                }
                let Some(addr) = self.spec.drives[d].interpolation_register() else { continue };
                let x = Exchange::Read { addr, len: 1 };
                let held = self.exchange_at_startup(d, &x, &[]).map_err(|e| startup_alarm(&e, "reading back the interpolation period failed"))?;
                let held = held.first().copied().unwrap_or(0) as f64;
                let axis = &self.spec.drives[d].axis;
                if held < cycle_ms {
                    return Err(Alarm::new(
                        crate::alarm::MODBUS_CYCLE,
                        format!(
                            "Modbus link {}: axis {axis}'s drive holds an interpolation period of {held} ms after {cycle_ms} ms was written (register {addr}): it cannot interpolate over the link's cycle; see the drive's manual for the periods it takes",
                            self.spec.name
                        ),
                    ));
                }
                if held > cycle_ms {
                    tracing::warn!(link = %self.spec.name, "axis {axis}'s drive holds an interpolation period of {held} ms after {cycle_ms} ms was written: the link runs at {held} ms");
                    longest = longest.max(held);
                }
            }
            if longest == cycle_ms {
                return Ok(cycle_ms);
            }
            cycle_ms = longest;
        }
        Ok(cycle_ms)
    }

    fn run(&mut self, s: &SharedLink, cycle: Duration) {
        let mut next = Instant::now();
        let mut behind = Behind::default();
        loop {
            next += cycle;
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            } else if now > next + cycle {
                if let Ok(mut g) = s.0.lock() {
                    g.overruns += 1;
                }
                next = now;
            }
            if s.0.lock().map(|g| g.stop).unwrap_or(true) {
                return;
            }
            if self.ctx.is_none() {
                // Reconnect (TCP); a failure leaves the feedback ageing, which the cycle
                // thread turns into alarm 2015 past the feedback timeout.
                if let Err(e) = self.connect() {
                    if let Ok(mut g) = s.0.lock() {
                        for sl in g.slots.iter_mut() {
                            sl.last_error = Some(format!("link {} reconnecting: {e}", self.spec.name));
                        }
                    }
                    continue;
                }
                tracing::warn!(link = %self.spec.name, "Modbus link reconnected");
            }
            let t0 = Instant::now();
            self.cycle_once(s, next);
            if let Some(a) = behind.took(t0.elapsed(), cycle, &self.spec) {
                if let Ok(mut g) = s.0.lock() {
                    if g.alarm.is_none() {
                        g.alarm = Some((None, a));
                    }
                }
            }
        }
    }

    /// One exchange with every drive; an exception goes to `Shared::alarm`.
    /// `sched`: the instant this cycle was scheduled for (the set-points are for it).
    fn cycle_once(&mut self, s: &SharedLink, sched: Instant) {
        let offsets = self.spec.rtu_write_offsets();
        for d in 0..self.spec.drives.len() {
            // RTU: each drive's exchange starts at its fixed offset in the cycle, so that the
            // drive receives its set-point one link cycle after the last one, not whenever
            // the answers of the drives before it happened to end: a CSP drive interpolates
            // from the receipt, and a spindle at 1500 rpm turns 9° per ms of jitter (its 30°
            // window tripped on RTU). Its set-point is then taken and extrapolated for that
            // instant.
            let sched = sched + offsets.get(d).copied().unwrap_or_default();
            let now = Instant::now();
            if sched > now {
                std::thread::sleep(sched - now);
            }
            let cmd = match s.0.lock() {
                Ok(g) => g.slots[d].command,
                Err(_) => return,
            };
            let prev_target = self.spec.drives[d].last_target;
            let mut cmd = cmd;
            if let (true, Some(at)) = (cmd.stream, cmd.at) {
                // At most three machine cycles ahead: beyond that the cycle thread has
                // stopped and the set-point must stand.
                // Both instants are on ideal grids (this link's schedule, the machine cycle's),
                // so successive writes differ by exactly one link cycle of travel however
                // late the threads wake: the drive interpolates each over one period.
                let ahead = sched.saturating_duration_since(at).min(self.spec.machine_cycle * 3);
                let dx = (cmd.velocity * ahead.as_secs_f64()).round();
                if dx.is_finite() {
                    cmd.target = cmd.target.wrapping_add(dx.clamp(i32::MIN as f64, i32::MAX as f64) as i32);
                }
            }
            let mut reading = None;
            let mut err = None;
            tracing::trace!(
                unit = self.spec.drives[d].unit,
                target = cmd.target,
                late_us = Instant::now().saturating_duration_since(sched).as_micros() as u64,
                "write"
            );
            let plan = self.spec.drives[d].cyclic_writes(&cmd);
            let mut done = 0u64;
            for (x, data) in plan {
                match self.exchange(d, &x, &data) {
                    Ok(v) => {
                        done += 1;
                        if x.reads() {
                            reading = self.spec.drives[d].decode(&x, &v, reading);
                        }
                    }
                    Err(e) => {
                        err = Some(e);
                        break;
                    }
                }
            }
            if err.is_some() {
                // What was not acknowledged is written again next cycle.
                self.spec.drives[d].forget_writes();
            }
            let Ok(mut g) = s.0.lock() else { return };
            g.transactions += done + err.is_some() as u64;
            g.stale_bytes = self.stale_bytes;
            if d == 0 {
                g.cycles += 1;
            }
            match err {
                Some(TxError::Exception(m)) => {
                    // The others go on being served: the controlled stop must reach them.
                    g.failures += 1;
                    g.slots[d].last_error = Some(m.clone());
                    if !std::mem::replace(&mut g.slots[d].exception_reported, true) && g.alarm.is_none() {
                        g.alarm = Some((
                            Some(d),
                            Alarm::new(
                                crate::alarm::MODBUS_EXCEPTION,
                                format!("{m}; the drive refused the cyclic exchange: check its register map and its state"),
                            ),
                        ));
                    }
                }
                Some(TxError::Transport(m)) => {
                    g.failures += 1;
                    tracing::debug!("{m}");
                    g.slots[d].last_error = Some(m);
                }
                None => {
                    if !cmd.stream {
                        // Not streaming: the drive stands where it is read. The first
                        // streamed target is measured from there (the PR block's speed, the
                        // following error's demand), never from 0.
                        if let Some(r) = &reading {
                            self.spec.drives[d].last_target = r.position;
                        }
                    }
                    if let Some(mut r) = reading {
                        self.spec.drives[d].last_actual = Some(r.position);
                        let seq = g.slots[d].reading.seq + 1;
                        r.seq = seq;
                        r.at = Some(Instant::now());
                        r.command = cmd;
                        // In speed (CSV) the drive follows no position: nothing lags.
                        r.demand = if cmd.stream && !cmd.speed_mode { prev_target } else { r.position };
                        g.slots[d].reading = r;
                        g.slots[d].last_error = None;
                    }
                    if cmd.stream {
                        self.spec.drives[d].last_target = cmd.target;
                    }
                }
            }
        }
    }
}
