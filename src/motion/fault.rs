//! Controlled stop on a drive fault (see `CycleLoop`'s fault handling).
//!
//! When a drive that is not part of a running synchronised pair faults, `Motion::stop` is
//! enough: a thread keeps the axes locked to the braking spindle, a tap stroke brakes axis and
//! spindle on one profile. When the faulted drive *is* one of the pair (the spindle, or the
//! tapping / threading feed axis), it no longer follows its set-point — it runs its own fault
//! reaction — so the survivor follows the faulted drive's *actual* position through the
//! relation of the move until both are at rest: in a tap Z = Z₀ + lead·(θ_act − θ₀)/360 (or
//! the spindle from Z), in a thread the path position on the spindle's lock (or the spindle
//! angle from the path), in G92.1 the stroke's profile. The measured position is one cycle old
//! and the set-point acts a cycle later, so it is predicted over the feedback delay (plus the
//! feed axis' learnt lag), as the thread lock does. The survivor keeps its own acceleration
//! limit and never reverses (a tap must not be turned back into the thread by a noisy sample).

use super::{profile, Feedback, Motion, Run, AX_S, HIST, N_AXES};
use crate::motion::geom::Geom;

/// Faulted drive's speed below which it counts as at rest: degrees/s (spindle), mm/s.
const REST_DEG_S: f64 = 2.0;
const REST_MM_S: f64 = 0.2;
/// Cycles at rest (both) before the follow ends.
const REST_CYCLES: u32 = 10;
/// Longest follow, cycles (a faulted drive that coasts for ever must not hold the loop).
const MAX_FOLLOW_CYCLES: u32 = 10_000;

/// No end to keep within (a spindle following a faulted feed axis: the axis' own actual
/// bounds it).
const UNBOUNDED: (f64, f64) = (f64::NEG_INFINITY, f64::INFINITY);

/// The survivor of a synchronised pair following the faulted partner.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Follow {
    /// Motion axis of the faulted drive.
    faulted: usize,
    /// The survivor's coordinate (tap: position on the tapping axis or spindle angle; thread
    /// and G92.1: path position or spindle angle) and its speed per second.
    x: f64,
    v: f64,
    /// Direction the survivor moved in at the fault (+1, −1, 0): it never reverses.
    dir: f64,
    /// The faulted drive's last actual position and speed estimate.
    f_prev: Option<f64>,
    f_v: f64,
    still: u32,
    cycles: u32,
    /// The followed drive is healthy and braking on its own commanded ramp (a controlled stop
    /// of a thread): only the survivor's set-point is taken from its actual position.
    driven: bool,
}

impl Follow {
    fn new(faulted: usize, x: f64, v: f64, f_v: f64) -> Follow {
        let dir = if v > 0.0 {
            1.0
        } else if v < 0.0 {
            -1.0
        } else {
            0.0
        };
        Follow { faulted, x, v, dir, f_prev: None, f_v, still: 0, cycles: 0, driven: false }
    }

    /// One cycle towards `target` (moving at `vt`), within `a` per s², never against `dir`,
    /// and never past the move's ends `lo`..`hi` (survivor coordinates; infinite: none).
    fn track(&mut self, target: f64, vt: f64, a: f64, dt: f64, (lo, hi): (f64, f64)) {
        let dv = (a * dt).max(1e-12);
        let d = target - self.x;
        let vb = profile::v_allowed(d.abs(), dv, dt).copysign(d);
        let mut nv = (vt + vb).clamp(self.v - dv, self.v + dv);
        if self.dir > 0.0 {
            nv = nv.max(0.0);
        } else if self.dir < 0.0 {
            nv = nv.min(0.0);
        }
        // The target is clamped to the move, but a survivor at speed needs its braking
        // distance: from the speed that still stops at the end. A spindle braking slowly on its
        // fault reaction took a tap's Z 1.7 mm past the hole's bottom before this.
        if hi.is_finite() {
            nv = nv.min(profile::v_allowed(hi - self.x, dv, dt));
        }
        if lo.is_finite() {
            nv = nv.max(-profile::v_allowed(self.x - lo, dv, dt));
        }
        if !nv.is_finite() {
            nv = 0.0;
        }
        self.x += nv * dt;
        self.v = nv;
    }
}

/// Path position of a line at which feed axis `a` is at `p` (None: an arc, or `a` does not
/// move along it).
fn axis_progress(g: &Geom, a: usize, p: f64) -> Option<f64> {
    match *g {
        Geom::Line { start, delta, len, .. } if a < 3 && len > 0.0 && delta[a].abs() > 1e-9 * len => Some((p - start[a]) * len / delta[a]),
        _ => None,
    }
}

