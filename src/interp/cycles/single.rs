//! Single cycles: G90 (OD/ID turning, §2.15.1), G94 (facing, §2.15.2) and G92 (thread
//! cutting, §2.17.3). All start and end at the start point A; steps ①–④ as in the manual.

use super::{thread_path, CErr, RANGE_ALARM};
use crate::canon::{MoveKind, Pos, SrcPos};
use crate::interp::gcode::Decoded;
use crate::interp::{nosecomp, Interpreter};
use std::sync::Arc;

impl Interpreter {
    /// G90 / G94. G90: ① X rapid A→B (B = C's X + R radius, A's Z), ② feed B→C, ③ X feed to
    /// A's X (D), ④ Z rapid to A. G94: the same with the axes exchanged, R being the Z
    /// difference of the cutting start from C. The four sign cases of U/W/R all follow from
    /// these formulas; when R and the cut depth (U/2 for G90, W for G94) have opposite signs,
    /// |R| must not exceed it, or the path would cross the start point (figures 2.24/2.28).
    /// Under G41/G42 the cuts ② and ③ are offset by the nose radius towards A, the tip point
    /// running on them (Fanuc 0i-TF; see [`nosecomp::single_cycle_offset`]).
    pub(super) fn g90_g94(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        let g90 = self.st.motion == 900;
        let name = if g90 { "G90" } else { "G94" };
        self.cycle_plane_check(d, name)?;
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let a = self.pos;
        let (c, r) = self.single_target(d);
        let depth = if g90 { c.x - a.x } else { c.z - a.z };
        if r * depth < 0.0 && r.abs() > depth.abs() + 1e-9 {
            let what = if g90 { "|U/2|" } else { "|W|" };
            return Err((
                RANGE_ALARM,
                d.get('R').map(|v| v.col).or(Self::gcol(d)),
                format!(
                    "{name}: R{r:.3} and the cut have opposite signs and |R| > {what} ({:.3}): the taper would cross the start point",
                    depth.abs()
                ),
            ));
        }
        let tag: Arc<str> = Arc::from(name);
        let mut b = if g90 { Pos { x: c.x + r, ..a } } else { Pos { z: c.z + r, ..a } };
        let mut dpt = if g90 { Pos { x: a.x, ..c } } else { Pos { z: a.z, ..c } };
        let mut c = c;
        if self.nrc.active() && self.tool.nose_radius > 0.0 {
            // G41/G42 in force: the cuts are offset here, by the tip (see
            // `nosecomp::single_cycle_offset`); the stage passes the cycle's moves as they are.
            let (x_ax, z_ax) = ((0.0, 1.0), (1.0, 0.0));
            let (app, ret) = if g90 { (x_ax, z_ax) } else { (z_ax, x_ax) };
            let off = nosecomp::single_cycle_offset(a, b, c, dpt, app, ret, self.tool.nose_radius, self.tool.tip)
                .map_err(|m| (nosecomp::INTERFERENCE_ALARM, Self::gcol(d), format!("{name}: {m}")))?;
            if let Some((b2, c2, d2)) = off {
                (b, c, dpt) = (b2, c2, d2);
            }
        }
        self.cpush(src, &tag, 1, MoveKind::Rapid { end: b }, true);
        self.cpush(src, &tag, 2, MoveKind::Feed { end: c, feed }, false);
        self.cpush(src, &tag, 3, MoveKind::Feed { end: dpt, feed }, false);
        self.cpush(src, &tag, 4, MoveKind::Rapid { end: a }, true);
        Ok(())
    }

    /// G92: ① X rapid A→B, ② thread B→C (with the run-out of No.5130/No.5131 at its end),
    /// ③ X rapid to A's X, ④ Z rapid to A. H multi-start: F is the pitch, the lead is H × F
    /// and the cycle runs once per start at spindle angles Q + 360°·j/H (Q: Fanuc's G92
    /// start angle; the manual gives none for G92).
    pub(super) fn g92(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        self.cycle_plane_check(d, "G92")?;
        let pitch = self.thread_lead(d)?;
        let q = self.start_angle(d)?;
        let starts = match d.get('H') {
            None => 1,
            Some(h) if !h.bad_integer() && (1.0..=99.0).contains(&h.v) => h.v as u32,
            Some(h) => return Err((RANGE_ALARM, Some(h.col), format!("H{}: the number of thread starts must be 1–99", h.v))),
        };
        let lead = pitch * starts as f64;
        let a = self.pos;
        let (c, r) = self.single_target(d);
        let depth = c.x - a.x;
        if r * depth < 0.0 && r.abs() > depth.abs() + 1e-9 {
            return Err((
                RANGE_ALARM,
                d.get('R').map(|v| v.col).or(Self::gcol(d)),
                format!("G92: R{r:.3} and U have opposite signs: |R| must not exceed |U/2| ({:.3})", depth.abs()),
            ));
        }
        let b = Pos { x: c.x + r, ..a };
        // No.5130 × 0.1 × lead (the lead of one revolution is what a run-out is measured in).
        let runout = self.cyc.p5130 as f64 * 0.1 * lead;
        let segs = thread_path(b, c, lead, runout, self.cyc.p5131, a).map_err(|m| (RANGE_ALARM, Self::gcol(d), format!("G92: {m}")))?;
        let tag: Arc<str> = Arc::from("G92");
        for j in 0..starts {
            let angle = (q + 360.0 * j as f64 / starts as f64) % 360.0;
            self.cpush(src, &tag, 1, MoveKind::Rapid { end: b }, true);
            self.push_threads(src, &tag, 2, &segs, angle);
            let e = Pos { x: a.x, ..self.pos };
            self.cpush(src, &tag, 3, MoveKind::Rapid { end: e }, true);
            self.cpush(src, &tag, 4, MoveKind::Rapid { end: a }, true);
        }
        Ok(())
    }
}
