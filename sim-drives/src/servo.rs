//! One motor, its load and the drive's control cascade: position loop (P, gain Kv, with
//! velocity feed-forward) → velocity loop (PI) → torque (limited) → rigid inertia with
//! Coulomb and viscous friction. The encoder reports whole counts of the position unit; the
//! position loop closes on those. The velocity loop closes on a speed estimated as real
//! drives do it: the difference of a finer internal encoder reading (2^speed_encoder_bits
//! per rev) per control tick, low-pass filtered.

use crate::config::Physics;
use std::f64::consts::PI;

/// What the control cascade is asked to do this tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// Power stage off: no torque, the load coasts.
    Off,
    /// Follow a position demand (counts, unwrapped) with a velocity feed-forward (counts/s).
    Position { demand: f64, vff: f64 },
    /// Follow a velocity (counts/s) with the velocity loop only.
    Velocity { v: f64 },
}

#[derive(Clone, Debug)]
pub struct Servo {
    p: Physics,
    /// rad per count.
    rad_per_count: f64,
    /// Motor position in counts, continuous and unwrapped.
    pos: f64,
    /// Motor speed, rad/s.
    omega: f64,
    /// Torque the velocity loop asks for (held between ticks), N·m.
    torque_cmd: f64,
    /// Torque the current loop delivers (first-order lag behind the command), N·m.
    torque: f64,
    /// Velocity-loop integrator, N·m.
    integ: f64,
    /// Velocity reference of the last tick, rad/s (for logs and tests).
    vref: f64,
    /// Internal encoder reading at the last tick (whole increments) and the filtered speed
    /// estimate the velocity loop uses, rad/s.
    enc_prev: f64,
    omega_est: f64,
    /// External load torque (fault injection: gravity, a cutting force), N·m.
    pub load_torque: f64,
    /// Extra dry friction (fault injection: a jammed slide, a crashed tool), N·m.
    pub jam_friction: f64,
    /// Torque offset the master sends with its position set-points (CSP's 0x60B2), N·m:
    /// added to what the velocity loop asks for, in position control only.
    pub torque_offset: f64,
    /// Position quantum of a coarse encoder, counts (1 = the position unit's own count).
    quantum: f64,
    /// Behind a compliance (`Extra::load_stiffness`): the load's position (counts, motor
    /// side) and speed (rad/s).
    load_pos: f64,
    load_omega: f64,
}

impl Servo {
    pub fn new(p: Physics, counts_per_rev: u32) -> Servo {
        let enc = p.extra.encoder_counts_per_rev;
        let quantum = if enc > 0 { (counts_per_rev.max(1) as f64 / enc as f64).max(1.0) } else { 1.0 };
        Servo {
            quantum,
            load_pos: 0.0,
            load_omega: 0.0,
            p,
            rad_per_count: 2.0 * PI / counts_per_rev.max(1) as f64,
            pos: 0.0,
            omega: 0.0,
            torque_cmd: 0.0,
            torque: 0.0,
            integ: 0.0,
            vref: 0.0,
            enc_prev: 0.0,
            omega_est: 0.0,
            load_torque: 0.0,
            jam_friction: 0.0,
            torque_offset: 0.0,
        }
    }

    pub fn physics(&self) -> &Physics {
        &self.p
    }

    /// Encoder reading: whole counts, unwrapped (whole encoder lines of a coarse encoder).
    pub fn position_counts(&self) -> i64 {
        self.read_pos() as i64
    }

    /// What the encoder reads, in counts.
    fn read_pos(&self) -> f64 {
        if self.quantum == 1.0 {
            self.pos.floor()
        } else {
            (self.pos / self.quantum).floor() * self.quantum
        }
    }

    /// Exact position (counts), for tests and plots.
    pub fn position_exact(&self) -> f64 {
        self.pos
    }

    /// Speed in counts/s.
    pub fn velocity_counts(&self) -> f64 {
        self.omega / self.rad_per_count
    }

    pub fn torque(&self) -> f64 {
        self.torque
    }

    /// Put the motor at a position (power-on offset of an absolute encoder).
    pub fn set_position(&mut self, counts: f64) {
        self.load_pos += counts - self.pos;
        self.pos = counts;
        self.enc_prev = self.encoder();
    }

    /// True at standstill as a drive's speed window sees it (below ~1 rpm).
    pub fn at_rest(&self) -> bool {
        self.omega.abs() < 0.1
    }

    /// The fine internal encoder: whole increments of 2π / 2^speed_encoder_bits.
    fn encoder(&self) -> f64 {
        let per_rad = (self.p.speed_encoder_bits.min(40) as f64).exp2() / (2.0 * PI);
        (self.pos * self.rad_per_count * per_rad).floor()
    }

