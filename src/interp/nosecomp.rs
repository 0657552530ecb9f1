//! Tool nose radius compensation G40/G41/G42 (manual 004 §2.18), applied to the canonical
//! move stream after the interpreter made it, with one motion of look-ahead for the corners
//! and a window of three compensated blocks for the interference check.
//!
//! Geometry, in the ZX plane with u = Z, v = X (radius), the axes in which G03 is
//! counter-clockwise (X up, Z right, seen from +Y; the rear-tool-post picture, fig. 2.63):
//! - G41 puts the nose centre R to the left of the programmed path, G42 to the right.
//! - The programmed point is the imaginary tool tip (fig. 2.62): the machine point is
//!   `centre + R·t`, t the direction from the nose centre to the imaginary tip of the tip
//!   number (1: +X+Z, 2: +X−Z, 3: −X−Z, 4: −X+Z, 5: +Z, 6: +X, 7: −Z, 8: −X, 0/9: the
//!   centre itself — the usual Fanuc numbering; figs. 2.63/2.64 draw the same numbers for the
//!   rear and the front tool post, mirrored with the X axis, so in X/Z terms they agree).
//! - Corners use the manual's linear transitions by the corner angle α on the workpiece side
//!   (fig. 2.68): 180° ≤ α < 360° shortening (the offset curves' intersection), 90° ≤ α <
//!   180° lengthening (the intersection of the offset lines, for an arc its tangent line at
//!   the offset point), 0° ≤ α < 90° insertion (both offset lines extended by R and one line
//!   inserted between their ends). Start-up (the first motion after G41/G42) runs from the
//!   uncompensated position to the corner point of its end, and cancel (the motion of the
//!   G40 block) from the corner point of its start to the uncompensated end point, with the
//!   same three rules. Neither may be an arc.
//!
//! Alarms (numbers from the manual where it gives them): 3605 interference (a compensated
//! line runs 90°–270° against its programmed direction, an inner arc smaller than the
//! radius, an arc whose compensated sweep turns the other way, offset curves that do not
//! meet), 3607 corner angle under 0.1° (the path turns back on itself: α < 0.1° or
//! α > 359.9°), 3576 G41↔G42 without G40, 3577 T while compensating. Start-up or cancel
//! on an arc has no number in the manual: Fanuc 0i-TF PS0034 "no circular interpolation
//! allowed in start-up/cancel"; G41/G42 outside G18 is PS0010 here (the lathe has no Y for
//! the G17/G19 cases of the tip note).
//!
//! Moves the compensation does not apply to pass through unchanged and end the offset the way
//! a cancel would, the next motion starting up again: threads, taps, and the moves of the
//! cycles G71–G76 (§2.16 note 5), G92/G92.1 and the drilling cycles. G90/G94 arrive already
//! offset: the interpreter offsets their cuts by the tip (Fanuc 0i-TF; the manual says
//! nothing), see [`single_cycle_offset`]. G70's finishing contour is compensated like the
//! blocks it repeats.
//!
//! Look-ahead: besides the pending motion, up to [`LOOK_AHEAD`] compensated blocks wait in a
//! window before they leave, so that each block's nose path is checked (3605) against the
//! programmed contour of the blocks up to three before it, not only its neighbour (Fanuc
//! 0i-TF checks over its buffer the same way); the window empties whenever the offset ends
//! (G40, a cycle, G52, the end). Non-motion moves (M, S, T,
//! dwell) wait behind the pending motion, in order. G52 ends the offset for a moment
//! (§2.12.3 note 2). G41/G42 in G12.1 mode compensate in the virtual X–C plane (tip 0).
//!
//! A G40/G41/G42 takes effect at its place in the move stream (the interpreter passes the
//! index of the next move to be queued), since G70 runs many contour blocks in one step.

use crate::canon::{Move, MoveKind, Plane, Pos};
use crate::Alarm;

/// §2.18.4: interference (overcut).
pub const INTERFERENCE_ALARM: u32 = crate::alarm::NOSE_INTERFERENCE;
/// §2.18.4 note 1: corner angle under 0.1°.
pub const CORNER_ANGLE_ALARM: u32 = crate::alarm::NOSE_CORNER_ANGLE;
/// §2.18.4 note 2: G41 ↔ G42 without G40.
pub const SWITCH_ALARM: u32 = crate::alarm::NOSE_SWITCH;
/// §2.18.4 note 3: T code while compensating.
pub const T_ALARM: u32 = crate::alarm::NOSE_T_CODE;
/// Fanuc PS0034: start-up or cancel on an arc (the manual: "不允许").
pub const ARC_STARTUP_ALARM: u32 = crate::alarm::NOSE_ARC_STARTUP;

