//! G51.2/G50.2 polygon turning (manual 004 §2.8): a second rotary drive, the tool spindle,
//! turns at Q/P of the work spindle with phase R, so that a fly cutter on it cuts flats.
//!
//! The tool spindle is an optional axis of the machine config (`kind = "spindle"`,
//! `role = "tool_spindle"`), driven in position (CSP) every cycle. Its setpoint follows the
//! work spindle's **actual** angle, so that a work spindle slowed by the cut still meets the
//! cutter at the same phase:
//!
//! θ_tool* = (Q/P)·(θ_work,measured + ω_work,measured·H) + R
//!
//! where H bridges the feedback's age and the tool drive's own delay. H starts at two
//! feedback delays and is learnt online from the measured sync error
//! e = θ_tool,actual − (Q/P)·θ_work,actual − R (both actuals of the same instant) while the
//! spindles turn steadily — a slow integrator, never a cycle-by-cycle correction (the loop
//! through the drives is several cycles long). The setpoint moves towards θ_tool* within the
//! tool spindle's acceleration and speed limits (No.721 clamps the speed): after G51.2 it
//! runs up, then closes the phase by the shorter way (mod 360°); G50.2 (and reset, M30, a
//! controlled stop) brakes it to rest at its acceleration.
//!
//! Where the manual is silent, Fanuc 0i-TF: when S × Q/P would exceed the tool spindle's
//! clamp (No.721), the *work* spindle is slowed so that the ratio still holds (a polygon with
//! a slipping ratio is scrap), to 98 % of that so that the tool spindle keeps a margin for
//! holding the phase; likewise the work spindle's acceleration is limited to 75 % of what
//! the tool spindle can follow at the ratio (it sees the ramp a few cycles late). G51.2 starts the work spindle at S (M03 sense if it was
//! stopped). A machine without a tool spindle refuses G51.2 before any motion (alarm
//! [`NO_TOOL_SPINDLE`]).

use super::{alarms, Motion, AX_S};
use crate::canon::PolygonCmd;
use crate::config::MachineConfig;
use crate::Alarm;

use crate::alarm::NO_TOOL_SPINDLE;

/// Gain of the horizon's integrator per cycle (fraction of the error's equivalent time).
const H_GAIN: f64 = 0.05;
/// The horizon is learnt only while the work spindle turns faster than this, °/s (10 rpm).
const H_MIN_SPEED: f64 = 60.0;
/// ... and its measured speed changed by less than this since the last cycle, °/s.
const H_STEADY: f64 = 30.0;
/// Bounds of the horizon, s.
const H_MAX: f64 = 0.05;
/// Share of the tool spindle's speed and acceleration kept for holding the phase: the work
/// spindle's speed and acceleration are limited so that the ratio needs at most the rest.
const HEADROOM: f64 = 0.02;
/// The same for the acceleration: the tool spindle sees the work spindle's ramp only through
/// the feedback, a few cycles late, and needs room to catch up.
const ACCEL_HEADROOM: f64 = 0.25;

/// The tool spindle of a machine config: its drive index (configuration order, as the bus
/// orders drives) and limits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToolSpindle {
    pub drive: usize,
    /// Largest speed, °/s: the axis' max_speed, clamped by No.721 when set.
    pub vmax: f64,
    /// Largest acceleration, °/s².
    pub amax: f64,
}

impl ToolSpindle {
    /// The axis with `role = "tool_spindle"`, if the machine has one.
    pub fn from_config(cfg: &MachineConfig) -> Option<ToolSpindle> {
        let (drive, a) = cfg.tool_spindle()?;
        let mut rpm = a.max_speed;
        if let Some(c) = cfg.param(721).filter(|c| c.is_finite() && *c > 0.0) {
            rpm = rpm.min(c);
        }
        Some(ToolSpindle { drive, vmax: rpm * 6.0, amax: a.max_accel * 6.0 })
    }
}

/// The tool spindle's state inside [`Motion`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct ToolSync {
    present: bool,
    vmax: f64,
    amax: f64,
    /// Setpoint, ° (continuous), and its speed, °/s.
    pos: f64,
    vel: f64,
    /// (Q/P, R) while G51.2 is in force.
    lock: Option<(f64, f64)>,
    /// Prediction horizon H, s.
    horizon: f64,
    /// Measured tool spindle angle of this cycle (same instant as `Feedback::pos`).
    act: Option<f64>,
    /// Work spindle speed measured last cycle, °/s.
    w_prev: f64,
    /// Measured sync error of this cycle, ° of the tool spindle (0 when not locked).
    err: f64,
}

