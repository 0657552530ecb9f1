//! Points and vectors of a plane as `(u, v)` pairs, for the contour geometry of chamfer /
//! corner R and nose-radius compensation.

pub type P = (f64, f64);

pub fn sub(a: P, b: P) -> P {
    (a.0 - b.0, a.1 - b.1)
}
pub fn add(a: P, b: P) -> P {
    (a.0 + b.0, a.1 + b.1)
}
pub fn mul(a: P, k: f64) -> P {
    (a.0 * k, a.1 * k)
}
pub fn dot(a: P, b: P) -> f64 {
    a.0 * b.0 + a.1 * b.1
}
pub fn cross(a: P, b: P) -> f64 {
    a.0 * b.1 - a.1 * b.0
}
pub fn norm(a: P) -> f64 {
    a.0.hypot(a.1)
}
/// The unit vector along `a`; zero for a zero-length `a`.
pub fn unit(a: P) -> P {
    let n = norm(a);
    if n < 1e-12 {
        (0.0, 0.0)
    } else {
        (a.0 / n, a.1 / n)
    }
}
/// Left normal (90° counter-clockwise).
pub fn left(a: P) -> P {
    (-a.1, a.0)
}
