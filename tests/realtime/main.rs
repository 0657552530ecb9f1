//! Real time and separate processes: the cycle loop on the wall clock, sim-drives as a process
//! (socketcand, Modbus TCP/RTU), a terminal (tmux), processes killed. Every test of this binary
//! needs the machine to itself: .config/nextest.toml runs `binary(realtime)` one test at a
//! time, with one retry. One test binary for the folder (one link of the crate instead of one
//! per file); each file is a module, its tests are `FILE::test_name`.
//!
//! `tap_return_kill` installs this binary's `#[global_allocator]` (a counting one, counting only
//! on the thread that arms it); a binary has at most one, so tests/no_alloc.rs stays its own.

#[path = "../io_common/mod.rs"]
mod io_common;
mod modbus_common;

mod cli_modbus;
mod cli_tmux;
mod controller_death;
mod io_process;
mod io_python;
mod mdi_tmux;
mod modbus_maps;
mod modbus_run;
mod modbus_vendor;
mod realtime_inproc;
mod stop_process;
mod tap_return_kill;
