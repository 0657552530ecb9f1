//! Chamfer `,C` and corner R `,R` between two moves (manual §2.23), in plane coordinates
//! (u, v) where counter-clockwise is G03.
//!
//! Chamfer: the chamfer's ends lie at distance C from the virtual corner, along a line or —
//! on an arc — where the circle of radius C about the corner meets the arc (the manual
//! defines C only as a distance from the virtual corner). Corner R: a circle of radius R
//! tangent to both paths, on the inside of the turn. Within ±1° of a straight continuation
//! nothing is inserted (§2.23 note 5).

pub use super::vec2::P;
use super::vec2::{add, cross, dot, left, mul, norm, sub, unit};

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Seg {
    Line { a: P, b: P },
    Arc { a: P, b: P, c: P, cw: bool },
}

/// What to insert: the first move now ends at `p1`, the inserted move runs `p1 → p2`
/// (a line, or an arc about `center` with direction `cw`), the second move starts at `p2`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cut {
    pub p1: P,
    pub p2: P,
    pub arc: Option<(P, bool)>,
}

impl Seg {
    fn start(&self) -> P {
        match *self {
            Seg::Line { a, .. } | Seg::Arc { a, .. } => a,
        }
    }
    fn end(&self) -> P {
        match *self {
            Seg::Line { b, .. } | Seg::Arc { b, .. } => b,
        }
    }
    /// Unit direction of travel at point `p` of the path.
    fn tangent(&self, p: P) -> P {
        match *self {
            Seg::Line { a, b } => unit(sub(b, a)),
            Seg::Arc { c, cw, .. } => {
                let t = unit(left(sub(p, c)));
                if cw {
                    mul(t, -1.0)
                } else {
                    t
                }
            }
        }
    }
    /// Travelled fraction 0…1 of point `p` (which lies on the path's line/circle).
    fn param(&self, p: P) -> f64 {
        match *self {
            Seg::Line { a, b } => {
                let d = sub(b, a);
                let l2 = dot(d, d);
                if l2 < 1e-18 {
                    0.0
                } else {
                    dot(sub(p, a), d) / l2
                }
            }
            Seg::Arc { a, b, c, cw } => {
                let ang = |q: P| {
                    let (x, y) = sub(q, c);
                    y.atan2(x)
                };
                let tau = std::f64::consts::TAU;
                let dir = if cw { -1.0 } else { 1.0 };
                let sweep = {
                    let s = ((ang(b) - ang(a)) * dir).rem_euclid(tau);
                    if s < 1e-12 {
                        tau
                    } else {
                        s
                    }
                };
                let mut t = ((ang(p) - ang(a)) * dir).rem_euclid(tau);
                // A point just before the start (rounding) counts as the start.
                if t > tau - 1e-9 {
                    t = 0.0;
                }
                t / sweep
            }
        }
    }
}

/// Intersections of the circle (c, r) with the circle (k, d).
fn circle_circle(c: P, r: f64, k: P, d: f64) -> Vec<P> {
    let v = sub(k, c);
    let l = norm(v);
    if l < 1e-12 || l > r + d + 1e-9 || l < (r - d).abs() - 1e-9 {
        return vec![];
    }
    let a = (r * r - d * d + l * l) / (2.0 * l);
    let h = (r * r - a * a).max(0.0).sqrt();
    let m = add(c, mul(v, a / l));
    let n = mul(left(unit(v)), h);
    vec![add(m, n), sub(m, n)]
}

/// Intersections of the line through `p` with direction `t` (unit) and the circle (c, r).
fn line_circle(p: P, t: P, c: P, r: f64) -> Vec<P> {
    let f = sub(p, c);
    let b = dot(f, t);
    let disc = b * b - (dot(f, f) - r * r);
    if disc < -1e-9 {
        return vec![];
    }
    let s = disc.max(0.0).sqrt();
    vec![add(p, mul(t, -b + s)), add(p, mul(t, -b - s))]
}

const FLAT: f64 = 1.0; // degrees, §2.23 note 5

fn turn(s1: &Seg, s2: &Seg) -> f64 {
    let k = s1.end();
    let (t1, t2) = (s1.tangent(k), s2.tangent(k));
    cross(t1, t2).atan2(dot(t1, t2)).to_degrees()
}

fn on(seg: &Seg, p: P, what: &str) -> Result<(), String> {
    let t = seg.param(p);
    if !(-1e-9..=1.0 + 1e-9).contains(&t) {
        return Err(format!("the {what} does not fit on the neighbouring move: the move is too short"));
    }
    Ok(())
}

/// Point of `seg` at distance `d` from `k` (= one of its ends), on the side `toward`.
fn at_distance(seg: &Seg, k: P, d: f64, backward: bool) -> Result<P, String> {
    let p = match *seg {
        Seg::Line { .. } => {
            let t = seg.tangent(k);
            add(k, mul(t, if backward { -d } else { d }))
        }
        Seg::Arc { c, .. } => {
            let r = norm(sub(k, c));
            let t = seg.tangent(k);
            let want = if backward { mul(t, -1.0) } else { t };
            circle_circle(c, r, k, d)
                .into_iter()
                .max_by(|x, y| dot(sub(*x, k), want).total_cmp(&dot(sub(*y, k), want)))
                .ok_or_else(|| format!("chamfer {d} is larger than the arc's diameter"))?
        }
    };
    on(seg, p, "chamfer")?;
    Ok(p)
}

/// Chamfer of length `c` (from the virtual corner) between `s1` and `s2` (s1 ends where s2
/// starts). `None` when the paths continue straight (within ±1°).
pub fn chamfer(s1: &Seg, s2: &Seg, c: f64) -> Result<Option<Cut>, String> {
    if c <= 0.0 || turn(s1, s2).abs() <= FLAT {
        return Ok(None);
    }
    let k = s1.end();
    let p1 = at_distance(s1, k, c, true)?;
    let p2 = at_distance(s2, k, c, false)?;
    Ok(Some(Cut { p1, p2, arc: None }))
}

