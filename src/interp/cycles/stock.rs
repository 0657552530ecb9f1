//! G71 stock removal in turning (§2.16.1, type I) and G70 finishing (§2.16.4), on the
//! finishing contour N(ns)…N(nf) of the current program.
//!
//! The contour is obtained by running its blocks through the interpreter itself on a copy of
//! the modal state (so absolute/incremental words, arcs by R or I/K, `,C`/`,R` corners and
//! modal G00–G03 mean exactly what they mean when G70 runs them), then restoring the state:
//! in G71 the contour's M/S/T/F have no effect (§2.16.1 "M、S、T、F").
//!
//! G71 type I (the ns block moves X only): the rough contour is the finishing contour moved
//! by (Δu/2, Δw). From A, each pass infeeds by Δd (G00 or G01 as the ns block), cuts along Z
//! to the rough contour (or to C' beyond its end), retreats 45° by e, and returns Z to A at
//! rapid; the last pass follows the rough contour B'→C' at feed, then the tool returns to A
//! at rapid. The manual's figure 2.30 carries the step numbers but not its text, so the
//! steps are ours: ① infeed, ② cut, ③ 45° retreat, ④ Z return, ⑤ infeed to B', ⑥ the
//! contour B'→C', ⑦ return to A (X first, then Z; G72 the other way round). A program whose contour follows the G71 block directly
//! continues after N(nf) (the contour is only run by G70), as on a Fanuc 0i-TF.
//!
//! U(Δd) and R(e) of the first block are written back to No.5147/No.5148: the values are
//! kept in the interpreter's cycle state (initialised from the configuration) and used by
//! later G71 blocks that omit them.
//!
//! Alarms (Fanuc PS numbers): 61 P or Q missing, 62 Δd not positive / no infeed, 63 N(ns) or
//! N(nf) not found, 64 the contour is not monotonic (type I in X and Z), 65 the ns block is
//! not G00/G01, 66 a code note 3 forbids in the contour.

use super::{CErr, G76_VALUE_ALARM};
use crate::canon::{Feed, Move, MoveKind, Pos, SrcPos};
use crate::interp::gcode::{self, Decoded};
use crate::interp::{parse, Interpreter, Loc};
use std::sync::Arc;

/// One contour element in machine coordinates.
#[derive(Clone, Debug)]
pub(super) struct Elem {
    pub(super) kind: MoveKind,
    /// The element's start.
    pub(super) a: Pos,
}

impl Interpreter {
    /// Lines of N`ns` and N`nf` in the current program.
    pub(super) fn contour_span(&self, d: &Decoded, name: &str) -> Result<(Loc, Loc, u32, u32), CErr> {
        let gc = Self::gcol(d);
        let p = d.get('P').ok_or((61, gc, format!("{name}: P(ns), the first block of the finishing contour, is missing")))?;
        let q = d.get('Q').ok_or((61, gc, format!("{name}: Q(nf), the last block of the finishing contour, is missing")))?;
        let (ns, nf) = (p.v.round() as u32, q.v.round() as u32);
        let find =
            |n: u32, col| self.labels.get(&(self.prog, n)).copied().ok_or((63, Some(col), format!("{name}: there is no block N{n} in this program")));
        let (l1, l2) = (find(ns, p.col)?, find(nf, q.col)?);
        if l2 < l1 {
            return Err((63, Some(q.col), format!("{name}: N{nf} comes before N{ns}; P must name the first block, Q the last")));
        }
        Ok((l1, l2, ns, nf))
    }

