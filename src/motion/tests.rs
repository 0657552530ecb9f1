use super::*;
use crate::canon::{CycleTag, SrcPos};
use proptest::prelude::*;
use std::sync::Arc;

/// The embedded machine's limits for ideal drives: the actual is the last setpoint.
fn lim() -> Limits {
    let mut l = Limits::from_config(&MachineConfig::embedded());
    l.feedback_delay = 1;
    l
}

fn mv(line: u32, kind: MoveKind) -> Move {
    Move { src: SrcPos::new(Arc::from("t.nc"), line, 1), kind, exact_stop: true, work_offset: Pos::ZERO, tag: None::<CycleTag> }
}

fn rapid(x: f64, z: f64) -> MoveKind {
    MoveKind::Rapid { end: Pos::xz(x, z) }
}
fn feed(x: f64, z: f64, f: f64) -> MoveKind {
    MoveKind::Feed { end: Pos::xz(x, z), feed: Feed::PerMin(f) }
}
fn spindle(dir: SpindleDir, rpm: f64) -> MoveKind {
    MoveKind::Spindle(SpindleCmd { dir, rpm, css: None, max_rpm: None })
}

const START: [f64; N_AXES] = [50.0, 0.0, 0.0, 0.0];

/// Step until idle (and `extra` cycles more), with an ideal spindle drive: the measured speed is
/// last cycle's command.
fn run(m: &mut Motion, max: usize) -> Vec<Setpoint> {
    let mut out = Vec::new();
    // The drives are where the last setpoint put them (the sync monitor reads this).
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    while !m.is_idle() {
        assert!(out.len() < max, "not idle after {max} cycles");
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        out.push(sp);
    }
    out
}

/// No axis exceeds its speed or acceleration, judged on the setpoints as the drives see them
/// (first and second differences), starting at rest at `start`.
fn check_limits(l: &Limits, start: [f64; N_AXES], sps: &[Setpoint]) -> Result<(), String> {
    let dt = l.cycle_s;
    let mut p = start;
    let mut v = [0.0; N_AXES];
    for (k, sp) in sps.iter().enumerate() {
        for i in 0..N_AXES {
            let nv = (sp.pos[i] - p[i]) / dt;
            let acc = (nv - v[i]) / dt;
            if nv.abs() > l.vmax[i] * (1.0 + 1e-9) + 1e-9 {
                return Err(format!("cycle {k}: axis {i} speed {nv} > {}", l.vmax[i]));
            }
            // The spindle angle integrates the speed, so its second difference is the
            // speed step: also bounded by amax.
            if acc.abs() > l.amax[i] * (1.0 + 1e-6) + 1e-6 {
                return Err(format!("cycle {k}: axis {i} accel {acc} > {} (v {} → {nv})", l.amax[i], v[i]));
            }
            if (sp.vel[i] - nv).abs() > 1e-6 * (1.0 + nv.abs()) {
                return Err(format!("cycle {k}: axis {i} vel {} disagrees with setpoints {nv}", sp.vel[i]));
            }
            p[i] = sp.pos[i];
            v[i] = nv;
        }
    }
    Ok(())
}

#[test]
fn straight_feed_takes_expected_time_and_ends_exactly() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(10, feed(50.0, -100.0, 1200.0))).unwrap();
    let sps = run(&mut m, 10_000);
    // 20 mm/s, 2000 mm/s²: 100/20 + 20/2000 = 5.01 s; +1 cycle of exact stop at rest.
    let expect = 5.01 / l.cycle_s + 1.0;
    assert!((sps.len() as f64 - expect).abs() <= 2.0, "{} cycles, expected {expect}", sps.len());
    let last = sps.last().unwrap();
    assert_eq!(last.pos[AX_Z], -100.0);
    assert_eq!(last.pos[AX_X], 50.0);
    assert_eq!(last.line, 10);
    let top = sps.iter().map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top - 1200.0).abs() < 1e-9, "top speed {top}");
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn diagonal_feed_ends_bit_exact_on_both_axes() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    let (x, z) = (12.345678912345, -77.77777777777);
    m.push(&mv(1, feed(x, z, 3000.0))).unwrap();
    let sps = run(&mut m, 20_000);
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (x, z));
    // The landing cycle is the one before the rest cycle; both sit on the end point.
    assert_eq!(sps[sps.len() - 2].pos, last.pos);
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn rapid_runs_at_the_slowest_axis_rate_in_a_straight_line() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    // X 40 mm at 10000 mm/min and Z 40 mm at 12000: X limits, path = √2·X speed.
    m.push(&mv(1, rapid(10.0, -40.0))).unwrap();
    let sps = run(&mut m, 10_000);
    let vx = sps.iter().map(|s| s.vel[AX_X].abs()).fold(0.0, f64::max);
    let vz = sps.iter().map(|s| s.vel[AX_Z].abs()).fold(0.0, f64::max);
    assert!((vx - 10000.0 / 60.0).abs() < 1e-6, "x at {vx}");
    assert!((vz - vx).abs() < 1e-6, "z at {vz}, must follow the straight line");
    for s in &sps {
        // On the line x − 50 = (z − 0)·(−40/−40)… i.e. x = 50 + z.
        assert!((s.pos[AX_X] - (50.0 + s.pos[AX_Z])).abs() < 1e-9);
    }
    assert_eq!(sps.last().unwrap().pos[..3], [10.0, 0.0, -40.0]);
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn feed_is_clamped_by_parameter_6023() {
    let l = lim();
    assert!((l.feed_clamp - 5000.0 / 60.0).abs() < 1e-12);
    let mut m = Motion::new(l, START);
    m.push(&mv(1, feed(50.0, -200.0, 9000.0))).unwrap();
    let top = run(&mut m, 100_000).iter().map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top - 5000.0).abs() < 1e-9, "top {top}");
}

fn arc_zx(x: f64, z: f64, cx: f64, cz: f64, cw: bool, f: f64) -> MoveKind {
    MoveKind::Arc { end: Pos::xz(x, z), center: Pos::xz(cx, cz), cw, plane: Plane::Zx, feed: Feed::PerMin(f) }
}

#[test]
fn arc_stays_on_the_circle_and_ends_exactly() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    // Quarter circle r = 20 about (x 50, z −20), from (50, 0) to (70, −20) counter-clockwise,
    // then a full circle back the other way round.
    m.push(&mv(1, arc_zx(70.0, -20.0, 50.0, -20.0, false, 2000.0))).unwrap();
    m.push(&mv(2, arc_zx(70.0, -20.0, 50.0, -20.0, true, 2000.0))).unwrap();
    let sps = run(&mut m, 100_000);
    let mut n_on = 0;
    for s in &sps {
        let r = (s.pos[AX_X] - 50.0).hypot(s.pos[AX_Z] + 20.0);
        assert!((r - 20.0).abs() <= 1e-6, "off circle by {}", r - 20.0);
        n_on += 1;
    }
    assert!(n_on > 1000);
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (70.0, -20.0));
    // Quarter: 31.4 mm, full: 125.7 mm at 33.3 mm/s ≈ 4.7 s.
    let t = sps.len() as f64 * l.cycle_s;
    assert!((t - (157.08 / (2000.0 / 60.0))).abs() < 0.1, "took {t} s");
    check_limits(&l, START, &sps).unwrap();
    // Sense: in the (Z, X) plane seen from +Y (Z right, X up), counter-clockwise from the
    // +Z side of the centre goes up, towards +X.
    let first = sps.iter().find(|s| s.pos[AX_X] != 50.0).unwrap();
    assert!(first.pos[AX_X] > 50.0);
    // The full circle passes below the centre (x < 40 at some point), clockwise.
    assert!(sps.iter().any(|s| s.pos[AX_X] < 31.0));
}

#[test]
fn small_arc_speed_respects_chord_tolerance_and_accel() {
    // Stiff axes, so that the chord tolerance rather than the centripetal acceleration limits
    // the speed on a small arc.
    let mut l = lim();
    l.amax = [50_000.0, 50_000.0, 50_000.0, l.amax[AX_S]];
    let mut m = Motion::new(l.clone(), START);
    // r = 1 mm at F5000: centripetal and chord limits must slow it down.
    m.push(&mv(1, arc_zx(51.0, -1.0, 50.0, -1.0, true, 5000.0))).unwrap();
    let sps = run(&mut m, 100_000);
    let mut prev = [START[0], START[2]];
    for s in &sps {
        let cur = [s.pos[AX_X], s.pos[AX_Z]];
        // Sagitta of the chord prev→cur: distance of its midpoint from the circle.
        let mid = [(prev[0] + cur[0]) / 2.0, (prev[1] + cur[1]) / 2.0];
        let sag = 1.0 - (mid[0] - 50.0).hypot(mid[1] + 1.0);
        assert!(sag <= l.chord_tol + 1e-9, "sagitta {sag}");
        prev = cur;
    }
    // ... and the chord limit is what binds: √(8·r·tol)/dt = 44.7 mm/s.
    let top = sps.iter().map(|s| s.path_feed).fold(0.0, f64::max) / 60.0;
    assert!((top - (8.0f64 * 1.0 * l.chord_tol).sqrt() / l.cycle_s).abs() < 1e-6, "top {top} mm/s");
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn dwell_of_half_a_second_lasts_250_cycles() {
    let mut m = Motion::new(lim(), START);
    m.push(&mv(5, MoveKind::Dwell { seconds: 0.5 })).unwrap();
    m.push(&mv(6, MoveKind::Aux { letter: 'M', value: 8.0 })).unwrap();
    let fb = Feedback::default();
    let mut n = 0;
    loop {
        let sp = m.step(&fb);
        n += 1;
        assert_eq!(sp.pos, START);
        if sp.event != Event::None {
            assert_eq!(sp.event, Event::Aux { letter: 'M', value: 8.0 });
            break;
        }
        assert_eq!(sp.line, 5);
        assert!(n < 1000);
    }
    assert_eq!(n, 251, "dwell lasted {} cycles", n - 1);
}

#[test]
fn spindle_ramps_at_its_acceleration_and_angle_integrates_speed() {
    let l = lim();
    let dt = l.cycle_s;
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 1000.0))).unwrap();
    m.push(&mv(2, MoveKind::Dwell { seconds: 0.3 })).unwrap();
    m.push(&mv(3, spindle(SpindleDir::Ccw, 500.0))).unwrap();
    m.push(&mv(4, MoveKind::Dwell { seconds: 0.5 })).unwrap();
    m.push(&mv(5, spindle(SpindleDir::Stop, 0.0))).unwrap();
    m.push(&mv(6, MoveKind::Dwell { seconds: 0.2 })).unwrap();
    let sps = run(&mut m, 10_000);
    let step = 6000.0 * dt; // rpm per cycle
    let mut rpm = 0.0;
    let mut ang = START[AX_S];
    let mut reached_1000 = None;
    for (k, s) in sps.iter().enumerate() {
        assert!((s.spindle_rpm - rpm).abs() <= step + 1e-9, "cycle {k}: {rpm} → {}", s.spindle_rpm);
        assert!((s.pos[AX_S] - ang - s.spindle_rpm * 6.0 * dt).abs() < 1e-9, "angle is not the integral");
        if reached_1000.is_none() && s.spindle_rpm == 1000.0 {
            reached_1000 = Some(k);
        }
        rpm = s.spindle_rpm;
        ang = s.pos[AX_S];
    }
    // 1000 rpm at 6000 rpm/s: 1/6 s = 83.3 cycles.
    assert_eq!(reached_1000, Some(84));
    assert!(sps.iter().any(|s| s.spindle_rpm == -500.0), "reached M04 speed");
    assert_eq!(sps.last().unwrap().spindle_rpm, 0.0);
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn css_speed_follows_commanded_x_and_is_clamped() {
    let mut m = Motion::new(lim(), START);
    let css = SpindleCmd { dir: SpindleDir::Cw, rpm: 0.0, css: Some(100.0), max_rpm: Some(3000.0) };
    m.push(&mv(1, MoveKind::Spindle(css))).unwrap();
    m.push(&mv(2, MoveKind::Dwell { seconds: 0.2 })).unwrap();
    let sps = run(&mut m, 1000);
    let want = 100_000.0 / (std::f64::consts::TAU * 50.0);
    assert!((sps.last().unwrap().spindle_rpm - want).abs() < 1e-9);
    m.push(&mv(3, feed(2.0, 0.0, 4000.0))).unwrap();
    m.push(&mv(4, MoveKind::Dwell { seconds: 0.5 })).unwrap();
    let sps = run(&mut m, 10_000);
    // Mid-way through the facing cut the speed tracks x; at x = 2 the clamp holds.
    let mid = sps.iter().find(|s| s.pos[AX_X] < 20.0).unwrap();
    assert!(mid.spindle_rpm > want * 2.0);
    assert_eq!(sps.last().unwrap().spindle_rpm, 3000.0);
}

#[test]
fn events_arrive_in_order_after_the_preceding_motion() {
    let mut m = Motion::new(lim(), START);
    m.push(&mv(1, rapid(30.0, -5.0))).unwrap();
    m.push(&mv(2, MoveKind::Aux { letter: 'M', value: 8.0 })).unwrap();
    m.push(&mv(3, MoveKind::Aux { letter: 'T', value: 101.0 })).unwrap();
    m.push(&mv(4, MoveKind::Stop { optional: true })).unwrap(); // switch off: no wait
    m.push(&mv(5, feed(30.0, -10.0, 500.0))).unwrap();
    m.push(&mv(6, MoveKind::End { code: 30 })).unwrap();
    let sps = run(&mut m, 10_000);
    let evs: Vec<(Event, u32, f64)> = sps.iter().filter(|s| s.event != Event::None).map(|s| (s.event, s.line, s.pos[AX_Z])).collect();
    assert_eq!(
        evs,
        vec![
            (Event::Aux { letter: 'M', value: 8.0 }, 2, -5.0),
            (Event::Aux { letter: 'T', value: 101.0 }, 3, -5.0),
            (Event::Stop { optional: true }, 4, -5.0),
            (Event::End, 6, -10.0),
        ]
    );
    // After the end: the final position, no events, idle.
    let fb = Feedback::default();
    for _ in 0..100 {
        let sp = m.step(&fb);
        assert_eq!(sp.pos[..3], [30.0, 0.0, -10.0]);
        assert_eq!(sp.event, Event::None);
        assert_eq!(sp.vel[..3], [0.0; 3]);
        assert!(m.is_idle());
    }
}

#[test]
fn m00_waits_for_cycle_start() {
    let mut m = Motion::new(lim(), START);
    m.push(&mv(1, MoveKind::Stop { optional: false })).unwrap();
    m.push(&mv(2, rapid(40.0, 0.0))).unwrap();
    let fb = Feedback::default();
    assert_eq!(m.step(&fb).event, Event::Stop { optional: false });
    for _ in 0..50 {
        assert_eq!(m.step(&fb).pos, START);
    }
    assert!(m.is_held() && !m.is_idle());
    m.cycle_start();
    let sps = run(&mut m, 10_000);
    assert_eq!(sps.last().unwrap().pos[AX_X], 40.0);
}