impl ToolSync {
    pub(super) fn none() -> ToolSync {
        ToolSync { present: false, vmax: 0.0, amax: 0.0, pos: 0.0, vel: 0.0, lock: None, horizon: 0.0, act: None, w_prev: 0.0, err: 0.0 }
    }

    pub(super) fn at_rest(&self) -> bool {
        self.lock.is_none() && self.vel == 0.0
    }

    pub(super) fn unlock(&mut self) {
        self.lock = None;
    }

    pub(super) fn pos(&self) -> f64 {
        self.pos
    }

    /// The work spindle's largest acceleration (°/s²) while locked: what the tool spindle can
    /// follow at the ratio, with [`HEADROOM`] left for holding the phase.
    pub(super) fn work_accel_cap(&self) -> f64 {
        match self.lock {
            Some((ratio, _)) if ratio > 0.0 => (1.0 - ACCEL_HEADROOM) * self.amax / ratio,
            _ => f64::INFINITY,
        }
    }

    /// One cycle: `th` the work spindle's measured angle, `w` its measured speed (°/s),
    /// `delay` the feedback's pairing delay (s).
    fn step(&mut self, th: f64, w: f64, dt: f64) {
        if !self.present {
            return;
        }
        let dv = self.amax * dt;
        let steady = (w - self.w_prev).abs() < H_STEADY;
        self.w_prev = w;
        self.err = 0.0;
        let v_target = match self.lock {
            Some((ratio, phase)) => {
                let target = ratio * (th + w * self.horizon) + phase;
                // Phase error left after this cycle's feed-forward step.
                let e = wrap(target - (self.pos + ratio * w * dt));
                // Learn H from the sync error of the actuals, at steady speed, while the
                // setpoint sits on its target (not while running up or closing the phase).
                if let Some(act) = self.act {
                    let es = wrap(act - ratio * th - phase);
                    self.err = es;
                    let wt = ratio * w;
                    if steady && w.abs() > H_MIN_SPEED && e.abs() < 1.0 && (self.vel - wt).abs() < H_STEADY * ratio {
                        self.horizon = (self.horizon - H_GAIN * es / wt).clamp(0.0, H_MAX);
                    }
                }
                // Feed-forward of the work spindle's speed, plus the phase error closed as
                // fast as half the acceleration allows (within one cycle once it is small).
                let corr = (self.amax * e.abs()).sqrt().min(e.abs() / dt);
                ratio * w + corr.copysign(e)
            }
            None => 0.0,
        };
        let v = if v_target.is_finite() { v_target } else { 0.0 };
        let mut nv = self.vel + (v - self.vel).clamp(-dv, dv);
        nv = nv.clamp(-self.vmax, self.vmax);
        if self.lock.is_none() && nv.abs() <= dv {
            nv = if self.vel.abs() <= dv { 0.0 } else { nv };
        }
        self.pos += nv * dt;
        self.vel = nv;
    }
}

/// Into (−180°, 180°].
fn wrap(a: f64) -> f64 {
    a - 360.0 * (a / 360.0).round()
}

impl Motion {
    /// Give motion the machine's tool spindle and where it stands (°). Without this call
    /// G51.2 is refused.
    pub fn set_tool_spindle(&mut self, t: &ToolSpindle, start_deg: f64) {
        let start = if start_deg.is_finite() { start_deg } else { 0.0 };
        self.tool = ToolSync {
            present: t.vmax > 0.0 && t.amax > 0.0,
            vmax: t.vmax.max(0.0),
            amax: t.amax.max(0.0),
            pos: start,
            vel: 0.0,
            lock: None,
            horizon: self.lim.feedback_delay as f64 * self.lim.cycle_s,
            act: None,
            w_prev: 0.0,
            err: 0.0,
        };
    }

    /// The tool spindle's measured angle this cycle (call before `step`, paired like
    /// `Feedback::pos`), for learning the prediction horizon.
    pub fn set_tool_feedback(&mut self, act_deg: f64) {
        self.tool.act = act_deg.is_finite().then_some(act_deg);
    }

    /// The tool spindle's setpoint (°) — also in every `Setpoint::tool_spindle`.
    pub fn tool_spindle(&self) -> f64 {
        self.tool.pos
    }

    /// Polygon sync error of the last cycle: measured tool angle − (Q/P·work angle + R),
    /// degrees of the tool spindle; 0 when not in G51.2 or without tool feedback.
    pub fn polygon_error(&self) -> f64 {
        self.tool.err
    }