    /// Run the contour blocks l1..=l2 (`dry`: on a copy of the state, returning the motion
    /// moves; otherwise for real, G70). The first NC block must be G00/G01 (§2.16.7 note 2);
    /// note 3's codes are refused.
    fn run_contour(&mut self, l1: Loc, l2: Loc, ns: u32, name: &str, dry: bool) -> Result<(Vec<Move>, bool), CErr> {
        let saved = (self.pos, self.st.clone(), self.cyc.clone(), self.ended, self.queue.len());
        // G41/G42 in the contour take effect when G70 runs it, not in a dry run.
        let saved_nrc = self.nrc.clone();
        let file = self.cur_file();
        let mut first = true;
        let mut first_rapid = false;
        let mut result: Result<(), CErr> = Ok(());
        let mut next = l1;
        while next <= l2 {
            let (text, after) = self.line_after(next);
            let i = std::mem::replace(&mut next, after);
            let at = |m: String| format!("{name}, contour line {} ({}): {m}", i.line + 1, text.trim());
            let b = match parse::parse_line(&text) {
                Ok(b) => b,
                Err(e) => {
                    result = Err((e.number, None, at(e.message)));
                    break;
                }
            };
            if b.skip && self.block_skip {
                continue;
            }
            let words = match b.stmt {
                parse::Stmt::Empty | parse::Stmt::Percent => continue,
                parse::Stmt::Nc(w) => w,
                _ => {
                    result = Err((66, None, at("macro statements cannot be part of a finishing contour".into())));
                    break;
                }
            };
            let d = match self.decode_words(&words, &self.vars) {
                Ok(d) => d,
                Err(a) => {
                    result = Err((a.number, None, at(a.message)));
                    break;
                }
            };
            let bad = d.g.iter().map(|g| g.0).find(|&g| {
                let grp = gcode::ginfo(g).map(|i| i.group).unwrap_or(0);
                (grp == 0 && g != 40) || (grp == 1 && !matches!(g, 0 | 10 | 20 | 30)) || g == 200 || g == 210
            });
            if let Some(g) = bad {
                result = Err((66, None, at(format!("{} is not allowed between P and Q (§2.16.7 note 3)", gcode::gname(g)))));
                break;
            }
            if let Some(m) = d.m.iter().find(|m| m.0 == 98 || m.0 == 99) {
                result = Err((66, None, at(format!("M{} is not allowed between P and Q (§2.16.7 note 3)", m.0))));
                break;
            }
            if first {
                first = false;
                match d.group(1) {
                    Some(0) => first_rapid = true,
                    Some(10) => {}
                    _ => {
                        result = Err((65, None, at(format!("the block N{ns} must command G00 or G01 (§2.16.7 note 2)"))));
                        break;
                    }
                }
            }
            let src = SrcPos::new(file.clone(), i.line + 1, b.col);
            if let Err((n, _, m)) = self.exec(&d, &src) {
                result = Err((n, None, at(m)));
                break;
            }
        }
        if result.is_ok() && self.corner.is_some() {
            result = Err((51, None, format!("{name}: the contour ends with ,C/,R: a G01/G02/G03 move must follow inside N(ns)–N(nf)")));
        }
        if dry || result.is_err() {
            let moves: Vec<Move> = self.queue.drain(saved.4..).collect();
            self.corner = None;
            self.held.clear();
            (self.pos, self.st, self.cyc, self.ended) = (saved.0, saved.1, saved.2, saved.3);
            self.nrc = saved_nrc;
            result?;
            return Ok((moves.into_iter().filter(|m| m.kind.end().is_some()).collect(), first_rapid));
        }
        Ok((Vec::new(), first_rapid))
    }

    /// G70 P(ns) Q(nf): run the contour blocks with their F/S/T/M, then rapid back to the
    /// start point. Contour moves are tagged G70 ①, the return ②.
    pub(super) fn g70(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G70")?;
        let (l1, l2, ns, _) = self.contour_span(d, "G70")?;
        let a = self.pos;
        let before = self.queue.len();
        self.run_contour(l1, l2, ns, "G70", false)?;
        let tag: Arc<str> = Arc::from("G70");
        for m in self.queue.range_mut(before..) {
            if m.kind.end().is_some() {
                m.tag = Some(crate::canon::CycleTag { cycle: tag.clone(), step: 1 });
            }
        }
        self.cpush(src, &tag, 2, MoveKind::Rapid { end: a }, true);
        Ok(())
    }

