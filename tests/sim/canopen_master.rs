//! The CANopen master against the emulated drives (sim-drives) on the in-process bus, in
//! simulated time: SDO block transfer, the fault diagnosis in alarm 2010, profile position
//! and homing, bus faults, late boot.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::drives::canopen::sdo_client::SdoError;
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw_bus::canopen::sdo::abort;
use cncgw_bus::transport::inproc::InprocBus;
use cncgw_bus::Clock;
use sim_drives::drive::{USER_DATA, USER_DATA_LEN};
use sim_drives::{SimConfig, SimWorld};

const MS: u64 = 1_000_000;

fn rig() -> (MachineConfig, InprocBus, SimWorld, CanOpenMaster<cncgw_bus::transport::inproc::InprocEndpoint>) {
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let m = CanOpenMaster::new(bus.endpoint(), &cfg);
    (cfg, bus, w, m)
}

fn pattern(n: usize) -> Vec<u8> {
    (0..n).map(|i| (i * 7 + i / 251) as u8).collect()
}

#[test]
fn block_transfer_moves_a_large_domain_both_ways() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    // Full size, and sizes that leave 0…6 bytes in the last segment, and more than one
    // sub-block (127 × 7 = 889 bytes).
    for n in [USER_DATA_LEN, 0, 1, 7, 889, 890, 1000, 3333] {
        let data = pattern(n);
        m.sdo_block_download(&mut w, 1, USER_DATA, 0, &data).unwrap_or_else(|e| panic!("block download of {n} bytes: {e}"));
        assert_eq!(m.sdo_block_upload(&mut w, 1, USER_DATA, 0).unwrap(), data, "block upload of {n} bytes");
        // The same object read the segmented way agrees.
        assert_eq!(m.sdo_upload(&mut w, 1, USER_DATA, 0).unwrap(), data, "segmented upload of {n} bytes");
    }
    // A string object by block upload.
    let name = m.sdo_block_upload(&mut w, 1, 0x1008, 0).unwrap();
    assert_eq!(name, m.sdo_upload(&mut w, 1, 0x1008, 0).unwrap());
    assert!(!name.is_empty());
}

#[test]
fn block_transfer_aborts_are_reported() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    let e = m.sdo_block_download(&mut w, 1, USER_DATA, 0, &pattern(USER_DATA_LEN + 1)).unwrap_err();
    assert_eq!(e, SdoError::Abort { code: abort::TOO_LONG });
    let e = m.sdo_block_upload(&mut w, 1, 0x2345, 0).unwrap_err();
    assert_eq!(e.to_string(), "SDO abort 0x06020000 object does not exist in the object dictionary");
    let e = m.sdo_block_download(&mut w, 1, 0x1000, 0, &[1, 2, 3, 4]).unwrap_err();
    assert_eq!(e, SdoError::Abort { code: abort::READ_ONLY });
    // A 4-byte object written by block download.
    m.sdo_block_download(&mut w, 1, 0x6065, 0, &1234u32.to_le_bytes()).unwrap();
    assert_eq!(m.sdo_upload(&mut w, 1, 0x6065, 0).unwrap(), 1234u32.to_le_bytes());
    // The server is free again after each abort.
    assert_eq!(m.sdo_upload(&mut w, 1, 0x1000, 0).unwrap(), 0x0002_0192u32.to_le_bytes());
}

#[test]
fn block_upload_needs_fewer_round_trips_than_segmented() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    let data = pattern(USER_DATA_LEN);
    m.sdo_block_download(&mut w, 1, USER_DATA, 0, &data).unwrap();
    let t0 = w.now_ns();
    m.sdo_upload(&mut w, 1, USER_DATA, 0).unwrap();
    let seg = w.now_ns() - t0;
    let t0 = w.now_ns();
    m.sdo_block_upload(&mut w, 1, USER_DATA, 0).unwrap();
    let blk = w.now_ns() - t0;
    // Segmented: one round trip per 7 bytes (586 for 4096 bytes); block: one per 889.
    assert!(blk * 20 < seg, "block {} µs vs segmented {} µs", blk / 1000, seg / 1000);
    let _ = MS;
}

