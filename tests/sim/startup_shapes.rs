//! Start-up against drives shaped like commercial ones (sim-drives `[drive.shape]`), in
//! simulated time: `examples/first_part.nc` either runs to its end point on the drives' own
//! positions, or stops before any motion with an alarm that says what the drive is and what
//! to configure — never a jump, never "ok" at the wrong place. Also: a second master on the
//! bus, a failed start-up leaving the drives as found, the master heartbeat's period, a TPDO
//! of the wrong length, node guarding.

use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::drives::DriveBus;
use cncgw::Alarm;
use cncgw_bus::canopen::nmt::NmtState;
use cncgw_bus::cia402::State;
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use cncgw_bus::{CanBus, Clock};
use sim_drives::config::Shape;
use sim_drives::{SimConfig, SimWorld};

use crate::inproc_run::{run, Ran};

const MS: u64 = 1_000_000;
const CSP: u32 = 1 << 8;

fn first_part() -> String {
    std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc")).unwrap()
}

/// The default lathe's drives, each changed by `f`.
fn shaped(f: impl Fn(&mut Shape, u8)) -> SimConfig {
    let mut sim = SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap();
    for d in &mut sim.drives {
        f(&mut d.shape, d.node);
    }
    sim
}

impl Ran {
    /// Start-up left the drives as it found them: PDOs valid with their power-on mapping, the
    /// application objects written back, pre-operational (as they booted).
    fn assert_left_as_found(&self, sim: &SimConfig) {
        for cfg in &sim.drives {
            let d = self.world.drive(cfg.node).unwrap();
            let n = cfg.node as i64;
            assert_eq!(d.object(0x1400, 1), Some(0x200 + n), "node {}: RPDO1 valid again", cfg.node);
            assert_eq!(d.object(0x1800, 1), Some(0x180 + n), "node {}: TPDO1 valid again", cfg.node);
            assert_eq!(d.object(0x1A00, 0), Some(2), "node {}: TPDO1 mapping as at power-on", cfg.node);
            assert_eq!(d.object(0x1016, 1).unwrap_or(0), 0, "node {}: consumes no heartbeat", cfg.node);
            assert_eq!(d.object(0x6060, 0), Some(cfg.shape.boot_mode as i64), "node {}: 0x6060 as found", cfg.node);
            assert_eq!(
                d.object(0x6065, 0),
                Some((cfg.following_error_window as f64 / cfg.increments_per_unit()).round() as i64),
                "node {}: 0x6065 as found",
                cfg.node
            );
            assert_eq!(d.nmt_state(), NmtState::PreOperational, "node {}", cfg.node);
        }
    }
}

#[test]
fn pp_boot_drives_are_enabled_only_in_csp_and_run_to_the_end_point() {
    // Boots in profile position; a new mode shows (and acts) 300 ms and 50 SYNCs later.
    let sim = shaped(|s, _| {
        s.boot_mode = 1;
        s.mode_switch_ms = 300.0;
        s.mode_switch_syncs = 50;
    });
    let r = run(&MachineConfig::embedded(), sim, &first_part());
    let s = r.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(s.at_program_end(), "{s:#?}");
    for n in [1u8, 2, 3] {
        assert_eq!(r.world.drive(n).unwrap().enabled_modes(), CSP, "node {n} was enabled in another mode than CSP");
    }
    // On the drives' own positions: X100 Z5 (X a diameter).
    assert_eq!(r.world.drive(1).unwrap().position_unwrapped(), 500_000);
    assert_eq!(r.world.drive(2).unwrap().position_unwrapped(), 50_000);
    for a in &s.axes[1..] {
        assert!(a.max_following_error < 0.05, "axis {} lagged {} mm: a jump", a.name, a.max_following_error);
    }
    assert!(s.enable_time_s > 0.3, "waited for the mode: enabled after {} s", s.enable_time_s);
}

