//! CANopen figures on the in-process bus with the emulated drives (sim-drives):
//! SDO round trips per second, the time from start to every drive in Operation Enabled, and
//! SDO block vs segmented upload throughput (simulated time and, over socketcand on
//! 127.0.0.1 against sim-drives' server, real time).
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

    block_vs_segmented();
}

/// Bytes per second of one 4096-byte upload of the DOMAIN 0x2200, block and segmented.
fn throughput(m: &mut CanOpenMaster<impl cncgw_bus::CanBus>, clock: &mut dyn Clock, reps: usize) -> (f64, f64, f64, f64) {
    use sim_drives::drive::{USER_DATA, USER_DATA_LEN};
    let data: Vec<u8> = (0..USER_DATA_LEN).map(|i| (i * 13) as u8).collect();
    m.sdo_block_download(clock, 1, USER_DATA, 0, &data).expect("block download");
    let mut run = |block: bool, clock: &mut dyn Clock| {
        let (t0, w0) = (clock.now_ns(), Instant::now());
        for _ in 0..reps {
            let got = if block { m.sdo_block_upload(clock, 1, USER_DATA, 0) } else { m.sdo_upload(clock, 1, USER_DATA, 0) };
            assert_eq!(got.expect("upload"), data);
        }
        let bytes = (reps * USER_DATA_LEN) as f64;
        (bytes / ((clock.now_ns() - t0) as f64 * 1e-9), bytes / w0.elapsed().as_secs_f64())
    };
    let (b_clock, b_wall) = run(true, clock);
    let (s_clock, s_wall) = run(false, clock);
    (b_clock, b_wall, s_clock, s_wall)
}

fn block_vs_segmented() {
    let (cfg, bus, mut w) = world();
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("startup");
    let (b, bw, s, sw) = throughput(&mut m, &mut w, 50);
    println!(
        "SDO upload of 4096 bytes (in-process bus, simulated time, master polling every 200 µs): block {:.0} B/s, segmented {:.0} B/s (×{:.1}); wall {:.0} vs {:.0} B/s",
        b, s, b / s, bw, sw
    );

    // Real time over socketcand: sim-drives' server on a free port, our socketcand client.
    let server = match sim_drives::socketcand::SocketcandServer::bind("127.0.0.1:0", "can0") {
        Ok(s) => s,
        Err(e) => return println!("socketcand figure skipped: {e}"),
    };
    let addr = server.local_addr().to_string();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let st = stop.clone();
    let sim =
        std::thread::spawn(move || sim_drives::run_realtime(Box::new(server), sim_drives::SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap(), st));
    let sock = cncgw_bus::transport::socketcand::Socketcand::connect(&addr, "can0").expect("connect to the socketcand server");
    let mut m = CanOpenMaster::new(sock, &cfg);
    let mut clock = cncgw_bus::RealClock::new();
    m.nmt_command(0, cncgw_bus::canopen::nmt::NmtCommand::ResetCommunication).unwrap();
    assert!(m.wait_boot(&mut clock, 5000), "drives boot over socketcand");
    let (b, _, s, _) = throughput(&mut m, &mut clock, 5);
    println!("SDO upload of 4096 bytes over socketcand (127.0.0.1, real time): block {:.0} B/s, segmented {:.0} B/s (×{:.1})", b, s, b / s);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let _ = sim.join();
}
