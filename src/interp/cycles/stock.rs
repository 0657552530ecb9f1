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
//! contour B'→C', ⑦ return to A. A program whose contour follows the G71 block directly
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
use crate::canon::{Move, MoveKind, Pos, SrcPos};
use crate::interp::gcode::{self, Decoded};
use crate::interp::{parse, Interpreter};
use std::sync::Arc;

/// One contour element in machine coordinates.
#[derive(Clone, Debug)]
struct Elem {
    kind: MoveKind,
    /// The element's start and end.
    a: Pos,
}

impl Interpreter {
    /// Lines (indices) of N`ns` and N`nf` in the current program.
    fn contour_span(&self, d: &Decoded, name: &str) -> Result<(usize, usize, u32, u32), CErr> {
        let gc = Self::gcol(d);
        let p = d.get('P').ok_or((61, gc, format!("{name}: P(ns), the first block of the finishing contour, is missing")))?;
        let q = d.get('Q').ok_or((61, gc, format!("{name}: Q(nf), the last block of the finishing contour, is missing")))?;
        let (ns, nf) = (p.v.round() as u32, q.v.round() as u32);
        let find = |n: u32, col| {
            self.labels
                .get(&(self.prog, n))
                .copied()
                .ok_or((63, Some(col), format!("{name}: there is no block N{n} in this program")))
        };
        let (l1, l2) = (find(ns, p.col)?, find(nf, q.col)?);
        if l2 < l1 {
            return Err((63, Some(q.col), format!("{name}: N{nf} comes before N{ns}; P must name the first block, Q the last")));
        }
        Ok((l1, l2, ns, nf))
    }

    /// Run the contour blocks l1..=l2 (`dry`: on a copy of the state, returning the motion
    /// moves; otherwise for real, G70). The first NC block must be G00/G01 (§2.16.7 note 2);
    /// note 3's codes are refused.
    fn run_contour(&mut self, l1: usize, l2: usize, ns: u32, name: &str, dry: bool) -> Result<(Vec<Move>, bool), CErr> {
        let saved = (self.pos, self.st.clone(), self.cyc.clone(), self.ended, self.queue.len());
        let file = self.cur_file();
        let mut first = true;
        let mut first_rapid = false;
        let mut result: Result<(), CErr> = Ok(());
        for i in l1..=l2 {
            let text = self.line_text(i).to_string();
            let at = |m: String| format!("{name}, contour line {} ({}): {m}", i + 1, text.trim());
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
            let src = SrcPos::new(file.clone(), i as u32 + 1, b.col);
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

    /// G71, both blocks.
    pub(super) fn g71(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G71")?;
        let gc = Self::gcol(d);
        if !(d.has('P') || d.has('Q')) {
            // First block: U(Δd) R(e) → No.5147 / No.5148.
            if let Some(u) = d.get('U') {
                let v = self.len(u);
                if v <= 0.0 {
                    return Err((G76_VALUE_ALARM, Some(u.col), "G71 U(Δd), the depth of cut, must be positive".into()));
                }
                self.cyc.p5147 = v;
            }
            if let Some(r) = d.get('R') {
                let v = self.len(r);
                if v < 0.0 {
                    return Err((G76_VALUE_ALARM, Some(r.col), "G71 R(e), the retract amount, cannot be negative".into()));
                }
                self.cyc.p5148 = v;
            }
            return Ok(());
        }
        let (dd, e) = (self.cyc.p5147, self.cyc.p5148);
        if dd <= 0.0 {
            return Err((G76_VALUE_ALARM, gc, "G71: the depth of cut Δd is not set: program G71 U(Δd) R(e) first (or No.5147)".into()));
        }
        let du = d.get('U').map(|v| self.len(v) * 0.5).unwrap_or(0.0);
        let dw = d.get('W').map(|v| self.len(v)).unwrap_or(0.0);
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let (l1, l2, ns, nf) = self.contour_span(d, "G71")?;
        // Is the ns block X-only (type I)?
        let ns_text = self.line_text(l1).to_string();
        if let Ok(parse::Block { stmt: parse::Stmt::Nc(w), .. }) = parse::parse_line(&ns_text) {
            if w.iter().any(|w| !w.comma && matches!(w.letter, 'Z' | 'W')) {
                return Err((10, gc, "G71 type II (the N(ns) block moves Z too) is not supported yet".into()));
            }
        }
        let a = self.pos;
        let (moves, ns_rapid) = self.run_contour(l1, l2, ns, "G71", true)?;
        if moves.is_empty() {
            return Err((65, gc, format!("G71: N{ns}–N{nf} make no move")));
        }
        let off = Pos { x: du, z: dw, ..Pos::ZERO };
        let mut elems = Vec::new();
        let mut start = a;
        for m in &moves {
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
        // B' = end of the ns move; the rough contour is elems[1..].
        let bp = elems[0].kind.end().unwrap_or(a);
        let dir = (bp.x - a.x).signum();
        if bp.x == a.x {
            return Err((G76_VALUE_ALARM, gc, format!("G71: N{ns} does not move X, so the infeed direction is unknown")));
        }
        let contour = &elems[1..];
        let pts = polyline(bp, contour);
        let cp = *pts.last().unwrap_or(&bp);
        let zdir = (cp.z - bp.z).signum();
        for w in pts.windows(2) {
            let (dx, dz) = (w[1].x - w[0].x, w[1].z - w[0].z);
            if dx * dir > 1e-6 || dz * zdir < -1e-6 {
                return Err((
                    64,
                    gc,
                    format!("G71 type I: the contour N{ns}–N{nf} must be monotonic in X and Z (it turns back near X{:.3} Z{:.3})", w[1].x * 2.0, w[1].z),
                ));
            }
        }
        let tag: Arc<str> = Arc::from("G71");
        let depth_total = (bp.x - a.x) * dir;
        let mut k = 1usize;
        loop {
            let depth = k as f64 * dd;
            if depth >= depth_total - 1e-9 {
                break;
            }
            if k > super::MAX_PASSES {
                return Err((G76_VALUE_ALARM, gc, format!("G71 would cut more than {} passes: increase U(Δd)", super::MAX_PASSES)));
            }
            let x = a.x + dir * depth;
            let lvl = Pos { x, ..a };
            let infeed = if ns_rapid { MoveKind::Rapid { end: lvl } } else { MoveKind::Feed { end: lvl, feed } };
            self.cpush(src, &tag, 1, infeed, false);
            let z = level_z(&pts, x).unwrap_or(cp.z);
            self.cpush(src, &tag, 2, MoveKind::Feed { end: Pos { z, ..lvl }, feed }, false);
            let back = Pos { x: x - dir * e, z: z - zdir * e, ..lvl };
            self.cpush(src, &tag, 3, MoveKind::Feed { end: back, feed }, false);
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: Pos { z: a.z, ..back } }, true);
            k += 1;
        }
        let infeed = if ns_rapid { MoveKind::Rapid { end: bp } } else { MoveKind::Feed { end: bp, feed } };
        self.cpush(src, &tag, 5, infeed, false);
        for el in contour {
            self.cpush(src, &tag, 6, el.kind.clone(), false);
        }
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: a }, true);
        // The contour is run only by G70: continue after N(nf) when it follows directly.
        if l1 == self.line {
            self.line = l2 + 1;
        }
        Ok(())
    }
}