#[test]
fn move_beyond_travel_is_refused_and_nothing_moves() {
    let mut m = Motion::new(lim(), START);
    let e = m.push(&mv(7, rapid(160.0, 0.0))).unwrap_err();
    assert_eq!(e.number, alarms::TRAVEL);
    assert_eq!(e.pos.as_ref().map(|p| p.line), Some(7));
    assert!(e.message.contains("X end point"), "{}", e.message);
    let e = m.push(&mv(8, feed(50.0, 6.0, 100.0))).unwrap_err();
    assert_eq!(e.number, alarms::TRAVEL);
    let e = m.push(&mv(9, MoveKind::Rapid { end: Pos { y: 3.0, ..Pos::xz(50.0, 0.0) } })).unwrap_err();
    assert!(e.message.contains("not configured"), "{}", e.message);
    assert!(m.is_idle());
    assert_eq!(m.step(&Feedback::default()).pos, START);
}

#[test]
fn bad_feeds_and_arcs_are_refused() {
    let mut m = Motion::new(lim(), START);
    let per_rev = MoveKind::Feed { end: Pos::xz(50.0, -10.0), feed: Feed::PerRev(0.1) };
    assert_eq!(m.push(&mv(1, per_rev.clone())).unwrap_err().number, alarms::PER_REV_SPINDLE_STOPPED);
    assert_eq!(m.push(&mv(1, feed(50.0, -10.0, 0.0))).unwrap_err().number, alarms::FEED_ZERO);
    assert_eq!(m.push(&mv(1, feed(50.0, -10.0, f64::NAN))).unwrap_err().number, alarms::FEED_ZERO);
    // End 21 mm from the centre, start 20 mm.
    assert_eq!(m.push(&mv(1, arc_zx(71.0, -20.0, 50.0, -20.0, true, 100.0))).unwrap_err().number, alarms::ARC_RADIUS);
    assert_eq!(m.push(&mv(1, MoveKind::Dwell { seconds: -1.0 })).unwrap_err().number, alarms::BAD_VALUE);
    m.push(&mv(2, spindle(SpindleDir::Cw, 1000.0))).unwrap();
    m.push(&mv(3, per_rev)).unwrap();
    m.push(&mv(4, spindle(SpindleDir::Stop, 0.0))).unwrap();
    let again = MoveKind::Feed { end: Pos::xz(50.0, -20.0), feed: Feed::PerRev(0.1) };
    assert_eq!(m.push(&mv(5, again)).unwrap_err().number, alarms::PER_REV_SPINDLE_STOPPED);
}

#[test]
fn per_rev_feed_follows_measured_spindle_speed() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 1000.0))).unwrap();
    m.push(&mv(2, MoveKind::Feed { end: Pos::xz(50.0, -10.0), feed: Feed::PerRev(0.2) })).unwrap();
    let sps = run(&mut m, 100_000);
    // 0.2 mm/rev × 1000 rpm = 200 mm/min once the spindle is up to speed.
    let top = sps.iter().map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top - 200.0).abs() < 1e-6, "top {top}");
    // While the spindle ramps, the feed stays at or below F × measured rpm (+ one accel step).
    let dv = l.amax[AX_Z] * l.cycle_s * 60.0;
    for w in sps.windows(2) {
        assert!(w[1].path_feed <= 0.2 * w[0].spindle_rpm + dv + 1e-9);
    }
    assert_eq!(sps.last().unwrap().pos[AX_Z], -10.0);
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn stop_decelerates_on_the_path_and_drops_the_rest() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 2000.0))).unwrap();
    m.push(&mv(2, rapid(10.0, -300.0))).unwrap();
    m.push(&mv(3, rapid(100.0, 0.0))).unwrap();
    let fb = Feedback::default();
    let mut sps: Vec<Setpoint> = (0..300).map(|_| m.step(&fb)).collect();
    assert!(sps.last().unwrap().path_feed > 1000.0);
    m.stop();
    assert!(!m.is_idle());
    assert_eq!(m.push(&mv(4, rapid(0.0, 0.0))).unwrap_err().number, alarms::STOPPING);
    sps.extend(run(&mut m, 10_000));
    for _ in 0..200 {
        sps.push(m.step(&fb));
    }
    check_limits(&l, START, &sps).unwrap();
    let last = *sps.last().unwrap();
    // Stopped on the first rapid's line (x − 50 = 40/300 · z), short of its end.
    assert!((last.pos[AX_X] - (50.0 + 40.0 / 300.0 * last.pos[AX_Z])).abs() < 1e-9);
    assert!(last.pos[AX_Z] > -300.0);
    assert_eq!(last.spindle_rpm, 0.0);
    // Planning restarts from the stop point.
    m.push(&mv(5, rapid(last.pos[AX_X], 0.0))).unwrap();
    let sps = run(&mut m, 10_000);
    assert!(sps.iter().all(|s| s.pos[AX_X] == last.pos[AX_X]));
    assert_eq!(sps.last().unwrap().pos[AX_Z], 0.0);
}

#[test]
fn feed_hold_decelerates_and_resumes() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, feed(50.0, -50.0, 3000.0))).unwrap();
    let fb = Feedback::default();
    let mut sps: Vec<Setpoint> = (0..200).map(|_| m.step(&fb)).collect();
    m.feed_hold();
    sps.extend((0..200).map(|_| m.step(&fb)));
    let held_at = sps.last().unwrap().pos;
    assert_eq!(sps.last().unwrap().path_feed, 0.0);
    assert_eq!(m.step(&fb).pos, held_at);
    m.cycle_start();
    sps.extend(run(&mut m, 10_000));
    assert_eq!(sps.last().unwrap().pos[AX_Z], -50.0);
    check_limits(&l, START, &sps[..]).unwrap();
}

#[test]
fn feed_override_scales_cutting_feed() {
    let mut m = Motion::new(lim(), START);
    m.set_feed_override(0.5);
    m.push(&mv(1, feed(50.0, -20.0, 1000.0))).unwrap();
    let top = run(&mut m, 100_000).iter().map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top - 500.0).abs() < 1e-9);
}

#[test]
fn queue_full_is_refused() {
    let mut l = lim();
    l.queue_len = 2;
    let mut m = Motion::new(l, START);
    m.push(&mv(1, rapid(40.0, 0.0))).unwrap();
    m.push(&mv(2, rapid(30.0, 0.0))).unwrap();
    assert!(!m.has_room());
    assert_eq!(m.push(&mv(3, rapid(20.0, 0.0))).unwrap_err().number, alarms::QUEUE_FULL);
    let sps = run(&mut m, 10_000);
    assert_eq!(sps.last().unwrap().pos[AX_X], 30.0);
}

/// A random program segment inside the travel limits.
#[derive(Clone, Debug)]
enum Seg3 {
    Rapid(f64, f64),
    Feed(f64, f64, f64),
    Arc { cx: f64, cz: f64, ang: f64, sweep: f64, r: f64, cw: bool, f: f64 },
}

fn seg_strategy() -> impl Strategy<Value = Seg3> {
    prop_oneof![
        (0.0..150.0f64, -400.0..5.0f64).prop_map(|(x, z)| Seg3::Rapid(x, z)),
        // F ≥ 50 mm/min: 430 mm at F1 would take 13 million cycles, past `run`'s budget.
        (0.0..150.0f64, -400.0..5.0f64, 50.0..8000.0f64).prop_map(|(x, z, f)| Seg3::Feed(x, z, f)),
        (0.5..40.0f64, 0.0..6.3f64, 0.01..6.3f64, any::<bool>(), 10.0..6000.0f64, 40.0..100.0f64, -300.0..-50.0f64)
            .prop_map(|(r, ang, sweep, cw, f, cx, cz)| Seg3::Arc { cx, cz, ang, sweep, r, cw, f }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]
    #[test]
    fn random_programs_respect_limits_and_end_exactly(segs in prop::collection::vec(seg_strategy(), 1..6)) {
        let l = lim();
        let mut m = Motion::new(l.clone(), START);
        let mut end = (START[AX_X], START[AX_Z]);
        for (i, s) in segs.iter().enumerate() {
            let line = i as u32 + 1;
            match *s {
                Seg3::Rapid(x, z) => { m.push(&mv(line, rapid(x, z))).unwrap(); end = (x, z); }
                Seg3::Feed(x, z, f) => { m.push(&mv(line, feed(x, z, f))).unwrap(); end = (x, z); }
                Seg3::Arc { cx, cz, ang, sweep, r, cw, f } => {
                    // Move to the start point on the circle, then the arc.
                    let (sx, sz) = (cx + r * ang.sin(), cz + r * ang.cos());
                    m.push(&mv(line, rapid(sx, sz))).unwrap();
                    let a1 = if cw { ang - sweep } else { ang + sweep };
                    let (ex, ez) = (cx + r * a1.sin(), cz + r * a1.cos());
                    m.push(&mv(line, arc_zx(ex, ez, cx, cz, cw, f))).unwrap();
                    end = (ex, ez);
                }
            }
        }
        let sps = run(&mut m, 2_000_000);
        let last = sps.last().unwrap();
        prop_assert_eq!((last.pos[AX_X], last.pos[AX_Z]), end);
        if let Err(e) = check_limits(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
    }
}

// ---- Look-ahead (G64) ----

fn mv_g64(line: u32, kind: MoveKind) -> Move {
    Move { exact_stop: false, ..mv(line, kind) }
}

#[test]
fn collinear_g64_segments_keep_the_feed_through_the_junctions() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    for (i, z) in [-10.0, -20.0, -30.0, -40.0].iter().enumerate() {
        m.push(&mv_g64(i as u32 + 1, feed(50.0, *z, 1200.0))).unwrap();
    }
    m.push(&mv(5, feed(50.0, -50.0, 1200.0))).unwrap();
    let sps = run(&mut m, 100_000);
    for s in &sps {
        if s.pos[AX_Z] < -2.0 && s.pos[AX_Z] > -48.0 {
            assert_eq!(s.path_feed, 1200.0, "slowed down at z {}", s.pos[AX_Z]);
        }
    }
    // 50 mm at 20 mm/s plus the ramps at the blended (half) acceleration, 1000 mm/s².
    let t = sps.len() as f64 * l.cycle_s;
    assert!((t - (2.5 + 0.02)).abs() < 0.01, "took {t} s");
    assert_eq!(sps.last().unwrap().pos[AX_Z], -50.0);
    check_limits(&l, START, &sps).unwrap();
}

/// Distance of `p` from the segment `a`–`b` (plane points).
fn dist_seg(p: (f64, f64), a: (f64, f64), b: (f64, f64)) -> f64 {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let t = (((p.0 - a.0) * dx + (p.1 - a.1) * dy) / (dx * dx + dy * dy)).clamp(0.0, 1.0);
    (p.0 - a.0 - t * dx).hypot(p.1 - a.1 - t * dy)
}

#[test]
fn g64_corner_is_crossed_at_the_corner_speed_and_g61_stops_there() {
    let l = lim();
    for exact in [false, true] {
        let mut m = Motion::new(l.clone(), START);
        // Along −Z, then turning 30° towards +X.
        let (x2, z2) = (50.0 + 10.0 * 0.5, -20.0 - 10.0 * 0.75f64.sqrt());
        m.push(&Move { exact_stop: exact, ..mv(1, feed(50.0, -20.0, 2000.0)) }).unwrap();
        m.push(&mv(2, feed(x2, z2, 2000.0))).unwrap();
        let sps = run(&mut m, 100_000);
        check_limits(&l, START, &sps).unwrap();
        let k = sps.iter().position(|s| s.line == 2).unwrap();
        // Speed in the cycle that reaches (G61) or crosses (G64) the corner.
        let corner = sps[k - 1..=k].iter().map(|s| s.path_feed).fold(f64::INFINITY, f64::min);
        let at_rest = sps.iter().any(|s| s.pos[..3] == [50.0, 0.0, -20.0] && s.vel[..3] == [0.0; 3]);
        if exact {
            assert!(at_rest, "G61 must stop on the corner");
        } else {
            // 30°: X's speed jumps by v·sin 30° across the corner; v·0.5 ≤ ½·a·dt ⇒ v ≤ 4 mm/s.
            assert!(!at_rest, "G64 must not stop on the corner");
            assert!(corner > 0.0 && corner <= 240.0 + 1e-9, "corner speed {corner} mm/min");
            // The corner is cut by less than one cycle's travel.
            let dev = sps
                .iter()
                .map(|s| {
                    let p = (s.pos[AX_X], s.pos[AX_Z]);
                    dist_seg(p, (50.0, 0.0), (50.0, -20.0)).min(dist_seg(p, (50.0, -20.0), (x2, z2)))
                })
                .fold(f64::MIN, f64::max);
            assert!(dev <= 240.0 / 60.0 * l.cycle_s, "cut the corner by {dev} mm");
        }
    }
}

#[test]
fn g64_late_push_still_blends_or_stops_safely() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv_g64(1, feed(50.0, -30.0, 3000.0))).unwrap();
    let fb = Feedback::default();
    let mut sps: Vec<Setpoint> = (0..300).map(|_| m.step(&fb)).collect();
    // Pushed while the first is already braking for its (provisional) exact stop.
    m.push(&mv_g64(2, feed(50.0, -60.0, 3000.0))).unwrap();
    sps.extend((0..400).map(|_| m.step(&fb)));
    m.push(&mv(3, feed(60.0, -60.0, 3000.0))).unwrap();
    sps.extend(run(&mut m, 100_000));
    check_limits(&l, START, &sps).unwrap();
    assert_eq!(sps.last().unwrap().pos[..3], [60.0, 0.0, -60.0]);
}

#[test]
fn g64_tiny_segments_run_without_stopping() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    // A 0.05 mm polyline approximating a shallow curve: more segments than cycles per mm.
    let n = 200;
    let mut longest: f64 = 0.0;
    let mut prev = (50.0, 0.0);
    for i in 1..=n {
        let z = -0.05 * i as f64;
        let x = 50.0 + 0.2 * (z / 3.0).sin();
        longest = longest.max((x - prev.0).hypot(z - prev.1));
        prev = (x, z);
        let k = if i == n { mv(i, feed(x, z, 3000.0)) } else { mv_g64(i, feed(x, z, 3000.0)) };
        m.push(&k).unwrap();
    }
    let sps = run(&mut m, 100_000);
    check_limits(&l, START, &sps).unwrap();
    let moving = &sps[5..sps.len() - 5];
    assert!(moving.iter().all(|s| s.path_feed > 0.0), "stopped on the way");
    // Several junctions per cycle: the feed (3000 mm/min, 0.1 mm per cycle, two segments of
    // ≈ 0.05 mm) is reached; one junction per cycle capped it at ≈ 1500 mm/min.
    let vmax = MAX_JUNCTIONS as f64 * longest / l.cycle_s * 60.0;
    assert!(sps.iter().all(|s| s.path_feed <= vmax + 1e-9), "more than MAX_JUNCTIONS segments per cycle");
    assert!(sps.iter().any(|s| s.path_feed > 0.99 * 3000.0), "tiny segments ran slower than the feed");
    assert!(sps.iter().all(|s| s.path_feed <= 3000.0 * (1.0 + 1e-9)), "faster than the feed");
}

// ---- CAM contours: chains of tiny segments (issue 23) ----

/// Pushes `moves` as the cycle loop does (whenever there is room, one step otherwise), then
/// runs to idle: every setpoint, from `start` at rest.
fn feed_and_run(m: &mut Motion, start: [f64; N_AXES], moves: &[Move]) -> Vec<Setpoint> {
    let mut fb = Feedback { pos: start, spindle_rpm: 0.0, ..Default::default() };
    let mut out = Vec::new();
    for k in moves {
        while !m.has_room() {
            let sp = m.step(&fb);
            fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
            out.push(sp);
        }
        m.push(k).unwrap();
    }
    out.extend(run_from(m, fb, 10_000_000));
    out
}

