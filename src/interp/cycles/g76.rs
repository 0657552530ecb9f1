//! G76 multiple thread cutting cycle (§2.17.4), two blocks:
//! `G76 P(m)(r)(a) Q(Δdmin) R(d);` then `G76 X(U) Z(W) R(i) P(k) Q(Δd) F;`.
//!
//! Points (figure 2.58): A start, D = X/Z thread end, C = (D's X + i, A's Z) thread start,
//! B = C moved outwards by k (depth 0). Pass n infeeds to B_n at depth d_n from B, shifted
//! along Z by d_n·tan(a/2) in the A→D direction (single-flank infeed), cuts parallel to C→D
//! to D's Z (with the r run-out), retracts X to A's X (E) and returns Z to A.
//!
//! Depths (004 §2.17.4 step ⑤, to the letter): d_1 = Δd; d_n = max(√n·Δd, √(n−1)·Δd + Δdmin).
//! The clamp adds Δdmin to the *unclamped* previous depth √(n−1)·Δd, not to the depth actually
//! cut, so once the minimum applies a pass may cut less than Δdmin (0.4 → 0.65 → 0.8157 for
//! Δd 0.4, Δdmin 0.25). G78 (manual 002) is different: there the next depth is the previous
//! one plus Δdmin. When d_n ≥ k − d the pass is cut at k − d and is the last rough pass;
//! note 6: Δd > k gives one rough pass at k − d. Then m finishing passes at depth k.
//!
//! Tags: first rough pass ①②③④; later rough passes ⑤②③④; the last rough pass (from the
//! second on) ⑤⑥⑦⑧; every finishing pass ⑨ (⑩ is the manual's repeat decision, not a move).

use super::{thread_path_js, CErr, G76_VALUE_ALARM, MAX_PASSES, RANGE_ALARM};
use crate::canon::{MoveKind, Pos, SrcPos};
use crate::interp::gcode::Decoded;
use crate::interp::Interpreter;
use std::sync::Arc;

/// What differs between G76 and G78 in the second block.
struct Style {
    name: &'static str,
    /// G78 infeed mode P(r) 0–4; None = G76 (single flank towards D).
    g78_mode: Option<u32>,
    decreasing: bool,
    /// Run-out: long-axis length and short-axis amount (mm).
    runout: (f64, f64),
}

impl Interpreter {
    pub(super) fn g76(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G76")?;
        let second = ['X', 'U', 'Z', 'W'].iter().any(|l| d.has(*l));
        if !second {
            return self.g76_first(d);
        }
        let lead = self.thread_lead(d)?;
        let r = self.cyc.p5130 as f64 * 0.1 * lead;
        let a = self.cyc.p5131;
        let angle = if (1.0..=89.0).contains(&a) { a } else { 45.0 };
        let style = Style { name: "G76", g78_mode: None, decreasing: true, runout: (r, r * angle.to_radians().tan()) };
        self.multi_thread(d, src, lead, style)
    }

    /// The second block of G76/G78.
    fn multi_thread(&mut self, d: &Decoded, src: &SrcPos, lead: f64, style: Style) -> Result<(), CErr> {
        let name = style.name;
        let gc = Self::gcol(d);
        let bad = |col: Option<u32>, m: String| (G76_VALUE_ALARM, col.or(gc), m);
        let k = d.get('P').ok_or_else(|| bad(None, format!("{name}: P(k), the thread height, is missing")))?;
        let dd = d.get('Q').ok_or_else(|| bad(None, format!("{name}: Q(Δd), the first depth of cut, is missing")))?;
        let (kc, ddc) = (Some(k.col), Some(dd.col));
        let (k, dd) = (self.len(k), self.len(dd));
        if k <= 0.0 {
            return Err(bad(kc, format!("{name}: P(k) = {k} — the thread height must be positive")));
        }
        if dd <= 0.0 {
            return Err(bad(ddc, format!("{name}: Q(Δd) = {dd} — the first depth of cut must be positive")));
        }
        let (dmin, fin, m, a_deg) = (self.cyc.p5140, self.cyc.p5141, self.cyc.p5142, self.cyc.p5143);
        // Note 7.
        if dmin > k {
            return Err(bad(kc, format!("{name}: the minimum depth of cut Δdmin {dmin} is larger than the thread height {k}")));
        }
        if fin > k {
            return Err(bad(kc, format!("{name}: the finishing allowance d {fin} is larger than the thread height {k}")));
        }
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
            return Err(bad(None, format!("{name} cannot cut face threads: Z(W) must differ from the start point")));
        }
        // Inwards = towards D's X from A (U's sign); B is outwards of C by k.
        let inward = (dpt.x - a.x).signum();
        if dpt.x == a.x {
            return Err(bad(None, format!("{name}: X(U) must differ from the start point (it gives the infeed direction)")));
        }
        let c = Pos { x: dpt.x + i, ..a };
        let b = Pos { x: c.x - inward * k, ..a };
        let slope = (dpt.x - c.x) / (dpt.z - c.z);
        let zdir = (dpt.z - a.z).signum();
        let tan = (a_deg as f64 / 2.0).to_radians().tan();
        let (runout, short) = style.runout;