#[test]
fn a_drive_that_never_shows_the_mode_stops_before_motion_naming_the_mode_it_shows() {
    let sim = shaped(|s, _| {
        s.boot_mode = 1;
        s.mode_switch_ms = 10_000.0;
    });
    let r = run(&MachineConfig::embedded(), sim.clone(), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_MODE, "{a}");
    assert!(
        a.message.starts_with("node 1 (axis x): asked for cyclic synchronous position (8) (0x6060), it still reports profile position (1) in 0x6061 after 2000 ms; nothing was enabled"),
        "{a}"
    );
    r.assert_nothing_moved();
    r.assert_left_as_found(&sim);
}

#[test]
fn user_unit_drives_are_refused_before_motion_with_the_counts_per_unit_that_matches() {
    // 0x6092 = 10000 per revolution on a 10 mm screw: positions in µm (10 increments each).
    let sim = shaped(|s, node| s.feed_constant = if node == 3 { 36_000 } else { 10_000 });
    let r = run(&MachineConfig::embedded(), sim.clone(), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_SCALING, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): the drive scales positions: 1 position unit = 10 encoder increments"), "{a}");
    assert!(a.message.contains("the axis would move 10× the programmed travel. Set axes.x.counts_per_unit = 1000"), "{a}");
    r.assert_nothing_moved();
    r.assert_left_as_found(&sim);
}

#[test]
fn user_unit_drives_run_on_their_own_positions_with_counts_per_unit_in_their_units() {
    let sim = shaped(|s, node| s.feed_constant = if node == 3 { 36_000 } else { 10_000 });
    let mut cfg = MachineConfig::embedded();
    for (axis, cpu, travel) in [("x", 1000.0, 10.0), ("z", 1000.0, 10.0), ("s1", 100.0, 360.0)] {
        let a = cfg.axes.get_mut(axis).unwrap();
        a.counts_per_unit = cpu;
        a.travel_per_rev = Some(travel);
    }
    let r = run(&cfg, sim, &first_part());
    let s = r.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(s.at_program_end(), "{s:#?}");
    // X at 50 mm (radius): 50000 µm, 500000 encoder increments; Z at 5 mm.
    let (x, z) = (r.world.drive(1).unwrap(), r.world.drive(2).unwrap());
    assert_eq!(x.position_actual(), 50_000);
    assert!((x.position_unwrapped() - 500_000).abs() <= 10, "{}", x.position_unwrapped());
    assert_eq!(z.position_actual(), 5_000);
    // A wrong travel per revolution is caught too.
    let sim = shaped(|s, node| s.feed_constant = if node == 3 { 36_000 } else { 10_000 });
    cfg.axes.get_mut("x").unwrap().travel_per_rev = Some(5.0);
    let r = run(&cfg, sim, &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_SCALING, "{a}");
    assert!(a.message.contains("that is 2000 per mm with axes.x.travel_per_rev = 5 mm; counts_per_unit = 1000 would move the axis 0.5× the programmed travel. Set axes.x.counts_per_unit = 2000"), "{a}");
}

#[test]
fn an_inverted_drive_is_refused_unless_the_config_says_so() {
    let sim = shaped(|s, node| s.polarity = if node == 2 { 0x80 } else { 0 });
    let r = run(&MachineConfig::embedded(), sim.clone(), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_SCALING, "{a}");
    assert!(a.message.starts_with("node 2 (axis z): the drive inverts positions (0x607E = 0x80, bit 7)"), "{a}");
    assert!(a.message.contains("axes.z.polarity = \"inverted\""), "{a}");
    r.assert_nothing_moved();
    let mut cfg = MachineConfig::embedded();
    cfg.axes.get_mut("z").unwrap().polarity = cncgw::config::Polarity::Inverted;
    let r = run(&cfg, sim, &first_part());
    let s = r.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(s.at_program_end());
    // Z ends at +5 mm in the program, −5 mm of the motor's own direction.
    assert_eq!(r.world.drive(2).unwrap().position_unwrapped(), -50_000);
}

