//! CANopen figures on the in-process bus with the emulated drives (sim-drives):
//! SDO round trips per second, and the time from start to every drive in Operation Enabled.
//!
//! `cargo bench --bench canopen` prints them. Simulated time advances in 200 µs polling steps
//! (like the master's real-time polling), so "per second" is wall-clock throughput of the
//! whole stack: SDO client, bus, emulated SDO server and physics stepping.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use std::time::Instant;

fn world() -> (MachineConfig, InprocBus, sim_drives::SimWorld) {
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let w = sim_drives::SimWorld::new(&bus, sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    (cfg, bus, w)
}

fn main() {
    // Start-up to Operation Enabled, 3 drives.
    let mut wall = Vec::new();
    let mut sim = Vec::new();
    for _ in 0..20 {
        let (cfg, bus, mut w) = world();
        let t = Instant::now();
        let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
        m.startup(&mut w).expect("startup");
        let mut next = w.now_ns();
        loop {
            next += 2_000_000;
            w.wait_until(next);
            m.receive(next).unwrap();
            let done = m.enable_step().unwrap();
            m.transmit(next).unwrap();
            if done {
                break;
            }
        }
        wall.push(t.elapsed().as_secs_f64());
        sim.push(w.now_ns() as f64 * 1e-9);
    }
    wall.sort_by(f64::total_cmp);
    sim.sort_by(f64::total_cmp);
    println!(
        "start to all 3 drives Operation Enabled (in-process bus): wall median {:.2} ms (min {:.2}, max {:.2}); bus time {:.1} ms",
        wall[wall.len() / 2] * 1e3,
        wall[0] * 1e3,
        wall[wall.len() - 1] * 1e3,
        sim[sim.len() / 2] * 1e3
    );

    // SDO expedited round trips.
    let (cfg, bus, mut w) = world();
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("startup");
    let n = 20_000;
    let t = Instant::now();
    for _ in 0..n {
        let v = m.sdo_read(&mut w, 1, 0x1000, 0).unwrap();
        assert_eq!(v.len(), 4);
    }
    let dt = t.elapsed().as_secs_f64();
    println!("SDO expedited upload round trips (in-process bus): {:.0} per second wall ({n} in {:.3} s)", n as f64 / dt, dt);
    let t = Instant::now();
    for _ in 0..2_000 {
        m.sdo_read(&mut w, 1, 0x1008, 0).unwrap();
    }
    let dt = t.elapsed().as_secs_f64();
    println!("SDO segmented upload of 0x1008 (in-process bus): {:.0} per second wall", 2_000.0 / dt);
}