        // Rough depths.
        let rough_total = k - fin;
        let mut depths = Vec::new();
        if rough_total > 1e-12 {
            let mut prev = 0.0;
            let mut n = 1usize;
            loop {
                let mut dn = if style.decreasing { (n as f64).sqrt() * dd } else { n as f64 * dd };
                if n > 1 {
                    // G76: √(n−1)·Δd + Δdmin (004 step ⑤); G78: previous depth + Δdmin (002).
                    let base = if style.g78_mode.is_none() { ((n - 1) as f64).sqrt() * dd } else { prev };
                    dn = dn.max(base + dmin);
                }
                if dn >= rough_total - 1e-12 {
                    depths.push(rough_total);
                    break;
                }
                depths.push(dn);
                prev = dn;
                n += 1;
                if depths.len() + m as usize > MAX_PASSES {
                    return Err(bad(ddc, format!("{name} would cut more than {MAX_PASSES} passes: increase Q(Δd) or Δdmin")));
                }
            }
        }
        let tag: Arc<str> = Arc::from(name);
        let nr = depths.len();
        let g78 = style.g78_mode.is_some();
        // (depth, Z shift, steps).
        let mut passes: Vec<(f64, f64, [u8; 4])> = depths
            .iter()
            .enumerate()
            .map(|(j, &dn)| {
                let steps = match (g78, j, j + 1 == nr) {
                    (true, _, _) => [3, 4, 5, 5],
                    (false, 0, _) => [1, 2, 3, 4],
                    (false, _, false) => [5, 2, 3, 4],
                    (false, _, true) => [5, 6, 7, 8],
                };
                (dn, Self::flank_shift(style.g78_mode, j, zdir) * dn * tan, steps)
            })
            .collect();
        // G76: finishing at depth k on the flank line; G78 (002 note 2): at the last rough
        // pass's Z.
        let fin_shift = match (style.g78_mode, passes.last()) {
            (Some(_), Some(p)) => p.1,
            (Some(_), None) => 0.0,
            (None, _) => zdir * k * tan,
        };
        let fin_steps = if g78 { [7, 7, 8, 8] } else { [9, 9, 9, 9] };
        passes.extend((0..m).map(|_| (k, fin_shift, fin_steps)));
        // Check every pass's run-out before emitting anything.
        let mut paths = Vec::with_capacity(passes.len());
        for &(dn, dz, _) in &passes {
            let bn = Pos { x: b.x + inward * dn, z: a.z + dz, ..a };
            let end = Pos { x: bn.x + slope * (dpt.z - bn.z), z: dpt.z, ..a };
            let segs = thread_path_js(bn, end, lead, runout, short, a).map_err(|m| (RANGE_ALARM, gc, format!("{name}: {m}")))?;
            paths.push((bn, segs));
        }
        for ((_, _, st), (bn, segs)) in passes.iter().zip(paths) {
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

    /// Z shift direction (× depth·tan(a/2)) of rough pass `j` (0-based): G76 towards D;
    /// G78 (002 "切入方式"): 0 centre (none), 1 left flank (−Z), 2 right flank (+Z),
    /// 3 right and centre in turn, 4 left and right in turn (starting with the first named).
    fn flank_shift(mode: Option<u32>, j: usize, zdir: f64) -> f64 {
        match mode {
            None => zdir,
            Some(1) => -1.0,
            Some(2) => 1.0,
            Some(3) => {
                if j % 2 == 0 {
                    1.0
                } else {
                    0.0
                }
            }
            Some(4) => {
                if j % 2 == 0 {
                    -1.0
                } else {
                    1.0
                }
            }
            Some(_) => 0.0,
        }
    }

    /// G78 (manual 002), both blocks. First: `P(m)(r)(a) Q(Δdmin) R(d) D`; r is the infeed
    /// mode 0–4, D the depth mode (0 constant Δd per pass, 1 decreasing as G76). Second:
    /// `X(U) Z(W) R(i) P(k) Q(Δd) J K F(I)`: J/K the run-out's short/long amounts (modal,
    /// else No.5130/5131), I threads per inch. Steps are the manual's (3) infeed, (4) thread,
    /// (5) X then Z rapid return, (7) finishing infeed and thread, (8) its return. E (lead-in)
    /// and L are printed in the format but not described, so they are refused rather than
    /// guessed.
    pub(super) fn g78(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G78")?;
        for l in ['E', 'L'] {
            if let Some(v) = d.get(l) {
                return Err((10, Some(v.col), format!("G78 {l}: the manual does not describe this address; it is not supported")));
            }
        }
        let second = ['X', 'U', 'Z', 'W'].iter().any(|l| d.has(*l));
        if !second {
            let mode_before = self.cyc.p5130;
            let mut p_r = None;
            if let Some(p) = d.get('P') {
                let r = ((p.v.round() as u64) / 100) % 100;
                if r > 4 {
                    return Err((G76_VALUE_ALARM, Some(p.col), format!("G78 P: infeed mode r = {r}, must be 0–4")));
                }
                p_r = Some(r as u32);
            }
            self.g76_first(d)?;
            // P(r) of G78 is the infeed mode, not the run-out: undo g76_first's No.5130.
            self.cyc.p5130 = mode_before;
            if let Some(r) = p_r {
                self.cyc.g78_mode = r;
            }
            if let Some(v) = d.get('D') {
                if v.v != 0.0 && v.v != 1.0 {
                    return Err((G76_VALUE_ALARM, Some(v.col), format!("G78 D{}: the depth mode is 0 (constant) or 1 (decreasing)", v.v)));
                }
                self.cyc.g78_decreasing = v.v == 1.0;
            }
            return Ok(());
        }
        let lead = if let Some(i) = d.get('I') {
            if i.v <= 0.0 {
                return Err((11, Some(i.col), "G78 I (threads per inch) must be positive".into()));
            }
            self.cyc.lead = Some(25.4 / i.v);
            25.4 / i.v
        } else {
            self.thread_lead(d)?
        };
        for (l, slot) in [('J', 0), ('K', 1)] {
            if let Some(v) = d.get(l) {
                let x = self.len(v);
                if x < 0.0 {
                    return Err((G76_VALUE_ALARM, Some(v.col), format!("G78 {l} is unsigned")));
                }
                if slot == 0 {
                    self.cyc.g78_jk.0 = Some(x);
                } else {
                    self.cyc.g78_jk.1 = Some(x);
                }
            }
        }
        let runout = match self.cyc.g78_jk {
            (None, None) => {
                let r = self.cyc.p5130 as f64 * 0.1 * lead;
                let a = self.cyc.p5131;
                let angle = if (1.0..=89.0).contains(&a) { a } else { 45.0 };
                (r, r * angle.to_radians().tan())
            }
            // One of J/K alone: 45°, as No.5131 = 0.
            (j, k) => {
                let k = k.or(j).unwrap_or(0.0);
                (k, j.unwrap_or(k))
            }
        };
        let style = Style { name: "G78", g78_mode: Some(self.cyc.g78_mode), decreasing: self.cyc.g78_decreasing, runout };
        self.multi_thread(d, src, lead, style)
    }
}
