//! Drives: the `DriveBus` trait the cycle loop uses, and its CANopen (CiA 402)
//! implementation. Positions cross this boundary in machine units (mm, X as a radius;
//! degrees for a spindle); counts exist only below it.

pub mod access;
pub mod canopen;
pub mod friction;
pub mod modbus;
pub mod multi;
pub mod scale_watch;

use crate::Alarm;
use cncgw_bus::cia402::State;
use cncgw_bus::Clock;

/// What the drive of one axis reported in the last cycle.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AxisFeedback {
    /// Actual position in machine units, unwrapped (a spindle's angle keeps counting).
    pub pos: f64,
    /// Actual position in counts, unwrapped.
    pub counts: i64,
    pub statusword: u16,
    /// Cycles since the last feedback frame from this drive (0 = fresh this cycle).
    pub age_cycles: u32,
    /// The drive's position demand at the instant of `counts`, when the bus knows it (Modbus:
    /// the link's own cycle); `None`: the cycle loop pairs the feedback with the target it
    /// sent two cycles before (CANopen CSP timing).
    pub demand_counts: Option<i64>,
    /// When `counts` was read, ns on the bus's own monotonic clock, for a bus that reads at
    /// its own rate (Modbus: the link's cycle, with its jitter); `None`: at the cycle
    /// (`age_cycles` says how old). The spindle's speed is measured over it.
    pub sampled_ns: Option<u64>,
}

impl AxisFeedback {
    pub fn state(&self) -> State {
        State::from_statusword(self.statusword)
    }
}

