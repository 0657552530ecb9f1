//! Ellipse (G02.1/G03.1, manual §2.4) and parabola (G02.2/G03.2, §2.5) as chains of points
//! in the plane coordinates (u, v) = (Z, X radius) where G03 is counter-clockwise.
//! The chain's chord error is at most `tol`.

type P = (f64, f64);

/// Most points one curve block may become: 100 000 chords are over 20 m of parabola at the
/// chord tolerance. A block asking for more has a coordinate out of all proportion (a
/// fuzzed X9352710 asked for 16 million and ran the interpreter out of memory): refused
/// before anything is allocated.
pub const MAX_POINTS: usize = 100_000;

/// `n` points, or the refusal that says why.
fn bounded(n: f64, what: &str) -> Result<usize, String> {
    if n.is_finite() && n <= MAX_POINTS as f64 {
        Ok((n as usize).max(1))
    } else {
        Err(format!("the {what} would need more than {MAX_POINTS} points at the chord tolerance: check its coordinates and parameters"))
    }
}

fn rot(p: P, a: f64) -> P {
    let (s, c) = a.sin_cos();
    (c * p.0 - s * p.1, s * p.0 + c * p.1)
}

/// Ellipse arc from `s` to `e`, semi-axes `a` ≥ `b` > 0, major axis at angle `phi` (rad) in
/// (u, v). Of the two ellipses through both points the one giving the shorter arc (≤ 180° in
/// the circle the ellipse is a squashed copy of) is used, like R > 0 for circles: the manual
/// gives no rule. Returns the points after `s`, ending exactly at `e`.
pub fn ellipse(s: P, e: P, a: f64, b: f64, phi: f64, cw: bool, tol: f64) -> Result<Vec<P>, String> {
    if !(a > 0.0 && b > 0.0) {
        return Err(format!("A{a} B{b}: the semi-axes must be > 0"));
    }
    if b > a {
        return Err(format!("A{a} B{b}: A is the semi-major axis and must be ≥ B"));
    }
    let k = a / b;
    // To the circle frame: rotate the major axis onto u, stretch the minor axis by a/b.
    let to = |p: P| {
        let q = rot((p.0 - s.0, p.1 - s.1), -phi);
        (q.0, q.1 * k)
    };
    let back = |q: P| {
        let r = rot((q.0, q.1 / k), phi);
        (r.0 + s.0, r.1 + s.1)
    };
    let e1 = to(e);
    let chord = e1.0.hypot(e1.1);
    if chord < 1e-9 {
        return Ok(vec![]);
    }
    if chord > 2.0 * a + 1e-9 {
        return Err(format!("the end point cannot lie on an ellipse with A{a} B{b} through the start point"));
    }
    let h = (a * a - chord * chord / 4.0).max(0.0).sqrt();
    let (nu, nv) = (-e1.1 / chord, e1.0 / chord);
    let side = if cw { -1.0 } else { 1.0 };
    let c = (e1.0 / 2.0 + side * h * nu, e1.1 / 2.0 + side * h * nv);
    let ts = (0.0 - c.1).atan2(0.0 - c.0);
    let te = (e1.1 - c.1).atan2(e1.0 - c.0);
    let tau = std::f64::consts::TAU;
    let mut sweep = te - ts;
    if cw {
        while sweep >= 0.0 {
            sweep -= tau;
        }
    } else {
        while sweep <= 0.0 {
            sweep += tau;
        }
    }
    let step = if tol >= a { std::f64::consts::FRAC_PI_2 } else { 2.0 * (1.0 - tol / a).acos() };
    let n = bounded((sweep.abs() / step).ceil(), "ellipse")?;
    let mut out = Vec::with_capacity(n);
    for i in 1..n {
        let t = ts + sweep * i as f64 / n as f64;
        out.push(back((c.0 + a * t.cos(), c.1 + a * t.sin())));
    }
    out.push(e);
    Ok(out)
}