/// A half circle of radius `r` (centre X 30, Z −100, from its +Z end over +X) as `n` G1
/// chords at feed `f` (G64, the last one an exact stop), run from its start.
/// Returns the start, the end, the chain's length and the setpoints.
fn run_chord_half_circle(l: &Limits, r: f64, n: usize, f: f64) -> ([f64; N_AXES], [f64; 2], f64, Vec<Setpoint>) {
    let pt = |k: usize| {
        let th = std::f64::consts::PI * k as f64 / n as f64;
        (30.0 + r * th.sin(), -100.0 + r * th.cos())
    };
    let mut len = 0.0;
    let mut prev = pt(0);
    let mut moves = Vec::new();
    for k in 1..=n {
        let (x, z) = pt(k);
        len += (x - prev.0).hypot(z - prev.1);
        prev = (x, z);
        let k32 = k as u32;
        moves.push(if k == n { mv(k32, feed(x, z, f)) } else { mv_g64(k32, feed(x, z, f)) });
    }
    let (x0, z0) = pt(0);
    let start = [x0, 0.0, z0, 0.0];
    let sps = feed_and_run(&mut Motion::new(l.clone(), start), start, &moves);
    (start, [prev.0, prev.1], len, sps)
}

/// Cycles from the first setpoint that moves to the last one (inclusive), times the cycle.
fn path_time(l: &Limits, start: [f64; N_AXES], sps: &[Setpoint]) -> f64 {
    let mut p = start;
    let (mut first, mut last) = (None, 0);
    for (k, s) in sps.iter().enumerate() {
        if s.pos != p {
            first.get_or_insert(k);
            last = k;
        }
        p = s.pos;
    }
    (last + 1 - first.unwrap_or(0)) as f64 * l.cycle_s
}

/// Runs a chord half circle R20 and checks the run: axis limits on the setpoints, the path
/// speed never above the feed, the end exactly on the end point at rest. Returns the ratio of
/// the optimum time (L/F at the feed, ramps at the axes' full acceleration) to the path time.
fn chord_ratio(chord: f64, f: f64) -> f64 {
    chord_run(chord, f, 0.0).0
}

/// `chord_ratio` with a jerk limit `j` on X and Z (0: none); also the largest change of an
/// axis acceleration from one cycle to the next.
fn chord_run(chord: f64, f: f64, j: f64) -> (f64, f64) {
    let mut l = lim();
    l.feed_clamp = f64::INFINITY;
    l.jmax[AX_X] = j;
    l.jmax[AX_Z] = j;
    let n = (std::f64::consts::PI * 20.0 / chord).round() as usize;
    let (start, end, len, sps) = run_chord_half_circle(&l, 20.0, n, f);
    check_limits(&l, start, &sps).unwrap();
    assert!(sps.iter().all(|s| s.path_feed <= f * (1.0 + 1e-9)), "faster than F{f}");
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (end[0], end[1]), "not on the end point");
    assert_eq!(last.vel[..3], [0.0; 3], "not at rest at the end");
    let v = f / 60.0;
    let (mut p, mut vel, mut acc, mut dacc) = (start, [0.0; 3], [0.0; 3], 0.0f64);
    for s in &sps {
        for i in [AX_X, AX_Z] {
            let nv = (s.pos[i] - p[i]) / l.cycle_s;
            let na = (nv - vel[i]) / l.cycle_s;
            dacc = dacc.max((na - acc[i]).abs());
            (vel[i], acc[i]) = (nv, na);
        }
        p = s.pos;
    }
    // Jerk-limited ramps at the axes' full acceleration take A/J longer each.
    let ramps = v / l.amax[AX_X] + if j > 0.0 { l.amax[AX_X] / j } else { 0.0 };
    ((len / v + ramps) / path_time(&l, start, &sps), dacc)
}

#[test]
fn chord_half_circle_runs_at_90_percent_of_the_optimum() {
    // 0.05 mm chords at F3000 and 0.02 mm at F6000: 0.49 and 0.10 with one junction a cycle.
    for (chord, f) in [(0.05, 3000.0), (0.02, 6000.0)] {
        let r = chord_ratio(chord, f);
        assert!(r >= 0.9, "{chord} mm chords at F{f}: {r:.3} of the optimum");
    }
}

#[test]
fn chord_half_circle_with_s_curve_keeps_the_jerk_bound_at_90_percent() {
    // No.1772 = 32 ms (j = 62 500 mm/s³): the chain brakes with one jerk-limited profile;
    // the axes' acceleration changes by j·dt per cycle (plus the chords' small turns), and
    // the ratio to the optimum (ramps `v/A + A/J` at the axes' A) stays ≥ 0.9 (0.85 while
    // the look-ahead counted only v²/2A for a cruise at the feed).
    let j = 2000.0 / 0.032;
    for (chord, f) in [(0.05, 3000.0), (0.02, 6000.0)] {
        let (r, dacc) = chord_run(chord, f, j);
        assert!(r >= 0.9, "{chord} mm chords at F{f}: {r:.3} of the optimum");
        assert!(dacc <= 1.1 * j * lim().cycle_s, "{chord} mm chords at F{f}: Δa {dacc} mm/s² per cycle");
    }
}

#[test]
fn chord_chain_speed_is_limited_by_its_centripetal_acceleration() {
    // R1 in 0.01 mm chords at F6000: a circle's chords turn by h/R each, so the axes see the
    // centripetal v²/R (times their share of the normal); the chain must slow down to keep it
    // within the corner's share, ½·2000 mm/s² on each axis: v ≤ √(1000·1) ≈ 31.6 mm/s where
    // one axis takes all of it, √(1000·√2) ≈ 37.6 mm/s at 45°. Not 100 mm/s.
    let mut l = lim();
    l.feed_clamp = f64::INFINITY;
    let n = (std::f64::consts::PI * 1.0 / 0.01).round() as usize;
    let (start, _, _, sps) = run_chord_half_circle(&l, 1.0, n, 6000.0);
    check_limits(&l, start, &sps).unwrap();
    let top = sps.iter().map(|s| s.path_feed / 60.0).fold(0.0, f64::max);
    assert!(top <= (1000.0 * 2f64.sqrt()).sqrt() * 1.01, "top speed {top} mm/s");
    assert!(top >= 0.9 * 1000f64.sqrt(), "top speed {top} mm/s: slower than needed");
}

#[test]
fn at_most_max_junctions_are_crossed_per_cycle() {
    // 0.001 mm segments at F6000 (100 mm/s = 200 segments per cycle): capped at
    // MAX_JUNCTIONS segments per cycle, the line number advancing by at most that much.
    let mut l = lim();
    l.feed_clamp = f64::INFINITY;
    l.queue_len = 4096;
    let mut m = Motion::new(l.clone(), START);
    let n = 3000;
    for i in 1..=n {
        let z = -0.001 * i as f64;
        let k = if i == n { mv(i, feed(50.0, z, 6000.0)) } else { mv_g64(i, feed(50.0, z, 6000.0)) };
        m.push(&k).unwrap();
    }
    let sps = run(&mut m, 1_000_000);
    check_limits(&l, START, &sps).unwrap();
    let cap = MAX_JUNCTIONS as f64 * 0.001 / l.cycle_s * 60.0;
    assert!(sps.iter().all(|s| s.path_feed <= cap * (1.0 + 1e-6)), "more than MAX_JUNCTIONS per cycle");
    let top = sps.iter().map(|s| s.path_feed).fold(0.0, f64::max);
    // The crossing speed stays a speed step (a·dt) below the junctions' limit.
    assert!(top >= 0.9 * cap, "never near the cap {cap}: {top}");
    assert!(sps.windows(2).all(|w| w[1].line - w[0].line <= MAX_JUNCTIONS as u32));
    assert_eq!(sps.last().unwrap().pos[AX_Z], -0.001 * n as f64);
}

#[test]
fn a_starved_queue_limits_the_speed_to_what_it_can_stop_within() {
    // The interpreter stops delivering mid-contour: the chain queued so far (G64 up to its
    // last block, which has no successor yet) must end at rest exactly on its last point,
    // within the limits — the speed allowed was one the queued distance can brake from.
    let mut l = lim();
    l.feed_clamp = f64::INFINITY;
    for q in [4, 16, 64] {
        l.queue_len = q;
        let mut m = Motion::new(l.clone(), START);
        let mut z = 0.0;
        for i in 1..=q as u32 {
            z -= 0.05;
            m.push(&mv_g64(i, feed(50.0, z, 6000.0))).unwrap();
        }
        let sps = run(&mut m, 1_000_000);
        check_limits(&l, START, &sps).unwrap();
        assert_eq!(sps.last().unwrap().pos[AX_Z], z, "queue {q}");
        // Braking within the queued 0.05·q mm at the blended 1000 mm/s²: v ≤ √(2·1000·L).
        let top = sps.iter().map(|s| s.path_feed / 60.0).fold(0.0, f64::max);
        assert!(top <= (2.0 * 1000.0 * 0.05 * q as f64).sqrt() + 2.0, "queue {q}: {top} mm/s");
    }
}

/// One block of a random chain of short segments: its length, the turn from the previous
/// direction (radians), the feed (mm/min); or a pause of the interpreter (cycles).
#[derive(Clone, Debug)]
enum Short {
    Seg {
        len: f64,
        turn: f64,
        f: f64,
    },
    /// A G2/G3 of radius `r` turning by `phi` (radians, + = counter-clockwise seen from +Y),
    /// tangent to the direction so far.
    Arc {
        r: f64,
        phi: f64,
        f: f64,
    },
    Starve(usize),
    /// Feed hold for that many cycles, then cycle start.
    Hold(usize),
}

fn short_strategy() -> impl Strategy<Value = Short> {
    prop_oneof![
        8 => (0.001..0.2f64, -0.3..0.3f64, 100.0..8000.0f64).prop_map(|(len, turn, f)| Short::Seg { len, turn, f }),
        1 => (0.001..0.2f64, -2.5..2.5f64, 100.0..8000.0f64).prop_map(|(len, turn, f)| Short::Seg { len, turn, f }),
        2 => (0.02..2.0f64, -1.0..1.0f64, 100.0..8000.0f64).prop_map(|(r, phi, f)| Short::Arc { r, phi, f }),
        1 => (1..40usize).prop_map(Short::Starve),
        1 => (1..200usize).prop_map(Short::Hold),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]
    /// Random chains of short G64 segments (smooth and sharp turns, feed changes, an
    /// tangent arcs, an interpreter that pauses, feed holds, a small queue): no axis beyond its speed or acceleration in
    /// any cycle, the path speed never above the feed, and the end exactly on the last point
    /// at rest.
    #[test]
    fn random_short_segment_chains_respect_limits_and_end_at_rest(
        blocks in prop::collection::vec(short_strategy(), 1..300),
        queue in 8..300usize,
        scurve in any::<bool>(),
    ) {
        let mut l = lim();
        l.feed_clamp = f64::INFINITY;
        l.queue_len = queue;
        if scurve {
            l.jmax = [50_000.0, 50_000.0, 50_000.0, 0.0];
        }
        // 300 blocks of ≤ 0.2 mm stay within the travel from here.
        let start = [75.0, 0.0, -200.0, 0.0];
        let mut m = Motion::new(l.clone(), start);
        let (mut x, mut z, mut dir) = (start[AX_X], start[AX_Z], std::f64::consts::PI);
        let mut sps = Vec::new();
        let mut fb = Feedback { pos: start, spindle_rpm: 0.0, ..Default::default() };
        let mut fmax: f64 = 0.0;
        let segs = blocks.iter().filter(|b| matches!(b, Short::Seg { .. } | Short::Arc { .. })).count();
        let mut pushed = 0;
        for b in &blocks {
            match *b {
                Short::Seg { .. } | Short::Arc { .. } => {
                    let (kind, f) = match *b {
                        Short::Seg { len, turn, f } => {
                            dir += turn;
                            x += len * dir.sin();
                            z += len * dir.cos();
                            (feed(x, z, f), f)
                        }
                        Short::Arc { r, phi, f } => {
                            // Centre on the side the arc turns to; (z, x) is the plane with the
                            // angle measured from +Z towards +X.
                            let side = phi.signum();
                            let (cz, cx) = (z - side * r * dir.sin(), x + side * r * dir.cos());
                            let th0 = (x - cx).atan2(z - cz);
                            z = cz + r * (th0 + phi).cos();
                            x = cx + r * (th0 + phi).sin();
                            dir += phi;
                            (arc_zx(x, z, cx, cz, phi < 0.0, f), f)
                        }
                        _ => unreachable!(),
                    };
                    pushed += 1;
                    fmax = fmax.max(f);
                    let k = Move { exact_stop: pushed == segs, ..mv(pushed as u32, kind) };
                    while !m.has_room() {
                        let sp = m.step(&fb);
                        fb = Feedback { pos: sp.pos, spindle_rpm: 0.0, ..Default::default() };
                        sps.push(sp);
                    }
                    m.push(&k).unwrap();
                }
                Short::Starve(n) | Short::Hold(n) => {
                    if matches!(b, Short::Hold(_)) {
                        m.feed_hold();
                    }
                    for _ in 0..n {
                        let sp = m.step(&fb);
                        fb = Feedback { pos: sp.pos, spindle_rpm: 0.0, ..Default::default() };
                        sps.push(sp);
                    }
                    m.cycle_start();
                }
            }
        }
        sps.extend(run_from(&mut m, fb, 5_000_000));
        if let Err(e) = check_limits(&l, start, &sps) {
            prop_assert!(false, "{}", e);
        }
        prop_assert!(sps.iter().all(|s| s.path_feed <= fmax * (1.0 + 1e-9)));
        if pushed > 0 {
            let last = sps.last().unwrap();
            prop_assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (x, z));
            prop_assert_eq!(&last.vel[..3], &[0.0; 3]);
        }
    }
}

/// A random chain of lines and arcs, with random exact-stop flags, from the current point.
#[derive(Clone, Debug)]
enum Step {
    Line { x: f64, z: f64, f: f64, exact: bool },
    Arc { dx: f64, dz: f64, ang: f64, cw: bool, f: f64, exact: bool },
}

