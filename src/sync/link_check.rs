//! Refuse, before any motion, a spindle-synchronised move (thread, rigid tap, G92.1) that an
//! axis's link cannot hold within the sync tolerance.
//!
//! A Modbus drive has no SYNC: it takes a new set-point whenever the link's transaction
//! reaches it, and its feedback is up to one link cycle old. So along a synchronised move an
//! axis on a link of cycle T can be off its spindle-locked position by up to v × T (v its
//! speed in the move). That must stay within `machine.sync_error_limit_um`; otherwise the
//! move is refused with the cycle (or the spindle speed) that would do. CANopen axes get
//! their set-points at SYNC, in step with the spindle, and are not limited here.

use crate::canon::{Move, MoveKind, Pos};
use crate::Alarm;

/// One axis on a slow link: the motion axis letter (`x`, `z`, `y`, or `s` for the spindle),
/// its link and the link's cycle.
#[derive(Clone, Debug)]
pub struct SlowAxis {
    pub axis: String,
    pub link: String,
    pub cycle_s: f64,
}

/// Checks every synchronised move of a program.
pub struct LinkCheck<'a> {
    axes: &'a [SlowAxis],
    limit_mm: f64,
    pos: Pos,
    rpm: f64,
}

impl<'a> LinkCheck<'a> {
    pub fn new(axes: &'a [SlowAxis], limit_um: f64, start: Pos) -> Self {
        LinkCheck { axes, limit_mm: limit_um * 1e-3, pos: start, rpm: 0.0 }
    }

    /// Look at the next move of the program (in order).
    pub fn check(&mut self, m: &Move) -> Result<(), Alarm> {
        let from = self.pos;
        if let MoveKind::Spindle(s) = &m.kind {
            // Threads usually run in G97; under G96 the clamp bounds the speed.
            self.rpm = if s.rpm > 0.0 { s.rpm } else { s.max_rpm.unwrap_or(0.0) };
        }
        if let Some(e) = m.kind.end() {
            self.pos = e;
        }
        let (end, lead, rpm, name) = match m.kind {
            MoveKind::Thread { end, lead, .. } => (end, lead, self.rpm, "thread"),
            MoveKind::Tap { end, lead, rpm, .. } => (end, lead, rpm, "rigid tap"),
            MoveKind::RigidThread { end, lead, rpm } => (end, lead, rpm, "G92.1 rigid thread"),
            _ => return Ok(()),
        };
        if self.axes.is_empty() || rpm <= 0.0 {
            return Ok(());
        }
        // Speed along the long axis is lead × rpm; each axis moves in proportion.
        let (dx, dz, dy) = ((end.x - from.x).abs(), (end.z - from.z).abs(), (end.y - from.y).abs());
        let long = dx.max(dz).max(dy);
        let v_long = lead.abs() * rpm / 60.0; // mm/s
        for a in self.axes {
            let share = match a.axis.as_str() {
                "x" => dx,
                "z" => dz,
                "y" => dy,
                // The spindle carries the whole thread: its angle error × lead / 360.
                "s" => long,
                _ => 0.0,
            };
            if share <= 0.0 || long <= 0.0 {
                continue;
            }
            let v = v_long * share / long;
            let err = v * a.cycle_s;
            if err > self.limit_mm {
                let need_cycle_ms = self.limit_mm / v * 1e3;
                let max_rpm = rpm * self.limit_mm / err;
                return Err(Alarm::new(
                    super::super::drives::modbus::alarm::SYNC_TOO_SLOW,
                    format!(
                        "{name} at lead {:.4} mm × {rpm:.0} rpm moves axis {} at {:.1} mm/min; its link {} (cycle {:.1} ms) cannot hold it within the sync tolerance of {:.0} µm (up to {:.0} µm per cycle): a link cycle of {:.2} ms or less is needed, or at most {:.0} rpm; nothing was moved",
                        lead.abs(),
                        a.axis.to_uppercase(),
                        v * 60.0,
                        a.link,
                        a.cycle_s * 1e3,
                        self.limit_mm * 1e3,
                        err * 1e3,
                        need_cycle_ms,
                        max_rpm.floor()
                    ),
                )
                .at(m.src.clone()));
            }
        }
        Ok(())
    }
}

