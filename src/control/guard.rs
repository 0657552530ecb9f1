//! Limits before motion, in two places.
//!
//! 1. **Before the first move** ([`check_program`]): `cncgw run` runs the interpreter over the
//!    whole program once (as it does for the Modbus link check) and refuses the program if
//!    its path is known to leave the software travel limits — end points and the bulge of
//!    every arc, in whichever plane — or to enter the G22 stored-stroke area (the
//!    interpreter checks G22 on every move, `interp::cycles::stroke`; its alarm 502/503
//!    found here refuses the program). `Motion::push` makes the same travel check (2301), but
//!    only when the move reaches the look-ahead queue, possibly long after motion started;
//!    a Fanuc checks stroke limits before movement (No.1300#7 BFA) only block by block, so
//!    refusing the whole program up front is stricter, and the path of a program whose
//!    branches depend on an input (M91/M92) is only known up to that input: the checks at
//!    run time stay.
//! 2. **Every set-point** ([`Guard::check`]): the cycle loop checks each set-point against
//!    the travel box just before it is sent; a set-point outside is never sent and every
//!    drive gets quick stop (Fanuc OT0500/OT0501, "+/− overtravel (soft 1)"). This is the
//!    last line against a planner or correction bug: with a correct planner it never trips.
//!    A set-point outside the box that moves back towards it is allowed, so a machine
//!    switched on beyond a limit can be brought back (Fanuc does the same before the
//!    reference is set). What is checked is the interpolated position (`Motion::position`);
//!    the rigid-tap sync correction added on top of it (≤ 0.5 mm, so that the *actual*
//!    position follows the interpolated one) is a servo-level compensation, exempt as a
//!    Fanuc's stroke check exempts its compensations.
//!
//! The G22 area is switched by the program: G22/G23 reach the cycle loop in the move stream
//! ([`MoveKind::StrokeCheck`], passed through motion as `Event::Stroke2` in program order),
//! and the loop calls [`Guard::set_stroke2`] in the cycle execution reaches the block, before
//! checking that cycle's set-point. The interpreter checks the exact programmed path as well
//! (arcs on chords of ≤ 2°, and before the first move via [`check_program`]); the per-set-point
//! check also catches a move that never went through the interpreter.

use crate::canon::{Move, MoveKind, Plane, Pos};
use crate::motion::geom::{self, Geom};
use crate::motion::{alarms, Limits, StrokeArea as Area, AX_X, AX_Y, AX_Z, N_AXES};
use crate::Alarm;

/// Fanuc OT0500: + overtravel (soft 1).
pub const PLUS_OVERTRAVEL: u32 = crate::alarm::PLUS_OVERTRAVEL;
/// Fanuc OT0501: − overtravel (soft 1).
pub const MINUS_OVERTRAVEL: u32 = crate::alarm::MINUS_OVERTRAVEL;

/// Set-points may exceed a limit by this much (rounding of the interpolation), mm.
const TOL: f64 = 1e-6;
const NAMES: [char; 3] = ['X', 'Y', 'Z'];

/// What a refused set-point did (no allocation; [`Violation::alarm`] makes the message).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Violation {
    /// 0 X, 1 Y, 2 Z.
    pub axis: usize,
    pub value: f64,
    /// The limit it crossed (for the G22 area: the boundary of that axis).
    pub limit: f64,
    pub plus: bool,
    /// The G22 area rather than the travel limits.
    pub stroke2: bool,
}

impl Violation {
    pub fn alarm(&self, line: u32) -> Alarm {
        let name = NAMES[self.axis];
        let radius = if self.axis == AX_X { " (radius)" } else { "" };
        let what = if self.stroke2 { "the G22 stored-stroke area" } else { "its software travel limit" };
        Alarm::new(
            if self.stroke2 {
                if self.plus { crate::alarm::PLUS_STROKE } else { crate::alarm::MINUS_STROKE }
            } else if self.plus {
                PLUS_OVERTRAVEL
            } else {
                MINUS_OVERTRAVEL
            },
            format!(
                "{} overtravel at line {line}: the set-point {name}{:.4} mm{radius} crosses {what} ({:.4}); it was not sent and every drive was sent quick stop; move the axis back inside in jog and check the program and the offsets",
                if self.plus { "+" } else { "−" },
                self.value,
                self.limit
            ),
        )
    }
}