fn chain_strategy() -> impl Strategy<Value = Step> {
    prop_oneof![
        (10.0..140.0f64, -390.0..-10.0f64, 10.0..6000.0f64, any::<bool>()).prop_map(|(x, z, f, exact)| Step::Line { x, z, f, exact }),
        (-8.0..8.0f64, -8.0..8.0f64, 0.0..6.3f64, any::<bool>(), 10.0..6000.0f64, any::<bool>()).prop_map(|(dx, dz, ang, cw, f, exact)| Step::Arc {
            dx,
            dz,
            ang,
            cw,
            f,
            exact
        }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]
    #[test]
    fn random_g64_chains_respect_limits_and_end_exactly(steps in prop::collection::vec(chain_strategy(), 1..10)) {
        let l = lim();
        let start = [60.0, 0.0, -100.0, 0.0];
        let mut m = Motion::new(l.clone(), start);
        let mut cur = (start[AX_X], start[AX_Z]);
        for (i, s) in steps.iter().enumerate() {
            let line = i as u32 + 1;
            let last = i + 1 == steps.len();
            match *s {
                Step::Line { x, z, f, exact } => {
                    m.push(&Move { exact_stop: exact || last, ..mv(line, feed(x, z, f)) }).unwrap();
                    cur = (x, z);
                }
                Step::Arc { dx, dz, ang, cw, f, exact } => {
                    let (cx, cz) = (cur.0 + dx, cur.1 + dz);
                    let r = dx.hypot(dz);
                    if r < 0.1 { continue; }
                    let (ex, ez) = (cx + r * ang.sin(), cz + r * ang.cos());
                    match m.push(&Move { exact_stop: exact || last, ..mv(line, arc_zx(ex, ez, cx, cz, cw, f)) }) {
                        Ok(()) => cur = (ex, ez),
                        // End point or bulge beyond the travel: refused, the chain goes on.
                        Err(e) if e.number == alarms::TRAVEL => continue,
                        Err(e) => prop_assert!(false, "{}", e),
                    }
                }
            }
        }
        let sps = run(&mut m, 5_000_000);
        if let Some(last) = sps.last() {
            prop_assert_eq!((last.pos[AX_X], last.pos[AX_Z]), cur);
        }
        if let Err(e) = check_limits(&l, start, &sps) {
            prop_assert!(false, "{}", e);
        }
    }
}

// ---- Threading and rigid tapping ----

fn thread(x: f64, z: f64, lead: f64, start_angle: f64) -> MoveKind {
    MoveKind::Thread { end: Pos::xz(x, z), lead, start_angle, continuous: false, lead_inc: 0.0 }
}

/// Run a thread pass after `wait` seconds of dwell; return the setpoints and, for the cycles
/// locked to the spindle, the phase θ − 360·(z0 − z)/lead of the same cycle's setpoints
/// (constant when locked: the lock predicts the spindle one cycle ahead).
fn thread_pass(wait: f64, start_angle: f64) -> (Vec<Setpoint>, Vec<f64>) {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 600.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    m.push(&mv(3, MoveKind::Dwell { seconds: wait })).unwrap();
    m.push(&mv(4, thread(20.0, -30.0, 2.0, start_angle))).unwrap();
    let sps = run(&mut m, 100_000);
    check_limits(&l, START, &sps).unwrap();
    assert_eq!(sps.last().unwrap().pos[..3], [20.0, 0.0, -30.0]);
    // Locked cycles: thread running at full synchronous speed, 20 mm/s at 600 rpm × 2 mm.
    let mut phases = Vec::new();
    for k in 1..sps.len() {
        if sps[k].line == 4 && (sps[k].path_feed - 1200.0).abs() < 1e-6 {
            let theta = sps[k].pos[AX_S];
            phases.push(theta - 360.0 * (2.0 - sps[k].pos[AX_Z]) / 2.0);
        }
    }
    assert!(phases.len() > 500, "only {} locked cycles", phases.len());
    (sps, phases)
}

#[test]
fn thread_is_locked_to_the_spindle_angle_with_the_programmed_phase() {
    let (_, ph) = thread_pass(0.1, 0.0);
    for p in &ph {
        assert!((p - ph[0]).abs() < 1e-6, "phase drifts: {p} vs {}", ph[0]);
    }
    // θ0 ≡ start angle (0°) modulo one revolution.
    let r = ph[0].rem_euclid(360.0);
    assert!(r.min(360.0 - r) < 1e-6, "phase {} ≢ 0", ph[0]);
}

#[test]
fn repeated_thread_passes_cut_the_same_groove_and_start_angle_shifts_it() {
    let (_, a) = thread_pass(0.1, 0.0);
    let (_, b) = thread_pass(0.337, 0.0); // spindle at a different angle when the pass starts
    let (_, c) = thread_pass(0.1, 180.0); // second start of a two-start thread
    let d_ab = (a[0] - b[0]).rem_euclid(360.0);
    assert!(d_ab.min(360.0 - d_ab) < 1e-6, "passes differ by {d_ab}°");
    let d_ac = (c[0] - a[0]).rem_euclid(360.0);
    assert!((d_ac - 180.0).abs() < 1e-6, "second start offset {d_ac}°");
}

#[test]
fn thread_is_refused_without_spindle_or_when_too_fast() {
    let mut m = Motion::new(lim(), START);
    assert_eq!(m.push(&mv(1, thread(50.0, -10.0, 2.0, 0.0))).unwrap_err().number, alarms::PER_REV_SPINDLE_STOPPED);
    m.push(&mv(2, spindle(SpindleDir::Cw, 3000.0))).unwrap();
    // 10 mm × 3000 rpm = 30 m/min, more than Z's 12 m/min.
    assert_eq!(m.push(&mv(3, thread(50.0, -10.0, 10.0, 0.0))).unwrap_err().number, alarms::THREAD_TOO_FAST);
}

#[test]
fn rigid_tap_keeps_spindle_angle_and_z_locked_and_returns() {
    let l = lim();
    let mut m = Motion::new(l.clone(), [0.0, 0.0, 0.0, 0.0]);
    m.push(&mv(1, spindle(SpindleDir::Cw, 800.0))).unwrap(); // running: the tap brakes it first
    m.push(&mv(2, rapid(0.0, 2.0))).unwrap();
    m.push(&mv(3, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
    m.push(&mv(4, MoveKind::Tap { end: Pos::xz(0.0, 2.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
    let sps = run(&mut m, 100_000);
    check_limits(&l, [0.0; N_AXES], &sps).unwrap();
    let first = sps.iter().position(|s| s.line == 3).unwrap();
    let stroke: Vec<&Setpoint> = sps[first..].iter().filter(|s| s.line >= 3).collect();
    // The spindle is at rest when the stroke starts; take its angle there.
    let k0 = stroke.iter().position(|s| s.pos[AX_Z] != 2.0).unwrap();
    assert_eq!(stroke[k0 - 1].spindle_rpm, 0.0);
    let th0 = stroke[k0 - 1].pos[AX_S];
    for s in &stroke[k0 - 1..] {
        let want = th0 + 360.0 * (s.pos[AX_Z] - 2.0) / 1.5;
        assert!((s.pos[AX_S] - want).abs() < 1e-9, "spindle {} vs {want} at z {}", s.pos[AX_S], s.pos[AX_Z]);
    }
    // Bottom reached exactly, and the reverse stroke brings the spindle back to its angle.
    assert!(sps.iter().any(|s| s.pos[AX_Z] == -20.0));
    let last = sps.last().unwrap();
    assert_eq!(last.pos[AX_Z], 2.0);
    assert_eq!(last.pos[AX_S], th0);
    // 1000 rpm × 1.5 mm = 25 mm/s at full speed, turning backwards (−Z with a + lead).
    let top = sps.iter().map(|s| s.spindle_rpm).fold(0.0, f64::min);
    assert!((top + 1000.0).abs() < 1e-6, "tap speed {top} rpm");
}

#[test]
fn arc_bulging_beyond_travel_is_refused() {
    let start = [145.0, 0.0, -10.0, 0.0];
    let mut m = Motion::new(lim(), start);
    // Half circle r = 10 about (x 145, z −20): counter-clockwise it passes x = 155 > 150.
    let e = m.push(&mv(1, arc_zx(145.0, -30.0, 145.0, -20.0, false, 1000.0))).unwrap_err();
    assert_eq!(e.number, alarms::TRAVEL);
    assert!(e.message.contains("X arc 155"), "{}", e.message);
    // Clockwise it passes x = 135: fine.
    m.push(&mv(2, arc_zx(145.0, -30.0, 145.0, -20.0, true, 1000.0))).unwrap();
    let sps = run(&mut m, 100_000);
    assert!(sps.iter().all(|s| s.pos[AX_X] <= 145.0 + 1e-9));
    assert_eq!(sps.last().unwrap().pos[AX_Z], -30.0);
}

#[test]
fn rapid_override_scales_rapids_only() {
    let mut m = Motion::new(lim(), START);
    m.set_rapid_override(0.25);
    m.set_feed_override(2.0);
    m.push(&mv(1, rapid(50.0, -100.0))).unwrap();
    m.push(&mv(2, feed(50.0, -110.0, 600.0))).unwrap();
    let sps = run(&mut m, 100_000);
    let top = |line| sps.iter().filter(|s| s.line == line).map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top(1) - 3000.0).abs() < 1e-6, "rapid at {}", top(1));
    assert!((top(2) - 1200.0).abs() < 1e-6, "feed at {}", top(2));
}

/// Rapid override F0 is No.1421's rate (Fanuc), not 0 % of the rapid rate; without No.1421
/// rapids stand at F0 (and go on when the override is raised).
#[test]
fn rapid_override_f0_is_no_1421s_rate() {
    let mut l = lim();
    l.rapid_f0 = 600.0 / 60.0; // No.1421 = 600 mm/min
    let mut m = Motion::new(l, START);
    m.set_rapid_override(0.0);
    m.push(&mv(1, rapid(50.0, -20.0))).unwrap();
    let sps = run(&mut m, 100_000);
    let top = sps.iter().filter(|s| s.line == 1).map(|s| s.path_feed).fold(0.0, f64::max);
    assert!((top - 600.0).abs() < 1e-6, "F0 rapid at {top} mm/min");
    // Unset: nothing moves at F0.
    let mut m = Motion::new(lim(), START);
    m.set_rapid_override(0.0);
    m.push(&mv(1, rapid(50.0, -20.0))).unwrap();
    let fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
    for _ in 0..500 {
        let sp = m.step(&fb);
        assert_eq!(sp.pos[AX_Z], 0.0, "moved at F0 without No.1421");
    }
}

#[test]
fn feed_hold_waits_for_the_end_of_a_thread() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 600.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    m.push(&mv(3, thread(20.0, -30.0, 2.0, 0.0))).unwrap();
    m.push(&mv(4, rapid(25.0, -30.0))).unwrap();
    let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
    let mut sps = Vec::new();
    for k in 0..20_000 {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        sps.push(sp);
        if sp.line == 3 && sp.pos[AX_Z] < -10.0 && !m.is_held() {
            m.feed_hold(); // mid-thread: must not stop the cut
        }
        if k > 10_000 {
            break;
        }
    }
    // The thread ran to its end at full speed; the hold then stopped before the next rapid.
    assert!(sps.iter().any(|s| s.pos[AX_Z] == -30.0 && s.line == 3));
    assert!(sps.iter().all(|s| s.line != 4 || s.pos[AX_X] == 20.0));
    assert!(m.is_held());
    check_limits(&l, START, &sps).unwrap();
}

/// Arbitrary, including non-finite, numbers.
fn any_f64() -> impl Strategy<Value = f64> + Clone {
    prop_oneof![-500.0..500.0f64, Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY), Just(0.0), Just(-0.0), Just(1e300), Just(-1e-300),]
}

fn any_move() -> impl Strategy<Value = MoveKind> {
    fn pos() -> impl Strategy<Value = Pos> {
        // Mostly valid coordinates, so that motion actually runs, sometimes anything.
        (
            prop_oneof![3 => 0.0..150.0f64, 1 => any_f64()],
            prop_oneof![3 => Just(0.0), 1 => any_f64()],
            prop_oneof![3 => -400.0..5.0f64, 1 => any_f64()],
            prop_oneof![3 => Just(0.0), 1 => any_f64()],
        )
            .prop_map(|(x, y, z, c)| Pos { x, y, z, c })
    }
    prop_oneof![
        pos().prop_map(|end| MoveKind::Rapid { end }),
        (pos(), any_f64(), any::<bool>()).prop_map(|(end, f, r)| MoveKind::Feed { end, feed: if r { Feed::PerRev(f) } else { Feed::PerMin(f) } }),
        (pos(), pos(), any::<bool>(), 0..3u8, any_f64()).prop_map(|(end, center, cw, pl, f)| MoveKind::Arc {
            end,
            center,
            cw,
            plane: [Plane::Xy, Plane::Zx, Plane::Yz][pl as usize],
            feed: Feed::PerMin(f)
        }),
        (pos(), any_f64(), any_f64()).prop_map(|(end, lead, start_angle)| MoveKind::Thread {
            end,
            lead,
            start_angle,
            continuous: false,
            lead_inc: 0.0
        }),
        (pos(), any_f64(), any_f64()).prop_map(|(end, lead, rpm)| MoveKind::Tap { end, lead, rpm, spindle: 1 }),
        any_f64().prop_map(|seconds| MoveKind::Dwell { seconds: seconds.abs().min(0.05) }),
        (0..3u8, any_f64(), prop::option::of(any_f64()), prop::option::of(any_f64())).prop_map(|(d, rpm, css, max_rpm)| {
            MoveKind::Spindle(SpindleCmd { dir: [SpindleDir::Cw, SpindleDir::Ccw, SpindleDir::Stop][d as usize], rpm, css, max_rpm })
        }),
        any::<bool>().prop_map(|optional| MoveKind::Stop { optional }),
    ]
}

/// Operator actions between cycles.
#[derive(Clone, Debug)]
enum Op {
    Steps(u16),
    Hold,
    Start,
    Stop,
    FeedOvr(f64),
    RapidOvr(f64),
    Fb(f64, f64),
    Single(bool),
}

fn any_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => (1..400u16).prop_map(Op::Steps),
        1 => Just(Op::Hold),
        2 => Just(Op::Start),
        1 => Just(Op::Stop),
        1 => any_f64().prop_map(Op::FeedOvr),
        1 => any_f64().prop_map(Op::RapidOvr),
        1 => (any_f64(), any_f64()).prop_map(|(a, r)| Op::Fb(a, r)),
        1 => any::<bool>().prop_map(Op::Single),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// No input makes push or step panic; the setpoint stays finite and inside the travel.
    #[test]
    fn arbitrary_moves_and_operator_actions_never_panic(
        moves in prop::collection::vec((any_move(), any::<bool>()), 0..12),
        ops in prop::collection::vec(any_op(), 0..12),
    ) {
        let l = lim();
        let mut m = Motion::new(l.clone(), START);
        for (i, (k, exact)) in moves.iter().enumerate() {
            let _ = m.push(&Move { exact_stop: *exact, ..mv(i as u32, k.clone()) });
        }
        let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
        for op in &ops {
            match *op {
                Op::Steps(n) => {
                    for _ in 0..n {
                        let sp = m.step(&fb);
                        for i in 0..3 {
                            prop_assert!(sp.pos[i].is_finite());
                            if l.present[i] {
                                prop_assert!(sp.pos[i] >= l.travel[i].0.min(START[i]) - 1e-9);
                                prop_assert!(sp.pos[i] <= l.travel[i].1.max(START[i]) + 1e-9);
                            }
                        }
                        prop_assert!(sp.pos[AX_S].is_finite() && sp.spindle_rpm.is_finite());
                        // The spindle's limit, within the rounding of a position difference.
                        prop_assert!(sp.spindle_rpm.abs() <= 6000.0 * (1.0 + 1e-9));
                        fb.pos = sp.pos;
                    }
                }
                Op::Hold => m.feed_hold(),
                Op::Start => m.cycle_start(),
                Op::Stop => m.stop(),
                Op::FeedOvr(f) => m.set_feed_override(f),
                Op::RapidOvr(f) => m.set_rapid_override(f),
                Op::Fb(a, r) => { fb.pos[AX_S] = a; fb.spindle_rpm = r; }
                Op::Single(on) => m.set_single_block(on),
            }
        }
        let _ = m.take_alarm();
    }

    /// Feed hold, cycle start, override changes and a stop at random moments of a G64 chain
    /// never push an axis past its limits.
    #[test]
    fn operator_actions_during_g64_chains_respect_limits(
        steps in prop::collection::vec(chain_strategy(), 1..8),
        ops in prop::collection::vec(any_op(), 1..16),
    ) {
        let l = lim();
        let start = [60.0, 0.0, -100.0, 0.0];
        let mut m = Motion::new(l.clone(), start);
        let mut cur = (start[AX_X], start[AX_Z]);
        for (i, s) in steps.iter().enumerate() {
            let k = match *s {
                Step::Line { x, z, f, exact } => (feed(x, z, f), exact, (x, z)),
                Step::Arc { dx, dz, ang, cw, f, exact } => {
                    let (cx, cz) = (cur.0 + dx, cur.1 + dz);
                    let r = dx.hypot(dz);
                    if r < 0.1 { continue; }
                    let e = (cx + r * ang.sin(), cz + r * ang.cos());
                    (arc_zx(e.0, e.1, cx, cz, cw, f), exact, e)
                }
            };
            if m.push(&Move { exact_stop: k.1, ..mv(i as u32 + 1, k.0) }).is_ok() {
                cur = k.2;
            }
        }
        let mut sps = Vec::new();
        let fb = Feedback::default();
        for op in &ops {
            match *op {
                Op::Steps(n) => sps.extend((0..n).map(|_| m.step(&fb))),
                Op::Hold => m.feed_hold(),
                Op::Start => m.cycle_start(),
                Op::Stop => m.stop(),
                Op::FeedOvr(f) => m.set_feed_override(f),
                Op::RapidOvr(f) => m.set_rapid_override(f),
                Op::Fb(..) => {}
                Op::Single(on) => m.set_single_block(on),
            }
        }
        m.cycle_start();
        let mut n = 0;
        while !m.is_idle() && n < 5_000_000 {
            sps.push(m.step(&fb));
            n += 1;
            if n % 1000 == 0 {
                m.set_feed_override(1.0);
                m.cycle_start();
            }
        }
        prop_assert!(m.is_idle(), "never finished");
        if let Err(e) = check_limits(&l, start, &sps) {
            prop_assert!(false, "{}", e);
        }
    }
}

/// Found by `operator_actions_during_g64_chains_respect_limits`: two ZX arcs then a line in
/// G64; Z exceeded its acceleration by 0.005 % in the cycle that crossed a junction.
#[test]
fn g64_arc_arc_line_chain_respects_axis_acceleration() {
    let l = lim();
    let start = [60.0, 0.0, -100.0, 0.0];
    let mut m = Motion::new(l.clone(), start);
    let mut cur = (start[AX_X], start[AX_Z]);
    let arcs: [(f64, f64, f64, f64); 2] = [
        (7.745089048262591, 5.698848737278121, 5.873325701664951, 1706.2782375199995),
        (-1.498093624610482, 2.6751980848044883, 5.696948537933448, 2001.550879933548),
    ];
    for (i, &(dx, dz, ang, f)) in arcs.iter().enumerate() {
        let (cx, cz) = (cur.0 + dx, cur.1 + dz);
        let r = dx.hypot(dz);
        let e = (cx + r * ang.sin(), cz + r * ang.cos());
        m.push(&mv_g64(i as u32 + 1, arc_zx(e.0, e.1, cx, cz, false, f))).unwrap();
        cur = e;
    }
    m.push(&mv_g64(3, feed(29.37159612284516, -198.92710961056466, 452.73766351187834))).unwrap();
    let sps = run(&mut m, 1_000_000);
    assert!(m.is_idle());
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (29.37159612284516, -198.92710961056466));
    check_limits(&l, start, &sps).unwrap();
}

#[test]
fn single_block_stops_after_every_block_even_in_g64() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.set_single_block(true);
    let ends = [(50.0, -10.0), (55.0, -20.0), (55.0, -30.0)];
    for (i, (x, z)) in ends.iter().enumerate() {
        m.push(&mv_g64(i as u32 + 1, feed(*x, *z, 2000.0))).unwrap();
    }
    m.push(&mv(4, MoveKind::Dwell { seconds: 0.01 })).unwrap();
    let fb = Feedback::default();
    let mut sps = Vec::new();
    let mut stops = Vec::new();
    for _ in 0..20_000 {
        let sp = m.step(&fb);
        sps.push(sp);
        if m.is_held() {
            stops.push((sp.pos[AX_X], sp.pos[AX_Z], sp.vel[AX_X], sp.vel[AX_Z]));
            m.cycle_start();
        }
        if m.is_idle() {
            break;
        }
    }
    assert_eq!(stops, vec![(50.0, -10.0, 0.0, 0.0), (55.0, -20.0, 0.0, 0.0), (55.0, -30.0, 0.0, 0.0), (55.0, -30.0, 0.0, 0.0)]);
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn single_block_switched_on_mid_chain_stops_safely() {
    let l = lim();
    // Collinear G64 blocks at full speed: switched on right before a junction, the block can
    // no longer stop at its end; it stops at the end of a later block instead.
    let mut m = Motion::new(l.clone(), START);
    for i in 1..=5 {
        m.push(&mv_g64(i, feed(50.0, -10.0 * i as f64, 4000.0))).unwrap();
    }
    m.push(&mv(6, feed(50.0, -60.0, 4000.0))).unwrap();
    let fb = Feedback::default();
    let mut sps = Vec::new();
    while sps.last().is_none_or(|s: &Setpoint| s.pos[AX_Z] > -19.9) {
        sps.push(m.step(&fb));
    }
    m.set_single_block(true);
    while !m.is_held() {
        sps.push(m.step(&fb));
        assert!(sps.len() < 100_000);
    }
    let at = sps.last().unwrap().pos[AX_Z];
    assert!(at == -30.0 || at == -40.0, "stopped at z {at}, not on a block end");
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn spindle_override_scales_the_commanded_speed_within_the_machine_maximum() {
    let mut m = Motion::new(lim(), START);
    m.set_spindle_override(1.2);
    m.push(&mv(1, spindle(SpindleDir::Ccw, 1000.0))).unwrap();
    m.push(&mv(2, MoveKind::Dwell { seconds: 0.5 })).unwrap();
    assert_eq!(run(&mut m, 10_000).last().unwrap().spindle_rpm, -1200.0);
    m.push(&mv(3, spindle(SpindleDir::Cw, 5900.0))).unwrap();
    m.push(&mv(4, MoveKind::Dwell { seconds: 3.0 })).unwrap();
    assert_eq!(run(&mut m, 10_000).last().unwrap().spindle_rpm, 6000.0);
    // Under css the G50 clamp holds after the override: 100 m/min at r 50 is 318 rpm.
    let css = SpindleCmd { dir: SpindleDir::Cw, rpm: 0.0, css: Some(100.0), max_rpm: Some(350.0) };
    m.push(&mv(5, MoveKind::Spindle(css))).unwrap();
    m.push(&mv(6, MoveKind::Dwell { seconds: 1.0 })).unwrap();
    assert_eq!(run(&mut m, 10_000).last().unwrap().spindle_rpm, 350.0);
    m.push(&mv(7, spindle(SpindleDir::Cw, 5900.0))).unwrap();
    m.set_spindle_override(f64::NAN);
    m.push(&mv(8, MoveKind::Dwell { seconds: 1.2 })).unwrap();
    assert_eq!(run(&mut m, 10_000).last().unwrap().spindle_rpm, 5900.0);
}

/// Rigid tap at (x 0): R point z 2, bottom z −20, dwell at the bottom, return, then away.
fn tap_program(m: &mut Motion) {
    m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
    m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.0, rpm: 600.0, spindle: 1 })).unwrap();
    m.push(&mv(3, MoveKind::Dwell { seconds: 0.1 })).unwrap();
    m.push(&mv(4, MoveKind::Tap { end: Pos::xz(0.0, 2.0), lead: 1.0, rpm: 600.0, spindle: 1 })).unwrap();
    m.push(&mv(5, rapid(10.0, 2.0))).unwrap();
}

