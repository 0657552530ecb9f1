//! Faults injected at run time by SDO writes to the manufacturer record 0x2100, seen from
//! a test master on the in-process bus in simulated time.

use cncgw_bus::canopen::nmt::NmtCommand;
use cncgw_bus::canopen::sdo::{SdoRequest, SdoResponse};
use cncgw_bus::canopen::{emcy::Emcy, sync_frame};
use cncgw_bus::cia402::{sw, State};
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{CanBus, CanFrame, Clock};
use sim_drives::drive::{fault_sub as fs, SIM_FAULTS};
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

    fn run(&mut self, dt: u64) -> Vec<CanFrame> {
        let t = self.w.now_ns() + dt;
        self.w.wait_until(t);
        let mut got = Vec::new();
        while let Some(f) = self.m.try_recv().unwrap() {
            got.push(f);
        }
        got
    }

    /// Expedited download; `None` if the node did not answer within 1 ms.
    fn write(&mut self, index: u16, sub: u8, v: u32, len: usize) -> Option<Result<(), u32>> {
        let mut d = [0u8; 4];
        d[..len].copy_from_slice(&v.to_le_bytes()[..len]);
        let req = SdoRequest::InitiateDownload { index, sub, expedited: true, size: Some(len as u32), data: d };
        self.m.send(&req.encode(1)).unwrap();
        let got = self.run(MS);
        got.iter().find(|f| f.cob_id() == 0x581).and_then(SdoResponse::decode).map(|r| match r {
            SdoResponse::InitiateDownload { .. } => Ok(()),
            SdoResponse::Abort { code, .. } => Err(code),
            r => panic!("unexpected {r:?}"),
        })
    }

    fn fault(&mut self, sub: u8, v: u32, len: usize) -> Vec<CanFrame> {
        let mut d = [0u8; 4];
        d[..len].copy_from_slice(&v.to_le_bytes()[..len]);
        let req = SdoRequest::InitiateDownload { index: SIM_FAULTS, sub, expedited: true, size: Some(len as u32), data: d };
        self.m.send(&req.encode(1)).unwrap();
        let got = self.run(MS);
        let ans = got.iter().find(|f| f.cob_id() == 0x581).and_then(SdoResponse::decode);
        assert!(matches!(ans, Some(SdoResponse::InitiateDownload { .. })), "0x2100:{sub} = {v} accepted: {ans:?}");
        got
    }

    fn read(&mut self, index: u16, sub: u8) -> u32 {
        self.m.send(&SdoRequest::InitiateUpload { index, sub }.encode(1)).unwrap();
        let got = self.run(MS);
        match got.iter().find(|f| f.cob_id() == 0x581).and_then(SdoResponse::decode) {
            Some(SdoResponse::InitiateUpload { data, .. }) => u32::from_le_bytes(data),
            r => panic!("read 0x{index:04X}:{sub}: {r:?}"),
        }
    }

    /// RPDO1 + SYNC, wait `dt`; TPDO1 of node 1 if it came.
    fn cycle(&mut self, cwd: u16, target: i32, dt: u64) -> Option<(u16, i32)> {
        let mut d = [0u8; 6];
        d[..2].copy_from_slice(&cwd.to_le_bytes());
        d[2..].copy_from_slice(&target.to_le_bytes());
        self.m.send(&CanFrame::new(0x201, &d)).unwrap();
        self.m.send(&sync_frame(None)).unwrap();
        self.run(dt).iter().find(|f| f.cob_id() == 0x181).map(|f| {
            let d = f.data();
            (u16::from_le_bytes([d[0], d[1]]), i32::from_le_bytes([d[2], d[3], d[4], d[5]]))
        })
    }

    fn enable(&mut self) {
        assert_eq!(self.write(0x6060, 0, 8, 1), Some(Ok(())));
        self.m.send(&NmtCommand::Start.frame(1)).unwrap();
        self.run(MS);
        let target = self.w.drive(1).unwrap().position_actual();
        let mut cwd = 0u16;
        for _ in 0..20 {
            let (s, _) = self.cycle(cwd, target, 2 * MS).expect("TPDO1");
            let st = State::from_statusword(s);
            if st == State::OperationEnabled {
                return;
            }
            cwd = st.controlword_towards(State::OperationEnabled);
        }
        panic!("not enabled");
    }

    fn state(&self) -> State {
        self.w.drive(1).unwrap().state()
    }

    /// Fault reset through the controlword (rising edge of bit 7) by SDO.
    fn fault_reset(&mut self) {
        assert_eq!(self.write(0x6040, 0, 0x00, 2), Some(Ok(())));
        assert_eq!(self.write(0x6040, 0, 0x80, 2), Some(Ok(())));
        self.run(MS);
    }
}