    /// Speed estimate (counts/s) as the velocity loop sees it and 0x606C reports it.
    pub fn velocity_estimate_counts(&self) -> f64 {
        self.omega_est / self.rad_per_count
    }

    /// One control tick: compute the torque held until the next tick.
    pub fn control(&mut self, cmd: Command, dt: f64) {
        // Speed from encoder increments per tick, filtered (first order).
        let enc = self.encoder();
        if dt > 0.0 {
            let per_rad = (self.p.speed_encoder_bits.min(40) as f64).exp2() / (2.0 * PI);
            let raw = (enc - self.enc_prev) / per_rad / dt;
            let tf = self.p.speed_filter_ms * 1e-3;
            let a = if tf > 0.0 { 1.0 - (-dt / tf).exp() } else { 1.0 };
            self.omega_est += (raw - self.omega_est) * a;
        }
        self.enc_prev = enc;
        let vmax = self.p.max_speed_rpm * 2.0 * PI / 60.0;
        let vref_counts = match cmd {
            Command::Off => {
                // Power stage off: the current decays at once (the bridge is open).
                self.torque_cmd = 0.0;
                self.torque = 0.0;
                self.integ = 0.0;
                self.vref = 0.0;
                return;
            }
            Command::Position { demand, vff } => {
                // The loop closes on whole encoder counts, as the drive sees them.
                let e = demand - self.read_pos();
                self.p.velocity_ff * vff + self.p.kv * e
            }
            Command::Velocity { v } => v,
        };
        let toff = if matches!(cmd, Command::Position { .. }) { self.torque_offset } else { 0.0 };
        let vref = (vref_counts * self.rad_per_count).clamp(-vmax, vmax);
        self.vref = vref;
        let err = vref - self.omega_est;
        let ki = self.p.vel_kp / (self.p.vel_ti_ms * 1e-3);
        let lim = self.p.torque_limit;
        let unsat = self.p.vel_kp * err + self.integ + toff;
        // Conditional integration (anti-windup): stop integrating into the limit.
        let saturating = (unsat >= lim && err > 0.0) || (unsat <= -lim && err < 0.0);
        if !saturating {
            self.integ = (self.integ + ki * err * dt).clamp(-lim, lim);
        }
        self.torque_cmd = (self.p.vel_kp * err + self.integ + toff).clamp(-lim, lim);
    }

    /// Integrate the mechanics over `dt` seconds with the held torque.
    pub fn integrate(&mut self, dt: f64) {
        if dt <= 0.0 {
            return;
        }
        // Current loop: first-order lag of the torque behind its command.
        let tau = self.p.current_loop_tc_ms * 1e-3;
        let a = if tau > 0.0 { 1.0 - (-dt / tau).exp() } else { 1.0 };
        self.torque += (self.torque_cmd - self.torque) * a;
        if self.p.extra.load_stiffness > 0.0 {
            self.integrate_two_mass(dt);
            return;
        }
        let j = self.p.inertia();
        let tc = self.p.coulomb_friction + self.jam_friction;
        let drive = self.torque - self.load_torque;
        let w0 = self.omega;
        let w1 = if w0 == 0.0 {
            if drive.abs() <= tc {
                0.0 // sticking: dry friction takes up the whole torque
            } else {
                let net = drive - tc * drive.signum();
                net / j * dt
            }
        } else {
            // Viscous part implicit (stable for any dt), Coulomb explicit.
            let b = self.p.viscous_friction;
            let w = (j * w0 + dt * (drive - tc * w0.signum())) / (j + dt * b);
            if w.signum() != w0.signum() && drive.abs() <= tc {
                0.0 // crossed zero and friction holds it there
            } else {
                w
            }
        };
        self.pos += 0.5 * (w0 + w1) * dt / self.rad_per_count;
        self.omega = w1;
        self.load_pos = self.pos;
        self.load_omega = w1;
    }