/// Offset of a path by `d` to its left: a line (point, unit direction) or a circle.
enum Off {
    Line(P, P),
    Circle(P, f64),
}

fn offset(seg: &Seg, d: f64) -> Result<Off, String> {
    match *seg {
        Seg::Line { a, b } => {
            let t = unit(sub(b, a));
            Ok(Off::Line(add(a, mul(left(t), d)), t))
        }
        Seg::Arc { a, c, cw, .. } => {
            let r = norm(sub(a, c));
            // Left of a CCW arc is toward its centre.
            let r2 = if cw { r + d } else { r - d };
            if r2 <= 1e-9 {
                return Err(format!("corner R{} is larger than the radius of the arc next to it", d.abs()));
            }
            Ok(Off::Circle(c, r2))
        }
    }
}

/// Corner radius `r` between `s1` and `s2`. `None` when the paths continue straight.
pub fn round(s1: &Seg, s2: &Seg, r: f64) -> Result<Option<Cut>, String> {
    let turn = turn(s1, s2);
    if r <= 0.0 || turn.abs() <= FLAT {
        return Ok(None);
    }
    let k = s1.end();
    // Left turn: the rounding circle lies left of both paths.
    let side = if turn > 0.0 { 1.0 } else { -1.0 };
    let (o1, o2) = (offset(s1, side * r)?, offset(s2, side * r)?);
    let cands = match (&o1, &o2) {
        (Off::Line(p, t), Off::Line(q, u)) => {
            let den = cross(*t, *u);
            if den.abs() < 1e-12 {
                vec![]
            } else {
                let s = cross(sub(*q, *p), *u) / den;
                vec![add(*p, mul(*t, s))]
            }
        }
        (Off::Line(p, t), Off::Circle(c, rr)) | (Off::Circle(c, rr), Off::Line(p, t)) => line_circle(*p, *t, *c, *rr),
        (Off::Circle(c1, r1), Off::Circle(c2, r2)) => circle_circle(*c1, *r1, *c2, *r2),
    };
    let o = cands
        .into_iter()
        .min_by(|x, y| norm(sub(*x, k)).total_cmp(&norm(sub(*y, k))))
        .ok_or_else(|| format!("no corner R{r} fits between these moves"))?;
    let foot = |seg: &Seg| match *seg {
        Seg::Line { a, b } => {
            let t = unit(sub(b, a));
            add(a, mul(t, dot(sub(o, a), t)))
        }
        Seg::Arc { a, c, .. } => {
            let rr = norm(sub(a, c));
            add(c, mul(unit(sub(o, c)), rr))
        }
    };
    let (p1, p2) = (foot(s1), foot(s2));
    on(s1, p1, "corner R")?;
    on(s2, p2, "corner R")?;
    let _ = s2.start();
    Ok(Some(Cut { p1, p2, arc: Some((o, side < 0.0)) }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn near(a: P, b: P) -> bool {
        norm(sub(a, b)) < 1e-9
    }

    #[test]
    fn line_line_chamfer_and_round() {
        // Along −Z at radius 20, then up to radius 30 (a 90° turn).
        let s1 = Seg::Line { a: (0.0, 20.0), b: (-10.0, 20.0) };
        let s2 = Seg::Line { a: (-10.0, 20.0), b: (-10.0, 30.0) };
        let c = chamfer(&s1, &s2, 2.0).unwrap().unwrap();
        assert!(near(c.p1, (-8.0, 20.0)) && near(c.p2, (-10.0, 22.0)));
        let r = round(&s1, &s2, 2.0).unwrap().unwrap();
        assert!(near(r.p1, (-8.0, 20.0)) && near(r.p2, (-10.0, 22.0)));
        let (o, cw) = r.arc.unwrap();
        assert!(near(o, (-8.0, 22.0)));
        assert!(cw, "turning right (from −Z to +X in (Z, X)) is clockwise");
        assert!(chamfer(&s1, &s2, 11.0).is_err());
        // Straight on: nothing inserted.
        let s3 = Seg::Line { a: (-10.0, 20.0), b: (-20.0, 20.1) };
        assert_eq!(chamfer(&s1, &s3, 1.0).unwrap(), None);
    }

    #[test]
    fn line_arc_round_is_tangent() {
        let s1 = Seg::Line { a: (0.0, 0.0), b: (10.0, 0.0) };
        // Quarter circle CCW of radius 10 about (10, 10)... starting at (10,0) going right-up:
        // CCW about (20, 0)? Use a CW arc about (10, -10) turning right.
        let s2 = Seg::Arc { a: (10.0, 0.0), b: (20.0, -10.0), c: (10.0, -10.0), cw: true };
        let r = round(&s1, &s2, 1.0);
        // Tangent continuation (0°): nothing inserted.
        assert_eq!(r.unwrap(), None);
        let s2 = Seg::Arc { a: (10.0, 0.0), b: (0.0, 10.0), c: (0.0, 0.0), cw: false };
        let r = round(&s1, &s2, 1.0).unwrap().unwrap();
        let (o, _) = r.arc.unwrap();
        // Tangent to the line: centre 1 above it; tangent to the circle: 9 from its centre.
        assert!((o.1 - 1.0).abs() < 1e-9);
        assert!((norm(o) - 9.0).abs() < 1e-9);
        assert!((norm(sub(r.p1, o)) - 1.0).abs() < 1e-9 && (norm(sub(r.p2, o)) - 1.0).abs() < 1e-9);
    }
}