#[test]
fn a_drive_producing_sync_is_named_and_nothing_is_reset() {
    let sim = shaped(|s, node| s.sync_producer = node == 2);
    let r = run(&MachineConfig::embedded(), sim, &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::FOREIGN_MASTER, "{a}");
    assert!(
        a.message.starts_with("node 2 (axis z): the drive produces SYNC itself (0x1005 = 0x40000080, bit 30, every 2 ms (0x1006)); with this master's SYNC the drives would see two and fault"),
        "{a}"
    );
    assert!(a.message.contains("cncgw sdo write 2 0x1005 0 --type u32 0x80") && a.message.ends_with("nothing was reset"), "{a}");
    for n in [1u8, 2, 3] {
        assert_eq!(r.world.drive(n).unwrap().nmt_resets(), 0, "node {n} was reset");
    }
    r.assert_nothing_moved();
}

#[test]
fn drives_without_0x6502_are_checked_by_0x6061_and_drives_without_csp_are_refused_in_words() {
    let r = run(&MachineConfig::embedded(), shaped(|s, _| s.supported_modes_object = false), &first_part());
    assert!(r.result.as_ref().unwrap_or_else(|a| panic!("{a}")).at_program_end());
    // No CSP, with 0x6502: refused before the mode is asked for.
    let r = run(&MachineConfig::embedded(), shaped(|s, _| s.modes = vec![1, 6]), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::DRIVE_MODE, "{a}");
    assert!(
        a.message.starts_with(
            "node 1 (axis x): this drive has no CSP (cyclic synchronous position) mode: its supported drive modes 0x6502 = 0x00000021 list PP, HM"
        ),
        "{a}"
    );
    r.assert_nothing_moved();
    // No CSP and no 0x6502: the abort on 0x6060 says the same in words.
    let r = run(
        &MachineConfig::embedded(),
        shaped(|s, _| {
            s.modes = vec![1, 6];
            s.supported_modes_object = false;
        }),
        &first_part(),
    );
    let a = r.alarm();
    assert_eq!(a.number, cncgw::alarm::SDO_CONFIG, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): this drive has no CSP (cyclic synchronous position) mode (it refuses 0x6060 = 8)"), "{a}");
    assert!(a.message.contains("(writing 0x6060:00 = 8 was refused: SDO abort 0x06090030"), "{a}");
    r.assert_nothing_moved();
}

#[test]
fn a_drive_that_cannot_map_its_mode_display_is_polled() {
    let r = run(&MachineConfig::embedded(), shaped(|s, node| s.mode_display_pdo = node != 1), &first_part());
    let s = r.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(s.at_program_end());
    assert_eq!(r.world.drive(1).unwrap().object(0x1A00, 0), Some(2), "TPDO1 without 0x6061");
    assert_eq!(r.world.drive(2).unwrap().object(0x1A00, 0), Some(3), "TPDO1 with 0x6061");
    assert_eq!(r.master.mode_display(1), Some(8));
}

#[test]
fn a_hidden_feedback_scaling_stops_the_run_instead_of_ok() {
    // No factor group to check at start-up; 0x6064 reports 10× (then: sign-flipped) the
    // position in 0x607A's units.
    for (factor, words) in [(10.0, "moves 10×"), (-1.0, "moves against the commanded motion (sign-flipped)")] {
        let sim = shaped(|s, node| {
            s.factor_group = false;
            s.feedback_factor = if node == 1 { factor } else { 1.0 };
        });
        let r = run(&MachineConfig::embedded(), sim, &first_part());
        let a = r.alarm();
        assert_eq!(a.number, cncgw::alarm::FEEDBACK_SCALE, "{a}");
        // The ratio in the message is measured, lag included: 10× within a few per mille.
        let said = a.message.split_once("moves ").and_then(|(_, r)| r.split_once('×')).and_then(|(r, _)| r.parse::<f64>().ok());
        match said {
            Some(r) => assert!(words == "moves 10×" && (r - 10.0).abs() < 0.05, "{a}"),
            None => assert!(a.message.starts_with(&format!("axis x: the position feedback {words}")), "{a}"),
        }
        // Found within two spans of 10 following-error windows (1 mm) of commanded travel.
        let x = r.world.drive(1).unwrap().position_unwrapped() as f64 / 1e4;
        assert!(x.abs() < 25.0, "X stopped at {x} mm");
    }
}