use super::vec2::{add, cross, dot, left, mul, norm, sub, unit, P as P2};

fn uv(p: Pos) -> P2 {
    (p.z, p.x)
}

/// Direction from the nose centre to the imaginary tip of tip number `tip`, in (Z, X).
pub fn tip_vector(tip: u8) -> P2 {
    match tip {
        1 => (1.0, 1.0),
        2 => (-1.0, 1.0),
        3 => (-1.0, -1.0),
        4 => (1.0, -1.0),
        5 => (1.0, 0.0),
        6 => (0.0, 1.0),
        7 => (-1.0, 0.0),
        8 => (0.0, -1.0),
        _ => (0.0, 0.0),
    }
}

/// A change of the compensation at a place in the move stream.
#[derive(Clone, Copy, Debug)]
enum Change {
    Mode(Option<Side>, f64, P2),
    Suspend,
}

/// Which side the nose centre goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    Left,
    Right,
}

/// A programmed path segment in (Z, X).
#[derive(Clone, Debug)]
struct Seg {
    a: P2,
    b: P2,
    /// Arc centre and clockwise flag.
    arc: Option<(P2, bool)>,
    /// `c_zero` of a G12.1 move (its coordinates are virtual X–C).
    polar: Option<f64>,
    mv: Move,
}

impl Seg {
    /// Unit tangent at parameter end (`at_end`) or start.
    fn tangent(&self, at_end: bool) -> P2 {
        let p = if at_end { self.b } else { self.a };
        match self.arc {
            None => unit(sub(self.b, self.a)),
            Some((c, cw)) => {
                let r = unit(sub(p, c));
                if cw {
                    (r.1, -r.0)
                } else {
                    left(r)
                }
            }
        }
    }
}

/// The compensation stage. [`NoseComp::feed`] takes the interpreter's moves in order and
/// appends the compensated ones to `out`; [`NoseComp::finish`] flushes at the end.
#[derive(Clone, Debug)]
pub struct NoseComp {
    /// Mode in force for the moves being fed (G40 = None).
    mode: Option<Side>,
    /// The last mode the program asked for (checked against the next request and T).
    requested: Option<Side>,
    /// Mode changes not yet reached by the stream: (index of the first move they apply to,
    /// mode, radius, tip vector). G70 runs many blocks in one step, so a change must apply at
    /// its place in the queue, not when it is executed.
    changes: std::collections::VecDeque<(u64, Change)>,
    /// Moves fed so far.
    fed: u64,
    radius: f64,
    tip: P2,
    /// The programmed position (end of the last move seen).
    prog: Pos,
    /// Machine position of the last move emitted (or the programmed one when none).
    mach: P2,
    /// Motion waiting for the next one to fix its end, with its side and whether it starts up.
    pending: Option<(Seg, Side, bool)>,
    /// Non-motion moves behind `pending`.
    held: Vec<Move>,
    /// Compensated blocks not yet released, the newest last: each is checked against the
    /// ones up to [`LOOK_AHEAD`] blocks before it (see [`NoseComp::push_group`]).
    window: std::collections::VecDeque<Group>,
}

/// How many blocks ahead the interference check looks (Fanuc 0i-TF: 3 in its buffer).
pub const LOOK_AHEAD: usize = 3;

/// One compensated block on its way out: its moves, its programmed curve and its nose-centre
/// path, both as polylines in (Z, X).
#[derive(Clone, Debug)]
struct Group {
    moves: Vec<Move>,
    prog: Vec<P2>,
    path: Vec<P2>,
    /// Checked against its neighbours (not a start-up, not in the G12.1 plane).
    check: bool,
}

impl Default for NoseComp {
    fn default() -> Self {
        NoseComp {
            mode: None,
            requested: None,
            changes: Default::default(),
            fed: 0,
            radius: 0.0,
            tip: (0.0, 0.0),
            prog: Pos::ZERO,
            mach: (0.0, 0.0),
            pending: None,
            held: Vec::new(),
            window: Default::default(),
        }
    }
}

impl NoseComp {
    pub fn set_start(&mut self, p: Pos) {
        self.prog = p;
        self.mach = uv(p);
    }

    pub fn active(&self) -> bool {
        self.requested.is_some()
    }

    /// Moves fed so far: a mode change requested now applies from move number
    /// `fed() + (moves queued but not yet fed)`.
    pub fn fed(&self) -> u64 {
        self.fed
    }

