//! G74 face grooving / deep-hole peck cycle (§2.16.5) and G75 OD/ID grooving (§2.16.6):
//! `G7x R(e);` then `G7x X(U) Z(W) P(Δi) Q(Δk) R(Δd) F;`. One implementation on
//! (peck axis, step axis): G74 pecks along Z and steps in X by Δi, G75 pecks along X by Δi
//! and steps in Z by Δk. Steps ①–⑦ are the manual's: ① first peck feed, ② rapid back by e,
//! ③ the following feeds (Δk + e, the last one to B_n), ④ rapid side retract Δd, ⑤ rapid
//! back to the start's peck coordinate, ⑥ rapid step to the next A_n, ⑦ rapid back to A.
//!
//! P(Δi) and Q(Δk) follow Fanuc's rule for addresses that take no decimal point: without one
//! they are in least input increments (0.001 mm, 0.0001 inch) whatever No.3401#0 says, so
//! the manual's G75 example `P6000 Q3000` runs as printed (6 mm / 3 mm). The manual's own
//! G74 example `P3 Q5` contradicts it (it means 3 mm / 5 mm); as printed it would peck 5 µm
//! and is refused (too many passes, PS0062): write `P3. Q5.` or `P3000 Q5000`. A value with
//! a decimal point is taken in mm (inch). R(e) is kept as No.5139. A zero peck (or step)
//! amount with a distance to cover in that axis is Fanuc PS0062.

use super::{CErr, G76_VALUE_ALARM, MAX_PASSES};
use crate::canon::{MoveKind, Pos, SrcPos};
use crate::interp::gcode::{Decoded, Val};
use crate::interp::Interpreter;
use std::sync::Arc;

impl Interpreter {
    pub(super) fn groove(&mut self, d: &Decoded, src: &SrcPos, radial: bool) -> Result<(), CErr> {
        let name = if radial { "G75" } else { "G74" };
        self.cycle_plane_check(d, name)?;
        let gc = Self::gcol(d);
        let second = ['X', 'U', 'Z', 'W', 'P', 'Q'].iter().any(|l| d.has(*l));
        if !second {
            if let Some(r) = d.get('R') {
                let v = self.len(r);
                if v < 0.0 {
                    return Err((G76_VALUE_ALARM, Some(r.col), format!("{name} R(e) cannot be negative")));
                }
                self.cyc.p5139 = v;
            }
            return Ok(());
        }
        let e = self.cyc.p5139;
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let unsigned = |l: char, len: &dyn Fn(Val) -> f64| -> Result<f64, CErr> {
            match d.get(l) {
                None => Ok(0.0),
                Some(v) if v.v < 0.0 => Err((G76_VALUE_ALARM, Some(v.col), format!("{name} {l} is unsigned"))),
                Some(v) => Ok(len(v)),
            }
        };
        let inc = |v| self.increment_len(v);
        let (di, dk, dd) = (unsigned('P', &inc)?, unsigned('Q', &inc)?, unsigned('R', &|v| self.len(v))?);
        let a = self.pos;
        let off = self.offset();
        let work = a.sub(off);
        let mut bf = work;
        if let Some(v) = d.get('X') {
            bf.x = self.len(v) * 0.5;
        } else if let Some(v) = d.get('U') {
            bf.x = work.x + self.len(v) * 0.5;
        }
        if let Some(v) = d.get('Z') {
            bf.z = self.len(v);
        } else if let Some(v) = d.get('W') {
            bf.z = work.z + self.len(v);
        }
        let bf = bf.add(off);
        // (peck, step) coordinates and amounts.
        let pq = |p: Pos| if radial { (p.x, p.z) } else { (p.z, p.x) };
        let at = |p: f64, q: f64| if radial { Pos { x: p, z: q, ..a } } else { Pos { z: p, x: q, ..a } };
        let (peck, step) = if radial { (di, dk) } else { (dk, di) };
        let ((ap, aq), (bp, bq)) = (pq(a), pq(bf));
        let (ptot, qtot) = ((bp - ap).abs(), (bq - aq).abs());
        let (sp, sq) = ((bp - ap).signum(), (bq - aq).signum());
        let axis = |peck_axis: bool| if radial == peck_axis { 'X' } else { 'Z' };
        if ptot > 1e-9 && peck <= 0.0 {
            return Err((
                G76_VALUE_ALARM,
                gc,
                format!("{name}: the peck amount along {} is zero (program {})", axis(true), if radial { 'P' } else { 'Q' }),
            ));
        }
        if qtot > 1e-9 && step <= 0.0 {
            return Err((
                G76_VALUE_ALARM,
                gc,
                format!("{name}: the step along {} is zero (program {})", axis(false), if radial { 'Q' } else { 'P' }),
            ));
        }
        let npeck = if ptot > 1e-9 { (ptot / peck).ceil() } else { 1.0 };
        let nstep = if qtot > 1e-9 { (qtot / step).ceil() + 1.0 } else { 1.0 };
        if npeck * nstep > MAX_PASSES as f64 * 10.0 {
            return Err((G76_VALUE_ALARM, gc, format!("{name}: {} pecks: increase P/Q", npeck * nstep)));
        }
        // ④'s side retract: +q when B_f is below A on the step axis, else −q.
        let side = if bq < aq { 1.0 } else { -1.0 };
        let tag: Arc<str> = Arc::from(name);
        let mut qn = aq;
        loop {
            let last = (qn - aq).abs() >= qtot - 1e-9;
            // ①–③ pecks from A_n to B_n.
            let mut depth = 0.0;
            let mut first = true;
            loop {
                let next = depth + peck;
                let st = if first { 1 } else { 3 };
                if next >= ptot - 1e-9 || peck <= 0.0 {
                    self.cpush(src, &tag, st, MoveKind::Feed { end: at(bp, qn), feed }, false);
                    break;
                }
                self.cpush(src, &tag, st, MoveKind::Feed { end: at(ap + sp * next, qn), feed }, false);
                let back = (next - e).max(0.0);
                self.cpush(src, &tag, 2, MoveKind::Rapid { end: at(ap + sp * back, qn) }, true);
                depth = next;
                first = false;
            }
            let qc = qn + side * dd;
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: at(bp, qc) }, true);
            self.cpush(src, &tag, 5, MoveKind::Rapid { end: at(ap, qc) }, true);
            if last {
                self.cpush(src, &tag, 7, MoveKind::Rapid { end: a }, true);
                break;
            }
            let next = qn + sq * step;
            qn = if (next - aq).abs() >= qtot - 1e-9 { bq } else { next };
            self.cpush(src, &tag, 6, MoveKind::Rapid { end: at(ap, qn) }, true);
        }
        Ok(())
    }
}
