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

/// One constant-jerk phase of an S-curve plan: (jerk, duration in s).
type Phase = (f64, f64);

/// The time-optimal jerk-limited change from speed `v` and acceleration `a` to speed `vt`
/// at zero acceleration, with |acceleration| ≤ `amax` and |jerk| ≤ `j` (both > 0): at most
/// three constant-jerk phases (ramp the acceleration towards a peak, hold it, ramp it back
/// to 0). O(1). An acceleration beyond `amax` (limits lowered under way) is ramped back first.
pub fn plan(v: f64, a: f64, vt: f64, amax: f64, j: f64) -> [Phase; 3] {
    // Speed reached if the acceleration were ramped to 0 at once.
    let vz = v + a * a.abs() / (2.0 * j);
    let sg = if vz < vt {
        1.0
    } else if vz > vt {
        -1.0
    } else {
        return [(-a.signum() * j, a.abs() / j), (0.0, 0.0), (0.0, 0.0)];
    };
    // Mirrored so that the speed must rise by `dvt > 0`.
    let (am, dvt) = (sg * a, sg * (vt - v));
    let mut ap = (j * dvt + 0.5 * am * am).max(0.0).sqrt();
    let mut t2 = 0.0;
    if ap > amax {
        ap = amax;
        let t1 = (ap - am).abs() / j;
        let dv1 = 0.5 * (am + ap) * t1;
        let dv3 = 0.5 * ap * ap / j;
        t2 = ((dvt - dv1 - dv3) / ap).max(0.0);
    }
    let j1 = if ap >= am { j } else { -j };
    [(sg * j1, (ap - am).abs() / j), (0.0, t2), (-sg * j, ap / j)]
}

/// Follow `ph` (from speed `v`, acceleration `a`) for `t` seconds, then hold `vt`:
/// (distance, speed, acceleration) at `t`. A plan that ends within `t` ends exactly on
/// (`vt`, 0), so that a stop is exactly at rest.
pub fn advance(mut v: f64, mut a: f64, ph: &[Phase; 3], t: f64, vt: f64) -> (f64, f64, f64) {
    let total: f64 = ph.iter().map(|p| p.1).sum();
    let mut s = 0.0;
    let mut rem = t;
    for &(jk, d) in ph {
        let tau = d.min(rem);
        if tau > 0.0 {
            s += tau * (v + tau * (a / 2.0 + jk * tau / 6.0));
            v += tau * (a + jk * tau / 2.0);
            a += jk * tau;
            rem -= tau;
        }
    }
    if t >= total {
        v = vt;
        a = 0.0;
        s += vt * (t - total).max(0.0);
    }
    (s, v, a)
}

/// Shortest distance in which speed `v` and acceleration `a` can be brought to rest with
/// |acceleration| ≤ `amax` and |jerk| ≤ `j` (the whole of [`plan`] to 0).
pub fn stop_dist(v: f64, a: f64, amax: f64, j: f64) -> f64 {
    let ph = plan(v, a, 0.0, amax, j);
    let total: f64 = ph.iter().map(|p| p.1).sum();
    advance(v, a, &ph, total, 0.0).0
}