    /// G40 (None) / G41 / G42 with the nose radius and tip of the selected offset. Errors are
    /// (alarm number, message) for the interpreter to place.
    pub fn set_mode(&mut self, side: Option<Side>, radius: f64, tip: u8, plane: Plane, at: u64) -> Result<(), (u32, String)> {
        if let (Some(old), Some(new)) = (self.requested, side) {
            if old != new {
                return Err((SWITCH_ALARM, format!("{} directly after {}: cancel with G40 first (§2.18.4 note 2)", side_name(new), side_name(old))));
            }
        }
        if side.is_some() && plane != Plane::Zx {
            return Err((10, "tool nose radius compensation works in the ZX plane (G18) only".into()));
        }
        self.requested = side;
        self.changes.push_back((at, Change::Mode(side, radius.max(0.0), tip_vector(tip))));
        Ok(())
    }

    /// G52 (§2.12.3 note 2): the offset is cancelled for a moment: the motion before ends
    /// perpendicular to its end, the next one starts up again.
    pub fn suspend(&mut self, at: u64) {
        if self.requested.is_some() {
            self.changes.push_back((at, Change::Suspend));
        }
    }

    /// Apply the changes that take effect at move number `k`.
    fn apply_changes(&mut self, k: u64, out: &mut Vec<Move>) -> Result<(), Alarm> {
        while let Some(&(at, ch)) = self.changes.front() {
            if at > k {
                break;
            }
            self.changes.pop_front();
            match ch {
                Change::Mode(side, r, t) => {
                    self.mode = side;
                    if side.is_some() {
                        self.radius = r;
                        self.tip = t;
                    }
                }
                Change::Suspend => self.flush_perpendicular(out)?,
            }
        }
        Ok(())
    }

    fn compensable(m: &Move) -> bool {
        let tagged_ok = match &m.tag {
            None => true,
            Some(t) => &*t.cycle == "G70",
        };
        tagged_ok
            && match &m.kind {
                MoveKind::Rapid { .. } | MoveKind::Feed { .. } => true,
                MoveKind::Arc { plane, .. } => *plane == Plane::Zx,
                MoveKind::Polar { .. } => true,
                _ => false,
            }
    }

    /// Machine point of a nose-centre point.
    fn machine(&self, c: P2) -> P2 {
        add(c, mul(self.tip, self.radius))
    }

    /// Take one move from the interpreter.
    pub fn feed(&mut self, m: Move, out: &mut Vec<Move>) -> Result<(), Alarm> {
        self.apply_changes(self.fed, out)?;
        self.fed += 1;
        let Some(end) = m.kind.end() else {
            if self.pending.is_some() {
                self.held.push(m);
            } else {
                self.release(0, out);
                out.push(m);
            }
            return Ok(());
        };
        let start = self.prog;
        self.prog = end;
        // G12.1 moves are compensated in their virtual X–C plane.
        let (a, b, polar) = match &m.kind {
            MoveKind::Polar { from, to, c_zero, .. } => ((from[0], from[1]), (to[0], to[1]), Some(*c_zero)),
            _ => (uv(start), uv(end), None),
        };
        if self.pending.as_ref().is_some_and(|p| p.0.polar.is_some() != polar.is_some()) {
            // Into or out of the polar plane: the offset ends here and starts up again.
            self.flush_perpendicular(out)?;
        }
        if !Self::compensable(&m) {
            self.flush_perpendicular(out)?;
            self.release(0, out);
            self.mach = b;
            out.push(m);
            return Ok(());
        }
        if self.mode.is_none() && self.pending.is_none() {
            self.release(0, out);
            self.mach = b;
            out.push(m);
            return Ok(());
        }
        if norm(sub(b, a)) < 1e-9 {
            // No motion in the plane (a C or Y move only): keep it in order, on the path.
            if self.pending.is_some() {
                self.held.push(m);
            } else {
                let mut m = m;
                if polar.is_none() {
                    set_uv(&mut m.kind, self.mach);
                }
                self.release(0, out);
                out.push(m);
            }
            return Ok(());
        }
        let arc = match &m.kind {
            MoveKind::Arc { center, cw, .. } => Some((uv(*center), *cw)),
            MoveKind::Polar { center: Some(c), cw, .. } => Some(((c[0], c[1]), *cw)),
            _ => None,
        };
        let seg = Seg { a, b, arc, polar, mv: m };
        match self.pending.take() {
            None => {
                // Start-up (mode is on: the G40 case without a pending motion returned above).
                let side = self.mode.unwrap_or(Side::Left);
                if seg.arc.is_some() {
                    return Err(at(
                        &seg.mv,
                        ARC_STARTUP_ALARM,
                        "tool nose radius compensation cannot start on an arc (§2.18.3): start it with a G00/G01 move",
                    ));
                }
                // The tool is where the last move left it: at `seg.a`, or near it when an
                // offset was just ended (G52, a cycle); after a change of plane (G12.1/G13.1)
                // `mach` is in the other plane's coordinates and `seg.a` is the start.
                if norm(sub(self.mach, seg.a)) > 3.0 * self.radius + 1e-6 {
                    self.mach = seg.a;
                }
                self.pending = Some((seg, side, true));
            }
            Some((prev, side, startup)) if self.mode.is_some() => {
                let (prev_end, extra, next_start) = self.corner(&prev, &seg, side, false)?;
                self.emit(&prev, side, startup, prev_end, &extra, out)?;
                self.mach = self.machine(next_start);
                self.pending = Some((seg, side, false));
            }
            Some((prev, side, startup)) => {
                // Cancel: this line leaves the offset for the programmed end point.
                if seg.arc.is_some() {
                    return Err(at(
                        &seg.mv,
                        ARC_STARTUP_ALARM,
                        "tool nose radius compensation cannot be cancelled on an arc (§2.18.3): cancel it with a G00/G01 move",
                    ));
                }
                let (prev_end, extra, _) = self.corner(&prev, &seg, side, true)?;
                self.emit(&prev, side, startup, prev_end, &extra, out)?;
                let mut mv = seg.mv;
                if let MoveKind::Polar { from, .. } = &mut mv.kind {
                    *from = [self.mach.0, self.mach.1];
                }
                self.mach = seg.b;
                self.release(0, out);
                out.push(mv);
            }
        }
        Ok(())
    }