/// Start-up and enable: the cycle running, every drive in Operation Enabled.
fn enabled() -> (MachineConfig, InprocBus, SimWorld, CanOpenMaster<cncgw_bus::transport::inproc::InprocEndpoint>, u64) {
    let (cfg, bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    let mut next = w.now_ns();
    for _ in 0..1000 {
        next += 2 * MS;
        w.wait_until(next);
        m.receive(next).unwrap();
        let done = m.enable_step().unwrap();
        m.transmit(next).unwrap();
        if done {
            return (cfg, bus, w, m, next);
        }
    }
    panic!("drives not enabled");
}

/// Hold every axis where it is until an alarm comes (or `cycles` pass).
fn cycle_until_alarm(
    w: &mut SimWorld,
    m: &mut CanOpenMaster<cncgw_bus::transport::inproc::InprocEndpoint>,
    next: &mut u64,
    cycles: u32,
) -> Option<(cncgw::Alarm, u32)> {
    for k in 0..cycles {
        *next += 2 * MS;
        w.wait_until(*next);
        if let Err(a) = m.receive(*next) {
            return Some((a, k));
        }
        for ax in 0..m.axis_count() {
            let p = m.feedback(ax).pos;
            m.set_target(ax, p);
        }
        m.transmit(*next).unwrap();
    }
    None
}

#[test]
fn a_drive_fault_names_error_code_and_register_in_words() {
    let (_cfg, _bus, mut w, mut m, mut next) = enabled();
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 5).is_none());
    assert!(w.inject_fault(2, 0x3210));
    let (a, k) = cycle_until_alarm(&mut w, &mut m, &mut next, 50).expect("alarm 2010");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{}", a.message);
    // EMCY seen, then 0x603F and 0x1001 read over SDO: within a few cycles.
    assert!(k <= 4, "alarm after {k} cycles");
    assert!(a.message.starts_with("node 2 (axis z): drive fault EMCY 0x3210 DC-link overvoltage"), "{}", a.message);
    assert!(a.message.contains("0x603F error code 0x3210 DC-link overvoltage"), "{}", a.message);
    assert!(a.message.contains("0x1001 error register 0x05 generic error, voltage"), "{}", a.message);
    // The other axes were told to quick-stop as soon as the fault was seen (at rest, the
    // stop ends at once in Switch On Disabled: 0x605A = 2).
    let x = m.node_ids().iter().position(|&n| n == 1).unwrap();
    assert_eq!(m.feedback(x).state(), cncgw_bus::cia402::State::SwitchOnDisabled);
    assert_eq!(w.drive(1).unwrap().state(), cncgw_bus::cia402::State::SwitchOnDisabled);
}

#[test]
fn a_fault_without_emcy_is_diagnosed_too() {
    let (_cfg, _bus, mut w, mut m, _) = enabled();
    // The EMCY is lost (its COB-ID invalid), the statusword still shows the fault.
    m.sdo_write(&mut w, 1, 0x1014, 0, &0x8000_0081u32.to_le_bytes()).unwrap();
    let mut next = w.now_ns();
    assert!(w.set_sim_fault(1, sim_drives::drive::fault_sub::RAISE, 0x7305).is_ok());
    let (a, _) = cycle_until_alarm(&mut w, &mut m, &mut next, 50).expect("alarm 2010");
    assert_eq!(a.number, cncgw::alarm::DRIVE_FAULT, "{}", a.message);
    assert!(a.message.contains("drive left Operation Enabled"), "{}", a.message);
    assert!(a.message.contains("0x603F error code 0x7305 incremental encoder 1 broken"), "{}", a.message);
    assert!(a.message.contains("0x1001 error register 0x01 generic error;"), "{}", a.message);
    assert!(m.last_emcy(1).is_none(), "no EMCY was sent");
}