#[test]
fn feed_hold_in_a_rigid_tap_waits_for_the_r_point_by_default() {
    let l = lim();
    assert!(!l.tap_hold_in_hole, "lathe.toml has No.5200#6 = 0");
    let mut m = Motion::new(l.clone(), [0.0; N_AXES]);
    tap_program(&mut m);
    let mut fb = Feedback::default();
    let mut sps = Vec::new();
    for _ in 0..20_000 {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() }; // ideal drives: the sync monitor reads them
        sps.push(sp);
        if sp.line == 2 && sp.pos[AX_Z] < -5.0 && !m.is_held() {
            m.feed_hold();
        }
        if m.is_held() && sps.len() > 10_000 {
            break;
        }
    }
    // Held at the R point after the return stroke, not in the hole.
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (0.0, 2.0));
    assert!(sps.iter().any(|s| s.pos[AX_Z] == -20.0), "the tap reached the bottom");
    assert!(sps.iter().all(|s| s.line <= 4));
    m.cycle_start();
    let rest = run(&mut m, 100_000);
    assert_eq!(rest.last().unwrap().pos[AX_X], 10.0);
    sps.extend(rest);
    check_limits(&l, [0.0; N_AXES], &sps).unwrap();
}

#[test]
fn feed_hold_in_a_rigid_tap_brakes_z_and_spindle_together_with_5200_bit6() {
    let mut l = lim();
    l.tap_hold_in_hole = true;
    let mut m = Motion::new(l.clone(), [0.0; N_AXES]);
    tap_program(&mut m);
    let mut fb = Feedback::default();
    let mut sps = Vec::new();
    let mut theta_r = None;
    for _ in 0..3000 {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() }; // ideal drives: the sync monitor reads them
        if sp.line == 2 && sp.pos[AX_Z] == 2.0 && sp.spindle_rpm == 0.0 {
            theta_r = Some(sp.pos[AX_S]);
        }
        sps.push(sp);
        if sp.line == 2 && sp.pos[AX_Z] < -5.0 {
            m.feed_hold();
        }
    }
    let last = *sps.last().unwrap();
    assert!(last.pos[AX_Z] < -5.0 && last.pos[AX_Z] > -20.0, "stopped in the hole at {}", last.pos[AX_Z]);
    assert_eq!((last.vel[AX_Z], last.spindle_rpm), (0.0, 0.0));
    let th = theta_r.unwrap();
    assert!((last.pos[AX_S] - (th + 360.0 * (last.pos[AX_Z] - 2.0))).abs() < 1e-9, "spindle left the thread");
    m.cycle_start();
    sps.extend(run(&mut m, 100_000));
    assert_eq!(sps.last().unwrap().pos[AX_X], 10.0);
    check_limits(&l, [0.0; N_AXES], &sps).unwrap();
}

#[test]
fn single_block_does_not_stop_inside_a_rigid_tap() {
    let mut m = Motion::new(lim(), [0.0; N_AXES]);
    m.set_single_block(true);
    tap_program(&mut m);
    let mut fb = Feedback::default();
    let mut stops = Vec::new();
    for _ in 0..100_000 {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() }; // ideal drives: the sync monitor reads them
        if m.is_held() {
            stops.push(sp.pos[AX_Z]);
            m.cycle_start();
        }
        if m.is_idle() {
            break;
        }
    }
    // After the rapid to R and after the final rapid; never at the bottom.
    assert_eq!(stops, vec![2.0, 2.0]);
}

// ---- Continuous thread segments, G34 ----

fn thread_k(x: f64, z: f64, lead: f64, continuous: bool, lead_inc: f64) -> MoveKind {
    MoveKind::Thread { end: Pos::xz(x, z), lead, start_angle: 0.0, continuous, lead_inc }
}

#[test]
fn g92_run_out_continues_the_lock_without_rearming() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 600.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    // G92 pass: the thread, then the 45° run-out chamfer (continuous), then the retract.
    m.push(&mv(3, thread_k(20.0, -20.0, 2.0, false, 0.0))).unwrap();
    m.push(&mv(4, thread_k(22.0, -22.0, 2.0, true, 0.0))).unwrap();
    m.push(&mv(5, rapid(25.0, -22.0))).unwrap();
    let sps = run(&mut m, 100_000);
    // The synchronous line from a locked cycle in the middle of the thread.
    let k_mid = sps.iter().position(|s| s.line == 3 && s.pos[AX_Z] < -10.0).unwrap();
    let (z_m, th_m) = (sps[k_mid].pos[AX_Z], sps[k_mid].pos[AX_S]);
    let mut crossed = 0;
    for s in &sps[k_mid..] {
        if !(s.line == 3 || s.line == 4) || s.pos[AX_Z] < -21.7 {
            continue; // before the lock, the braking at the chamfer's end, the retract
        }
        // z = z0 − lead·(θ − θ0)/360 on both sides of the junction.
        let want = z_m - 2.0 * (s.pos[AX_S] - th_m) / 360.0;
        assert!((s.pos[AX_Z] - want).abs() < 1e-6, "line {} z {} vs {want}", s.line, s.pos[AX_Z]);
        assert!(s.path_feed > 1000.0, "stopped at z {} (re-armed?)", s.pos[AX_Z]);
        if s.line == 4 {
            crossed += 1;
            // On the chamfer: x = 20 + (−20 − z).
            assert!((s.pos[AX_X] - (20.0 - 20.0 - s.pos[AX_Z])).abs() < 1e-9);
        }
    }
    assert!(crossed > 10, "only {crossed} chamfer cycles checked");
    let last = sps.last().unwrap();
    assert_eq!(last.pos[..3], [25.0, 0.0, -22.0]);
}

#[test]
fn consecutive_g32_blocks_pushed_late_still_keep_the_lock() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 600.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    m.push(&mv(3, thread_k(20.0, -10.0, 2.0, false, 0.0))).unwrap();
    let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
    let mut sps = Vec::new();
    // Run until the first block has ended (at rest), then push its continuation.
    while !m.is_idle() {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        sps.push(sp);
    }
    m.push(&mv(4, thread_k(20.0, -20.0, 2.0, true, 0.0))).unwrap();
    let k_mid = sps.iter().position(|s| s.line == 3 && s.pos[AX_Z] < -5.0).unwrap();
    let (z_m, th_m) = (sps[k_mid].pos[AX_Z], sps[k_mid].pos[AX_S]);
    sps.extend(run_from(&mut m, fb, 100_000));
    // It catches up with the same line (no wait for a new one-revolution signal): once caught
    // up, z is on the first block's synchronous line again.
    let on_line: Vec<_> = sps
        .iter()
        .filter(|s| s.line == 4 && s.pos[AX_Z] > -19.0 && s.pos[AX_Z] < -14.0)
        .map(|s| s.pos[AX_Z] - (z_m - 2.0 * (s.pos[AX_S] - th_m) / 360.0))
        .collect();
    assert!(!on_line.is_empty());
    assert!(on_line.iter().all(|e| e.abs() < 1e-6), "off the line: {:?}", &on_line[..3.min(on_line.len())]);
}

fn run_from(m: &mut Motion, mut fb: Feedback, max: usize) -> Vec<Setpoint> {
    let mut out = Vec::new();
    while !m.is_idle() {
        assert!(out.len() < max, "not idle after {max} cycles");
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        out.push(sp);
    }
    out
}

#[test]
fn g34_lead_grows_by_k_per_revolution() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 300.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    m.push(&mv(3, thread_k(20.0, -40.0, 2.0, false, 0.1))).unwrap();
    let sps = run(&mut m, 100_000);
    check_limits(&l, START, &sps).unwrap();
    assert_eq!(sps.last().unwrap().pos[..3], [20.0, 0.0, -40.0]);
    // Revolutions n after θ0 for a distance D: L0·n + K·n²/2 = D.
    let revs = |d: f64| (-2.0 + (4.0 + 0.2 * d).sqrt()) / 0.1;
    let k_mid = sps.iter().position(|s| s.line == 3 && s.pos[AX_Z] < -20.0).unwrap();
    let th0 = sps[k_mid].pos[AX_S] - 360.0 * revs(2.0 - sps[k_mid].pos[AX_Z]);
    // θ0 is on the one-revolution reference (start angle 0).
    let r = th0.rem_euclid(360.0);
    assert!(r.min(360.0 - r) < 1e-6, "θ0 {th0}");
    let mut n_checked = 0;
    for s in sps.iter().filter(|s| s.line == 3 && s.pos[AX_Z] < -2.0 && s.pos[AX_Z] > -39.0) {
        let n = (s.pos[AX_S] - th0) / 360.0;
        let want = 2.0 - (2.0 * n + 0.1 * n * n / 2.0);
        assert!((s.pos[AX_Z] - want).abs() < 1e-6, "n {n}: z {} vs {want}", s.pos[AX_Z]);
        n_checked += 1;
    }
    assert!(n_checked > 1000);
}

