//! What publishing the OPC UA snapshot costs the cycle thread (`control::snapshot`): the time
//! of one `Snapshot::publish` of a full record (8 drives), alone and with readers copying it
//! as fast as they can (far more often than the server's 50 ms task), and how often a
//! reader had to retry. A figure for the README, not a test.
//!
//!     cargo run --release --example snapshot_cost

use cncgw::control::snapshot::{AxisSnap, MachineSnap, MachineState, Snapshot, SNAP_AXES};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

fn record(k: u64) -> MachineSnap {
    let mut s = MachineSnap { cycle: k, state: MachineState::Running, line: k as u32, blocks: k, n_axes: SNAP_AXES as u8, ..Default::default() };
    for (d, a) in s.axes.iter_mut().enumerate() {
        *a = AxisSnap { cmd: k as f64 + d as f64, act: k as f64, ferr: 1e-3, statusword: 0x1237 };
    }
    s
}

/// ns per publish over `n` publishes, and the p99 of batches of 100.
fn measure(snap: &Snapshot, n: u64) -> (f64, f64) {
    let mut batches = Vec::with_capacity((n / 100) as usize);
    let t0 = Instant::now();
    for b in 0..n / 100 {
        let t = Instant::now();
        for k in 0..100 {
            snap.publish(std::hint::black_box(&record(b * 100 + k)));
        }
        batches.push(t.elapsed().as_nanos() as f64 / 100.0);
    }
    let mean = t0.elapsed().as_nanos() as f64 / n as f64;
    batches.sort_by(f64::total_cmp);
    (mean, batches[batches.len() * 99 / 100])
}

fn main() {
    let n = 2_000_000;
    let snap = Arc::new(Snapshot::new());
    let (mean, p99) = measure(&snap, n);
    println!("publish alone:            {mean:6.1} ns mean, {p99:6.1} ns p99 (batches of 100)");
    for readers in [1usize, 10] {
        let stop = Arc::new(AtomicBool::new(false));
        let reads = Arc::new(AtomicU64::new(0));
        let hs: Vec<_> = (0..readers)
            .map(|_| {
                let (s, stop, reads) = (snap.clone(), stop.clone(), reads.clone());
                std::thread::spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        std::hint::black_box(s.read());
                        reads.fetch_add(1, Ordering::Relaxed);
                    }
                })
            })
            .collect();
        let (mean, p99) = measure(&snap, n);
        stop.store(true, Ordering::Relaxed);
        for h in hs {
            let _ = h.join();
        }
        println!("publish with {readers:2} reader(s): {mean:6.1} ns mean, {p99:6.1} ns p99; {} reads meanwhile", reads.load(Ordering::Relaxed));
    }
    println!("MachineSnap: {} bytes", std::mem::size_of::<MachineSnap>());
}