/// A set of drives on one bus, driven cyclically. The cycle loop calls, every cycle:
/// `receive` → (compute) → `set_target` per axis → `transmit`.
pub trait DriveBus {
    /// Bring every drive up: boot, identity check, configuration, NMT start. Blocking; uses
    /// `clock` to wait, so it runs the same in simulated time.
    fn startup(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm>;
    /// Process everything received since the last cycle. Errors are drive alarms (EMCY,
    /// heartbeat loss, fault state).
    fn receive(&mut self, now_ns: u64) -> Result<(), Alarm>;
    fn feedback(&self, axis: usize) -> AxisFeedback;
    /// Target position for the next cycle, machine units.
    fn set_target(&mut self, axis: usize, pos: f64);
    /// Commanded position in counts (unwrapped) last sent to `axis`.
    fn target_counts(&self, axis: usize) -> i64;
    /// Send targets and SYNC (and the master heartbeat when due).
    fn transmit(&mut self, now_ns: u64) -> Result<(), Alarm>;
    /// One cycle of walking every drive towards Operation Enabled while holding position.
    /// Returns true once all are enabled.
    fn enable_step(&mut self) -> Result<bool, Alarm>;
    /// Quick stop on every drive (E-stop, fault reaction).
    fn quick_stop(&mut self);
    /// Orderly shutdown at exit: disable the drives, stop them expecting our heartbeat.
    fn shutdown(&mut self, clock: &mut dyn Clock);
    fn axis_count(&self) -> usize;
    fn axis_name(&self, axis: usize) -> &str;
    /// Counts per machine unit of `axis` (for reporting in counts).
    fn counts_per_unit(&self, axis: usize) -> f64;
    /// For an axis on a link with its own, slower cycle (Modbus): the link's name, what it
    /// is, and its cycle in seconds, once started. `None`: the axis gets its set-point every
    /// machine cycle at SYNC.
    fn link_cycle(&self, _axis: usize) -> Option<(String, String, f64)> {
        None
    }
    /// Ask the bus to isolate a drive fault: put only the faulted drive into its own fault
    /// reaction and keep the others following their targets, so that the layer above can stop
    /// them under control (a tap's spindle and feed axis together). Returns whether the bus
    /// does so; one that returns false quick-stops every drive on a fault (the default).
    fn isolate_faults(&mut self, _on: bool) -> bool {
        false
    }
    /// Under `isolate_faults`: the drive that faulted (EMCY, fault state, heartbeat lost, stale
    /// feedback, left NMT operational), from the `receive` that saw it on. `None` again when a
    /// second drive faulted too: the bus then quick-stopped every drive.
    fn faulted(&self) -> Option<usize> {
        None
    }
    /// Start-up (with the enabling that follows it) failed: leave the drives as `startup`
    /// found them, where the bus knows how (CANopen: objects written back, communication
    /// reset, NMT state restored). Default: nothing.
    fn abandon_startup(&mut self, _clock: &mut dyn Clock) {}
    /// The following-error window of `axis` (machine units) the drive enforces, when known:
    /// the bound on an honest drive's lag, used to tell a scaling error from lag.
    fn following_window(&self, _axis: usize) -> Option<f64> {
        None
    }
    /// Why `axis`'s position can no longer be trusted, if the bus saw it (CANopen: a boot-up
    /// message it did not cause, an encoder EMCY 0x73xx): its reference is lost.
    fn position_lost(&self, _axis: usize) -> Option<String> {
        None
    }
    /// A CiA 401 I/O module on this bus (`[io.devices.*] canopen_node`): its digital inputs
    /// (0x6000, bit 0 = input 1) as last received; `None` when the bus has no such module or
    /// has heard nothing from it yet.
    fn io_inputs(&self, _node: u8) -> Option<u32> {
        None
    }
    /// The module's digital outputs (0x6200), sent with every `transmit` from now on.
    fn set_io_outputs(&mut self, _node: u8, _bits: u32) {}
    /// How the spindle `axis` on a link with its own cycle (Modbus) is driven from now on,
    /// asked with the drives enabled and at rest, before a run's first motion. Returns whether
    /// the bus did it; one that returns false keeps position control and its window.
    fn set_spindle_control(&mut self, _axis: usize, _control: SpindleControl) -> bool {
        false
    }
    /// Whether `axis` follows its position set-point (false: a spindle the bus drives in
    /// speed, whose position target means nothing — the program's end does not wait for it
    /// to settle on one, and the stop counts it at rest when it stands still).
    fn holds_position(&self, _axis: usize) -> bool {
        true
    }

    /// The torque actual value 0x6077 (per mille of the rated torque) `axis` last reported,
    /// where the bus reads it (CANopen: a spindle's, by SDO while running); `None` otherwise.
    fn torque_permille(&self, _axis: usize) -> Option<i16> {
        None
    }

    /// The drive's torque limit, in the unit of `torque_permille` (CANopen: a spindle's max
    /// torque 0x6072, read at start-up); `None` where it is not known.
    fn max_torque_permille(&self, _axis: usize) -> Option<u16> {
        None
    }

    /// `torque_permille` as a share of the rated torque (1.0 = rated); NaN where not read.
    fn torque_rated(&self, axis: usize) -> f64 {
        self.torque_permille(axis).map_or(f64::NAN, |t| f64::from(t) / PER_MILLE)
    }

    /// `max_torque_permille` as a share of the rated torque; NaN where not known.
    fn max_torque_rated(&self, axis: usize) -> f64 {
        self.max_torque_permille(axis).map_or(f64::NAN, |t| f64::from(t) / PER_MILLE)
    }
}

/// Torque objects (0x6072, 0x6077) count in thousandths of the rated torque (CiA 402).
const PER_MILLE: f64 = 1000.0;

/// How a spindle on a slow link is driven (`DriveBus::set_spindle_control`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SpindleControl {
    /// In speed (CiA 402 cyclic synchronous velocity): the drive turns at the set-point's
    /// speed, written every link cycle, and watches no following error; feed per revolution
    /// follows its measured speed. Turning and threading.
    Speed,
    /// In position (cyclic synchronous position) with a following-error window of `window`
    /// machine units (degrees): Cs, rigid tapping, polar and polygon turning.
    Position { window: f64 },
}
