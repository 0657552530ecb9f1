//! A link's byte stream (TCP connection or serial line), shared between tokio-modbus, which
//! frames requests and answers on it, and the link, which discards stale bytes before each
//! request.
//!
//! Why: an answer that arrives after its transaction timed out stays in the operating
//! system's buffer (tokio-modbus clears only its own), and is then read as the answer to the
//! next request — "mismatching function codes" or a wrong transaction id — and that
//! request's own answer to the one after it, and so on for good. No valid answer can be
//! pending when the master is about to send (the previous transaction was answered or
//! given up), so whatever is waiting then is stale: dropping it puts the exchange back in
//! step. A late answer that arrives during the next exchange fails that one transaction;
//! its own answer is dropped before the one after.

use std::io;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

#[derive(Debug)]
enum Port {
    Tcp(tokio::net::TcpStream),
    Serial(tokio_serial::SerialStream),
}

/// The stream; clones share it (one goes to tokio-modbus, one stays with the link).
#[derive(Clone, Debug)]
pub struct Line(Arc<Mutex<Port>>);

impl Line {
    pub fn tcp(s: tokio::net::TcpStream) -> Line {
        Line(Arc::new(Mutex::new(Port::Tcp(s))))
    }

    pub fn serial(s: tokio_serial::SerialStream) -> Line {
        Line(Arc::new(Mutex::new(Port::Serial(s))))
    }

    fn port(&self) -> MutexGuard<'_, Port> {
        // Only the link thread uses it, one poll at a time: a poisoned lock is still usable.
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Drop whatever was received and not read: bytes dropped (serial: as reported waiting).
    pub fn drain(&self) -> usize {
        match &mut *self.port() {
            Port::Tcp(s) => {
                let mut buf = [0u8; 256];
                let mut n = 0;
                while let Ok(k @ 1..) = s.try_read(&mut buf) {
                    n += k;
                }
                n
            }
            Port::Serial(s) => {
                use tokio_serial::SerialPort;
                let n = s.bytes_to_read().unwrap_or(0) as usize;
                if n > 0 {
                    let _ = s.clear(tokio_serial::ClearBuffer::Input);
                }
                n
            }
        }
    }
}

impl AsyncRead for Line {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        match &mut *self.port() {
            Port::Tcp(s) => Pin::new(s).poll_read(cx, buf),
            Port::Serial(s) => Pin::new(s).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Line {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, data: &[u8]) -> Poll<io::Result<usize>> {
        match &mut *self.port() {
            Port::Tcp(s) => Pin::new(s).poll_write(cx, data),
            Port::Serial(s) => Pin::new(s).poll_write(cx, data),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut *self.port() {
            Port::Tcp(s) => Pin::new(s).poll_flush(cx),
            Port::Serial(s) => Pin::new(s).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut *self.port() {
            Port::Tcp(s) => Pin::new(s).poll_shutdown(cx),
            Port::Serial(s) => Pin::new(s).poll_shutdown(cx),
        }
    }
}