/// What a program asks of a spindle on a slow link (a Modbus drive, whose set-point
/// arrives once per link cycle): whether any move needs it in position, and how fast it
/// turns at most.
///
/// Turning and threading only need its speed and its measured angle (a thread follows the
/// angle the spindle reports): it runs in speed, and a late set-point is a late speed, not
/// a following error. Cs positioning (a C word), rigid tapping, G92.1, polar and polygon
/// turning steer its angle: position control, whose following-error window must hold what
/// a link cycle leaves the drive behind (`position_window`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SpindleUse {
    /// The first move that needs position control, in words with its line.
    pub position: Option<String>,
    /// The highest speed the program asks (G96: its clamp, else the axis's maximum), rpm.
    pub max_rpm: f64,
}

impl SpindleUse {
    /// Scan a program's moves; `max_speed`: the spindle axis's maximum, rpm.
    pub fn scan(moves: impl IntoIterator<Item = Move>, max_speed: f64) -> SpindleUse {
        let mut u = SpindleUse::default();
        let mut prev_c: Option<f64> = None;
        for m in moves {
            let (need, rpm) = match &m.kind {
                MoveKind::Spindle(s) if s.dir != crate::canon::SpindleDir::Stop => {
                    (None, if s.css.is_some() { s.max_rpm.unwrap_or(max_speed) } else { s.rpm })
                }
                MoveKind::Tap { rpm, .. } => (Some("a rigid tap"), *rpm),
                MoveKind::RigidThread { rpm, .. } => (Some("a G92.1 rigid thread"), *rpm),
                // The C axis' own moves run up to the spindle's maximum (a Cs rapid does).
                MoveKind::Polar { .. } => (Some("polar interpolation (G12.1)"), max_speed),
                MoveKind::Polygon(Some(p)) => (Some("polygon turning (G51.2)"), p.rpm),
                MoveKind::Rapid { end } if prev_c.is_some_and(|c| c != end.c && end.c.is_finite()) => (Some("Cs positioning (a C word)"), max_speed),
                _ => (None, 0.0),
            };
            if let Some(e) = m.kind.end() {
                prev_c = Some(e.c);
            }
            if rpm.is_finite() {
                u.max_rpm = u.max_rpm.max(rpm.min(max_speed));
            }
            if let (None, Some(what)) = (&u.position, need) {
                u.position = Some(format!("{what} at {}:{}", m.src.file, m.src.line));
            }
        }
        u
    }