    /// End of the program (or the stream): a pending motion ends perpendicular to its end.
    pub fn finish(&mut self, out: &mut Vec<Move>) -> Result<(), Alarm> {
        self.apply_changes(u64::MAX, out)?;
        self.flush_perpendicular(out)?;
        self.release(0, out);
        Ok(())
    }

    /// The pending motion ends at its end point offset perpendicularly; the offset is then
    /// suspended (the next compensable motion starts up again if G41/G42 is still on).
    fn flush_perpendicular(&mut self, out: &mut Vec<Move>) -> Result<(), Alarm> {
        if let Some((prev, side, startup)) = self.pending.take() {
            let n = mul(normal(prev.tangent(true), side), self.radius);
            let e = add(prev.b, n);
            self.emit(&prev, side, startup, e, &[], out)?;
        }
        Ok(())
    }

    /// Emit `prev` compensated: its own curve to the centre point `end`, then the transition
    /// lines through `extra`, then the held non-motion moves.
    fn emit(&mut self, prev: &Seg, side: Side, startup: bool, end: P2, extra: &[P2], out: &mut Vec<Move>) -> Result<(), Alarm> {
        let mut g = Vec::with_capacity(2 + extra.len() + self.held.len());
        let from = self.mach;
        let to = self.machine(end);
        let mut mv = prev.mv.clone();
        let last_exact = mv.exact_stop;
        match (&mut mv.kind, prev.arc) {
            (MoveKind::Arc { .. } | MoveKind::Polar { .. }, Some((c, cw))) => {
                let r = norm(sub(prev.a, c));
                let sgn = if cw { 1.0 } else { -1.0 } * if side == Side::Left { 1.0 } else { -1.0 };
                // Left of a CCW arc is the centre side: the radius shrinks.
                let r2 = r + sgn * self.radius;
                if r2 <= 1e-9 {
                    return Err(at(
                        &prev.mv,
                        INTERFERENCE_ALARM,
                        format!(
                            "interference: the arc's radius {r:.3} mm is not larger than the nose radius {:.3} mm on the inside (§2.18.4)",
                            self.radius
                        ),
                    ));
                }
                let sweep = |s: P2, e: P2| {
                    let mut d = (cross(s, e)).atan2(dot(s, e));
                    if cw {
                        d = -d;
                    }
                    if d < 0.0 {
                        d += std::f64::consts::TAU;
                    }
                    d
                };
                let ps = sweep(sub(prev.a, c), sub(prev.b, c));
                let cs = sweep(sub(sub(from, mul(self.tip, self.radius)), c), sub(end, c));
                if (ps - cs).abs() > std::f64::consts::PI && ps > 1e-9 {
                    return Err(at(
                        &prev.mv,
                        INTERFERENCE_ALARM,
                        "interference: the compensated arc turns the other way round (the groove or step is narrower than the nose, §2.18.4)",
                    ));
                }
                if let MoveKind::Arc { center, .. } = &mut mv.kind {
                    *center = set_p(*center, self.machine(c));
                }
            }
            _ => {
                if !startup {
                    let pd = sub(prev.b, prev.a);
                    let cd = sub(to, from);
                    if norm(cd) > 1e-9 && dot(pd, cd) < 0.0 {
                        return Err(at(&prev.mv, INTERFERENCE_ALARM, "interference: the compensated path runs against the programmed direction (the step is smaller than the nose radius, §2.18.4)"));
                    }
                }
            }
        }
        place(&mut mv, from, to);
        mv.exact_stop = last_exact && extra.is_empty();
        g.push(mv);
        let mut cur = to;
        for (i, p) in extra.iter().enumerate() {
            let q = self.machine(*p);
            if norm(sub(q, cur)) < 1e-9 {
                continue;
            }
            let feed = match &prev.mv.kind {
                MoveKind::Feed { feed, .. } | MoveKind::Arc { feed, .. } => Some(*feed),
                _ => None,
            };
            let endp = set_p(prev.mv.kind.end().unwrap_or(Pos::ZERO), q);
            let kind = match (feed, &prev.mv.kind) {
                (Some(feed), MoveKind::Polar { end, c_zero, .. }) => {
                    MoveKind::Polar { end: *end, from: [0.0; 2], to: [0.0; 2], center: None, cw: false, c_zero: *c_zero, feed }
                }
                (Some(feed), _) => MoveKind::Feed { end: endp, feed },
                (None, _) => MoveKind::Rapid { end: endp },
            };
            let mut m = prev.mv.clone();
            m.kind = kind;
            place(&mut m, cur, q);
            m.exact_stop = last_exact && i + 1 == extra.len();
            g.push(m);
            cur = q;
        }
        self.mach = cur;
        for mut h in self.held.drain(..) {
            if h.kind.end().is_some() && prev.polar.is_none() {
                set_uv(&mut h.kind, cur);
            }
            g.push(h);
        }
        // The nose-centre path of what was emitted, and the programmed curve, for the check
        // against the blocks around it.
        let tv = mul(self.tip, self.radius);
        let mut path = vec![sub(from, tv)];
        match prev.arc {
            Some((c, cw)) if prev.polar.is_none() => path.extend(arc_points(sub(from, tv), end, c, cw)),
            _ => path.push(end),
        }
        path.extend(extra.iter().copied());
        let prog = match prev.arc {
            Some((c, cw)) => {
                let mut p = vec![prev.a];
                p.extend(arc_points(prev.a, prev.b, c, cw));
                p
            }
            None => vec![prev.a, prev.b],
        };
        let check = !startup && prev.polar.is_none();
        self.push_group(Group { moves: g, prog, path, check }, &prev.mv, out)
    }

