//! One run of the program through the cycle loop, one function per phase of a cycle:
//!
//! 1. [`CycleLoop::feed`] — fill the look-ahead queue from the interpreter;
//! 2. [`CycleLoop::keep_time`] — wait for the cycle, count overruns, watchdog;
//! 3. [`CycleLoop::read_feedback`] — receive, drive faults, actual positions, following error,
//!    feedback scaling, spindle speed;
//! 4. [`CycleLoop::operator`] — signals and the panel;
//! 5. [`CycleLoop::command`] — interpolate, G22 switch, limits, send the set-points;
//! 6. [`CycleLoop::after_send`] — rigid-tap gate, trace, motion alarms, events, progress, the
//!    end of the program (settling).
//!
//! Every allocation is made in [`Run::new`], before the first cycle. A phase that ends the
//! run returns the alarm, with the controlled stop it needs already started.

use super::settle::{EndSettle, HuntWatch};
use super::{alarms, periods_passed, stall_in_sync, traced_cmd, AxisSummary, CycleLoop, Progress, RunSummary, SpindleMeter, MAX_CATCH_UP};
use crate::canon::{Move, Pos};
use crate::control::guard::Guard;
use crate::control::io::IoStop;
use crate::control::snapshot::{MachineState, SNAP_AXES};
use crate::control::trace::{TraceRow, MAX_TRACE_AXES};
use crate::drives::scale_watch::{self, ScaleWatch};
use crate::motion::{Event, Feedback, Limits, Motion, Setpoint, AX_X, AX_Y, AX_Z, N_AXES};
use crate::sync::sample_time::SampleTiming;
use crate::Alarm;
use std::sync::mpsc::{Receiver, TryRecvError};

/// The state of one run that lives from cycle to cycle.
pub(super) struct Run {
    /// Drive index → motion axis.
    map: Vec<Option<usize>>,
    simulated: bool,
    dt: f64,
    guard: Guard,
    overruns_in_a_row: u32,
    /// The program's last end point (for "ended within one count").
    end_pos: Option<Pos>,
    /// Demand history: the drive's demand at SYNC k is the target sent at k−1, and its
    /// actual at SYNC k reaches us at k+1, so compare with the target of two cycles ago.
    hist: Vec<[i64; 2]>,
    /// The line of each of those two set-points.
    line_hist: [u32; 2],
    /// The last line of defence against a feedback scaled differently from the set-points.
    scale: Vec<ScaleWatch>,
    /// The line of the block in execution (the last set-point's).
    cur_line: u32,
    input_open: bool,
    ended: bool,
    max_settle: u32,
    /// Each drive settling onto its last set-point at the program's end.
    settle: EndSettle,
    /// Each feed axis on a set-point that stands still mid-program, watched for a hunt.
    hunt: HuntWatch,
    late_prev: bool,
    spindle_rpm: f64,
    meter: SpindleMeter,
    progress_every: u64,
    t_start: u64,
    next: u64,
    /// How late after its slot this cycle sent its own SYNC, ns (`None`: the SYNC is
    /// external); the next cycle's feedback was latched at that SYNC (`Feedback::late_s`).
    sync_late_ns: Option<u64>,
    /// The spindle's last fresh position taken back to its slot (`spindle_to_slot`).
    spindle_slot: Option<f64>,
    /// Whether the drives' positions show a SYNC's lateness (they latch when it arrives).
    timing: SampleTiming,
}

/// What [`CycleLoop::keep_time`] found about this cycle.
struct Tick {
    now: u64,
    /// Whole cycles missed (caught up by the interpolator, at most the watchdog's bridge).
    missed: u64,
    /// Whole cycles missed as woken (before that bound).
    late: u64,
    /// The cycle before this one woke late: its feedback does not pair with its demand.
    late_before: bool,
}

/// An axis' in-position width in whole counts, at least one (`Limits::in_position`).
fn in_position_counts(lim: &Limits, axis: Option<usize>, counts_per_unit: f64) -> i64 {
    let w = axis.and_then(|a| lim.in_position.get(a).copied()).unwrap_or(0.0) * counts_per_unit.abs();
    if w.is_finite() {
        (w.floor() as i64).max(1)
    } else {
        1
    }
}