    /// Motor and load joined by a spring with damping and lost motion (a belt, a long screw
    /// with a backlash): the motor carries its rotor, the load side its inertia, the friction
    /// and the process load. Semi-implicit Euler (stable at the 50 µs step for resonances up
    /// to a few hundred Hz).
    fn integrate_two_mass(&mut self, dt: f64) {
        let x = self.p.extra;
        let half_gap = x.backlash_deg.to_radians() * 0.5;
        let twist = (self.pos - self.load_pos) * self.rad_per_count;
        let engaged = twist.abs() > half_gap;
        let spring =
            if engaged { x.load_stiffness * (twist - half_gap * twist.signum()) + x.load_damping * (self.omega - self.load_omega) } else { 0.0 };
        let jm = self.p.motor_inertia;
        self.omega += (self.torque - spring) / jm * dt;
        self.pos += self.omega * dt / self.rad_per_count;
        let jl = self.p.load_inertia.max(1e-9);
        let tc = self.p.coulomb_friction + self.jam_friction;
        let drive = spring - self.load_torque;
        let w0 = self.load_omega;
        let w1 = if w0 == 0.0 {
            if drive.abs() <= tc {
                0.0
            } else {
                (drive - tc * drive.signum()) / jl * dt
            }
        } else {
            let b = self.p.viscous_friction;
            let w = (jl * w0 + dt * (drive - tc * w0.signum())) / (jl + dt * b);
            if w.signum() != w0.signum() && drive.abs() <= tc {
                0.0
            } else {
                w
            }
        };
        self.load_pos += 0.5 * (w0 + w1) * dt / self.rad_per_count;
        self.load_omega = w1;
    }

    /// The load's position behind the compliance, counts (the motor's when rigid).
    pub fn load_position_exact(&self) -> f64 {
        self.load_pos
    }
}

/// Step response of a servo model: position step of `step` counts with no feed-forward,
/// sampled every `dt`. Returns (rise time 10→90 % in s, overshoot in % of the step,
/// settling time into ±1 count in s, final error in counts).
pub fn step_response(p: &Physics, counts_per_rev: u32, step: f64, dt: f64, t_end: f64) -> (f64, f64, f64, f64) {
    let mut s = Servo::new(p.clone(), counts_per_rev);
    let n = (t_end / dt).ceil() as usize;
    let (mut t10, mut t90) = (None, None);
    let mut peak = 0.0f64;
    let mut settle = 0.0;
    for i in 0..n {
        let t = i as f64 * dt;
        s.control(Command::Position { demand: step, vff: 0.0 }, dt);
        s.integrate(dt);
        let x = s.position_exact();
        if t10.is_none() && x >= 0.1 * step {
            t10 = Some(t);
        }
        if t90.is_none() && x >= 0.9 * step {
            t90 = Some(t);
        }
        peak = peak.max(x);
        if (s.position_counts() as f64 - step).abs() > 1.0 {
            settle = t + dt;
        }
    }
    let rise = match (t10, t90) {
        (Some(a), Some(b)) => b - a,
        _ => f64::INFINITY,
    };
    let overshoot = ((peak - step) / step * 100.0).max(0.0);
    (rise, overshoot, settle, s.position_counts() as f64 - step)
}

/// The position step response sampled every `every` seconds: (t, position counts).
pub fn step_trace(p: &Physics, counts_per_rev: u32, step: f64, dt: f64, t_end: f64, every: f64) -> Vec<(f64, f64)> {
    let mut s = Servo::new(p.clone(), counts_per_rev);
    let n = (t_end / dt).ceil() as usize;
    let k = ((every / dt).round() as usize).max(1);
    let mut out = vec![(0.0, 0.0)];
    for i in 1..=n {
        s.control(Command::Position { demand: step, vff: 0.0 }, dt);
        s.integrate(dt);
        if i % k == 0 {
            out.push((i as f64 * dt, s.position_exact()));
        }
    }
    out
}