/// Cycle at 2 ms until every drive is enabled (at most 1 s); the time of the last cycle.
fn enable(w: &mut SimWorld, m: &mut CanOpenMaster<InprocEndpoint>) -> u64 {
    let mut next = w.now_ns();
    for _ in 0..500 {
        next += 2 * MS;
        w.wait_until(next);
        m.receive(next).unwrap();
        if m.enable_step().unwrap() {
            break;
        }
        m.transmit(next).unwrap();
    }
    next
}

#[test]
fn without_a_heartbeat_consumer_the_drive_is_guarded_and_stops_by_itself_when_the_master_dies() {
    let sim = shaped(|s, _| s.heartbeat_consumer = false);
    let cfg = MachineConfig::embedded();
    let mut r = run(&cfg, sim.clone(), &first_part());
    let s = r.result.as_ref().unwrap_or_else(|a| panic!("{a}"));
    assert!(s.at_program_end());
    // At the end of the run the master switched life guarding off before going silent.
    let t = r.world.now_ns() + 500 * MS;
    r.world.wait_until(t);
    for n in [1u8, 2, 3] {
        let d = r.world.drive(n).unwrap();
        assert_ne!(d.state(), State::Fault, "node {n} faulted after a normal end");
        assert_eq!(d.object(0x100C, 0), Some(0), "node {n}: life guarding off");
    }
    // Enabled, then the master dies: life guarding (100 ms × 3) faults the drives.
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, sim);
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("start-up");
    assert!([1, 2, 3].iter().all(|&n| m.guarded(n)), "node guarding instead of the heartbeat");
    let d = w.drive(1).unwrap();
    assert_eq!((d.object(0x100C, 0), d.object(0x100D, 0), d.object(0x1017, 0)), (Some(100), Some(3), Some(0)));
    let mut next = enable(&mut w, &mut m);
    for _ in 0..100 {
        next += 2 * MS;
        w.wait_until(next);
        m.receive(next).expect("guarded: no heartbeat alarm");
        m.transmit(next).unwrap();
    }
    assert_eq!(w.drive(1).unwrap().state(), State::OperationEnabled);
    w.wait_until(next + 400 * MS);
    for n in [1u8, 2, 3] {
        let d = w.drive(n).unwrap();
        assert_eq!((d.state(), d.error_code()), (State::Fault, 0x8130), "node {n}: life guarding");
    }
    // Neither heartbeat consumer nor guarding: runs, with a warning.
    let r = run(
        &cfg,
        shaped(|s, _| {
            s.heartbeat_consumer = false;
            s.node_guarding = false;
        }),
        &first_part(),
    );
    assert!(r.result.as_ref().unwrap_or_else(|a| panic!("{a}")).at_program_end());
    assert!(!r.master.guarded(1));
}

#[test]
fn start_up_sets_0x1029_so_that_a_drive_losing_the_master_leaves_operational() {
    // Nodes 1 and 2 have 0x1029 (shipped as 1, no state change), node 3 has none.
    let sim = shaped(|s, n| s.error_behaviour_object = n != 3);
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, sim);
    assert_eq!(w.drive(1).unwrap().object(0x1029, 1), Some(1));
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("start-up: a drive without 0x1029 is not refused");
    assert_eq!((w.drive(1).unwrap().object(0x1029, 1), w.drive(2).unwrap().object(0x1029, 1)), (Some(0), Some(0)));
    assert_eq!(w.drive(3).unwrap().object(0x1029, 1), None);
    let mut next = enable(&mut w, &mut m);
    for _ in 0..50 {
        next += 2 * MS;
        w.wait_until(next);
        m.receive(next).unwrap();
        m.transmit(next).unwrap();
    }
    assert_eq!((w.drive(1).unwrap().state(), w.drive(1).unwrap().nmt_state()), (State::OperationEnabled, NmtState::Operational));
    // The master dies: every drive's heartbeat consumer (3 × 100 ms) times out; 0x6007 = 1
    // faults it, and 0x1029:1 = 0 takes it to pre-operational (no more PDOs taken).
    w.wait_until(next + 400 * MS);
    for (n, nmt) in [(1u8, NmtState::PreOperational), (2, NmtState::PreOperational), (3, NmtState::Operational)] {
        let d = w.drive(n).unwrap();
        assert_eq!((d.state(), d.error_code(), d.nmt_state()), (State::Fault, 0x8130, nmt), "node {n}");
    }
}