    /// Queue a compensated block: the interference check (3605) of its nose-centre path
    /// against the programmed blocks up to [`LOOK_AHEAD`] before it, and of theirs against
    /// its programmed curve — the blocks next to each other are checked by the corner rules
    /// (§2.18.4 criterion 1); this catches the nose of one block reaching into a block two or
    /// three further on, e.g. past a short block between them, where each pair alone looks
    /// right (Fanuc 0i-TF checks the blocks in its look-ahead buffer the same way). Then the
    /// oldest blocks leave for `out` once they have been checked against every later one
    /// in reach.
    fn push_group(&mut self, g: Group, mv: &Move, out: &mut Vec<Move>) -> Result<(), Alarm> {
        let r = self.radius - 1e-4;
        if g.check && r > 0.0 {
            let n = self.window.len();
            for (k, old) in self.window.iter().enumerate() {
                // Only non-neighbours: `old` is n − k blocks before `g`.
                if n - k < 2 || !old.check {
                    continue;
                }
                let gap = polyline_gap(&g.path, &old.prog).min(polyline_gap(&old.path, &g.prog));
                if gap < r {
                    let line = old.moves.first().map(|m| m.src.line).unwrap_or(0);
                    return Err(at(mv, INTERFERENCE_ALARM, format!(
                        "interference: the nose ({:.3} mm) would cut into the contour of line {line}, {} blocks before this one, by {:.3} mm (a block between them is shorter than the nose radius, §2.18.4)",
                        self.radius, n - k, self.radius - gap)));
                }
            }
        }
        self.window.push_back(g);
        self.release(LOOK_AHEAD, out);
        Ok(())
    }