    /// The following-error window (degrees) of a spindle in position control over a link of
    /// cycle `cycle_s`: the configured window (the drive's own lag) plus two link cycles of
    /// travel at the program's highest speed — the drive's demand trails the set-point by up
    /// to one cycle, and a set-point one cycle late (jitter; a drive that holds) adds one.
    /// A fixed window (30°) is 3 ms of travel at 1500 rpm: one late write on a 5 ms link.
    pub fn position_window(&self, configured_deg: f64, cycle_s: f64) -> f64 {
        configured_deg + 2.0 * self.max_rpm * 6.0 * cycle_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canon::{SpindleCmd, SpindleDir, SrcPos};

    fn mv(kind: MoveKind) -> Move {
        Move { src: SrcPos::new("t.nc".into(), 1, 1), kind, exact_stop: false, work_offset: Pos::default(), tag: None }
    }

    /// Turning and threading leave the spindle in speed; a C word or a rigid tap put it in
    /// position, with a window of two link cycles at the highest speed over the configured.
    #[test]
    fn spindle_use_finds_the_moves_that_steer_its_angle() {
        let spin = |rpm| MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm, css: None, max_rpm: None });
        let thread = MoveKind::Thread { end: Pos::xz(10.0, -20.0), lead: 1.5, start_angle: 0.0, continuous: false, lead_inc: 0.0 };
        let u = SpindleUse::scan([mv(spin(1500.0)), mv(MoveKind::Rapid { end: Pos::xz(10.0, 5.0) }), mv(thread)], 6000.0);
        assert_eq!(u, SpindleUse { position: None, max_rpm: 1500.0 });
        let cs = MoveKind::Rapid { end: Pos { c: 90.0, ..Pos::xz(10.0, 5.0) } };
        let u = SpindleUse::scan([mv(spin(800.0)), mv(MoveKind::Rapid { end: Pos::xz(10.0, 5.0) }), mv(cs)], 6000.0);
        assert_eq!(u.position.as_deref(), Some("Cs positioning (a C word) at t.nc:1"));
        assert_eq!(u.max_rpm, 6000.0);
        // 30° + 2 × 4 ms × 36 000°/s.
        assert!((u.position_window(30.0, 0.004) - 318.0).abs() < 1e-9);
        let tap = MoveKind::Tap { end: Pos::xz(0.0, -10.0), lead: 1.5, rpm: 500.0, spindle: 1 };
        let u = SpindleUse::scan([mv(tap)], 6000.0);
        assert_eq!((u.position.is_some(), u.max_rpm), (true, 500.0));
    }

    #[test]
    fn tap_on_a_slow_link_is_refused_with_the_cycle_needed() {
        let axes = [SlowAxis { axis: "z".into(), link: "tcp".into(), cycle_s: 0.010 }];
        let mut c = LinkCheck::new(&axes, 100.0, Pos { z: 5.0, ..Pos::default() });
        // M10×1.5 at 1000 rpm: 25 mm/s; 10 ms → 250 µm > 100 µm.
        let err = c.check(&mv(MoveKind::Tap { end: Pos { z: -20.0, ..Pos::default() }, lead: 1.5, rpm: 1000.0, spindle: 1 })).unwrap_err();
        assert_eq!(err.number, crate::alarm::MODBUS_SYNC_TOO_SLOW);
        assert!(err.message.contains("4.00 ms or less"), "{}", err.message);
        assert!(err.message.contains("at most 400 rpm"), "{}", err.message);
        // At 300 rpm it fits: 7.5 mm/s × 10 ms = 75 µm.
        let mut c = LinkCheck::new(&axes, 100.0, Pos { z: 5.0, ..Pos::default() });
        assert!(c.check(&mv(MoveKind::Tap { end: Pos { z: -20.0, ..Pos::default() }, lead: 1.5, rpm: 300.0, spindle: 1 })).is_ok());
    }

    #[test]
    fn thread_uses_the_programmed_spindle_speed_and_the_axis_share() {
        let axes = [SlowAxis { axis: "x".into(), link: "rtu".into(), cycle_s: 0.020 }];
        let mut c = LinkCheck::new(&axes, 100.0, Pos { x: 20.0, z: 2.0, ..Pos::default() });
        c.check(&mv(MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm: 600.0, css: None, max_rpm: None }))).unwrap();
        // A straight thread along Z does not move X: accepted whatever the speed.
        let straight =
            MoveKind::Thread { end: Pos { x: 20.0, z: -30.0, ..Pos::default() }, lead: 2.0, start_angle: 0.0, continuous: false, lead_inc: 0.0 };
        assert!(c.check(&mv(straight)).is_ok());
        // A taper moving X by 1 mm over 32 mm of Z: v_x = 20 mm/s / 32 → 12.5 µm per 20 ms: fine.
        let mut c = LinkCheck::new(&axes, 100.0, Pos { x: 20.0, z: 2.0, ..Pos::default() });
        c.check(&mv(MoveKind::Spindle(SpindleCmd { dir: SpindleDir::Cw, rpm: 600.0, css: None, max_rpm: None }))).unwrap();
        let taper =
            MoveKind::Thread { end: Pos { x: 21.0, z: -30.0, ..Pos::default() }, lead: 2.0, start_angle: 0.0, continuous: false, lead_inc: 0.0 };
        assert!(c.check(&mv(taper.clone())).is_ok());
        // A face thread (X only) at the same speed: 20 mm/s × 20 ms = 400 µm: refused.
        let face =
            MoveKind::Thread { end: Pos { x: 5.0, z: -30.0, ..Pos::default() }, lead: 2.0, start_angle: 0.0, continuous: false, lead_inc: 0.0 };
        assert_eq!(c.check(&mv(face)).unwrap_err().number, crate::alarm::MODBUS_SYNC_TOO_SLOW);
    }
}
