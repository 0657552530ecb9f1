//! The cycle loop: every bus cycle read the drives' feedback, advance the interpolator,
//! write the setpoints, send SYNC. Not async; it runs on its own thread with an injected
//! clock, so the same code runs against real drives in real time and against emulated drives
//! in simulated time.
//!
//! After start-up the loop allocates nothing: moves arrive over a bounded channel from the
//! interpreter thread, the look-ahead queue and the statistics are fixed-size.

use crate::canon::Move;
use crate::control::guard::Guard;
use crate::control::panel::{Panel, PanelReader};
use crate::control::snapshot::{MachineSnap, MachineState, Snapshot, SNAP_AXES};
use crate::control::tapstate::TapWatch;
use crate::control::trace::{Trace, TraceRow, MAX_TRACE_AXES};

use crate::drives::DriveBus;
use crate::motion::polygon::ToolSpindle;
use crate::motion::{Event, Feedback, Limits, Motion, AX_S, AX_X, AX_Y, AX_Z, N_AXES};
use crate::Alarm;
use cncgw_bus::Clock;
use std::sync::mpsc::Receiver;

mod program;
mod rest;
mod settle;
pub use rest::Rest;
pub use settle::{Hunt, SettleMiss};

/// Alarms of the controller itself (2400–2499).
pub mod alarms {
    /// E-stop pressed: every drive was sent quick stop.
    pub const ESTOP: u32 = crate::alarm::ESTOP;
    /// Reset by the operator: controlled stop, the program ended.
    pub const RESET: u32 = crate::alarm::RESET;
    /// Too many cycle overruns (watchdog).
    pub const WATCHDOG: u32 = crate::alarm::WATCHDOG;
    /// The controller stalled inside a thread or rigid tap longer than the drives bridge.
    pub const STALL_IN_SYNC: u32 = crate::alarm::STALL_IN_SYNC;
}

/// At most this many missed cycles are caught up after an overrun (100 ms at 2 ms).
const MAX_CATCH_UP: u64 = 50;

/// The cycle watchdog: when the loop cannot keep its period, stop the machine (alarm 2402).
///
/// Two limits, as a PLC task watchdog has them (CODESYS: watchdog time and "sensitivity",
/// the number of consecutive violations tolerated): `max_consecutive` cycles in a row that
/// woke a whole period late (`machine.watchdog_overruns`, 0 = off), or one wake-up
/// `max_missed` or more periods late (`machine.watchdog_missed_cycles`: the drives bridge a
/// late SYNC for about 10 periods and the loop catches up at most 50, beyond which the
/// trajectory would lose its time base). A single short overrun is only counted
/// (`RunSummary::overruns`): a desktop kernel is late now and then, and the drives ride
/// through it. The stop is a controlled one along the path (spindle and feed axes of a tap
/// or thread decelerate together); E-stop still overrides it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Watchdog {
    pub max_consecutive: u32,
    pub max_missed: u64,
    /// Cycles the drives bridge a late SYNC by extrapolating (`late_sync_extrapolation`): the
    /// most the loop catches the path up after a late wake-up; the rest of the delay shifts the
    /// path's time base. 0 (the default): the drives hold their target, nothing is caught up.
    pub catch_up: u64,
}

impl Default for Watchdog {
    fn default() -> Self {
        Watchdog { max_consecutive: 5, max_missed: 25, catch_up: 0 }
    }
}

impl Watchdog {
    pub fn from_config(cfg: &crate::config::MachineConfig) -> Watchdog {
        Watchdog {
            max_consecutive: cfg.machine.watchdog_overruns,
            max_missed: cfg.machine.watchdog_missed_cycles as u64,
            catch_up: cfg.late_sync_extrapolation() as u64,
        }
    }

    /// One cycle that woke `late` whole periods after its slot (0 = on time), with
    /// `consecutive` the overruns in a row before it (updated). `Some(alarm)`: stop.
    fn cycle(&self, late: u64, consecutive: &mut u32, line: u32, cycle_ns: u64) -> Option<Alarm> {
        if late == 0 {
            *consecutive = 0;
            return None;
        }
        *consecutive += 1;
        let too_many = self.max_consecutive > 0 && *consecutive >= self.max_consecutive;
        let too_late = self.max_missed > 0 && late >= self.max_missed;
        (too_many || too_late).then(|| {
            Alarm::new(
                alarms::WATCHDOG,
                format!(
                    "cycle watchdog at line {line}: {} (period {:.3} ms); the axes were stopped under control. The controller cannot keep its cycle: give the cycle thread real-time priority and a core (`--rt-priority`, `--cpu`), reduce the load, then restart",
                    if too_late {
                        format!("one cycle woke {late} periods late (limit {}, machine.watchdog_missed_cycles)", self.max_missed)
                    } else {
                        format!("{} cycles in a row woke late (limit {}, machine.watchdog_overruns)", *consecutive, self.max_consecutive)
                    },
                    cycle_ns as f64 * 1e-6
                ),
            )
        })
    }
}

/// Whole periods from the slot `*next` to `now`, `*next` moved on by them (onto the slot of
/// the period `now` is in). 0: `now` is still in the slot's period. Every loop that sends
/// cyclic set-points counts by it the SYNCs that passed: a wake-up that late, or SYNCs that
/// came after it (an external SYNC, `Clock::poll_sync`).
fn periods_passed(next: &mut u64, now: u64, cycle_ns: u64) -> u64 {
    let cycle_ns = cycle_ns.max(1);
    if now < *next + cycle_ns {
        return 0;
    }
    let n = (now - *next) / cycle_ns;
    *next += n * cycle_ns;
    n
}

