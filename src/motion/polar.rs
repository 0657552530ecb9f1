//! G12.1 polar coordinate interpolation in the motion layer (manual 004 §2.7).
//!
//! The interpreter sends one [`MoveKind::Polar`](crate::canon::MoveKind::Polar) per block: a
//! line or an arc in the virtual plane of X (radius) and the hypothetical axis C (mm), origin
//! on the rotation centre. Here the path is interpolated *in that plane* at the programmed
//! tangential feed (note 5), and every cycle the virtual point is converted to machine X
//! (`work_x + √(x² + c²)`) and spindle angle C (`c_zero + atan2(c, x)`, continuous: the
//! representative nearest to the last setpoint), so lines and arcs are exact at every
//! setpoint, not chorded beforehand.
//!
//! **The spindle as a Cs axis.** A polar segment first brakes the spindle (as a rigid tap
//! does), then drives it in position. If its stopped angle is not where the program's C puts
//! the start point (the spindle ran in speed mode since C was last positioned; note 10 asks
//! for a positioned spindle), C is first turned there alone at the spindle's limits, by the
//! shorter way. After G13.1 the spindle stays stopped in position until the program's next
//! M03/M04 puts it back in speed mode.
//!
//! **Speed near the centre.** Near the centre a modest tangential feed turns C very fast.
//! The manual (note 9) alarms when the C component exceeds C's maximum — the interpreter
//! checks that for G98 feeds — and Fanuc 0i-TF clamps the feed automatically near the centre.
//! Both hold here: the path speed is limited *at every point* so that C's speed and
//! acceleration and X's speed and acceleration stay within the machine's limits. For a point
//! p moving with speed v along unit tangent t (curvature vector k):
//! - C speed: θ̇ = v·(p×t)/r² → v ≤ ω_max·r²/|p×t|;
//! - C acceleration at constant v: θ̈ = v²·((p×k)/r² − 2(p×t)(p·t)/r⁴);
//! - X speed: ṙ = v·(p·t)/r; X acceleration at constant v: r̈ = v²·((1 + p·k)/r − (p·t)²/r³).
//!
//! The velocity-squared terms get 45 % of C's and X's acceleration, the tangential ramp 50 %
//! (its C share scaled by the segment's smallest r²/|p×t|). The limit varies along the path,
//! so each cycle looks ahead over its braking distance (a fixed number of samples plus the
//! point nearest the centre: O(1)) and brakes for the lowest point in time. A path that
//! passes within [`MIN_CENTRE_MM`] of the centre is refused: C would have to turn 180° at once.
//!
//! Consecutive polar segments whose tangents agree within [`TANGENT_TOL`] (a circle made of
//! two arcs, an arc tangent to a line) are crossed without stopping, at a speed that the next
//! segment can still brake from; corners stop.

use super::{alarms, profile, Entry, Item, Motion, Run, Speed, AX_S, AX_X, AX_Y, AX_Z};
use crate::canon::{polar_to_machine, Feed, Pos};
use crate::Alarm;

/// Look-ahead samples per cycle over the braking distance.
const SAMPLES: usize = 24;
/// Samples of a segment at push (travel, closest approach, tangential acceleration limit).
const PUSH_SAMPLES: usize = 256;
/// Margin under the machine limits for the sampled look-ahead.
const SAFETY: f64 = 0.95;
/// Share of C's and X's acceleration for the velocity-squared terms; the tangential ramp gets
/// [`TANGENTIAL`].
const NORMAL: f64 = 0.45;
const TANGENTIAL: f64 = 0.5;
/// A path closer than this to the rotation centre is refused, mm.
pub const MIN_CENTRE_MM: f64 = 1e-3;
/// Largest tangent change crossed without stopping (0.5°), as |t₁ − t₀|.
const TANGENT_TOL: f64 = 0.0087;

/// One polar segment, planned at push. Virtual coordinates [x, c] in mm; the path parameter
/// `s` runs over `len` = √(virtual length² + Z travel²).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct PolarSeg {
    from: [f64; 2],
    to: [f64; 2],
    /// Arc: centre, start radius, radius change, start angle, signed sweep (rad).
    arc: Option<([f64; 2], f64, f64, f64, f64)>,
    /// Virtual length and path length.
    len_v: f64,
    pub(super) len: f64,
    c_zero: f64,
    work_x: f64,
    y: f64,
    z0: f64,
    z1: f64,
    speed: Speed,
    /// Path speed limit from Z (mm/s); the per-point limits come from `vloc`.
    vlim: f64,
    /// Path acceleration, mm/s².
    alim: f64,
    /// C speed (rad/s) and acceleration share (rad/s²); X speed (mm/s) and acceleration share.
    wc: f64,
    ac: f64,
    vx: f64,
    ax: f64,
    /// Path parameter of the point nearest the centre.
    s_close: f64,
    exact: bool,
}

