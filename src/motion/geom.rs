//! Path geometry of one segment, parameterised by arc length `s ∈ [0, len]`.
//! Only X, Y, Z (indices 0..3) move along a path; the spindle has its own ramp.

/// A straight line or a circular (possibly helical or slightly spiral) arc.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Geom {
    Line {
        start: [f64; 3],
        delta: [f64; 3],
        end: [f64; 3],
        len: f64,
    },
    /// In the plane of axes `ia`, `ib` (angle measured from `ia` towards `ib`); `ic` is the
    /// third axis, moving linearly with the angle (helix). The radius goes linearly from `r0`
    /// to `r0 + dr`, so that the arc ends exactly on its end point even when the programmed
    /// radii differ by a rounding error.
    Arc {
        ia: usize,
        ib: usize,
        ic: usize,
        ca: f64,
        cb: f64,
        r0: f64,
        dr: f64,
        th0: f64,
        sweep: f64,
        c0: f64,
        dc: f64,
        end: [f64; 3],
        len: f64,
    },
}

impl Geom {
    pub fn len(&self) -> f64 {
        match self {
            Geom::Line { len, .. } | Geom::Arc { len, .. } => *len,
        }
    }

    pub fn end(&self) -> [f64; 3] {
        match self {
            Geom::Line { end, .. } | Geom::Arc { end, .. } => *end,
        }
    }

    /// The point at arc length `s`. At `s ≥ len` it is the end point bit for bit, so a segment
    /// never leaves a rounding residue for the drives.
    pub fn at(&self, s: f64) -> [f64; 3] {
        let len = self.len();
        if !(s < len) {
            return self.end();
        }
        let f = if len > 0.0 { (s / len).max(0.0) } else { 1.0 };
        match *self {
            Geom::Line { start, delta, .. } => {
                // start + delta·f: an axis that does not move (delta = 0) keeps its exact value.
                [start[0] + delta[0] * f, start[1] + delta[1] * f, start[2] + delta[2] * f]
            }
            Geom::Arc { ia, ib, ic, ca, cb, r0, dr, th0, sweep, c0, dc, .. } => {
                let th = th0 + sweep * f;
                let r = r0 + dr * f;
                let mut p = [0.0; 3];
                p[ia] = ca + r * th.cos();
                p[ib] = cb + r * th.sin();
                p[ic] = c0 + dc * f;
                p
            }
        }
    }
}

impl Geom {
    /// Unit tangents (direction of travel) at the start and at the end.
    pub fn tangents(&self) -> ([f64; 3], [f64; 3]) {
        match *self {
            Geom::Line { delta, len, .. } => {
                if len > 0.0 {
                    let u = [delta[0] / len, delta[1] / len, delta[2] / len];
                    (u, u)
                } else {
                    ([0.0; 3], [0.0; 3])
                }
            }
            Geom::Arc { ia, ib, ic, r0, dr, th0, sweep, dc, .. } => {
                // d/df of (r cos θ, r sin θ, c) with θ = th0 + sweep·f, r = r0 + dr·f.
                let tan = |f: f64| {
                    let (th, r) = (th0 + sweep * f, r0 + dr * f);
                    let mut t = [0.0; 3];
                    t[ia] = dr * th.cos() - r * sweep * th.sin();
                    t[ib] = dr * th.sin() + r * sweep * th.cos();
                    t[ic] = dc;
                    let n = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
                    if n > 0.0 {
                        [t[0] / n, t[1] / n, t[2] / n]
                    } else {
                        [0.0; 3]
                    }
                };
                (tan(0.0), tan(1.0))
            }
        }
    }
}

/// Build an arc from its start, end and centre (all X, Y, Z), the plane axes (`ia`, `ib`,
/// third `ic`) and the sense. `cw` is clockwise seen from the positive third axis looking
/// down on the (`ia`, `ib`) plane, i.e. a negative angle. Returns `None` for a degenerate arc
/// (zero radius). A start equal to the end gives a full circle.
pub fn arc(start: [f64; 3], end: [f64; 3], center: [f64; 3], (ia, ib, ic): (usize, usize, usize), cw: bool) -> Option<(Geom, f64, f64)> {
    let (ca, cb) = (center[ia], center[ib]);
    let (sa, sb) = (start[ia] - ca, start[ib] - cb);
    let (ea, eb) = (end[ia] - ca, end[ib] - cb);
    let r0 = sa.hypot(sb);
    let r1 = ea.hypot(eb);
    if !(r0 > 1e-9 && r1 > 1e-9) {
        return None;
    }
    let th0 = sb.atan2(sa);
    let th1 = eb.atan2(ea);
    let tau = std::f64::consts::TAU;
    let same = (start[ia] - end[ia]).abs() < 1e-9 && (start[ib] - end[ib]).abs() < 1e-9;
    let sweep = if cw {
        let mut d = th0 - th1; // positive amount turned clockwise
        d = d.rem_euclid(tau);
        if same || d < 1e-12 {
            d = tau;
        }
        -d
    } else {
        let mut d = (th1 - th0).rem_euclid(tau);
        if same || d < 1e-12 {
            d = tau;
        }
        d
    };
    let dc = end[ic] - start[ic];
    let planar = 0.5 * (r0 + r1) * sweep.abs();
    let len = planar.hypot(dc);
    let g = Geom::Arc { ia, ib, ic, ca, cb, r0, dr: r1 - r0, th0, sweep, c0: start[ic], dc, end, len };
    Some((g, r0, r1))
}

/// A straight line from `start` to `end`.
pub fn line(start: [f64; 3], end: [f64; 3]) -> Geom {
    let delta = [end[0] - start[0], end[1] - start[1], end[2] - start[2]];
    let len = (delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2]).sqrt();
    Geom::Line { start, delta, end, len }
}
