//! Whether the spindle drive can keep up the acceleration it is commanded *thermally*: a
//! spindle that has the torque for a tap's acceleration may still not have it for long. An
//! amplifier allows its peak torque for a few seconds (commonly 300 % of the rated torque for
//! 3 s) and trips on overload (EMCY 0x2310) past it; a S6000 tap over 200 mm accelerates or
//! brakes the spindle for almost all of its 5 s, and a spindle of 0.11 kg·m² on 70 N·m drew
//! 2.6 × its rated torque throughout and tripped near the top of the hole (drive matrix, air).
//!
//! The amplifier's overload is modelled as amplifiers rate it: I²t, the load ∫(q² − 1) dt
//! (q the torque in units of the rated torque, the load never below 0), which trips at
//! (q_peak² − 1)·t_peak. q comes from the drive's torque actual 0x6077 (per mille of its
//! rated torque 0x6076, CiA 402), as it is read (ten times a second on CANopen). Once the
//! load passes [`WARN_SHARE`] of the rating, the spindle's acceleration is capped where its
//! torque stays near [`Q_TARGET`] times the rated one: from the ratio of torque to commanded
//! acceleration seen at the highest acceleration so far (friction included, so the cap errs
//! on the slow side). A drive that reports no torque is never judged. O(1), no allocation.
//!
//! The manual is silent; a Fanuc 0i-TF leaves the rigid-tap acceleration to the machine
//! builder (No.5261) and alarms on the spindle amplifier's overload (SP9018-like); a
//! SINUMERIK 828D plans within the spindle's acceleration characteristic (MD35200).

/// Share of the amplifier's overload rating at which the acceleration is capped.
const WARN_SHARE: f64 = 0.25;
/// Share of the rating past which the cap cannot wait for the next stroke.
const URGENT_SHARE: f64 = 0.6;
/// Torque (× rated) the capped acceleration aims at: the load grows by q² − 1 = 1.25 per
/// second of acceleration, the rest of the rating lasts more than 14 s of it.
const Q_TARGET: f64 = 1.5;
/// Time constant with which the commanded acceleration is smoothed, s: the torque read is up
/// to one poll (0.1 s) old.
const ACC_SMOOTH_S: f64 = 0.05;
/// Share of the highest acceleration seen at which the torque-per-acceleration is taken.
const ACC_NEAR_PEAK: f64 = 0.8;

/// The spindle amplifier's overload load, tracked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpindleOverload {
    /// The rating: (q_peak² − 1)·t_peak, s.
    rating: f64,
    /// The load ∫(q² − 1) dt, ≥ 0, s.
    load: f64,
    /// The last two set-points (degrees) and the smoothed |commanded acceleration| (deg/s²).
    last: Option<(f64, f64)>,
    acc: f64,
    acc_peak: f64,
    /// Torque (× rated) per deg/s² seen near the highest acceleration.
    per_acc: f64,
}

impl SpindleOverload {
    /// An amplifier that allows `peak_pct` % of its rated torque for `peak_s` seconds.
    pub fn new(peak_pct: f64, peak_s: f64) -> SpindleOverload {
        let q = peak_pct / 100.0;
        let rating = if q > 1.0 && peak_s > 0.0 { (q * q - 1.0) * peak_s } else { f64::INFINITY };
        SpindleOverload { rating, load: 0.0, last: None, acc: 0.0, acc_peak: 0.0, per_acc: 0.0 }
    }

    /// One cycle: `sent` the spindle set-point (degrees), `q` its torque as last read (× rated;
    /// NaN when the drive gives none), `dt` the cycle (s). Returns the acceleration (deg/s²)
    /// to plan with from now on once the load passes its share of the rating, else None.
    pub fn update(&mut self, sent: f64, q: f64, dt: f64) -> Option<f64> {
        if !(sent.is_finite() && dt > 0.0) {
            self.last = None;
            return None;
        }
        if let Some((p1, p0)) = self.last {
            let a = ((sent - 2.0 * p1 + p0) / (dt * dt)).abs();
            self.acc += (a - self.acc) * (dt / ACC_SMOOTH_S).min(1.0);
        }
        self.last = Some((sent, self.last.map_or(sent, |l| l.0)));
        if !q.is_finite() {
            return None;
        }
        let q = q.abs();
        self.acc_peak = self.acc_peak.max(self.acc);
        if self.acc > 0.0 && self.acc >= ACC_NEAR_PEAK * self.acc_peak {
            self.per_acc = q / self.acc;
        }
        self.load = (self.load + (q * q - 1.0) * dt).max(0.0);
        (self.load > WARN_SHARE * self.rating && self.per_acc > 0.0).then(|| Q_TARGET / self.per_acc)
    }

    /// The load as a share of the rating (0 … 1 before a trip).
    pub fn share(&self) -> f64 {
        self.load / self.rating
    }

    /// The load is near the trip: the cap is needed now, not at the next stroke.
    pub fn urgent(&self) -> bool {
        self.share() > URGENT_SHARE
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spindle commanded a constant acceleration, its torque `q_of(acc)`: the cycles until
    /// a cap, and the cap.
    fn accelerate(ov: &mut SpindleOverload, acc: f64, q: f64, secs: f64) -> Option<(f64, f64)> {
        let dt = 0.002;
        let n = (secs / dt) as usize;
        for k in 0..n {
            let t = k as f64 * dt;
            if let Some(cap) = ov.update(0.5 * acc * t * t, q, dt) {
                return Some((t, cap));
            }
        }
        None
    }

    #[test]
    fn a_spindle_near_its_rated_torque_is_never_capped() {
        let mut ov = SpindleOverload::new(300.0, 3.0);
        // 1.3 × rated for a minute: the load grows by 0.69 per second, capped after 8.7 s —
        // at 1.5 / (1.3 / a), above what it is commanded: the plan is unchanged.
        let (_, cap) = accelerate(&mut ov, 30000.0, 1.3, 60.0).expect("the load passes a quarter");
        assert!(cap > 30000.0, "cap {cap}");
    }

    #[test]
    fn a_spindle_at_two_and_a_half_times_its_rating_is_capped_in_time() {
        let mut ov = SpindleOverload::new(300.0, 3.0);
        let (t, cap) = accelerate(&mut ov, 30000.0, 2.5, 10.0).expect("capped");
        // A quarter of 24 at 5.25 per second: 1.14 s, long before the trip (4.6 s).
        assert!((t - 1.14).abs() < 0.1, "t {t}");
        assert!((cap - 30000.0 * 1.5 / 2.5).abs() < 300.0, "cap {cap}");
        assert!(ov.share() < 0.3);
    }

    #[test]
    fn a_drive_without_torque_actual_is_never_judged() {
        let mut ov = SpindleOverload::new(300.0, 3.0);
        assert_eq!(accelerate(&mut ov, 30000.0, f64::NAN, 30.0), None);
        assert_eq!(ov.share(), 0.0);
    }
}