/// The per-set-point check: O(1), no allocation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Guard {
    present: [bool; 3],
    lo: [f64; 3],
    hi: [f64; 3],
    stroke2: Option<Area>,
    /// The last set-point passed (to allow moving back towards the box).
    last: [f64; 3],
}

impl Guard {
    /// The travel limits of the configured linear axes (X, Y, Z), as `Motion` uses them.
    pub fn from_limits(l: &Limits) -> Guard {
        let mut g = Guard { present: [false; 3], lo: [0.0; 3], hi: [0.0; 3], stroke2: None, last: [0.0; 3] };
        for i in [AX_X, AX_Y, AX_Z] {
            g.present[i] = l.present[i];
            (g.lo[i], g.hi[i]) = l.travel[i];
        }
        g
    }

    /// Narrow the travel box of axis `i` (0 X, 1 Y, 2 Z), e.g. to a fixture's envelope.
    pub fn set_travel(&mut self, i: usize, lo: f64, hi: f64) {
        if i < 3 {
            (self.lo[i], self.hi[i]) = (lo, hi);
        }
    }

    /// Also keep set-points out of (or, `outside`, inside) a fixed area.
    pub fn set_stroke2(&mut self, area: Option<Area>) {
        self.stroke2 = area;
    }

    /// Where the axes are before the first set-point.
    pub fn set_start(&mut self, pos: &[f64; N_AXES]) {
        self.last = [pos[AX_X], pos[AX_Y], pos[AX_Z]];
    }

    /// May `pos` be sent? A set-point beyond a limit passes only if it is no further beyond
    /// than the last one passed.
    #[inline]
    pub fn check(&mut self, pos: &[f64; N_AXES]) -> Result<(), Violation> {
        let p = [pos[AX_X], pos[AX_Y], pos[AX_Z]];
        for i in 0..3 {
            if !self.present[i] {
                continue;
            }
            let (v, last) = (p[i], self.last[i]);
            if !v.is_finite() {
                return Err(Violation { axis: i, value: v, limit: self.hi[i], plus: true, stroke2: false });
            }
            if v > self.hi[i] + TOL && v > last + TOL {
                return Err(Violation { axis: i, value: v, limit: self.hi[i], plus: true, stroke2: false });
            }
            if v < self.lo[i] - TOL && v < last - TOL {
                return Err(Violation { axis: i, value: v, limit: self.lo[i], plus: false, stroke2: false });
            }
        }
        if let Some(a) = self.stroke2 {
            let inside = |q: &[f64; 3]| (0..3).all(|i| q[i] > a.lo[i] + TOL && q[i] < a.hi[i] - TOL);
            let bad = if a.outside { !inside(&p) && inside(&self.last) } else { inside(&p) && !inside(&self.last) };
            if bad {
                // Name the axis that moved most.
                let i = (0..3).max_by(|&x, &y| (p[x] - self.last[x]).abs().total_cmp(&(p[y] - self.last[y]).abs())).unwrap_or(0);
                let plus = p[i] >= self.last[i];
                let limit = if plus == a.outside { a.hi[i] } else { a.lo[i] };
                return Err(Violation { axis: i, value: p[i], limit, plus, stroke2: true });
            }
        }
        self.last = p;
        Ok(())
    }
}

fn xyz(p: &Pos) -> [f64; 3] {
    [p.x, p.y, p.z]
}

/// Before the first move: follow the program's moves (from `start`, machine coordinates) and
/// refuse it if the path leaves the travel limits of `limits` (alarm 2301, as
/// `Motion::push` would later) or the interpreter finds the G22 area entered (502/503).
/// Other program alarms are left to the run, which stops at their block. The caller bounds
/// the iterator (a program ending in M99 never ends).
pub fn check_program(moves: impl Iterator<Item = Result<Move, Alarm>>, limits: &Limits, start: Pos) -> Result<(), Alarm> {
    check_program_with(moves, limits, start, None, usize::MAX)
}