impl Run {
    pub(super) fn new(lp: &mut CycleLoop, motion: &Motion, start: &[f64; N_AXES], summary: &mut RunSummary) -> Run {
        let map = lp.map();
        let n = map.len();
        let dt = lp.cycle_ns as f64 * 1e-9;
        let mut guard = lp.guard.unwrap_or_else(|| Guard::from_limits(motion.limits()));
        guard.set_start(start);
        summary.axes = (0..n)
            .map(|d| AxisSummary {
                name: lp.drives.axis_name(d).to_string(),
                max_following_error: 0.0,
                counts_per_unit: lp.drives.counts_per_unit(d),
                in_position_counts: in_position_counts(motion.limits(), map[d], lp.drives.counts_per_unit(d)),
                final_actual_counts: 0,
                final_target_counts: 0,
                program_end_counts: None,
                settle_miss: None,
                hunt: None,
            })
            .collect();
        let hist = (0..n).map(|d| [lp.drives.feedback(d).counts; 2]).collect();
        let scale = (0..n).map(|d| ScaleWatch::new(lp.drives.following_window(d).map(|w| w * lp.drives.counts_per_unit(d)))).collect();
        let t_start = lp.clock.now_ns();
        lp.trace_t0 = t_start;
        Run {
            map,
            simulated: lp.clock.is_simulated(),
            dt,
            guard,
            overruns_in_a_row: 0,
            end_pos: None,
            hist,
            line_hist: [0; 2],
            scale,
            cur_line: 0,
            input_open: true,
            ended: false,
            max_settle: (2.0 / dt) as u32,
            settle: EndSettle::new(n),
            hunt: HuntWatch::new(n, dt),
            late_prev: false,
            spindle_rpm: 0.0,
            meter: SpindleMeter::new(lp.spindle_drive.map(|d| lp.drives.feedback(d).pos).unwrap_or(0.0), 0.0),
            progress_every: ((0.05 / dt).round() as u64).max(1),
            t_start,
            next: t_start,
            sync_late_ns: None,
            spindle_slot: None,
            timing: SampleTiming::default(),
        }
    }
}