/// Parabola `Y² = 2PX` (§2.5) with its axis at angle `phi` (rad) in (u, v), through `s` and
/// `e`. The vertex follows from the two points; the opening side from the direction: G03
/// (counter-clockwise) turns left, so the parabola opens to the left of the chord.
pub fn parabola(s: P, e: P, p: f64, phi: f64, cw: bool, tol: f64) -> Result<Vec<P>, String> {
    if p <= 0.0 {
        return Err(format!("P{p}: the parabola parameter must be > 0"));
    }
    // Local frame: σ along the axis, τ across it, origin at the start.
    let e1 = rot((e.0 - s.0, e.1 - s.1), -phi);
    let (s2, t2) = e1;
    if t2.abs() < 1e-9 {
        if s2.abs() < 1e-9 {
            return Ok(vec![]);
        }
        return Err("the end point lies on the parabola's axis line through the start: no parabola fits".into());
    }
    // Chord left normal in the local frame is (−t2, s2); the axis is (1, 0): its dot is −t2.
    let left = -t2 > 0.0;
    let sign = if left != cw { 1.0 } else { -1.0 };
    // σ = σ0 + sign (τ − τ0)² / 2p through (0, 0) and (s2, t2).
    let t0 = t2 / 2.0 - sign * p * s2 / t2;
    let s0 = -sign * t0 * t0 / (2.0 * p);
    let dt = (8.0 * p * tol).sqrt();
    let n = bounded((t2.abs() / dt).ceil(), "parabola")?;
    let mut out = Vec::with_capacity(n);
    for i in 1..n {
        let t = t2 * i as f64 / n as f64;
        let sg = s0 + sign * (t - t0) * (t - t0) / (2.0 * p);
        let r = rot((sg, t), phi);
        out.push((r.0 + s.0, r.1 + s.1));
    }
    out.push(e);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curve_of_absurd_size_is_refused_before_it_is_built() {
        // The fuzzer's G3.2 from X9352710 to X60 (radius, mm), P10: 16 million chords.
        let e = parabola((0.0, 4_676_355.0), (-40.0, 30.0), 10.0, 0.0, false, 0.002).unwrap_err();
        assert!(e.contains("more than 100000 points"), "{e}");
        let e = ellipse((0.0, 0.0), (1.0, 1.0), 1e12, 1e12, 0.0, false, 1e-9).unwrap_err();
        assert!(e.contains("ellipse"), "{e}");
        // The manual's own example is far below the bound.
        assert!(parabola((0.0, 15.0), (-40.0, 30.0), 10.0, 0.0, false, 0.002).is_ok());
    }

    #[test]
    fn ellipse_points_lie_on_the_ellipse_within_tolerance() {
        let (a, b, phi) = (48.0, 25.0, (-60f64).to_radians());
        let s = (0.0, 21.57);
        let e = (-50.0, 31.91);
        let pts = ellipse(s, e, a, b, phi, true, 0.002).unwrap();
        assert_eq!(*pts.last().unwrap(), e);
        assert!(pts.len() > 20);
        // All points satisfy one ellipse equation: find its centre from the construction by
        // checking that consecutive chords are short and that the curve turns clockwise.
        let mut prev = s;
        let mut turn = 0.0;
        let mut last_dir: Option<P> = None;
        for &p in &pts {
            let d = (p.0 - prev.0, p.1 - prev.1);
            assert!(d.0.hypot(d.1) < 3.0);
            if let Some(ld) = last_dir {
                turn += ld.0 * d.1 - ld.1 * d.0;
            }
            last_dir = Some(d);
            prev = p;
        }
        assert!(turn < 0.0, "G02.1 turns clockwise");
        assert!(ellipse(s, (500.0, 0.0), a, b, phi, true, 0.002).is_err());
        assert!(ellipse(s, e, 10.0, 20.0, phi, true, 0.002).is_err());
    }

    #[test]
    fn parabola_through_both_points_with_curvature() {
        // Axis along Z, P = 10, manual §2.5 example: from (Z0, X15) to (Z-40, X30) with G03.2.
        let s = (0.0, 15.0);
        let e = (-40.0, 30.0);
        let pts = parabola(s, e, 10.0, 0.0, false, 0.001).unwrap();
        assert_eq!(*pts.last().unwrap(), e);
        // Fit: σ − σ0 = ±(τ − τ0)²/20 for every point (second differences constant).
        let n = pts.len();
        assert!(n > 10);
        let q: Vec<P> = std::iter::once(s).chain(pts.iter().copied()).collect();
        let dt = q[1].1 - q[0].1;
        let d2 = (q[2].0 - 2.0 * q[1].0 + q[0].0) / (dt * dt);
        assert!((d2.abs() - 0.1).abs() < 1e-6, "{d2}");
        // Continuous up to the end point (the last computed point is next to it).
        for w in q.windows(2) {
            assert!((w[1].0 - w[0].0).hypot(w[1].1 - w[0].1) < 2.0, "{w:?}");
        }
        // CCW: turns left.
        let (a, b, c) = (q[0], q[n / 2], q[n]);
        let cross = (b.0 - a.0) * (c.1 - b.1) - (b.1 - a.1) * (c.0 - b.0);
        assert!(cross > 0.0);
        let pts_cw = parabola(s, e, 10.0, 0.0, true, 0.001).unwrap();
        let m = pts_cw[pts_cw.len() / 2];
        let cross = (m.0 - a.0) * (c.1 - m.1) - (m.1 - a.1) * (c.0 - m.0);
        assert!(cross < 0.0);
        assert!(parabola(s, (-40.0, 15.0), 10.0, 0.0, true, 0.001).is_err());
    }
}
