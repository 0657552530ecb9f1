//! G22/G23 stored stroke check 2 (manual 004 §2.10), checked on every move before it leaves
//! the interpreter, so a program that would enter the forbidden area stops at the block that
//! would do it, before any motion of that block.
//!
//! `G22 X Z I K` (and `Y J` on a machine with Y): X/Y/Z the corner on the positive side, I/J/K
//! the one on the negative side, machine coordinates, X and I as diameters like every X word.
//! Without them the area is No.1360+i (positive) and No.1370+i (negative), i = 0 X, 1 Y,
//! 2 Z, in least input increments (0.001 mm, X as a diameter) from reference point 1
//! (No.1240) (note 2). No.1002 bit 0: 0 the inside of the area is forbidden, 1 the outside
//! (note 3). Note 6: G22/G23 must be the only G code of the block. Note 7: switching on
//! while the tool is in the forbidden area: inside type — the next move alarms (it starts
//! inside); outside type — at once. Note 8: a corner in the wrong order (negative > positive
//! on an axis) disables the check. Note 4: in G22 with the inside forbidden, reference
//! point 1 in the area alarms at once. (The interpreter does not know whether the machine
//! has been referenced, note 4's first half; the motion layer's soft limits apply anyway.)
//!
//! The check uses the programmed path with the tool offsets (before nose radius
//! compensation, which moves it by at most the nose radius); arcs are checked on chords of
//! at most 2°.
//!
//! Alarm numbers (the manual gives none): Fanuc 0i-TF OT0502 "+ overtravel (soft 2)" and
//! OT0503 "− overtravel (soft 2)", by the direction of the move on the axis that meets the
//! boundary.

use super::CErr;
use crate::canon::{Move, MoveKind, Pos, SrcPos, StrokeArea};
use crate::config::MachineConfig;
use crate::interp::gcode::Decoded;
use crate::interp::Interpreter;
use crate::Alarm;

pub const PLUS_ALARM: u32 = crate::alarm::PLUS_STROKE;
pub const MINUS_ALARM: u32 = crate::alarm::MINUS_STROKE;

#[derive(Clone, Debug, Default)]
pub struct Stroke2 {
    on: bool,
    /// No.1002#0: the outside of the area is forbidden.
    outside: bool,
    /// The area (machine, X radius); `None` when the corners are in the wrong order.
    area: Option<(Pos, Pos)>,
    /// The area of the parameters, if set.
    param_area: Option<(Pos, Pos)>,
    ref1: Pos,
    /// Where the last move checked ended.
    last: Pos,
}

/// Box with its Y extent unbounded when the machine has no Y limits.
fn ordered(lo: Pos, hi: Pos) -> Option<(Pos, Pos)> {
    (lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z).then_some((lo, hi))
}

fn inside(p: Pos, (lo, hi): (Pos, Pos)) -> bool {
    let e = 1e-9;
    p.x > lo.x + e && p.x < hi.x - e && p.y > lo.y + e && p.y < hi.y - e && p.z > lo.z + e && p.z < hi.z - e
}

/// Does the segment a–b pass through the open box? (Slab method.)
fn seg_hits(a: Pos, b: Pos, (lo, hi): (Pos, Pos)) -> bool {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (s, e, l, h) in [(a.x, b.x, lo.x, hi.x), (a.y, b.y, lo.y, hi.y), (a.z, b.z, lo.z, hi.z)] {
        let (l, h) = (l + 1e-9, h - 1e-9);
        let d = e - s;
        if d.abs() < 1e-15 {
            if s <= l || s >= h {
                return false;
            }
        } else {
            let (mut u, mut v) = ((l - s) / d, (h - s) / d);
            if u > v {
                std::mem::swap(&mut u, &mut v);
            }
            t0 = t0.max(u);
            t1 = t1.min(v);
            if t0 >= t1 {
                return false;
            }
        }
    }
    true
}

impl Stroke2 {
    pub fn new(cfg: &MachineConfig) -> Stroke2 {
        let r1 = Pos {
            x: cfg.param_axis(1240, "x").unwrap_or(0.0) / 2.0,
            y: cfg.param_axis(1240, "y").unwrap_or(0.0),
            z: cfg.param_axis(1240, "z").unwrap_or(0.0),
            c: 0.0,
        };
        let get = |n: u32| cfg.param(n).filter(|v| v.is_finite()).map(|v| v * 0.001);
        let corner = |base: u32, inf: f64| -> Option<Pos> {
            let x = get(base)?;
            let z = get(base + 2)?;
            let y = get(base + 1).unwrap_or(inf);
            Some(Pos { x: r1.x + x / 2.0, y: if y.is_finite() { r1.y + y } else { y }, z: r1.z + z, c: 0.0 })
        };
        let param_area = match (corner(1370, f64::NEG_INFINITY), corner(1360, f64::INFINITY)) {
            (Some(lo), Some(hi)) => Some((lo, hi)),
            _ => None,
        };
        Stroke2 { on: false, outside: cfg.param(1002).is_some_and(|v| (v as i64) & 1 == 1), area: None, param_area, ref1: r1, last: Pos::ZERO }
    }

