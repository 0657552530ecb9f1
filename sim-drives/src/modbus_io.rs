//! An emulated Modbus TCP I/O unit: coils (outputs, FC01 read / FC05 / FC15 write) and
//! discrete inputs (FC02), the inputs made by the same wiring as the CiA 401 module's
//! (`io401::Wiring`: on from the start, following a coil after a delay, timed events), in
//! real time from the server's start. Any unit id is answered (one unit per address).

use crate::io401::{IoEmulation, Wiring};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

struct Unit {
    wiring: Mutex<Wiring>,
    t0: Instant,
}

impl Unit {
    fn now(&self) -> u64 {
        self.t0.elapsed().as_nanos() as u64
    }
}

/// The server; its threads end when `stop` is set.
pub struct IoServer {
    pub addr: std::net::SocketAddr,
    unit: Arc<Unit>,
}

impl IoServer {
    /// The coils as last written.
    pub fn outputs(&self) -> u32 {
        self.unit.wiring.lock().map(|w| w.outputs()).unwrap_or(0)
    }
    /// Force a discrete input (None: back to the wiring).
    pub fn force(&self, bit: u8, v: Option<bool>) {
        if let Ok(mut w) = self.unit.wiring.lock() {
            w.force(bit, v);
        }
    }
}

/// Serve a unit with `emu`'s wiring on `addr` until `stop`.
pub fn serve(addr: &str, emu: IoEmulation, stop: Arc<AtomicBool>) -> std::io::Result<IoServer> {
    let l = TcpListener::bind(addr)?;
    l.set_nonblocking(true)?;
    let unit = Arc::new(Unit { wiring: Mutex::new(Wiring::new(emu)), t0: Instant::now() });
    let server = IoServer { addr: l.local_addr()?, unit: unit.clone() };
    tracing::info!("Modbus I/O unit on {}", server.addr);
    std::thread::Builder::new().name("modbus-io".into()).spawn(move || {
        while !stop.load(Ordering::Relaxed) {
            match l.accept() {
                Ok((s, _)) => {
                    let (u, st) = (unit.clone(), stop.clone());
                    let _ = std::thread::Builder::new().name("modbus-io-conn".into()).spawn(move || connection(s, &u, &st));
                }
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    })?;
    Ok(server)
}

fn connection(mut s: TcpStream, u: &Unit, stop: &AtomicBool) {
    let _ = s.set_read_timeout(Some(Duration::from_millis(100)));
    let _ = s.set_nodelay(true);
    let mut head = [0u8; 7];
    while !stop.load(Ordering::Relaxed) {
        match s.read_exact(&mut head) {
            Ok(()) => {}
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => continue,
            Err(_) => return,
        }
        let len = u16::from_be_bytes([head[4], head[5]]) as usize;
        let mut pdu = vec![0u8; len.saturating_sub(1)];
        if s.read_exact(&mut pdu).is_err() || pdu.is_empty() {
            return;
        }
        let resp = answer(&pdu, u);
        let mut out = Vec::with_capacity(7 + resp.len());
        out.extend_from_slice(&head[..4]);
        out.extend_from_slice(&((resp.len() + 1) as u16).to_be_bytes());
        out.push(head[6]);
        out.extend_from_slice(&resp);
        if s.write_all(&out).is_err() {
            return;
        }
    }
}

fn bits_reply(fc: u8, v: u32, first: u16, n: u16) -> Vec<u8> {
    let bytes = n.div_ceil(8) as usize;
    let mut r = vec![fc, bytes as u8];
    for b in 0..bytes {
        let mut byte = 0u8;
        for k in 0..8 {
            let i = first as u32 + (b * 8 + k) as u32;
            if (b * 8 + k) < n as usize && i < 32 && v >> i & 1 == 1 {
                byte |= 1 << k;
            }
        }
        r.push(byte);
    }
    r
}

fn answer(pdu: &[u8], u: &Unit) -> Vec<u8> {
    let fc = pdu[0];
    let word = |i: usize| pdu.get(i..i + 2).map(|b| u16::from_be_bytes([b[0], b[1]]));
    let (Some(a), Some(n)) = (word(1), word(3)) else { return vec![fc | 0x80, 3] };
    let now = u.now();
    let Ok(mut w) = u.wiring.lock() else { return vec![fc | 0x80, 4] };
    match fc {
        0x01 if a as u32 + n as u32 <= 32 => bits_reply(fc, w.outputs(), a, n),
        0x02 if a as u32 + n as u32 <= 32 => bits_reply(fc, w.inputs(now), a, n),
        0x05 if a < 32 => {
            let o = if n == 0xFF00 { w.outputs() | 1 << a } else { w.outputs() & !(1 << a) };
            w.set_outputs(o, now);
            pdu[..5].to_vec()
        }
        0x0F if a as u32 + n as u32 <= 32 => {
            let mut o = w.outputs();
            for k in 0..n {
                let on = pdu.get(6 + k as usize / 8).is_some_and(|b| b >> (k % 8) & 1 == 1);
                let bit = 1u32 << (a + k);
                o = if on { o | bit } else { o & !bit };
            }
            w.set_outputs(o, now);
            pdu[..5].to_vec()
        }
        0x01 | 0x02 | 0x05 | 0x0F => vec![fc | 0x80, 2],
        _ => vec![fc | 0x80, 1],
    }
}