#[test]
fn profile_move_reaches_its_target_on_a_trapezoid() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    assert_eq!(m.sdo_read(&mut w, 1, 0x6502, 0).unwrap(), 0x1A1u32.to_le_bytes(), "0x6502: PP, homing, CSP, CSV");
    let x0 = w.drive(1).unwrap().position_unwrapped() as f64 / 1e4;
    let t0 = w.now_ns();
    // 10 mm at 50 mm/s and 500 mm/s²: 0.1 s up, 0.1 s down, 0.1 s at speed = 0.3 s.
    m.profile_move(&mut w, 1, x0 + 10.0, 50.0, 500.0).unwrap();
    let took = (w.now_ns() - t0) as f64 * 1e-9;
    let d = w.drive(1).unwrap();
    assert!((d.position_unwrapped() as f64 / 1e4 - (x0 + 10.0)).abs() < 0.002, "at {} mm", d.position_unwrapped() as f64 / 1e4);
    assert!(took > 0.3 && took < 0.45, "the move took {took} s (0.3 s of profile, start-up enable and handshakes)");
    assert_eq!(d.mode_display(), 8, "back in CSP");
    // The cycle goes on in CSP without a jump or an alarm; the other axes held.
    let mut next = w.now_ns();
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 50).is_none());
    assert!((w.drive(1).unwrap().position_unwrapped() as f64 / 1e4 - (x0 + 10.0)).abs() < 0.002);
    // Back, faster: 10 mm at 100 mm/s, 1000 mm/s² → 0.2 s.
    let t0 = w.now_ns();
    m.profile_move(&mut w, 1, x0, 100.0, 1000.0).unwrap();
    assert!((w.drive(1).unwrap().position_unwrapped() as f64 / 1e4 - x0).abs() < 0.002);
    assert!((w.now_ns() - t0) as f64 * 1e-9 < 0.4);
}

#[test]
fn profile_move_outside_the_software_limits_stops_at_the_limit_and_says_so() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    // X max is 150 mm: the drive clamps the target (0x607D), so the move ends at 150.
    m.profile_move(&mut w, 1, 170.0, 400.0, 4000.0).unwrap();
    assert!((w.drive(1).unwrap().position_unwrapped() as f64 / 1e4 - 150.0).abs() < 0.002);
    let e = m.profile_move(&mut w, 1, 1.0, 0.0, 100.0).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::PROFILE_MOVE);
    assert!(e.message.contains("profile velocity 0 is out of range"), "{}", e.message);
}

#[test]
fn homing_on_the_present_position() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    m.profile_move(&mut w, 2, -3.25, 50.0, 500.0).unwrap();
    m.home(&mut w, 2, 35, 10.0, 1.0, 100.0, 1000).unwrap();
    let d = w.drive(2).unwrap();
    assert!(d.position_unwrapped().abs() <= 5, "0x6064 = {} after homing on the present position", d.position_unwrapped());
    let z = m.node_ids().iter().position(|&n| n == 2).unwrap();
    let mut next = w.now_ns();
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 3).is_none());
    assert!(m.feedback(z).pos.abs() < 0.001, "the master's feedback follows: {}", m.feedback(z).pos);
    // Method 37 with a home offset of 2 mm.
    m.sdo_write(&mut w, 2, 0x607C, 0, &20000i32.to_le_bytes()).unwrap();
    m.home(&mut w, 2, 37, 10.0, 1.0, 100.0, 1000).unwrap();
    assert!((w.drive(2).unwrap().position_unwrapped() - 20000).abs() <= 5);
    let mut next = w.now_ns();
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 3).is_none());
    assert!((m.feedback(z).pos - 2.0).abs() < 0.001, "the master's feedback follows: {}", m.feedback(z).pos);
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 50).is_none(), "the cycle goes on after homing");
}

