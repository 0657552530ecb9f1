//! G12.1/G13.1 polar coordinate interpolation (manual 004 §2.7) and G51.2/G50.2 polygon
//! turning (§2.8).
//!
//! Polar: in G12.1 mode X (diameter) and C (the hypothetical axis, radius, mm: "C 轴用半径
//! 编程(编程单位为 mm)") are written as cartesian coordinates of a plane whose origin is the
//! workpiece zero, the rotation centre (note 7). G12.1 takes the tool's current X as the
//! point (x, 0) at the spindle's current angle (note 10: "从角度 0 开始"). Every G01/G02/G03
//! becomes one [`MoveKind::Polar`] that the motion layer converts to X/C each cycle. Arcs
//! take R only (note 6). Only G01, G02, G03, G04, G40–G42, G98, G99 (and G13.1) are allowed
//! (note 4); G12.1/G13.1 must be in G40 (note 8) and alone in their block.
//!
//! Note 9 (the C speed near the centre): a G98 feed F along a path that comes within d of
//! the centre turns C at up to F/d rad/min; above the C axis' speed (the spindle's
//! `max_speed` × 360 °/min, or axis `c`'s) the block is refused before it runs. A path through
//! the centre itself is refused the same way.
//!
//! Polygon: `G51.2 P Q R S` (alone in the block, note 1) emits [`MoveKind::Polygon`] with the
//! tool spindle at S × Q / P clamped to No.721 (note 3); G51.2 again in the mode changes the
//! speed (note 4); G50.2 cancels. In the mode the work and tool spindle cannot be moved as
//! axes (note 11: C/H refused). The motion layer needs a tool spindle to execute it.
//!
//! Alarm numbers: the manual gives none. Fanuc 0i-TF: 10 a G code not allowed in the mode or
//! G12.1/G51.2 with other commands, 22 I/J/K in polar mode (R only), 20 R too small, 37
//! G12.1/G13.1 in G41/G42 (PS0037: plane change during compensation); ours [`RANGE_ALARM`]
//! (2510) for P/Q/R/S out of the manual's ranges and the C speed of note 9 (Fanuc clamps the
//! feed instead; the manual says alarm).

use super::{CErr, RANGE_ALARM};
use crate::canon::{polar_to_machine, Feed, MoveKind, PolygonCmd, SrcPos};
use crate::interp::gcode::{self, Decoded, GCode};
use crate::interp::Interpreter;

/// State of G12.1 mode.
#[derive(Clone, Debug)]
pub struct PolarState {
    /// Machine C (degrees) of the virtual +X direction.
    c_zero: f64,
    /// Current virtual point [x, c] (mm, x as a radius).
    v: [f64; 2],
}

/// Codes allowed in polar mode (note 4), ×10.
const POLAR_OK: [GCode; 10] = [10, 20, 30, 40, 400, 410, 420, 980, 990, 131];

impl Interpreter {
    /// G12.1/G13.1 and G51.2/G50.2 of the block, and the polar-mode checks. Called from
    /// `exec_block` after the modal groups are read.
    pub(in crate::interp) fn special_modes(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        let gcol = |g: GCode| d.g.iter().find(|x| x.0 == g).map(|x| x.1);
        if let Some(g) = d.group(21) {
            if self.nrc.active() {
                return Err((37, gcol(g), format!("{}: cancel tool nose radius compensation (G40) first (§2.7 note 8)", gcode::gname(g))));
            }
            if d.g.len() > 1 || d.letters().next().is_some() || !d.m.is_empty() {
                return Err((10, gcol(g), format!("{} must be alone in its block (§2.7)", gcode::gname(g))));
            }
            if g == 121 {
                if !self.has_c {
                    return Err((10, gcol(g), "G12.1 needs a C axis (the spindle as a Cs axis) in the configuration".into()));
                }
                if self.polar.is_none() {
                    let work_x = self.pos.x - self.offset().x;
                    self.polar = Some(PolarState { c_zero: self.pos.c, v: [work_x, 0.0] });
                }
            } else {
                self.polar = None;
            }
            return Ok(());
        }
        if self.polar.is_some() {
            if let Some(&(g, col)) = d.g.iter().find(|g| !POLAR_OK.contains(&g.0)) {
                return Err((
                    10,
                    Some(col),
                    format!(
                        "{} is not allowed in polar coordinate interpolation (G12.1): only G01 G02 G03 G04 G40 G41 G42 G98 G99 (§2.7 note 4)",
                        gcode::gname(g)
                    ),
                ));
            }
        }
        if let Some(g) = d.group(20) {
            return self.polygon(d, src, g, gcol(g));
        }
        if self.cyc.polygon {
            if let Some(l) = ['C', 'H'].into_iter().find(|l| d.has(*l)) {
                return Err((
                    9,
                    d.get(l).map(|v| v.col),
                    format!("{l}: the spindles cannot be moved as axes during polygon turning (§2.8 note 11); cancel with G50.2 first"),
                ));
            }
        }
        Ok(())
    }

