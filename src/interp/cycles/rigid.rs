//! G92.1 rigid thread cutting cycle (manual 001 §3.24.10): like G92, but the spindle is a
//! position axis interpolated with the feed axes ([`MoveKind::RigidThread`]).
//!
//! ① X rapid A→B, the spindle positioned (same rapid) to this start's angle
//! c₀ + 360°·j/L; ② rigid thread B→C, the spindle turning 360° per lead along the long axis,
//! both stopping at C (note 6: no run-out); ③ X rapid to A's X; ④ Z rapid to A, the spindle
//! back to c₀ turning on in the cutting direction (note 7). c₀ is the spindle (C) position
//! before the cycle block. F (mm or inch per rev) or I (threads per inch): a negative value
//! is a left-hand thread, the spindle turning the other way. L (1–99 starts) and F/I are
//! modal; X/Z/R are kept like G92's. The spindle speed is the modal S (G97, or the G96 speed
//! at the start X). Faces cannot be cut: Z must move.

use super::{CErr, MAX_LEAD, RANGE_ALARM};
use crate::canon::{MoveKind, Pos, SrcPos};
use crate::interp::gcode::Decoded;
use crate::interp::Interpreter;
use std::sync::Arc;

/// The first angle ≥ `from` (dir > 0) or ≤ `from` (dir < 0) congruent to `target` mod 360.
pub fn forward_angle(from: f64, target: f64, dir: f64) -> f64 {
    let diff = (target - from).rem_euclid(360.0);
    let diff = if diff.abs() < 1e-9 || (360.0 - diff).abs() < 1e-9 { 0.0 } else { diff };
    if dir >= 0.0 {
        from + diff
    } else if diff == 0.0 {
        from
    } else {
        from - (360.0 - diff)
    }
}

impl Interpreter {
    pub(super) fn g92_1(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G92.1")?;
        let gc = Self::gcol(d);
        if let Some(i) = d.get('I') {
            if i.v == 0.0 {
                return Err((11, Some(i.col), "G92.1 I (threads per inch) cannot be zero".into()));
            }
            self.cyc.rigid_lead = Some(25.4 / i.v);
        } else if let Some(f) = d.get('F') {
            if f.v == 0.0 {
                return Err((11, Some(f.col), "G92.1 F (lead) cannot be zero".into()));
            }
            self.cyc.rigid_lead = Some(if self.st.inch { f.v * 25.4 } else { f.v });
        }
        let lead =
            self.cyc.rigid_lead.ok_or((11, gc, "G92.1: no lead: program F (mm/rev, negative = left hand) or I (threads per inch)".to_string()))?;
        if lead.abs() > MAX_LEAD {
            return Err((14, gc, format!("G92.1: lead {lead:.3} mm is more than {MAX_LEAD} mm")));
        }
        if let Some(l) = d.get('L') {
            if !(1.0..=99.0).contains(&l.v) {
                return Err((RANGE_ALARM, Some(l.col), format!("G92.1 L{}: the number of thread starts must be 1–99", l.v)));
            }
            self.cyc.rigid_starts = l.v as u32;
        }
        let starts = self.cyc.rigid_starts;
        let rpm = if self.st.css { self.css_rpm(self.st.css_v.unwrap_or(0.0)) } else { self.st.rpm };
        if rpm <= 0.0 {
            return Err((RANGE_ALARM, gc, "G92.1 needs a spindle speed: program S (it is modal)".into()));
        }
        let a = self.pos;
        let (c, r) = self.single_target(d);
        if (c.z - a.z).abs() < 1e-9 {
            return Err((RANGE_ALARM, gc, "G92.1 cannot cut face threads: Z(W) must move".into()));
        }
        let depth = c.x - a.x;
        if r * depth < 0.0 && r.abs() > depth.abs() + 1e-9 {
            return Err((
                RANGE_ALARM,
                d.get('R').map(|v| v.col).or(gc),
                format!("G92.1: R{r:.3} and U have opposite signs: |R| must not exceed |U/2| ({:.3})", depth.abs()),
            ));
        }
        let b = Pos { x: c.x + r, ..a };
        let long = (c.z - b.z).abs().max((c.x - b.x).abs());
        let dir = lead.signum();
        let turn = dir * 360.0 * long / lead.abs();
        let c0 = a.c;
        let tag: Arc<str> = Arc::from("G92.1");
        for j in 0..starts {
            let start_c = forward_angle(self.pos.c, c0 + 360.0 * j as f64 / starts as f64, dir);
            self.cpush(src, &tag, 1, MoveKind::Rapid { end: Pos { c: start_c, ..b } }, true);
            let end = Pos { c: self.pos.c + turn, ..c };
            self.cpush(src, &tag, 2, MoveKind::RigidThread { end, lead, rpm }, true);
            self.cpush(src, &tag, 3, MoveKind::Rapid { end: Pos { x: a.x, ..self.pos } }, true);
            let back = forward_angle(self.pos.c, c0, dir);
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: Pos { c: back, ..a } }, true);
        }
        Ok(())
    }
}