#[test]
fn homing_on_the_negative_limit_switch() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    let z0 = w.drive(2).unwrap().position_unwrapped();
    // The switch closes 5 mm below the power-on position.
    let sw = (z0 - 50_000) as i32;
    m.sdo_write(&mut w, 2, sim_drives::drive::profile::SIM_SWITCHES, 1, &sw.to_le_bytes()).unwrap();
    let t0 = w.now_ns();
    // 20 mm/s towards the switch, 1 mm/s off it, 200 mm/s².
    m.home(&mut w, 2, 17, 20.0, 1.0, 200.0, 5000).unwrap();
    let took = (w.now_ns() - t0) as f64 * 1e-9;
    let d = w.drive(2).unwrap();
    // Home (0) is where the switch released; the axis stopped just past it (1 mm/s at
    // 200 mm/s²: 2.5 µm), off the switch.
    let p = d.position_unwrapped();
    assert!((0..=200).contains(&p), "0x6064 = {p} counts after homing");
    assert_eq!(d.object(0x60FD, 0), Some(0), "0x60FD: switch released");
    assert!(took > 0.25 && took < 1.5, "homing took {took} s");
    // The switch is at physical z0 − 50000: the axis is at z0 − 50000 + p physically, so a
    // move to −10 mm in the new coordinate runs onto it (and 0x60FD says so).
    m.profile_move(&mut w, 2, -1.0, 20.0, 200.0).unwrap();
    let mut next = w.now_ns();
    cycle_until_alarm(&mut w, &mut m, &mut next, 2);
    assert_eq!(w.drive(2).unwrap().object(0x60FD, 0), Some(1), "0x60FD bit 0: negative limit switch");
}

#[test]
fn homing_on_the_limit_switch_and_the_index_pulse() {
    use cncgw_bus::CanBus;
    let (_cfg, bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    // The switch edge 0.25 mm above an index pulse (one every 10000 counts = 1 mm), 4.75 mm below.
    let z0 = w.drive(2).unwrap().position_unwrapped();
    let sw = ((z0 - 50_000).div_euclid(10_000) * 10_000 + 2_500) as i32;
    m.sdo_write(&mut w, 2, sim_drives::drive::profile::SIM_SWITCHES, 1, &sw.to_le_bytes()).unwrap();
    // Method 1: the negative limit switch, left moving positive, then the next index pulse.
    m.home(&mut w, 2, 1, 20.0, 1.0, 200.0, 8000).unwrap();
    let p = w.drive(2).unwrap().position_unwrapped();
    assert!((0..=200).contains(&p), "0x6064 = {p} counts after homing");
    // Home is the index pulse 0.75 mm past the switch edge: -0.7 mm is off it, -0.8 on it.
    let z = m.node_ids().iter().position(|&n| n == 2).unwrap();
    for (to, on) in [(-0.7, 0), (-0.8, 1)] {
        m.profile_move(&mut w, 2, to, 20.0, 200.0).unwrap();
        let mut next = w.now_ns();
        cycle_until_alarm(&mut w, &mut m, &mut next, 2);
        assert_eq!(w.drive(2).unwrap().object(0x60FD, 0), Some(on), "at {to} mm");
    }
    assert!(m.position_lost(z).is_none());
    // A boot-up the master did not cause (a third party's NMT reset node): the drive
    // restarted, its homing is gone, and the master says the position is lost.
    let mut other = bus.endpoint();
    other.send(&cncgw_bus::CanFrame::new(0x000, &[0x81, 2])).unwrap();
    let mut next = w.now_ns();
    cycle_until_alarm(&mut w, &mut m, &mut next, 20);
    let why = m.position_lost(z).expect("reboot seen");
    assert!(why.contains("boot-up message") && why.contains("rebooted"), "{why}");
    let p = w.drive(2).unwrap().position_unwrapped();
    assert!((p - (sw as i64 + 7_500 - 8_000)).abs() <= 300, "0x6064 = {p}: the encoder's count again (the switch at {sw})");
    assert!(m.position_lost(0).is_none(), "X did not reboot");
}

#[test]
fn homing_errors_are_alarms() {
    let (_cfg, _bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    // No positive limit switch fitted: the drive reports a homing error (bit 13).
    let e = m.home(&mut w, 1, 18, 10.0, 1.0, 100.0, 2000).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::HOMING);
    assert!(e.message.contains("homing method 18 failed (0x6041 bit 13 homing error)"), "{}", e.message);
    // An unsupported method is refused by the drive.
    let e = m.home(&mut w, 1, 31, 10.0, 1.0, 100.0, 2000).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::HOMING);
    assert!(e.message.contains("0x06090030") && e.message.contains("not supported"), "{}", e.message);
    // The drive is usable afterwards.
    m.profile_move(&mut w, 1, 1.0, 10.0, 100.0).unwrap();
}

