//! How much faster than real time the default machine's drives simulate: 3 drives, CSP,
//! a 2 ms SYNC with RPDOs and TPDOs every cycle, all axes moving.
//!
//!     cargo run --release -p sim-drives --example sim_speed

use cncgw_bus::canopen::{nmt::NmtCommand, sync_frame};
use cncgw_bus::cia402::State;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::{CanBus, CanFrame, Clock};
use sim_drives::{SimConfig, SimWorld};

fn main() {
    let bus = InprocBus::new();
    let mut m = bus.endpoint();
    let mut w = SimWorld::new(&bus, SimConfig::default_lathe());
    let cycle = 2_000_000u64;
    w.wait_until(10_000_000);
    for n in 1..=3u8 {
        // CSP: 2F 60 60 00 08.
        m.send(&CanFrame::new(0x600 + n as u16, &[0x2F, 0x60, 0x60, 0, 8, 0, 0, 0])).unwrap();
    }
    m.send(&NmtCommand::Start.frame(0)).unwrap();
    let sim_s = 60.0;
    let cycles = (sim_s / 2e-3) as u64;
    let mut cw = [0u16; 4];
    let start = std::time::Instant::now();
    for k in 0..cycles {
        let t = k as f64 * 2e-3;
        for n in 1..=3u8 {
            // A slow sine on each axis once enabled.
            let target = if cw[n as usize] == 0x0F { (20_000.0 * (1.0 - (t * 2.0).cos())) as i32 } else { 0 };
            let mut d = [0u8; 6];
            d[..2].copy_from_slice(&cw[n as usize].to_le_bytes());
            d[2..].copy_from_slice(&target.to_le_bytes());
            m.send(&CanFrame::new(0x200 + n as u16, &d)).unwrap();
        }
        m.send(&sync_frame(None)).unwrap();
        let now = w.now_ns();
        w.wait_until(now + cycle);
        while let Ok(Some(f)) = m.try_recv() {
            let id = f.cob_id();
            if (0x181..=0x183).contains(&id) {
                let s = u16::from_le_bytes([f.data[0], f.data[1]]);
                let st = State::from_statusword(s);
                cw[(id - 0x180) as usize] = st.controlword_towards(State::OperationEnabled);
            }
        }
    }
    let wall = start.elapsed().as_secs_f64();
    for d in w.drives() {
        println!("node {}: {:?}, position {} counts, following error {} counts", d.node(), d.state(), d.position_actual(), d.following_error());
    }
    println!("{sim_s} s simulated in {wall:.3} s wall: {:.0}× real time ({} frames on the bus)", sim_s / wall, bus.frames_sent());
}