/// Master A runs its cycle on `world` whenever master B waits on this clock.
struct BesideA<'a> {
    world: &'a mut SimWorld,
    a: &'a mut CanOpenMaster<InprocEndpoint>,
    next: u64,
}

impl Clock for BesideA<'_> {
    fn now_ns(&self) -> u64 {
        self.world.now_ns()
    }
    fn wait_until(&mut self, t: u64) {
        while self.next <= t {
            self.world.wait_until(self.next);
            self.a.receive(self.next).expect("master A runs on");
            for ax in 0..self.a.axis_count() {
                let p = self.a.feedback(ax).pos;
                self.a.set_target(ax, p);
            }
            self.a.transmit(self.next).unwrap();
            self.next += 2 * MS;
        }
        self.world.wait_until(t);
    }
    fn is_simulated(&self) -> bool {
        true
    }
}

#[test]
fn a_second_master_is_refused_before_it_resets_anything() {
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut a = CanOpenMaster::new(bus.endpoint(), &cfg);
    a.startup(&mut w).expect("master A starts");
    let mut next = w.now_ns();
    loop {
        next += 2 * MS;
        w.wait_until(next);
        a.receive(next).unwrap();
        let done = a.enable_step().unwrap();
        a.transmit(next).unwrap();
        if done {
            break;
        }
    }
    let resets: Vec<u32> = [1u8, 2, 3].iter().map(|&n| w.drive(n).unwrap().nmt_resets()).collect();
    let mut b = CanOpenMaster::new(bus.endpoint(), &cfg);
    let mut clock = BesideA { world: &mut w, a: &mut a, next: next + 2 * MS };
    let e = b.startup(&mut clock).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::FOREIGN_MASTER, "{e}");
    assert!(e.message.starts_with("another CANopen master is active on bus inproc: heard "), "{e}");
    assert!(e.message.contains("Nothing was reset"), "{e}");
    // Master A's machine runs on: no reset, every drive still enabled.
    let t = clock.now_ns() + 200 * MS;
    clock.wait_until(t);
    let resets_after: Vec<u32> = [1u8, 2, 3].iter().map(|&n| w.drive(n).unwrap().nmt_resets()).collect();
    assert_eq!(resets, resets_after);
    assert!(w.drives().iter().all(|d| d.state() == State::OperationEnabled));
}

#[test]
fn a_failed_start_up_restores_the_nmt_state_it_found() {
    // Drives already operational and heard (heartbeat 50 ms) when start-up begins; one of
    // them refuses the mode: everything goes back, and the drives are operational again.
    let sim = shaped(|s, node| {
        if node == 3 {
            s.modes = vec![1, 6];
        }
    });
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, sim.clone());
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    assert!(m.wait_boot(&mut w, 100));
    for n in [1u8, 2, 3] {
        m.sdo_write(&mut w, n, 0x1017, 0, &50u16.to_le_bytes()).unwrap();
    }
    m.nmt_command(0, cncgw_bus::canopen::nmt::NmtCommand::Start).unwrap();
    m.listen(&mut w, 10);
    let e = m.startup(&mut w).unwrap_err();
    assert_eq!(e.number, cncgw::alarm::DRIVE_MODE, "{e}");
    assert!(e.message.starts_with("node 3 (axis s1): this drive has no CSP"), "{e}");
    for n in [1u8, 2, 3] {
        let d = w.drive(n).unwrap();
        assert_eq!(d.nmt_state(), NmtState::Operational, "node {n} back in the state it was found in");
        assert_eq!(d.object(0x1400, 1), Some(0x200 + n as i64), "node {n}: RPDO1 valid");
        assert_eq!(d.object(0x6060, 0), Some(0), "node {n}: 0x6060 written back");
        assert_eq!(d.state(), State::SwitchOnDisabled);
    }
}