// ---- Wire faults (in-process bus, seeded: every run the same) -------------------------

use cncgw_bus::transport::inproc::WireFaults;

fn only(lo: u16, hi: u16, seed: u64) -> WireFaults {
    WireFaults { seed, ids: Some((lo, hi)), ..WireFaults::default() }
}

#[test]
fn lost_or_late_feedback_is_alarm_2015() {
    // Node 2's TPDO1 lost from now on.
    let (_cfg, bus, mut w, mut m, mut next) = enabled();
    bus.set_faults(Some(WireFaults { drop: 1.0, ..only(0x182, 0x182, 1) }));
    let (a, k) = cycle_until_alarm(&mut w, &mut m, &mut next, 100).expect("alarm");
    assert_eq!(a.number, cncgw::alarm::STALE_FEEDBACK, "{}", a.message);
    assert!(a.message.starts_with("node 2 (axis z): no position feedback"), "{}", a.message);
    assert!((9..=12).contains(&k), "after {k} cycles (feedback timeout 20 ms)");

    // Delayed by 30 ms: too late as well.
    let (_cfg, bus, mut w, mut m, mut next) = enabled();
    bus.set_faults(Some(WireFaults { delay: 1.0, delay_ns: 30 * MS, ..only(0x181, 0x181, 1) }));
    let (a, _) = cycle_until_alarm(&mut w, &mut m, &mut next, 100).expect("alarm");
    assert_eq!(a.number, cncgw::alarm::STALE_FEEDBACK, "{}", a.message);
    assert!(a.message.starts_with("node 1 (axis x)"), "{}", a.message);

    // Delayed by 5 ms: the master runs on. A constant latency cannot be seen by the age
    // check (a TPDO still arrives every cycle, only an older one).
    let (_cfg, bus, mut w, mut m, mut next) = enabled();
    bus.set_faults(Some(WireFaults { delay: 1.0, delay_ns: 5 * MS, ..only(0x181, 0x181, 1) }));
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 200).is_none());
    assert!(bus.fault_counts().delayed >= 200);
    // One in five lost: still within the 20 ms feedback timeout.
    bus.set_faults(Some(WireFaults { drop: 0.2, ..only(0x181, 0x183, 3) }));
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 500).is_none());
    assert!(bus.fault_counts().dropped > 200);
}