    pub(in crate::interp) fn polar_active(&self) -> bool {
        self.polar.is_some()
    }

    /// G51.2 P Q R S / G50.2.
    fn polygon(&mut self, d: &Decoded, src: &SrcPos, g: GCode, col: Option<u32>) -> Result<(), CErr> {
        if d.g.len() > 1 || !d.m.is_empty() || d.letters().any(|l| !matches!(l, 'P' | 'Q' | 'R' | 'S')) {
            return Err((10, col, format!("{} must be alone in its block, with P Q R S only (§2.8 note 1)", gcode::gname(g))));
        }
        if !self.cyc.tool_spindle {
            return Err((
                crate::alarm::NO_TOOL_SPINDLE,
                col,
                format!("{}: polygon turning needs a tool spindle, and this machine's config has none; add an axis with kind = \"spindle\" and role = \"tool_spindle\" (see config/lathe-polygon.toml) or remove the polygon turning blocks", gcode::gname(g)),
            ));
        }
        if g == 502 {
            self.cyc.polygon = false;
            self.push(src, MoveKind::Polygon(None), true);
            return Ok(());
        }
        let int = |l: char, lo: f64, hi: f64, def: f64| -> Result<f64, CErr> {
            match d.get(l) {
                None => Ok(def),
                Some(v) if v.v.fract() == 0.0 && (lo..=hi).contains(&v.v) => Ok(v.v),
                Some(v) => Err((RANGE_ALARM, Some(v.col), format!("G51.2 {l}{}: must be a whole number {lo}–{hi} (§2.8)", v.v))),
            }
        };
        let p = int('P', 1.0, 999.0, 1.0)?;
        let q = int('Q', 1.0, 999.0, 1.0)?;
        let phase = match d.get('R') {
            None => 0.0,
            Some(r) if (0.0..360.0).contains(&r.v) => r.v,
            Some(r) => return Err((RANGE_ALARM, Some(r.col), format!("G51.2 R{}: the phase must be 0–359.999°", r.v))),
        };
        let s = match d.get('S') {
            Some(_) => int('S', 1.0, 9999.0, 0.0)?,
            None if self.st.rpm >= 1.0 => self.st.rpm,
            None => return Err((RANGE_ALARM, col, "G51.2 needs S, the work spindle speed (1–9999 rpm)".into())),
        };
        let mut tool = s * q / p;
        if let Some(clamp) = self.cyc.p721.filter(|c| *c > 0.0) {
            tool = tool.min(clamp);
        }
        self.st.rpm = s;
        self.cyc.polygon = true;
        let cmd = PolygonCmd { p: p as u32, q: q as u32, phase, rpm: s, tool_rpm: tool };
        self.push(src, MoveKind::Polygon(Some(cmd)), true);
        Ok(())
    }

