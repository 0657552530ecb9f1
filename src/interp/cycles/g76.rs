//! G76 multiple thread cutting cycle (§2.17.4), two blocks:
//! `G76 P(m)(r)(a) Q(Δdmin) R(d);` then `G76 X(U) Z(W) R(i) P(k) Q(Δd) F;`.
//!
//! Points (figure 2.58): A start, D = X/Z thread end, C = (D's X + i, A's Z) thread start,
//! B = C moved outwards by k (depth 0). Pass n infeeds to B_n at depth d_n from B, shifted
//! along Z by d_n·tan(a/2) in the A→D direction (single-flank infeed), cuts parallel to C→D
//! to D's Z (with the r run-out), retracts X to A's X (E) and returns Z to A.
//!
//! Depths: d_1 = Δd; d_n = max(√n·Δd, d_{n−1} + Δdmin). The manual writes the clamp as
//! √(n−1)·Δd + Δdmin, which is the same while no earlier pass was clamped; we add Δdmin to
//! the depth actually cut, as Fanuc does, so that no pass cuts less than Δdmin (the stated
//! purpose of Δdmin). When d_n ≥ k − d the pass is cut at k − d and is the last rough pass;
//! note 6: Δd > k gives one rough pass at k − d. Then m finishing passes at depth k.
//!
//! Tags: first rough pass ①②③④; later rough passes ⑤②③④; the last rough pass (from the
//! second on) ⑤⑥⑦⑧; every finishing pass ⑨ (⑩ is the manual's repeat decision, not a move).

use super::{thread_path, CErr, G76_VALUE_ALARM, MAX_PASSES, RANGE_ALARM};
use crate::canon::{MoveKind, Pos, SrcPos};
use crate::interp::gcode::Decoded;
use crate::interp::Interpreter;
use std::sync::Arc;