#[test]
fn the_master_heartbeat_keeps_its_period_on_a_cycle_that_does_not_divide_it() {
    // 3 ms cycle, 100 ms heartbeat: sent from the first cycle at or after each due time,
    // on the grid of due times (measured from each late send it ran at 102 ms).
    let mut cfg = MachineConfig::embedded();
    cfg.machine.cycle_ms = 3.0;
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    let mut spy = bus.endpoint();
    m.startup(&mut w).expect("start-up");
    while let Ok(Some(_)) = spy.try_recv() {}
    let mut beats = Vec::new();
    let mut next = w.now_ns();
    for _ in 0..2000 {
        next += 3 * MS;
        w.wait_until(next);
        m.receive(next).unwrap();
        let _ = m.enable_step().unwrap();
        m.transmit(next).unwrap();
        while let Ok(Some(f)) = spy.try_recv() {
            if f.cob_id() == 0x77F {
                beats.push(next);
            }
        }
    }
    let n = beats.len() as f64 - 1.0;
    let mean = (beats[beats.len() - 1] - beats[0]) as f64 / n / 1e6;
    eprintln!("master heartbeat: {} beats, mean period {mean:.3} ms", beats.len());
    assert!(beats.len() > 50);
    // Each beat is seen at its cycle (3 ms resolution at both ends of ≈ 60 periods).
    assert!((mean - 100.0).abs() < 0.11, "mean period {mean} ms");
}

#[test]
fn a_tpdo_of_the_wrong_length_is_alarm_2018_naming_both_lengths() {
    let cfg = MachineConfig::embedded();
    let bus = InprocBus::new();
    let mut w = SimWorld::new(&bus, SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap());
    let mut m = CanOpenMaster::new(bus.endpoint(), &cfg);
    m.startup(&mut w).expect("start-up");
    let mut next = w.now_ns();
    let mut cycle = |w: &mut SimWorld, m: &mut CanOpenMaster<InprocEndpoint>| -> Result<(), Alarm> {
        next += 2 * MS;
        w.wait_until(next);
        m.receive(next)?;
        let _ = m.enable_step()?;
        m.transmit(next)
    };
    for _ in 0..100 {
        cycle(&mut w, &mut m).unwrap();
    }
    // Someone remaps Z's TPDO1 to statusword + mode display: 3 bytes.
    m.sdo_write(&mut w, 2, 0x1800, 1, &0x8000_0182u32.to_le_bytes()).unwrap();
    m.sdo_write(&mut w, 2, 0x1A00, 0, &[0]).unwrap();
    m.sdo_write(&mut w, 2, 0x1A00, 2, &0x6061_0008u32.to_le_bytes()).unwrap();
    m.sdo_write(&mut w, 2, 0x1A00, 0, &[2]).unwrap();
    m.sdo_write(&mut w, 2, 0x1800, 1, &0x182u32.to_le_bytes()).unwrap();
    let mut alarm = None;
    for k in 0..20 {
        if let Err(a) = cycle(&mut w, &mut m) {
            alarm = Some((a, k));
            break;
        }
    }
    let (a, k) = alarm.expect("an alarm");
    assert_eq!(a.number, cncgw::alarm::TPDO_LENGTH, "{a}");
    assert!(a.message.starts_with("node 2 (axis z): TPDO1 (COB-ID 0x182) arrives with 3 bytes, start-up mapped 7 (0x6041 statusword, 0x6064 position actual, 0x6061 mode display)"), "{a}");
    assert!(k <= 4, "after {k} cycles");
    assert!(m.pdo_length_errors(2) >= 3);
}