fn emcy_codes(frames: &[CanFrame]) -> Vec<u16> {
    frames.iter().filter_map(Emcy::decode).filter(|(n, _)| *n == 1).map(|(_, e)| e.code).collect()
}

#[test]
fn raise_any_fault_code_and_overcurrent() {
    let mut r = Rig::new();
    r.enable();
    let got = r.fault(fs::RAISE, 0x4310, 2); // drive temperature
    assert_eq!(emcy_codes(&got), vec![0x4310]);
    r.run(20 * MS);
    assert_eq!(r.state(), State::Fault);
    assert_eq!(r.read(0x603F, 0), 0x4310);
    assert_eq!(r.read(SIM_FAULTS, fs::RAISE), 0x4310, "reads back the last code raised");
    r.fault_reset();
    assert_eq!(r.state(), State::SwitchOnDisabled);
    assert_eq!(r.read(0x603F, 0), 0);

    r.enable();
    let got = r.fault(fs::OVERCURRENT, 1, 1);
    assert_eq!(emcy_codes(&got), vec![0x2310]);
    assert_eq!(r.read(SIM_FAULTS, fs::OVERCURRENT), 0, "a trip, not a lasting condition");
    r.run(20 * MS);
    r.fault_reset();
    assert_eq!(r.state(), State::SwitchOnDisabled, "an overcurrent trip resets");
    // Values outside an object's range abort like any other object.
    assert_eq!(r.write(SIM_FAULTS, fs::OVERCURRENT, 2, 1), Some(Err(0x0609_0031)));
    assert_eq!(r.write(SIM_FAULTS, fs::PDO_DROP_PERMILLE, 1001, 2), Some(Err(0x0609_0031)));
    assert_eq!(r.write(SIM_FAULTS, 12, 0, 1), Some(Err(0x0609_0011)));
}

#[test]
fn encoder_loss_freezes_feedback_and_blocks_reset_until_repaired() {
    let mut r = Rig::new();
    r.enable();
    let p0 = r.w.drive(1).unwrap().position_actual();
    for k in 1..=50 {
        r.cycle(0x0F, p0 + 40 * k, 2 * MS);
    }
    let got = r.fault(fs::ENCODER_LOST, 1, 1);
    assert_eq!(emcy_codes(&got), vec![0x7305]);
    let frozen = r.read(0x6064, 0) as i32;
    r.run(200 * MS);
    assert_eq!(r.state(), State::Fault);
    assert_eq!(r.read(0x6064, 0) as i32, frozen, "no encoder, no new position");
    // The cause is still there: a fault reset is refused and the EMCY repeated.
    r.write(0x6040, 0, 0x00, 2);
    r.m.send(&SdoRequest::InitiateDownload { index: 0x6040, sub: 0, expedited: true, size: Some(2), data: [0x80, 0, 0, 0] }.encode(1)).unwrap();
    assert_eq!(emcy_codes(&r.run(MS)), vec![0x7305]);
    assert_eq!(r.state(), State::Fault);
    // An NMT reset does not repair hardware.
    r.m.send(&NmtCommand::ResetNode.frame(1)).unwrap();
    r.run(20 * MS);
    assert_eq!(r.read(SIM_FAULTS, fs::ENCODER_LOST), 1);
    r.fault(fs::ENCODER_LOST, 0, 1);
    r.fault_reset();
    assert_eq!(r.state(), State::SwitchOnDisabled);
    assert_eq!(r.read(0x603F, 0), 0);
}

#[test]
fn dc_link_undervoltage_clears_voltage_enabled() {
    let mut r = Rig::new();
    r.enable();
    assert_ne!(r.read(0x6041, 0) as u16 & sw::VOLTAGE_ENABLED, 0);
    let got = r.fault(fs::UNDERVOLTAGE, 1, 1);
    assert_eq!(emcy_codes(&got), vec![0x3220]);
    r.run(20 * MS);
    let s = r.read(0x6041, 0) as u16;
    assert_eq!(s & sw::VOLTAGE_ENABLED, 0, "statusword 0x{s:04X}");
    assert_eq!(State::from_statusword(s), State::Fault);
    r.fault_reset();
    assert_eq!(r.state(), State::Fault, "no reset while the DC link is low");
    r.fault(fs::UNDERVOLTAGE, 0, 1);
    r.fault_reset();
    assert_eq!(r.state(), State::SwitchOnDisabled);
    assert_ne!(r.read(0x6041, 0) as u16 & sw::VOLTAGE_ENABLED, 0);
}