impl Interpreter {
    pub(super) fn g76(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G76")?;
        let second = ['X', 'U', 'Z', 'W'].iter().any(|l| d.has(*l));
        if !second {
            return self.g76_first(d);
        }
        let gc = Self::gcol(d);
        let bad = |col: Option<u32>, m: String| (G76_VALUE_ALARM, col.or(gc), m);
        let k = d.get('P').ok_or_else(|| bad(None, "G76: P(k), the thread height, is missing".into()))?;
        let dd = d.get('Q').ok_or_else(|| bad(None, "G76: Q(Δd), the first depth of cut, is missing".into()))?;
        let (kc, ddc) = (Some(k.col), Some(dd.col));
        let (k, dd) = (self.len(k), self.len(dd));
        if k <= 0.0 {
            return Err(bad(kc, format!("G76: P(k) = {k} — the thread height must be positive")));
        }
        if dd <= 0.0 {
            return Err(bad(ddc, format!("G76: Q(Δd) = {dd} — the first depth of cut must be positive")));
        }
        let (dmin, fin, m, r, a_deg) = (self.cyc.p5140, self.cyc.p5141, self.cyc.p5142, self.cyc.p5130, self.cyc.p5143);
        // Note 7.
        if dmin > k {
            return Err(bad(kc, format!("G76: the minimum depth of cut Δdmin {dmin} is larger than the thread height {k}")));
        }
        if fin > k {
            return Err(bad(kc, format!("G76: the finishing allowance d {fin} is larger than the thread height {k}")));
        }
        let lead = self.thread_lead(d)?;
        let a = self.pos;
        let off = self.offset();
        let work = a.sub(off);
        let mut dpt = work;
        if let Some(v) = d.get('X') {
            dpt.x = self.len(v) * 0.5;
        } else if let Some(v) = d.get('U') {
            dpt.x = work.x + self.len(v) * 0.5;
        }
        if let Some(v) = d.get('Z') {
            dpt.z = self.len(v);
        } else if let Some(v) = d.get('W') {
            dpt.z = work.z + self.len(v);
        }
        let dpt = dpt.add(off);
        let i = d.get('R').map(|v| self.len(v)).unwrap_or(0.0);
        if (dpt.z - a.z).abs() < 1e-9 {
            return Err(bad(None, "G76 cannot cut face threads: Z(W) must differ from the start point".into()));
        }
        // Inwards = towards D's X from A (U's sign); B is outwards of C by k.
        let inward = (dpt.x - a.x).signum();
        if dpt.x == a.x {
            return Err(bad(None, "G76: X(U) must differ from the start point (it gives the infeed direction)".into()));
        }
        let c = Pos { x: dpt.x + i, ..a };
        let b = Pos { x: c.x - inward * k, ..a };
        let slope = (dpt.x - c.x) / (dpt.z - c.z);
        let zdir = (dpt.z - a.z).signum();
        let tan = (a_deg as f64 / 2.0).to_radians().tan();
        let runout = r as f64 * 0.1 * lead;

        // Rough depths.
        let rough_total = k - fin;
        let mut depths = Vec::new();
        if rough_total > 1e-12 {
            let mut prev = 0.0;
            let mut n = 1usize;
            loop {
                let mut dn = if n == 1 { dd } else { (n as f64).sqrt() * dd };
                if n > 1 {
                    dn = dn.max(prev + dmin);
                }
                if dn >= rough_total - 1e-12 {
                    depths.push(rough_total);
                    break;
                }
                depths.push(dn);
                prev = dn;
                n += 1;
                if depths.len() + m as usize > MAX_PASSES {
                    return Err(bad(ddc, format!("G76 would cut more than {MAX_PASSES} passes: increase Q(Δd) or Δdmin")));
                }
            }
        }
        let tag: Arc<str> = Arc::from("G76");
        let nr = depths.len();
        let mut passes: Vec<(f64, [u8; 4])> = depths
            .iter()
            .enumerate()
            .map(|(j, &dn)| {
                let steps = match (j, j + 1 == nr) {
                    (0, _) => [1, 2, 3, 4],
                    (_, false) => [5, 2, 3, 4],
                    (_, true) => [5, 6, 7, 8],
                };
                (dn, steps)
            })
            .collect();
        passes.extend((0..m).map(|_| (k, [9, 9, 9, 9])));
        // Check every pass's run-out before emitting anything.
        let mut paths = Vec::with_capacity(passes.len());
        for &(dn, _) in &passes {
            let bn = Pos { x: b.x + inward * dn, z: a.z + zdir * dn * tan, ..a };
            let end = Pos { x: bn.x + slope * (dpt.z - bn.z), z: dpt.z, ..a };
            let segs = thread_path(bn, end, lead, runout, self.cyc.p5131, a)
                .map_err(|m| (RANGE_ALARM, gc, format!("G76: {m}")))?;
            paths.push((bn, segs));
        }
        for ((_, st), (bn, segs)) in passes.iter().zip(paths) {
            self.cpush(src, &tag, st[0], MoveKind::Rapid { end: bn }, true);
            self.push_threads(src, &tag, st[1], &segs, 0.0);
            let e = Pos { x: a.x, ..self.pos };
            self.cpush(src, &tag, st[2], MoveKind::Rapid { end: e }, true);
            self.cpush(src, &tag, st[3], MoveKind::Rapid { end: a }, true);
        }
        Ok(())
    }

    /// First G76 block: packed P(m)(r)(a) (note 4: last two digits a, the two before r, the
    /// rest m), Q(Δdmin), R(d); each given value replaces its parameter (kept in the
    /// interpreter's state).
    fn g76_first(&mut self, d: &Decoded) -> Result<(), CErr> {
        let bad = |col: u32, m: String| (G76_VALUE_ALARM, Some(col), m);
        let mut new = self.cyc.clone();
        if let Some(p) = d.get('P') {
            if p.bad_integer() {
                return Err((7, Some(p.col), "G76 P(m)(r)(a) is a packed integer (e.g. P020560): no decimal point".into()));
            }
            if p.v < 0.0 {
                return Err(bad(p.col, "G76 P(m)(r)(a) cannot be negative".into()));
            }
            let v = p.v.round() as u64;
            let (m, r, a) = (v / 10000, (v / 100) % 100, v % 100);
            if !(1..=99).contains(&m) {
                return Err(bad(p.col, format!("G76 P: finishing passes m = {m}, must be 01–99")));
            }
            new.p5142 = m as u32;
            new.p5130 = r as u32;
            new.p5143 = a as u32;
        }
        if let Some(q) = d.get('Q') {
            let v = self.len(q);
            if v < 0.0 {
                return Err(bad(q.col, "G76 Q(Δdmin) cannot be negative".into()));
            }
            new.p5140 = v;
        }
        if let Some(r) = d.get('R') {
            let v = self.len(r);
            if v < 0.0 {
                return Err(bad(r.col, "G76 R(d) cannot be negative".into()));
            }
            new.p5141 = v;
        }
        self.cyc = new;
        Ok(())
    }
}