/// One cycle of the jerk-limited (S-curve) path-speed law: from speed `v` and acceleration
/// `a` at the start of the cycle, with `x` still to go before rest (the segment's end plus
/// its look-ahead extension), the commanded speed `v_cmd`, path limits `amax` and `j` and the
/// cycle `dt`: returns (speed, acceleration, distance) at the end of the cycle.
///
/// The profile is continuous in time (piecewise-constant jerk, switching at any instant),
/// sampled at the cycle: it heads for `v_cmd` on [`plan`] until the latest instant from which
/// [`stop_dist`] still fits in what is left, then follows the braking plan. The setpoints are
/// samples of a profile with bounded acceleration and jerk, so their differences are bounded
/// by the same limits. A braking plan, followed, is still the braking plan of the states it
/// passes (time-optimal plans are consistent), so a segment lands on its end exactly at rest.
/// O(1): a fixed 40-step bisection on the switching instant, only in the cycle where braking
/// begins.
pub fn next_state(v: f64, a: f64, v_cmd: f64, x: f64, amax: f64, j: f64, dt: f64) -> (f64, f64, f64) {
    let vc = if v_cmd.is_finite() { v_cmd.max(0.0) } else { 0.0 };
    let x = if x.is_finite() { x.max(0.0) } else { 0.0 };
    let go = plan(v, a, vc, amax, j);
    let slack = |tau: f64| {
        let (s, v1, a1) = advance(v, a, &go, tau, vc);
        (x - s - stop_dist(v1, a1, amax, j), s, v1, a1)
    };
    let (f, s, v1, a1) = slack(dt);
    if f >= 0.0 {
        return (v1, a1, s);
    }
    // Switch to braking at the latest instant `lo` that still fits.
    let (mut lo, mut hi) = (0.0, dt);
    if slack(0.0).0 > 0.0 {
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if slack(mid).0 >= 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
    }
    let (s0, v0, a0) = advance(v, a, &go, lo, vc);
    let brake = plan(v0, a0, 0.0, amax, j);
    let (s1, v1, a1) = advance(v0, a0, &brake, dt - lo, 0.0);
    (v1.max(0.0), a1, (s0 + s1).max(0.0))
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

    #[test]
    fn s_curve_stop_distance_matches_the_closed_form() {
        let (amax, j) = (2000.0, 50_000.0);
        // From cruise: v·√(v/j) below A²/j (no constant-deceleration phase), else
        // v²/2A + v·A/2j.
        for v in [1.0f64, 10.0, 79.0, 81.0, 200.0, 1000.0] {
            let want = if v <= amax * amax / j { v * (v / j).sqrt() } else { v * v / (2.0 * amax) + v * amax / (2.0 * j) };
            let got = stop_dist(v, 0.0, amax, j);
            assert!((got - want).abs() < 1e-9 * (1.0 + want), "v {v}: {got} vs {want}");
        }
        // Already at full deceleration: v²/2A + A³/24j².
        let v = 300.0f64;
        let want = v * v / (2.0 * amax) + amax.powi(3) / (24.0 * j * j);
        assert!((stop_dist(v, -amax, amax, j) - want).abs() < 1e-9 * want);
    }

    #[test]
    fn s_curve_plans_reach_their_target_exactly_within_the_limits() {
        let (amax, j) = (1500.0, 20_000.0);
        for &(v, a, vt) in &[
            (0.0, 0.0, 100.0),
            (100.0, 0.0, 0.0),
            (50.0, 800.0, 20.0),
            (50.0, -800.0, 90.0),
            (10.0, 1500.0, 400.0),
            (400.0, -1500.0, 0.0),
            (30.0, 1900.0, 200.0),
        ] {
            let ph = plan(v, a, vt, amax, j);
            let total: f64 = ph.iter().map(|p| p.1).sum();
            // Walk the plan finely: jerk and acceleration within the limits (an acceleration
            // beyond amax only falls), and it ends on (vt, 0).
            let n = 10_000;
            let mut prev_a = a;
            for k in 1..=n {
                let (_, _, ak) = advance(v, a, &ph, total * k as f64 / n as f64, vt);
                assert!(ak.abs() <= amax.max(a.abs()) + 1e-9, "a {ak}");
                assert!((ak - prev_a).abs() <= j * total / n as f64 + 1e-6, "jerk");
                prev_a = ak;
            }
            assert!(ph.iter().all(|p| p.1 >= 0.0 && p.0.abs() <= j));
            let (_, ve, ae) = advance(v, a, &ph, total, vt);
            assert_eq!((ve, ae), (vt, 0.0));
        }
    }

    #[test]
    fn s_curve_cycles_land_exactly_on_the_end_at_rest() {
        let (amax, j, dt) = (2000.0, 40_000.0, 0.002);
        for &(x, vc) in &[(0.0005, 100.0), (0.3, 100.0), (37.0, 150.0), (2.5, 1000.0)] {
            let (mut v, mut a, mut s) = (0.0, 0.0, 0.0);
            let mut n = 0;
            while x - s > 1e-9 {
                let (nv, na, ds) = next_state(v, a, vc, x - s, amax, j, dt);
                assert!(nv >= 0.0 && nv <= vc + 1e-9 && na.abs() <= amax + 1e-9);
                assert!((na - a).abs() <= j * dt + 1e-6, "jerk");
                v = nv;
                a = na;
                s += ds;
                n += 1;
                assert!(n < 100_000);
            }
            assert!((x - s).abs() <= 1e-9, "x {x}: {s}");
            assert!(v < 1e-6 && a.abs() < 1e-3, "at rest: v {v} a {a}");
        }
    }
}