impl Motion {
    /// A drive faulted: controlled stop. `axis` is the motion axis of the faulted drive (None:
    /// a drive motion does not command). If it is one of the pair of the synchronised move
    /// running now, the survivor follows its actual position (see the module doc) instead of
    /// the profile; otherwise this is `stop()`. Then wait for `is_idle()` as after `stop()`.
    pub fn fault_stop(&mut self, axis: Option<usize>) {
        let dt = self.lim.cycle_s;
        let k = self.hist_k;
        let k1 = (k + HIST - 1) % HIST;
        let vel = |i: usize| (self.hist[k][i] - self.hist[k1][i]) / dt;
        self.follow = match (axis, self.run) {
            (Some(a), Run::Tap { seg, theta0: Some(_), landed: false, .. }) if a == AX_S || a == seg.axis => {
                let p = if a == AX_S { seg.axis } else { AX_S };
                Some(Follow::new(a, self.pos[p], vel(p), vel(a)))
            }
            (Some(a), Run::Thread { seg, sync: Some(_), s, v, landed: false }) if a == AX_S || a == seg.long_axis => {
                Some(if a == AX_S { Follow::new(a, s, v, vel(a)) } else { Follow::new(a, self.pos[AX_S], self.sp_cur * 6.0, vel(a)) })
            }
            (Some(a), Run::Rigid { seg, theta0: Some(_), s, v, landed: false })
                if seg.u_long > 0.0 && seg.dc != 0.0 && (a == AX_S || axis_progress(&seg.geom, a, 0.0).is_some()) =>
            {
                Some(if a == AX_S { Follow::new(a, s, v, vel(a)) } else { Follow::new(a, self.pos[AX_S], vel(AX_S), vel(a)) })
            }
            _ => None,
        };
        self.stop();
    }

    /// Controlled stop (reset, program alarm): as `stop()`, but a thread pass locked to the
    /// spindle follows the braking spindle's *actual* angle, predicted from its measured
    /// speed, rather than the lock's filtered speed estimate (which lags a braking spindle:
    /// 25 µm off the thread on the emulated drives at S800, lead 2, against 2 µm so).
    pub fn stop_following(&mut self) {
        let dt = self.lim.cycle_s;
        let k = self.hist_k;
        let k1 = (k + HIST - 1) % HIST;
        if let Run::Thread { sync: Some(_), s, v, landed: false, .. } = self.run {
            if self.follow.is_none() {
                let mut f = Follow::new(AX_S, s, v, (self.hist[k][AX_S] - self.hist[k1][AX_S]) / dt);
                f.driven = true;
                self.follow = Some(f);
            }
        }
        self.stop();
    }

    /// Under a follow: no sync correction (the survivor already follows the actual position).
    /// True if it took the place of `sync_corr` this cycle.
    pub(super) fn follow_corr(&mut self) -> bool {
        if self.follow.is_none() {
            return false;
        }
        self.corr.clear();
        true
    }

