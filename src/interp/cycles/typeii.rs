//! G71/G72 type II (manual 004 §2.16.1, "连续凹槽加工"): the ns block names both axes
//! (note 1: `W0` when Z does not move), and the contour need not be monotonic along the
//! infeed axis; up to [`MAX_POCKETS`] pockets. Written on (p, q) = (infeed axis, cutting
//! axis) like type I, so G72 is the same code with the axes swapped.
//!
//! The rough contour is the finishing contour shifted along the infeed axis only (note 2:
//! the other allowance, W for G71 / U for G72, is ignored). The ns move A→B' bounds the
//! stock on the start side ("the first cut need not be perpendicular", fig. 2.35). At each
//! level p = A + k·Δd (strictly above the deepest point) the material to cut is where the
//! contour lies deeper than p; these intervals of q nest from one level to the next. A chain
//! of intervals, one per level, is cut level by level; the first interval of a level under
//! an interval already continued starts a new chain, a pocket. Chains are cut in order:
//! the main one first, then each pocket in the cutting direction.
//!
//! Steps (the manual's figures 2.36–2.38 are not in the text; numbering as type I):
//! ① infeed to the level (G00/G01 as the ns block when it starts on the ns move, else G01),
//! ② cut along q, ③ 45° retreat by e (No.5148), ④ rapid at the retreat height to where
//! the next level starts (back to A's q while the levels start on the ns move, as type I).
//! A chain whose last level ends inside the part leaves straight out to A's level; the next
//! pocket is then approached at rapid to e above the level cut before it and at G01 for the
//! rest (note 3; all of it at G01 when that distance is not more than e). Then ⑤ the ns move
//! from A to B', ⑥ the contour B'→C', ⑦ rapid out to A's level + allowance + Δd, over to
//! above A, and to A (note 7).
//!
//! Notes 5/6 (arcs in a type II contour need a non-zero No.3410 radius tolerance, checked
//! regardless of the allowance): this interpreter never runs with a zero tolerance (No.3410
//! = 0 or absent means 0.01 mm), and the contour's arcs are checked against it when the
//! contour is run, so the note's alarm condition cannot arise.
//!
//! Alarms: 64 (Fanuc PS0064) the contour is not monotonic along the cutting axis (note 4) or
//! has more than 10 pockets; 62 no infeed / too many passes.

use super::stock::polyline;
use super::{CErr, G76_VALUE_ALARM, MAX_PASSES};
use crate::canon::{Feed, MoveKind, Pos, SrcPos};
use crate::interp::gcode::Decoded;
use crate::interp::Interpreter;
use std::sync::Arc;

/// "最多可以有 10 个凹槽".
pub const MAX_POCKETS: usize = 10;

const EPS: f64 = 1e-9;

/// One level of a chain: level p, interval q0→q1, and whether q0 lies on the ns move.
#[derive(Clone, Copy, Debug)]
struct Row {
    p: f64,
    q0: f64,
    q1: f64,
    on_ns: bool,
}

#[derive(Clone, Debug)]
struct Chain {
    /// Level cut just before the chain's first row (A's level for the first level).
    top: f64,
    rows: Vec<Row>,
}

/// Where the (p, q) polyline `pts` lies deeper than `lvl` (in direction `dir`): intervals
/// (q0, q1, q0 on the first segment) in order along the polyline.
fn intervals(pts: &[(f64, f64)], lvl: f64, dir: f64) -> Vec<(f64, f64, bool)> {
    let mut out = Vec::new();
    let mut open: Option<(f64, bool)> = None;
    let cross = |(p0, q0): (f64, f64), (p1, q1): (f64, f64)| {
        if (p1 - p0).abs() < 1e-12 {
            q0
        } else {
            q0 + (lvl - p0) / (p1 - p0) * (q1 - q0)
        }
    };
    for (i, w) in pts.windows(2).enumerate() {
        let (a, b) = (w[0], w[1]);
        let ina = (a.0 - lvl) * dir > EPS;
        let inb = (b.0 - lvl) * dir > EPS;
        if ina && open.is_none() {
            open = Some((a.1, i == 0));
        }
        if !ina && inb {
            open = Some((cross(a, b), i == 0));
        } else if ina && !inb {
            if let Some((q0, on)) = open.take() {
                out.push((q0, cross(a, b), on));
            }
        }
    }
    if let (Some((q0, on)), Some(last)) = (open, pts.last()) {
        out.push((q0, last.1, on));
    }
    out.retain(|(a, b, _)| (b - a).abs() > 1e-6);
    out
}