    /// First block of G71/G72: U(Δd) (G71) or W(Δd) (G72), R(e) → No.5147 / No.5148.
    fn rough_first(&mut self, d: &Decoded, name: &str, letter: char) -> Result<(), CErr> {
        if let Some(u) = d.get(letter) {
            let v = self.len(u);
            if v <= 0.0 {
                return Err((G76_VALUE_ALARM, Some(u.col), format!("{name} {letter}(Δd), the depth of cut, must be positive")));
            }
            self.cyc.p5147 = v;
        }
        if let Some(r) = d.get('R') {
            let v = self.len(r);
            if v < 0.0 {
                return Err((G76_VALUE_ALARM, Some(r.col), format!("{name} R(e), the retract amount, cannot be negative")));
            }
            self.cyc.p5148 = v;
        }
        Ok(())
    }

    /// The contour of a G71/G72/G73 second block shifted by `off`: (B', elements after the
    /// ns move, whether the ns move is G00, the ns move itself shifted).
    pub(super) fn shifted_contour(&mut self, l1: Loc, l2: Loc, ns: u32, nf: u32, name: &str, gc: Option<u32>) -> Result<(Vec<Move>, bool), CErr> {
        let (moves, ns_rapid) = self.run_contour(l1, l2, ns, name, true)?;
        if moves.is_empty() {
            return Err((65, gc, format!("{name}: N{ns}–N{nf} make no move")));
        }
        Ok((moves, ns_rapid))
    }

    /// The contour moves moved by `off`, as elements with their start points (from `a`).
    pub(super) fn offset_elems(moves: &[Move], a: Pos, off: Pos, feed: Feed) -> Vec<Elem> {
        let mut elems = Vec::new();
        let mut start = a;
        for m in moves {
            let end = m.kind.end().unwrap_or(start);
            let kind = match &m.kind {
                MoveKind::Arc { end, center, cw, plane, .. } => {
                    MoveKind::Arc { end: end.add(off), center: center.add(off), cw: *cw, plane: *plane, feed }
                }
                _ => MoveKind::Feed { end: end.add(off), feed },
            };
            elems.push(Elem { kind, a: start.add(off) });
            start = end;
        }
        elems
    }