/// Alarm 2403: the controller stalled inside a thread or rigid tap for longer than the
/// drives bridge (their time base cannot be shifted: the spindle turns on).
fn stall_in_sync(line: u32, missed: u64, bridged: u64, cycle_ns: u64) -> Alarm {
    Alarm::new(
        alarms::STALL_IN_SYNC,
        format!(
            "line {line}: the controller itself woke {missed} cycles ({:.1} ms) late inside a thread or rigid tap — a stall of this computer, not of a drive — and the drives bridge {bridged} (axes.*.late_sync_extrapolation); spindle and axes were stopped together. Give the cycle thread real-time priority and a core of its own (`--rt-priority`, `--cpu`), then restart",
            missed as f64 * cycle_ns as f64 * 1e-6
        ),
    )
}

/// Progress, reported to the caller every few cycles.
#[derive(Clone, Copy, Debug, Default)]
pub struct Progress {
    pub t_s: f64,
    pub line: u32,
    pub pos: [f64; N_AXES],
    pub feed: f64,
    pub spindle_rpm: f64,
    /// Measured spindle–axis sync error, µm (0 outside synchronised moves).
    pub sync_err_um: f64,
}

/// Per-axis result of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct AxisSummary {
    pub name: String,
    /// Largest |demand − actual| seen while running, machine units.
    pub max_following_error: f64,
    pub counts_per_unit: f64,
    /// The in-position width (`axes.NAME.in_position`) in counts, at least one: standing
    /// within it of the program's end point is having reached it.
    pub in_position_counts: i64,
    pub final_actual_counts: i64,
    pub final_target_counts: i64,
    /// The program's end point for this axis, in counts, where the program moved it.
    pub program_end_counts: Option<i64>,
    /// How it moved about its last set-point where it had not settled on it when the run
    /// stopped waiting at the program's end.
    pub settle_miss: Option<SettleMiss>,
    /// A hunt about a set-point that stood still mid-program (the largest, or the one still
    /// going on when an alarm stopped the run).
    pub hunt: Option<Hunt>,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunSummary {
    /// Blocks executed: that produced moves or codes and were reached (consecutive items of
    /// one block count once; blocks read ahead but dropped by a stop do not count).
    pub blocks: u64,
    /// Moves the interpreter handed to motion (read ahead of execution).
    pub moves: u64,
    /// Time from the first cycle of motion to the program's end or the stop, seconds
    /// (simulated time under the embedded emulated drives).
    pub machining_time_s: f64,
    /// M02/M30 was reached.
    pub ended: bool,
    /// Time from start to every drive in Operation Enabled, seconds of clock time.
    pub enable_time_s: f64,
    pub cycles: u64,
    /// Cycles in which the loop woke a whole period late (real time only).
    pub overruns: u64,
    pub axes: Vec<AxisSummary>,
    pub simulated: bool,
    /// How spindle and axes came to rest at the end (every cause).
    pub rest: Rest,
    /// The spindle could not give its configured acceleration: what it managed (rpm/s), which
    /// the run planned with 80 % of from then on (`Motion::spindle_accel_found`).
    pub spindle_accel_rpm_s: Option<f64>,
    /// That acceleration is what it gave at its drive's torque limit (`sync::torque_margin`),
    /// not short of the one asked.
    pub spindle_accel_at_torque_limit: bool,
    /// The spindle amplifier's overload load passed a quarter of its rating: the acceleration
    /// (rpm/s) the run planned with from then on (`Motion::spindle_overload_found`).
    pub spindle_overload_rpm_s: Option<f64>,
}

/// What to do about a drive that hunts on a set-point that stands still.
const HUNT_ADVICE: &str = "the drive's own loops do not settle (as a Fanuc's SV0410, excess error at stop): lower its velocity-loop gain, lengthen its integral time or speed filter, look for lost motion (belt, coupling), then run";

impl AxisSummary {
    /// Within its in-position width of the program's end point (true where the program did
    /// not move it).
    pub fn in_position(&self) -> bool {
        self.program_end_counts.is_none_or(|e| (self.final_actual_counts - e).abs() <= self.in_position_counts.max(1))
    }

    /// The operator's units: mm (X as a diameter, as the programs write it) or degrees for a
    /// spindle — (unit, diameter?, units per count).
    pub fn units(&self) -> (&'static str, bool, f64) {
        let spindle = self.name.starts_with('s');
        let diameter = self.name == "x";
        let cpu = if self.counts_per_unit.is_finite() && self.counts_per_unit != 0.0 { self.counts_per_unit } else { 1.0 };
        (if spindle { "deg" } else { "mm" }, diameter, if diameter { 2.0 } else { 1.0 } / cpu)
    }

    /// How it missed its last set-point at the program's end, in words, where it had not
    /// settled on it (`SettleMiss`).
    pub fn settle_text(&self) -> Option<String> {
        let m = self.settle_miss?;
        let (unit, diameter, k) = self.units();
        let on = if diameter { " on the diameter" } else { "" };
        let name = &self.name;
        let w = m.waited_s;
        Some(if m.hunts() {
            format!(
                "axis {name} hunted about its end point and had not settled after {w:.1} s: {} — {HUNT_ADVICE} `cncgw identify {name}`",
                self.swing_words(&m)
            )
        } else if m.step_counts != 0 {
            format!(
                "axis {name} was still moving onto its end point after {w:.1} s, {:.4} {unit}{on} ({} counts) from it",
                m.off_counts as f64 * k,
                m.off_counts
            )
        } else {
            format!(
                "axis {name} stood {:.4} {unit}{on} ({} counts) from its end point after {w:.1} s: the drive does not close its last counts (friction against its integral action, a dead band or a position window of its own)",
                m.off_counts as f64 * k, m.off_counts
            )
        })
    }

