//! Emulated CiA 402 servo and spindle amplifiers on a CANopen bus, for cncgw tests, CI and
//! first runs without hardware. Physically: motor + load inertia, torque limit, velocity PI,
//! position P with feed-forward, friction, whole-count encoder. On the wire: NMT slave,
//! SDO server, PDOs, SYNC, heartbeat, EMCY, the 402 state machine — all through the codecs
//! of `cncgw-bus`, the same ones the master uses.
//!
//! Two ways to run: `SimWorld` in simulated time (it is the `Clock` of the test or of the
//! default machine: waiting on it advances the drives deterministically), and
//! `run_realtime` on any `CanBus` (the `sim-drives` binary on vcan0/can0).

pub mod buslog;
pub mod config;
pub mod drive;
pub mod io401;
pub mod modbus;
pub mod modbus_io;
pub mod od;
pub mod report;
pub mod servo;
pub mod socketcand;

pub use config::{DriveConfig, DriveKind, ModbusQuirks, Physics, SimConfig};
pub use drive::SimDrive;

use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{BusError, CanBus, CanFrame, Clock};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A fault for `sim-drives --fault`: the write `value` → 0x2100:`sub` of `node`, `at_ns`
/// after the start (see `drive::fault_sub` and the README).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaultAt {
    pub node: u8,
    pub sub: u8,
    pub value: u32,
    pub at_ns: u64,
}

/// Fault names accepted by `--fault`, their 0x2100 sub-index and the value when none is given.
pub const FAULT_NAMES: &[(&str, u8, Option<u32>)] = &[
    ("raise", drive::fault_sub::RAISE, None),
    ("encoder-lost", drive::fault_sub::ENCODER_LOST, Some(1)),
    ("undervoltage", drive::fault_sub::UNDERVOLTAGE, Some(1)),
    ("overcurrent", drive::fault_sub::OVERCURRENT, Some(1)),
    ("jam-mnm", drive::fault_sub::JAM_MNM, None),
    ("heartbeat-stop", drive::fault_sub::HEARTBEAT_MUTED, Some(1)),
    ("silent-ms", drive::fault_sub::SILENT_MS, Some(u32::MAX)),
    ("pdo-drop-permille", drive::fault_sub::PDO_DROP_PERMILLE, None),
    ("tpdo-delay-us", drive::fault_sub::TPDO_DELAY_US, None),
    ("ip-disable", drive::fault_sub::IP_DISABLE, Some(1)),
    ("sync-stop", drive::fault_sub::SYNC_MUTED, Some(1)),
];

/// Parse `NODE:NAME[=VALUE][@MS]`, e.g. `1:encoder-lost@2000`, `2:pdo-drop-permille=50`,
/// `1:raise=0x4310@500`, `3:silent-ms=300@1000` (no value: silent for good).
pub fn parse_fault(spec: &str) -> Result<FaultAt, String> {
    let bad = |why: &str| {
        let names: Vec<&str> = FAULT_NAMES.iter().map(|n| n.0).collect();
        format!("--fault {spec}: {why}; expected NODE:NAME[=VALUE][@MS] with NAME one of {}", names.join(", "))
    };
    let (spec_main, at) = match spec.split_once('@') {
        Some((a, b)) => (a, b.trim().parse::<u64>().map_err(|_| bad("@MS is not a whole number of milliseconds"))?),
        None => (spec, 0),
    };
    let (node, rest) = spec_main.split_once(':').ok_or_else(|| bad("no NODE:"))?;
    let node: u8 = node.trim().parse().ok().filter(|n| (1..=127).contains(n)).ok_or_else(|| bad("NODE must be 1–127"))?;
    let (name, value) = match rest.split_once('=') {
        Some((n, v)) => (n.trim(), Some(v.trim())),
        None => (rest.trim(), None),
    };
    let &(_, sub, default) = FAULT_NAMES.iter().find(|n| n.0 == name).ok_or_else(|| bad(&format!("unknown fault {name:?}")))?;
    let value = match value {
        Some(v) => {
            let parsed = match v.strip_prefix("0x").or_else(|| v.strip_prefix("0X")) {
                Some(h) => u32::from_str_radix(h, 16).ok(),
                None => v.parse::<u32>().ok(),
            };
            parsed.ok_or_else(|| bad(&format!("value {v:?} is not a number")))?
        }
        None => default.ok_or_else(|| bad(&format!("{name} needs =VALUE")))?,
    };
    Ok(FaultAt { node, sub, value, at_ns: at * 1_000_000 })
}

