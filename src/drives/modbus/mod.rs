//! Modbus RTU / TCP drives behind the same `DriveBus` as CANopen.
//!
//! Each `[modbus.NAME]` link runs on its own I/O thread (`link`) at the cycle the link can
//! really carry: computed from baud, framing, request/response sizes and the 3.5-character
//! silence on RTU, measured from the round trip on TCP; never shorter than the machine
//! cycle, in whole milliseconds (the drives' interpolation-period register is in ms). The
//! cycle thread hands each drive its latest set-point every machine cycle; the link sends
//! the latest one every link cycle and the drive interpolates over the link cycle — so the
//! planner's path is sampled at the link's cycle for those axes. The CiA 402 state machine
//! is the CANopen layer's (`cncgw_bus::cia402::Enabler`).

pub mod io;
pub mod line;
pub mod link;
pub mod plan;

use crate::config::MachineConfig;
use crate::drives::{AxisFeedback, DriveBus, SpindleControl};
use crate::Alarm;
use cncgw_bus::canopen::emcy::error_text;
use cncgw_bus::cia402::{cw, EnableProgress, Enabler, State};
use cncgw_bus::modbus::Profile;
use cncgw_bus::Clock;
use link::{Command, LinkSpec, LinkState, SharedLink};
use plan::DrivePlan;
use std::time::{Duration, Instant};

/// Alarm numbers of the Modbus layer.
pub mod alarm {
    /// The link cannot be opened (connection refused, no serial device).
    pub const LINK: u32 = crate::alarm::MODBUS_LINK;
    /// A drive answered with an exception.
    pub const EXCEPTION: u32 = crate::alarm::MODBUS_EXCEPTION;
    /// A drive did not answer.
    pub const TIMEOUT: u32 = crate::alarm::MODBUS_TIMEOUT;
    /// A spindle-synchronised move needs a faster link than this one.
    pub const SYNC_TOO_SLOW: u32 = crate::alarm::MODBUS_SYNC_TOO_SLOW;
    /// A configured link cycle is shorter than the link can carry.
    pub const CYCLE: u32 = crate::alarm::MODBUS_CYCLE;
}

/// What a link has done.
#[derive(Clone, Debug, Default)]
pub struct LinkStats {
    pub name: String,
    /// The cycle it runs at.
    pub cycle: Duration,
    /// Modbus transactions (answered or failed), failed ones, link cycles run, and link
    /// cycles that started more than a cycle late.
    pub transactions: u64,
    pub failures: u64,
    pub cycles: u64,
    pub overruns: u64,
    /// Bytes of late answers dropped to keep the exchange in step.
    pub stale_bytes: u64,
}

/// A link before start-up.
pub struct PlannedLink {
    pub name: String,
    pub what: String,
    /// Transactions per link cycle.
    pub transactions: usize,
    /// RTU: the time one cycle's transactions take on the line (s) and the link cycle run
    /// over it (ms). TCP's cycle is measured at start-up.
    pub rtu: Option<(f64, f64)>,
}

/// An axis speed (`max_speed`: mm/min, or rpm for a spindle) in motor rpm of a drive with
/// `counts_per_rev` counts per motor revolution.
fn motor_rpm(speed: f64, a: &crate::config::AxisConfig, counts_per_rev: u32) -> f64 {
    let per_min = match a.kind {
        crate::config::AxisKind::Linear => speed * a.counts_per_unit,
        _ => speed * 360.0 * a.counts_per_unit,
    };
    per_min / counts_per_rev.max(1) as f64
}

struct Axis {
    name: String,
    link: usize,
    slot: usize,
    unit: u8,
    profile: Profile,
    counts_per_unit: f64,
    /// A CiA 402 spindle: may run in speed (`set_spindle_control`).
    speed_capable: bool,
    // The cycle thread's view.
    cmd: Command,
    enabler: Enabler,
    enabled: bool,
    last_seq: u64,
    raw: i32,
    unwrapped: i64,
    demand: i64,
    statusword: u16,
    error_code: u16,
    fb_at: Option<Instant>,
    have_fb: bool,
    target: i64,
    last_error: Option<String>,
    /// Its leaving Operation Enabled was alarmed (not again: the others stop under control).
    reported: bool,
}