    /// The learnt prediction horizon H (s).
    pub fn polygon_horizon(&self) -> f64 {
        self.tool.horizon
    }

    /// Check a G51.2/G50.2 at push.
    pub(super) fn check_polygon(&self, cmd: &Option<PolygonCmd>) -> Result<Option<PolygonCmd>, Alarm> {
        if !self.tool.present {
            return Err(Alarm::new(
                NO_TOOL_SPINDLE,
                "G51.2/G50.2 polygon turning needs a tool spindle: this machine's config has none; add an axis with kind = \"spindle\" and role = \"tool_spindle\" (see config/lathe-polygon.toml) or remove G51.2",
            ));
        }
        if !self.lim.present[AX_S] {
            return Err(Alarm::new(NO_TOOL_SPINDLE, "G51.2 polygon turning needs a work spindle in the config"));
        }
        if let Some(c) = cmd {
            let ok = c.p > 0 && c.q > 0 && c.phase.is_finite() && c.rpm.is_finite() && c.rpm > 0.0 && c.tool_rpm.is_finite() && c.tool_rpm > 0.0;
            if !ok {
                return Err(Alarm::new(alarms::BAD_VALUE, format!("G51.2 P{} Q{} R{} S{}: P, Q and S must be > 0", c.p, c.q, c.phase, c.rpm)));
            }
        }
        Ok(*cmd)
    }

    /// Take a G51.2/G50.2 in program order.
    pub(super) fn apply_polygon(&mut self, c: Option<PolygonCmd>) {
        match c {
            Some(c) => {
                let ratio = c.q as f64 / c.p as f64;
                // The ratio must hold: a tool spindle clamped (No.721, or its max) slows the
                // work spindle with it.
                let tool_max = (c.tool_rpm.min(self.tool.vmax / 6.0)).max(0.0) * (1.0 - HEADROOM);
                self.sp_rpm = c.rpm.min(tool_max / ratio);
                self.sp_css = None;
                if self.sp_dir == 0.0 {
                    self.sp_dir = 1.0;
                }
                self.tool.lock = Some((ratio, c.phase));
            }
            None => self.tool.lock = None,
        }
    }

    /// The tool spindle's cycle (called once per `step`, after the work spindle's).
    pub(super) fn step_tool(&mut self, th: f64, w: f64) {
        if self.stopping {
            self.tool.lock = None;
        }
        let (th, w) = if th.is_finite() && w.is_finite() { (th, w) } else { (self.pos[AX_S], 0.0) };
        self.tool.step(th, w, self.lim.cycle_s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sync(ratio: f64, phase: f64) -> ToolSync {
        ToolSync {
            present: true,
            vmax: 6000.0 * 6.0,
            amax: 6000.0 * 6.0,
            pos: 17.0,
            vel: 0.0,
            lock: Some((ratio, phase)),
            horizon: 0.0,
            act: None,
            w_prev: 0.0,
            err: 0.0,
        }
    }

    /// Ideal: a work spindle at a steady 1000 rpm read without delay; the tool runs up,
    /// then sits on Q/P·θ + R (mod 360) to rounding, within its acceleration throughout.
    #[test]
    fn locks_to_ratio_and_phase_within_the_acceleration() {
        let dt = 0.002;
        let mut t = sync(2.0, 60.0);
        let w = 6000.0;
        let mut th = 5.0;
        let mut worst_after = 0.0f64;
        let mut vprev = 0.0;
        for k in 0..2000 {
            th += w * dt;
            t.step(th, w, dt);
            assert!((t.vel - vprev).abs() <= t.amax * dt * (1.0 + 1e-9), "cycle {k}: jump {}", t.vel - vprev);
            vprev = t.vel;
            if k > 1000 {
                worst_after = worst_after.max(wrap(t.pos - (2.0 * th + 60.0)).abs());
            }
        }
        assert!(worst_after < 1e-6, "phase error {worst_after}°");
        // G50.2: brakes to rest.
        t.lock = None;
        for _ in 0..1000 {
            t.step(th, w, dt);
        }
        assert!(t.at_rest());
    }

    #[test]
    fn speed_is_clamped() {
        let dt = 0.002;
        let mut t = sync(3.0, 0.0);
        t.vmax = 1000.0 * 6.0;
        let w = 6000.0; // ×3 = 3000 rpm asked, 1000 allowed
        let mut th = 0.0;
        for _ in 0..2000 {
            th += w * dt;
            t.step(th, w, dt);
            assert!(t.vel.abs() <= t.vmax + 1e-9);
        }
    }
}
