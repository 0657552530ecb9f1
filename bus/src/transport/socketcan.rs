//! SocketCAN (can0, vcan0): a raw CAN socket in non-blocking mode, used directly from the
//! cycle thread. One system call per frame and no thread hop: under a loaded kernel (or the
//! User-Mode Linux guest of the vcan tier, where a syscall costs ~20 µs) an async runtime's
//! wake-ups between the socket and the cycle loop cost more than the frames themselves.

use super::{BusError, CanBus};
use crate::can_error::{ControllerStatus, ErrorFrame};
use crate::frame::CanFrame;
use socketcan::Socket;
use std::io::ErrorKind;
use std::os::fd::AsRawFd;
use std::time::Duration;

pub struct SocketCan {
    name: String,
    sock: socketcan::CanSocket,
    /// SO_TIMESTAMPNS is on: frames carry their kernel arrival time.
    timestamps: bool,
    last_age: Option<Duration>,
    /// The controller's state from the error frames (CAN_RAW_ERR_FILTER); None when the
    /// kernel refused the subscription.
    status: Option<ControllerStatus>,
}

fn to_sc(f: &CanFrame) -> Option<socketcan::CanFrame> {
    use socketcan::{EmbeddedFrame, ExtendedId, StandardId};
    if f.extended {
        let id = ExtendedId::new(f.id)?;
        if f.rtr {
            socketcan::CanFrame::new_remote(id, f.len as usize)
        } else {
            socketcan::CanFrame::new(id, f.data())
        }
    } else {
        let id = StandardId::new(f.id as u16)?;
        if f.rtr {
            socketcan::CanFrame::new_remote(id, f.len as usize)
        } else {
            socketcan::CanFrame::new(id, f.data())
        }
    }
}

fn from_sc(f: &socketcan::CanFrame) -> Option<CanFrame> {
    use socketcan::{EmbeddedFrame, Frame};
    if f.is_error_frame() {
        return None;
    }
    let mut out = CanFrame { id: f.raw_id(), extended: f.is_extended(), rtr: f.is_remote_frame(), len: f.dlc().min(8) as u8, data: [0; 8] };
    let d = f.data();
    out.data[..d.len().min(8)].copy_from_slice(&d[..d.len().min(8)]);
    if !out.rtr {
        out.len = d.len().min(8) as u8;
    }
    Some(out)
}

impl SocketCan {
    /// Open `iface` (e.g. `vcan0`). Fails with a message that says how to bring it up.
    pub fn open(iface: &str) -> Result<Self, BusError> {
        let name = iface.to_string();
        // The kernel's SocketCAN first: without it, the interface lookup below fails with
        // "no such device", which would send the user looking for an interface.
        // SAFETY: a socket we close at once.
        let fd = unsafe { libc::socket(libc::AF_CAN, libc::SOCK_RAW, 1) };
        if fd < 0 {
            let e = std::io::Error::last_os_error();
            if e.raw_os_error() == Some(libc::EAFNOSUPPORT) {
                return Err(BusError::Open {
                    bus: name.clone(),
                    reason: "this kernel has no SocketCAN (socket(AF_CAN) fails with EAFNOSUPPORT); use --bus inproc, socketcand://…, or a machine with CAN support".into(),
                });
            }
        } else {
            // SAFETY: the descriptor opened just above.
            unsafe { libc::close(fd) };
        }
        let sock = socketcan::CanSocket::open(iface).map_err(|e| {
            let reason = if e.raw_os_error() == Some(97) {
                "this kernel has no SocketCAN (socket(AF_CAN) fails with EAFNOSUPPORT); use --bus inproc, socketcand://…, or a machine with CAN support".to_string()
            } else {
                format!("{e}; bring it up first, e.g. `ip link set {iface} up type can bitrate 1000000` (or `modprobe vcan; ip link add {iface} type vcan; ip link set {iface} up`)")
            };
            BusError::Open { bus: name.clone(), reason }
        })?;
        sock.set_nonblocking(true).map_err(|e| BusError::Open { bus: name.clone(), reason: e.to_string() })?;
        let timestamps = socketcan::SocketOptions::set_recv_timestamp(&sock, true).is_ok();
        // Error frames: the controller's state changes, missing ACK, overflows (issue 21).
        let status = socketcan::SocketOptions::set_error_filter_accept_all(&sock).is_ok().then(ControllerStatus::default);
        Ok(SocketCan { name, sock, timestamps, last_age: None, status })
    }