#[test]
fn g34_is_refused_when_the_lead_vanishes_or_gets_too_fast() {
    let mut m = Motion::new(lim(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 3000.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    // 2 mm − 0.2 mm/rev: 0 after 10 revolutions (20 mm), the thread is 42 mm.
    let e = m.push(&mv(3, thread_k(20.0, -40.0, 2.0, false, -0.2))).unwrap_err();
    assert_eq!(e.number, alarms::ILLEGAL_LEAD);
    // 3.5 mm × 3000 rpm = 10.5 m/min is fine; growing to 7.2 mm at the end is not (Z 12 m/min).
    let e = m.push(&mv(3, thread_k(20.0, -40.0, 3.5, false, 0.5))).unwrap_err();
    assert_eq!(e.number, alarms::THREAD_TOO_FAST);
    m.push(&mv(3, thread_k(20.0, -40.0, 3.5, false, 0.0))).unwrap();
}

// ---- G92.1 rigid thread ----

#[test]
fn g92_1_interpolates_spindle_angle_and_axes_on_one_profile() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 800.0))).unwrap(); // running: braked first
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    // Taper thread 22 mm long in Z at 1.5 mm: 5280° of spindle.
    let end = Pos { c: 360.0 * 22.0 / 1.5, ..Pos::xz(19.0, -20.0) };
    m.push(&mv(3, MoveKind::RigidThread { end, lead: 1.5, rpm: 1000.0 })).unwrap();
    // The retract keeps the spindle where the stroke left it (C unchanged).
    m.push(&mv(4, MoveKind::Rapid { end: Pos { c: end.c, ..Pos::xz(25.0, -20.0) } })).unwrap();
    let sps = run(&mut m, 100_000);
    check_limits(&l, START, &sps).unwrap();
    let k0 = sps.iter().position(|s| s.line == 3 && s.pos[AX_Z] != 2.0).unwrap();
    assert_eq!(sps[k0 - 1].spindle_rpm, 0.0, "the spindle is at rest when the stroke starts");
    let th0 = sps[k0 - 1].pos[AX_S];
    for s in sps[k0 - 1..].iter().filter(|s| s.line == 3) {
        let want = th0 + 360.0 * (2.0 - s.pos[AX_Z]) / 1.5;
        assert!((s.pos[AX_S] - want).abs() < 1e-9, "spindle {} vs {want} at z {}", s.pos[AX_S], s.pos[AX_Z]);
        let x = 20.0 - (2.0 - s.pos[AX_Z]) / 22.0;
        assert!((s.pos[AX_X] - x).abs() < 1e-9);
    }
    let end_k = sps.iter().rposition(|s| s.line == 3).unwrap();
    assert_eq!(sps[end_k].pos[..3], [19.0, 0.0, -20.0]);
    assert_eq!(sps[end_k].pos[AX_S], th0 + 5280.0);
    let top = sps.iter().filter(|s| s.line == 3).map(|s| s.spindle_rpm).fold(0.0, f64::max);
    assert!((top - 1000.0).abs() < 1e-6, "G92.1 at {top} rpm");
}

#[test]
fn g92_1_is_refused_before_motion_when_infeasible() {
    let mut m = Motion::new(lim(), START);
    m.push(&mv(1, rapid(20.0, 2.0))).unwrap();
    let c = 360.0 * 22.0 / 3.0;
    // 3 mm × 6000 rpm = 18 m/min: more than Z's 12 m/min.
    let e = m.push(&mv(2, MoveKind::RigidThread { end: Pos { c, ..Pos::xz(20.0, -20.0) }, lead: 3.0, rpm: 6000.0 }));
    assert_eq!(e.unwrap_err().number, alarms::THREAD_TOO_FAST);
    // A spindle travel that does not match the lead.
    let e = m.push(&mv(2, MoveKind::RigidThread { end: Pos { c: c + 90.0, ..Pos::xz(20.0, -20.0) }, lead: 3.0, rpm: 500.0 }));
    assert_eq!(e.unwrap_err().number, alarms::BAD_VALUE);
    m.push(&mv(2, MoveKind::RigidThread { end: Pos { c, ..Pos::xz(20.0, -20.0) }, lead: 3.0, rpm: 500.0 })).unwrap();
    let sps = run(&mut m, 100_000);
    assert_eq!(sps.last().unwrap().pos[AX_Z], -20.0);
}

// ---- Sync-error monitor ----

/// A thread pass (600 rpm × 2 mm = 20 mm/s) whose Z feedback lags the setpoint by `lag`
/// extra cycles; returns the setpoints, the sync errors and the first alarm.
fn lagging_thread(lag: usize, limit_um: f64) -> (Vec<Setpoint>, Vec<f64>, Option<Alarm>) {
    let mut l = lim();
    l.sync_err_limit_um = limit_um;
    // The monitor itself: without the correction, which would learn the lag and hide it.
    l.sync_correction = false;
    // A lead-in with a step in acceleration (No.1626 = 0): the one-cycle lag passes the limit
    // once the ramp is on the synchronous line, against which the stop is checked.
    l.thread_leadin_s = 0.0;
    let mut m = Motion::new(l, START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 600.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    m.push(&mv(3, thread(20.0, -30.0, 2.0, 0.0))).unwrap();
    let mut fb = Feedback { pos: START, spindle_rpm: 0.0, ..Default::default() };
    let (mut sps, mut errs, mut alarm) = (Vec::<Setpoint>::new(), Vec::new(), None);
    for _ in 0..20_000 {
        if m.is_idle() && sps.last().is_some_and(|s| s.spindle_rpm == 0.0) {
            break;
        }
        let sp = m.step(&fb);
        errs.push(m.sync_error());
        if alarm.is_none() {
            alarm = m.take_alarm();
        }
        sps.push(sp);
        let zk = sps.len().saturating_sub(1 + lag);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        fb.pos[AX_Z] = sps[zk].pos[AX_Z];
    }
    (sps, errs, alarm)
}

#[test]
fn sync_error_is_measured_from_actual_positions() {
    // Drives that reach every setpoint by the next cycle: no sync error.
    let (_, errs, alarm) = lagging_thread(0, 100.0);
    assert!(alarm.is_none());
    let measured = errs.iter().filter(|e| **e != 0.0).count();
    let worst = errs.iter().fold(0.0f64, |m, e| m.max(e.abs()));
    assert!(worst < 0.01, "ideal drives show {worst} µm");
    // Z one cycle late: 20 mm/s × 2 ms = 40 µm behind the spindle.
    let (_, errs, alarm) = lagging_thread(1, 100.0);
    assert!(alarm.is_none());
    let locked: Vec<f64> = errs.iter().copied().filter(|e| (e + 40.0).abs() < 0.01).collect();
    assert!(locked.len() > 500 && measured < errs.len(), "{} cycles at −40 µm", locked.len());
    assert!(errs.iter().all(|e| *e <= 0.01 && *e >= -40.01), "behind by at most one cycle");
}

#[test]
fn sync_error_beyond_the_limit_alarms_and_stops_spindle_and_axis_together() {
    let l = lim();
    let (sps, errs, alarm) = lagging_thread(1, 30.0);
    let a = alarm.expect("sync error alarm");
    assert_eq!(a.number, alarms::SYNC_ERROR);
    assert!(a.message.contains("µm"), "{}", a.message);
    let k = errs.iter().position(|e| e.abs() > 30.0).unwrap();
    // Stopped while cutting, well before the end of the thread.
    assert!(sps[k].pos[AX_Z] > -30.0 + 1.0);
    // From then on the axis stays on the spindle's line while both decelerate to rest.
    let (z0, th0) = (sps[k].pos[AX_Z], sps[k].pos[AX_S]);
    for s in &sps[k..] {
        let want = z0 - 2.0 * (s.pos[AX_S] - th0) / 360.0;
        assert!((s.pos[AX_Z] - want).abs() < 1e-6, "z {} off the thread ({want})", s.pos[AX_Z]);
    }
    let last = sps.last().unwrap();
    assert_eq!(last.spindle_rpm, 0.0);
    assert!(last.pos[AX_Z] > -30.0);
    // The spindle braked at its ramp, not at once.
    let ramp = l.amax[AX_S] / 6.0 * l.cycle_s;
    for w in sps[k..].windows(2) {
        assert!((w[0].spindle_rpm - w[1].spindle_rpm).abs() <= ramp + 1e-9);
    }
    check_limits(&l, START, &sps).unwrap();
}

#[test]
fn rigid_tap_sync_error_uses_actual_spindle_angle() {
    let mut l = lim();
    l.sync_err_limit_um = 20.0;
    // The monitor itself, without the correction that would follow the lagging spindle.
    l.sync_correction = false;
    let mut m = Motion::new(l, [0.0; N_AXES]);
    m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
    m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
    let mut fb = Feedback::default();
    let mut prev: Option<Setpoint> = None;
    let mut worst: f64 = 0.0;
    let mut alarm = None;
    for _ in 0..20_000 {
        let sp = m.step(&fb);
        worst = worst.max(m.sync_error().abs());
        alarm = alarm.or(m.take_alarm());
        // The spindle lags one extra cycle (a slower drive).
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        if let Some(p) = prev {
            fb.pos[AX_S] = p.pos[AX_S];
        }
        prev = Some(sp);
        if m.is_idle() {
            break;
        }
    }
    // 25 mm/s for one cycle: 50 µm, beyond 20.
    assert_eq!(alarm.map(|a| a.number), Some(alarms::SYNC_ERROR));
    assert!(worst > 20.0);
}

/// A late spindle TPDO: now and then the spindle's angle is a cycle old while Z's is fresh.
/// Said so (`Feedback::age`), the monitor must not pair them (the same stale angle unflagged
/// trips alarm 2307 above), and the correction must ride over it.
#[test]
fn a_late_spindle_tpdo_is_not_read_as_a_sync_error() {
    for corr in [false, true] {
        let mut l = lim();
        l.sync_err_limit_um = 20.0;
        l.sync_correction = corr;
        let mut m = Motion::new(l, [0.0; N_AXES]);
        m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
        m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
        let mut fb = Feedback::default();
        let (mut prev, mut worst, mut alarm) = (None::<Setpoint>, 0.0f64, None);
        for k in 0..20_000 {
            let sp = m.step(&fb);
            worst = worst.max(m.sync_error().abs());
            alarm = alarm.or(m.take_alarm());
            fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
            if let (Some(p), true) = (prev, k % 7 == 3) {
                fb.pos[AX_S] = p.pos[AX_S];
                fb.age[AX_S] = 1;
            }
            prev = Some(sp);
            if m.is_idle() {
                break;
            }
        }
        assert!(alarm.is_none(), "correction {corr}: {alarm:?}");
        assert!(worst < 1.0, "correction {corr}: worst {worst} µm");
        assert!(m.unpaired_cycles() > 50, "correction {corr}: {} unpaired", m.unpaired_cycles());
    }
}

#[test]
fn rapid_with_c_positions_the_spindle_with_the_axes() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, spindle(SpindleDir::Cw, 500.0))).unwrap();
    m.push(&mv(2, rapid(20.0, 2.0))).unwrap();
    // G92.1's approach: X and the spindle's start angle together, then C alone.
    m.push(&mv(3, MoveKind::Rapid { end: Pos { c: 90.0, ..Pos::xz(21.0, 2.0) } })).unwrap();
    m.push(&mv(4, MoveKind::Rapid { end: Pos { c: -270.0, ..Pos::xz(21.0, 2.0) } })).unwrap();
    let sps = run(&mut m, 100_000);
    check_limits(&l, START, &sps).unwrap();
    let k0 = sps.iter().position(|s| s.line == 3 && s.pos[AX_X] != 20.0).unwrap();
    assert_eq!(sps[k0 - 1].spindle_rpm, 0.0, "braked before positioning");
    let th0 = sps[k0 - 1].pos[AX_S];
    for s in sps[k0 - 1..].iter().filter(|s| s.line == 3) {
        let want = th0 + 90.0 * (s.pos[AX_X] - 20.0);
        assert!((s.pos[AX_S] - want).abs() < 1e-9, "C {} vs {want}", s.pos[AX_S]);
    }
    let last = sps.last().unwrap();
    assert_eq!(last.pos[..3], [21.0, 0.0, 2.0]);
    assert_eq!(last.pos[AX_S], th0 + 90.0 - 360.0);
    assert_eq!(last.spindle_rpm, 0.0);
}

// ---- Rigid tap: feasibility, matched acceleration, sync correction ----

#[test]
fn a_rigid_tap_too_fast_for_z_or_the_spindle_is_refused_at_push() {
    let mut m = Motion::new(lim(), [0.0; N_AXES]);
    m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
    // Lead 3 × S5000 = 15000 mm/min > Z's 12000.
    let e = m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 3.0, rpm: 5000.0, spindle: 1 })).unwrap_err();
    assert_eq!(e.number, alarms::THREAD_TOO_FAST);
    assert!(e.message.contains("lower S"), "{}", e.message);
    // Above the spindle's 6000 rpm (Z would manage: 0.5 × 7000 = 3500 mm/min).
    let e = m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 0.5, rpm: 7000.0, spindle: 1 })).unwrap_err();
    assert_eq!(e.number, alarms::THREAD_TOO_FAST);
    // Nothing was queued: only the rapid runs.
    let sps = run(&mut m, 10_000);
    assert!(sps.iter().all(|s| s.pos[AX_S] == 0.0 && s.pos[AX_Z] >= 0.0));
}

/// A rigid tap at lead 1.5, S2000 under `l`: in from Z2 to Z-20 (line 2), out to Z2 (line 3).
fn rigid_tap_in_and_out(l: &Limits) -> Vec<Setpoint> {
    let mut m = Motion::new(l.clone(), [0.0; N_AXES]);
    m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
    m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -20.0), lead: 1.5, rpm: 2000.0, spindle: 1 })).unwrap();
    m.push(&mv(3, MoveKind::Tap { end: Pos::xz(0.0, 2.0), lead: 1.5, rpm: 2000.0, spindle: 1 })).unwrap();
    run(&mut m, 100_000)
}

/// Largest |second difference| of axis `i` over setpoints of line `line`, units/s².
fn peak_accel(sps: &[Setpoint], i: usize, line: u32, dt: f64) -> f64 {
    sps.windows(3).filter(|w| w[1].line == line).map(|w| ((w[2].pos[i] - 2.0 * w[1].pos[i] + w[0].pos[i]) / (dt * dt)).abs()).fold(0.0, f64::max)
}

