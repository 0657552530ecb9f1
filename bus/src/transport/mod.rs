//! CAN transports behind one trait: SocketCAN (can0, vcan0) and the in-process bus.
//!
//! The trait is synchronous and non-allocating so that the cycle loop (its own thread, not
//! async) can use it directly; transports that need async I/O run it in a thin task behind
//! bounded channels.

pub mod inproc;
pub mod socketcan;
pub mod socketcand;

use crate::frame::CanFrame;
use std::time::Duration;

#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum BusError {
    #[error("bus {bus}: cannot open: {reason}")]
    Open { bus: String, reason: String },
    #[error("bus {bus}: transport failed: {reason}")]
    Io { bus: String, reason: String },
    #[error("bus {bus}: bus-off (the CAN controller stopped after too many errors); check wiring, termination and bitrate, then restart")]
    BusOff { bus: String },
    #[error("bus {bus}: receive queue overflow, {dropped} frames lost")]
    Overflow { bus: String, dropped: u64 },
    #[error("bus {bus}: closed")]
    Closed { bus: String },
}

pub trait CanBus: Send {
    /// Queue one frame for transmission. Never blocks.
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError>;
    /// The next received frame, if one is waiting. Never blocks.
    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError>;
    /// Wait up to `timeout` for a frame (real-time use only; simulated time never blocks).
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError>;
    /// Interface name for messages (`inproc`, `vcan0`, …).
    fn name(&self) -> &str;
    /// How long ago the frame last returned by `try_recv`/`recv_timeout` arrived, where the
    /// transport knows it (SocketCAN: the kernel's receive timestamp). Emulated drives use it
    /// to act at the frame's arrival time even when their process was busy or descheduled.
    fn last_rx_age(&self) -> Option<Duration> {
        None
    }
    /// Whether the transport carries remote frames (RTR). CAN does; the socketcand protocol
    /// has no remote frames, so node guarding (CiA 301 RTR requests) cannot run over it.
    fn remote_frames(&self) -> bool {
        true
    }
    /// The CAN controller's own state from its error frames (error-warning, error-passive,
    /// bus-off, …, counters), where the transport receives them (SocketCAN with
    /// CAN_RAW_ERR_FILTER). None: this transport does not tell.
    fn controller(&self) -> Option<crate::can_error::ControllerStatus> {
        None
    }
}

impl<T: CanBus + ?Sized> CanBus for Box<T> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        (**self).send(frame)
    }
    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        (**self).try_recv()
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        (**self).recv_timeout(timeout)
    }
    fn name(&self) -> &str {
        (**self).name()
    }
    fn last_rx_age(&self) -> Option<Duration> {
        (**self).last_rx_age()
    }
    fn remote_frames(&self) -> bool {
        (**self).remote_frames()
    }
    fn controller(&self) -> Option<crate::can_error::ControllerStatus> {
        (**self).controller()
    }
}