/// Velocity-loop step response: speed step of `v` counts/s from standstill. Returns
/// (rise time 10→90 % in s, overshoot in %).
pub fn velocity_step_response(p: &Physics, counts_per_rev: u32, v: f64, dt: f64, t_end: f64) -> (f64, f64) {
    let mut s = Servo::new(p.clone(), counts_per_rev);
    let (mut t10, mut t90, mut peak) = (None, None, 0.0f64);
    for i in 0..(t_end / dt).ceil() as usize {
        let t = i as f64 * dt;
        s.control(Command::Velocity { v }, dt);
        s.integrate(dt);
        let x = s.velocity_counts();
        if t10.is_none() && x >= 0.1 * v {
            t10 = Some(t);
        }
        if t90.is_none() && x >= 0.9 * v {
            t90 = Some(t);
        }
        peak = peak.max(x);
    }
    let rise = match (t10, t90) {
        (Some(a), Some(b)) => b - a,
        _ => f64::INFINITY,
    };
    (rise, ((peak - v) / v * 100.0).max(0.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DriveKind;

    fn run_to(s: &mut Servo, demand: f64, secs: f64) {
        let dt = 50e-6;
        for _ in 0..(secs / dt) as usize {
            s.control(Command::Position { demand, vff: 0.0 }, dt);
            s.integrate(dt);
        }
    }

    #[test]
    fn settles_within_one_count_with_friction() {
        for kind in [DriveKind::Linear, DriveKind::Spindle] {
            let p = Physics::default_for(kind);
            assert!(p.coulomb_friction > 0.0);
            let mut s = Servo::new(p, 100_000);
            for target in [1000.0, 1003.0, -257.0, 0.0, 1.0] {
                run_to(&mut s, target, 1.5);
                let e = s.position_counts() as f64 - target;
                assert!(e.abs() <= 1.0, "{kind:?} target {target}: error {e} counts");
                // And it stays there (no limit cycle walking away).
                run_to(&mut s, target, 0.5);
                let e = s.position_counts() as f64 - target;
                assert!(e.abs() <= 1.0, "{kind:?} target {target} later: error {e} counts");
            }
        }
    }

    #[test]
    fn settles_within_one_count_with_heavy_friction() {
        // Five times the default dry friction (a tight gib, cold grease): the integrator
        // must still push it onto the count without hunting.
        for kind in [DriveKind::Linear, DriveKind::Spindle] {
            let mut p = Physics::default_for(kind);
            p.coulomb_friction *= 5.0;
            p.viscous_friction *= 3.0;
            let mut s = Servo::new(p, 100_000);
            for target in [50_000.0, 50_017.0, 49_999.0, -3.0] {
                run_to(&mut s, target, 2.0);
                let mut worst = 0.0f64;
                for _ in 0..4 {
                    run_to(&mut s, target, 0.25);
                    worst = worst.max((s.position_counts() as f64 - target).abs());
                }
                assert!(worst <= 1.0, "{kind:?} target {target}: error up to {worst} counts");
            }
        }
    }

    /// Cycles (2 ms) before a linear axis at rest leaves its count when its set-point starts
    /// to creep (0.25 counts per cycle) with four times the default dry friction.
    fn breakaway_cycles(offset: f64) -> usize {
        let mut p = Physics::default_for(DriveKind::Linear);
        p.coulomb_friction *= 4.0;
        let tc = p.coulomb_friction;
        let mut s = Servo::new(p, 100_000);
        s.torque_offset = offset * tc;
        let dt = 50e-6;
        for cycle in 0..200 {
            for _ in 0..40 {
                let demand = 0.25 * (cycle as f64 + 1.0);
                s.control(Command::Position { demand, vff: 125.0 }, dt);
                s.integrate(dt);
            }
            if s.position_exact() > 0.5 {
                return cycle;
            }
        }
        200
    }

    #[test]
    fn a_torque_offset_the_size_of_the_dry_friction_breaks_the_stiction_at_once() {
        // CSP's 0x60B2 (the master's friction feed-forward): the velocity loop's integrator no
        // longer has to wind up through the friction before the slide moves.
        let (without, with) = (breakaway_cycles(0.0), breakaway_cycles(1.0));
        eprintln!("breakaway after {with} cycles with the offset, {without} without");
        assert!(with + 3 <= without, "breakaway after {with} cycles with the offset, {without} without");
    }

    #[test]
    fn dry_friction_holds_a_small_torque() {
        let p = Physics::default_for(DriveKind::Linear);
        let mut s = Servo::new(p.clone(), 100_000);
        s.load_torque = 0.5 * p.coulomb_friction;
        s.control(Command::Off, 1e-3);
        for _ in 0..1000 {
            s.integrate(1e-4);
        }
        assert_eq!(s.position_exact(), 0.0);
        s.load_torque = 2.0 * p.coulomb_friction;
        for _ in 0..1000 {
            s.integrate(1e-4);
        }
        assert!(s.position_exact() < -1.0, "a load above the friction moves it");
    }

    #[test]
    fn step_responses_are_servo_like() {
        let lin = step_response(&Physics::default_for(DriveKind::Linear), 100_000, 1000.0, 50e-6, 1.0);
        let sp = step_response(&Physics::default_for(DriveKind::Spindle), 360_000, 1000.0, 50e-6, 2.0);
        // Kv = 50 → first-order-like rise ≈ 2.2/Kv = 44 ms; the spindle's Kv = 20 → ≈ 110 ms.
        assert!(lin.0 > 0.02 && lin.0 < 0.08, "linear rise {lin:?}");
        assert!(sp.0 > 0.06 && sp.0 < 0.25, "spindle rise {sp:?}");
        assert!(lin.1 < 10.0 && sp.1 < 15.0, "overshoot {lin:?} {sp:?}");
        assert!(lin.3.abs() <= 1.0 && sp.3.abs() <= 1.0);
        assert!(sp.0 > lin.0, "the spindle is the slower axis");
    }
}