/// Where a polar segment stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Phase {
    /// Braking the spindle out of speed mode.
    Brake,
    /// Turning C alone from `c0` by `dc` degrees to the start point's angle; `done` degrees
    /// so far at `v` °/s.
    Align { c0: f64, dc: f64, done: f64, v: f64 },
    /// On the path.
    Path,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct PolarRun {
    pub(super) seg: PolarSeg,
    pub(super) phase: Phase,
    s: f64,
    v: f64,
    pub(super) landed: bool,
    /// Speed at which the end is crossed into the next polar segment (0: stop at the end).
    vj: f64,
}

impl PolarRun {
    pub(super) fn new(seg: PolarSeg) -> PolarRun {
        PolarRun { seg, phase: Phase::Brake, s: 0.0, v: 0.0, landed: false, vj: 0.0 }
    }

    /// The spindle is a position axis driven by this segment (no speed ramp).
    pub(super) fn holds_spindle(&self) -> bool {
        self.phase != Phase::Brake
    }
}

fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

impl PolarSeg {
    /// Virtual point, unit tangent, curvature vector and Z at path parameter `s`. At `s ≥ len`
    /// the point is `to` bit for bit.
    fn eval(&self, s: f64) -> ([f64; 2], [f64; 2], [f64; 2], f64) {
        let f = if self.len > 0.0 { (s / self.len).clamp(0.0, 1.0) } else { 1.0 };
        let z = if f >= 1.0 { self.z1 } else { self.z0 + (self.z1 - self.z0) * f };
        match self.arc {
            None => {
                let d = [self.to[0] - self.from[0], self.to[1] - self.from[1]];
                let t = if self.len_v > 0.0 { [d[0] / self.len_v, d[1] / self.len_v] } else { [0.0, 0.0] };
                let p = if f >= 1.0 { self.to } else { [self.from[0] + d[0] * f, self.from[1] + d[1] * f] };
                (p, t, [0.0, 0.0], z)
            }
            Some((c, r0, dr, a0, sweep)) => {
                let a = a0 + sweep * f;
                let r = r0 + dr * f;
                let (sn, cs) = a.sin_cos();
                let p = if f >= 1.0 { self.to } else { [c[0] + r * cs, c[1] + r * sn] };
                let sg = sweep.signum();
                let rr = r.max(1e-12);
                (p, [-sg * sn, sg * cs], [-cs / rr, -sn / rr], z)
            }
        }
    }

    /// Largest path speed at `s` (mm/s) that keeps C's and X's speed and the velocity-squared
    /// parts of their accelerations within limits.
    fn vloc(&self, s: f64) -> f64 {
        if !(self.len_v > 0.0) {
            return f64::INFINITY;
        }
        let (p, t, k, _) = self.eval(s);
        let r2 = dot(p, p);
        if !(r2 > 1e-18) {
            return 0.0;
        }
        let r = r2.sqrt();
        let cr = cross(p, t);
        let dp = dot(p, t);
        let mut v = f64::INFINITY;
        if cr.abs() > 1e-15 {
            v = v.min(self.wc * r2 / cr.abs());
        }
        let kc = cross(p, k) / r2 - 2.0 * cr * dp / (r2 * r2);
        if kc.abs() > 1e-15 {
            v = v.min((self.ac / kc.abs()).sqrt());
        }
        let kx = (1.0 + dot(p, k)) / r - dp * dp / (r2 * r);
        if kx.abs() > 1e-15 {
            v = v.min((self.ax / kx.abs()).sqrt());
        }
        if dp.abs() > 1e-15 {
            v = v.min(self.vx * r / dp.abs());
        }
        // Path speed from the virtual speed (Z moving too).
        v * self.len / self.len_v
    }