/// [`check_program`], also planning every move as motion will (`Motion::push`: feed, spindle,
/// threads and taps against the axes, C, …) with the tool spindle `tool` if the machine has
/// one, and refusing a program that ends without M02/M30 (Fanuc's "end of record", PS5010)
/// unless it is still going after `bound` moves (an M99 loop).
pub fn check_program_with(
    moves: impl Iterator<Item = Result<Move, Alarm>>,
    limits: &Limits,
    start: Pos,
    tool: Option<&crate::motion::polygon::ToolSpindle>,
    bound: usize,
) -> Result<(), Alarm> {
    let refuse = |a: Alarm| Alarm { message: format!("{} — refused before any motion", a.message), ..a };
    let mut pos = xyz(&start);
    let mut plan = crate::motion::Motion::new(limits.clone(), [start.x, start.y, start.z, start.c]);
    if let Some(t) = tool {
        plan.set_tool_spindle(t, 0.0);
    }
    let (mut count, mut ended, mut last_src) = (0usize, false, None);
    for m in moves.take(bound) {
        let m = match m {
            Ok(m) => m,
            // The program runs from the same start, variables and tables: an alarm here (a
            // macro error, a user alarm #3000, G22) would stop the run at the same block,
            // after the moves before it — refused before any of them.
            Err(a) => return Err(refuse(a)),
        };
        count += 1;
        ended |= matches!(m.kind, MoveKind::End { .. });
        last_src = Some(m.src.clone());
        if let Some(end) = m.kind.end().filter(|_| !matches!(m.kind, MoveKind::Polar { .. })) {
            // (Polar moves are in the virtual X–C plane: motion checks the converted X and C.)
            check_path(limits, &pos, &m, xyz(&end)).map_err(refuse)?;
            pos = xyz(&end);
        }
        if !plan.has_room() {
            plan.discard_queue();
        }
        plan.push(&m).map_err(refuse)?;
    }
    if !ended && count < bound {
        let a = end_of_record(count == 0);
        return Err(refuse(match last_src {
            Some(s) => a.at(s),
            None => a,
        }));
    }
    Ok(())
}

/// The travel check of one move from `pos` to `end`: its end point and the bulge of an arc.
fn check_path(limits: &Limits, pos: &[f64; 3], m: &Move, end: [f64; 3]) -> Result<(), Alarm> {
    let pos = *pos;
    let at = |a: Alarm| a.at(m.src.clone());
    check_point(limits, &pos, &end, "end point").map_err(at)?;
    if let MoveKind::Arc { center, cw, plane, .. } = &m.kind {
        let axes = match plane {
            Plane::Xy => (AX_X, AX_Y, AX_Z),
            Plane::Zx => (AX_Z, AX_X, AX_Y),
            Plane::Yz => (AX_Y, AX_Z, AX_X),
        };
        if let Some((Geom::Arc { ia, ib, ca, cb, r0, dr, th0, sweep, .. }, _, _)) = geom::arc(pos, end, xyz(center), axes, *cw) {
            // The arc's outermost points: where it crosses the plane axes' directions.
            let r = r0.max(r0 + dr);
            for k in 0..4 {
                let ang = k as f64 * std::f64::consts::FRAC_PI_2;
                let rel = if sweep >= 0.0 { (ang - th0).rem_euclid(std::f64::consts::TAU) } else { (th0 - ang).rem_euclid(std::f64::consts::TAU) };
                if rel <= sweep.abs() {
                    let mut q = pos;
                    match k {
                        0 => q[ia] = ca + r,
                        1 => q[ib] = cb + r,
                        2 => q[ia] = ca - r,
                        _ => q[ib] = cb - r,
                    }
                    check_point(limits, &pos, &q, "arc").map_err(at)?;
                }
            }
        }
    }
    Ok(())
}

