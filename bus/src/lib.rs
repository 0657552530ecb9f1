//! Shared by the cncgw master and `sim-drives`: CAN frames, the CANopen and CiA 402 codecs
//! (sans-I/O: bytes in, values out), the CAN transports behind one trait, and the injected
//! clock.
//!
//! This is its own crate because the `cncgw` binary embeds the emulator (the default
//! machine runs on in-process emulated drives) while the emulator needs the codecs: with the
//! codecs inside `cncgw`, cargo would see a package cycle. One implementation of each codec,
//! used by both sides.

pub mod busload;
pub mod can_error;
pub mod canopen;
pub mod cia402;
pub mod clock;
pub mod frame;
pub mod modbus;
pub mod rt;
pub mod socketcand;
pub mod sync_source;
pub mod transport;

pub use clock::{Clock, RealClock, WakeStep, WakeStrategy};
pub use frame::CanFrame;
pub use transport::{BusError, CanBus};
