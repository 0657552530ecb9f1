//! The machine in operation: the cycle loop that runs the planner against the drives every
//! bus cycle, what watches it (travel guard, rigid-tap state, trace), the operator's panel,
//! the real-time setup of the cycle thread, and [`job`], the one sequence that runs a
//! program (start the drives, the interpreter thread, the loop, torque off).
//!
//! Floors: `control` uses `motion`, `sync`, `drives`, `interp`; nothing below imports it.

pub mod cycle;
#[cfg(feature = "embedded")]
pub mod embedded;
pub mod guard;
pub mod io;
pub mod job;
pub mod panel;
pub mod rt;
pub mod snapshot;
pub mod tapstate;
pub mod trace;

/// A CAN bus endpoint and the clock a run waits on: the real clock for hardware, the
/// emulator itself for the embedded machine.
pub type BusClock = (Box<dyn cncgw_bus::CanBus>, Box<dyn cncgw_bus::Clock>);
