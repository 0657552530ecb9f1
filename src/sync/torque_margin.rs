//! Whether the spindle has torque to spare for the acceleration it is commanded: a spindle
//! that gives a tap's acceleration only at its drive's torque limit keeps up in speed — the
//! acceleration it manages is the one asked, so `governor` sees nothing — but has nothing
//! left to correct its lag with. The lag grows for the whole ramp and the wound-up loop
//! overshoots where the tap turns to brake (0.114 kg·m² on 72 N·m at 5000 rpm/s: 70 N·m
//! throughout the S3000 ramp, 126° behind at its end, then 185° ahead while braking: alarm
//! 2010, the window 180°).
//!
//! So the torque is read where the drive gives its limit (CiA 402 max torque 0x6072 and
//! torque actual 0x6077, both per mille of the rated torque): [`CONFIRM`] cycles in a row at
//! [`NEAR_LIMIT`] of it or more, in the direction the spindle is commanded to accelerate (or
//! brake), find the acceleration it can give at its limit; `Motion` then plans with 80 % of
//! it, the running stroke too where it can still brake at that rate, as for `governor`.
//! Friction is counted as if it grew with the acceleration, so the rate found errs low.
//! A drive that gives no torque or no limit is never judged. O(1), no allocation.
//!
//! The manual is silent; a SINUMERIK 828D plans a rigid tap within the acceleration its
//! commissioning set (MD35210 GEAR_STEP_POSCTRL_ACCEL), a Fanuc 0i-TF stops with SV0411.

/// Share of the torque limit at which the drive counts as at its limit: a spindle sized for
/// its tap draws well under it after the ramp's first jerk.
const NEAR_LIMIT: f64 = 0.9;
/// Cycles in a row (the torque is read every other cycle) at the limit before it counts.
const CONFIRM: u32 = 10;
/// Largest change of the commanded acceleration from one cycle to the next (share of it)
/// that is judged: in a ramp's jerk phases the loop still draws torque to take up the lag the
/// jerk left, and the rate found there came out at about half the one at the limit (seed
/// 20261207's m41_heavy, during development).
const STEADY: f64 = 0.02;

/// The spindle's torque against its limit, tracked.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TorqueMargin {
    /// The last two set-points (degrees).
    last: Option<(f64, f64)>,
    /// The commanded acceleration of the last cycle (deg/s²).
    acc_last: f64,
    /// Cycles in a row at the limit.
    at_limit: u32,
    /// The sign of the ramp it was found in: the rest of that ramp is not judged again (its
    /// loop draws torque to take up the lag it built at the limit: 95 % of the limit at 80 %
    /// of the acceleration, m41).
    found_in: f64,
}

impl TorqueMargin {
    /// One cycle: `sent` the spindle set-point (degrees), `q` its torque as last read and
    /// `q_max` its limit (both × rated; NaN or ≤ 0 when unknown), `dt` the cycle (s).
    /// Returns the acceleration (deg/s², > 0) the spindle gives at its torque limit once it
    /// is found there, else None.
    pub fn update(&mut self, sent: f64, q: f64, q_max: f64, dt: f64) -> Option<f64> {
        let acc = self.commanded(sent, dt)?;
        let steady = (acc - std::mem::replace(&mut self.acc_last, acc)).abs() <= STEADY * acc.abs();
        let known = q.is_finite() && q_max.is_finite() && q_max > 0.0;
        if acc.signum() != self.found_in || acc == 0.0 {
            self.found_in = 0.0;
        }
        let judged = steady && acc != 0.0 && self.found_in == 0.0;
        let near = known && judged && q * acc.signum() >= NEAR_LIMIT * q_max;
        self.at_limit = if near { self.at_limit + 1 } else { 0 };
        if self.at_limit < CONFIRM {
            return None;
        }
        self.at_limit = 0;
        self.found_in = acc.signum();
        Some(acc.abs() * q_max / q.abs())
    }

    /// The commanded acceleration from the last three set-points (deg/s²).
    fn commanded(&mut self, sent: f64, dt: f64) -> Option<f64> {
        if !(sent.is_finite() && dt > 0.0) {
            *self = TorqueMargin::default();
            return None;
        }
        let prev = self.last;
        self.last = Some((prev.map_or(sent, |p| p.1), sent));
        let (s0, s1) = prev?;
        Some((sent - 2.0 * s1 + s0) / (dt * dt))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ramp of 30 000 °/s² (5000 rpm/s) reached over a jerk phase of 20 cycles, with the
    /// torque at `q` of a limit of 3 × rated: the cycle it is found at and what it gives at
    /// the limit.
    fn ramp(q: f64) -> Option<(usize, f64)> {
        let mut m = TorqueMargin::default();
        let (dt, mut v, mut p) = (0.002, 0.0, 0.0);
        (0..300).find_map(|k| {
            v += 30000.0 * (k as f64 / 20.0).min(1.0) * dt;
            p += v * dt;
            m.update(p, q, 3.0, dt).map(|a| (k, a))
        })
    }

    #[test]
    fn a_spindle_at_its_torque_limit_is_found_within_its_ramp() {
        let (k, a) = ramp(0.97 * 3.0).expect("found");
        // Not in the jerk phase; within 10 cycles of its end.
        assert!((30..=32).contains(&k), "found after {k} cycles");
        assert!((a - 30000.0 / 0.97).abs() < 1.0, "{a}");
    }

    #[test]
    fn a_spindle_with_torque_to_spare_or_without_a_limit_is_not_judged() {
        assert_eq!(ramp(0.8 * 3.0), None);
        assert_eq!(ramp(f64::NAN), None);
        // At its limit against the ramp (a torque that brakes it) is not short of torque for it.
        assert_eq!(ramp(-0.97 * 3.0), None);
        let mut m = TorqueMargin::default();
        assert!((0..300).all(|k| m.update(k as f64, 2.9, 3.0, 0.002).is_none()), "constant speed");
    }
}