#[test]
fn a_jammed_slide_trips_on_following_error() {
    let mut r = Rig::new();
    r.enable();
    // 20 N·m of dry friction: twice the motor's peak torque.
    r.fault(fs::JAM_MNM, 20_000, 4);
    let p0 = r.w.drive(1).unwrap().position_actual();
    let mut emcy = Vec::new();
    for k in 1..=200 {
        let target = p0 + 400 * k; // 200 mm/s... of a slide that cannot move
        r.m.send(&CanFrame::new(0x201, &{
            let mut d = [0u8; 6];
            d[..2].copy_from_slice(&0x0Fu16.to_le_bytes());
            d[2..].copy_from_slice(&target.to_le_bytes());
            d
        }))
        .unwrap();
        r.m.send(&sync_frame(None)).unwrap();
        emcy.extend(emcy_codes(&r.run(2 * MS)));
        if !emcy.is_empty() {
            break;
        }
    }
    assert_eq!(emcy, vec![0x8611]);
    assert!((r.w.drive(1).unwrap().position_actual() - p0).abs() < 50, "the slide did not move");
    r.fault(fs::JAM_MNM, 0, 4);
}

#[test]
fn heartbeat_stops_and_comes_back() {
    let mut r = Rig::new();
    assert_eq!(r.write(0x1017, 0, 10, 2), Some(Ok(())));
    let hb = |f: &Vec<CanFrame>| f.iter().filter(|f| f.cob_id() == 0x701).count();
    assert!((9..=11).contains(&hb(&r.run(100 * MS))));
    r.fault(fs::HEARTBEAT_MUTED, 1, 1);
    assert_eq!(hb(&r.run(100 * MS)), 0);
    // The node is otherwise alive.
    assert_eq!(r.read(0x1000, 0), 0x0002_0192);
    r.fault(fs::HEARTBEAT_MUTED, 0, 1);
    assert!((9..=11).contains(&hb(&r.run(100 * MS))));
}

#[test]
fn node_falls_silent_for_a_while() {
    let mut r = Rig::new();
    // The write is answered, then nothing for 50 ms: no SDO answer, no boot-up after NMT.
    r.fault(fs::SILENT_MS, 50, 4);
    assert!(r.w.drive(1).unwrap().is_silent());
    assert_eq!(r.write(0x1017, 0, 10, 2), None);
    r.run(45 * MS);
    assert_eq!(r.write(0x1017, 0, 10, 2), None);
    r.run(5 * MS);
    assert_eq!(r.write(0x1017, 0, 10, 2), Some(Ok(())), "back on the bus after 50 ms");
    assert_eq!(r.read(SIM_FAULTS, fs::SILENT_MS), 0);
}

#[test]
fn pdo_loss_rate() {
    let mut r = Rig::new();
    r.enable();
    let p = r.w.drive(1).unwrap().position_actual();
    r.fault(fs::PDO_DROP_PERMILLE, 300, 2);
    let n = 1000;
    let got = (0..n).filter(|_| r.cycle(0x0F, p, MS).is_some()).count();
    // 30 % lost (≈ 300 ± 3σ ≈ 45): the TPDOs that came.
    assert!((610..=790).contains(&got), "{got} of {n} TPDOs");
    r.fault(fs::PDO_DROP_PERMILLE, 0, 2);
    assert_eq!((0..100).filter(|_| r.cycle(0x0F, p, MS).is_some()).count(), 100);
}

#[test]
fn tpdos_delayed() {
    let mut r = Rig::new();
    r.enable();
    let p = r.w.drive(1).unwrap().position_actual();
    r.fault(fs::TPDO_DELAY_US, 1500, 4);
    for _ in 0..5 {
        r.m.send(&CanFrame::new(0x201, &[0x0F, 0, p as u8, (p >> 8) as u8, (p >> 16) as u8, (p >> 24) as u8])).unwrap();
        r.m.send(&sync_frame(None)).unwrap();
        let t0 = r.w.now_ns();
        assert!(r.run(1400 * 1000).iter().all(|f| f.cob_id() != 0x181), "not before 1.5 ms");
        let late = r.run(200 * 1000);
        assert_eq!(late.iter().filter(|f| f.cob_id() == 0x181).count(), 1, "at 1.5 ms");
        assert_eq!(r.w.now_ns() - t0, 1600 * 1000);
        r.run(400 * 1000);
    }
}