    /// One cycle of the survivor following the faulted drive (instead of the run's own step).
    /// Returns the path speed, mm/s.
    pub(super) fn step_follow(&mut self, fb: &Feedback, prev: &[f64; N_AXES]) -> f64 {
        let Some(mut f) = self.follow else { return 0.0 };
        let dt = self.lim.cycle_s;
        let a = f.faulted;
        // A non-finite reading counts as "stopped where it was last seen".
        let act = if fb.pos[a].is_finite() { fb.pos[a] } else { f.f_prev.unwrap_or(self.pos[a]) };
        let fv = match f.f_prev {
            Some(p) => (act - p) / dt,
            None => f.f_v,
        };
        f.f_prev = Some(act);
        f.f_v = fv;
        let h = dt * (self.lim.feedback_delay as f64 - 1.0).max(0.0);
        let pred = act + fv * h;
        let mut path_v = 0.0;
        // Nothing to follow along (cannot happen for what `fault_stop` sets up): back to the
        // run's own controlled stop.
        let mut abandon = false;
        match self.run {
            Run::Tap { seg, theta0: Some((pr, thr)), .. } => {
                if a == AX_S {
                    let tau = if self.lim.sync_correction { self.axis_lag(seg.axis) } else { 0.0 };
                    let raw = pr + seg.lead * (pred + fv * tau - thr) / 360.0;
                    let ends = (seg.p0.min(seg.p1), seg.p0.max(seg.p1));
                    let tgt = raw.clamp(ends.0, ends.1);
                    let vt = if tgt == raw { seg.lead * fv / 360.0 } else { 0.0 };
                    f.track(tgt, vt, self.lim.amax[seg.axis], dt, ends);
                    self.pos[seg.axis] = f.x;
                    self.pos[AX_S] = act;
                    path_v = f.v.abs();
                } else {
                    let tgt = thr + 360.0 * (pred - pr) / seg.lead;
                    f.track(tgt, 360.0 * fv / seg.lead, self.lim.amax[AX_S], dt, UNBOUNDED);
                    self.pos[AX_S] = f.x;
                    self.pos[seg.axis] = act;
                    path_v = fv.abs();
                }
                self.monitor.watch(true);
            }
            Run::Rigid { seg, theta0: Some(th0), .. } => {
                if a == AX_S {
                    let raw = (pred - th0) * seg.plen / seg.dc;
                    let tgt = raw.clamp(0.0, seg.plen);
                    let vt = if tgt == raw { fv * seg.plen / seg.dc } else { 0.0 };
                    f.track(tgt, vt, seg.alim, dt, (0.0, seg.plen));
                    if seg.geom.len() > 0.0 {
                        self.pos[..3].copy_from_slice(&seg.geom.at(f.x.clamp(0.0, seg.plen)));
                    }
                    self.pos[AX_S] = act;
                    path_v = f.v.abs();
                } else if let (Some(s), Some(s1)) = (axis_progress(&seg.geom, a, pred), axis_progress(&seg.geom, a, pred + fv * dt)) {
                    let s = s.clamp(0.0, seg.plen);
                    f.track(th0 + seg.dc * s / seg.plen, seg.dc * (s1 - s) / dt / seg.plen, self.lim.amax[AX_S], dt, UNBOUNDED);
                    self.pos[..3].copy_from_slice(&seg.geom.at(s));
                    self.pos[a] = act;
                    self.pos[AX_S] = f.x;
                    path_v = ((s1 - s) / dt).abs();
                } else {
                    abandon = true;
                }
                self.monitor.watch(true);
            }
            Run::Thread { seg, sync: Some(t), .. } => {
                let len = seg.geom.len();
                if a == AX_S {
                    let tau = if self.lim.sync_correction { self.axis_lag(seg.long_axis) } else { 0.0 };
                    let th = pred + fv * tau;
                    let raw = t.target(th);
                    let tgt = raw.clamp(0.0, len);
                    let vt = if tgt == raw { (t.target(th + fv * dt) - raw) / dt } else { 0.0 };
                    f.track(tgt, vt, seg.alim, dt, (0.0, len));
                    self.pos[..3].copy_from_slice(&seg.geom.at(f.x.clamp(0.0, len)));
                    if !f.driven {
                        self.pos[AX_S] = act;
                    }
                    path_v = f.v.abs();
                } else if let (Some(s), Some(s1)) = (axis_progress(&seg.geom, a, pred), axis_progress(&seg.geom, a, pred + fv * dt)) {
                    let s = s.clamp(0.0, len);
                    if let (Some(th), Some(th1)) = (t.angle_at(s), t.angle_at(s1.clamp(0.0, len))) {
                        f.track(th, (th1 - th) / dt, self.lim.amax[AX_S], dt, UNBOUNDED);
                    } else {
                        f.track(f.x, 0.0, self.lim.amax[AX_S], dt, UNBOUNDED);
                    }
                    self.pos[..3].copy_from_slice(&seg.geom.at(s));
                    self.pos[a] = act;
                    self.pos[AX_S] = f.x;
                    path_v = ((s1 - s) / dt).abs();
                } else {
                    abandon = true;
                }
                self.monitor.watch(true);
            }
            _ => abandon = true,
        }
        if abandon {
            self.follow = None;
            return path_v;
        }
        self.sp_cur = (self.pos[AX_S] - prev[AX_S]) / dt / 6.0;
        let rest = |ax: usize, v: f64| v.abs() < if ax == AX_S { REST_DEG_S } else { REST_MM_S };
        let survivor = if a == AX_S { 0 } else { AX_S };
        f.still = if rest(a, fv) && rest(survivor, f.v) { f.still + 1 } else { 0 };
        f.cycles += 1;
        if f.still >= REST_CYCLES || f.cycles >= MAX_FOLLOW_CYCLES {
            self.follow = None;
            self.sp_cur = 0.0;
            self.run = Run::None;
        } else {
            self.follow = Some(f);
        }
        path_v
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canon::{Move, MoveKind, Pos, SrcPos};
    use crate::config::MachineConfig;
    use crate::motion::Limits;
    use std::sync::Arc;

    fn mv(kind: MoveKind) -> Move {
        Move { src: SrcPos::new(Arc::from("t.nc"), 1, 1), kind, exact_stop: true, work_offset: Pos::ZERO, tag: None }
    }

    /// Ideal healthy drives (actual = last set-point); the faulted axis `f` runs its own
    /// fault reaction from the fault on: braking at `decel` per s² from its speed then.
    /// Returns the (faulted actual, survivor set-point) pairs through the stop and the cycles.
    fn fault_in(kind: MoveKind, at: usize, f: usize, survivor: usize, decel: f64) -> (Vec<(f64, f64)>, usize) {
        let mut l = Limits::from_config(&MachineConfig::embedded());
        l.feedback_delay = 1;
        l.sync_correction = false;
        let dt = l.cycle_s;
        let mut m = Motion::new(l, [0.0, 0.0, 2.0, 0.0]);
        m.push(&mv(kind)).unwrap();
        let mut fb = Feedback { pos: m.position(), spindle_rpm: 0.0, ..Default::default() };
        let mut prev = fb.pos;
        for _ in 0..at {
            let sp = m.step(&fb);
            prev = fb.pos;
            fb.pos = sp.pos;
        }
        let mut v = (fb.pos[f] - prev[f]) / dt;
        assert!(v.abs() > 1.0, "the faulted axis moves at the fault ({v})");
        m.fault_stop(Some(f));
        let mut out = Vec::new();
        let mut act = fb.pos[f];
        for k in 0..20_000 {
            if m.is_idle() {
                return (out, k);
            }
            let sp = m.step(&fb);
            // The faulted drive brakes on its own ramp, whatever it is sent.
            let nv = if v > 0.0 { (v - decel * dt).max(0.0) } else { (v + decel * dt).min(0.0) };
            act += 0.5 * (v + nv) * dt;
            v = nv;
            fb.pos = sp.pos;
            fb.pos[f] = act;
            out.push((act, sp.pos[survivor]));
        }
        panic!("not idle");
    }

    #[test]
    fn z_follows_a_faulted_spindle_in_a_tap() {
        // Motion's tap relation: Z − Z₀ = lead·(θ − θ₀)/360 (the lead's sign says which way
        // the spindle turns into the hole).
        let (trace, cycles) = fault_in(MoveKind::Tap { end: Pos::xz(0.0, -30.0), lead: 1.5, rpm: 1000.0, spindle: 1 }, 400, AX_S, 2, 18_000.0);
        let (th0, z0) = trace[0];
        let mut worst = 0.0f64;
        for w in trace.windows(2) {
            let (th, z) = w[1];
            worst = worst.max(((z - z0) - 1.5 * (th - th0) / 360.0).abs());
            assert!(w[1].1 <= w[0].1 + 1e-12, "Z never backs out of the hole");
        }
        assert!(worst < 0.002, "Z kept to the spindle within {:.1} µm", worst * 1000.0);
        assert!(cycles < 400, "{cycles} cycles");
    }

    #[test]
    fn z_stops_at_the_holes_bottom_when_a_faulted_spindle_brakes_past_it() {
        // S1000 at lead 1.5 is 25 mm/s of Z; a spindle that brakes at 600°/s² on its fault
        // reaction turns 30000° more (125 mm of Z) — far past the 32 mm stroke's bottom.
        let (trace, _) = fault_in(MoveKind::Tap { end: Pos::xz(0.0, -30.0), lead: 1.5, rpm: 1000.0, spindle: 1 }, 400, AX_S, 2, 600.0);
        let deepest = trace.iter().map(|t| t.1).fold(f64::INFINITY, f64::min);
        assert!(deepest >= -30.0 - 1e-9, "Z went {:.4} mm past the hole's bottom", -30.0 - deepest);
        assert!(deepest < -29.99, "Z stopped at {deepest} mm, short of the bottom the spindle's turns take it to");
    }

    #[test]
    fn the_spindle_follows_a_faulted_z_in_g92_1() {
        // G92.1 from Z2 to Z-28 at S600, lead 3: the spindle turns 3600° along; Z faults and
        // stops on its own 50 mm/s² ramp; the spindle keeps to it.
        let kind = MoveKind::RigidThread { end: Pos { x: 0.0, y: 0.0, z: -28.0, c: 3600.0 }, lead: 3.0, rpm: 600.0 };
        let (trace, cycles) = fault_in(kind, 300, 2, AX_S, 50.0);
        let (z0, th0) = trace[0];
        let worst = trace.iter().map(|&(z, th)| ((z0 - z) - 3.0 * (th - th0) / 360.0).abs()).fold(0.0, f64::max);
        assert!(worst < 0.003, "spindle kept to Z within {:.1} µm", worst * 1000.0);
        assert!(cycles < 800, "{cycles}");
    }
}
