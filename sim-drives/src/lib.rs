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
pub mod od;
pub mod servo;
pub mod socketcand;

pub use config::{DriveConfig, DriveKind, Physics, SimConfig};
pub use drive::SimDrive;

use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{BusError, CanBus, CanFrame, Clock};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The drives and their common time, independent of the transport.
struct Core {
    drives: Vec<SimDrive>,
    now: u64,
    step_ns: u64,
    last_tick: Option<u64>,
    out: Vec<CanFrame>,
}

impl Core {
    fn new(cfg: SimConfig) -> Core {
        let step_us = cfg.step_us.clamp(1, 100);
        let mut drives: Vec<SimDrive> = cfg.drives.into_iter().map(|d| SimDrive::new(d, step_us)).collect();
        drives.sort_by_key(|d| d.node());
        Core { drives, now: 0, step_ns: step_us as u64 * 1000, last_tick: None, out: Vec::new() }
    }

    fn collect(&mut self) {
        for d in &mut self.drives {
            d.take_output(&mut self.out);
        }
    }

    fn handle(&mut self, f: &CanFrame) {
        for d in &mut self.drives {
            d.handle_frame(f, self.now);
        }
        self.collect();
    }

    /// Timers and (on the grid) the control tick at the present instant.
    fn fire(&mut self) {
        let now = self.now;
        for d in &mut self.drives {
            d.on_time(now);
        }
        if now % self.step_ns == 0 && self.last_tick != Some(now) {
            self.last_tick = Some(now);
            for d in &mut self.drives {
                d.tick(now);
            }
        }
        self.collect();
    }

    /// Integrate to `t` in steps no longer than the control period, stopping at every
    /// control tick and timer.
    fn advance_to(&mut self, t: u64, mut flush: impl FnMut(&mut Vec<CanFrame>)) {
        loop {
            self.fire();
            flush(&mut self.out);
            if self.now >= t {
                return;
            }
            let mut next = ((self.now / self.step_ns) + 1) * self.step_ns;
            next = next.min(t);
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
}

impl SimWorld {
    pub fn new(bus: &InprocBus, cfg: SimConfig) -> SimWorld {
        SimWorld { core: Core::new(cfg), ep: bus.endpoint() }
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

    /// Raise a fault on `node` now (EMCY, 0x603F, fault reaction). False if no such node.
    pub fn inject_fault(&mut self, node: u8, code: u16) -> bool {
        let now = self.core.now;
        match self.core.drive_mut(node) {
            Some(d) => {
                d.inject_fault(code, now);
                self.core.collect();
                let SimWorld { core, ep } = self;
                send_all(ep, &mut core.out);
                true
            }
            None => false,
        }
    }

    fn pump(&mut self) {
        loop {
            match self.ep.try_recv() {
                Ok(Some(f)) => {
                    self.core.handle(&f);
                    let SimWorld { core, ep } = self;
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
        self.pump();
        let SimWorld { core, ep } = self;
        core.advance_to(t_ns, |out| send_all(ep, out));
    }

    fn is_simulated(&self) -> bool {
        true
    }
}

/// Real time: serve the drives on `bus` until `stop` is set. Frames are handled as they
/// arrive (a SYNC gets its TPDOs at once); between frames the physics is integrated up to
/// the wall clock in control steps and timers fire.
pub fn run_realtime(mut bus: Box<dyn CanBus>, cfg: SimConfig, stop: Arc<AtomicBool>) -> Result<(), String> {
    cfg.validate()?;
    let mut core = Core::new(cfg);
    let start = Instant::now();
    let now = |s: &Instant| s.elapsed().as_nanos() as u64;
    let name = bus.name().to_string();
    tracing::info!("sim-drives on {name}: nodes {:?}", core.drives.iter().map(|d| d.node()).collect::<Vec<_>>());
    while !stop.load(Ordering::Relaxed) {
        let t = now(&start);
        core.advance_to(t, |out| send_all(&mut bus, out));
        // Wake for the next timer or control work at least every 0.5 ms.
        let mut wait = Duration::from_micros(500);
        if let Some(e) = core.drives.iter().filter_map(|d| d.next_event()).min() {
            wait = wait.min(Duration::from_nanos(e.saturating_sub(t)));
        }
        match bus.recv_timeout(wait) {
            Ok(Some(f)) => {
                let mut f = Some(f);
                while let Some(fr) = f {
                    core.advance_to(now(&start), |out| send_all(&mut bus, out));
                    core.handle(&fr);
                    send_all(&mut bus, &mut core.out);
                    f = match bus.try_recv() {
                        Ok(x) => x,
                        Err(BusError::Overflow { dropped, .. }) => {
                            tracing::warn!("{name}: receive overflow, {dropped} frames lost");
                            None
                        }
                        Err(e) => return Err(e.to_string()),
                    };
                }
            }
            Ok(None) => {}
            Err(BusError::Overflow { dropped, .. }) => tracing::warn!("{name}: receive overflow, {dropped} frames lost"),
            Err(e) => return Err(e.to_string()),
        }
    }
    tracing::info!("sim-drives on {name}: stopped");
    Ok(())
}