/// The rough contour as points from `start`, arcs cut into chords of at most 2° (used for
/// the monotonic check and the pass ends; the contour pass itself keeps the true arcs).
fn polyline(start: Pos, elems: &[Elem]) -> Vec<Pos> {
    let mut pts = vec![start];
    for el in elems {
        match &el.kind {
            MoveKind::Arc { end, center, cw, .. } => {
                let a0 = (el.a.x - center.x).atan2(el.a.z - center.z);
                let a1 = (end.x - center.x).atan2(end.z - center.z);
                let r = (el.a.x - center.x).hypot(el.a.z - center.z);
                // In (z, x) a G03 is counter-clockwise (canon: G18 plane, u = Z, v = X).
                let mut sweep = a1 - a0;
                let tau = std::f64::consts::TAU;
                if *cw {
                    while sweep > 1e-12 {
                        sweep -= tau;
                    }
                } else {
                    while sweep < -1e-12 {
                        sweep += tau;
                    }
                }
                let n = ((sweep.abs() / 2f64.to_radians()).ceil() as usize).max(1);
                for j in 1..n {
                    let t = a0 + sweep * j as f64 / n as f64;
                    pts.push(Pos { x: center.x + r * t.sin(), z: center.z + r * t.cos(), ..*end });
                }
                pts.push(*end);
            }
            k => pts.push(k.end().unwrap_or(start)),
        }
    }
    pts
}

/// Z where the polyline first reaches X = `x` (from its start), if it does.
fn level_z(pts: &[Pos], x: f64) -> Option<f64> {
    for w in pts.windows(2) {
        let (p, q) = (w[0], w[1]);
        let (lo, hi) = if p.x <= q.x { (p.x, q.x) } else { (q.x, p.x) };
        if x >= lo - 1e-9 && x <= hi + 1e-9 {
            if (q.x - p.x).abs() < 1e-12 {
                return Some(p.z);
            }
            return Some(p.z + (x - p.x) / (q.x - p.x) * (q.z - p.z));
        }
    }
    None
}
