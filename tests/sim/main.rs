//! The whole chain on emulated drives in simulated time (sync, stops, faults, late cycles,
//! drive models and profiles, identification). One test binary for the folder (one link of the
//! crate instead of one per file); each file is a module, its tests are `FILE::test_name`.
//!
//! `polygon_sim` installs this binary's `#[global_allocator]` (a counting one, counting only on
//! the thread that arms it); a binary has at most one, so tests/no_alloc.rs stays its own.

#[path = "../io_common/mod.rs"]
mod io_common;
#[path = "../profiles_common/mod.rs"]
mod profiles_common;
mod sim_probe;

mod canopen_master;
mod drive_matrix;
mod drive_profiles;
mod fault_matrix;
mod identify;
mod inproc_run;
mod io_run;
mod late_cycle;
mod late_external_sync;
mod limits_watchdog;
mod polar_sim;
mod polygon_sim;
mod run_inproc;
mod startup_shapes;
mod stop_sequence;
mod stroke_guard;
mod sync_sim;
mod tap_g88_sim;
mod tap_state_property;
