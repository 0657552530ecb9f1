//! The position-register (PR) move of a Modbus servo: a trapezoidal profile to an absolute
//! position, generated in the drive every millisecond and fed to its CSP interpolator.
//! A new trigger during a move retargets it from the present position and speed.

/// The profile generator of one drive (positions in counts, speeds in counts/s).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Gen {
    /// Profile position and speed.
    pub p: f64,
    pub v: f64,
    pub target: f64,
    vmax: f64,
    acc: f64,
    dec: f64,
    moving: bool,
    dwell_ns: u64,
    /// End of the dwell after the last move (ns).
    dwell_until: u64,
}

impl Gen {
    /// Standing at `p`.
    pub fn hold(p: f64) -> Gen {
        Gen { p, v: 0.0, target: p, vmax: 0.0, acc: 1.0, dec: 1.0, moving: false, dwell_ns: 0, dwell_until: 0 }
    }

    /// Move to `target` at up to `vmax` counts/s, accelerating at `acc` and braking at `dec`
    /// counts/s², then dwell `dwell_ns`.
    pub fn start(&mut self, target: f64, vmax: f64, acc: f64, dec: f64, dwell_ns: u64) {
        self.target = target;
        self.vmax = vmax.max(0.0);
        self.acc = acc.max(1.0);
        self.dec = dec.max(1.0);
        self.dwell_ns = dwell_ns;
        self.moving = true;
    }

    /// A move or its dwell is in progress.
    pub fn running(&self, now: u64) -> bool {
        self.moving || now < self.dwell_until
    }

    /// Advance the profile by `dt` seconds, ending at `now` (ns).
    pub fn step(&mut self, dt: f64, now: u64) {
        if !self.moving {
            return;
        }
        let e = self.target - self.p;
        if e == 0.0 && self.v == 0.0 {
            self.finish(now);
            return;
        }
        // The fastest speed from which braking at `dec` in steps of dt still stops on the
        // target (k steps of dec·dt cover dec·dt²·k(k+1)/2), capped at vmax.
        let ddt = self.dec * dt;
        let k = if ddt > 0.0 { ((1.0 + 8.0 * e.abs() / (ddt * dt)).sqrt() - 1.0) / 2.0 } else { 0.0 };
        let v_des = e.signum() * self.vmax.min(ddt * k);
        let braking = self.v != 0.0 && (v_des.signum() != self.v.signum() || v_des.abs() < self.v.abs());
        let lim = if braking { self.dec } else { self.acc } * dt;
        self.v += (v_des - self.v).clamp(-lim, lim);
        let p1 = self.p + self.v * dt;
        let e1 = self.target - p1;
        // Reaching or crossing the target at a crawl (the last step of the braking curve)
        // ends the move on it; crossing it fast (a retarget behind) brakes and comes back.
        if (e1 == 0.0 || e1.signum() != e.signum()) && self.v.abs() <= 4.0 * self.dec * dt {
            self.p = self.target;
            self.v = 0.0;
            self.finish(now);
            return;
        }
        self.p = p1;
    }

    fn finish(&mut self, now: u64) {
        self.moving = false;
        self.v = 0.0;
        self.dwell_until = now + self.dwell_ns;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn run(g: &mut Gen, t0: u64, ms: u64) -> (u64, f64) {
        let mut vpeak = 0.0f64;
        let mut t = t0;
        for _ in 0..ms {
            t += MS;
            g.step(1e-3, t);
            vpeak = vpeak.max(g.v.abs());
            if !g.running(t) {
                break;
            }
        }
        (t, vpeak)
    }

    #[test]
    fn trapezoid_reaches_the_target_at_the_set_speed() {
        // 100 000 counts at up to 200 000 counts/s, 1e6 counts/s² both ways:
        // 0.2 s ramps (20 000 counts each), 60 000 counts at cruise (0.3 s) → 0.7 s.
        let mut g = Gen::hold(0.0);
        g.start(100_000.0, 200_000.0, 1e6, 1e6, 0);
        let (t, vpeak) = run(&mut g, 0, 5000);
        assert_eq!(g.p, 100_000.0);
        assert!(!g.running(t));
        assert!((vpeak - 200_000.0).abs() < 1.0, "{vpeak}");
        let secs = t as f64 * 1e-9;
        assert!((secs - 0.7).abs() < 0.01, "{secs}");
    }

    #[test]
    fn short_move_is_a_triangle_and_dwell_keeps_it_running() {
        let mut g = Gen::hold(500.0);
        g.start(400.0, 1e6, 1e6, 1e6, 50 * MS);
        let (mut t, mut vpeak) = (0, 0.0f64);
        while g.p != 400.0 && t < 5000 * MS {
            t += MS;
            g.step(1e-3, t);
            vpeak = vpeak.max(g.v.abs());
        }
        assert_eq!(g.p, 400.0);
        // 100 counts as a triangle: peak √(d·100) = 10 000 counts/s, well below vmax.
        assert!(vpeak < 12_000.0, "{vpeak}");
        // Arrived; the dwell runs 50 ms more.
        assert!(g.running(t) && g.running(t + 49 * MS) && !g.running(t + 50 * MS));
    }

    #[test]
    fn retarget_behind_brakes_then_returns() {
        let mut g = Gen::hold(0.0);
        g.start(100_000.0, 200_000.0, 1e6, 1e6, 0);
        run(&mut g, 0, 300);
        assert!(g.v > 100_000.0);
        let p_then = g.p;
        g.start(0.0, 200_000.0, 1e6, 1e6, 0);
        let mut max_p = p_then;
        let mut t = 300 * MS;
        for _ in 0..5000 {
            t += MS;
            g.step(1e-3, t);
            max_p = max_p.max(g.p);
            if !g.running(t) {
                break;
            }
        }
        assert_eq!(g.p, 0.0);
        // Braked at 1e6 counts/s² from ~200 000 counts/s: ~20 000 counts past the retarget point.
        assert!(max_p - p_then < 25_000.0 && max_p > p_then, "{p_then} {max_p}");
    }
}