    /// G71 (`facing` = false: passes parallel to Z, infeed in X) and G72 (`facing`: passes
    /// parallel to X, infeed in Z), both blocks. The algorithm is written on (p, q) = the
    /// infeed axis and the cutting axis.
    pub(super) fn rough(&mut self, d: &Decoded, src: &SrcPos, facing: bool) -> Result<(), CErr> {
        let name = if facing { "G72" } else { "G71" };
        self.cycle_plane_check(d, name)?;
        let gc = Self::gcol(d);
        if !(d.has('P') || d.has('Q')) {
            return self.rough_first(d, name, if facing { 'W' } else { 'U' });
        }
        let (dd, e) = (self.cyc.p5147, self.cyc.p5148);
        if dd <= 0.0 {
            return Err((G76_VALUE_ALARM, gc, format!("{name}: the depth of cut Δd is not set: program the first {name} block (or No.5147)")));
        }
        let du = d.get('U').map(|v| self.len(v) * 0.5).unwrap_or(0.0);
        let dw = d.get('W').map(|v| self.len(v)).unwrap_or(0.0);
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let (l1, l2, ns, nf) = self.contour_span(d, name)?;
        // Type I: the ns block moves the infeed axis only.
        let ns_text = self.line_text(l1);
        let other: [char; 2] = if facing { ['X', 'U'] } else { ['Z', 'W'] };
        if let Ok(parse::Block { stmt: parse::Stmt::Nc(w), .. }) = parse::parse_line(&ns_text) {
            if w.iter().any(|w| !w.comma && other.contains(&w.letter)) {
                // Type II: the ns block names both axes (note 1).
                return self.rough_type2(d, src, facing, (dd, e), (du, dw), feed, (l1, l2, ns, nf));
            }
        }
        let a = self.pos;
        let (moves, ns_rapid) = self.shifted_contour(l1, l2, ns, nf, name, gc)?;
        let elems = Self::offset_elems(&moves, a, Pos { x: du, z: dw, ..Pos::ZERO }, feed);
        let pq = |p: Pos| if facing { (p.z, p.x) } else { (p.x, p.z) };
        let at = |p: f64, q: f64| if facing { Pos { z: p, x: q, ..a } } else { Pos { x: p, z: q, ..a } };
        let bp = elems[0].kind.end().unwrap_or(a);
        let (ap, aq) = pq(a);
        let (bpp, _) = pq(bp);
        if bpp == ap {
            return Err((
                G76_VALUE_ALARM,
                gc,
                format!("{name}: N{ns} does not move {}, so the infeed direction is unknown", if facing { 'Z' } else { 'X' }),
            ));
        }
        let dir = (bpp - ap).signum();
        let contour = &elems[1..];
        let pts: Vec<(f64, f64)> = polyline(bp, contour).into_iter().map(pq).collect();
        let (cpp, cpq) = *pts.last().unwrap_or(&pq(bp));
        let _ = cpp;
        let qdir = (cpq - pts[0].1).signum();
        for w in pts.windows(2) {
            let (dp, dq) = (w[1].0 - w[0].0, w[1].1 - w[0].1);
            if dp * dir > 1e-6 || dq * qdir < -1e-6 {
                let p = at(w[1].0, w[1].1);
                return Err((
                    64,
                    gc,
                    format!("{name} type I: the contour N{ns}–N{nf} must be monotonic in X and Z (it turns back near X{:.3} Z{:.3})", p.x * 2.0, p.z),
                ));
            }
        }
        let tag: Arc<str> = Arc::from(name);
        let depth_total = (bpp - ap) * dir;
        // Checked before any move is queued, so that an alarm leaves no half cycle behind.
        if depth_total / dd > super::MAX_PASSES as f64 {
            return Err((G76_VALUE_ALARM, gc, format!("{name} would cut more than {} passes: increase Δd", super::MAX_PASSES)));
        }
        let mut k = 1usize;
        loop {
            let depth = k as f64 * dd;
            if depth >= depth_total - 1e-9 {
                break;
            }
            let p = ap + dir * depth;
            let lvl = at(p, aq);
            let infeed = if ns_rapid { MoveKind::Rapid { end: lvl } } else { MoveKind::Feed { end: lvl, feed } };
            self.cpush(src, &tag, 1, infeed, false);
            let q = level_q(&pts, p).unwrap_or(cpq);
            self.cpush(src, &tag, 2, MoveKind::Feed { end: at(p, q), feed }, false);
            let back = at(p - dir * e, q - qdir * e);
            self.cpush(src, &tag, 3, MoveKind::Feed { end: back, feed }, false);
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(p - dir * e, aq) }, true);
            k += 1;
        }
        let infeed = if ns_rapid { MoveKind::Rapid { end: bp } } else { MoveKind::Feed { end: bp, feed } };
        self.cpush(src, &tag, 5, infeed, false);
        for el in contour {
            self.cpush(src, &tag, 6, el.kind.clone(), false);
        }
        // ⑦ Back to A: the infeed axis first (straight out of the part, as G90's ③④), then
        // the cutting axis, rather than a diagonal through the rough contour.
        let (_, cq) = pq(self.pos);
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: at(ap, cq) }, true);
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: a }, true);
        self.skip_contour(l1, l2);
        Ok(())
    }

    /// The contour is run only by G70: continue after N(nf) when it follows directly.
    pub(super) fn skip_contour(&mut self, l1: Loc, l2: Loc) {
        if l1 == self.line {
            self.line = self.line_after(l2).1;
        }
    }

    /// G73 pattern repeating, both blocks: `U(Δi) W(Δk) R(d)` (No.5144–5146), then
    /// `P Q U(Δu) W(Δw) F`. Pass n of d follows the contour moved by
    /// (Δu/2 + Δi·(d−n)/(d−1), Δw + Δk·(d−n)/(d−1)) (radius), so the first pass is offset by
    /// (Δi + Δu/2, Δk + Δw) and the last by (Δu/2, Δw) (§2.16.3). Each pass: ① rapid from A to
    /// the shifted start A_n, ② the ns move (G00 or G01 as programmed), ③ the rest of the
    /// contour at the cycle's feed, ④ rapid back to A (figure 2.42's numbers are not in the
    /// text; these are ours). d = 1 cuts the last pass only.
    pub(super) fn g73(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G73")?;
        let gc = Self::gcol(d);
        if !(d.has('P') || d.has('Q')) {
            if let Some(u) = d.get('U') {
                self.cyc.p5144 = self.len(u);
            }
            if let Some(w) = d.get('W') {
                self.cyc.p5145 = self.len(w);
            }
            if let Some(r) = d.get('R') {
                if r.bad_integer() || !(1.0..=99999.0).contains(&r.v) {
                    return Err((G76_VALUE_ALARM, Some(r.col), format!("G73 R(d): the number of passes must be a whole number ≥ 1, not {}", r.v)));
                }
                self.cyc.p5146 = r.v as u32;
            }
            return Ok(());
        }
        let (di, dk, n) = (self.cyc.p5144, self.cyc.p5145, self.cyc.p5146);
        if n == 0 {
            return Err((G76_VALUE_ALARM, gc, "G73: the number of passes R(d) is not set: program G73 U W R first (or No.5146)".into()));
        }
        if n as usize > super::MAX_PASSES {
            return Err((G76_VALUE_ALARM, gc, format!("G73: more than {} passes", super::MAX_PASSES)));
        }
        let du = d.get('U').map(|v| self.len(v) * 0.5).unwrap_or(0.0);
        let dw = d.get('W').map(|v| self.len(v)).unwrap_or(0.0);
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let (l1, l2, ns, nf) = self.contour_span(d, "G73")?;
        let a = self.pos;
        let (moves, ns_rapid) = self.shifted_contour(l1, l2, ns, nf, "G73", gc)?;
        let tag: Arc<str> = Arc::from("G73");
        for j in 1..=n {
            let f = if n == 1 { 0.0 } else { (n - j) as f64 / (n - 1) as f64 };
            let off = Pos { x: du + di * f, z: dw + dk * f, ..Pos::ZERO };
            let elems = Self::offset_elems(&moves, a, off, feed);
            self.cpush(src, &tag, 1, MoveKind::Rapid { end: a.add(off) }, true);
            for (i, el) in elems.iter().enumerate() {
                let kind = match (&el.kind, i == 0 && ns_rapid) {
                    (k, true) => MoveKind::Rapid { end: k.end().unwrap_or(a) },
                    (k, false) => k.clone(),
                };
                self.cpush(src, &tag, if i == 0 { 2 } else { 3 }, kind, false);
            }
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: a }, true);
        }
        self.skip_contour(l1, l2);
        Ok(())
    }
}

/// The rough contour as points from `start`, arcs cut into chords of at most 2° (used for
/// the monotonic check and the pass ends; the contour pass itself keeps the true arcs).
pub(super) fn polyline(start: Pos, elems: &[Elem]) -> Vec<Pos> {
    let mut pts = vec![start];
    for el in elems {
        match &el.kind {
            MoveKind::Arc { end, center, cw, .. } => {
                pts.extend(crate::canon::zx_arc_chord_points(el.a, *end, *center, *cw));
                pts.push(*end);
            }
            k => pts.push(k.end().unwrap_or(start)),
        }
    }
    pts
}

/// The cutting-axis coordinate where the (p, q) polyline first reaches p = `lvl`.
fn level_q(pts: &[(f64, f64)], lvl: f64) -> Option<f64> {
    for w in pts.windows(2) {
        let ((p0, q0), (p1, q1)) = (w[0], w[1]);
        if lvl >= p0.min(p1) - 1e-9 && lvl <= p0.max(p1) + 1e-9 {
            if (p1 - p0).abs() < 1e-12 {
                return Some(q0);
            }
            return Some(q0 + (lvl - p0) / (p1 - p0) * (q1 - q0));
        }
    }
    None
}
