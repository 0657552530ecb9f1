//! SocketCAN (can0, vcan0) through `socketcan::tokio::CanSocket`, in a thin task on a
//! current-thread runtime of its own, so that the synchronous cycle loop only touches
//! bounded, pre-allocated channels.

use super::{BusError, CanBus};
use crate::frame::CanFrame;
use std::sync::mpsc;
use std::time::Duration;

pub struct SocketCan {
    name: String,
    rx: mpsc::Receiver<Result<CanFrame, BusError>>,
    tx: tokio::sync::mpsc::Sender<CanFrame>,
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
    let mut out = CanFrame {
        id: f.raw_id(),
        extended: f.is_extended(),
        rtr: f.is_remote_frame(),
        len: f.dlc().min(8) as u8,
        data: [0; 8],
    };
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
        let (rx_tx, rx) = mpsc::sync_channel::<Result<CanFrame, BusError>>(4096);
        let (tx, mut tx_rx) = tokio::sync::mpsc::channel::<CanFrame>(4096);
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<(), BusError>>(1);
        let n2 = name.clone();
        std::thread::Builder::new()
            .name(format!("can-{iface}"))
            .spawn(move || {
                let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = ready_tx.send(Err(BusError::Open { bus: n2, reason: e.to_string() }));
                        return;
                    }
                };
                rt.block_on(async move {
                    use futures_util::{SinkExt, StreamExt};
                    let sock = match socketcan::tokio::CanSocket::open(&n2) {
                        Ok(s) => s,
                        Err(e) => {
                            let reason = if e.raw_os_error() == Some(97) {
                                "this kernel has no SocketCAN (socket(AF_CAN) fails with EAFNOSUPPORT); use --bus inproc or a machine with CAN support".to_string()
                            } else {
                                format!("{e}; bring it up first, e.g. `ip link set {n2} up type can bitrate 1000000` (or `modprobe vcan; ip link add {n2} type vcan; ip link set {n2} up`)")
                            };
                            let _ = ready_tx.send(Err(BusError::Open { bus: n2, reason }));
                            return;
                        }
                    };
                    let _ = ready_tx.send(Ok(()));
                    let (mut sink, mut stream) = sock.split();
                    let bus = n2.clone();
                    let reader = async {
                        while let Some(r) = stream.next().await {
                            let item = match r {
                                Ok(f) => match from_sc(&f) {
                                    Some(f) => Ok(f),
                                    None => continue,
                                },
                                Err(e) => Err(BusError::Io { bus: bus.clone(), reason: e.to_string() }),
                            };
                            let fatal = item.is_err();
                            if rx_tx.send(item).is_err() || fatal {
                                break;
                            }
                        }
                    };
                    let writer = async {
                        while let Some(f) = tx_rx.recv().await {
                            if let Some(sf) = to_sc(&f) {
                                if sink.send(sf).await.is_err() {
                                    break;
                                }
                            }
                        }
                    };
                    tokio::select! { _ = reader => {}, _ = writer => {} }
                });
            })
            .map_err(|e| BusError::Open { bus: name.clone(), reason: e.to_string() })?;
        match ready_rx.recv() {
            Ok(Ok(())) => Ok(SocketCan { name, rx, tx }),
            Ok(Err(e)) => Err(e),
            Err(_) => Err(BusError::Open { bus: name, reason: "transport thread ended".into() }),
        }
    }
}

impl CanBus for SocketCan {
    fn send(&mut self, frame: &CanFrame) -> Result<(), BusError> {
        self.tx.try_send(*frame).map_err(|e| match e {
            tokio::sync::mpsc::error::TrySendError::Full(_) => {
                BusError::Io { bus: self.name.clone(), reason: "transmit queue full".into() }
            }
            tokio::sync::mpsc::error::TrySendError::Closed(_) => BusError::Closed { bus: self.name.clone() },
        })
    }

    fn try_recv(&mut self) -> Result<Option<CanFrame>, BusError> {
        match self.rx.try_recv() {
            Ok(r) => r.map(Some),
            Err(mpsc::TryRecvError::Empty) => Ok(None),
            Err(mpsc::TryRecvError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<CanFrame>, BusError> {
        match self.rx.recv_timeout(timeout) {
            Ok(r) => r.map(Some),
            Err(mpsc::RecvTimeoutError::Timeout) => Ok(None),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(BusError::Closed { bus: self.name.clone() }),
        }
    }

    fn name(&self) -> &str {
        &self.name
    }
}
