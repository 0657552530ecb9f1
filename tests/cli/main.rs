//! The `cncgw` binary run as a person or a service runs it (service commands, preview, trace,
//! MDI, offsets, state, deploy files, the OPC UA server, drives we did not write), none of which
//! needs the machine to itself. One test binary for the folder (one link of the crate instead
//! of one per file); each file is a module, its tests are `FILE::test_name`.

mod svg_common;

mod alarm_history;
mod cli_diag;
mod cli_man;
mod cli_messages;
mod cli_preview;
mod cli_service;
mod cli_taptest;
mod config_check;
mod deploy;
mod mdi;
mod monitor_io;
mod offsets_cli;
mod opcua_server;
mod persist_kill;
mod python_drives;
mod reference;
mod restart;
mod state_persist;
mod trace_cli;
