//! cncgw: a CNC lathe / turn-mill controller core and fieldbus gateway.
//!
//! Data flow (see docs/ARCHITECTURE.md): part program → [`interp`] → [`canon::Move`] stream →
//! [`motion`] planner and interpolator (+ [`sync`]) → per-cycle setpoints, sent by the
//! [`control`] cycle loop → [`drives`]
//! (CiA 402 over CANopen, Modbus) → bus.

pub mod alarm;
pub mod canon;
pub mod cli;
pub mod config;
pub mod control;
pub mod drives;
pub mod interp;
pub mod io;
pub mod motion;
pub mod offsets;
/// The read-only OPC UA server of `cncgw run` (feature `opcua`; between `cli` and `control`).
#[cfg(feature = "opcua")]
pub mod opcua;
pub mod params;
pub mod persist;
pub mod plot;
pub mod reference;
pub mod sync;

pub use alarm::Alarm;
/// The shared codecs, transports and clock (its own crate so that `sim-drives` can use them).
pub use cncgw_bus as bus;
