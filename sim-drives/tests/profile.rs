//! Profile position (mode 1) seen from a test master on the in-process bus in simulated
//! time, all by SDO: the set-point handshake, buffered and immediate set-points, the
//! velocity and acceleration of the drive's own trapezoid.

use cncgw_bus::canopen::nmt::NmtCommand;
use cncgw_bus::canopen::sdo::{SdoRequest, SdoResponse};
use cncgw_bus::cia402::sw;
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{CanBus, Clock};
use sim_drives::{DriveConfig, DriveKind, SimConfig, SimWorld};

const MS: u64 = 1_000_000;

struct Rig {
    m: InprocEndpoint,
    w: SimWorld,
}

impl Rig {
    fn new() -> Rig {
        let bus = InprocBus::new();
        let m = bus.endpoint();
        let cfg = SimConfig { drives: vec![DriveConfig::new(1, DriveKind::Linear, "x", 10000.0)], step_us: 50 };
        let w = SimWorld::new(&bus, cfg);
        let mut r = Rig { m, w };
        r.run(10 * MS);
        r
    }

    fn run(&mut self, dt: u64) {
        let t = self.w.now_ns() + dt;
        self.w.wait_until(t);
        while self.m.try_recv().unwrap().is_some() {}
    }

    fn sdo(&mut self, req: SdoRequest) -> SdoResponse {
        self.m.send(&req.encode(1)).unwrap();
        let t = self.w.now_ns() + MS;
        self.w.wait_until(t);
        let mut answer = None;
        while let Some(f) = self.m.try_recv().unwrap() {
            if f.cob_id() == 0x581 {
                answer = SdoResponse::decode(&f);
            }
        }
        answer.expect("an SDO answer within 1 ms")
    }

    fn write(&mut self, index: u16, sub: u8, v: &[u8]) {
        let mut data = [0u8; 4];
        data[..v.len()].copy_from_slice(v);
        let r = self.sdo(SdoRequest::InitiateDownload { index, sub, expedited: true, size: Some(v.len() as u32), data });
        assert_eq!(r, SdoResponse::InitiateDownload { index, sub }, "write 0x{index:04X}:{sub}");
    }

    fn cw(&mut self, c: u16) {
        self.write(0x6040, 0, &c.to_le_bytes());
    }

    fn status(&mut self) -> u16 {
        match self.sdo(SdoRequest::InitiateUpload { index: 0x6041, sub: 0 }) {
            SdoResponse::InitiateUpload { data, .. } => u16::from_le_bytes([data[0], data[1]]),
            r => panic!("{r:?}"),
        }
    }

    fn pos(&self) -> i64 {
        self.w.drive(1).unwrap().position_unwrapped()
    }

    /// Run until bit 10 is set, sampling the largest speed; (time ms, max |speed|).
    fn until_reached(&mut self, max_ms: u64) -> (u64, f64) {
        let t0 = self.w.now_ns();
        let mut vmax: f64 = 0.0;
        for _ in 0..max_ms {
            self.run(MS);
            vmax = vmax.max((self.w.drive(1).unwrap().velocity_actual() as f64).abs());
            if self.w.drive(1).unwrap().statusword() & sw::TARGET_REACHED != 0 {
                return ((self.w.now_ns() - t0) / MS, vmax);
            }
        }
        panic!("target not reached within {max_ms} ms");
    }
}

fn enabled_pp() -> Rig {
    let mut r = Rig::new();
    r.m.send(&NmtCommand::Start.frame(1)).unwrap();
    r.run(MS);
    r.write(0x6060, 0, &[1]);
    r.write(0x6081, 0, &20_000u32.to_le_bytes()); // 2 mm/s
    r.write(0x6083, 0, &200_000u32.to_le_bytes());
    r.write(0x6084, 0, &400_000u32.to_le_bytes());
    for c in [0x06, 0x07, 0x0F] {
        r.cw(c);
    }
    assert_eq!(r.w.drive(1).unwrap().mode_display(), 1);
    r
}