    /// How it swung about a set-point: "±… (… counts), through it n times (≈ f Hz)".
    fn swing_words(&self, m: &SettleMiss) -> String {
        let (unit, diameter, k) = self.units();
        let on = if diameter { " on the diameter" } else { "" };
        format!(
            "±{:.4} {unit}{on} ({} counts), through it {} times ({}) on a set-point that stood still",
            m.peak_counts as f64 * k,
            m.peak_counts,
            m.crossings,
            if m.resolved { format!("≈ {:.1} Hz", m.hunt_hz) } else { "faster than the bus cycle resolves: its velocity loop".to_string() }
        )
    }

    /// Its hunt mid-program, in words (`Hunt`).
    pub fn hunt_text(&self) -> Option<String> {
        let h = self.hunt?;
        let name = &self.name;
        let when = if h.at_alarm { "was hunting when the run stopped" } else { "hunted" };
        Some(format!(
            "axis {name} {when} at line {} ({:.2} s on its set-point): {} — {HUNT_ADVICE} `cncgw identify {name}`",
            h.line,
            h.miss.waited_s,
            self.swing_words(&h.miss)
        ))
    }
}

impl RunSummary {
    /// True if the program reached M02/M30 and every axis it moved ended within its
    /// in-position width of the program's end point.
    pub fn at_program_end(&self) -> bool {
        self.ended && self.axes.iter().all(AxisSummary::in_position)
    }
}

/// A run that stopped on an alarm, with what had happened until then.
#[derive(Debug)]
pub struct RunFailure {
    pub alarm: Alarm,
    pub summary: RunSummary,
}

/// The spindle speed from its position, as the cycle loop measures it.
struct SpindleMeter {
    prev: f64,
    rpm: f64,
    /// Time since the last fresh position, s (before this cycle).
    since: f64,
    /// The bus's instant of the last position taken (`AxisFeedback::sampled_ns`).
    sampled: Option<u64>,
}

impl SpindleMeter {
    fn new(pos: f64, rpm: f64) -> Self {
        SpindleMeter { prev: pos, rpm, since: 0.0, sampled: None }
    }

    /// rpm after this cycle (`dt` s) from the spindle drive's feedback `f`. A bus that says
    /// when it read the position (Modbus) gives the time between two readings: counted in
    /// machine cycles from when the cycle first saw each, a 45 ms link cycle came out
    /// 44–46 ms with a 2 ms machine cycle, ±4 % of speed (and of a feed per revolution) at
    /// every reading.
    fn update_fb(&mut self, f: &crate::drives::AxisFeedback, dt: f64) -> f64 {
        let Some(t) = f.sampled_ns else { return self.update(f.pos, f.age_cycles == 0, dt) };
        self.since += dt;
        if self.sampled == Some(t) {
            return self.rpm;
        }
        let elapsed = match self.sampled.replace(t) {
            Some(t0) if t > t0 => (t - t0) as f64 * 1e-9,
            // The first reading seen may be the one `new` started from: it only sets the
            // reference (the speed given to `new` holds until the next one).
            _ => {
                self.prev = f.pos;
                self.since = 0.0;
                return self.rpm;
            }
        };
        self.since = 0.0;
        self.take(f.pos, elapsed)
    }

    /// rpm after this cycle (`dt` s) with the spindle at `pos`, `fresh` if the drive reported
    /// it this cycle: the speed over the time since the last fresh position, through a
    /// 1st-order filter, τ = 8 ms (one cycle's difference is quantised to a count). A stale
    /// position (a Modbus link slower than the cycle, a lost TPDO) holds the speed: read as
    /// 0 rpm and then as a jump, it made a feed per revolution pulse at the link's rate.
    fn update(&mut self, pos: f64, fresh: bool, dt: f64) -> f64 {
        self.since += dt;
        if !fresh {
            return self.rpm;
        }
        let elapsed = self.since;
        self.since = 0.0;
        self.take(pos, elapsed)
    }

    /// The position `pos` read `elapsed` s after the last one taken.
    fn take(&mut self, pos: f64, elapsed: f64) -> f64 {
        if elapsed <= 0.0 {
            return self.rpm;
        }
        let inst = (pos - self.prev) / 360.0 / elapsed * 60.0;
        self.prev = pos;
        self.rpm += (elapsed / 0.008).min(1.0) * (inst - self.rpm);
        self.rpm
    }
}

/// The alarm a fault stop ends on: the drive's own (`first`), with `then` — what went wrong
/// while the others were stopping and made it a quick stop of every drive — named after it.
fn then(first: Option<Alarm>, then: Alarm) -> Alarm {
    match first {
        None => then,
        Some(mut a) => {
            a.message.push_str(&format!("; while the others stopped, alarm {}: {}, so every drive was sent quick stop", then.number, then.message));
            a
        }
    }
}

/// What drive `d` was sent this cycle, for the trace: its motion axis' set-point, the tool
/// spindle's (`tool_drive`), or its actual position (a drive the program does not move).
fn traced_cmd(d: usize, axis: Option<usize>, tool_drive: Option<usize>, sp: &crate::motion::Setpoint, act: f64) -> f64 {
    match axis {
        Some(a) => sp.pos[a],
        None if tool_drive == Some(d) => sp.tool_spindle,
        None => act,
    }
}

/// Which motion axis each drive follows (by the config's axis names: x, y, z; the spindle).
fn motion_axis(name: &str, spindle: bool) -> Option<usize> {
    if spindle {
        return Some(AX_S);
    }
    match name {
        "x" => Some(AX_X),
        "y" => Some(AX_Y),
        "z" => Some(AX_Z),
        _ => None,
    }
}