    /// Let the oldest compensated blocks out until `keep` remain.
    fn release(&mut self, keep: usize, out: &mut Vec<Move>) {
        while self.window.len() > keep {
            if let Some(g) = self.window.pop_front() {
                out.extend(g.moves);
            }
        }
    }

    /// The corner between `prev` and `next` (both offset to `side`): the centre point where
    /// prev's offset curve ends, the transition points after it, and where next's offset
    /// curve starts (the last of them).
    fn corner(&self, prev: &Seg, next: &Seg, side: Side, cancel: bool) -> Result<(P2, Vec<P2>, P2), Alarm> {
        let r = self.radius;
        let p = prev.b;
        let ta = prev.tangent(true);
        let tb = next.tangent(false);
        let na = normal(ta, side);
        let nb = normal(tb, side);
        let s = if side == Side::Left { 1.0 } else { -1.0 };
        let theta = cross(ta, tb).atan2(dot(ta, tb)).to_degrees();
        let alpha = 180.0 + s * theta;
        if !(0.1..=359.9).contains(&alpha) {
            return Err(at(&next.mv, CORNER_ANGLE_ALARM, format!(
                "the corner angle between this block and the previous one is {alpha:.3}°, under the 0.1° limit: the path turns back on itself (§2.18.4 note 1)")));
        }
        let ea = add(p, mul(na, r));
        let sb = add(p, mul(nb, r));
        if r < 1e-12 {
            return Ok((p, vec![], p));
        }
        if alpha >= 180.0 {
            // Shortening: where the offset curves cross.
            if theta.abs() < 1e-9 || norm(sub(ea, sb)) < 1e-9 {
                return Ok((ea, vec![], ea));
            }
            let x = intersect(prev, next, side, r, cancel, ea)
                .ok_or_else(|| at(&next.mv, INTERFERENCE_ALARM, "interference: the offset paths of this block and the previous one do not meet (a step or groove smaller than the nose radius, §2.18.4)"))?;
            return Ok((x, vec![], x));
        }
        let next_line = next.arc.is_none() || cancel;
        let mut extra = Vec::new();
        let prev_end;
        if alpha >= 90.0 {
            // Lengthening: the offset (tangent) lines meet.
            let x = line_line(ea, ta, sb, tb).unwrap_or(ea);
            if prev.arc.is_none() {
                prev_end = x;
            } else {
                prev_end = ea;
                extra.push(x);
            }
        } else {
            // Insertion: both lines extended by R, one line between.
            let q1 = add(ea, mul(ta, r));
            let q2 = sub(sb, mul(tb, r));
            if prev.arc.is_none() {
                prev_end = q1;
            } else {
                prev_end = ea;
                extra.push(q1);
            }
            extra.push(q2);
        }
        if !next_line {
            extra.push(sb);
        }
        let next_start = extra.last().copied().unwrap_or(prev_end);
        Ok((prev_end, extra, next_start))
    }
}

fn side_name(s: Side) -> &'static str {
    match s {
        Side::Left => "G41",
        Side::Right => "G42",
    }
}

fn normal(t: P2, side: Side) -> P2 {
    match side {
        Side::Left => left(t),
        Side::Right => mul(left(t), -1.0),
    }
}

fn at(m: &Move, n: u32, msg: impl Into<String>) -> Alarm {
    Alarm::new(n, msg).at(m.src.clone())
}

fn set_p(mut p: Pos, q: P2) -> Pos {
    p.z = q.0;
    p.x = q.1;
    p
}

fn set_uv(k: &mut MoveKind, q: P2) {
    match k {
        MoveKind::Rapid { end }
        | MoveKind::Feed { end, .. }
        | MoveKind::Arc { end, .. }
        | MoveKind::Thread { end, .. }
        | MoveKind::Tap { end, .. }
        | MoveKind::RigidThread { end, .. } => *end = set_p(*end, q),
        _ => {}
    }
}

/// Put a compensated move from `from` to `to` (plane coordinates): the end point, and for
/// a G12.1 move its virtual points and the machine end converted from them.
fn place(m: &mut Move, from: P2, to: P2) {
    let wx = m.work_offset.x;
    match &mut m.kind {
        MoveKind::Polar { end, from: f, to: t, c_zero, .. } => {
            *f = [from.0, from.1];
            *t = [to.0, to.1];
            let (x, c) = crate::canon::polar_to_machine(*t, *c_zero, wx, end.c);
            end.x = x;
            end.c = c;
        }
        k => set_uv(k, to),
    }
}