#[test]
fn lost_sdo_frames_are_retried_then_a_timeout() {
    let (_cfg, bus, mut w, mut m) = rig();
    m.startup(&mut w).expect("startup");
    // Every answer of node 1 lost: two attempts of 500 ms (bus.sdo_timeout_ms), then the error.
    bus.set_faults(Some(WireFaults { drop: 1.0, ..only(0x581, 0x581, 1) }));
    let t0 = w.now_ns();
    let e = m.sdo_upload(&mut w, 1, 0x1000, 0).unwrap_err();
    let took = (w.now_ns() - t0) / MS;
    assert_eq!(e.to_string(), "no SDO answer within 500 ms (is the node powered, on the bus, with this node id?)");
    assert!((1000..=1002).contains(&took), "took {took} ms: one retry");

    // A third of the requests and answers lost: some reads need the retry, some fail, none
    // returns a wrong value; the same seed gives the same outcomes.
    let outcomes = |seed: u64| {
        let (_cfg, bus, mut w, mut m) = rig();
        m.startup(&mut w).expect("startup");
        bus.set_faults(Some(WireFaults { drop: 0.33, ..only(0x581, 0x601, seed) }));
        (0..20)
            .map(|_| {
                let t0 = w.now_ns();
                let r = m.sdo_upload(&mut w, 1, 0x1000, 0);
                if let Ok(v) = &r {
                    assert_eq!(v, &0x0002_0192u32.to_le_bytes());
                }
                (r.is_ok(), (w.now_ns() - t0) / (400 * MS))
            })
            .collect::<Vec<_>>()
    };
    let a = outcomes(5);
    assert_eq!(a, outcomes(5));
    assert!(a.iter().any(|&(ok, t)| ok && t == 0), "{a:?}");
    assert!(a.iter().any(|&(ok, t)| ok && t >= 1), "some succeed on the retry: {a:?}");
    assert!(a.iter().any(|&(ok, _)| !ok), "some fail twice: {a:?}");
}

#[test]
fn corrupted_block_uploads_are_caught_by_the_crc() {
    let data = pattern(USER_DATA_LEN);
    let mut caught = 0;
    for seed in 1..=10 {
        let (_cfg, bus, mut w, mut m) = rig();
        m.startup(&mut w).expect("startup");
        m.sdo_block_download(&mut w, 1, USER_DATA, 0, &data).unwrap();
        // One answer frame in 200 with a bit flipped (≈ 3 per 4096-byte upload).
        bus.set_faults(Some(WireFaults { corrupt: 0.005, ..only(0x581, 0x581, seed) }));
        let r = m.sdo_block_upload(&mut w, 1, USER_DATA, 0);
        let corrupted = bus.fault_counts().corrupted;
        match r {
            Ok(v) => assert_eq!(v, data, "seed {seed}: an upload with {corrupted} corrupted frames passed as good"),
            Err(e) => {
                // The CRC, or for a flipped sequence number or command byte a protocol error.
                assert!(corrupted > 0, "seed {seed}: {e} without any corruption");
                if e == (SdoError::Abort { code: abort::CRC }) {
                    caught += 1;
                }
                eprintln!("seed {seed}: {corrupted} corrupted frames: {e}");
            }
        }
    }
    assert!(caught >= 3, "only {caught} of 10 corrupted uploads were caught by the CRC");
}

// ---- Late boot ---------------------------------------------------------------------------

fn rig_with_boot_delay(node: u8, ms: f64) -> (SimWorld, CanOpenMaster<cncgw_bus::transport::inproc::InprocEndpoint>) {
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let mut sim = SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap();
    for d in sim.drives.iter_mut().filter(|d| d.node == node) {
        d.boot_delay_ms = ms;
    }
    let w = SimWorld::new(&bus, sim);
    (w, CanOpenMaster::new(bus.endpoint(), &cfg))
}

#[test]
fn a_drive_booting_after_the_boot_wait_is_alarm_2001_naming_it() {
    // The master waits 4 × sdo_timeout_ms = 2000 ms for every boot-up after its NMT reset.
    let (mut w, mut m) = rig_with_boot_delay(3, 2500.0);
    let e = m.startup(&mut w).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::CANOPEN_BOOT, "{}", e.message);
    assert!(e.message.starts_with("node 3 (axis s1): no boot-up message within 2000 ms"), "{}", e.message);
    assert!(m.booted(1) && m.booted(2) && !m.booted(3));
    // After listening 120 ms for another master (1.2 × heartbeat_ms), then 2000 ms for the
    // boot-ups; the two nodes that booted are reset once more (left as found, 2–3 ms).
    assert!((2120..2130).contains(&(w.now_ns() / MS)), "gave up at {} ms", w.now_ns() / MS);
}

