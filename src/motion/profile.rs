//! The scalar path-speed law, evaluated once per cycle (online, so that a per-revolution feed
//! can follow the measured spindle speed and an override or feed hold takes effect at once).
//!
//! Time is discrete: during one cycle the path advances `v·dt`, and `v` may change by at most
//! `dv = a·dt` from one cycle to the next. That is exactly what the drives see (the second
//! difference of the setpoints), so the limits hold on the setpoints themselves, not only on
//! an ideal continuous profile.

/// Largest speed for this cycle from which the remaining distance `d` can still be covered
/// with speeds that drop by at most `dv` per cycle, landing exactly on the end with a speed
/// of at most `dv` (so that the following cycle can be at rest).
///
/// With `v` the speed of this cycle, the distance needed is `dt·G(v)`,
/// `G(v) = v + Σ_{k≥1} max(v − k·dv, 0)`, a continuous, strictly increasing, piecewise-linear
/// function; this returns `G⁻¹(d/dt)` in O(1) (one square root). On `[m·dv, (m+1)·dv]`,
/// `G(v) = (m+1)·v − dv·m(m+1)/2`, and `G(m·dv) = dv·m(m+1)/2`.
///
/// Why this is safe: if this cycle's speed `v ≤ G⁻¹(d/dt)`, then after it the rest
/// `d − v·dt ≥ dt·G(v − dv)`, so next cycle `G⁻¹ ≥ v − dv`: the brake never needs more than `dv`.
pub fn v_allowed(d: f64, dv: f64, dt: f64) -> f64 {
    if !(d > 0.0) || !(dt > 0.0) || !(dv > 0.0) {
        return 0.0;
    }
    let y = d / dt;
    let m = ((-1.0 + (1.0 + 8.0 * y / dv).sqrt()) / 2.0).floor().max(0.0);
    ((y + dv * m * (m + 1.0) / 2.0) / (m + 1.0)).max(0.0)
}

/// `G(v)` itself (see [`v_allowed`]): the distance, in units of `dt`, that a cycle at speed `v`
/// and the braking staircase after it cover before rest.
pub fn g(v: f64, dv: f64) -> f64 {
    if !(v > 0.0) {
        return 0.0;
    }
    if !(dv > 0.0) {
        return f64::INFINITY;
    }
    let m = (v / dv).floor();
    (m + 1.0) * v - dv * m * (m + 1.0) / 2.0
}

/// The path speed for the next cycle: towards `v_cmd` by at most `dv`, never more than what
/// still allows stopping exactly within the remaining distance `d` (see [`v_allowed`]).
pub fn next_speed(v: f64, v_cmd: f64, d: f64, dv: f64, dt: f64) -> f64 {
    let lo = (v - dv).max(0.0);
    let hi = v + dv;
    // max/min rather than clamp: no panic even if a caller passes lo > hi or NaN.
    let want = if v_cmd.is_finite() { v_cmd.max(lo).min(hi) } else { lo };
    want.min(v_allowed(d, dv, dt)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// G(v) by brute force, for v_end = 0.
    fn brute_g(v: f64, dv: f64) -> f64 {
        let mut s = 0.0;
        let mut k = 0.0;
        while v - k * dv > 0.0 {
            s += v - k * dv;
            k += 1.0;
        }
        s
    }

    #[test]
    fn g_matches_brute_force_and_inverts() {
        let dv = 0.37;
        for i in 0..500 {
            let v = i as f64 * 0.0213;
            assert!((g(v, dv) - brute_g(v, dv)).abs() < 1e-9);
            assert!((v_allowed(g(v, dv) * 0.002, dv, 0.002) - v).abs() < 1e-9);
        }
    }

    #[test]
    fn inverse_matches_brute_force() {
        let (dv, dt) = (0.004, 0.002);
        for i in 1..2000 {
            let d = i as f64 * 1e-4;
            let v = v_allowed(d, dv, dt);
            let back = brute_g(v, dv) * dt;
            assert!((back - d).abs() < 1e-12, "d={d} v={v} G={back}");
        }
    }

    #[test]
    fn stopping_from_allowed_speed_lands_exactly_with_bounded_steps() {
        let (dv, dt) = (4.0 * 0.002, 0.002);
        let mut d = 3.7;
        let mut v = v_allowed(d, dv, dt);
        let mut n = 0;
        while d > 1e-12 {
            let nv = next_speed(v, 1e9, d, dv, dt);
            assert!(nv >= v - dv - 1e-12 && nv <= v + dv + 1e-12);
            d -= nv * dt;
            v = nv;
            n += 1;
            assert!(n < 100_000);
        }
        assert!(d > -1e-9, "overshoot {d}");
        assert!(v <= dv + 1e-12, "lands at {v}, more than one step above rest");
    }
}