pub struct CycleLoop<'a> {
    pub drives: &'a mut dyn DriveBus,
    pub clock: &'a mut dyn Clock,
    pub limits: Limits,
    /// Drive index → motion axis.
    pub spindle_drive: Option<usize>,
    pub cycle_ns: u64,
    /// Per-cycle trace (`--trace`), recorded without allocating.
    trace: Option<Trace>,
    /// Clock time of the program's start: the trace's time origin.
    trace_t0: u64,
    /// The operator panel; without one (a batch run) M00/M01 go on as if cycle start had
    /// been pressed.
    panel: Option<PanelReader>,
    /// The tool spindle of polygon turning (G51.2), driven from `Setpoint::tool_spindle`.
    tool: Option<ToolSpindle>,
    /// Rigid-tap state publisher (`control::tapstate`), fed every push and every cycle.
    tap: Option<TapWatch>,
    /// Overrun limits (default: `Watchdog::default()`).
    watchdog: Watchdog,
    /// The per-set-point limit check; `None`: from `limits` at `run`.
    guard: Option<Guard>,
    /// The guard of the run in progress, for the stop at its end.
    active_guard: Option<Guard>,
    /// Every drive was sent quick stop (E-stop, a bus error, a second fault, a limit).
    quick: bool,
    /// Clock time the run's stop began (a controlled stop on an alarm or reset, a drive
    /// fault's stop), if one did: `to_rest` counts the time to standstill from there.
    stop_t0: Option<u64>,
    /// A drive ran its own fault reaction in the stop (`fault_stop`).
    fault_reaction: bool,
    /// The spindle speed measured last, rpm.
    rpm: f64,
    /// Set (to the signal's number) by SIGTERM/SIGINT/SIGHUP: stop as on reset. With the
    /// signal's name for the message.
    signal: Option<SignalSource>,
    /// The machine's I/O (`[io]`): M/T codes, safety inputs (`control::io`); an Err is
    /// raised by `start`.
    pub io: Result<Option<super::io::IoRun>, Alarm>,
    /// The lock-free state record observers read (`control::snapshot`, the OPC UA server),
    /// published every cycle of `run`, and the record as this loop last filled it.
    snapshot: Option<std::sync::Arc<Snapshot>>,
    snap: MachineSnap,
}

/// The flag a signal handler sets (to the signal's number) and the signal's name.
pub type SignalSource = (&'static std::sync::atomic::AtomicI32, fn(i32) -> &'static str);

impl<'a> CycleLoop<'a> {
    pub fn new(drives: &'a mut dyn DriveBus, clock: &'a mut dyn Clock, limits: Limits, spindle_drive: Option<usize>, cycle_ns: u64) -> Self {
        CycleLoop {
            drives,
            clock,
            limits,
            spindle_drive,
            cycle_ns,
            trace: None,
            trace_t0: 0,
            panel: None,
            tool: None,
            tap: None,
            watchdog: Watchdog::default(),
            guard: None,
            active_guard: None,
            quick: false,
            stop_t0: None,
            fault_reaction: false,
            rpm: 0.0,
            signal: None,
            io: Ok(None),
            snapshot: None,
            snap: MachineSnap::default(),
        }
    }

    /// Publish the machine's state into `s` every cycle of `run` (`control::snapshot`).
    pub fn set_snapshot(&mut self, s: std::sync::Arc<Snapshot>) {
        self.snap = s.read();
        self.snapshot = Some(s);
    }

    /// Publish this loop's record, if it has a snapshot: a few dozen atomic stores.
    fn publish(&self) {
        if let Some(s) = &self.snapshot {
            s.publish(&self.snap);
        }
    }

    /// Stop the machine past these overrun limits (`Watchdog::from_config`).
    pub fn set_watchdog(&mut self, w: Watchdog) {
        self.watchdog = w;
    }

    /// Check set-points with this guard instead of one made from `limits`.
    pub fn set_guard(&mut self, g: Guard) {
        self.guard = Some(g);
    }

    /// Drive the tool spindle of polygon turning (`ToolSpindle::from_config`): its drive
    /// follows `Setpoint::tool_spindle`, and its actual angle goes back to motion every cycle.
    /// Without it G51.2 is refused.
    pub fn set_tool_spindle(&mut self, tool: ToolSpindle) {
        self.tool = Some(tool).filter(|t| t.drive < self.drives.axis_count() && Some(t.drive) != self.spindle_drive);
    }

    /// Take feed hold, cycle start, single block, reset, E-stop and the overrides from `panel`
    /// every cycle of `run`.
    pub fn set_panel(&mut self, panel: &Panel) {
        self.panel = Some(panel.reader());
    }

    /// Stop the run as on reset when `flag` becomes non-zero (a termination signal's number,
    /// named by `name` in the alarm).
    pub fn set_signal(&mut self, flag: &'static std::sync::atomic::AtomicI32, name: fn(i32) -> &'static str) {
        self.signal = Some((flag, name));
    }

    /// Record every cycle of `run` into `trace` (its drives in this loop's drive order).
    pub fn set_trace(&mut self, trace: Trace) {
        self.trace = Some(trace);
    }

    /// Publish the rigid-tap state every cycle of `run` (see `control::tapstate`).
    pub fn set_tap_watch(&mut self, w: TapWatch) {
        self.tap = Some(w);
    }

    /// The trace, after `run`, to `finish` it.
    pub fn take_trace(&mut self) -> Option<Trace> {
        self.trace.take()
    }

    /// Drive names in drive order (for a trace header).
    pub fn drive_names(&self) -> Vec<String> {
        (0..self.drives.axis_count()).map(|d| self.drives.axis_name(d).to_string()).collect()
    }

    fn map(&self) -> Vec<Option<usize>> {
        (0..self.drives.axis_count()).map(|d| motion_axis(self.drives.axis_name(d), Some(d) == self.spindle_drive)).collect()
    }