#[test]
fn rigid_tap_matches_acceleration_with_5261_in_and_5271_out() {
    let mut l = lim();
    // No.5261 200 ms to 1000 rpm in, No.5271 400 ms out.
    l.tap_accel = 1000.0 / 0.2 * 6.0;
    l.tap_retract_accel = 1000.0 / 0.4 * 6.0;
    let dt = l.cycle_s;
    let sps = rigid_tap_in_and_out(&l);
    // Spindle and Z on one profile: the spindle's limit sets Z's (the lower of the two).
    let (s_in, s_out) = (peak_accel(&sps, AX_S, 2, dt), peak_accel(&sps, AX_S, 3, dt));
    assert!((s_in - l.tap_accel).abs() < 0.01 * l.tap_accel, "in: {s_in} deg/s²");
    assert!((s_out - l.tap_retract_accel).abs() < 0.01 * l.tap_retract_accel, "out: {s_out} deg/s²");
    let z_in = peak_accel(&sps, AX_Z, 2, dt);
    assert!((z_in - l.tap_accel * 1.5 / 360.0).abs() < 0.01 * z_in, "Z in: {z_in} mm/s²");
    assert_eq!(sps.last().unwrap().pos[AX_Z], 2.0);
}

#[test]
fn rigid_tap_with_a_bell_shaped_acceleration_ramps_it_and_lands_exactly() {
    let mut l = lim();
    l.tap_accel = 1000.0 / 0.2 * 6.0;
    // No.5365: the acceleration ramps over 40 ms (jerk = a / 0.04 s).
    l.tap_bell_s = 0.04;
    l.sync_correction = false;
    let dt = l.cycle_s;
    let sps = rigid_tap_in_and_out(&l);
    let tap: Vec<&Setpoint> = sps.iter().filter(|s| s.line == 2).collect();
    let a_max = l.tap_accel * 1.5 / 360.0;
    let (mut peak_a, mut peak_j) = (0.0f64, 0.0f64);
    for w in tap.windows(4) {
        let a = |i: usize| (w[i + 1].pos[AX_Z] - 2.0 * w[i].pos[AX_Z] + w[i - 1].pos[AX_Z]) / (dt * dt);
        peak_a = peak_a.max(a(1).abs());
        peak_j = peak_j.max(((a(2) - a(1)) / dt).abs());
    }
    // Still the linear constant's acceleration at its peak, but reached through a ramp: no
    // step of the acceleration bigger than the jerk allows (a linear profile steps by a_max).
    assert!(peak_a <= a_max * 1.01 && peak_a > 0.9 * a_max, "peak accel {peak_a} of {a_max}");
    assert!(peak_j <= a_max / 0.04 * 1.05, "peak jerk {peak_j} mm/s³, limit {}", a_max / 0.04);
    // One profile: the spindle stays on the tap relation, and both land exactly.
    for s in &tap {
        let rel = 2.0 + 1.5 * s.pos[AX_S] / 360.0;
        assert!((s.pos[AX_Z] - rel).abs() < 1e-9, "z {} spindle relation {rel}", s.pos[AX_Z]);
    }
    assert_eq!(tap.last().unwrap().pos[AX_Z], -20.0);
    assert_eq!(sps.last().unwrap().pos[AX_Z], 2.0);
}