    pub fn set_start(&mut self, p: Pos) {
        self.last = p;
    }

    /// Check one move (every move passes here in order).
    pub fn check(&mut self, m: &Move) -> Result<(), Alarm> {
        let Some(end) = m.kind.end() else { return Ok(()) };
        let start = std::mem::replace(&mut self.last, end);
        let Some(area) = self.area.filter(|_| self.on) else { return Ok(()) };
        let mut pts = vec![start];
        if let MoveKind::Arc { center, cw, .. } = &m.kind {
            // ZX arcs (the lathe's); other planes are checked on their chord.
            pts.extend(crate::canon::zx_arc_chord_points(start, end, *center, *cw));
        }
        pts.push(end);
        for w in pts.windows(2) {
            let (a, b) = (w[0], w[1]);
            let bad = if self.outside { !inside(b, area) || !inside(a, area) } else { seg_hits(a, b, area) };
            if bad {
                let d = b.sub(a);
                let dom = [d.x, d.y, d.z].into_iter().fold(0.0f64, |m, v| if v.abs() > m.abs() { v } else { m });
                let n = if dom >= 0.0 { PLUS_ALARM } else { MINUS_ALARM };
                let (lo, hi) = area;
                return Err(Alarm::new(
                    n,
                    format!(
                        "stored stroke check 2 (G22): this move {} the forbidden area ({} of X{:.3}…{:.3} Z{:.3}…{:.3}, machine, X diameter); change the path or cancel with G23 (§2.10)",
                        if self.outside { "leaves the allowed area into" } else { "enters" },
                        if self.outside { "outside" } else { "inside" },
                        lo.x * 2.0,
                        hi.x * 2.0,
                        lo.z,
                        hi.z
                    ),
                )
                .at(m.src.clone()));
            }
        }
        Ok(())
    }
}

impl Interpreter {
    /// G22/G23 of the block. Returns true when the block was a G22/G23 block (nothing else
    /// in it runs: note 6). The switch is also put in the move stream
    /// ([`MoveKind::StrokeCheck`]) so that the motion layer's per-set-point guard switches
    /// with it when execution reaches this block.
    pub(in crate::interp) fn stroke_block(&mut self, d: &Decoded, src: &SrcPos) -> Result<bool, CErr> {
        let Some(g) = d.group(4) else { return Ok(false) };
        let col = d.g.iter().find(|x| x.0 == g).map(|x| x.1);
        if d.g.len() > 1 {
            return Err((10, col, format!("G{}: G22/G23 must be the only G code of its block (§2.10 note 6)", g / 10)));
        }
        if g == 230 {
            self.cyc.stroke.on = false;
            self.push(src, MoveKind::StrokeCheck { area: None }, false);
            return Ok(true);
        }
        let words = ['X', 'Z', 'I', 'K'];
        let area = if words.iter().any(|l| d.has(*l)) || d.has('Y') || d.has('J') {
            let need = |l: char| -> Result<f64, CErr> {
                d.get(l).map(|v| self.len(v)).ok_or((10, col, format!("G22 with a boundary needs X, Z, I and K (missing {l}) (§2.10)")))
            };
            let hi = Pos { x: need('X')? / 2.0, z: need('Z')?, y: d.get('Y').map(|v| self.len(v)).unwrap_or(f64::INFINITY), c: 0.0 };
            let lo = Pos { x: need('I')? / 2.0, z: need('K')?, y: d.get('J').map(|v| self.len(v)).unwrap_or(f64::NEG_INFINITY), c: 0.0 };
            Some((lo, hi))
        } else {
            self.cyc.stroke.param_area
        };
        let Some((lo, hi)) = area else {
            return Err((10, col, "G22 without X Z I K needs the boundary in No.1360–1375 (§2.10)".into()));
        };
        let st = &mut self.cyc.stroke;
        st.area = ordered(lo, hi);
        st.on = true;
        if let Some(a) = st.area {
            if st.outside && !inside(st.last, a) {
                st.on = false;
                return Err((PLUS_ALARM, col, "G22: the tool is already outside the allowed area (§2.10 note 7): move it inside, then G22".into()));
            }
            if !st.outside && inside(st.ref1, a) {
                st.on = false;
                return Err((PLUS_ALARM, col, "G22: reference point 1 lies in the forbidden area (§2.10 note 4): correct the boundary".into()));
            }
        }
        let (outside, area) = (st.outside, st.area);
        let area = area.map(|(lo, hi)| StrokeArea { lo, hi, outside });
        self.push(src, MoveKind::StrokeCheck { area }, false);
        Ok(true)
    }
}