    /// Largest speed for this cycle from which every point within the braking distance can be
    /// reached at no more than its local limit (see `profile::v_allowed`).
    fn window_limit(&self, s: f64, v: f64, dv: f64, dt: f64) -> f64 {
        if !(self.len_v > 0.0) {
            return f64::INFINITY;
        }
        let reach = dt * profile::g(v + dv, dv) + (v + dv) * dt;
        let end = (s + reach).min(self.len);
        let mut lim = f64::INFINITY;
        let mut probe = |sj: f64| {
            let vl = self.vloc(sj).min(1e6);
            lim = lim.min(profile::v_allowed((sj - s).max(0.0) + dt * profile::g(vl, dv), dv, dt));
        };
        for j in 0..=SAMPLES {
            probe(s + (end - s) * j as f64 / SAMPLES as f64);
        }
        if self.s_close > s && self.s_close < end {
            probe(self.s_close);
        }
        lim
    }

    /// Unit tangent in (virtual x, virtual c, z) at `s`.
    fn tangent3(&self, s: f64) -> [f64; 3] {
        let (_, t, _, _) = self.eval(s);
        if !(self.len > 0.0) {
            return [0.0; 3];
        }
        let kv = self.len_v / self.len;
        [t[0] * kv, t[1] * kv, (self.z1 - self.z0) / self.len]
    }

    /// Machine X (radius) and C at `s`, C nearest `near_c`.
    fn machine(&self, s: f64, near_c: f64) -> (f64, f64, f64) {
        let (p, _, _, z) = self.eval(s);
        let (x, c) = polar_to_machine(p, self.c_zero, self.work_x, near_c);
        (x, c, z)
    }
}

/// A polar arc's centre, start radius, radius change, start angle and sweep; its radii must
/// agree within `tol` (PS0020).
fn polar_arc(from: [f64; 2], to: [f64; 2], c: [f64; 2], cw: bool, tol: f64) -> Result<([f64; 2], f64, f64, f64, f64), Alarm> {
    let r0 = (from[0] - c[0]).hypot(from[1] - c[1]);
    let r1 = (to[0] - c[0]).hypot(to[1] - c[1]);
    if !(r0 > 0.0 && r1 > 0.0) {
        return Err(Alarm::new(alarms::BAD_VALUE, "polar arc with zero radius: correct R"));
    }
    if (r0 - r1).abs() > tol {
        return Err(Alarm::new(
            alarms::ARC_RADIUS,
            format!("polar arc radius differs between start ({r0:.4}) and end ({r1:.4}) by more than {tol} mm; correct R or the end point"),
        ));
    }
    let (a0, sweep) = crate::canon::arc_sweep(from, to, c, cw);
    Ok((c, r0, r1 - r0, a0, sweep))
}

/// How a polar path lies around the rotation centre.
struct Extent {
    rmin: f64,
    rmax: f64,
    /// Arc length at the closest approach.
    s_close: f64,
    /// The smallest r²/|p×t| (the tangential ramp's share of C's acceleration).
    rc_min: f64,
}

/// Along the path: the radii X takes (travel), the closest approach to the centre, and the
/// smallest r²/|p×t| — sampled, plus the exact closest point of a line or an arc.
fn path_extent(seg: &PolarSeg) -> Extent {
    let (len, len_v, from, to) = (seg.len, seg.len_v, seg.from, seg.to);
    let mut x = Extent { rmin: f64::INFINITY, rmax: 0.0, s_close: 0.0, rc_min: f64::INFINITY };
    let mut probe = |s: f64| {
        let (p, t, _, _) = seg.eval(s);
        let r = p[0].hypot(p[1]);
        if r < x.rmin {
            x.rmin = r;
            x.s_close = s;
        }
        x.rmax = x.rmax.max(r);
        let cr = cross(p, t).abs();
        if cr > 0.0 {
            x.rc_min = x.rc_min.min(r * r / cr);
        }
    };
    for j in 0..=PUSH_SAMPLES {
        probe(len * j as f64 / PUSH_SAMPLES as f64);
    }
    match seg.arc {
        None => {
            let d = [to[0] - from[0], to[1] - from[1]];
            let u = -dot(from, d) / (len_v * len_v).max(1e-300);
            if (0.0..=1.0).contains(&u) {
                probe(u * len);
            }
        }
        Some((c, _, _, a0, sweep)) => {
            let toward = (-c[1]).atan2(-c[0]);
            let rel = if sweep >= 0.0 { (toward - a0).rem_euclid(std::f64::consts::TAU) } else { (a0 - toward).rem_euclid(std::f64::consts::TAU) };
            if rel <= sweep.abs() {
                probe(len * rel / sweep.abs());
            }
        }
    }
    x
}