    /// Send an error frame (CAN_ERR_FLAG) as a controller would report it: for tests and
    /// emulators on a virtual bus (vcan delivers it to every other socket subscribed to
    /// error frames). A real controller's driver sends these itself.
    pub fn inject_error(&mut self, e: &ErrorFrame) -> Result<(), BusError> {
        let (id, data) = e.encode();
        let f = socketcan::CanErrorFrame::new_error(id, &data).map_err(|x| BusError::Io { bus: self.name.clone(), reason: x.to_string() })?;
        self.sock.write_frame(&socketcan::CanFrame::Error(f)).map_err(|x| self.io(x))
    }

    fn io(&self, e: std::io::Error) -> BusError {
        BusError::Io { bus: self.name.clone(), reason: e.to_string() }
    }
}

impl CanBus for SocketCan {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        let Some(f) = to_sc(frame) else {
            return Err(BusError::Io { bus: self.name.clone(), reason: format!("invalid frame {frame:?}") });
        };
        match self.sock.write_frame(&f) {
            Ok(()) => Ok(()),
            // ENOBUFS / EAGAIN: the interface's transmit queue is full (bus-off or unplugged
            // cable on a real controller).
            Err(e) if e.kind() == ErrorKind::WouldBlock || e.raw_os_error() == Some(105) => Err(BusError::Io {
                bus: self.name.clone(),
                reason: "transmit queue full (bus-off, no other node acknowledging, or cable unplugged?)".into(),
            }),
            Err(e) => Err(self.io(e)),
        }
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        loop {
            let r = if self.timestamps {
                self.sock.read_frame_with_timestamp().map(|(f, ts)| (f, std::time::SystemTime::now().duration_since(ts).ok()))
            } else {
                self.sock.read_frame().map(|f| (f, None))
            };
            match r {
                Ok((socketcan::CanFrame::Error(e), _)) => {
                    // Not data: the controller's report, kept for `controller`.
                    if let Some(st) = &mut self.status {
                        st.apply(&ErrorFrame::decode(e.error_bits(), socketcan::EmbeddedFrame::data(&e)));
                    }
                }
                Ok((f, age)) => match from_sc(&f) {
                    Some(f) => {
                        self.last_age = age;
                        return Ok(Some(f));
                    }
                    None => continue,
                },
                Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(None),
                Err(e) => return Err(self.io(e)),
            }
        }
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        if let Some(f) = self.try_recv()? {
            return Ok(Some(f));
        }
        // ppoll, not socketcan's read_frame_timeout: that one converts the timeout to whole
        // milliseconds, so every sub-millisecond wait became a zero-timeout busy loop.
        let mut pfd = libc::pollfd { fd: self.sock.as_raw_fd(), events: libc::POLLIN, revents: 0 };
        let ts = libc::timespec { tv_sec: timeout.as_secs() as libc::time_t, tv_nsec: timeout.subsec_nanos() as libc::c_long };
        // SAFETY: one valid pollfd for the socket we own, a valid timespec, no signal mask.
        let r = unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) };
        if r < 0 {
            let e = std::io::Error::last_os_error();
            if e.kind() == ErrorKind::Interrupted {
                return Ok(None);
            }
            return Err(self.io(e));
        }
        if r == 0 {
            return Ok(None);
        }
        self.try_recv()
    }

    fn name(&self) -> &str {
        &self.name
    }

    fn last_rx_age(&self) -> Option<Duration> {
        self.last_age
    }

    fn controller(&self) -> Option<ControllerStatus> {
        self.status
    }
}