fn overlap(a: (f64, f64), b: (f64, f64)) -> bool {
    let (alo, ahi) = (a.0.min(a.1), a.0.max(a.1));
    let (blo, bhi) = (b.0.min(b.1), b.0.max(b.1));
    ahi.min(bhi) - alo.max(blo) > 1e-9
}

impl Interpreter {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn rough_type2(
        &mut self,
        d: &Decoded,
        src: &SrcPos,
        facing: bool,
        (dd, e): (f64, f64),
        (du, dw): (f64, f64),
        feed: Feed,
        (l1, l2, ns, nf): (crate::interp::Loc, crate::interp::Loc, u32, u32),
    ) -> Result<(), CErr> {
        let name = if facing { "G72" } else { "G71" };
        let gc = Self::gcol(d);
        let a = self.pos;
        let (moves, ns_rapid) = self.shifted_contour(l1, l2, ns, nf, name, gc)?;
        // Note 2: the allowance along the infeed axis only.
        let off = if facing { Pos { z: dw, ..Pos::ZERO } } else { Pos { x: du, ..Pos::ZERO } };
        let allow = if facing { dw } else { du }.abs();
        let elems = Self::offset_elems(&moves, a, off, feed);
        let pq = |p: Pos| if facing { (p.z, p.x) } else { (p.x, p.z) };
        let at = |p: f64, q: f64| if facing { Pos { z: p, x: q, ..a } } else { Pos { x: p, z: q, ..a } };
        let bp = elems[0].kind.end().unwrap_or(a);
        let (ap, aq) = pq(a);
        let contour = &elems[1..];
        let mut pts: Vec<(f64, f64)> = vec![(ap, aq)];
        pts.extend(polyline(bp, contour).into_iter().map(pq));
        let (cpp, cpq) = *pts.last().unwrap_or(&(ap, aq));
        let _ = cpp;
        // Infeed direction: towards the deepest point of the contour.
        let far = pts.iter().map(|p| p.0).fold(ap, |m, p| if (p - ap).abs() > (m - ap).abs() { p } else { m });
        if (far - ap).abs() < EPS {
            return Err((
                G76_VALUE_ALARM,
                gc,
                format!("{name} type II: the contour N{ns}–N{nf} never leaves the start level, so there is nothing to rough"),
            ));
        }
        let dir = (far - ap).signum();
        let qdir = (cpq - aq).signum();
        let axis_q = if facing { 'X' } else { 'Z' };
        if qdir == 0.0 {
            return Err((64, gc, format!("{name} type II: the contour must move along {axis_q} (note 4)")));
        }
        for w in pts.windows(2) {
            if (w[1].1 - w[0].1) * qdir < -1e-6 {
                let p = at(w[1].0, w[1].1);
                return Err((
                    64,
                    gc,
                    format!(
                        "{name} type II: the contour N{ns}–N{nf} must be monotonic in {axis_q} (note 4); it turns back near X{:.3} Z{:.3}",
                        p.x * 2.0,
                        p.z
                    ),
                ));
            }
        }
        let depth_max = (far - ap) * dir;
        if depth_max / dd > MAX_PASSES as f64 {
            return Err((G76_VALUE_ALARM, gc, format!("{name} would cut more than {MAX_PASSES} passes: increase Δd")));
        }
        // Levels and chains.
        let mut chains: Vec<Chain> = Vec::new();
        let mut prev: Vec<((f64, f64), usize)> = Vec::new();
        let mut k = 1usize;
        while (k as f64) * dd < depth_max - EPS {
            let p = ap + dir * k as f64 * dd;
            let top = ap + dir * (k - 1) as f64 * dd;
            let mut used: Vec<usize> = Vec::new();
            let mut now = Vec::new();
            for (q0, q1, on_ns) in intervals(&pts, p, dir) {
                let row = Row { p, q0, q1, on_ns };
                let parent = prev.iter().find(|(iv, _)| overlap(*iv, (q0, q1))).map(|x| x.1);
                let ci = match parent {
                    Some(ci) if !used.contains(&ci) => {
                        chains[ci].rows.push(row);
                        ci
                    }
                    _ => {
                        chains.push(Chain { top, rows: vec![row] });
                        chains.len() - 1
                    }
                };
                used.push(ci);
                now.push(((q0, q1), ci));
            }
            prev = now;
            k += 1;
        }
        // Pockets: every chain after the first, and the first one's dip if it goes into one.
        let pockets = chains.len().saturating_sub(1) + chains.first().map_or(0, |c| c.rows.iter().any(|r| !r.on_ns) as usize);
        if pockets > MAX_POCKETS {
            return Err((64, gc, format!("{name} type II: the contour has {pockets} pockets, at most {MAX_POCKETS} are allowed")));
        }
        let tag: Arc<str> = Arc::from(name);
        for (ci, ch) in chains.iter().enumerate() {
            if ci > 0 {
                // Note 3: rapid over the pocket, to e above the level cut before it, G01 on.
                let r0 = ch.rows[0];
                let (cur_p, _) = pq(self.pos);
                if (cur_p - ap).abs() > EPS {
                    let (_, cq) = pq(self.pos);
                    self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(ap, cq) }, true);
                }
                self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(ap, r0.q0) }, true);
                let near = ch.top - dir * e;
                if (near - ap) * dir > EPS {
                    self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(near, r0.q0) }, true);
                }
            }
            for (i, r) in ch.rows.iter().enumerate() {
                let lvl = at(r.p, r.q0);
                let infeed = if r.on_ns && ns_rapid { MoveKind::Rapid { end: lvl } } else { MoveKind::Feed { end: lvl, feed } };
                self.cpush(src, &tag, 1, infeed, false);
                self.cpush(src, &tag, 2, MoveKind::Feed { end: at(r.p, r.q1), feed }, false);
                self.cpush(src, &tag, 3, MoveKind::Feed { end: at(r.p - dir * e, r.q1 - qdir * e), feed }, false);
                let back = r.p - dir * e;
                match ch.rows.get(i + 1) {
                    Some(nx) if nx.on_ns => self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(back, aq) }, true),
                    Some(nx) => self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(back, nx.q0) }, true),
                    None if r.on_ns => self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(back, aq) }, true),
                    None => {
                        // Out of the part straight along the infeed axis: the levels above
                        // are cut wider, so the way out is clear.
                        let (_, cq) = pq(self.pos);
                        self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(ap, cq) }, true);
                    }
                }
            }
        }
        // ⑤ from A along the ns move to B', ⑥ the contour.
        let (cur_p, cq) = pq(self.pos);
        if (cur_p - ap).abs() > EPS {
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(ap, cq) }, true);
        }
        self.cpush(src, &tag, 4, MoveKind::Rapid { end: a }, true);
        let infeed = if ns_rapid { MoveKind::Rapid { end: bp } } else { MoveKind::Feed { end: bp, feed } };
        self.cpush(src, &tag, 5, infeed, false);
        for el in contour {
            self.cpush(src, &tag, 6, el.kind.clone(), false);
        }
        // ⑦ note 7.
        let safe = ap - dir * (allow + dd);
        let (_, cq) = pq(self.pos);
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: at(safe, cq) }, true);
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: at(safe, aq) }, true);
        self.cpush(src, &tag, 7, MoveKind::Rapid { end: a }, true);
        self.skip_contour(l1, l2);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn intervals_split_at_a_peak() {
        // p = radius, going down (dir −1); q = Z going −.
        let pts = [(30.0, 2.0), (25.0, 0.0), (25.0, -10.0), (15.0, -15.0), (15.0, -20.0), (25.0, -25.0), (25.0, -30.0)];
        let iv = intervals(&pts, 27.0, -1.0);
        assert_eq!(iv.len(), 1);
        assert!((iv[0].0 - 0.8).abs() < 1e-9 && iv[0].1 == -30.0 && iv[0].2);
        let iv = intervals(&pts, 20.0, -1.0);
        assert_eq!(iv.len(), 1);
        assert!((iv[0].0 + 12.5).abs() < 1e-9 && (iv[0].1 + 22.5).abs() < 1e-9 && !iv[0].2, "{iv:?}");
        assert!(intervals(&pts, 15.0, -1.0).is_empty());
    }
}