    /// Start the drives and enable them, holding position. Returns the machine position
    /// (motion axes) the program starts from.
    pub fn start(&mut self, summary: &mut RunSummary) -> Result<[f64; N_AXES], Alarm> {
        let t0 = self.clock.now_ns();
        summary.simulated = self.clock.is_simulated();
        if let Err(a) = &self.io {
            return Err(a.clone());
        }
        self.drives.startup(self.clock)?;
        let mut next = self.clock.now_ns();
        loop {
            next += self.cycle_ns;
            self.clock.wait_until(next);
            let now = self.clock.now_ns();
            if now >= next + self.cycle_ns {
                next = now - (now - next) % self.cycle_ns;
            }
            let step = self.drives.receive(now).and_then(|_| self.drives.enable_step()).and_then(|done| self.drives.transmit(now).map(|_| done));
            match step {
                Ok(true) => break,
                Ok(false) => {}
                Err(a) => {
                    // Enabling failed: the drives are left as start-up found them.
                    self.drives.abandon_startup(self.clock);
                    return Err(a);
                }
            }
        }
        summary.enable_time_s = (self.clock.now_ns() - t0) as f64 * 1e-9;
        self.io_start()?;
        let mut start = [0.0; N_AXES];
        for (d, ax) in self.map().iter().enumerate() {
            if let Some(a) = ax {
                start[*a] = self.drives.feedback(d).pos;
            }
        }
        Ok(start)
    }

    /// Run moves from `rx` to the end of the program, then bring every drive to rest
    /// (`to_rest`: whatever ended the run — the program's end, an alarm, reset, E-stop, a
    /// signal, a drive fault — spindle and axes stand still before `finish` removes torque;
    /// `RunSummary::rest` says how). `progress` is called about every 50 ms of clock time.
    pub fn run(
        &mut self,
        start: [f64; N_AXES],
        rx: Receiver<Result<Move, Alarm>>,
        summary: &mut RunSummary,
        progress: &mut dyn FnMut(&Progress),
    ) -> Result<(), Alarm> {
        let mut limits = self.limits.clone();
        // The sync correction pairs feedback with setpoints over the CANopen delay; an axis on
        // a link with its own cycle (Modbus) does not answer that way.
        limits.sync_correction &= (0..self.drives.axis_count()).all(|d| self.drives.link_cycle(d).is_none());
        let mut motion = Motion::new(limits, start);
        self.quick = false;
        self.stop_t0 = None;
        self.fault_reaction = false;
        self.rpm = 0.0;
        // Each drive's feedback period in cycles (a Modbus link's cycle; 1 at SYNC), for the
        // stop's silence test. Allocated here, before the first cycle.
        let cycle_s = self.cycle_ns as f64 * 1e-9;
        let periods: Vec<u32> =
            (0..self.drives.axis_count()).map(|d| self.drives.link_cycle(d).map_or(1, |(_, _, s)| (s / cycle_s).ceil().max(1.0) as u32)).collect();
        let mut still = rest::Still::new(&periods);
        let t0 = self.clock.now_ns();
        let r = self.run_program(&mut motion, start, rx, summary, progress);
        if summary.machining_time_s == 0.0 {
            // Stopped before the end: the time until the stop.
            summary.machining_time_s = self.clock.now_ns().saturating_sub(t0) as f64 * 1e-9;
        }
        let (rest, raised) = self.to_rest(&mut motion, &mut still);
        summary.rest = rest;
        let r = match (r, raised) {
            // The program ended, then a drive faulted while coming to rest: that is the run's end.
            (Ok(()), Some(a)) => {
                // What the axes did while the run waited for them to settle: a drive that hunts
                // on its own trips coming to rest, and the hunt is the cause.
                let mut message = format!("after the program's end, while the drives came to rest: {}", a.message);
                for t in summary.axes.iter().filter_map(AxisSummary::settle_text) {
                    message.push_str("; before that, ");
                    message.push_str(&t);
                }
                Err(Alarm { message, ..a })
            }
            // Stopped mid-program: a drive that was hunting on a set-point that stood is named
            // (a 0x8611 that a hunt tripped reads as lag otherwise).
            (Err(mut a), _) => {
                for h in summary.axes.iter().filter(|x| x.hunt.is_some_and(|h| h.at_alarm)).filter_map(AxisSummary::hunt_text) {
                    a.message.push_str("; ");
                    a.message.push_str(&h);
                }
                Err(a)
            }
            (r, _) => r,
        };
        summary.spindle_accel_rpm_s = motion.spindle_accel_found();
        summary.spindle_accel_at_torque_limit = motion.spindle_accel_at_torque_limit();
        summary.spindle_overload_rpm_s = motion.spindle_overload_found();
        // Where every drive stands once at rest (after an alarm too, not zeros).
        for (d, a) in summary.axes.iter_mut().enumerate() {
            a.final_actual_counts = self.drives.feedback(d).counts;
            a.final_target_counts = self.drives.target_counts(d);
        }
        self.publish_end(&r);
        r
    }

    /// The record once at rest: where the drives stand, and idle or the alarm that ended it.
    fn publish_end(&mut self, r: &Result<(), Alarm>) {
        for d in 0..self.drives.axis_count().min(SNAP_AXES) {
            let f = self.drives.feedback(d);
            self.snap.axes[d].act = f.pos;
            self.snap.axes[d].statusword = f.statusword;
        }
        self.snap.spindle_act_rpm = 0.0;
        self.snap.spindle_cmd_rpm = 0.0;
        self.snap.feed = 0.0;
        (self.snap.state, self.snap.alarm) = match r {
            Ok(()) => (MachineState::Idle, 0),
            Err(a) if a.number == alarms::ESTOP => (MachineState::EStop, a.number),
            Err(a) => (MachineState::Alarm, a.number),
        };
        self.snap.cycle += 1;
        self.publish();
    }