#[test]
fn a_drive_booting_late_but_within_the_wait_is_started() {
    let (mut w, mut m) = rig_with_boot_delay(2, 1500.0);
    m.startup(&mut w).expect("startup waits for the late drive");
    assert!(w.now_ns() > 1500 * MS);
    let info = m.infos().into_iter().find(|i| i.node == 2).expect("node 2 identified");
    assert_eq!(info.device_type, 0x0002_0192);
    assert_eq!(w.drive(2).unwrap().nmt_state(), cncgw_bus::canopen::nmt::NmtState::Operational);
}

// ---- EDS ---------------------------------------------------------------------------------

use cncgw_bus::canopen::eds::Eds;

fn sim_eds_text() -> String {
    std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds")).unwrap()
}

fn line_of(text: &str, header: &str) -> usize {
    text.lines().position(|l| l.trim() == header).unwrap() + 1
}

#[test]
fn startup_objects_are_checked_against_the_eds() {
    let (_cfg, _bus, _w, m) = rig();
    let text = sim_eds_text();
    let eds = Eds::parse("sim_drive.eds", &text).unwrap();
    for node in [1, 2, 3] {
        assert_eq!(m.check_eds(node, &eds), Vec::<String>::new(), "node {node}");
    }
    // A vendor file that says the controlword cannot be mapped and has no 0x6065.
    let bad = text.replacen("AccessType=rw\nDefaultValue=0\nPDOMapping=1\n\n[6041]", "AccessType=rw\nDefaultValue=0\nPDOMapping=0\n\n[6041]", 1);
    assert_ne!(bad, text, "the test edits the file");
    let bad = bad.replacen("[6065]", "[6965]", 1);
    let eds = Eds::parse("vendor.eds", &bad).unwrap();
    let msgs = m.check_eds(1, &eds);
    assert_eq!(msgs.len(), 2, "{msgs:#?}");
    assert_eq!(msgs[0], "vendor.eds: object 0x6065:00 is not in the EDS");
    assert_eq!(msgs[1], format!("vendor.eds:{} [6040] \"Controlword\": PDOMapping=0 but the master maps 0x6040:00", line_of(&bad, "[6040]")));
}

#[test]
fn od_check_of_a_live_drive_against_its_eds() {
    let (_cfg, _bus, mut w, mut m) = rig();
    assert!(m.wait_boot(&mut w, 100));
    let text = sim_eds_text();
    let eds = Eds::parse("sim_drive.eds", &text).unwrap();
    assert_eq!(m.check_od(&mut w, 1, &eds), Vec::<String>::new());
    // A file with an object the drive lacks, a wrong type and a wrong access.
    let bad = format!("{text}\n[2345]\nParameterName=Vendor thing\nObjectType=0x7\nDataType=0x0007\nAccessType=rw\n")
        .replacen(
            "[1017]\nParameterName=Producer heartbeat time\nObjectType=0x7\nDataType=0x0006",
            "[1017]\nParameterName=Producer heartbeat time\nObjectType=0x7\nDataType=0x0007",
            1,
        )
        .replacen(
            "[6041]\nParameterName=Statusword\nObjectType=0x7\nDataType=0x0006\nAccessType=ro",
            "[6041]\nParameterName=Statusword\nObjectType=0x7\nDataType=0x0006\nAccessType=rw",
            1,
        );
    let eds = Eds::parse("vendor.eds", &bad).unwrap();
    let msgs = m.check_od(&mut w, 1, &eds);
    assert_eq!(
        msgs,
        vec![
            format!(
                "vendor.eds:{} [1017] \"Producer heartbeat time\": DataType UNSIGNED32 is 4 bytes but node 1 answers 2 bytes",
                line_of(&bad, "[1017]")
            ),
            format!(
                "vendor.eds:{} [2345] \"Vendor thing\": node 1 does not have 0x2345:00 (object does not exist in the object dictionary)",
                line_of(&bad, "[2345]")
            ),
        ],
        "(the statusword's access is not tried: writing a rw object could move something)"
    );
}