// ---- As an operator runs it: `cncgw run --sim-config FILE` on the embedded drives, shaped.

/// `cncgw run --batch examples/first_part.nc` on three drives shaped by `shape` (TOML lines
/// of `[drive.shape]`). Exit code, stdout, stderr.
fn cli_run(name: &str, shape: &str) -> (i32, String, String) {
    let dir = std::env::temp_dir().join(format!("cncgw_startup_shapes_{name}_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut t = String::new();
    for (node, kind, axis, cpu) in [(1, "linear", "x", 10000.0), (2, "linear", "z", 10000.0), (3, "spindle", "s1", 1000.0)] {
        t.push_str(&format!("[[drive]]\nnode = {node}\nkind = \"{kind}\"\naxis = \"{axis}\"\ncounts_per_unit = {cpu:?}\n[drive.shape]\n{shape}\n"));
    }
    let sim = dir.join("drives.toml");
    std::fs::write(&sim, t).unwrap();
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .args(["run", "--batch", "--sim-config"])
        .arg(&sim)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc"))
        .env("CNCGW_STATE_DIR", &dir)
        .output()
        .expect("run cncgw");
    let _ = std::fs::remove_dir_all(&dir);
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stdout).into_owned(), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn cncgw_run_waits_for_a_pp_boot_drive_and_refuses_sync_producers_and_user_units() {
    let (code, out, err) = cli_run("pp", "boot_mode = 1\nmode_switch_ms = 300.0\nmode_switch_syncs = 50");
    assert_eq!(code, 0, "{out}{err}");
    assert!(out.contains("x ") && out.matches("ok (within 1 count)").count() == 2, "{out}");
    let (code, out, err) = cli_run("sync", "sync_producer = true");
    assert_eq!(code, 3, "{out}{err}");
    assert!(err.contains("alarm 2007: node 1 (axis x): the drive produces SYNC itself"), "{err}");
    assert!(!out.contains("ok (within"), "no summary of a run that never started: {out}");
    let (code, out, err) = cli_run("um", "feed_constant = 10000");
    assert_eq!(code, 3, "{out}{err}");
    assert!(err.contains("alarm 2006: node 1 (axis x): the drive scales positions") && err.contains("Set axes.x.counts_per_unit = 1000"), "{err}");
}

#[test]
fn an_eds_without_a_heartbeat_consumer_is_not_refused_but_a_wrong_optional_object_is() {
    // The Technosoft iPOS EDS has no 0x1016: start-up guards such a drive instead.
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds")).unwrap();
    let mut no_1016 = String::new();
    let mut skip = false;
    for l in text.lines() {
        if l.starts_with('[') {
            skip = l.starts_with("[1016");
        }
        if !skip {
            no_1016.push_str(l);
            no_1016.push('\n');
        }
    }
    assert!(!no_1016.contains("[1016]") && no_1016.contains("[1017]"));
    let cfg = MachineConfig::embedded();
    let m = CanOpenMaster::new(InprocBus::new().endpoint(), &cfg);
    let eds = cncgw_bus::canopen::eds::Eds::parse("ipos-like.eds", &no_1016).unwrap();
    assert_eq!(m.check_eds(1, &eds), Vec::<String>::new());
    // Present but read-only: still a problem, named with the file and line.
    let ro = text.replacen(
        "[100C]\nParameterName=Guard time\nObjectType=0x7\nDataType=0x0006\nAccessType=rw",
        "[100C]\nParameterName=Guard time\nObjectType=0x7\nDataType=0x0006\nAccessType=ro",
        1,
    );
    assert_ne!(ro, text);
    let eds = cncgw_bus::canopen::eds::Eds::parse("ro.eds", &ro).unwrap();
    let bad = m.check_eds(1, &eds);
    assert_eq!(bad.len(), 1, "{bad:?}");
    assert!(bad[0].contains("[100C] \"Guard time\": AccessType=ro but the master writes 0x100C:00"), "{bad:?}");
}