/// Intersection of the lines p + λ·d and q + μ·e.
fn line_line(p: P2, d: P2, q: P2, e: P2) -> Option<P2> {
    let den = cross(d, e);
    if den.abs() < 1e-12 {
        return None;
    }
    let lam = cross(sub(q, p), e) / den;
    Some(add(p, mul(d, lam)))
}

/// The offset curve of a segment: a line (point, direction) or a circle (centre, radius).
enum Off {
    Line(P2, P2),
    Circle(P2, f64),
}

fn offset_curve(s: &Seg, side: Side, r: f64, as_line: bool) -> Off {
    match s.arc {
        Some((c, cw)) if !as_line => {
            let rr = norm(sub(s.a, c));
            let sgn = if cw { 1.0 } else { -1.0 } * if side == Side::Left { 1.0 } else { -1.0 };
            Off::Circle(c, (rr + sgn * r).max(0.0))
        }
        _ => {
            let t = s.tangent(false);
            Off::Line(add(s.a, mul(normal(t, side), r)), t)
        }
    }
}

/// Where the offset curves of `prev` and `next` cross, the solution nearest `near`.
fn intersect(prev: &Seg, next: &Seg, side: Side, r: f64, cancel: bool, near: P2) -> Option<P2> {
    let a = offset_curve(prev, side, r, false);
    let b = offset_curve(next, side, r, cancel);
    let cands: Vec<P2> = match (&a, &b) {
        (Off::Line(p, d), Off::Line(q, e)) => line_line(*p, *d, *q, *e).into_iter().collect(),
        (Off::Line(p, d), Off::Circle(c, rr)) | (Off::Circle(c, rr), Off::Line(p, d)) => line_circle(*p, *d, *c, *rr),
        (Off::Circle(c1, r1), Off::Circle(c2, r2)) => circle_circle(*c1, *r1, *c2, *r2),
    };
    cands.into_iter().min_by(|x, y| norm(sub(*x, near)).total_cmp(&norm(sub(*y, near))))
}

fn line_circle(p: P2, d: P2, c: P2, r: f64) -> Vec<P2> {
    let d = unit(d);
    let f = sub(p, c);
    let b = dot(f, d);
    let disc = b * b - (dot(f, f) - r * r);
    if disc < -1e-9 {
        return vec![];
    }
    let s = disc.max(0.0).sqrt();
    vec![add(p, mul(d, -b - s)), add(p, mul(d, -b + s))]
}

fn circle_circle(c1: P2, r1: f64, c2: P2, r2: f64) -> Vec<P2> {
    let d = norm(sub(c2, c1));
    if d < 1e-12 || d > r1 + r2 + 1e-9 || d < (r1 - r2).abs() - 1e-9 {
        return vec![];
    }
    let a = (r1 * r1 - r2 * r2 + d * d) / (2.0 * d);
    let h = (r1 * r1 - a * a).max(0.0).sqrt();
    let u = unit(sub(c2, c1));
    let m = add(c1, mul(u, a));
    vec![add(m, mul(left(u), h)), sub(m, mul(left(u), h))]
}