#[test]
fn spindle_in_cyclic_synchronous_velocity_and_back() {
    let (_cfg, _bus, mut w, mut m, mut next) = enabled();
    m.velocity_mode(&mut w, 3).unwrap();
    assert_eq!(w.drive(3).unwrap().mode_display(), 9);
    // 600 rpm = 3600 °/s = 3.6e6 counts/s.
    m.set_velocity(3, 3600.0);
    let mut run = |w: &mut SimWorld, m: &mut CanOpenMaster<_>, cycles: u32| {
        for _ in 0..cycles {
            next += 2 * MS;
            w.wait_until(next);
            m.receive(next).unwrap();
            m.transmit(next).unwrap();
        }
    };
    run(&mut w, &mut m, 1000);
    let v = w.drive(3).unwrap().velocity_actual() as f64;
    assert!((v - 3.6e6).abs() < 0.01 * 3.6e6, "spindle at {v} counts/s");
    // The position feedback goes on (unwrapped through the INTEGER32 wrap).
    let ax = m.node_ids().iter().position(|&n| n == 3).unwrap();
    let p0 = m.feedback(ax).pos;
    run(&mut w, &mut m, 100);
    let turned = m.feedback(ax).pos - p0;
    assert!((turned - 720.0).abs() < 10.0, "turned {turned}° in 0.2 s");
    m.position_mode(&mut w, 3, 5000).unwrap();
    assert_eq!(w.drive(3).unwrap().mode_display(), 8);
    let at = w.drive(3).unwrap().position_unwrapped();
    let mut next = w.now_ns();
    assert!(cycle_until_alarm(&mut w, &mut m, &mut next, 100).is_none());
    let moved = w.drive(3).unwrap().position_unwrapped() - at;
    assert!(moved.abs() < 200, "holds where it stopped (moved {moved} counts)");
}

#[test]
fn startup_checks_the_eds_named_in_the_config() {
    let good = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds");
    let mut cfg = MachineConfig::embedded();
    cfg.axes.get_mut("z").unwrap().eds = Some(good.into());
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("the EDS fits");

    // A data sheet whose 0x6065 is read-only.
    let text = sim_eds_text();
    let bad_text = text.replacen(
        "[6065]\nParameterName=Following error window\nObjectType=0x7\nDataType=0x0007\nAccessType=rw",
        "[6065]\nParameterName=Following error window\nObjectType=0x7\nDataType=0x0007\nAccessType=ro",
        1,
    );
    assert_ne!(bad_text, text);
    let bad = std::env::temp_dir().join(format!("cncgw_startup_eds_{}.eds", std::process::id()));
    std::fs::write(&bad, &bad_text).unwrap();
    cfg.axes.get_mut("z").unwrap().eds = Some(bad.to_string_lossy().into_owned());
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    let e = m.startup(&mut w).unwrap_err();
    let _ = std::fs::remove_file(&bad);
    assert_eq!(e.number, cncgw::alarm::EDS, "{}", e.message);
    assert!(e.message.starts_with("node 2 (axis z): the configuration does not fit the drive's EDS (1 problem(s))"), "{}", e.message);
    assert!(
        e.message.contains(&format!(
            ".eds:{} [6065] \"Following error window\": AccessType=ro but the master writes 0x6065:00",
            line_of(&bad_text, "[6065]")
        )),
        "{}",
        e.message
    );
}