impl CycleLoop<'_> {
    pub(super) fn run_program(
        &mut self,
        motion: &mut Motion,
        start: [f64; N_AXES],
        rx: Receiver<Result<Move, Alarm>>,
        summary: &mut RunSummary,
        progress: &mut dyn FnMut(&Progress),
    ) -> Result<(), Alarm> {
        let mut run = Run::new(self, motion, &start, summary);
        self.active_guard = Some(run.guard);
        // With a tap-state file a hole's first stroke waits at R until its entry is on disk.
        if self.tap.is_some() {
            motion.gate_taps();
        }
        // One drive's fault stops the others under control (a tap's pair together) where the
        // bus can isolate it; otherwise every drive is quick-stopped.
        let isolate = self.drives.isolate_faults(true);
        if let Some(t) = self.tool {
            motion.set_tool_spindle(&t, self.drives.feedback(t.drive).pos);
        }
        let r = self.cycles(motion, &rx, &mut run, summary, isolate, progress);
        // A drive still swinging on a set-point that stood is the likely cause of the alarm.
        if r.is_err() {
            run.hunt.at_alarm();
        }
        for (d, a) in summary.axes.iter_mut().enumerate() {
            a.hunt = run.hunt.hunt(d);
        }
        r?;
        self.program_end_counts(&run, &start, summary);
        Ok(())
    }

    /// The cycles of the run, to the program's end or an alarm.
    fn cycles(
        &mut self,
        motion: &mut Motion,
        rx: &Receiver<Result<Move, Alarm>>,
        run: &mut Run,
        summary: &mut RunSummary,
        isolate: bool,
        progress: &mut dyn FnMut(&Progress),
    ) -> Result<(), Alarm> {
        loop {
            self.feed(motion, rx, run, summary)?;
            let tick = self.keep_time(motion, run, summary)?;
            let mut row = TraceRow { t_s: (tick.now - run.t_start) as f64 * 1e-9, ..TraceRow::default() };
            let fb = self.read_drives(motion, run, summary, &tick, isolate, &mut row)?;
            self.operator(motion, run)?;
            let sp = self.command(motion, run, summary, &fb, &tick)?;
            if self.after_send(motion, run, summary, &sp, &fb, &mut row, tick.now, progress)? {
                return Ok(());
            }
        }
    }

    /// Feed the look-ahead queue. Under simulated time, block for the interpreter so that
    /// every run is identical; in real time never block the cycle.
    fn feed(&mut self, motion: &mut Motion, rx: &Receiver<Result<Move, Alarm>>, run: &mut Run, summary: &mut RunSummary) -> Result<(), Alarm> {
        while run.input_open && motion.has_room() {
            let item = if run.simulated { rx.recv().map_err(|_| TryRecvError::Disconnected) } else { rx.try_recv() };
            match item {
                Ok(Ok(m)) => {
                    summary.moves += 1;
                    if let Some(e) = m.kind.end() {
                        run.end_pos = Some(e);
                    }
                    if let Err(a) = motion.push(&m) {
                        self.halt(motion, run.spindle_rpm);
                        return Err(a);
                    }
                    if let Some(w) = self.tap.as_mut() {
                        w.on_push(&m);
                    }
                }
                Ok(Err(a)) => {
                    // A run-time program alarm: stop at this block, in a controlled way.
                    self.halt(motion, run.spindle_rpm);
                    return Err(a);
                }
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => run.input_open = false,
            }
        }
        Ok(())
    }

    /// Wait for the next cycle. Overrun: whole periods were missed (real time only). The
    /// drives bridged the late SYNC as they do (`Watchdog::catch_up`): the interpolator
    /// catches up as many cycles as they extrapolated, so the set-point is where they are
    /// now, and holds the trajectory's time base back by the rest — a drive that held its
    /// target gets the next cycle's step, never the whole missed travel at once. In a thread
    /// or tap time cannot be shifted: that is a controlled stop naming the stall.
    fn keep_time(&mut self, motion: &mut Motion, run: &mut Run, summary: &mut RunSummary) -> Result<Tick, Alarm> {
        run.next += self.cycle_ns;
        self.clock.wait_until(run.next);
        let now = self.clock.now_ns();
        summary.cycles += 1;
        let late_before = run.late_prev;
        let mut missed = 0u64;
        run.late_prev = now >= run.next + self.cycle_ns / 2;
        let late = periods_passed(&mut run.next, now, self.cycle_ns);
        if late > 0 {
            summary.overruns += 1;
            missed = late.min(MAX_CATCH_UP);
        }
        if let Some(a) = self.watchdog.cycle(missed, &mut run.overruns_in_a_row, run.cur_line, self.cycle_ns) {
            self.halt(motion, run.spindle_rpm);
            return Err(a);
        }
        if missed > self.watchdog.catch_up && motion.is_synchronised() {
            self.halt(motion, run.spindle_rpm);
            return Err(stall_in_sync(run.cur_line, missed, self.watchdog.catch_up, self.cycle_ns));
        }
        Ok(Tick { now, missed: missed.min(self.watchdog.catch_up), late: missed, late_before })
    }

    /// Receive the drives' answers; a faulted drive or a lost bus ends the run. Returns the
    /// actual positions as motion takes them, with the following error and the feedback
    /// scaling checked on the way and the spindle speed measured.
    fn read_drives(
        &mut self,
        motion: &mut Motion,
        run: &mut Run,
        summary: &mut RunSummary,
        tick: &Tick,
        isolate: bool,
        row: &mut TraceRow,
    ) -> Result<Feedback, Alarm> {
        let received = self.drives.receive(tick.now);
        if let Some(d) = if isolate { self.drives.faulted() } else { None } {
            return Err(self.fault_stop(motion, d, received.err(), run.spindle_rpm, run.cur_line, run.ended));
        }
        if let Err(a) = received {
            if a.number == crate::alarm::SYNC_LOST {
                // The external SYNC stopped: the path is stopped under control (quick stop
                // would be no faster — without SYNC the drives take no set-point either way).
                self.halt_now(motion, run.spindle_rpm);
                return Err(a);
            }
            self.quick_stop_all();
            let _ = self.drives.transmit(tick.now);
            return Err(a);
        }
        let mut fb = Feedback::default();
        let mut scaled: Option<(usize, f64)> = None;
        let timing = Self::sample_timing_lateness(run, tick);
        for (d, ax) in run.map.iter().enumerate() {
            let f = self.drives.feedback(d);
            if timing {
                // Latched at the SYNC this loop sent (`sync::sample_time`).
                let fresh = f.age_cycles == 0 && f.sampled_ns.is_none();
                let v = (run.hist[d][1] - run.hist[d][0]) as f64 / run.dt;
                run.timing.sample(d, fresh.then_some(f.counts as f64), v);
            }
            if let Some(a) = ax {
                fb.pos[*a] = f.pos;
                run.hunt.update(d, &f, run.hist[d][0], run.line_hist[0]);
            }
            if d < MAX_TRACE_AXES {
                row.act[d] = f.pos;
                row.age[d] = f.age_cycles;
            }
            if d < SNAP_AXES {
                self.snap.axes[d].act = f.pos;
                self.snap.axes[d].statusword = f.statusword;
            }
            // Only fresh feedback in a cycle that followed its predecessor on time pairs
            // with the demand of two cycles ago; anything else would measure the jitter.
            // A bus that knows the drive's demand at the feedback's instant (Modbus, on
            // its own link cycle) gives it; CANopen pairs with the target of k−2.
            let demand = match f.demand_counts {
                Some(demand) if f.age_cycles == 0 => Some(demand),
                None if f.age_cycles == 0 && tick.missed == 0 && !tick.late_before => Some(run.hist[d][0]),
                _ => None,
            };
            if let Some(demand) = demand {
                scaled = scaled.or(run.scale[d].observe(demand, f.counts).map(|r| (d, r)));
                let a = &mut summary.axes[d];
                let err = (demand - f.counts) as f64 / a.counts_per_unit;
                if d < MAX_TRACE_AXES {
                    row.ferr[d] = err;
                }
                if d < SNAP_AXES {
                    self.snap.axes[d].ferr = err;
                }
                a.max_following_error = a.max_following_error.max(err.abs());
            }
        }
        if let Some((d, r)) = scaled {
            // The drive follows its set-points (only its feedback is off): a controlled
            // stop along the path, starting with this cycle's set-points.
            let msg = ScaleWatch::message(self.drives.axis_name(d), r, self.drives.counts_per_unit(d));
            self.halt_now(motion, run.spindle_rpm);
            return Err(Alarm::new(scale_watch::ALARM, format!("{msg} (line {})", run.cur_line)));
        }
        if let Some(sd) = self.spindle_drive {
            let mut f = self.drives.feedback(sd);
            if f.sampled_ns.is_none() {
                Self::spindle_to_slot(run, tick, &mut f, &mut fb);
            }
            run.spindle_rpm = run.meter.update_fb(&f, run.dt);
            fb.spindle_rpm = run.spindle_rpm;
            fb.spindle_torque = self.drives.torque_rated(sd);
            fb.spindle_torque_max = self.drives.max_torque_rated(sd);
            self.rpm = run.spindle_rpm;
        }
        Ok(fb)
    }

    /// The spindle's position as latched at the SYNC this loop sent last cycle, after its slot
    /// (a timer clock wakes late), taken back to the slot at its speed over the last interval
    /// (slot to late SYNC: exact at a constant speed), so the speed is measured between slots.
    /// Only for drives that show the lateness (`sync::sample_time`: a servo latches in time, a
    /// drive that steps per SYNC does not; for those `Feedback::late_s` stays 0).
    fn spindle_to_slot(run: &mut Run, tick: &Tick, f: &mut crate::drives::AxisFeedback, fb: &mut Feedback) {
        // A stale position, or one after a late cycle, is of another SYNC: left as it is.
        if f.age_cycles != 0 || tick.missed > 0 || tick.late_before {
            run.spindle_slot = None;
            return;
        }
        let late = if run.timing.latches_in_time() { run.sync_late_ns.map_or(0.0, |ns| ns as f64 * 1e-9) } else { 0.0 };
        let late = late.min(run.dt);
        fb.late_s = late;
        let w = run.spindle_slot.map_or(run.spindle_rpm * 6.0, |p| (f.pos - p) / (run.dt + late));
        f.pos -= w * late;
        fb.spindle_at_slot = f.pos;
        run.spindle_slot = Some(f.pos);
    }

    /// The lateness of the SYNC this loop sent last cycle into the regression of how much of
    /// it the drives show (`sync::sample_time`); false when there is none to learn from (an
    /// external SYNC, or a late cycle: the differences would span more than one period).
    fn sample_timing_lateness(run: &mut Run, tick: &Tick) -> bool {
        let Some(ns) = run.sync_late_ns else { return false };
        if tick.missed > 0 || tick.late_before {
            run.timing.restart();
            return false;
        }
        run.timing.lateness(ns as f64 * 1e-9);
        true
    }

    /// A signal (SIGTERM, SIGINT, SIGHUP) stops as reset does; the panel's keys.
    fn operator(&mut self, motion: &mut Motion, run: &Run) -> Result<(), Alarm> {
        let line = run.cur_line;
        if let Some((flag, name)) = self.signal {
            let sig = flag.load(std::sync::atomic::Ordering::Relaxed);
            if sig != 0 {
                // This cycle's set-points are not sent yet: the stop starts with them.
                self.halt_now(motion, run.spindle_rpm);
                let what = format!("{} at line {line}: stopped as on reset, the program ended", name(sig));
                return Err(Alarm::new(alarms::RESET, format!("{what}; start it again from the beginning or a safe block")));
            }
        }
        self.io_cycle(motion, run)?;
        let Some(r) = self.panel.as_mut() else { return Ok(()) };
        let i = r.poll();
        if i.estop {
            return Err(self.estop(line));
        }
        if i.reset {
            // This cycle's set-points are not sent yet: the stop starts with them.
            self.halt_now(motion, run.spindle_rpm);
            let what = format!("reset by the operator at line {line}: the axes were stopped under control and the program ended");
            return Err(Alarm::new(alarms::RESET, format!("{what}; start it again from the beginning or a safe block")));
        }
        if i.feed_hold {
            motion.feed_hold();
        }
        if i.cycle_start {
            motion.cycle_start();
        }
        motion.set_single_block(i.single_block);
        motion.set_optional_stop(i.optional_stop);
        motion.set_feed_override(i.feed_ovr);
        motion.set_rapid_override(i.rapid_ovr);
        motion.set_spindle_override(i.spindle_ovr);
        Ok(())
    }

    /// The I/O of this cycle: inputs read, safety inputs (E-stop as the panel's; door and
    /// chuck a controlled stop), the pending code's completion or timeout.
    fn io_cycle(&mut self, motion: &mut Motion, run: &Run) -> Result<(), Alarm> {
        let Ok(Some(io)) = self.io.as_mut() else { return Ok(()) };
        if let Err(a) = io.read(&*self.drives) {
            return Err(self.quick_stop_with(a));
        }
        // Shown before they are acted on: the display keeps the input that stopped the run.
        if let Some(r) = self.panel.as_ref() {
            r.report_safety(io.safety_inputs());
        }
        let stop = io.check_safety(run.spindle_rpm.abs() > 1.0, run.cur_line);
        let fin = if stop.is_none() { io.step_fin(run.spindle_rpm) } else { Ok(false) };
        match (stop, fin) {
            (Some(IoStop::Estop(name)), _) => Err(self.estop_input(run.cur_line, &name)),
            (Some(IoStop::Device(a)), _) => Err(self.quick_stop_with(a)),
            (Some(IoStop::Halt(a)), _) | (None, Err(a)) => {
                // This cycle's set-points are not sent yet: the stop starts with them.
                motion.wait_fin(false);
                self.halt_now(motion, run.spindle_rpm);
                Err(a)
            }
            (None, Ok(done)) => {
                if done {
                    motion.wait_fin(false);
                }
                Ok(())
            }
        }
    }

    /// Interpolate this cycle's set-point (and the cycles missed), switch the G22 area where
    /// the program does, refuse a set-point beyond the limits, send the targets.
    fn command(&mut self, motion: &mut Motion, run: &mut Run, summary: &mut RunSummary, fb: &Feedback, tick: &Tick) -> Result<Setpoint, Alarm> {
        if let Some(t) = self.tool {
            motion.set_tool_feedback(self.drives.feedback(t.drive).pos);
        }
        let sp = motion.step(fb);
        let sp = self.advance(motion, run, fb, sp, tick.missed)?;
        let passed = self.syncs_passed(motion, run, summary, tick)?;
        let sp = self.advance(motion, run, fb, sp, passed)?;
        // G22/G23 reached in program order: the guard switches before this set-point.
        if let Event::Stroke2(a) = sp.event {
            run.guard.set_stroke2(a);
        }
        // Limits before motion: a set-point beyond them is never sent. (The interpolated
        // position: the sync correction on top of it, ≤ 0.5 mm, makes the actual follow it.)
        self.active_guard = Some(run.guard);
        if let Err(v) = run.guard.check(&motion.position()) {
            return Err(self.quick_stop_with(v.alarm(sp.line)));
        }
        for (d, ax) in run.map.iter().enumerate() {
            if let Some(a) = ax {
                self.drives.set_target(d, sp.pos[*a]);
            }
            if self.tool.is_some_and(|t| t.drive == d) {
                self.drives.set_target(d, sp.tool_spindle);
            }
            run.hist[d][0] = run.hist[d][1];
            run.hist[d][1] = self.drives.target_counts(d);
        }
        run.line_hist = [run.line_hist[1], sp.line];
        if let Ok(Some(io)) = self.io.as_ref() {
            io.write(&mut *self.drives);
        }
        if let Err(a) = self.drives.transmit(tick.now) {
            self.quick_stop_all();
            return Err(a);
        }
        // The SYNC goes out last: now, after the set-points (later than the wake-up by the
        // cycle's work and whatever held the thread up meanwhile).
        if run.sync_late_ns.is_some() {
            run.sync_late_ns = Some(self.clock.now_ns().saturating_sub(run.next));
        }
        Ok(sp)
    }

    /// `n` more interpolation steps after `sp` (cycles missed), each step's event acted on
    /// in program order.
    fn advance(&mut self, motion: &mut Motion, run: &mut Run, fb: &Feedback, mut sp: Setpoint, n: u64) -> Result<Setpoint, Alarm> {
        for _ in 0..n {
            if let Event::Stroke2(a) = sp.event {
                run.guard.set_stroke2(a);
            }
            match self.on_event(motion, &sp) {
                Ok(end) => run.ended |= end,
                Err(a) => {
                    // This cycle's set-points are not sent yet: the stop starts with them.
                    self.halt_now(motion, run.spindle_rpm);
                    return Err(a);
                }
            }
            sp = motion.step(fb);
        }
        Ok(sp)
    }

    /// An external SYNC (`bus.sync = "external"`) does not wait for this cycle: SYNCs that
    /// came after the one it woke on, before its set-points go out (the thread was held up
    /// after its wake-up), make it a late cycle. Its set-points would act a SYNC later than
    /// computed — behind a drive that bridged the SYNC by extrapolating, a step back — so the
    /// cycle is counted, watched and caught up as one that woke that late (`keep_time`): the
    /// interpolator advances by the SYNCs the drives bridged, the rest holds the time base
    /// back, and in a thread or tap it is alarm 2403. Returns the further steps to take.
    /// (A SYNC between this look and the send still comes first; the window is the send.)
    fn syncs_passed(&mut self, motion: &mut Motion, run: &mut Run, summary: &mut RunSummary, tick: &Tick) -> Result<u64, Alarm> {
        let Some(now) = self.clock.poll_sync() else {
            // A timer clock: this loop sends the SYNC (`command` says when it went out).
            run.sync_late_ns = Some(0);
            return Ok(0);
        };
        run.sync_late_ns = None;
        let passed = periods_passed(&mut run.next, now, self.cycle_ns);
        if passed == 0 {
            return Ok(0);
        }
        run.late_prev = true;
        if tick.late == 0 {
            summary.overruns += 1;
        } else {
            // `keep_time` counted this cycle already: the watchdog sees it once, as late as it
            // turned out to be.
            run.overruns_in_a_row = run.overruns_in_a_row.saturating_sub(1);
        }
        let late = (tick.late + passed).min(MAX_CATCH_UP);
        if let Some(a) = self.watchdog.cycle(late, &mut run.overruns_in_a_row, run.cur_line, self.cycle_ns) {
            self.halt_now(motion, run.spindle_rpm);
            return Err(a);
        }
        if late > self.watchdog.catch_up && motion.is_synchronised() {
            self.halt_now(motion, run.spindle_rpm);
            return Err(stall_in_sync(run.cur_line, late, self.watchdog.catch_up, self.cycle_ns));
        }
        Ok(late.min(self.watchdog.catch_up) - tick.missed)
    }

    /// The rigid-tap state gate: a hole's first stroke waits until its entry is on disk.
    /// Under simulated time the wait for the disk is taken in wall time, outside the
    /// simulated clock (as the interpreter's channel is), so that every run is identical
    /// cycle for cycle.
    fn tap_gate(&mut self, motion: &mut Motion, run: &Run, sp: &Setpoint, fb: &Feedback) -> Result<(), Alarm> {
        let Some(w) = self.tap.as_mut() else { return Ok(()) };
        w.on_cycle(sp.line, &sp.pos, &fb.pos);
        let mut gate = w.gate(motion.tap_waiting());
        while run.simulated && matches!(gate, Ok(false)) && motion.tap_waiting().is_some() {
            std::thread::sleep(std::time::Duration::from_micros(200));
            gate = w.gate(motion.tap_waiting());
        }
        match gate {
            Ok(open) => {
                motion.open_tap_gate(open);
                Ok(())
            }
            Err(a) => {
                self.halt(motion, run.spindle_rpm);
                Err(a)
            }
        }
    }

    /// Everything after the set-points went out. True once the program ended and the drives
    /// settled onto the last set-point (within one count, at most 2 s).
    #[allow(clippy::too_many_arguments)]
    fn after_send(
        &mut self,
        motion: &mut Motion,
        run: &mut Run,
        summary: &mut RunSummary,
        sp: &Setpoint,
        fb: &Feedback,
        row: &mut TraceRow,
        now: u64,
        progress: &mut dyn FnMut(&Progress),
    ) -> Result<bool, Alarm> {
        self.tap_gate(motion, run, sp, fb)?;
        if let Some(t) = self.trace.as_mut() {
            for (d, ax) in run.map.iter().enumerate().take(MAX_TRACE_AXES) {
                row.cmd[d] = traced_cmd(d, *ax, self.tool.map(|t| t.drive), sp, row.act[d]);
            }
            row.line = sp.line;
            row.spindle_rpm = run.spindle_rpm;
            row.sync_err_um = motion.sync_error();
            t.record(row);
        }
        if let Some(a) = motion.take_alarm() {
            // The motion layer already started a controlled stop.
            self.halt(motion, run.spindle_rpm);
            return Err(a);
        }
        let ended_before = run.ended;
        match self.on_event(motion, sp) {
            Ok(end) => run.ended |= end,
            Err(a) => {
                self.halt(motion, run.spindle_rpm);
                return Err(a);
            }
        }
        if sp.line != run.cur_line && sp.line != 0 {
            summary.blocks += 1;
        }
        run.cur_line = sp.line;
        summary.ended = run.ended;
        if let Some(r) = self.panel.as_ref() {
            r.report(motion.is_held(), sp.line);
        }
        let t_s = (now - run.t_start) as f64 * 1e-9;
        self.publish_cycle(motion, run, summary, sp, t_s, run.ended && !ended_before);
        if summary.cycles % run.progress_every == 0 {
            let feed = sp.path_feed;
            progress(&Progress { t_s, line: sp.line, pos: sp.pos, feed, spindle_rpm: sp.spindle_rpm, sync_err_um: motion.sync_error() });
        }
        if !((run.ended || !run.input_open) && motion.is_idle()) {
            return Ok(false);
        }
        if summary.machining_time_s == 0.0 {
            summary.machining_time_s = t_s;
        }
        // Let the drives settle onto the last setpoint (within one count), bounded — and come
        // to rest there (`settle`). A spindle passing through its C angle at 1 °/s is within
        // a count for one sample; torque went off there and it coasted 0.04° off it. A spindle
        // driven in speed has no position to settle on, and its ramp down is the stop's
        // (`to_rest`): every Modbus run waited out the 2 s bound on it, 1.5° from an angle it
        // was never steered to, and reported it as not settled.
        let mut settled = true;
        for d in (0..run.map.len()).filter(|&d| self.drives.holds_position(d)) {
            settled &= run.settle.update(d, &self.drives.feedback(d), self.drives.target_counts(d));
        }
        run.settle.tick();
        Ok(settled || run.settle.cycles() > run.max_settle)
    }

    /// This cycle into the snapshot (`control::snapshot`): copies of what the cycle has
    /// computed, then the seqlock's stores. Nothing when no observer asked for it.
    /// `new_end`: the program's end (M02/M30) was reached in this cycle, one more part.
    fn publish_cycle(&mut self, motion: &Motion, run: &Run, summary: &RunSummary, sp: &Setpoint, t_s: f64, new_end: bool) {
        if self.snapshot.is_none() {
            return;
        }
        let load = self.spindle_drive.map_or(f64::NAN, |d| 100.0 * self.drives.torque_rated(d));
        let s = &mut self.snap;
        s.spindle_load_pct = load;
        s.parts += new_end as u64;
        for (d, ax) in run.map.iter().enumerate().take(SNAP_AXES) {
            s.axes[d].cmd = match ax {
                Some(a) => sp.pos[*a],
                None if self.tool.is_some_and(|t| t.drive == d) => sp.tool_spindle,
                None => s.axes[d].act,
            };
        }
        s.n_axes = run.map.len().min(SNAP_AXES) as u8;
        s.cycle += 1;
        s.state = if motion.is_held() { MachineState::Held } else { MachineState::Running };
        s.line = sp.line;
        s.blocks = summary.blocks;
        s.elapsed_s = t_s;
        s.spindle_cmd_rpm = sp.spindle_rpm;
        s.spindle_act_rpm = run.spindle_rpm;
        s.spindle_override = motion.spindle_override();
        s.feed_override = motion.feed_override();
        s.feed = sp.path_feed;
        s.sync_err_um = motion.sync_error();
        s.alarm = 0;
        self.publish();
    }

    /// Where each axis stands at the program's end, and where the program said it would.
    fn program_end_counts(&self, run: &Run, start: &[f64; N_AXES], summary: &mut RunSummary) {
        for (d, ax) in run.map.iter().enumerate() {
            let f = self.drives.feedback(d);
            let a = &mut summary.axes[d];
            a.final_actual_counts = f.counts;
            a.final_target_counts = self.drives.target_counts(d);
            a.settle_miss = run.settle.miss(d, run.dt);
            a.program_end_counts = match (ax, run.end_pos) {
                (Some(AX_X), Some(e)) => Some((e.x * a.counts_per_unit).round() as i64),
                (Some(AX_Z), Some(e)) => Some((e.z * a.counts_per_unit).round() as i64),
                (Some(AX_Y), Some(e)) if e.y != start[AX_Y] => Some((e.y * a.counts_per_unit).round() as i64),
                _ => None,
            };
        }
    }
}