#[test]
fn fault_flags_parse_and_fire_at_their_time() {
    use sim_drives::{parse_fault, FaultAt};
    assert_eq!(parse_fault("1:encoder-lost@2000"), Ok(FaultAt { node: 1, sub: fs::ENCODER_LOST, value: 1, at_ns: 2000 * MS }));
    assert_eq!(parse_fault("2:raise=0x4310"), Ok(FaultAt { node: 2, sub: fs::RAISE, value: 0x4310, at_ns: 0 }));
    assert_eq!(parse_fault("3:silent-ms"), Ok(FaultAt { node: 3, sub: fs::SILENT_MS, value: u32::MAX, at_ns: 0 }));
    assert_eq!(parse_fault("1:pdo-drop-permille=50@10").map(|f| (f.sub, f.value)), Ok((fs::PDO_DROP_PERMILLE, 50)));
    for bad in ["encoder-lost", "0:overcurrent", "1:melt", "1:raise", "1:jam-mnm=lots", "1:overcurrent@soon"] {
        let e = parse_fault(bad).unwrap_err();
        assert!(e.contains("NODE:NAME[=VALUE][@MS]") && e.contains(bad), "{e}");
    }

    let mut r = Rig::new();
    r.enable();
    let t0 = r.w.now_ns();
    r.w.schedule_faults(vec![parse_fault(&format!("1:undervoltage@{}", t0 / MS + 30)).unwrap()]);
    let mut seen = None;
    for _ in 0..40 {
        if let Some(code) = emcy_codes(&r.run(MS)).first() {
            seen = Some((*code, r.w.now_ns() - t0));
            break;
        }
    }
    assert_eq!(seen, Some((0x3220, 30 * MS)), "EMCY in the millisecond the fault was scheduled for");
    assert_eq!(r.w.set_sim_fault(1, fs::UNDERVOLTAGE, 0), Ok(()));
    assert_eq!(r.w.set_sim_fault(9, fs::UNDERVOLTAGE, 0), Err(0));
}

/// CSP: SYNCs in a row without a new target (the RPDO was lost) — the drive's set-point goes
/// on with the last increment for `0x2102` SYNCs (3 by default), then holds.
#[test]
fn a_lost_csp_set_point_is_bridged_with_the_last_increment_then_held() {
    use sim_drives::drive::CSP_EXTRAPOLATE;
    for (limit, expect_bridged) in [(None, 3), (Some(0u32), 0), (Some(5), 5)] {
        let mut r = Rig::new();
        if let Some(l) = limit {
            assert_eq!(r.write(CSP_EXTRAPOLATE, 0, l, 1), Some(Ok(())));
        }
        r.enable();
        let p0 = r.w.drive(1).unwrap().position_actual();
        // 100 counts per 2 ms cycle (5 mm/s).
        let mut last = p0;
        for k in 1..=50 {
            last = p0 + 100 * k;
            r.cycle(0x0F, last, 2 * MS);
        }
        let d0 = r.w.drive(1).unwrap().position_demand();
        assert!((d0 - last as f64).abs() < 1.0, "demand {d0} on the target {last}");
        // Six SYNCs without an RPDO.
        let mut demand = Vec::new();
        for _ in 0..6 {
            r.m.send(&sync_frame(None)).unwrap();
            r.run(2 * MS);
            demand.push(r.w.drive(1).unwrap().position_demand());
        }
        for (m, d) in demand.iter().enumerate() {
            let bridged = (m + 1).min(expect_bridged) as f64;
            let want = last as f64 + 100.0 * bridged;
            assert!((d - want).abs() < 1.0, "limit {limit:?}: SYNC {} without a target: demand {d}, expected {want} ({demand:?})", m + 1);
        }
        assert_eq!(r.state(), State::OperationEnabled);
    }
}

#[test]
fn a_sync_producer_stops_producing_when_muted() {
    let bus = InprocBus::new();
    let mut m = bus.endpoint();
    let mut d = DriveConfig::new(1, DriveKind::Linear, "x", 10000.0);
    d.shape.sync_producer = true;
    d.shape.sync_period_us = 2000;
    let mut w = SimWorld::new(&bus, SimConfig { drives: vec![d], step_us: 50 });
    let count = |w: &mut SimWorld, m: &mut InprocEndpoint, ms: u64| {
        let t = w.now_ns() + ms * MS;
        w.wait_until(t);
        let mut n = 0;
        while let Ok(Some(f)) = m.try_recv() {
            n += (f.cob_id() == 0x080) as u32;
        }
        n
    };
    count(&mut w, &mut m, 50);
    let before = count(&mut w, &mut m, 100);
    assert!((45..=55).contains(&before), "{before} SYNCs in 100 ms");
    // As `sim-drives --fault 1:sync-stop@MS` schedules it.
    let mut f = sim_drives::parse_fault("1:sync-stop@200").unwrap();
    assert_eq!((f.sub, f.value), (fs::SYNC_MUTED, 1));
    f.at_ns = w.now_ns() + 5 * MS;
    w.schedule_faults(vec![f]);
    count(&mut w, &mut m, 10);
    assert_eq!(count(&mut w, &mut m, 100), 0, "SYNC went on after 0x2100:{} = 1", fs::SYNC_MUTED);
    assert_eq!(w.drive(1).unwrap().object(SIM_FAULTS, fs::SYNC_MUTED), Some(1));
}