    /// Act on the event of a set-point; true at the program end. Err: an I/O code refused
    /// (the caller stops).
    fn on_event(&mut self, motion: &mut Motion, sp: &crate::motion::Setpoint) -> Result<bool, Alarm> {
        match sp.event {
            Event::End => {
                // Coolant off with the spindle stop (motion), as a 0i-TF at M02/M30.
                if let Ok(Some(io)) = self.io.as_mut() {
                    io.on_end();
                }
                Ok(true)
            }
            Event::Stop { optional } => {
                if self.panel.is_some() {
                    // The motion layer waits for the panel's cycle start.
                    tracing::info!(line = sp.line, "M0{} program stop: press cycle start", optional as u8);
                } else {
                    // No operator panel in a batch run: M00 is logged and the program goes on
                    // as if cycle start had been pressed.
                    tracing::info!(line = sp.line, "M0{} program stop (batch run: cycle start)", optional as u8);
                    motion.cycle_start();
                }
                Ok(false)
            }
            Event::Aux { letter, value } => {
                // An I/O code: its outputs now, the next item after its completion (FIN).
                if let Ok(Some(io)) = self.io.as_mut() {
                    if io.on_aux(letter, value, sp.line, motion.spindle_commanded(), self.rpm)? {
                        motion.wait_fin(true);
                    }
                }
                Ok(false)
            }
            Event::Stroke2(_) | Event::None => Ok(false),
        }
    }

    /// E-stop: quick stop on every drive at once (each on its own quick-stop ramp).
    fn estop(&mut self, line: u32) -> Alarm {
        self.quick_stop_all();
        let _ = self.drives.transmit(self.clock.now_ns());
        Alarm::new(
            alarms::ESTOP,
            format!("emergency stop at line {line}: every drive was sent quick stop; release the E-stop, find the cause, reset the drives (`cncgw drive fault-reset`) and restart the program"),
        )
    }

    /// The hardware E-stop input opened: the panel's E-stop path, naming the input.
    fn estop_input(&mut self, line: u32, input: &str) -> Alarm {
        let mut a = self.estop(line);
        a.message = format!(
            "emergency stop at line {line}: the E-stop input {input} opened and every drive was sent quick stop; find why the E-stop chain opened, close it, reset the drives (`cncgw drive fault-reset`) and restart the program"
        );
        a
    }

    /// The panel's E-stop or the E-stop input (read fresh: the stop loops call it after the
    /// bus's `receive`).
    fn estop_now(&mut self) -> bool {
        let panel = self.panel.as_mut().is_some_and(|r| r.poll().estop);
        let input = match self.io.as_mut() {
            Ok(Some(io)) => io.read(&*self.drives).is_err() || io.estop_open(),
            _ => false,
        };
        panel || input
    }

    /// Start the I/O: wait for every device's first inputs (at most 1 s of clock time), then
    /// the safety inputs must be closed before anything moves.
    fn io_start(&mut self) -> Result<(), Alarm> {
        let Ok(Some(io)) = self.io.as_mut() else { return Ok(()) };
        io.wait_modbus(1000)?;
        let mut next = self.clock.now_ns();
        for _ in 0..(1_000_000_000 / self.cycle_ns.max(1)) {
            if io.all_seen() {
                break;
            }
            next += self.cycle_ns;
            self.clock.wait_until(next);
            let now = self.clock.now_ns();
            let r = self.drives.receive(now).and_then(|_| io.read(&*self.drives)).and_then(|_| {
                io.write(&mut *self.drives);
                self.drives.transmit(now)
            });
            if let Err(a) = r {
                self.quick_stop_all();
                return Err(a);
            }
        }
        if let Some(r) = self.panel.as_ref() {
            r.report_safety(io.safety_inputs());
        }
        match io.check_safety(false, 0) {
            None => Ok(()),
            Some(stop) => {
                self.quick_stop_all();
                let _ = self.drives.transmit(self.clock.now_ns());
                Err(super::io::IoStop::refused(stop))
            }
        }
    }

    /// Quick stop on every drive at once, then `a`.
    fn quick_stop_with(&mut self, a: Alarm) -> Alarm {
        self.quick_stop_all();
        let _ = self.drives.transmit(self.clock.now_ns());
        a
    }

    /// The feedback of every drive motion commands, with the spindle speed measured as in
    /// `run` (a thread's lock predicts the spindle angle with it, also while stopping).
    fn read_feedback(&self, meter: &mut SpindleMeter) -> Feedback {
        let mut fb = Feedback::default();
        for d in 0..self.drives.axis_count() {
            if let Some(a) = motion_axis(self.drives.axis_name(d), Some(d) == self.spindle_drive) {
                let f = self.drives.feedback(d);
                fb.pos[a] = f.pos;
                fb.age[a] = f.age_cycles;
            }
        }
        if let Some(sd) = self.spindle_drive {
            let f = self.drives.feedback(sd);
            fb.spindle_rpm = meter.update_fb(&f, self.cycle_ns as f64 * 1e-9);
        }
        fb
    }