/// The drives and their common time, independent of the transport.
struct Core {
    drives: Vec<SimDrive>,
    now: u64,
    step_ns: u64,
    last_tick: Option<u64>,
    out: Vec<CanFrame>,
    /// Faults still to inject, latest first.
    faults: Vec<FaultAt>,
    /// CiA 401 I/O modules (`io401`).
    io: Vec<io401::SimIo>,
}

impl Core {
    fn new(cfg: SimConfig) -> Core {
        let step_us = cfg.step_us.clamp(1, 100);
        let mut drives: Vec<SimDrive> = cfg.drives.into_iter().map(|d| SimDrive::new(d, step_us)).collect();
        drives.sort_by_key(|d| d.node());
        Core { drives, now: 0, step_ns: step_us as u64 * 1000, last_tick: None, out: Vec::new(), faults: Vec::new(), io: Vec::new() }
    }

    fn collect(&mut self) {
        for m in &mut self.io {
            m.take_output(&mut self.out);
        }
        for k in 0..self.drives.len() {
            let from = self.out.len();
            self.drives[k].take_output(&mut self.out);
            // A SYNC one drive produces (0x1005 bit 30) reaches the others as on a real bus;
            // the producer acted on it already. Rare: only drives shaped as SYNC producers.
            let syncs = self.out[from..].iter().filter(|f| f.id == cncgw_bus::canopen::cob::SYNC as u32 && !f.extended && !f.rtr).count();
            for _ in 0..syncs {
                let f = cncgw_bus::canopen::sync_frame(None);
                for (j, d) in self.drives.iter_mut().enumerate() {
                    if j != k {
                        d.handle_frame(&f, self.now);
                        d.take_output(&mut self.out);
                    }
                }
            }
        }
    }

    fn handle(&mut self, f: &CanFrame) {
        for d in &mut self.drives {
            d.handle_frame(f, self.now);
        }
        for m in &mut self.io {
            m.handle_frame(f, self.now);
        }
        self.collect();
    }

    /// Timers and (on the grid) the control tick at the present instant.
    fn fire(&mut self) {
        let now = self.now;
        while self.faults.last().is_some_and(|f| f.at_ns <= now) {
            if let Some(f) = self.faults.pop() {
                match self.drive_mut(f.node).map(|d| d.set_sim_fault(f.sub, f.value, now)) {
                    Some(Ok(())) => tracing::warn!(node = f.node, "injected fault: 0x2100:{} = {}", f.sub, f.value),
                    Some(Err(code)) => tracing::error!(node = f.node, "fault 0x2100:{} = {} refused (abort 0x{code:08X})", f.sub, f.value),
                    None => tracing::error!("fault for node {}: no such node", f.node),
                }
            }
        }
        for d in &mut self.drives {
            d.on_time(now);
        }
        if now % self.step_ns == 0 && self.last_tick != Some(now) {
            self.last_tick = Some(now);
            for d in &mut self.drives {
                d.tick(now);
            }
            for m in &mut self.io {
                m.tick(now);
            }
        }
        self.collect();
    }

    /// Integrate to `t` in steps no longer than the control period, stopping at every
    /// control tick and timer.
    fn advance_to(&mut self, t: u64, mut flush: impl FnMut(&mut Vec<CanFrame>, u64)) {
        loop {
            self.fire();
            flush(&mut self.out, self.now);
            if self.now >= t {
                return;
            }
            let mut next = ((self.now / self.step_ns) + 1) * self.step_ns;
            next = next.min(t);
            if let Some(f) = self.faults.last() {
                if f.at_ns > self.now && f.at_ns < next {
                    next = f.at_ns;
                }
            }
            for d in &self.drives {
                if let Some(e) = d.next_event() {
                    if e > self.now && e < next {
                        next = e;
                    }
                }
            }
            let dt = (next - self.now) as f64 * 1e-9;
            for d in &mut self.drives {
                d.integrate(dt);
            }
            self.now = next;
        }
    }

    fn schedule(&mut self, mut faults: Vec<FaultAt>) {
        faults.sort_by_key(|f| std::cmp::Reverse(f.at_ns));
        self.faults = faults;
    }

    fn drive(&self, node: u8) -> Option<&SimDrive> {
        self.drives.iter().find(|d| d.node() == node)
    }

    fn drive_mut(&mut self, node: u8) -> Option<&mut SimDrive> {
        self.drives.iter_mut().find(|d| d.node() == node)
    }
}

