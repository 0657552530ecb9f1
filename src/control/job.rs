//! Running one program on a machine: the sequence every caller (`cncgw run`, `tap-test`,
//! `identify`, the tests and examples) used to write out by hand — make the cycle loop from
//! the configuration, start the drives, start the interpreter on its own thread ahead of
//! motion, run the loop to the program's end or an alarm, hand back the common variables.
//! Torque off ([`CycleLoop::finish`]) stays with the caller, which may still read the
//! drives (a trace, a probe) before it.

use super::cycle::{CycleLoop, Progress, RunSummary, Watchdog};
use crate::canon::{Move, Pos};
use crate::config::MachineConfig;
use crate::drives::DriveBus;
use crate::interp::Interpreter;
use crate::motion::polygon::ToolSpindle;
use crate::motion::{Limits, AX_S, AX_X, AX_Y, AX_Z, N_AXES};
use crate::Alarm;
use cncgw_bus::Clock;
use std::collections::HashMap;
use std::sync::mpsc::{sync_channel, Receiver};
use std::thread::JoinHandle;

/// Moves the interpreter may run ahead of motion (as on a Fanuc, macro statements are executed
/// while the blocks before them are buffered).
pub const LOOK_AHEAD_MOVES: usize = 256;

/// The common variables (#100–#199, #500–#999) as the interpreter leaves them.
pub type CommonVars = HashMap<u32, f64>;

impl<'a> CycleLoop<'a> {
    /// The cycle loop of the machine `cfg` describes: its limits, spindle, cycle period,
    /// overrun watchdog and tool spindle, resolved here once for every caller.
    pub fn from_config(drives: &'a mut dyn DriveBus, clock: &'a mut dyn Clock, cfg: &MachineConfig) -> Self {
        let mut lp = CycleLoop::new(drives, clock, Limits::from_config(cfg), cfg.spindle_index(), cfg.cycle_ns());
        if let Some(t) = ToolSpindle::from_config(cfg) {
            lp.set_tool_spindle(t);
        }
        lp.set_watchdog(Watchdog::from_config(cfg));
        lp.io = super::io::IoRun::new(cfg);
        lp
    }
}

/// Where the axes stand, as the interpreter's start position.
pub fn start_pos(start: &[f64; N_AXES]) -> Pos {
    Pos { x: start[AX_X], y: start[AX_Y], z: start[AX_Z], c: start[AX_S] }
}

/// A source of moves for the interpreter thread: the interpreter itself, or what wraps it
/// (a program restart's approach, MDI's blocks as they are typed); it hands back the common
/// variables at the end.
pub trait MoveFeed: Iterator<Item = Result<Move, Alarm>> + Send {
    fn common_vars(&self) -> CommonVars;
}

impl MoveFeed for Interpreter {
    fn common_vars(&self) -> CommonVars {
        Interpreter::common_vars(self).clone()
    }
}

/// The moves on their own thread, [`LOOK_AHEAD_MOVES`] ahead of motion. Start it before the
/// cycle thread takes its real-time policy (`control::rt::apply`), so that it does not
/// inherit it.
pub struct Feed {
    rx: Receiver<Result<Move, Alarm>>,
    handle: JoinHandle<CommonVars>,
}

impl Feed {
    /// The interpreter from where the axes stand (`start`).
    pub fn interpreter(mut interp: Interpreter, start: &[f64; N_AXES]) -> Result<Feed, Alarm> {
        interp.set_start_position(start_pos(start));
        Feed::spawn(Box::new(interp))
    }

    /// Start the thread; it stops at the first alarm and hands back the common variables
    /// when it ends.
    pub fn spawn(mut it: Box<dyn MoveFeed>) -> Result<Feed, Alarm> {
        let (tx, rx) = sync_channel(LOOK_AHEAD_MOVES);
        let handle = std::thread::Builder::new()
            .name("interp".into())
            .spawn(move || {
                for m in it.by_ref() {
                    let stop = m.is_err();
                    if tx.send(m).is_err() || stop {
                        break;
                    }
                }
                it.common_vars()
            })
            .map_err(|e| Alarm::new(crate::alarm::NO_THREAD, format!("cannot start the interpreter thread: {e}")))?;
        Ok(Feed { rx, handle })
    }

    /// Run the loop (started at `start`) on these moves to the end or an alarm. Returns the
    /// result and the common variables at the end (None if the feed's thread died, or with
    /// `live`: a feed that waits for a person's next line may never end, so it is left behind
    /// and its owner keeps the variables).
    pub fn run(
        self,
        lp: &mut CycleLoop,
        start: [f64; N_AXES],
        summary: &mut RunSummary,
        progress: &mut dyn FnMut(&Progress),
        live: bool,
    ) -> (Result<(), Alarm>, Option<CommonVars>) {
        let r = lp.run(start, self.rx, summary, progress);
        (r, if live { None } else { self.handle.join().ok() })
    }
}

/// Start the drives and run `interp` on them: [`CycleLoop::start`], then [`Feed`].
/// The caller turns torque off with [`CycleLoop::finish`].
pub fn run_program(lp: &mut CycleLoop, interp: Interpreter, summary: &mut RunSummary) -> Result<(), Alarm> {
    run_program_with(lp, interp, summary, &mut |_| {})
}

/// [`run_program`] with a progress report every few cycles.
pub fn run_program_with(lp: &mut CycleLoop, interp: Interpreter, summary: &mut RunSummary, progress: &mut dyn FnMut(&Progress)) -> Result<(), Alarm> {
    let start = lp.start(summary)?;
    Feed::interpreter(interp, &start)?.run(lp, start, summary, progress, false).0
}

/// Start the drives and run a list of moves made beforehand (tests, measurements): the
/// moves are queued at once, no interpreter thread.
pub fn run_moves(lp: &mut CycleLoop, moves: Vec<Move>, summary: &mut RunSummary, progress: &mut dyn FnMut(&Progress)) -> Result<(), Alarm> {
    let start = lp.start(summary)?;
    let (tx, rx) = sync_channel(moves.len().max(1));
    for m in moves {
        let _ = tx.send(Ok(m));
    }
    drop(tx);
    lp.run(start, rx, summary, progress)
}
