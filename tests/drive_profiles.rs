//! Issue 21: drives as machine builders buy them, emulated by sim-drives' named profiles
//! (`[[drive]] profile = "ip-only" | "pp-boot" | "no-1016" | "fixed-pdo"`), in simulated
//! time: `examples/first_part.nc` runs to its end point (within one count, on the drives' own
//! positions), or start-up stops before any motion with an alarm naming the object and
//! what to configure. Also start-up lists (`[[axes.NAME.sdo]]`) written and read back.

use cncgw::canon::Pos;
use cncgw::config::{CyclicMode, MachineConfig, EMBEDDED_LATHE};
use cncgw::drives::canopen::CanOpenMaster;
use cncgw::interp::Interpreter;
use cncgw::motion::cycle::{CycleLoop, RunSummary};
use cncgw::motion::{Limits, AX_S, AX_X, AX_Y, AX_Z};
use cncgw::Alarm;
use cncgw_bus::transport::inproc::{InprocBus, InprocEndpoint};
use sim_drives::config::Shape;
use sim_drives::{SimConfig, SimWorld};

const IP: u32 = 1 << 7;

fn first_part() -> String {
    std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc")).unwrap()
}

/// The default lathe's drives, every one of the named profile, then changed by `f`.
fn profiled(name: &str, f: impl Fn(&mut Shape)) -> SimConfig {
    let mut sim = SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap();
    for d in &mut sim.drives {
        d.shape = Shape::profile(name).unwrap();
        f(&mut d.shape);
    }
    sim
}

/// The default lathe with every axis in interpolated position.
fn ip_machine() -> MachineConfig {
    let mut cfg = MachineConfig::embedded();
    for a in cfg.axes.values_mut() {
        a.mode = CyclicMode::Ip;
    }
    cfg
}

struct Ran {
    result: Result<RunSummary, Alarm>,
    world: SimWorld,
    #[allow(dead_code)]
    master: CanOpenMaster<InprocEndpoint>,
    start: [i64; 3],
}

/// `program` on `cfg`'s machine with the emulated drives of `sim`, as `cncgw run` does it.
fn run(cfg: &MachineConfig, sim: SimConfig, program: &str) -> Ran {
    let mut interp = Interpreter::from_source("first_part.nc", program, cfg).expect("program parses");
    let wire = InprocBus::new();
    let mut world = SimWorld::new(&wire, sim);
    let start = [1, 2, 3].map(|n| world.drive(n).unwrap().position_unwrapped());
    let mut master = CanOpenMaster::new(wire.endpoint(), cfg);
    let spindle = cfg.spindle_index();
    let mut summary = RunSummary::default();
    let r = {
        let mut lp = CycleLoop::new(&mut master, &mut world, Limits::from_config(cfg), spindle, 2_000_000);
        match lp.start(&mut summary) {
            Err(a) => Err(a),
            Ok(st) => {
                interp.set_start_position(Pos { x: st[AX_X], y: st[AX_Y], z: st[AX_Z], c: st[AX_S] });
                let (tx, rx) = std::sync::mpsc::sync_channel(64);
                std::thread::spawn(move || {
                    for m in interp {
                        if tx.send(m).is_err() {
                            break;
                        }
                    }
                });
                let r = lp.run(st, rx, &mut summary, &mut |_| {});
                lp.finish();
                r
            }
        }
    };
    Ran { result: r.map(|_| summary), world, master, start }
}

impl Ran {
    fn alarm(&self) -> &Alarm {
        match &self.result {
            Err(a) => a,
            Ok(s) => panic!("expected an alarm, the run ended: {s:?}"),
        }
    }

    fn summary(&self) -> &RunSummary {
        self.result.as_ref().unwrap_or_else(|a| panic!("{a}"))
    }

    fn assert_nothing_moved(&self) {
        for (k, n) in [1u8, 2, 3].into_iter().enumerate() {
            let d = self.world.drive(n).unwrap();
            assert_eq!(d.enabled_modes(), 0, "node {n} was enabled");
            assert_eq!(d.position_unwrapped(), self.start[k], "node {n} moved");
        }
    }

    /// At the end point of first_part (X100 Z5, X a diameter), within one count, on the
    /// drives' own positions.
    fn assert_at_end_point(&self) {
        let s = self.summary();
        assert!(s.at_program_end(), "{s:#?}");
        for (n, want) in [(1u8, 500_000i64), (2, 50_000)] {
            let p = self.world.drive(n).unwrap().position_unwrapped();
            assert!((p - want).abs() <= 1, "node {n} at {p}, end point {want}");
        }
    }
}

#[test]
fn ip_only_drives_run_first_part_in_interpolated_position_to_its_end_point() {
    let r = run(&ip_machine(), profiled("ip-only", |_| {}), &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        let d = r.world.drive(n).unwrap();
        assert_eq!(d.enabled_modes(), IP, "node {n} was enabled in another mode than IP");
        // Linear sub-mode and the interpolation period = the 2 ms cycle.
        assert_eq!(d.object(0x60C0, 0), Some(0), "node {n}");
        assert_eq!((d.object(0x60C2, 1), d.object(0x60C2, 2)), (Some(2), Some(-3)), "node {n}");
        // Set-points went into 0x60C1:1 by RPDO1.
        assert_eq!(d.object(0x1600, 2), Some(0x60C1_0120), "node {n}");
    }
    for a in &r.summary().axes[1..] {
        assert!(a.max_following_error < 0.05, "axis {} lagged {} mm: a jump", a.name, a.max_following_error);
    }
}

#[test]
fn csp_on_an_ip_only_drive_stops_before_motion_and_names_the_ip_key() {
    let r = run(&MachineConfig::embedded(), profiled("ip-only", |_| {}), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, 2005, "{a}");
    assert!(a.message.starts_with("node 1 (axis x): this drive has no CSP (cyclic synchronous position) mode"), "{a}");
    assert!(a.message.contains("set axes.x.mode = \"ip\""), "{a}");
    r.assert_nothing_moved();
    // Without 0x6502 the refusal of 0x6060 = 8 (abort 0x06090030) says the same.
    let r = run(&MachineConfig::embedded(), profiled("ip-only", |s| s.supported_modes_object = false), &first_part());
    let a = r.alarm();
    assert_eq!(a.number, 2003, "{a}");
    assert!(a.message.contains("it refuses 0x6060 = 8") && a.message.contains("axes.NAME.mode = \"ip\""), "{a}");
    assert!(a.message.contains("0x06090030"), "{a}");
    r.assert_nothing_moved();
}

#[test]
fn a_drive_booting_in_profile_position_is_switched_to_ip_and_confirmed_before_it_is_enabled() {
    // Boots in PP (0x6061 = 1); a new mode shows 200 SYNCs (400 ms) after 0x6060 is written.
    let sim = profiled("ip-only", |s| {
        s.boot_mode = 1;
        s.mode_switch_syncs = 200;
    });
    let r = run(&ip_machine(), sim, &first_part());
    r.assert_at_end_point();
    for n in [1u8, 2, 3] {
        assert_eq!(r.world.drive(n).unwrap().enabled_modes(), IP, "node {n} was enabled in PP");
    }
    assert!(r.summary().enable_time_s > 0.4, "waited for the mode: enabled after {} s", r.summary().enable_time_s);
}