fn send_all(bus: &mut dyn CanBus, out: &mut Vec<CanFrame>) {
    for f in out.drain(..) {
        if let Err(e) = bus.send(&f) {
            // A drive on a bus-off bus loses its frames, as a real one does.
            tracing::debug!("send {f:?}: {e}");
        }
    }
}

/// Emulated drives on an in-process bus, stepped in simulated time. As a `Clock`,
/// `wait_until(t)` first handles every frame waiting on its endpoint (answers SDOs, applies
/// NMT, buffers RPDOs; on SYNC latches the CSP targets and sends the TPDOs sampled at that
/// instant), then integrates the physics from now to `t` in control steps (≤ 0.1 ms),
/// firing timers (boot-up, heartbeat, heartbeat-consumer timeout, following-error timeout)
/// at their exact times. Frames sent inside `wait_until` are on the bus when it returns.
/// Deterministic: same frames in, same frames out.
pub struct SimWorld {
    core: Core,
    ep: InprocEndpoint,
    /// The wire, whose time this world sets (delayed frames fall due by it).
    bus: InprocBus,
}

impl SimWorld {
    pub fn new(bus: &InprocBus, cfg: SimConfig) -> SimWorld {
        SimWorld { core: Core::new(cfg), ep: bus.endpoint(), bus: bus.clone() }
    }

    pub fn drive(&self, node: u8) -> Option<&SimDrive> {
        self.core.drive(node)
    }

    pub fn drive_mut(&mut self, node: u8) -> Option<&mut SimDrive> {
        self.core.drive_mut(node)
    }

    pub fn drives(&self) -> &[SimDrive] {
        &self.core.drives
    }

    /// Add an emulated CiA 401 I/O module (it sends its boot-up now).
    pub fn add_io_module(&mut self, cfg: io401::IoModuleConfig) {
        self.core.io.push(io401::SimIo::new(cfg));
    }

    /// Force input `bit` of I/O module `node` (`None`: back to its wiring). False: no such module.
    pub fn set_io_input(&mut self, node: u8, bit: u8, v: Option<bool>) -> bool {
        self.core.io.iter_mut().find(|m| m.node() == node).map(|m| m.wiring.force(bit, v)).is_some()
    }

    /// The outputs of I/O module `node`.
    pub fn io_outputs(&self, node: u8) -> Option<u32> {
        self.core.io.iter().find(|m| m.node() == node).map(|m| m.wiring.outputs())
    }

    /// Raise a fault on `node` now (EMCY, 0x603F, fault reaction). False if no such node.
    pub fn inject_fault(&mut self, node: u8, code: u16) -> bool {
        let now = self.core.now;
        match self.core.drive_mut(node) {
            Some(d) => {
                d.inject_fault(code, now);
                self.core.collect();
                let SimWorld { core, ep, .. } = self;
                send_all(ep, &mut core.out);
                true
            }
            None => false,
        }
    }

    /// Inject a fault now as the SDO write `value` → 0x2100:`sub` would (see
    /// `drive::fault_sub`). Err: the SDO abort code, or 0 if there is no such node.
    pub fn set_sim_fault(&mut self, node: u8, sub: u8, value: u32) -> Result<(), u32> {
        let now = self.core.now;
        let r = self.core.drive_mut(node).map(|d| d.set_sim_fault(sub, value, now)).unwrap_or(Err(0));
        self.core.collect();
        let SimWorld { core, ep, .. } = self;
        send_all(ep, &mut core.out);
        r
    }

    /// Faults to inject at their times (simulated time from 0), as `sim-drives --fault`.
    pub fn schedule_faults(&mut self, faults: Vec<FaultAt>) {
        self.core.schedule(faults);
    }

    fn pump(&mut self) {
        loop {
            match self.ep.try_recv() {
                Ok(Some(f)) => {
                    self.core.handle(&f);
                    let SimWorld { core, ep, .. } = self;
                    send_all(ep, &mut core.out);
                }
                Ok(None) => return,
                Err(BusError::Overflow { dropped, .. }) => {
                    tracing::warn!("sim-drives endpoint overflow: {dropped} frames lost");
                }
                Err(_) => return,
            }
        }
    }
}

impl Clock for SimWorld {
    fn now_ns(&self) -> u64 {
        self.core.now
    }

    fn wait_until(&mut self, t_ns: u64) {
        self.bus.set_time_ns(self.core.now);
        self.pump();
        let SimWorld { core, ep, bus } = self;
        core.advance_to(t_ns, |out, now| {
            bus.set_time_ns(now);
            send_all(ep, out)
        });
        bus.set_time_ns(core.now);
    }