#[test]
fn sync_correction_sends_z_after_the_spindle_actual_angle_and_fades_out_at_r() {
    let mut l = lim();
    l.feedback_delay = 2;
    let mut m = Motion::new(l, [0.0; N_AXES]);
    m.push(&mv(1, rapid(0.0, 2.0))).unwrap();
    m.push(&mv(2, MoveKind::Tap { end: Pos::xz(0.0, -10.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
    m.push(&mv(3, MoveKind::Tap { end: Pos::xz(0.0, 2.0), lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap();
    m.push(&mv(4, rapid(10.0, 2.0))).unwrap();
    // Drives two cycles behind (as on CANopen); the spindle 1° further behind than that.
    let mut sps: Vec<Setpoint> = Vec::new();
    let mut fb = Feedback::default();
    let mut spindle_moved = false;
    for _ in 0..20_000 {
        let sp = m.step(&fb);
        sps.push(sp);
        let k = sps.len().saturating_sub(2);
        fb = Feedback { pos: sps[k].pos, spindle_rpm: sps[k].spindle_rpm, ..Default::default() };
        spindle_moved |= sp.pos[AX_S] != 0.0;
        if spindle_moved {
            fb.pos[AX_S] += if sp.line >= 2 && sp.line <= 3 { -1.0f64.copysign(sps[k].vel[AX_S]) } else { 0.0 };
        }
        if m.is_idle() && sps.len() > 3 && sps[sps.len() - 3..].windows(2).all(|w| w[0].pos == w[1].pos) {
            break;
        }
    }
    // Mid-stroke (steady 1000 rpm, constant 1° lag): Z is sent 1° × 1.5/360 mm after the
    // nominal relation, i.e. where the spindle actually is.
    let mid: Vec<&Setpoint> = sps.iter().filter(|s| s.line == 2 && s.vel[AX_S] < -5999.0).collect();
    assert!(mid.len() > 50, "{} steady cycles", mid.len());
    for s in &mid[10..] {
        let nominal = 2.0 + 1.5 * s.pos[AX_S] / 360.0;
        assert!((s.pos[AX_Z] - nominal - 1.5 / 360.0).abs() < 1e-6, "z {} vs nominal {nominal}", s.pos[AX_Z]);
    }
    // After the hole the correction fades out: the program ends exactly on its end point.
    let last = sps.last().unwrap();
    assert_eq!(last.pos[..3], [10.0, 0.0, 2.0]);
}

// ---- Single block and feed hold by the actions of drilling/tapping cycles ----

/// A move tagged with a canned cycle's action.
fn cmv(line: u32, kind: MoveKind, cycle: &str, step: u8) -> Move {
    Move { tag: Some(CycleTag { cycle: Arc::from(cycle), step }), ..mv(line, kind) }
}

/// One hole at radius `x` on `line`: initial plane z 4, R z 2, bottom z −10. `cut` gives
/// the items of actions 3–5 (between the rapid to R and the rapid back to the initial plane).
fn hole(line: u32, x: f64, cycle: &str, cut: &dyn Fn(f64) -> Vec<(MoveKind, u8)>) -> Vec<Move> {
    let mut v = vec![cmv(line, rapid(x, 4.0), cycle, 1), cmv(line, rapid(x, 2.0), cycle, 2)];
    v.extend(cut(x).into_iter().map(|(k, s)| cmv(line, k, cycle, s)));
    v.push(cmv(line, rapid(x, 4.0), cycle, 6));
    v
}

fn boring(x: f64) -> Vec<(MoveKind, u8)> {
    vec![(feed(x, -10.0, 1200.0), 3), (MoveKind::Dwell { seconds: 0.05 }, 4), (feed(x, 2.0, 1200.0), 5)]
}

fn rigid_tap(x: f64) -> Vec<(MoveKind, u8)> {
    let tap = |z: f64| MoveKind::Tap { end: Pos::xz(x, z), lead: -1.0, rpm: 600.0, spindle: 1 };
    vec![(tap(-10.0), 3), (MoveKind::Dwell { seconds: 0.05 }, 4), (tap(2.0), 5)]
}

/// Flexible tapping as the interpreter expands it (004 §2.22.3): M03, feed per revolution
/// to the bottom, M05, dwell, M04, feed back to R, M05.
fn flexible_tap(x: f64) -> Vec<(MoveKind, u8)> {
    let f = |z: f64| MoveKind::Feed { end: Pos::xz(x, z), feed: Feed::PerRev(1.0) };
    vec![
        (spindle(SpindleDir::Cw, 600.0), 3),
        (f(-10.0), 3),
        (spindle(SpindleDir::Stop, 600.0), 3),
        (MoveKind::Dwell { seconds: 0.05 }, 4),
        (spindle(SpindleDir::Ccw, 600.0), 5),
        (f(2.0), 5),
        (spindle(SpindleDir::Stop, 600.0), 5),
    ]
}

/// Run with single block on and ideal drives, pressing cycle start at every stop; the
/// (x, z) of each stop. `push_late`: moves pushed only once the cycle `k` is reached.
fn single_block_stops(l: Limits, moves: &[Move], push_late: Option<(usize, usize)>) -> Vec<(f64, f64)> {
    let mut m = Motion::new(l, START);
    m.set_single_block(true);
    let split = push_late.map_or(moves.len(), |(n, _)| n);
    for x in &moves[..split] {
        m.push(x).unwrap();
    }
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    let mut stops = Vec::new();
    for k in 0..200_000 {
        if push_late.is_some_and(|(_, at)| at == k) {
            for x in &moves[split..] {
                m.push(x).unwrap();
            }
        }
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        if m.is_held() {
            stops.push((sp.pos[AX_X], sp.pos[AX_Z]));
            m.cycle_start();
        }
        if m.is_idle() && k > 10 && push_late.is_none_or(|(_, at)| k > at) {
            break;
        }
    }
    stops
}

/// 004 §2.21 note 2: in a drilling cycle single block stops at the ends of actions 1 (hole
/// position), 2 (R point) and 6 (initial plane) only, not at the bottom nor back at R.
#[test]
fn single_block_stops_at_the_ends_of_actions_1_2_and_6_in_a_drilling_cycle() {
    let mut p = hole(2, 10.0, "G85", &boring);
    p.extend(hole(3, 20.0, "G85", &boring));
    p.push(mv(4, rapid(30.0, 4.0)));
    let stops = single_block_stops(lim(), &p, None);
    assert_eq!(stops, [(10.0, 4.0), (10.0, 2.0), (10.0, 4.0), (20.0, 4.0), (20.0, 2.0), (20.0, 4.0), (30.0, 4.0)]);
    // The same moves untagged stop after every block, the bottom included.
    let plain: Vec<Move> = p.iter().map(|x| Move { tag: None, ..x.clone() }).collect();
    assert!(single_block_stops(lim(), &plain, None).contains(&(10.0, -10.0)));
}

/// Manual 000 "暂停与单段": in rigid tapping single block never stops within actions 1–6;
/// with No.5200#6 = 0 not between the holes either, only after the cycle's last hole; with
/// No.5200#6 = 1 after every hole.
#[test]
fn single_block_in_rigid_tapping_follows_no_5200_bit_6() {
    let mut p = hole(2, 10.0, "G84", &rigid_tap);
    p.extend(hole(3, 20.0, "G84", &rigid_tap));
    p.push(mv(4, rapid(30.0, 4.0)));
    let l = lim();
    assert!(!l.tap_hold_in_hole);
    assert_eq!(single_block_stops(l.clone(), &p, None), [(20.0, 4.0), (30.0, 4.0)]);
    // The hole is known to be rigid only when its first tap stroke arrives: here while the
    // rapid of action 1 is already running.
    assert_eq!(single_block_stops(l.clone(), &p, Some((2, 5))), [(20.0, 4.0), (30.0, 4.0)]);
    let mut l6 = l;
    l6.tap_hold_in_hole = true;
    assert_eq!(single_block_stops(l6, &p, None), [(10.0, 4.0), (20.0, 4.0), (30.0, 4.0)]);
}

/// 004 §2.22 note 4: single block in a (flexible) G84 stops at the ends of actions 1, 2
/// and 6; the spindle codes inside action 3–5 do not split the block.
#[test]
fn single_block_in_flexible_tapping_treats_actions_3_to_6_as_one_block() {
    let mut p = hole(2, 10.0, "G84", &flexible_tap);
    p.push(mv(3, rapid(30.0, 4.0)));
    assert_eq!(single_block_stops(lim(), &p, None), [(10.0, 4.0), (10.0, 2.0), (10.0, 4.0), (30.0, 4.0)]);
}

/// Step with ideal drives, pressing feed hold once the tool is below z −3 in the hole;
/// returns the setpoints until the axes have stood still for 0.2 s while held (longer than
/// the 0.05 s dwell at the bottom), or `max` cycles, and whether that happened.
fn hold_in_the_hole(m: &mut Motion, max: usize) -> (Vec<Setpoint>, bool) {
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    let mut sps: Vec<Setpoint> = Vec::new();
    let mut pressed = false;
    let mut still = 0;
    for _ in 0..max {
        let sp = m.step(&fb);
        fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
        let moved = sps.last().is_none_or(|p| p.pos[..3] != sp.pos[..3]);
        sps.push(sp);
        if !pressed && sp.pos[AX_Z] < -3.0 {
            m.feed_hold();
            pressed = true;
        }
        still = if pressed && !moved && m.is_held() { still + 1 } else { 0 };
        if still >= 100 {
            return (sps, true);
        }
    }
    (sps, false)
}

/// 004 §2.22 note 4: feed hold during a flexible tap (actions 3–5) does not stop the tap in
/// the hole; the tool goes to the bottom and back, and the hold takes effect at R. In a
/// drilling cycle (G85) the same hold stops at once.
#[test]
fn feed_hold_in_a_flexible_tap_takes_effect_back_at_r() {
    let l = lim();
    let mut m = Motion::new(l.clone(), START);
    let mut p = hole(2, 10.0, "G84", &flexible_tap);
    p.push(mv(3, rapid(30.0, 4.0)));
    for x in &p {
        m.push(x).unwrap();
    }
    let (sps, held) = hold_in_the_hole(&mut m, 100_000);
    assert!(held);
    let last = *sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (10.0, 2.0), "held at R");
    assert!(sps.iter().any(|s| s.pos[AX_Z] == -10.0), "the tap reached the bottom");
    assert_eq!(last.spindle_rpm, 0.0, "M05 of action 5 done");
    m.cycle_start();
    let rest = run(&mut m, 100_000);
    assert_eq!(rest.last().unwrap().pos[AX_X], 30.0);

    let mut m = Motion::new(l, START);
    for x in hole(2, 10.0, "G85", &boring) {
        m.push(&x).unwrap();
    }
    let (sps, held) = hold_in_the_hole(&mut m, 100_000);
    let z = sps.last().unwrap().pos[AX_Z];
    assert!(held && z < -3.0 && z > -10.0, "a drilling cycle holds in the hole (z {z})");
}

/// Manual 000 with No.5200#6 = 0: feed hold in a tagged rigid tap runs on to R, then holds
/// before action 6.
#[test]
fn feed_hold_in_a_rigid_tapping_cycle_holds_at_r() {
    let mut m = Motion::new(lim(), START);
    let mut p = hole(2, 10.0, "G84", &rigid_tap);
    p.push(mv(3, rapid(30.0, 4.0)));
    for x in &p {
        m.push(x).unwrap();
    }
    let (sps, held) = hold_in_the_hole(&mut m, 100_000);
    assert!(held);
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_Z]), (10.0, 2.0), "held at R");
    assert!(sps.iter().any(|s| s.pos[AX_Z] == -10.0));
}

/// G88: a tap stroke along X (a radius) locks the spindle to X exactly as G84 to Z; the
/// lead's sign says which way the spindle turns going in. A stroke moving two axes is refused.
#[test]
fn a_rigid_tap_stroke_runs_along_x() {
    let l = lim();
    let mut m = Motion::new(l.clone(), [30.0, 0.0, -12.0, 90.0]);
    let tap = |x: f64| MoveKind::Tap { end: Pos { x, z: -12.0, ..Pos::ZERO }, lead: -1.5, rpm: 800.0, spindle: 1 };
    m.push(&mv(1, tap(15.0))).unwrap();
    m.push(&mv(2, MoveKind::Dwell { seconds: 0.05 })).unwrap();
    m.push(&mv(3, tap(30.0))).unwrap();
    let sps = run(&mut m, 100_000);
    for s in &sps {
        let want = 90.0 + 360.0 * (s.pos[AX_X] - 30.0) / -1.5;
        assert!((s.pos[AX_S] - want).abs() < 1e-9, "spindle {} vs {want} at x {}", s.pos[AX_S], s.pos[AX_X]);
        assert_eq!(s.pos[AX_Z], -12.0);
    }
    assert!(sps.iter().any(|s| s.pos[AX_X] == 15.0));
    let last = sps.last().unwrap();
    assert_eq!((last.pos[AX_X], last.pos[AX_S]), (30.0, 90.0), "back on R and on the start angle");
    // Forward (M03 sense) going −X, reversed coming out.
    assert!(sps.iter().any(|s| s.spindle_rpm > 790.0) && sps.iter().any(|s| s.spindle_rpm < -790.0));
    check_limits(&l, [30.0, 0.0, -12.0, 90.0], &sps).unwrap();
    let mut m = Motion::new(l, [30.0, 0.0, -12.0, 0.0]);
    let e = m.push(&mv(1, MoveKind::Tap { end: Pos::xz(20.0, -20.0), lead: 1.0, rpm: 500.0, spindle: 1 })).unwrap_err();
    assert_eq!(e.number, alarms::BAD_VALUE, "{e}");
}

// ---- S-curve (jerk limit) ----

/// `lim()` with a jerk limit on X and Z (mm/s³) and the given acceleration and cycle.
fn lim_jerk(amax: f64, jerk: f64, dt: f64) -> Limits {
    let mut l = lim();
    l.amax[AX_X] = amax;
    l.amax[AX_Z] = amax;
    l.jmax[AX_X] = jerk;
    l.jmax[AX_Z] = jerk;
    l.cycle_s = dt;
    l
}

/// The acceleration of every axis, as the drives see it (second difference of the
/// setpoints), changes by at most `jmax·dt` per cycle, from rest at `start` and back to rest
/// (the setpoints held `hold` cycles more at the end); the largest change relative to the limit
/// is returned.
fn check_jerk(l: &Limits, start: [f64; N_AXES], sps: &[Setpoint]) -> Result<f64, String> {
    let dt = l.cycle_s;
    let (mut p, mut v, mut a) = (start, [0.0; N_AXES], [0.0; N_AXES]);
    let mut worst: f64 = 0.0;
    let last = sps.last().map(|s| s.pos).unwrap_or(start);
    // Two cycles at rest after the end: the stop itself must be jerk-limited too.
    let tail = [last, last];
    for (k, pos) in sps.iter().map(|s| s.pos).chain(tail).enumerate() {
        for i in [AX_X, AX_Z] {
            let nv = (pos[i] - p[i]) / dt;
            let na = (nv - v[i]) / dt;
            let jump = (na - a[i]).abs();
            let lim_j = l.jmax[i] * dt;
            worst = worst.max(jump / lim_j);
            // Tolerance: rounding, and the landing cycle, which puts the setpoint on the end
            // point bit for bit and so absorbs up to 1e-9 mm (see `step`).
            if jump > lim_j * (1.0 + 1e-6) + 4e-9 / (dt * dt) {
                return Err(format!("cycle {k}: axis {i} acceleration {} → {na}: change {jump} > j·dt {lim_j}", a[i]));
            }
            p[i] = pos[i];
            v[i] = nv;
            a[i] = na;
        }
    }
    Ok(worst)
}

#[test]
fn s_curve_move_ramps_its_acceleration_and_lands_exactly_at_rest() {
    let l = lim_jerk(2000.0, 20_000.0, 0.002);
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, feed(50.0, -80.0, 4000.0))).unwrap();
    let sps = run(&mut m, 100_000);
    assert_eq!(sps.last().unwrap().pos[AX_Z], -80.0);
    check_limits(&l, START, &sps).unwrap();
    let worst = check_jerk(&l, START, &sps).unwrap();
    assert!(worst > 0.9, "the jerk limit is used ({worst})");
    // It reaches the feed and cruises there.
    assert!(sps.iter().any(|s| (s.path_feed - 4000.0).abs() < 1e-6));
    // Slower than the trapezoid by at most A/j per ramp (0.1 s each way).
    let mut t = Motion::new(lim(), START);
    t.push(&mv(1, feed(50.0, -80.0, 4000.0))).unwrap();
    let n_trap = run(&mut t, 100_000).len();
    let extra = sps.len() as f64 - n_trap as f64;
    assert!(extra > 0.0 && extra * 0.002 < 0.2 + 0.01, "{} vs {n_trap} cycles", sps.len());
}

#[test]
fn s_curve_feed_hold_stops_smoothly_and_resumes() {
    let l = lim_jerk(2000.0, 50_000.0, 0.002);
    let mut m = Motion::new(l.clone(), START);
    m.push(&mv(1, feed(50.0, -100.0, 3000.0))).unwrap();
    let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
    let mut sps: Vec<Setpoint> = Vec::new();
    let mut held_at = None;
    for k in 0..20_000 {
        if k == 300 {
            m.feed_hold();
        }
        if k == 600 {
            m.cycle_start();
        }
        let sp = m.step(&fb);
        fb.pos = sp.pos;
        if k == 301 {
            // The hold acts at once: the acceleration turns down from the next cycle.
            let n = sps.len();
            let v1 = sp.pos[AX_Z] - sps[n - 1].pos[AX_Z];
            let v0 = sps[n - 1].pos[AX_Z] - sps[n - 2].pos[AX_Z];
            assert!(v1.abs() < v0.abs(), "slowing at once: {v0} → {v1}");
        }
        if k == 599 {
            held_at = Some(sp.pos[AX_Z]);
            assert_eq!(Some(sp.pos[AX_Z]), sps.last().map(|s| s.pos[AX_Z]), "at rest in the hold");
        }
        sps.push(sp);
        if m.is_idle() {
            break;
        }
    }
    assert!(held_at.is_some_and(|z| z > -100.0 && z < -2.0));
    assert_eq!(sps.last().unwrap().pos[AX_Z], -100.0);
    check_limits(&l, START, &sps).unwrap();
    check_jerk(&l, START, &sps).unwrap();
}

#[test]
fn s_curve_collinear_g64_chain_keeps_the_jerk_limit_through_feed_changes() {
    let l = lim_jerk(1500.0, 30_000.0, 0.001);
    let mut m = Motion::new(l.clone(), START);
    let zs = [-10.0, -10.5, -30.0, -31.0, -60.0];
    let fs = [3000.0, 800.0, 6000.0, 1500.0, 4000.0];
    for (i, (z, f)) in zs.iter().zip(fs).enumerate() {
        let k = mv_g64(i as u32 + 1, feed(50.0, *z, f));
        m.push(&if i == zs.len() - 1 { mv(i as u32 + 1, feed(50.0, *z, f)) } else { k }).unwrap();
    }
    let sps = run(&mut m, 100_000);
    assert_eq!(sps.last().unwrap().pos[AX_Z], -60.0);
    check_limits(&l, START, &sps).unwrap();
    check_jerk(&l, START, &sps).unwrap();
    // Blended: no stop at the junctions (every cycle moves until the end).
    let moving = sps.windows(2).take_while(|w| w[1].pos[AX_Z] != -60.0).all(|w| w[1].pos[AX_Z] < w[0].pos[AX_Z]);
    assert!(moving, "stopped at a junction");
}

#[test]
fn jerk_from_config_and_no_1772() {
    let l = lim();
    assert_eq!(l.jmax, [0.0; N_AXES], "off unless configured");
    let t = crate::config::EMBEDDED_LATHE.replace("[parameters]", "[parameters]\n1772 = 32");
    let l = Limits::from_config(&MachineConfig::from_toml("t", &t).unwrap());
    assert!((l.jmax[AX_Z] - 2000.0 / 0.032).abs() < 1e-6, "{:?}", l.jmax);
    let t = t.replace("max_accel = 2000.0          # mm/s²", "max_accel = 2000.0\njerk = 9000.0");
    let l = Limits::from_config(&MachineConfig::from_toml("t", &t).unwrap());
    assert_eq!(l.jmax[AX_X], 9000.0, "the axis' own jerk wins");
    let bad = crate::config::EMBEDDED_LATHE.replace("max_accel = 2000.0          # mm/s²", "max_accel = 2000.0\njerk = -1.0");
    let e = MachineConfig::from_toml("t", &bad).unwrap_err().to_string();
    assert!(e.contains("axes.x.jerk"), "{e}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]
    /// Random single moves (exact stop) under random limits: the acceleration never changes
    /// by more than j·dt per cycle, no axis exceeds its speed or acceleration, and the move
    /// lands exactly on its end at rest.
    #[test]
    fn s_curve_random_moves_respect_jerk_and_land_exactly(
        x in 0.0..150.0f64, dz in -300.0..-0.001f64, f in 300.0..20000.0f64, rapid_move in any::<bool>(),
        amax in 50.0..5000.0f64, jr in 0.05..100.0f64, ms in prop::sample::select(vec![1.0, 2.0]),
    ) {
        // Jerk as acceleration over a ramp time of 1 ms … 20 s.
        let jerk = amax * jr;
        let l = lim_jerk(amax, jerk, ms / 1000.0);
        let mut m = Motion::new(l.clone(), START);
        let end = (x, START[AX_Z] + dz);
        let k = if rapid_move { rapid(end.0, end.1) } else { feed(end.0, end.1, f) };
        m.push(&mv(1, k)).unwrap();
        let sps = run(&mut m, 5_000_000);
        let last = sps.last().unwrap();
        prop_assert_eq!((last.pos[AX_X], last.pos[AX_Z]), end);
        if let Err(e) = check_limits(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
        if let Err(e) = check_jerk(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
        // The feed is reached when the move is long enough, and never exceeded.
        for s in &sps {
            prop_assert!(rapid_move || s.path_feed <= f * (1.0 + 1e-9) + 1e-9, "feed {} > F{}", s.path_feed, f);
        }
    }

    /// Random collinear G64 chains with random feeds: the same, through the junctions.
    #[test]
    fn s_curve_random_collinear_chains_respect_jerk(
        steps in prop::collection::vec((0.01..40.0f64, 10.0..12000.0f64), 1..6),
        amax in 100.0..4000.0f64, jr in 0.5..60.0f64,
    ) {
        let l = lim_jerk(amax, amax * jr, 0.002);
        let mut m = Motion::new(l.clone(), START);
        let mut z = START[AX_Z];
        for (i, (dz, f)) in steps.iter().enumerate() {
            z -= dz;
            let k = feed(START[AX_X], z, *f);
            let mvk = if i + 1 == steps.len() { mv(i as u32 + 1, k) } else { mv_g64(i as u32 + 1, k) };
            m.push(&mvk).unwrap();
        }
        let sps = run(&mut m, 5_000_000);
        prop_assert_eq!(sps.last().unwrap().pos[AX_Z], z);
        if let Err(e) = check_limits(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
        if let Err(e) = check_jerk(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]
    /// Random programs of lines and arcs, blended (G64) or not, with jerk limits: every axis
    /// within its speed and acceleration (corners keep the velocity-jump rule of the
    /// trapezoid, so the jerk is not checked across them), and the end is exact.
    #[test]
    fn s_curve_random_programs_respect_limits_and_end_exactly(
        segs in prop::collection::vec((seg_strategy(), any::<bool>()), 1..6), jr in 2.0..60.0f64,
    ) {
        let l = lim_jerk(2000.0, 2000.0 * jr, 0.002);
        let mut m = Motion::new(l.clone(), START);
        let mut end = (START[AX_X], START[AX_Z]);
        let n = segs.len();
        for (i, (s, blend)) in segs.iter().enumerate() {
            let line = i as u32 + 1;
            // Not slower than F60: a bounded number of cycles.
            let s = &match s {
                Seg3::Feed(x, z, f) => Seg3::Feed(*x, *z, f.max(60.0)),
                other => other.clone(),
            };
            let put = |k: MoveKind| if *blend && i + 1 < n { mv_g64(line, k) } else { mv(line, k) };
            match *s {
                Seg3::Rapid(x, z) => { m.push(&put(rapid(x, z))).unwrap(); end = (x, z); }
                Seg3::Feed(x, z, f) => { m.push(&put(feed(x, z, f))).unwrap(); end = (x, z); }
                Seg3::Arc { cx, cz, ang, sweep, r, cw, f } => {
                    let (sx, sz) = (cx + r * ang.sin(), cz + r * ang.cos());
                    m.push(&put(feed(sx, sz, f))).unwrap();
                    let a1 = if cw { ang - sweep } else { ang + sweep };
                    let (ex, ez) = (cx + r * a1.sin(), cz + r * a1.cos());
                    m.push(&put(arc_zx(ex, ez, cx, cz, cw, f))).unwrap();
                    end = (ex, ez);
                }
            }
        }
        let sps = run(&mut m, 2_000_000);
        let last = sps.last().unwrap();
        prop_assert_eq!((last.pos[AX_X], last.pos[AX_Z]), end);
        if let Err(e) = check_limits(&l, START, &sps) {
            prop_assert!(false, "{}", e);
        }
    }
}

/// A C target from a macro so large that an angle no longer resolves a count (1e300: the
/// proptest case that made the spindle command run past its maximum speed) is refused.
#[test]
fn a_c_target_beyond_the_axis_resolution_is_refused_at_push() {
    let mut m = Motion::new(Limits::from_config(&crate::config::MachineConfig::embedded()), [0.0; N_AXES]);
    let mv = |c: f64| Move {
        src: crate::canon::SrcPos::new("t.nc".into(), 1, 1),
        kind: MoveKind::Rapid { end: Pos { c, ..Pos::ZERO } },
        exact_stop: true,
        work_offset: Pos::ZERO,
        tag: None,
    };
    let e = m.push(&mv(1e300)).unwrap_err();
    assert_eq!(e.number, alarms::BAD_VALUE, "{e}");
    assert!(e.message.contains("beyond what the spindle axis resolves"), "{e}");
}

/// A spindle found out of torque while the stroke still accelerates: the lower acceleration
/// (and its jerk) is taken only where the stroke can still stop within what is left, jerk
/// phases included. Judged on v²/2a alone, a cap found at 50.7 mm/s still accelerating at
/// 97 mm/s² with 21.9 mm to go (S3000, the 0.24 kg·m² spindle, a jittery SYNC) was taken, and
/// the stroke reached the bottom at 750 rpm.
#[test]
fn a_spindle_cap_is_taken_only_where_the_stroke_can_still_stop() {
    let mut m = Motion::new(lim(), START);
    // 60.6 mm/s² at 1.5 mm per revolution.
    m.sp_accel_cap = 60.557 / (1.5 / 360.0);
    let (alim, jlim) = (97.15, 1000.0);
    let per_deg = 1.5 / 360.0;
    let braking = |a: f64, j: f64| profile::stop_dist(50.746, 97.15, a, j);
    // v²/2a fits (21.26 mm) but the jerk phases do not.
    assert!(50.746f64.powi(2) / (2.0 * 60.557) <= 21.919 && braking(60.557, jlim * 60.557 / alim) > 21.919);
    assert_eq!(m.capped_accel(alim, jlim, per_deg, 50.746, 97.15, 21.919), (alim, jlim));
    // Early in the stroke it fits: taken, the jerk scaled with it.
    let (a, j) = m.capped_accel(alim, jlim, per_deg, 12.0, 97.15, 34.4);
    assert!((a - 60.557).abs() < 1e-9 && (j - jlim * a / alim).abs() < 1e-9, "{a} {j}");
    // Without a jerk limit (G92.1's profile) v²/2a is the braking distance: taken.
    let (a, _) = m.capped_accel(alim, 0.0, per_deg, 50.746, 0.0, 21.919);
    assert!((a - 60.557).abs() < 1e-9, "{a}");
}