#[test]
fn set_point_handshake_and_trapezoid() {
    let mut r = enabled_pp();
    let p0 = r.pos();
    assert_ne!(r.status() & sw::TARGET_REACHED, 0, "at rest: target reached");
    r.write(0x607A, 0, &((p0 + 10_000) as i32).to_le_bytes());
    r.cw(0x1F);
    let s = r.status();
    assert_ne!(s & sw::OMS12, 0, "set-point acknowledged");
    assert_eq!(s & sw::TARGET_REACHED, 0, "moving");
    r.cw(0x0F);
    assert_eq!(r.status() & sw::OMS12, 0, "acknowledge drops with bit 4");
    // 10000 counts at 20000 counts/s, up at 200000 counts/s² (0.1 s), down at 400000 (0.05 s):
    // 0.5 s + (0.1 + 0.05) / 2 = 0.575 s.
    let (ms, vmax) = r.until_reached(2000);
    assert!((560..=640).contains(&ms), "reached after {ms} ms");
    assert!(vmax <= 20_000.0 * 1.05 && vmax > 20_000.0 * 0.9, "peak speed {vmax} counts/s");
    assert!((r.pos() - (p0 + 10_000)).abs() <= 10, "at {} of {}", r.pos(), p0 + 10_000);
    // Relative (bit 6): 2500 counts back from the last target.
    r.write(0x607A, 0, &(-2500i32).to_le_bytes());
    r.cw(0x5F);
    r.cw(0x4F);
    r.until_reached(1000);
    assert!((r.pos() - (p0 + 7_500)).abs() <= 10);
}

#[test]
fn buffered_and_immediate_set_points() {
    let mut r = enabled_pp();
    let p0 = r.pos();
    r.write(0x607A, 0, &((p0 + 4_000) as i32).to_le_bytes());
    r.cw(0x1F);
    r.cw(0x0F);
    // A second set-point while moving, without "change immediately": buffered; the
    // acknowledge stays up while the buffer is full.
    r.write(0x607A, 0, &((p0 + 8_000) as i32).to_le_bytes());
    r.cw(0x1F);
    r.cw(0x0F);
    assert_ne!(r.status() & sw::OMS12, 0, "buffer full: bit 12 stays set");
    // A third is refused while the buffer is full.
    r.write(0x607A, 0, &((p0 + 50_000) as i32).to_le_bytes());
    r.cw(0x1F);
    r.cw(0x0F);
    r.until_reached(3000);
    assert!((r.pos() - (p0 + 8_000)).abs() <= 10, "both buffered moves, not the refused one: at {}", r.pos() - p0);
    assert_eq!(r.status() & sw::OMS12, 0);

    // Change immediately (bit 5): a far target replaced mid-way by a near one.
    r.write(0x607A, 0, &((p0 + 100_000) as i32).to_le_bytes());
    r.cw(0x3F);
    r.cw(0x2F);
    r.run(100 * MS);
    r.write(0x607A, 0, &((p0 + 10_000) as i32).to_le_bytes());
    r.cw(0x3F);
    r.cw(0x2F);
    r.until_reached(2000);
    assert!((r.pos() - (p0 + 10_000)).abs() <= 10, "at {}", r.pos() - p0);
}

#[test]
fn halt_stops_a_profile_move() {
    let mut r = enabled_pp();
    let p0 = r.pos();
    r.write(0x607A, 0, &((p0 + 100_000) as i32).to_le_bytes());
    r.cw(0x1F);
    r.cw(0x0F);
    r.run(200 * MS);
    r.cw(0x10F); // halt
    r.run(200 * MS);
    let p = r.pos();
    assert!(p - p0 > 2_000 && p - p0 < 6_000, "stopped at {}", p - p0);
    assert_ne!(r.status() & sw::TARGET_REACHED, 0, "halted at rest: bit 10");
    r.run(100 * MS);
    assert_eq!(r.pos(), p, "stays stopped");
}