    fn is_simulated(&self) -> bool {
        true
    }
}

/// How long before an expected SYNC the real-time loop integrates up to it.
const SYNC_LEAD_NS: u64 = 60_000;

/// Real time: serve the drives on `bus` until `stop` is set. Frames are handled as they
/// arrive (a SYNC gets its TPDOs at once); between frames the physics is integrated up to
/// the wall clock in control steps and timers fire.
pub fn run_realtime(bus: Box<dyn CanBus>, cfg: SimConfig, stop: Arc<AtomicBool>) -> Result<(), String> {
    run_realtime_with_faults(bus, cfg, stop, Vec::new())
}

/// `run_realtime`, injecting `faults` at their times after the start (`--fault`).
pub fn run_realtime_with_faults(bus: Box<dyn CanBus>, cfg: SimConfig, stop: Arc<AtomicBool>, faults: Vec<FaultAt>) -> Result<(), String> {
    run_realtime_with_io(bus, cfg, stop, faults, Vec::new())
}

/// `run_realtime_with_faults` with emulated CiA 401 I/O modules on the bus.
pub fn run_realtime_with_io(
    mut bus: Box<dyn CanBus>,
    cfg: SimConfig,
    stop: Arc<AtomicBool>,
    faults: Vec<FaultAt>,
    io: Vec<io401::IoModuleConfig>,
) -> Result<(), String> {
    cfg.validate()?;
    let mut core = Core::new(cfg);
    core.io = io.into_iter().map(io401::SimIo::new).collect();
    core.schedule(faults);
    let start = Instant::now();
    let now = |s: &Instant| s.elapsed().as_nanos() as u64;
    let name = bus.name().to_string();
    tracing::info!("sim-drives on {name}: nodes {:?}", core.drives.iter().map(|d| d.node()).collect::<Vec<_>>());
    while !stop.load(Ordering::Relaxed) {
        // Frames that queued up while this process was descheduled act at their arrival
        // times first: integrating to now before them would extrapolate past SYNCs the master
        // did send (a drive 10 periods ahead of the set-point it then reads: 0x8611).
        let first = bus.try_recv();
        handle_queued(&mut bus, &mut core, &start, first, &name)?;
        let t = now(&start);
        core.advance_to(t, |out, _| send_all(&mut bus, out));
        // Frames wake us; otherwise wake for the next timer, just before the next SYNC is
        // due (the physics is then integrated up to almost the SYNC instant beforehand, and
        // the TPDOs leave without a catch-up on the critical path), and at least every 2 ms
        // so that faults found by the physics are reported when the master is silent. Waking
        // more often only costs system calls (20 µs each in a UML guest).
        let mut wait = Duration::from_millis(2);
        if let Some(e) = core.drives.iter().filter_map(|d| d.next_event()).min() {
            wait = wait.min(Duration::from_nanos(e.saturating_sub(t)));
        }
        if let Some(s) = core.drives.iter().filter_map(|d| d.expected_sync()).min() {
            let pre = s.saturating_sub(SYNC_LEAD_NS);
            if pre > t {
                wait = wait.min(Duration::from_nanos(pre - t));
            }
        }
        let first = bus.recv_timeout(wait);
        handle_queued(&mut bus, &mut core, &start, first, &name)?;
    }
    tracing::info!("sim-drives on {name}: stopped");
    Ok(())
}

/// Handle `first` and every frame queued behind it, each at its arrival time where the
/// transport knows it: after this process was descheduled, queued SYNCs are still handled at
/// the instants the master sent them, as a real drive would have. Err: the bus failed.
fn handle_queued(
    bus: &mut Box<dyn CanBus>,
    core: &mut Core,
    start: &Instant,
    first: Result<Option<CanFrame>, BusError>,
    name: &str,
) -> Result<(), String> {
    let mut next = first;
    loop {
        let f = match next {
            Ok(Some(f)) => f,
            Ok(None) => return Ok(()),
            Err(BusError::Overflow { dropped, .. }) => {
                tracing::warn!("{name}: receive overflow, {dropped} frames lost");
                return Ok(());
            }
            Err(e) => return Err(e.to_string()),
        };
        let t_now = start.elapsed().as_nanos() as u64;
        let t = match bus.last_rx_age() {
            Some(age) => t_now.saturating_sub(age.as_nanos() as u64).max(core.now),
            None => t_now,
        };
        core.advance_to(t, |out, _| send_all(&mut **bus, out));
        core.handle(&f);
        send_all(&mut **bus, &mut core.out);
        next = bus.try_recv();
    }
}