impl Motion {
    /// Plan a G12.1 segment. Refuses a machine without a Cs spindle, a feed per revolution
    /// (the spindle is the C axis), non-finite values, an arc whose radii differ, X beyond its
    /// travel anywhere along the path, and a path through the centre.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn polar_seg(
        &self,
        end: &Pos,
        from: [f64; 2],
        to: [f64; 2],
        center: Option<[f64; 2]>,
        cw: bool,
        c_zero: f64,
        feed: &Feed,
        work_x: f64,
        exact: bool,
    ) -> Result<PolarSeg, Alarm> {
        let l = &self.lim;
        if !l.present[AX_S] {
            return Err(Alarm::new(
                alarms::UNSUPPORTED,
                "G12.1 polar coordinate interpolation drives the spindle as the C axis, and this machine has no spindle: add a spindle axis to the config or remove G12.1",
            ));
        }
        let speed = match *feed {
            Feed::PerRev(_) => {
                return Err(Alarm::new(
                    alarms::BAD_VALUE,
                    "feed per revolution (G99) in polar coordinate interpolation: the spindle is the C axis there and does not turn; program G98 and F in mm/min",
                ))
            }
            Feed::PerMin(_) => self.check_feed(feed)?,
        };
        let finite = from.iter().chain(to.iter()).chain(center.iter().flatten()).all(|v| v.is_finite());
        if !(finite && c_zero.is_finite() && work_x.is_finite()) {
            return Err(Alarm::new(alarms::BAD_VALUE, "polar interpolation point is not a finite number"));
        }
        let e = self.check_end(&Pos { c: self.plan_c.unwrap_or(end.c), ..*end })?;
        let (z0, z1) = (self.plan_end[AX_Z], e[AX_Z]);
        let arc = match center {
            None => None,
            Some(c) => Some(polar_arc(from, to, c, cw, l.arc_radius_tol)?),
        };
        let len_v = match arc {
            None => (to[0] - from[0]).hypot(to[1] - from[1]),
            Some((_, r0, dr, _, sweep)) => (r0 + dr / 2.0) * sweep.abs(),
        };
        let dz = z1 - z0;
        let len = len_v.hypot(dz);
        let deg = std::f64::consts::PI / 180.0;
        let mut seg = PolarSeg {
            from,
            to,
            arc,
            len_v,
            len,
            c_zero,
            work_x,
            y: self.plan_end[AX_Y],
            z0,
            z1,
            speed,
            vlim: f64::INFINITY,
            alim: f64::INFINITY,
            wc: SAFETY * l.vmax[AX_S] * deg,
            ac: NORMAL * l.amax[AX_S] * deg,
            vx: SAFETY * l.vmax[AX_X],
            ax: NORMAL * l.amax[AX_X],
            s_close: 0.0,
            exact,
        };
        if !(len > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, "polar interpolation move of zero length"));
        }
        let Extent { rmin, rmax, s_close, rc_min } = path_extent(&seg);
        self.check_axis(AX_X, work_x + rmax, "polar path")?;
        self.check_axis(AX_X, work_x + rmin, "polar path")?;
        if len_v > 0.0 && rmin < MIN_CENTRE_MM {
            return Err(Alarm::new(
                alarms::BAD_VALUE,
                format!("this polar interpolation move passes {rmin:.4} mm from the rotation centre: C would have to turn 180° at once there; keep the path at least {MIN_CENTRE_MM} mm away (§2.7 note 9)"),
            ));
        }
        seg.s_close = s_close;
        let kv = len_v / len;
        // Path acceleration: C's tangential share at the tightest point, X's, Z's.
        let mut a = TANGENTIAL * l.amax[AX_X];
        if rc_min.is_finite() {
            a = a.min(TANGENTIAL * l.amax[AX_S] * deg * rc_min);
        }
        let mut a_path = if kv > 0.0 { a / kv } else { f64::INFINITY };
        let mut v_path = f64::INFINITY;
        if dz.abs() > 0.0 {
            let uz = dz.abs() / len;
            a_path = a_path.min(l.amax[AX_Z] / uz);
            v_path = v_path.min(l.vmax[AX_Z] / uz);
        }
        seg.alim = if a_path.is_finite() { a_path.max(0.0) } else { 0.0 };
        seg.vlim = v_path;
        if !(seg.alim > 0.0) {
            return Err(Alarm::new(alarms::BAD_VALUE, "polar interpolation move with no usable acceleration (check the axis limits)"));
        }
        Ok(seg)
    }

    /// The commanded path speed (mm/s) of a polar segment this cycle.
    fn polar_v_cmd(&self, seg: &PolarSeg) -> f64 {
        if self.held || self.stopping {
            return 0.0;
        }
        match seg.speed {
            Speed::PerMin(f) => (f * self.feed_ovr).min(self.lim.feed_clamp).min(seg.vlim),
            _ => 0.0,
        }
    }

    /// Speed at which `seg`'s end may be crossed into the next queued polar segment: tangent
    /// continuous, same plane, both local limits there, and low enough that the next segment
    /// can brake within its own look-ahead. 0: stop at the end.
    fn polar_junction(&self, seg: &PolarSeg) -> f64 {
        let dt = self.lim.cycle_s;
        if seg.exact || self.single_block {
            return 0.0;
        }
        let Some(Entry { item: Item::Polar(next), .. }) = self.peek() else { return 0.0 };
        if next.c_zero != seg.c_zero || next.work_x != seg.work_x || next.from != seg.to {
            return 0.0;
        }
        let (t1, t0) = (seg.tangent3(seg.len), next.tangent3(0.0));
        let du = (0..3).map(|i| (t1[i] - t0[i]).abs()).fold(0.0f64, f64::max);
        if du > TANGENT_TOL {
            return 0.0;
        }
        let mut v = seg.vlim.min(next.vlim).min(seg.vloc(seg.len)).min(next.vloc(0.0)).min(next.len / dt);
        let a = seg.alim.min(next.alim);
        if du > 1e-12 {
            v = v.min(0.25 * a * dt / du);
        }
        let ndv = next.alim * dt;
        let vmax = self.polar_v_cmd(&next).max(ndv);
        v = v.min(next.window_limit(0.0, vmax.min(v), ndv, dt));
        v = v.min(profile::v_allowed(next.len, ndv, dt));
        let v = SAFETY * v;
        if v.is_finite() && v > seg.alim * dt {
            v
        } else {
            0.0
        }
    }

    /// One cycle of a polar segment; returns the path speed (mm/s).
    pub(super) fn step_polar(&mut self, r: PolarRun) -> f64 {
        let dt = self.lim.cycle_s;
        let prev_c = self.pos[AX_S];
        let seg = r.seg;
        match r.phase {
            Phase::Brake => {
                // Out of speed mode: brake (step_spindle), then drive the spindle in position.
                self.sp_dir = 0.0;
                self.sp_css = None;
                if self.stopping {
                    self.run = Run::None;
                } else if self.sp_cur == 0.0 {
                    let (_, c, _) = seg.machine(0.0, self.pos[AX_S]);
                    let dc = c - self.pos[AX_S];
                    let phase = if dc.abs() > 1e-9 { Phase::Align { c0: self.pos[AX_S], dc, done: 0.0, v: 0.0 } } else { Phase::Path };
                    self.run = Run::Polar(PolarRun { phase, vj: self.polar_junction(&seg), ..r });
                }
                0.0
            }
            Phase::Align { c0, dc, done, v } => {
                let len = dc.abs();
                let d = len - done;
                let v_cmd = if self.stopping { 0.0 } else { self.lim.vmax[AX_S] };
                let nv = profile::next_speed(v, v_cmd, d, self.lim.amax[AX_S] * dt, dt);
                let fin = d - nv * dt <= 1e-9;
                let done = if fin { len } else { done + nv * dt };
                self.pos[AX_S] = if fin { c0 + dc } else { c0 + done.copysign(dc) };
                self.sp_cur = (self.pos[AX_S] - prev_c) / dt / 6.0;
                if self.stopping && nv == 0.0 && !fin {
                    self.sp_cur = 0.0;
                    self.run = Run::None;
                } else {
                    let phase = if fin { Phase::Path } else { Phase::Align { c0, dc, done, v: nv } };
                    if fin {
                        self.sp_cur = 0.0;
                    }
                    self.run = Run::Polar(PolarRun { phase, ..r });
                }
                0.0
            }
            Phase::Path if r.landed => {
                // One cycle at rest on the end point, the spindle held in position.
                self.sp_cur = 0.0;
                self.run = Run::None;
                self.block_end();
                0.0
            }
            Phase::Path => {
                let d = seg.len - r.s;
                let dv = seg.alim * dt;
                let v_cmd = self.polar_v_cmd(&seg).min(seg.window_limit(r.s, r.v, dv, dt));
                let ext = if r.vj > 0.0 { dt * profile::g(r.vj, dv) } else { 0.0 };
                let nv = profile::next_speed(r.v, v_cmd, d + ext, dv, dt);
                let reach = d - nv * dt <= 1e-9;
                if reach && r.vj > 0.0 {
                    if let Some(Entry { item: Item::Polar(next), line, cyc }) = self.peek() {
                        // Cross the tangent junction within this cycle, onto the next segment.
                        self.pop();
                        self.line = line;
                        self.cur_cyc = cyc;
                        let s2 = (nv * dt - d).max(0.0).min(next.len);
                        let vj = self.polar_junction(&next);
                        self.polar_place(&next, s2, prev_c);
                        self.run = Run::Polar(PolarRun { seg: next, phase: Phase::Path, s: s2, v: nv, landed: false, vj });
                        return nv;
                    }
                }
                let (s2, landed) = if reach { (seg.len, true) } else { (r.s + nv * dt, false) };
                self.polar_place(&seg, s2, prev_c);
                if self.stopping && nv == 0.0 && !landed {
                    self.sp_cur = 0.0;
                    self.run = Run::None;
                } else {
                    self.run = Run::Polar(PolarRun { s: s2, v: nv, landed, ..r });
                }
                if landed {
                    d / dt
                } else {
                    nv
                }
            }
        }
    }

    /// Set X, Y, Z and C to the segment's point at `s`.
    fn polar_place(&mut self, seg: &PolarSeg, s: f64, prev_c: f64) {
        let dt = self.lim.cycle_s;
        let (x, c, z) = seg.machine(s, prev_c);
        self.pos[AX_X] = x;
        self.pos[AX_Y] = seg.y;
        self.pos[AX_Z] = z;
        self.pos[AX_S] = c;
        self.sp_cur = (c - prev_c) / dt / 6.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canon::{Move, MoveKind, SrcPos};
    use crate::motion::{Feedback, Limits, N_AXES};
    use std::sync::Arc;

    fn lim() -> Limits {
        let cfg = crate::config::MachineConfig::embedded();
        Limits::from_config(&cfg)
    }

    fn polar(from: [f64; 2], to: [f64; 2], center: Option<[f64; 2]>, cw: bool, f: f64, line: u32) -> Move {
        let (x, c) = polar_to_machine(to, 0.0, 0.0, 0.0);
        Move {
            src: SrcPos::new(Arc::from("p.nc"), line, 1),
            kind: MoveKind::Polar { end: Pos { x, c, ..Pos::ZERO }, from, to, center, cw, c_zero: 0.0, feed: Feed::PerMin(f) },
            exact_stop: false,
            work_offset: Pos::ZERO,
            tag: None,
        }
    }

    /// Ideal drives: every setpoint, converted back to the virtual plane, is on the line;
    /// C's speed stays within its limit through the near-centre clamp.
    #[test]
    fn line_near_the_centre_is_exact_and_clamped() {
        let mut l = lim();
        l.vmax[AX_S] = 360.0; // 60 rpm
        let mut m = Motion::new(l.clone(), [20.0, 0.0, 0.0, 0.0]);
        // y = 1: passes 1 mm from the centre; F3000 would turn C at 2865 °/s there.
        m.push(&polar([20.0, 0.0], [20.0, 1.0], None, false, 3000.0, 1)).unwrap();
        m.push(&polar([20.0, 1.0], [-20.0, 1.0], None, false, 3000.0, 2)).unwrap();
        let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
        let mut prev = m.position();
        let (mut worst, mut wmax, mut vmax_far) = (0.0f64, 0.0f64, 0.0f64);
        for _ in 0..20000 {
            let sp = m.step(&fb);
            fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
            let a = sp.pos[AX_S].to_radians();
            let p = [sp.pos[AX_X] * a.cos(), sp.pos[AX_X] * a.sin()];
            if sp.line == 2 {
                worst = worst.max((p[1] - 1.0).abs());
                if p[0].abs() > 15.0 && p[0].abs() < 18.0 {
                    vmax_far = vmax_far.max(sp.path_feed);
                }
            }
            wmax = wmax.max((sp.pos[AX_S] - prev[AX_S]).abs() / l.cycle_s);
            prev = sp.pos;
            if m.is_idle() {
                break;
            }
        }
        assert!(m.is_idle());
        assert!(worst < 1e-9, "off the line by {worst}");
        assert!(wmax <= 360.0 * 1.001, "C at {wmax} °/s");
        // Far from the centre (15–18 mm) the programmed feed: C turns at v·d/r² ≤ 0.22 rad/s
        // there, well inside its 6.3 rad/s.
        assert!((vmax_far - 3000.0).abs() < 1e-6, "far from the centre {vmax_far} mm/min");
        assert!((prev[AX_X] - 20.0249).abs() < 1e-3, "ends at radius {}", prev[AX_X]);
        let _ = N_AXES;
    }

    /// Feed hold brakes on the path and resumes on cycle start; a controlled stop ends on the
    /// path with the spindle held; every setpoint on the line, C within its limits.
    #[test]
    fn feed_hold_and_stop_stay_on_the_path() {
        let l = lim();
        let dt = l.cycle_s;
        for stop in [false, true] {
            let mut m = Motion::new(l.clone(), [30.0, 0.0, 0.0, 0.0]);
            m.push(&polar([30.0, 0.0], [30.0, 5.0], None, false, 3000.0, 1)).unwrap();
            m.push(&polar([30.0, 5.0], [-30.0, 5.0], None, false, 3000.0, 2)).unwrap();
            let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
            let (mut prev, mut v_prev) = (m.position(), 0.0);
            let (mut worst, mut held_at, mut amax) = (0.0f64, None, 0.0f64);
            for k in 0..20000 {
                if k == 600 {
                    if stop {
                        m.stop();
                    } else {
                        m.feed_hold();
                    }
                }
                if k == 1200 && !stop {
                    assert!(m.is_held());
                    held_at = Some(m.position());
                    m.cycle_start();
                }
                let sp = m.step(&fb);
                fb = Feedback { pos: sp.pos, spindle_rpm: sp.spindle_rpm, ..Default::default() };
                let p = [sp.pos[AX_X] * sp.pos[AX_S].to_radians().cos(), sp.pos[AX_X] * sp.pos[AX_S].to_radians().sin()];
                if sp.line == 2 {
                    worst = worst.max((p[1] - 5.0).abs());
                }
                let v = (sp.pos[AX_S] - prev[AX_S]) / dt;
                amax = amax.max(((v - v_prev) / dt).abs());
                (prev, v_prev) = (sp.pos, v);
                if m.is_idle() && k > 1300 {
                    break;
                }
            }
            assert!(m.is_idle());
            assert!(worst < 1e-9, "off the line by {worst}");
            assert!(amax <= l.amax[AX_S] * 1.001, "C accelerated at {amax} °/s²");
            let a = m.position()[AX_S].to_radians();
            let end = [m.position()[AX_X] * a.cos(), m.position()[AX_X] * a.sin()];
            if stop {
                // Stopped part-way along line 2 (10 mm/s² … 50 mm/s: well before its end).
                assert!(end[0] > -29.0 && (end[1] - 5.0).abs() < 1e-9, "stopped at {end:?}");
            } else {
                let h = held_at.expect("held");
                let ha = h[AX_S].to_radians();
                assert!((h[AX_X] * ha.sin() - 5.0).abs() < 1e-9, "held off the path");
                assert!((end[0] + 30.0).abs() < 1e-9 && (end[1] - 5.0).abs() < 1e-9, "ended at {end:?}");
            }
        }
    }

    #[test]
    fn through_the_centre_and_g99_are_refused() {
        let mut m = Motion::new(lim(), [20.0, 0.0, 0.0, 0.0]);
        let e = m.push(&polar([20.0, 0.0], [-20.0, 0.0], None, false, 100.0, 1)).unwrap_err();
        assert!(e.message.contains("from the rotation centre"), "{e}");
        let mut mv = polar([20.0, 0.0], [20.0, 5.0], None, false, 100.0, 1);
        if let MoveKind::Polar { feed, .. } = &mut mv.kind {
            *feed = Feed::PerRev(0.1);
        }
        let e = m.push(&mv).unwrap_err();
        assert!(e.message.contains("G99"), "{e}");
    }
}