struct Link {
    name: String,
    what: String,
    shared: Option<SharedLink>,
    thread: Option<std::thread::JoinHandle<()>>,
    spec: Option<LinkSpec>,
    cycle: Duration,
}

/// Every Modbus drive of a machine (the axes with `modbus = "LINK"`), in config order.
pub struct ModbusDrives {
    axes: Vec<Axis>,
    links: Vec<Link>,
    cycle_ns: u64,
    feedback_timeout: Duration,
    running: bool,
    /// `quick_stop` was sent: Quick Stop Active is ours.
    stopping: bool,
    /// `isolate_faults`: a drive that faults is stopped alone (`faulted`), the layer above
    /// stops the others under control.
    isolate: bool,
    faulted: Option<usize>,
    enable_cycles: u64,
    t0: Instant,
}

impl ModbusDrives {
    /// The SCHED_FIFO priority of the cycle thread (`--rt-priority` or `[rt] priority`): the
    /// link threads run one below it. Call before `startup`.
    pub fn set_rt_priority(&mut self, cycle_priority: Option<i32>) {
        for l in &mut self.links {
            if let Some(s) = &mut l.spec {
                s.rt_priority = cycle_priority.map(|p| (p - 1).max(1));
            }
        }
    }

    /// The Modbus axes of `cfg`. Nothing is opened until `startup`.
    pub fn new(cfg: &MachineConfig) -> ModbusDrives {
        let mut links: Vec<Link> = Vec::new();
        let mut axes = Vec::new();
        let cycle = Duration::from_secs_f64(cfg.machine.cycle_ms * 1e-3);
        for (name, a) in &cfg.axes {
            let Some(lname) = &a.modbus else { continue };
            let Some(lcfg) = cfg.modbus.get(lname) else { continue };
            let li = match links.iter().position(|l| &l.name == lname) {
                Some(i) => i,
                None => {
                    links.push(Link {
                        name: lname.clone(),
                        what: String::new(),
                        shared: None,
                        thread: None,
                        spec: Some(LinkSpec {
                            name: lname.clone(),
                            cfg: lcfg.clone(),
                            drives: Vec::new(),
                            machine_cycle: cycle,
                            rt_priority: cfg.rt.priority.map(|p| (p - 1).max(1)),
                        }),
                        cycle: Duration::ZERO,
                    });
                    links.len() - 1
                }
            };
            let ferr = (a.following_error * a.counts_per_unit).round().clamp(1.0, i32::MAX as f64) as u32;
            let mut plan =
                DrivePlan::new(name, a.node, a.modbus_profile, a.cia402_map.unwrap_or_default(), a.pr_map.unwrap_or_default(), lcfg.fc23, ferr);
            plan.max_rpm = motor_rpm(a.max_speed, a, plan.pr.counts_per_rev);
            if a.kind == crate::config::AxisKind::Spindle {
                plan.allow_speed_mode();
            }
            let speed_capable = plan.speed_capable;
            let spec = links[li].spec.as_mut().expect("spec is present until startup");
            let slot = spec.drives.len();
            spec.drives.push(plan);
            axes.push(Axis {
                name: name.clone(),
                link: li,
                slot,
                unit: a.node,
                profile: a.modbus_profile,
                counts_per_unit: a.counts_per_unit,
                speed_capable,
                cmd: Command::default(),
                enabler: Enabler::default(),
                enabled: false,
                last_seq: 0,
                raw: 0,
                unwrapped: 0,
                demand: 0,
                statusword: 0,
                error_code: 0,
                fb_at: None,
                have_fb: false,
                target: 0,
                last_error: None,
                reported: false,
            });
        }
        for l in &mut links {
            l.what = l.spec.as_ref().map(|s| s.what()).unwrap_or_default();
        }
        let cycle_ns = cfg.cycle_ns();
        ModbusDrives {
            axes,
            links,
            cycle_ns,
            feedback_timeout: Duration::from_secs_f64(cfg.bus.feedback_timeout_ms * 1e-3),
            running: false,
            stopping: false,
            isolate: false,
            faulted: None,
            enable_cycles: 0,
            t0: Instant::now(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.axes.is_empty()
    }

    /// Before start-up, per link: what `config check` says of it.
    pub fn planned_links(&self) -> Vec<PlannedLink> {
        self.links
            .iter()
            .filter_map(|l| {
                let s = l.spec.as_ref()?;
                let rtu = (s.cfg.transport == crate::config::LinkTransport::Rtu).then(|| (s.rtu_cycle_s(), s.rtu_link_cycle_ms()));
                Some(PlannedLink { name: l.name.clone(), what: l.what.clone(), transactions: s.transactions_per_cycle(), rtu })
            })
            .collect()
    }

    /// Per link: its statistics so far.
    pub fn link_stats(&self) -> Vec<LinkStats> {
        self.links
            .iter()
            .map(|l| {
                let mut st = LinkStats { name: l.name.clone(), cycle: l.cycle, ..LinkStats::default() };
                if let Some(g) = l.shared.as_ref().and_then(|s| s.0.lock().ok()) {
                    st.transactions = g.transactions;
                    st.failures = g.failures;
                    st.overruns = g.overruns;
                    st.cycles = g.cycles;
                    st.stale_bytes = g.stale_bytes;
                }
                st
            })
            .collect()
    }

    fn axis_alarm(&self, i: usize, number: u32, msg: impl std::fmt::Display) -> Alarm {
        let a = &self.axes[i];
        let l = &self.links[a.link];
        Alarm::new(number, format!("axis {} (Modbus link {}, unit {}): {msg}", a.name, l.name, self.unit(i)))
    }

    /// Alarm 2010 once for a drive that left Operation Enabled on its own while running: a
    /// fault (also while it brakes in Fault Reaction Active, which lasts as long as its stop
    /// ramp — over a second on a spindle), a quick stop of its own (a stop input, a limit),
    /// or a disable. Reported once, so that the controlled stop of the others goes on
    /// (CANopen's master isolates a faulted node the same way).
    fn left_operation_enabled(&mut self, i: usize) -> Option<Alarm> {
        let a = &self.axes[i];
        if !self.running || a.reported || !a.have_fb {
            return None;
        }
        let st = State::from_statusword(a.statusword);
        let code = a.error_code;
        let what = match st {
            State::OperationEnabled => return None,
            // Our own quick stop: not the drive's doing.
            State::QuickStopActive if self.stopping => return None,
            State::Fault => format!("drive fault, error code 0x{code:04X} {}", error_text(code)),
            State::FaultReactionActive => {
                format!("drive fault (Fault Reaction Active: the drive is braking on its own), error code 0x{code:04X} {}", error_text(code))
            }
            State::QuickStopActive => {
                "the drive went to Quick Stop Active on its own (a stop input or one of its limits); the others are stopped under control".into()
            }
            _ if self.stopping => return None,
            st => format!("the drive left Operation Enabled on its own: now {}", st.name()),
        };
        Some(self.report(i, crate::alarm::DRIVE_FAULT, what))
    }

    /// Alarm `number` for axis `i`, once: isolated (the first, when isolating) or every
    /// drive quick-stopped (a second one).
    fn report(&mut self, i: usize, number: u32, what: impl std::fmt::Display) -> Alarm {
        self.isolate_axis(i);
        self.axis_alarm(i, number, what)
    }

    fn isolate_axis(&mut self, i: usize) {
        self.axes[i].reported = true;
        if self.isolate && self.faulted.is_none_or(|f| f == i) {
            self.faulted = Some(i);
            let a = &mut self.axes[i];
            a.cmd.velocity = 0.0;
            match a.profile {
                Profile::Cia402 => a.cmd.controlword = cw::QUICK_STOP_CMD,
                Profile::Pr => a.cmd.target = a.raw,
            }
        } else {
            self.faulted = None;
        }
    }

    fn unit(&self, i: usize) -> u8 {
        self.axes[i].unit
    }

    fn stop_links(&mut self) {
        for l in &mut self.links {
            if let Some(s) = &l.shared {
                if let Ok(mut g) = s.0.lock() {
                    g.stop = true;
                }
            }
            if let Some(h) = l.thread.take() {
                let _ = h.join();
            }
        }
    }
}

impl Drop for ModbusDrives {
    fn drop(&mut self) {
        self.stop_links();
    }
}

impl DriveBus for ModbusDrives {
    fn startup(&mut self, _clock: &mut dyn Clock) -> Result<(), Alarm> {
        // Modbus runs in real time only (the emulated in-process bus is CANopen): waits
        // here are on the wall clock.
        self.t0 = Instant::now();
        for l in &mut self.links {
            let Some(spec) = l.spec.take() else { continue };
            let (shared, h) =
                link::spawn(spec).map_err(|e| Alarm::new(alarm::LINK, format!("Modbus link {}: cannot start its thread: {e}", l.name)))?;
            l.shared = Some(shared);
            l.thread = Some(h);
        }
        for li in 0..self.links.len() {
            let Some(s) = self.links[li].shared.clone() else { continue };
            let (m, cv) = &*s;
            let Ok(mut g) = m.lock() else { continue };
            let deadline = Instant::now() + Duration::from_secs(10);
            while matches!(g.state, LinkState::Starting) {
                let left = deadline.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    return Err(Alarm::new(alarm::TIMEOUT, format!("Modbus link {}: start-up did not finish within 10 s", self.links[li].name)));
                }
                g = match cv.wait_timeout(g, left) {
                    Ok((g, _)) => g,
                    Err(_) => return Err(Alarm::new(alarm::LINK, "Modbus link thread failed")),
                };
            }
            match &g.state {
                LinkState::Failed(a) => return Err(a.clone()),
                LinkState::Running { cycle } => {
                    self.links[li].cycle = *cycle;
                    tracing::info!(link = %self.links[li].name, "{}: cycle {:.0} ms", self.links[li].what, cycle.as_secs_f64() * 1e3);
                }
                LinkState::Starting => {}
            }
        }
        // Start from the drives' actual positions.
        self.receive(0)?;
        for a in &mut self.axes {
            a.target = a.unwrapped;
            a.cmd.target = a.raw;
            a.cmd.velocity = 0.0;
        }
        Ok(())
    }

    fn receive(&mut self, _now_ns: u64) -> Result<(), Alarm> {
        let now = Instant::now();
        for i in 0..self.axes.len() {
            let li = self.axes[i].link;
            let Some(s) = self.links[li].shared.clone() else { continue };
            let (r, last_error) = {
                let Ok(mut g) = s.0.lock() else { continue };
                if let LinkState::Failed(a) = &g.state {
                    return Err(a.clone());
                }
                if let Some((slot, a)) = g.alarm.take() {
                    drop(g);
                    // One drive's exception: that drive is isolated; the link's own
                    // trouble (falling behind its cycle) concerns every drive on it.
                    if let Some(ax) = slot.and_then(|sl| (0..self.axes.len()).find(|&k| self.axes[k].link == li && self.axes[k].slot == sl)) {
                        self.isolate_axis(ax);
                    }
                    return Err(a);
                }
                let sl = &g.slots[self.axes[i].slot];
                (sl.reading, sl.last_error.clone())
            };
            let a = &mut self.axes[i];
            a.last_error = last_error;
            if r.seq != a.last_seq && r.at.is_some() {
                a.last_seq = r.seq;
                let delta = r.position.wrapping_sub(a.raw) as i64;
                a.unwrapped = if a.have_fb { a.unwrapped + delta } else { r.position as i64 };
                a.demand = a.unwrapped + r.demand.wrapping_sub(r.position) as i64;
                a.raw = r.position;
                a.statusword = r.statusword;
                a.error_code = r.error_code;
                a.fb_at = r.at;
                a.have_fb = true;
            }
            let age = a.fb_at.map(|t| now.saturating_duration_since(t)).unwrap_or(Duration::MAX);
            let limit = self.feedback_timeout.max(self.links[li].cycle * 3);
            if self.running && age > limit && !self.axes[i].reported {
                let why = self.axes[i].last_error.clone().unwrap_or_else(|| "no answer".into());
                return Err(self.report(
                    i,
                    crate::alarm::STALE_FEEDBACK,
                    format!(
                        "no position feedback for {:.1} ms (link cycle {:.0} ms): {why}",
                        age.as_secs_f64() * 1e3,
                        self.links[li].cycle.as_secs_f64() * 1e3
                    ),
                ));
            }
            if let Some(a) = self.left_operation_enabled(i) {
                return Err(a);
            }
        }
        Ok(())
    }

    fn feedback(&self, axis: usize) -> AxisFeedback {
        let a = &self.axes[axis];
        let age = a.fb_at.map(|t| (Instant::now().saturating_duration_since(t).as_nanos() as u64 / self.cycle_ns.max(1)) as u32).unwrap_or(u32::MAX);
        AxisFeedback {
            pos: a.unwrapped as f64 / a.counts_per_unit,
            counts: a.unwrapped,
            statusword: a.statusword,
            age_cycles: age,
            demand_counts: Some(a.demand),
            sampled_ns: a.fb_at.map(|t| t.saturating_duration_since(self.t0).as_nanos() as u64),
        }
    }

    fn set_target(&mut self, axis: usize, pos: f64) {
        let a = &mut self.axes[axis];
        if !a.enabled {
            return;
        }
        let c = (pos * a.counts_per_unit).round();
        if c.is_finite() && c.abs() < 9.0e15 {
            // The set-point belongs to this machine cycle's slot on the ideal grid (the
            // thread's wake-up jitter is not part of the path).
            let t = Duration::from_nanos(self.cycle_ns.max(1));
            let k = (self.t0.elapsed().as_nanos() as f64 / t.as_nanos() as f64).round();
            let at = self.t0 + t.mul_f64(k);
            // Velocity of the set-point over the machine cycle (the planner's own step).
            a.cmd.velocity = (c as i64 - a.target) as f64 / (self.cycle_ns as f64 * 1e-9);
            a.cmd.at = Some(at);
            a.target = c as i64;
            // Wrap as the INTEGER32 object does.
            a.cmd.target = a.target as i32;
        }
    }

    fn target_counts(&self, axis: usize) -> i64 {
        self.axes[axis].target
    }

    fn transmit(&mut self, _now_ns: u64) -> Result<(), Alarm> {
        for a in &self.axes {
            if let Some(s) = &self.links[a.link].shared {
                if let Ok(mut g) = s.0.lock() {
                    g.slots[a.slot].command = a.cmd;
                }
            }
        }
        Ok(())
    }

    fn enable_step(&mut self) -> Result<bool, Alarm> {
        self.enable_cycles += 1;
        let mut all = true;
        for i in 0..self.axes.len() {
            let a = &mut self.axes[i];
            if !a.have_fb {
                all = false;
                continue;
            }
            if !a.enabled {
                // Hold the actual position while enabling so that nothing jumps: a CiA 402
                // drive gets it in its target register before the controlword that enables
                // it (as `drive enable` does), since many take 0x607A as it stands the moment
                // they enable, however old it is.
                a.target = a.unwrapped;
                a.cmd.target = a.raw;
                a.cmd.velocity = 0.0;
                a.cmd.at = None;
                a.cmd.stream = a.profile == Profile::Cia402;
            }
            match a.profile {
                Profile::Cia402 => {
                    // Step only on a reading taken after our last controlword was written,
                    // so that a fault reset edge is never lost between two link cycles.
                    // And only once the held target has been written (the reading's command
                    // streamed it), so that the enabling controlword never precedes it.
                    let fresh = self.links[a.link]
                        .shared
                        .as_ref()
                        .and_then(|s| {
                            s.0.lock().ok().map(|g| {
                                let c = g.slots[a.slot].reading.command;
                                c.controlword == a.enabler.controlword && c.stream
                            })
                        })
                        .unwrap_or(false);
                    if !fresh {
                        all &= a.enabled;
                        continue;
                    }
                    match a.enabler.step(a.statusword) {
                        EnableProgress::Enabled => {
                            a.enabled = true;
                            a.reported = false;
                            a.cmd.stream = true;
                        }
                        EnableProgress::Walking => {
                            all = false;
                            a.enabled = false;
                        }
                        EnableProgress::ResetFailed => {
                            let code = a.error_code;
                            return Err(self.axis_alarm(
                                i,
                                crate::alarm::FAULT_RESET,
                                format!(
                                    "fault reset did not clear the fault (error code 0x{code:04X} {}); fix the cause on the drive",
                                    error_text(code)
                                ),
                            ));
                        }
                    }
                    a.cmd.controlword = a.enabler.controlword;
                }
                Profile::Pr => {
                    let st = State::from_statusword(a.statusword);
                    match st {
                        State::OperationEnabled => {
                            a.enabled = true;
                            a.reported = false;
                            a.cmd.stream = true;
                        }
                        State::Fault => {
                            all = false;
                            let fresh = self.links[a.link]
                                .shared
                                .as_ref()
                                .and_then(|s| s.0.lock().ok().map(|g| g.slots[a.slot].reading.command.alarm_reset_seq == a.cmd.alarm_reset_seq))
                                .unwrap_or(false);
                            if fresh {
                                a.enabler.reset_attempts += 1;
                                if a.enabler.reset_attempts > Enabler::MAX_RESETS {
                                    let code = a.error_code;
                                    return Err(self.axis_alarm(
                                        i,
                                        crate::alarm::FAULT_RESET,
                                        format!("alarm reset did not clear alarm 0x{code:04X}; fix the cause on the drive"),
                                    ));
                                }
                                a.cmd.alarm_reset_seq = a.cmd.alarm_reset_seq.wrapping_add(1);
                            }
                        }
                        _ => {
                            all = false;
                            a.cmd.servo_on = true;
                        }
                    }
                }
            }
        }
        if all {
            self.running = true;
            self.stopping = false;
            self.faulted = None;
        } else if self.t0.elapsed() > Duration::from_secs(10) && self.enable_cycles > 10 {
            let i = self.axes.iter().position(|a| !a.enabled).unwrap_or(0);
            let st = State::from_statusword(self.axes[i].statusword);
            return Err(self.axis_alarm(
                i,
                crate::alarm::ENABLE_TIMEOUT,
                format!("did not reach Operation Enabled within 10 s (state {})", st.name()),
            ));
        }
        Ok(all)
    }

    fn quick_stop(&mut self) {
        self.stopping = true;
        for a in &mut self.axes {
            a.cmd.velocity = 0.0;
            match a.profile {
                Profile::Cia402 => a.cmd.controlword = cw::QUICK_STOP_CMD,
                // A PR drive has no quick stop: retarget it to where it is.
                Profile::Pr => a.cmd.target = a.raw,
            }
        }
        let _ = self.transmit(0);
    }

    fn shutdown(&mut self, _clock: &mut dyn Clock) {
        for a in &mut self.axes {
            a.cmd.stream = false;
            a.cmd.controlword = cw::SHUTDOWN;
            a.cmd.servo_on = false;
        }
        let _ = self.transmit(0);
        // Let every link write it at least twice.
        let longest = self.links.iter().map(|l| l.cycle).max().unwrap_or_default();
        std::thread::sleep((longest * 3).min(Duration::from_secs(2)));
        self.running = false;
        for st in self.link_stats() {
            tracing::info!(
                "Modbus link {}: {} transactions ({} failed) in {} link cycles of {:.0} ms, {} late; {} bytes of late answers dropped",
                st.name,
                st.transactions,
                st.failures,
                st.cycles,
                st.cycle.as_secs_f64() * 1e3,
                st.overruns,
                st.stale_bytes
            );
        }
        self.stop_links();
    }

    fn axis_count(&self) -> usize {
        self.axes.len()
    }

    fn axis_name(&self, axis: usize) -> &str {
        &self.axes[axis].name
    }

    fn counts_per_unit(&self, axis: usize) -> f64 {
        self.axes[axis].counts_per_unit
    }

    fn isolate_faults(&mut self, on: bool) -> bool {
        self.isolate = on;
        true
    }

    fn faulted(&self) -> Option<usize> {
        self.faulted
    }

    fn link_cycle(&self, axis: usize) -> Option<(String, String, f64)> {
        let l = &self.links[self.axes.get(axis)?.link];
        Some((l.name.clone(), l.what.clone(), l.cycle.as_secs_f64()))
    }

    /// Speed: mode 9 and the target velocity from the next link cycle on (a CiA 402 drive;
    /// a PR drive has no speed mode). Position: mode 8 and the window, in counts.
    fn set_spindle_control(&mut self, axis: usize, control: SpindleControl) -> bool {
        let Some(a) = self.axes.get_mut(axis) else { return false };
        let done = match control {
            SpindleControl::Speed if a.speed_capable => {
                a.cmd.speed_mode = true;
                true
            }
            SpindleControl::Speed => false,
            SpindleControl::Position { window } => {
                a.cmd.speed_mode = false;
                if a.profile == Profile::Cia402 {
                    a.cmd.ferr_window = (window * a.counts_per_unit).round().clamp(1.0, i32::MAX as f64) as u32;
                }
                a.profile == Profile::Cia402
            }
        };
        let _ = self.transmit(0);
        done
    }

    fn holds_position(&self, axis: usize) -> bool {
        self.axes.get(axis).is_none_or(|a| !a.cmd.speed_mode)
    }
}