/// G90/G94 under G41/G42 (manual 004 is silent; done as a Fanuc 0i-TF does, whose offset
/// direction in these cycles follows from the cycle and the imaginary tip, not from
/// G41/G42): the two cutting lines, ② `b`→`c` and ③ `c`→`d`, are offset by the nose radius
/// `r` towards the inside of the cycle's figure A-B-C-D (the stock a pass removes; the
/// finished surface lies beyond them), and the imaginary tip of tip number `tip` runs on
/// them: machine point = nose centre + r·tip vector. ① and ④ keep their axis (`approach`,
/// `ret`: (Z, X) unit vectors) and their end at `a`: ① ends where its axis through `a` meets
/// ②'s line, ③ where ④'s axis through `a` meets ③'s line. When ③ has no length (C at A's X
/// for G90, A's Z for G94) ② runs on until its line meets ④'s axis. For tip 3 (and 1, 2, 4
/// set the way the cut faces) a straight cycle keeps its programmed path, the tip point
/// being where the nose touches lines along the axes; tapers move, and tips 5–8/0/9 move
/// ends by r.
///
/// Returns the new (B, C, D) — None when ② has no length — or an interference message when
/// a compensated cut runs against its programmed direction (the taper or step is too short
/// for the nose, §2.18.4).
#[allow(clippy::too_many_arguments)]
pub fn single_cycle_offset(a: Pos, b: Pos, c: Pos, d: Pos, approach: P2, ret: P2, r: f64, tip: u8) -> Result<Option<(Pos, Pos, Pos)>, String> {
    let (pa, pb, pc, pd) = (uv(a), uv(b), uv(c), uv(d));
    let inside = mul(add(add(pa, pb), add(pc, pd)), 0.25);
    let side = |p: P2, q: P2| -> Option<(P2, P2)> {
        let t = unit(sub(q, p));
        let n = left(t);
        let s = dot(n, sub(inside, p));
        if norm(sub(q, p)) < 1e-9 || s.abs() < 1e-12 {
            return None;
        }
        Some((t, mul(n, s.signum())))
    };
    let Some((t1, n1)) = side(pb, pc) else {
        return Ok(None);
    };
    let tv = mul(tip_vector(tip), r);
    // The machine line of ②: the nose-centre line moved by the tip vector.
    let m1 = add(add(pb, mul(n1, r)), tv);
    let backwards = || {
        format!("interference: with the nose radius {r:.3} mm compensated, a cut of this cycle would run backwards (the taper or the step is too short for the nose, §2.18.4)")
    };
    let Some(b2) = line_line(pa, approach, m1, t1) else {
        return Ok(None);
    };
    let (c2, d2) = match side(pc, pd) {
        Some((t2, n2)) => {
            let m2 = add(add(pc, mul(n2, r)), tv);
            let (Some(c2), Some(d2)) = (line_line(m1, t1, m2, t2), line_line(pa, ret, m2, t2)) else {
                return Ok(None);
            };
            if dot(sub(d2, c2), t2) <= 0.0 {
                return Err(backwards());
            }
            (c2, d2)
        }
        None => match line_line(pa, ret, m1, t1) {
            Some(e) => (e, e),
            None => return Ok(None),
        },
    };
    if dot(sub(c2, b2), t1) <= 0.0 {
        return Err(backwards());
    }
    Ok(Some((set_p(b, b2), set_p(c, c2), set_p(d, d2))))
}

/// The points after `a` up to `b` on the arc about `c` (clockwise when `cw`, in (Z, X)), at
/// most 5° apart.
fn arc_points(a: P2, b: P2, c: P2, cw: bool) -> Vec<P2> {
    let (ra, rb) = (norm(sub(a, c)), norm(sub(b, c)));
    let a0 = (a.1 - c.1).atan2(a.0 - c.0);
    let sweep = crate::canon::wrap_sweep((b.1 - c.1).atan2(b.0 - c.0) - a0, cw);
    let n = ((sweep.abs() / 5f64.to_radians()).ceil() as usize).clamp(1, 72);
    (1..=n)
        .map(|j| {
            let f = j as f64 / n as f64;
            let t = a0 + sweep * f;
            let r = ra + (rb - ra) * f;
            (c.0 + r * t.cos(), c.1 + r * t.sin())
        })
        .collect()
}

/// The least distance between two polylines.
fn polyline_gap(p: &[P2], q: &[P2]) -> f64 {
    let mut best = f64::INFINITY;
    for a in p.windows(2) {
        for b in q.windows(2) {
            best = best.min(seg_gap(a[0], a[1], b[0], b[1]));
        }
    }
    if p.len() == 1 || q.len() == 1 {
        for a in p {
            for b in q.windows(2) {
                best = best.min(point_seg(*a, b[0], b[1]));
            }
        }
    }
    best
}

fn point_seg(p: P2, a: P2, b: P2) -> f64 {
    let d = sub(b, a);
    let l2 = dot(d, d);
    let t = if l2 < 1e-24 { 0.0 } else { (dot(sub(p, a), d) / l2).clamp(0.0, 1.0) };
    norm(sub(p, add(a, mul(d, t))))
}

/// Distance between the segments a–b and c–d (0 when they cross).
fn seg_gap(a: P2, b: P2, c: P2, d: P2) -> f64 {
    let (d1, d2) = (cross(sub(b, a), sub(c, a)), cross(sub(b, a), sub(d, a)));
    let (d3, d4) = (cross(sub(d, c), sub(a, c)), cross(sub(d, c), sub(b, c)));
    if d1 * d2 < 0.0 && d3 * d4 < 0.0 {
        return 0.0;
    }
    point_seg(a, c, d).min(point_seg(b, c, d)).min(point_seg(c, a, b)).min(point_seg(d, a, b))
}