    /// A drive faulted and the bus isolated it (`DriveBus::faulted`): it runs its own fault
    /// reaction while the others stop under control — in a thread or tap the survivor of the
    /// pair follows the faulted drive's actual position (`Motion::fault_stop`). Returns the
    /// drive's alarm (2010 once its 0x603F is read; 2011, 2014, 2015 at once) with the line
    /// the program stopped at (`ended`: it had reached its end there, the drives settling).
    /// Anything else going wrong meanwhile (a second drive, the bus, E-stop) quick-stops
    /// every drive.
    fn fault_stop(&mut self, motion: &mut Motion, d: usize, first: Option<Alarm>, rpm: f64, line: u32, ended: bool) -> Alarm {
        self.stop_t0.get_or_insert(self.clock.now_ns());
        self.fault_reaction = true;
        motion.fault_stop(motion_axis(self.drives.axis_name(d), Some(d) == self.spindle_drive));
        tracing::warn!(axis = self.drives.axis_name(d), line, "drive fault: controlled stop of the other drives");
        // `quick`: every drive was sent quick stop after all (the others are not under control).
        let at_line = |mut a: Alarm, quick: bool| {
            let when = if ended { "had reached its end" } else { "stopped" };
            let others = if quick { "" } else { ", the other axes under control" };
            a.message.push_str(&format!("; the program {when} at line {line}{others}"));
            a
        };
        let mut alarm = first;
        let mut meter = SpindleMeter::new(self.spindle_drive.map(|s| self.drives.feedback(s).pos).unwrap_or(0.0), rpm);
        let dt_ns = self.cycle_ns.max(1);
        let mut next = self.clock.now_ns();
        let mut now = next;
        let mut idle = 0u32;
        for k in 0..(10_000_000_000 / dt_ns) {
            if k > 0 {
                next += dt_ns;
                self.clock.wait_until(next);
                now = self.clock.now_ns();
                if let Err(a) = self.drives.receive(now) {
                    if self.drives.faulted() != Some(d) {
                        // Not about the isolated drive: stop everything now, and say why
                        // the others were not stopped under control after all.
                        self.quick_stop_all();
                        let _ = self.drives.transmit(now);
                        return at_line(then(alarm, a), true);
                    }
                    if alarm.is_none() {
                        alarm = Some(a);
                    }
                }
            }
            if self.estop_now() {
                self.quick_stop_all();
                let _ = self.drives.transmit(now);
                return at_line(then(alarm, Alarm::new(alarms::ESTOP, "emergency stop during a drive fault stop")), true);
            }
            let fb = self.read_feedback(&mut meter);
            let sp = self.stop_step(motion, &fb, &mut next, now);
            self.send(&sp);
            // The faulted drive ignores it in its fault reaction; after a fault reset it holds.
            let p = self.drives.feedback(d).pos;
            self.drives.set_target(d, p);
            if let Err(a) = self.drives.transmit(now) {
                self.quick_stop_all();
                return at_line(then(alarm, a), true);
            }
            if motion.is_idle() {
                if let Some(a) = alarm.take() {
                    return at_line(a, false);
                }
                // Wait a little for the faulted drive's diagnosis (0x603F over SDO).
                idle += 1;
                if idle > 250 {
                    break;
                }
            }
        }
        self.quick_stop_all();
        let _ = self.drives.transmit(now);
        let name = self.drives.axis_name(d).to_string();
        at_line(
            alarm.unwrap_or_else(|| {
                Alarm::new(crate::alarm::DRIVE_FAULT, format!("axis {name}: drive fault, not diagnosed; clear the cause, then reset"))
            }),
            false,
        )
    }

    /// Controlled stop on a program alarm: decelerate along the path (a thread or tap's pair
    /// together), then hold. Called between cycles (this cycle's set-points were sent).
    /// `rpm`: the spindle speed measured last.
    fn halt(&mut self, motion: &mut Motion, rpm: f64) {
        self.halt_from(motion, rpm, false)
    }

    /// `halt` from within a cycle whose feedback was received but whose set-points are not
    /// sent yet (reset): the stop's first set-points go out in this cycle. (Skipping it would
    /// leave the drives one SYNC without a set-point, a glitch in a tap.)
    fn halt_now(&mut self, motion: &mut Motion, rpm: f64) {
        self.halt_from(motion, rpm, true)
    }

    fn halt_from(&mut self, motion: &mut Motion, rpm: f64, this_cycle: bool) {
        self.stop_t0.get_or_insert(self.clock.now_ns());
        motion.stop_following();
        let mut meter = SpindleMeter::new(self.spindle_drive.map(|s| self.drives.feedback(s).pos).unwrap_or(0.0), rpm);
        let dt_ns = self.cycle_ns;
        let mut next = self.clock.now_ns();
        for k in 0..(5_000_000_000 / dt_ns.max(1)) {
            let now = if k == 0 && this_cycle {
                next
            } else {
                next += dt_ns;
                self.clock.wait_until(next);
                self.clock.now_ns()
            };
            if !(k == 0 && this_cycle) && self.drives.receive(now).is_err() {
                self.quick_stop_all();
                let _ = self.drives.transmit(now);
                return;
            }
            let fb = self.read_feedback(&mut meter);
            // E-stop overrides a controlled stop in progress.
            if self.estop_now() {
                self.quick_stop_all();
                let _ = self.drives.transmit(now);
                return;
            }
            let sp = self.stop_step(motion, &fb, &mut next, now);
            self.send(&sp);
            let _ = self.drives.transmit(now);
            if motion.is_idle() {
                return;
            }
        }
    }

    /// The set-point of a stop's cycle woken at `now` for the slot `*next`: one interpolation
    /// step for every SYNC since the last set-point went out, as the program's cycle takes
    /// them (`keep_time`, `syncs_passed`) — the whole periods the wake-up was late, and on an
    /// external SYNC those that came after it, before the send — at most as many more as the
    /// drives bridge (`Watchdog::catch_up`). The drives, having extrapolated over those SYNCs,
    /// get the stop's next step, not one they have passed (a step back, and the next one
    /// double); `*next` moves onto the period `now` is in, so no cycles are run back to back.
    /// The events of the steps skipped are not acted on: a stop runs no program.
    fn stop_step(&mut self, motion: &mut Motion, fb: &Feedback, next: &mut u64, now: u64) -> crate::motion::Setpoint {
        let late = periods_passed(next, now, self.cycle_ns);
        let passed = self.clock.poll_sync().map_or(0, |t| periods_passed(next, t, self.cycle_ns));
        let mut sp = motion.step(fb);
        for _ in 0..(late + passed).min(self.watchdog.catch_up) {
            sp = motion.step(fb);
        }
        // The speed the next stop loop's meter starts from (`to_rest` after a fault stop).
        self.rpm = fb.spindle_rpm;
        self.trace_stop(motion, &sp, fb, now);
        sp
    }

