//! A Modbus TCP I/O unit (`[io.devices.*] modbus = "host:port"`): discrete inputs (FC02)
//! read and coils (FC15) written every `poll_ms` on a thread of its own, exchanged with the
//! cycle loop through atomics (the cycle never waits for the unit). A request that fails or
//! is not answered within 3 poll periods (at least 100 ms) ends the exchange: the next
//! [`ModbusIo::inputs`] is alarm 2603, and the machine stops.

use crate::io::DeviceKind;
use crate::Alarm;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio_modbus::client::{Reader, Writer};
use tokio_modbus::prelude::SlaveContext;

#[derive(Default)]
struct Shared {
    inputs: AtomicU32,
    outputs: AtomicU32,
    have: AtomicBool,
    failed: AtomicBool,
    why: Mutex<String>,
    stop: AtomicBool,
}

/// The cycle loop's handle; dropping it stops the thread.
pub struct ModbusIo {
    shared: Arc<Shared>,
    name: String,
}

impl Drop for ModbusIo {
    fn drop(&mut self) {
        self.shared.stop.store(true, Relaxed);
    }
}

impl ModbusIo {
    /// Start polling the unit `kind` (a `DeviceKind::ModbusTcp`).
    pub fn start(name: &str, kind: &DeviceKind, inputs: u8, outputs: u8) -> Result<ModbusIo, Alarm> {
        let DeviceKind::ModbusTcp { address, unit, first_input, first_output, poll_ms } = kind.clone() else {
            return Err(Alarm::new(crate::alarm::CONFIG, format!("io.devices.{name}: not a Modbus unit")));
        };
        let shared = Arc::new(Shared::default());
        let s = shared.clone();
        let period = Duration::from_millis(poll_ms as u64);
        let timeout = (period * 3).max(Duration::from_millis(100));
        let what = format!("io.devices.{name} (Modbus TCP {address}, unit {unit})");
        let w = what.clone();
        std::thread::Builder::new()
            .name(format!("io-{name}"))
            .spawn(move || {
                let fail = |m: String| {
                    if let Ok(mut g) = s.why.lock() {
                        *g = m;
                    }
                    s.failed.store(true, Relaxed);
                };
                let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
                    Ok(rt) => rt,
                    Err(e) => return fail(format!("no runtime: {e}")),
                };
                let r: Result<(), String> = rt.block_on(async {
                    let sa = tokio::net::lookup_host(&address).await.map_err(|e| e.to_string())?.next().ok_or("no address")?;
                    let mut ctx = tokio::time::timeout(timeout.max(Duration::from_millis(500)), tokio_modbus::client::tcp::connect(sa))
                        .await
                        .map_err(|_| "connect timed out".to_string())?
                        .map_err(|e| format!("connect: {e}"))?;
                    ctx.set_slave(tokio_modbus::Slave(unit));
                    let mut coils = vec![false; outputs as usize];
                    while !s.stop.load(Relaxed) {
                        let t0 = tokio::time::Instant::now();
                        let o = s.outputs.load(Relaxed);
                        for (k, c) in coils.iter_mut().enumerate() {
                            *c = o >> k & 1 == 1;
                        }
                        let io = async {
                            ctx.write_multiple_coils(first_output, &coils).await.map_err(|e| e.to_string())?.map_err(|e| format!("exception {e}"))?;
                            ctx.read_discrete_inputs(first_input, inputs as u16)
                                .await
                                .map_err(|e| e.to_string())?
                                .map_err(|e| format!("exception {e}"))
                        };
                        let bits = tokio::time::timeout(timeout, io).await.map_err(|_| format!("no answer within {} ms", timeout.as_millis()))??;
                        let v = bits.iter().take(32).enumerate().fold(0u32, |v, (k, b)| v | (*b as u32) << k);
                        s.inputs.store(v, Relaxed);
                        s.have.store(true, Relaxed);
                        tokio::time::sleep_until(t0 + period).await;
                    }
                    Ok(())
                });
                if let Err(e) = r {
                    fail(e);
                }
            })
            .map_err(|e| Alarm::new(crate::alarm::NO_THREAD, format!("{what}: cannot start its thread: {e}")))?;
        Ok(ModbusIo { shared, name: w })
    }

    /// The inputs as last read (None before the first answer); Err once the unit failed.
    pub fn inputs(&self) -> Result<Option<u32>, Alarm> {
        if self.shared.failed.load(Relaxed) {
            let why = self.shared.why.lock().map(|g| g.clone()).unwrap_or_default();
            return Err(Alarm::new(
                crate::alarm::IO_DEVICE,
                format!("I/O unit {}: {why}; the machine was stopped. Check the unit's power, network and address", self.name),
            ));
        }
        Ok(self.shared.have.load(Relaxed).then(|| self.shared.inputs.load(Relaxed)))
    }

    /// The coils for the next exchange.
    pub fn set_outputs(&self, bits: u32) {
        self.shared.outputs.store(bits, Relaxed);
    }

    /// Wait (wall time, at most `ms`) for the first answer: start-up, before the first cycle.
    pub fn wait_first(&self, ms: u64) -> Result<(), Alarm> {
        let t = std::time::Instant::now();
        while t.elapsed() < Duration::from_millis(ms) {
            if self.inputs()?.is_some() {
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(2));
        }
        Err(Alarm::new(
            crate::alarm::IO_DEVICE,
            format!("I/O unit {}: no answer within {ms} ms of start-up; check its power, network and address", self.name),
        ))
    }
}