/// Fanuc PS5010 "end of record": the program's text ended before M02/M30.
pub const END_OF_RECORD: u32 = crate::alarm::END_OF_RECORD;

/// The PS5010 alarm of a program without M02/M30 (`empty`: it produced no move at all).
pub fn end_of_record(empty: bool) -> Alarm {
    Alarm::new(
        END_OF_RECORD,
        if empty {
            "the program is empty: nothing to run".to_string()
        } else {
            "the program ends without M02 or M30 (end of record): end it with M30 (or M02), so that the controller knows it is over".to_string()
        },
    )
}

/// [`check_program`] over a program file as `cncgw run` will execute it: from `start`, with
/// the common variables `vars` loaded; at most 2,000,000 moves (a program ending in M99
/// runs forever).
pub fn check_program_file(
    program: &std::path::Path,
    cfg: &crate::config::MachineConfig,
    start: Pos,
    vars: &std::collections::HashMap<u32, f64>,
) -> Result<(), Alarm> {
    let Ok(mut pre) = crate::interp::Interpreter::from_file(program, cfg) else { return Ok(()) };
    pre.set_start_position(start);
    pre.set_common_vars(vars.clone());
    check_program(pre.take(2_000_000), &Limits::from_config(cfg), start)
}

/// Axis values of `p` that changed from `from` must lie inside the travel (an axis that does
/// not move is not checked: the machine may stand outside a limit before it is referenced).
fn check_point(l: &Limits, from: &[f64; 3], p: &[f64; 3], what: &str) -> Result<(), Alarm> {
    for i in [AX_X, AX_Y, AX_Z] {
        if !l.present[i] || (p[i] - from[i]).abs() <= 1e-9 {
            continue;
        }
        let (lo, hi) = l.travel[i];
        let v = p[i];
        if !(v >= lo - TOL && v <= hi + TOL) {
            let radius = if i == AX_X { " (radius)" } else { "" };
            return Err(Alarm::new(
                alarms::TRAVEL,
                format!("the program's path leaves the travel limits: {} {what} {v:.4} mm{radius} is beyond [{lo}, {hi}]; correct the program or the work offset", NAMES[i]),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canon::{Feed, SrcPos};
    use crate::config::MachineConfig;
    use crate::interp::Interpreter;

    fn lim() -> Limits {
        Limits::from_config(&MachineConfig::embedded())
    }

    #[test]
    fn setpoints_outside_the_travel_are_refused_and_coming_back_is_allowed() {
        // Embedded lathe: X radius [-2, 150], Z [-400, 5].
        let mut g = Guard::from_limits(&lim());
        g.set_start(&[10.0, 0.0, 0.0, 0.0]);
        assert!(g.check(&[10.0, 0.0, 5.0, 0.0]).is_ok());
        let v = g.check(&[10.0, 0.0, 5.01, 0.0]).unwrap_err();
        assert_eq!((v.axis, v.plus, v.stroke2), (AX_Z, true, false));
        assert_eq!(v.alarm(7).number, PLUS_OVERTRAVEL);
        let v = g.check(&[-2.5, 0.0, 0.0, 0.0]).unwrap_err();
        assert_eq!((v.axis, v.plus), (AX_X, false));
        assert_eq!(v.alarm(7).number, MINUS_OVERTRAVEL);
        assert!(g.check(&[f64::NAN, 0.0, 0.0, 0.0]).is_err());
        // Y is not configured: not checked. The spindle never is.
        assert!(g.check(&[10.0, 999.0, 0.0, 1e9]).is_ok());
        // Started beyond +Z: may come back, may not go further.
        g.set_start(&[10.0, 0.0, 8.0, 0.0]);
        assert!(g.check(&[10.0, 0.0, 8.0, 0.0]).is_ok());
        assert!(g.check(&[10.0, 0.0, 7.5, 0.0]).is_ok());
        assert!(g.check(&[10.0, 0.0, 7.6, 0.0]).is_err());
    }

    #[test]
    fn setpoints_entering_a_stroke2_area_are_refused() {
        let mut g = Guard::from_limits(&lim());
        g.set_stroke2(Some(Area { lo: [20.0, f64::NEG_INFINITY, -50.0], hi: [40.0, f64::INFINITY, -10.0], outside: false }));
        g.set_start(&[50.0, 0.0, -30.0, 0.0]);
        assert!(g.check(&[40.5, 0.0, -30.0, 0.0]).is_ok());
        let v = g.check(&[39.5, 0.0, -30.0, 0.0]).unwrap_err();
        assert!(v.stroke2 && !v.plus && v.axis == AX_X, "{v:?}");
        assert_eq!(v.alarm(3).number, crate::alarm::MINUS_STROKE);
    }

    fn program(text: &str) -> Result<(), Alarm> {
        let cfg = MachineConfig::embedded();
        let it = Interpreter::from_source("guard.nc", text, &cfg).expect("parses");
        check_program(it.take(100_000), &lim(), Pos::ZERO)
    }

    #[test]
    fn a_program_whose_arc_bulges_past_a_limit_is_refused() {
        // Z max is 5. A half circle from (X Ø20, Z0) to (X Ø60, Z0), R10, centre (Ø40, Z0):
        // both end points inside; one sense bulges to Z+10 (beyond), the other to Z−10.
        let cw = program("G98 G00 X20 Z0\nG02 X60 Z0 R10 F100\nG00 X100\nM30\n");
        let ccw = program("G98 G00 X20 Z0\nG03 X60 Z0 R10 F100\nG00 X100\nM30\n");
        assert!(cw.is_err() != ccw.is_err(), "exactly one sense bulges past Z5: {cw:?} {ccw:?}");
        let e = cw.err().or(ccw.err()).unwrap();
        assert_eq!(e.number, alarms::TRAVEL, "{e}");
        assert_eq!(e.pos.as_ref().map(|p| p.line), Some(2), "{e}");
        assert!(e.message.contains("Z arc 10.0000") && e.message.contains("refused before any motion"), "{e}");
        // A half circle whose bulge stays inside: fine.
        assert!(program("G98 G00 X20 Z-6\nG02 X20 Z4 R5 F100\nG03 X20 Z-6 R5\nM30\n").is_ok());
    }

    #[test]
    fn a_program_entering_the_g22_area_is_refused_before_the_first_move() {
        let e = program("G98\nG00 X100 Z-100\nG22 X80 Z-20 I40 K-60\nG01 X100 Z-100 F100\nG01 X60 Z-40\nM30\n").unwrap_err();
        assert!(e.number == 502 || e.number == 503, "{e}");
        assert!(e.message.contains("refused before any motion"), "{e}");
        // Any other program alarm is refused before motion too (here: no feed, PS0011).
        let e = program("G00 X10\nG01 Z-10\nM30\n").unwrap_err();
        assert_eq!((e.number, e.pos.as_ref().map(|p| p.line)), (11, Some(2)), "{e}");
        assert!(e.message.contains("refused before any motion"), "{e}");
    }

    #[test]
    fn end_points_beyond_the_travel_are_refused() {
        let e = program("G00 X10 Z-10\nG01 X400 F100\nM30\n").unwrap_err();
        assert_eq!(e.number, alarms::TRAVEL);
        assert_eq!(e.pos.as_ref().map(|p| p.line), Some(2), "{e}");
        // Moves given directly (not via the interpreter) are checked the same way.
        let m = Move {
            src: SrcPos::new("t.nc".into(), 1, 1),
            kind: MoveKind::Feed { end: Pos { x: 10.0, y: 0.0, z: -500.0, c: 0.0 }, feed: Feed::PerMin(100.0) },
            exact_stop: false,
            work_offset: Pos::ZERO,
            tag: None,
        };
        assert!(check_program(std::iter::once(Ok(m)), &lim(), Pos::ZERO).is_err());
    }
}