    /// A stop loop's cycle into the trace, once a stop began (an alarm, reset, a drive
    /// fault): how the drives came to rest after it is what its diagnosis needs — a faulted
    /// spindle braking on its own, the feed axis following it. (The settling after a program's
    /// end is not traced: the program's cycles are the record.) The following error is not
    /// paired here (0).
    fn trace_stop(&mut self, motion: &Motion, sp: &crate::motion::Setpoint, fb: &Feedback, now: u64) {
        if self.trace.is_none() || self.stop_t0.is_none() {
            return;
        }
        let t_s = now.saturating_sub(self.trace_t0) as f64 * 1e-9;
        let mut row = TraceRow { t_s, line: sp.line, spindle_rpm: fb.spindle_rpm, sync_err_um: motion.sync_error(), ..TraceRow::default() };
        for d in 0..self.drives.axis_count().min(MAX_TRACE_AXES) {
            let f = self.drives.feedback(d);
            row.act[d] = f.pos;
            row.age[d] = f.age_cycles;
            let axis = motion_axis(self.drives.axis_name(d), Some(d) == self.spindle_drive);
            row.cmd[d] = traced_cmd(d, axis, self.tool.map(|t| t.drive), sp, f.pos);
        }
        if let Some(t) = self.trace.as_mut() {
            t.record(&row);
        }
    }

    /// Orderly end: disable drives.
    pub fn finish(&mut self) {
        self.drives.shutdown(self.clock);
    }
}

#[cfg(test)]
mod tests {
    use super::{AxisSummary, RunSummary, SpindleMeter};

    /// The program's end is reached within each axis' in-position width, at least a count;
    /// an axis the program did not move is not judged.
    #[test]
    fn the_program_end_is_reached_within_the_in_position_width() {
        let axis = |name: &str, off: i64, width: i64, end: Option<i64>| AxisSummary {
            name: name.into(),
            max_following_error: 0.0,
            counts_per_unit: 10_000.0,
            in_position_counts: width,
            final_actual_counts: 5000 + off,
            final_target_counts: 5000,
            program_end_counts: end,
            settle_miss: None,
            hunt: None,
        };
        let run = |axes| RunSummary { ended: true, axes, ..Default::default() };
        assert!(run(vec![axis("x", 2, 100, Some(5000)), axis("z", -100, 100, Some(5000))]).at_program_end());
        assert!(!run(vec![axis("z", 101, 100, Some(5000))]).at_program_end());
        assert!(run(vec![axis("z", 1, 0, Some(5000))]).at_program_end(), "at least one count");
        assert!(!run(vec![axis("z", 2, 0, Some(5000))]).at_program_end());
        assert!(run(vec![axis("y", 9999, 1, None)]).at_program_end(), "not moved by the program");
        assert!(!RunSummary { ended: false, ..run(vec![]) }.at_program_end(), "M30 not reached");
    }

    /// A spindle at 600 rpm read every 5th cycle (a Modbus link slower than the machine
    /// cycle): the speed holds at 600 rpm between readings instead of pulsing 0 / 3000 rpm,
    /// so a feed per revolution does not pulse at the link's rate (issue 22.9).
    #[test]
    fn a_spindle_read_every_few_cycles_measures_its_speed_without_pulsing() {
        let dt = 0.002;
        let deg_per_cycle = 600.0 * 360.0 / 60.0 * dt;
        let mut m = SpindleMeter::new(0.0, 600.0);
        let mut seen = (f64::INFINITY, 0.0f64);
        for k in 1..=500u32 {
            let fresh = k % 5 == 0;
            let pos = if fresh { deg_per_cycle * k as f64 } else { deg_per_cycle * (k - k % 5) as f64 };
            let rpm = m.update(pos, fresh, dt);
            if k > 50 {
                seen = (seen.0.min(rpm), seen.1.max(rpm));
            }
        }
        assert!((seen.0 - 600.0).abs() < 1e-6 && (seen.1 - 600.0).abs() < 1e-6, "speed between {} and {} rpm", seen.0, seen.1);
        // Fresh every cycle (CANopen): as before, the filtered speed of each cycle's step.
        let mut m = SpindleMeter::new(0.0, 0.0);
        let mut rpm = 0.0;
        for k in 1..=200u32 {
            rpm = m.update(deg_per_cycle * k as f64, true, dt);
        }
        assert!((rpm - 600.0).abs() < 1e-6, "{rpm}");
    }

    /// A Modbus spindle at 1500 rpm read every 45 ms ± 1.5 ms (the link's jitter) while the
    /// machine cycle is 2 ms: measured over the readings' own instants the speed is exact at
    /// every reading; counted in machine cycles it was off by up to ±4 %.
    #[test]
    fn a_spindle_on_a_slow_link_is_measured_over_its_readings_instants() {
        let dt = 0.002;
        let mut m = SpindleMeter::new(0.0, 0.0);
        let mut t_read = 0.0f64;
        let mut next_read = 0.045;
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for k in 1..=3000u32 {
            let now = k as f64 * dt;
            if now >= next_read {
                t_read = next_read;
                next_read += 0.045 + if k % 2 == 0 { 0.0015 } else { -0.0015 };
            }
            let f = crate::drives::AxisFeedback { pos: 9000.0 * t_read, sampled_ns: Some((t_read * 1e9).round() as u64), ..Default::default() };
            let rpm = m.update_fb(&f, dt);
            if now > 0.2 {
                (lo, hi) = (lo.min(rpm), hi.max(rpm));
            }
        }
        assert!((lo - 1500.0).abs() < 1e-6 && (hi - 1500.0).abs() < 1e-6, "speed between {lo} and {hi} rpm");
    }
}