    /// A motion block in G12.1 mode.
    pub(in crate::interp) fn polar_motion(&mut self, d: &Decoded, src: &SrcPos, exact: bool) -> Result<(), CErr> {
        let Some(ps) = self.polar.clone() else { return Ok(()) };
        if !['X', 'U', 'C', 'H', 'Z', 'W'].into_iter().any(|l| d.has(l)) {
            return Ok(());
        }
        let gc = d.g.first().map(|g| g.1);
        let axis = |abs: char, inc: char, cur: f64, scale: f64| -> f64 {
            if let Some(v) = d.get(abs) {
                self.len(v) * scale
            } else if let Some(v) = d.get(inc) {
                cur + self.len(v) * scale
            } else {
                cur
            }
        };
        let to = [axis('X', 'U', ps.v[0], 0.5), axis('C', 'H', ps.v[1], 1.0)];
        let off = self.offset();
        let z = axis('Z', 'W', self.pos.z - off.z, 1.0) + off.z;
        let from = ps.v;
        let center = match self.st.motion {
            10 => None,
            20 | 30 => {
                if let Some(l) = ['I', 'J', 'K'].into_iter().find(|l| d.has(*l)) {
                    return Err((
                        22,
                        d.get(l).map(|v| v.col),
                        format!("{l}: in polar coordinate interpolation an arc takes its radius R only (§2.7 note 6)"),
                    ));
                }
                match d.get('R') {
                    // §2.3 note 2 / No.3403#5 = 0: an arc without R is a straight line (this is
                    // how fig. 2.12's N210 C0, modal G03 without R, reads as a line).
                    None if !self.arc_missing_alarm => None,
                    None => return Err((22, gc, "in polar coordinate interpolation an arc needs R (§2.7 note 6)".to_string())),
                    Some(r) => {
                        let rv = self.len(r);
                        let (du, dv) = (to[0] - from[0], to[1] - from[1]);
                        let chord = du.hypot(dv);
                        if chord < 1e-9 {
                            return Ok(());
                        }
                        let half = chord / 2.0;
                        if half > rv.abs() + self.arc_tol {
                            return Err((20, Some(r.col), format!("R{:.4}: the end point is {chord:.4} mm away, more than the diameter", rv.abs())));
                        }
                        let h = (rv * rv - half * half).max(0.0).sqrt();
                        let (nu, nv) = (-dv / chord, du / chord);
                        let side = if self.st.motion == 20 { -1.0 } else { 1.0 } * if rv < 0.0 { -1.0 } else { 1.0 };
                        Some([(from[0] + to[0]) / 2.0 + side * h * nu, (from[1] + to[1]) / 2.0 + side * h * nv])
                    }
                }
            }
            g => {
                return Err((
                    10,
                    gc,
                    format!("{} is not allowed in polar coordinate interpolation (G12.1): only G01 G02 G03 (§2.7 note 4)", gcode::gname(g)),
                ))
            }
        };
        let cw = self.st.motion == 20;
        if from == to && (z - self.pos.z).abs() < 1e-12 {
            return Ok(());
        }
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        // The path sampled: the C angle it turns through (continuous) and its closest approach
        // to the centre.
        let pts = sample(from, to, center, cw);
        let mut turn = 0.0;
        let mut dmin = f64::INFINITY;
        for w in pts.windows(2) {
            let (a, b) = (w[0], w[1]);
            turn += (a[0] * b[1] - a[1] * b[0]).atan2(a[0] * b[0] + a[1] * b[1]);
            dmin = dmin.min(seg_dist(a, b));
        }
        if let Feed::PerMin(f) = feed {
            let limit = self.cyc.c_max_deg_min;
            let need = if dmin < 1e-9 { f64::INFINITY } else { f / dmin * 180.0 / std::f64::consts::PI };
            if limit.is_some_and(|l| need > l) || dmin < 1e-9 {
                return Err((
                    RANGE_ALARM,
                    gc,
                    format!(
                        "this move passes {dmin:.3} mm from the rotation centre: at F{f} the C axis would turn {:.0}°/min, more than its {:.0}°/min (§2.7 note 9); lower F or keep away from the centre",
                        need.min(1e12),
                        limit.unwrap_or(0.0)
                    ),
                ));
            }
        }
        let c_end = self.pos.c + turn.to_degrees();
        let (x, c) = polar_to_machine(to, ps.c_zero, off.x, c_end);
        let end = crate::canon::Pos { x, c, z, ..self.pos };
        self.pos = end;
        if let Some(p) = self.polar.as_mut() {
            p.v = to;
        }
        self.push(src, MoveKind::Polar { end, from, to, center, cw, c_zero: ps.c_zero, feed }, exact);
        Ok(())
    }
}

/// Points along a virtual line or arc (at most 2° of arc or 1/64 of a line apart).
pub(crate) fn sample(from: [f64; 2], to: [f64; 2], center: Option<[f64; 2]>, cw: bool) -> Vec<[f64; 2]> {
    match center {
        None => {
            let n = 64;
            (0..=n)
                .map(|i| {
                    let t = i as f64 / n as f64;
                    [from[0] + (to[0] - from[0]) * t, from[1] + (to[1] - from[1]) * t]
                })
                .collect()
        }
        Some(c) => {
            let (a0, sweep) = crate::canon::arc_sweep(from, to, c, cw);
            let r = (from[0] - c[0]).hypot(from[1] - c[1]);
            let n = ((sweep.abs() / 2f64.to_radians()).ceil() as usize).max(2);
            let mut v: Vec<[f64; 2]> = (0..n)
                .map(|i| {
                    let t = a0 + sweep * i as f64 / n as f64;
                    [c[0] + r * t.cos(), c[1] + r * t.sin()]
                })
                .collect();
            v.push(to);
            v
        }
    }
}

/// Distance from the origin to the segment a–b.
fn seg_dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    let d = [b[0] - a[0], b[1] - a[1]];
    let l2 = d[0] * d[0] + d[1] * d[1];
    let t = if l2 < 1e-24 { 0.0 } else { (-(a[0] * d[0] + a[1] * d[1]) / l2).clamp(0.0, 1.0) };
    (a[0] + d[0] * t).hypot(a[1] + d[1] * t)
}
