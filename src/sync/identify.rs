//! Identification of a drive's response to its cyclic set-points (commissioning): from the
//! set-points sent and the actual positions received every cycle, the model
//!
//! ```text
//!   y(s) = e^(−sT) · F(s) · (ff·τ·s + 1)/(τ·s + 1) · u(s)
//! ```
//!
//! — a pure delay `T` (transport, the drive's interpolation over a period, the feedback's own
//! cycle, as the controller sees them), the drive's fast inner loops `F` (velocity and current
//! loop: unity gain at rest, no lag of their own at constant speed — a PI velocity loop has
//! none), a share `ff` that follows at once (velocity feed-forward) and the rest through the
//! position loop's lag `τ` (≈ 1/Kv: the dominant pole of the closed cascade).
//!
//! How: (1) the dead time `d` (whole cycles) where the demand's speed turns a corner while the
//! axis moves one way (or from the step response of a plain ARX model, or where that is the
//! encoder's noise from the output-error fit's residual over whole delays; see `dead_time`);
//! (2) the following error `e = u(k−d) − y(k)` is fitted *output-error* (no measured output
//! among the regressors, so encoder quantisation does not bias it) as the command increments
//! through a slow pole τ and a fast second-order section (the velocity loop, oscillatory or
//! not) with a few free taps — least squares (nalgebra) for the taps, a grid and a pattern
//! search for the poles — plus a second input with its own taps through the same poles, the
//! sign of the demand's speed (dry friction: a torque step wherever the axis starts, stops or
//! reverses, as large in the error of a stiff feed axis as the position loop's own part) —
//! on every row and again without the rows where friction makes the response non-linear
//! (`linear_rows`), the shorter τ kept — and without the settling after the stops where that
//! settles otherwise than the axis moves (a slide stuck behind a belt, `SETTLES_APART`).
//! Fitting `e` rather than the increments matters: with
//! ff ≈ 0.995 the position loop carries half a percent of the motion but all of the following
//! error. (3) `ff` from the
//! error's gain at constant speed, `e = (1 − ff)·τ·v`; (4) `T` in the first-moment sense: the
//! velocity lag regressed on the data minus `(1 − ff)·τ`. A delay that is not a whole number of
//! cycles shows in the velocity lag (exactly) but is attributed to `ff` (by `f·dt/τ`), not to
//! `T`. Fit quality: the variance of the position increments the model accounts for (VAF).
//!
//! Derived: the velocity lag (actual ≈ command delayed by `T + (1 − ff)·τ` at constant
//! speed), what a following-error window must at least allow at the axis' maximum speed.

use nalgebra::{DMatrix, DVector};

/// A drive's identified response.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Response {
    /// The pure delay `T` in whole cycles (the fraction is in `delay_fraction`): the part of
    /// the lag at constant speed that the position loop does not explain.
    pub delay_cycles: u32,
    /// The part of a cycle beyond `delay_cycles`, 0 … 1.
    pub delay_fraction: f64,
    /// The share of a speed change that follows at once (velocity feed-forward).
    pub feed_forward: f64,
    /// Time constant of the rest, s.
    pub time_constant_s: f64,
    /// Variance of the position increments the model accounts for, 0 … 1.
    pub vaf: f64,
    /// Lag of the actual position behind the command at constant speed, s: regressed on
    /// the data directly (lag = T·v + A·a), so that it holds where the first-order model is
    /// only an approximation (a velocity loop that overshoots, a compliance).
    pub velocity_lag: f64,
    /// The drive's own lag per unit of acceleration, s²: its following error (demand after
    /// the delay − actual) regressed on the demand's speed and acceleration
    /// (`regress_own_lag`). A second-order drive with full feed-forward lags nothing at
    /// constant speed and a·τ² while it accelerates; a first-order model cannot say so.
    pub accel_lag: f64,
    /// Samples used.
    pub samples: usize,
}

impl Response {
    /// Lag of the actual position behind the command at constant speed, s (the regressed
    /// one; the model's own is `(d + f)·dt + (1 − ff)·τ`).
    pub fn velocity_lag_s(&self, _dt: f64) -> f64 {
        self.velocity_lag
    }

    /// The model's own lag at constant speed, s.
    pub fn velocity_lag_model(&self, dt: f64) -> f64 {
        (self.delay_cycles as f64 + self.delay_fraction) * dt + (1.0 - self.feed_forward) * self.time_constant_s
    }
}

/// The dead time in whole cycles. Dry friction fools a fit over the whole run: where the
/// axis starts from rest it sticks until the drive's integrator breaks it away, which reads
/// as delay, and the plain ARX model's step response then crosses its threshold a cycle early
/// (two-fold friction on Z: 5–7 % one cycle before the drive acts, 2.6 % without friction).
/// So the dead time is read first at the corners of the demand's speed where the axis is
/// moving one way throughout (the friction is then a constant torque the integrator holds):
/// the first lag at which the actual speed departs from its own trend by `ANSWER` of the
/// corner — the median over the corners. Where there are fewer than two, None: `identify`
/// asks the ARX fit or the output-error fit (`corners_resolved` says which first). Where the
/// corners and the ARX step both read, the later
/// of the two: each fails early, never late — friction the ARX step (above), and a belt
/// still ringing from the last speed change the corners (belt_kv15: lags 0, 0, 1, 2, median
/// 1 for 2; on probe belts and a random mix 1, 1, 2 and 3, 3, 4 — the ARX step read 2 and 4
/// in each; which corners answer early moved with a 3 % faster excitation).
fn dead_time(du: &[f64], dy: &[f64], max_delay: usize) -> Option<usize> {
    let mut lags = corners(du, dy, max_delay);
    lags.sort_unstable();
    if lags.len() < 2 {
        return None;
    }
    Some(lags[lags.len() / 2].max(dead_time_arx(du, dy, max_delay).unwrap_or(0)))
}

/// The share of a corner the actual speed must show (as the ARX step threshold).
const ANSWER: f64 = 0.04;
/// The least corner, in encoder counts per cycle per cycle, whose 4 % stands above one count.
const RESOLVED: f64 = 25.0;

/// The encoder's quantum: the least step the actual position makes (`steps` its increments).
fn quantum(steps: impl Iterator<Item = f64>) -> f64 {
    steps.map(f64::abs).filter(|v| *v > 0.0).fold(f64::INFINITY, f64::min)
}

/// Whether the encoder resolves the demand's sharpest corner (see `RESOLVED`). Where it does
/// not (a spindle encoder of 4096–16384 counts), the ARX step read the delay a cycle or two
/// early in three spindles of 28 (16384 counts, 0.059 kg·m²: 1 for 2; with two cycles of
/// transport delay 1 for 4) where the output-error fit read it right; where it does (a belt
/// with 90 % feed-forward, its corners ringing) the ARX step is right and the output-error
/// fit a cycle late.
fn corners_resolved(du: &[f64], dy: &[f64]) -> bool {
    let q = quantum(dy.iter().copied());
    du.windows(2).any(|w| (w[1] - w[0]).abs() >= RESOLVED * q)
}

/// The answer's lag at each clean corner of the demand's speed (see `dead_time`).
fn corners(du: &[f64], dy: &[f64], max_delay: usize) -> Vec<usize> {
    let n = du.len().min(dy.len());
    let q = quantum(dy.iter().copied());
    let mut lags = vec![];
    for k in 4..n.saturating_sub(max_delay + 1) {
        let c = du[k] - du[k - 1];
        // Steady for two cycles before; the axis moving one way from three before to the end.
        let steady = (du[k - 1] - du[k - 2]).abs() <= 0.01 * c.abs() && (du[k - 2] - du[k - 3]).abs() <= 0.01 * c.abs();
        let moving = (k - 3..=k + max_delay).all(|j| dy[j].abs() >= 0.5 * q && dy[j].signum() == dy[k - 3].signum());
        if !(c.abs() >= RESOLVED * q) || !steady || !moving {
            continue;
        }
        // The actual speed's own trend carries on (a slow drive still converging on the
        // last speed): the answer is what departs from it.
        let slope = (dy[k - 1] - dy[k - 3]) / 2.0;
        let answer = |j: usize| (dy[k + j] - dy[k - 1] - slope * (j + 1) as f64) * c.signum();
        // Held for two cycles: a lightly damped belt still ringing from the last speed change
        // crosses the threshold for a cycle before the drive answers (lags 1, 0, 2 on a belt
        // with 0.5° of lost motion: the median read 1 cycle for 2).
        let thr = (ANSWER * c.abs()).max(q);
        if let Some(j) = (0..=max_delay).find(|j| answer(*j) >= thr && answer(*j + 1) >= thr) {
            lags.push(j);
        }
    }
    lags
}

/// The dead time in whole cycles from the data as a whole (where `corners` has too few): the
/// first lag at which the actual answers a speed step with at least 4 % of it, on the step
/// response of a plain ARX model of the increments (four poles, inputs at lags 0 …
/// `max_delay + 6`). A drive that interpolates its set-point over the period answers in the
/// first period it acts (the emulator: ≈ 10–20 % of the step), so the threshold sits well
/// above the noise and below that.
fn dead_time_arx(du: &[f64], dy: &[f64], max_delay: usize) -> Option<usize> {
    let (na, nb) = (4, max_delay + 6);
    let n = du.len().min(dy.len());
    let k0 = na.max(nb);
    if n <= k0 + 2 * (na + nb) {
        return None;
    }
    let rows: Vec<usize> = (k0..n).collect();
    let phi = DMatrix::from_fn(rows.len(), na + nb, |r, c| if c < na { dy[rows[r] - 1 - c] } else { du[rows[r] - (c - na)] });
    let rhs = DVector::from_fn(rows.len(), |r, _| dy[rows[r]]);
    let x = phi.svd(true, true).solve(&rhs, 1e-14).ok()?;
    let mut step = vec![0.0; nb + 40];
    for k in 0..step.len() {
        let back: f64 = (0..na).filter(|i| k > *i).map(|i| x[i] * step[k - 1 - i]).sum();
        let input: f64 = (0..nb.min(k + 1)).map(|j| x[na + j]).sum();
        step[k] = back + input;
    }
    let fin = *step.last()?;
    if !(fin.abs() > 0.0) {
        return None;
    }
    let at = step.iter().position(|v| *v / fin >= ANSWER)?;
    // A step response that swings below zero first is the encoder's noise, not the drive.
    let clean = step[..(at + 2).min(step.len())].iter().all(|v| *v / fin >= -ANSWER);
    clean.then_some(at.min(max_delay))
}

/// Above the least residual by this factor, a whole delay does not fit (see `dead_time_oe`).
const DELAY_FITS: f64 = 1.2;

/// The dead time where neither the corners nor the ARX step response show it (a spindle
/// encoder of 4096 counts: its speed corners, hundredths of a degree per cycle², are far
/// below a count, and the ARX step swings ±70 % in its first cycles): the output-error fit
/// (`fit_poles`) for each whole delay from 0 up, the longest whose residual is within
/// `DELAY_FITS` of the least. One cycle less than the drive's fits as well (ff takes it up:
/// 0.961 for 0.998), one more does not (it asks for an answer before the drive acts:
/// residual ×2–12 on 4096–16384 counts; at 1.5 a Kv 21/s spindle with 96 % feed-forward read
/// a cycle late at 1.31). Not the rule where the data are clean: a soft spindle (Kv 8–12/s)
/// fits a cycle more within 1–20 % — and on a coarse encoder too (Kv 11–13/s, 97 %
/// feed-forward, 16384 counts: within 1 %, read a cycle late; not resolved).
fn dead_time_oe(cmd: &[f64], act: &[f64], dt: f64, max_delay: usize, keep: &[bool]) -> Option<usize> {
    let mut sse: Vec<f64> = vec![];
    for d in 0..=max_delay {
        let fit = fit_poles(cmd, act, d, dt, keep).and_then(|(t, w, z)| oe(cmd, act, d, (-dt / t).exp(), second_order(w, z, dt), keep));
        let e = fit.map_or(f64::INFINITY, |r| r.0);
        let least = sse.iter().copied().fold(f64::INFINITY, f64::min);
        sse.push(e);
        // Past the drive's delay the residual only grows.
        if e > DELAY_FITS * least {
            break;
        }
    }
    let least = sse.iter().copied().fold(f64::INFINITY, f64::min);
    least.is_finite().then(|| sse.iter().rposition(|e| *e <= DELAY_FITS * least)).flatten()
}

/// FIR taps on the filtered command in the output-error fit (the fast part's zeros).
const FAST_TAPS: usize = 5;

/// The denominator (a1, a2) of a second-order section `1 / (1 − a1·z⁻¹ − a2·z⁻²)` with natural
/// frequency `w` (rad/s) and damping `zeta`, sampled every `dt`.
fn second_order(w: f64, zeta: f64, dt: f64) -> (f64, f64) {
    if zeta < 1.0 {
        let (r, wd) = ((-zeta * w * dt).exp(), w * (1.0 - zeta * zeta).sqrt() * dt);
        (2.0 * r * wd.cos(), -r * r)
    } else {
        let q = w * (zeta * zeta - 1.0).sqrt();
        let (p1, p2) = ((-(zeta * w - q) * dt).exp(), (-(zeta * w + q) * dt).exp());
        (p1 + p2, -p1 * p2)
    }
}

/// The output-error fit for given poles: the following error `e = D − y` (`D` the command
/// delayed by `d`) against the command increments through the slow pole `alpha` and the fast
/// second-order section `fast` (the velocity loop), with `FAST_TAPS` free taps (least squares,
/// nalgebra), over the rows `keep` holds. (residual sum, gain of e per increment at constant
/// speed, the residuals).
fn oe(cmd: &[f64], act: &[f64], d: usize, alpha: f64, fast: (f64, f64), keep: &[bool]) -> Option<(f64, f64, DVector<f64>)> {
    let n = cmd.len().min(act.len());
    let dd = |k: usize| delayed(cmd, d, k);
    let (a1, a2) = fast;
    let (mut s1, mut s) = (vec![0.0; n], vec![0.0; n]);
    for k in 2..n {
        s1[k] = alpha * s1[k - 1] + (dd(k) - dd(k - 1));
        s[k] = a1 * s[k - 1] + a2 * s[k - 2] + (1.0 - a1 - a2) * s1[k];
    }
    let m = FAST_TAPS;
    // Dry friction: a torque of the sign of the speed, stepping where the demand starts,
    // stops or reverses; the loops answer it with the same poles. Its own taps, so that it
    // does not bend the poles (on a stiff feed axis it moves the error as much as the
    // position loop does).
    let sg = |k: usize| if k == 0 { 0.0 } else { (dd(k) - dd(k - 1)).signum() * f64::from(dd(k) != dd(k - 1)) };
    let (mut f1, mut f) = (vec![0.0; n], vec![0.0; n]);
    for k in 2..n {
        f1[k] = alpha * f1[k - 1] + (sg(k) - sg(k - 1));
        f[k] = a1 * f[k - 1] + a2 * f[k - 2] + (1.0 - a1 - a2) * f1[k];
    }
    let rows: Vec<usize> = (m..n).filter(|k| keep[*k]).collect();
    if rows.len() <= 4 * m {
        return None;
    }
    let phi = DMatrix::from_fn(rows.len(), 2 * m, |r, c| if c < m { s[rows[r] - c] } else { f[rows[r] - (c - m)] });
    let rhs = DVector::from_fn(rows.len(), |r, _| dd(rows[r]) - act[rows[r]]);
    let all = phi.clone().svd(true, true).solve(&rhs, 1e-14).ok()?;
    let res = &rhs - &phi * &all;
    let x = all.rows(0, m);
    // The slow mode's share of the error at constant speed, against a plain first-order lag
    // (1): near 0 when the taps' zeros cancel the slow pole and the fast section does its
    // work — then the "slow pole" is not the drive's, and this split is refused.
    let at_slow: f64 =
        x.iter().enumerate().map(|(j, c)| c * alpha.powi(-(j as i32))).sum::<f64>() * (1.0 - a1 - a2) / (1.0 - a1 / alpha - a2 / (alpha * alpha));
    if !(at_slow / x.sum() >= SLOW_SHARE) {
        return None;
    }
    Some((res.norm_squared(), x.sum(), res))
}

/// Left out after a breakaway, s (see `linear_rows`): the drive working off the stick, which
/// its position loop does over a few of its time constants — 3τ at Kv 15/s. At 40 ms a
/// Kv 15/s drive read τ 14 % short.
const AFTER_BREAKAWAY_S: f64 = 0.2;
/// The linear rows' τ stands while it is within this factor (or its inverse) of the fit
/// through every row (see `identify`).
const LINEAR_AGREES: f64 = 2.0 / 3.0;

/// The rows where the drive's response is linear, for the output-error fit. Dry friction
/// makes it non-linear where the axis rests: it stops short and creeps after the demand
/// stops, sticks as the demand starts until the integrator breaks it away, and then works off
/// what the stick left (error, integrator) — a transient the linear model has no input for.
/// Left out: from where the axis first stands still after the demand stopped, to `after`
/// cycles past where it moves again the way the demand does. A linear fit through them bent
/// τ by 10–150 % on drives with the emulator's own friction and other loops (Kv 90/s, a slow
/// velocity loop, 100 % feed-forward, three times the inertia). Where the axis never stands
/// still (no friction, unquantised data) every row is kept.
fn linear_rows(cmd: &[f64], act: &[f64], after: usize) -> Vec<bool> {
    let n = cmd.len().min(act.len());
    let q = quantum((1..n).map(|k| act[k] - act[k - 1]));
    let still = |k: usize| (act[k] - act[k - 1]).abs() < 0.5 * q;
    let (mut keep, mut at_rest, mut moved) = (vec![true; n], false, None);
    for k in 1..n {
        let demand = cmd[k] - cmd[k - 1];
        if !at_rest {
            at_rest = demand == 0.0 && still(k);
        } else if demand != 0.0 && !still(k) && (act[k] - act[k - 1]).signum() == demand.signum() {
            at_rest = false;
            moved = Some(k);
        }
        keep[k] = !at_rest && moved.is_none_or(|m| k >= m + after);
    }
    keep
}

/// How much worse the poles fitted through the settling after the stops must explain the rows
/// where the demand moves than those rows' own fit, for the settling to be taken as another
/// regime and left out. Behind a belt, dry friction holds the slide where the demand stops
/// while the motor still settles — against the wound belt, a stiffer and slower loop than the
/// one that moves the slide: 8 of 48 random belts with the default friction read τ 10–18 %
/// long through those rows (within 8 % with no friction). Where the moving rows are
/// explained 1.6–8.5 times better by their own fit (18 of the 48) that fit reads −1.3 …
/// +3.2 % (−0.5 … +14.8 % before); where the two explain them about as well (ratio
/// 0.65–1.45) the moving rows are too few to place τ (−25 … +8 %, the breakaways' 200 ms left
/// out) and the fit through every row stands (4 of the 48 still 11–18 % long).
const SETTLES_APART: f64 = 1.5;

/// `keep` less the rows where the demand (delayed by `d`) stands still: the settling after
/// the stops.
fn moving_rows(cmd: &[f64], d: usize, keep: &[bool]) -> Vec<bool> {
    let n = keep.len().min(cmd.len());
    (0..n).map(|k| keep[k] && k > 0 && delayed(cmd, d, k) != delayed(cmd, d, k - 1)).collect()
}

/// The command delayed by `d` rows at row `k` (the first row's before the recording).
fn delayed(cmd: &[f64], d: usize, k: usize) -> f64 {
    if k >= d {
        cmd[k - d]
    } else {
        cmd[0]
    }
}

/// The output-error residual of the poles `(τ, ω, ζ)` over the rows `keep` holds (∞ where
/// they do not fit, see `oe`).
fn residual(cmd: &[f64], act: &[f64], d: usize, dt: f64, (tau, w, zeta): (f64, f64, f64), keep: &[bool]) -> f64 {
    oe(cmd, act, d, (-dt / tau).exp(), second_order(w, zeta, dt), keep).map_or(f64::INFINITY, |r| r.0)
}

/// The least share of the slow pole in the following error at constant speed (see `oe`).
const SLOW_SHARE: f64 = 0.3;

/// How much faster than the slow pole the fast section must decay at least (its slowest
/// mode's rate over the slow pole's): else the two swap.
const FAST_OVER_SLOW: f64 = 2.0;
/// The same, relaxed: a heavy spindle's velocity loop (0.13–0.15 kg·m² on the default
/// tuning) decays only 1.8 times faster than its position loop's pole. Held to 2, the fit
/// could not place it and read τ 16–21 % long (69 ms for 58.6); relaxed to this it fits 35
/// times closer and reads 56.6. Taken only where it fits at least [`RELAXED_FITS`] times
/// closer: elsewhere the relaxed fit moves τ a little for a residual barely smaller (a belt:
/// 15 % smaller, τ 1.5 % longer).
const FAST_OVER_SLOW_RELAXED: f64 = 1.6;
/// How much smaller the relaxed fit's residual must be to be taken.
const RELAXED_FITS: f64 = 2.0;
/// A residual (RMS per row) within this of the recording's resolution is the recording's own:
/// no closer fit can be told from it (exact first-order data fits to 1.5·10⁻⁶; a belt's
/// residual is 4·10⁻⁴ mm, a heavy spindle's 0.07°).
const RESOLVED_RMS: f64 = 10.0 * RECORD_QUANTUM;

/// The poles that fit best: the slow time constant (s) and the fast section (natural
/// frequency rad/s, damping) — with the fast section at least [`FAST_OVER_SLOW`] times faster,
/// or [`FAST_OVER_SLOW_RELAXED`] where that fits [`RELAXED_FITS`] times closer than a
/// residual beyond [`RESOLVED_RMS`]. (τ, ω, ζ).
fn fit_poles(cmd: &[f64], act: &[f64], d: usize, dt: f64, keep: &[bool]) -> Option<(f64, f64, f64)> {
    let [strict, relaxed] = search_poles(cmd, act, d, dt, keep, [FAST_OVER_SLOW, FAST_OVER_SLOW_RELAXED]);
    let rows = keep.iter().filter(|k| **k).count().max(1) as f64;
    match (strict, relaxed) {
        (Some(s), Some(r)) if r.0 * RELAXED_FITS <= s.0 && (s.0 / rows).sqrt() > RESOLVED_RMS => Some(r.1),
        (Some(s), _) => Some(s.1),
        (None, r) => r.map(|r| r.1),
    }
}

/// A pole fit: (residual, (τ s, ω rad/s, ζ)).
type PoleFit = (f64, (f64, f64, f64));

/// The best poles with the fast section at least `ratios[i]` times faster than the slow pole
/// (the second the looser): a grid (τ from one cycle to 2 s; the fast section up to the
/// Nyquist frequency, damping 0.4 … 2.5), each point's residual computed once for both, then
/// a pattern search in (log τ, log ω, ζ) for each. (residual, (τ, ω, ζ)) per ratio.
fn search_poles(cmd: &[f64], act: &[f64], d: usize, dt: f64, keep: &[bool], ratios: [f64; 2]) -> [Option<PoleFit>; 2] {
    // How much faster the fast section's slowest mode decays than the slow pole; None
    // outside the search's bounds.
    let speedup = |lt: f64, lw: f64, z: f64| {
        let rate = if z < 1.0 { z } else { z - (z * z - 1.0).sqrt() } * lw.exp();
        ((0.2..=4.0).contains(&z) && (dt..=2.0).contains(&lt.exp())).then(|| rate * lt.exp())
    };
    let fit = |lt: f64, lw: f64, z: f64| oe(cmd, act, d, (-dt / lt.exp()).exp(), second_order(lw.exp(), z, dt), keep).map_or(f64::INFINITY, |r| r.0);
    let sse = |lt: f64, lw: f64, z: f64, ratio: f64| match speedup(lt, lw, z) {
        Some(r) if !(r < ratio) => fit(lt, lw, z),
        _ => f64::INFINITY,
    };
    const NT: usize = 30;
    const NW: usize = 14;
    let taus: Vec<f64> = (0..NT).map(|i| (dt * (2.0 / dt).powf(i as f64 / (NT - 1) as f64)).ln()).collect();
    let (wlo, whi) = (0.5f64, std::f64::consts::PI / dt);
    let ws: Vec<f64> = (0..NW).map(|i| (wlo * (whi / wlo).powf(i as f64 / (NW - 1) as f64)).ln()).collect();
    let mut best = [(f64::INFINITY, taus[0], ws[0], 1.0); 2];
    for t in &taus {
        for w in &ws {
            for z in [0.4, 0.7, 1.0, 1.6, 2.5] {
                let Some(r) = speedup(*t, *w, z).filter(|r| ratios.iter().any(|q| !(*r < *q))) else { continue };
                let e = fit(*t, *w, z);
                for (b, q) in best.iter_mut().zip(ratios) {
                    if !(r < q) && e < b.0 {
                        *b = (e, *t, *w, z);
                    }
                }
            }
        }
    }
    let refine = |(mut cur, mut t, mut w, mut z): (f64, f64, f64, f64), ratio: f64| {
        let mut st = taus[1] - taus[0];
        while st > 1e-4 {
            let next = [(st, 0.0, 0.0), (-st, 0.0, 0.0), (0.0, st, 0.0), (0.0, -st, 0.0), (0.0, 0.0, st), (0.0, 0.0, -st)]
                .into_iter()
                .map(|(a, b, c)| (sse(t + a, w + b, z + c, ratio), t + a, w + b, z + c))
                .find(|c| c.0 < cur);
            match next {
                Some(c) => (cur, t, w, z) = c,
                None => st *= 0.5,
            }
        }
        cur.is_finite().then(|| (cur, (t.exp(), w.exp(), z)))
    };
    [refine(best[0], ratios[0]), refine(best[1], ratios[1])]
}

/// Which actual positions answer their own SYNC (`fill_late` fills the others). An actual is
/// not its SYNC's own when:
/// - its frame came late (`age` > 0, the trace's `NAME_age`);
/// - it follows one that was not and the cycle loop could not pair it with its demand:
///   `ferr` exactly 0 while the demand moves (alone, a 0 is a drive with full feed-forward
///   that lags nothing: zff100);
/// - it repeats the previous count while the demand moves, after a step of more than 1.5× the
///   record's smallest: a drive that stalled sends its last position again (python peers on
///   a stalling host); a coarse encoder at a crawl repeats its count rightly.
///
/// The last two go on through the run of such samples.
pub fn fresh_samples(cmd: &[f64], act: &[f64], ferr: &[f64], age: &[f64]) -> Vec<bool> {
    let n = cmd.len().min(act.len()).min(ferr.len()).min(age.len());
    let quantum = (1..n).map(|k| (act[k] - act[k - 1]).abs()).filter(|d| *d > 0.0).fold(f64::INFINITY, f64::min);
    let mut fresh = vec![true; n];
    for k in 0..n {
        let moving = k >= 1 && cmd[k] != cmd[k - 1];
        let step = if k >= 2 { (act[k - 1] - act[k - 2]).abs() } else { 0.0 };
        // The actual was moving before this sample, or the one before was not fresh.
        let was_moving = k >= 2 && (step > 0.0 || !fresh[k - 1]);
        let held = k >= 2 && act[k] == act[k - 1] && (step > 1.5 * quantum || !fresh[k - 1]);
        let unpaired = k >= 1 && ferr[k] == 0.0 && !fresh[k - 1];
        fresh[k] = !(age[k] > 0.0 || (moving && was_moving && (unpaired || held)));
    }
    fresh
}

/// Fill the actual positions that came late (`fresh[k]` false: the drive's frame of SYNC k
/// had not come, `act[k]` holds an older one) from the fresh ones around them: a cubic
/// through the two fresh samples before and the two after (exact for a constant
/// acceleration; a line where fewer are fresh). A held value read as the drive's response
/// is a stop and a jump — the fit then bends its delay and time constant to them (python
/// peers under a stalling host: delay 2.0 → 3.8 cycles with 8 of 395 frames late). Runs at
/// either end are left as they are. Returns the samples filled.
pub fn fill_late(act: &mut [f64], fresh: &[bool]) -> usize {
    let n = act.len().min(fresh.len());
    let ok = |k: usize| k < n && fresh[k];
    let mut filled = 0;
    let mut k = 0;
    while k < n {
        if ok(k) {
            k += 1;
            continue;
        }
        let a = k;
        while k < n && !fresh[k] {
            k += 1;
        }
        if a == 0 || k == n {
            continue;
        }
        // Fresh at a − 1 and at k; with a − 2 and k + 1 too, a cubic.
        let (cubic, line) = ([a.saturating_sub(2), a - 1, k, k + 1], [a - 1, k]);
        let pts: &[usize] = if a >= 2 && ok(a - 2) && ok(k + 1) { &cubic } else { &line };
        for j in a..k {
            act[j] = lagrange(pts, act, j);
        }
        filled += k - a;
    }
    filled
}

/// The polynomial through `(i, y[i])` for `i` in `pts`, at `x`.
fn lagrange(pts: &[usize], y: &[f64], x: usize) -> f64 {
    let x = x as f64;
    pts.iter()
        .map(|&i| {
            let w: f64 = pts.iter().filter(|&&j| j != i).map(|&j| (x - j as f64) / (i as f64 - j as f64)).product();
            w * y[i]
        })
        .sum()
}

/// Identify from the commanded and the actual positions of the same cycles (`dt` the cycle,
/// s). `None`: too few samples or no motion.
pub fn identify(cmd: &[f64], act: &[f64], dt: f64, max_delay: usize) -> Option<Response> {
    let n = cmd.len().min(act.len());
    if n < 50 || !(dt > 0.0) {
        return None;
    }
    let du: Vec<f64> = (1..n).map(|k| cmd[k] - cmd[k - 1]).collect();
    let dy: Vec<f64> = (1..n).map(|k| act[k] - act[k - 1]).collect();
    let var = {
        let m = dy.iter().sum::<f64>() / dy.len() as f64;
        dy.iter().map(|v| (v - m) * (v - m)).sum::<f64>()
    };
    if !(var > 0.0) || du.iter().all(|v| *v == 0.0) {
        return None;
    }
    let linear = linear_rows(cmd, act, (AFTER_BREAKAWAY_S / dt).ceil() as usize);
    let d = match dead_time(&du, &dy, max_delay) {
        Some(d) => d,
        None if corners_resolved(&du, &dy) => dead_time_arx(&du, &dy, max_delay).or_else(|| dead_time_oe(cmd, act, dt, max_delay, &linear))?,
        None => dead_time_oe(cmd, act, dt, max_delay, &linear).or_else(|| dead_time_arx(&du, &dy, max_delay))?,
    };
    // Fitted twice: on every row, and on the rows where the response is linear (see
    // `linear_rows`). Friction bends the fit through every row either way (a stick holds the
    // error up; the breakaway's transient, which the friction input models only in part,
    // shortened τ by 11–24 % on Kv 15–25/s drives with 99.5 % feed-forward), so the linear
    // rows' fit stands — unless it is far from the other: where the linear rows are too few
    // to show the decay (a 2000-line encoder: τ 20× too long), the shorter of the two.
    let all = vec![true; n];
    let (fa, fl) = (fit_poles(cmd, act, d, dt, &all), fit_poles(cmd, act, d, dt, &linear));
    let (keep, poles) = match (fa, fl) {
        (Some(a), Some(l)) if !(LINEAR_AGREES..=1.0 / LINEAR_AGREES).contains(&(l.0 / a.0)) && a.0 < l.0 => (&all, a),
        (_, Some(l)) => (&linear, l),
        (Some(a), None) => (&all, a),
        (None, None) => return None,
    };
    // Where the axis settles after a stop otherwise than it moves (see `SETTLES_APART`), the
    // fit on the rows where the demand moves.
    let moving = moving_rows(cmd, d, keep);
    let (keep, (tau, w, zeta)) = match fit_poles(cmd, act, d, dt, &moving) {
        Some(m) if residual(cmd, act, d, dt, poles, &moving) > SETTLES_APART * residual(cmd, act, d, dt, m, &moving) => (&moving, m),
        _ => (keep, poles),
    };
    let alpha = (-dt / tau).exp();
    let (_, dc, res) = oe(cmd, act, d, alpha, second_order(w, zeta, dt), keep)?;
    // At constant speed e = (1 − ff)·τ per unit of speed: the DC gain gives ff.
    let feed_forward = (1.0 - dc / (1.0 - alpha) * dt / tau).clamp(0.0, 1.5);
    let velocity_lag = regress_lag(cmd, act, dt).unwrap_or(d as f64 * dt + (1.0 - feed_forward) * tau);
    // The delay in the first-moment sense: what of the lag at constant speed the loop does not
    // explain (the emulator: the whole cycles of its pipeline, exactly).
    let delay = ((velocity_lag - (1.0 - feed_forward) * tau) / dt).max(0.0);
    let sse: f64 = (1..res.len()).map(|k| (res[k] - res[k - 1]).powi(2)).sum();
    Some(Response {
        velocity_lag,
        accel_lag: regress_accel_lag(cmd, act, dt, delay, tau).unwrap_or(0.0),
        delay_cycles: delay.floor() as u32,
        delay_fraction: delay - delay.floor(),
        feed_forward,
        time_constant_s: tau,
        vaf: (1.0 - sse / var).max(0.0),
        samples: dy.len(),
    })
}

/// The resolution the set-points are recorded with, units (`cncgw identify` reads them from
/// its trace, which writes six decimals): a cruise's increments differ by up to two of it.
/// Asked to agree within 10⁻⁶ of themselves, a Z cruise at 19.87 mm/s (39.74 µm per cycle,
/// rounded to 1 nm: 2.5·10⁻⁵) had no steady row, and the fallback over every row read the lag
/// of a belt or of a Kv 15/s loop 0.6–1.5 ms short: a delay of 1.2–1.7 cycles for 2.
pub const RECORD_QUANTUM: f64 = 1e-6;

/// The lag at constant speed from the data, s: least squares of (command − actual) on the
/// command's speed over the cycles where that speed has been steady for `STEADY` cycles (the
/// drive's transient after a speed change has died out); where the run has too few of them,
/// over every cycle, with the acceleration as a second regressor.
fn regress_lag(cmd: &[f64], act: &[f64], dt: f64) -> Option<f64> {
    const STEADY: usize = 60;
    let n = cmd.len().min(act.len());
    let v = |k: usize| (cmd[k] - cmd[k - 1]) / dt;
    let same = |a: f64, b: f64| ((a - b) * dt).abs() <= (1e-6 * (b * dt).abs()).max(2.0 * RECORD_QUANTUM);
    let steady: Vec<usize> = (STEADY + 1..n).filter(|&k| v(k) != 0.0 && (k - STEADY..k).all(|j| same(v(j), v(k)))).collect();
    let (rows, cols) = if steady.len() >= 20 { (steady, 1) } else { ((2..n).collect(), 2) };
    let phi = DMatrix::from_fn(rows.len(), cols, |r, c| {
        let k = rows[r];
        if c == 0 {
            v(k)
        } else {
            (v(k) - v(k - 1)) / dt
        }
    });
    let lag = DVector::from_fn(rows.len(), |r, _| cmd[rows[r]] - act[rows[r]]);
    let x = phi.svd(true, true).solve(&lag, 1e-15).ok()?;
    x[0].is_finite().then_some(x[0])
}

/// The drive's own lag per unit of acceleration, s²: least squares of its following error
/// `e = cmd(k − delay) − act(k)` (the demand as the drive has it, interpolated to the fraction
/// of a cycle) on that demand's speed and acceleration, over the cycles where the
/// acceleration has held for `SETTLE_TAUS` of the drive's time constant `tau` (a second-order
/// drive takes that long to settle onto its lag a·τ²: over every row, ramps of 40–70 cycles
/// at τ 40 ms read it 31 % short); where the run has too few such rows, over every moving one.
fn regress_accel_lag(cmd: &[f64], act: &[f64], dt: f64, delay: f64, tau: f64) -> Option<f64> {
    const SETTLE_TAUS: f64 = 5.0;
    let n = cmd.len().min(act.len());
    let at = |t: f64| {
        let (i, f) = (t.floor() as usize, t - t.floor());
        cmd[i] + f * (cmd[(i + 1).min(n - 1)] - cmd[i])
    };
    let demand = |k: usize| at(k as f64 - delay);
    let v = |k: usize| (demand(k) - demand(k - 1)) / dt;
    let a = |k: usize| (v(k) - v(k - 1)) / dt;
    // Equal accelerations, to the recording's resolution (its second difference).
    let same = |x: f64, y: f64| (x - y).abs() <= 1e-3 * y.abs() + 4.0 * RECORD_QUANTUM / (dt * dt);
    let first = delay.ceil() as usize + 3;
    let settle = (SETTLE_TAUS * tau / dt).ceil() as usize;
    let moving: Vec<usize> = (first..n).filter(|&k| v(k) != 0.0 || a(k) != 0.0).collect();
    let held: Vec<usize> = moving.iter().copied().filter(|&k| k >= first + settle && (k - settle..k).all(|j| same(a(j), a(k)))).collect();
    let rows = if held.iter().filter(|&&k| !same(a(k), 0.0)).count() >= 20 { held } else { moving };
    if rows.len() < 20 {
        return None;
    }
    let phi = DMatrix::from_fn(rows.len(), 2, |r, c| if c == 0 { v(rows[r]) } else { a(rows[r]) });
    let e = DVector::from_fn(rows.len(), |r, _| demand(rows[r]) - act[rows[r]]);
    let x = phi.svd(true, true).solve(&e, 1e-15).ok()?;
    x[1].is_finite().then_some(x[1])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A second-order drive with full velocity feed-forward (τ²ÿ + 2τẏ + y = r + 2τṙ, the
    /// python peers' law) lags nothing at constant speed and a·τ² while it accelerates: the
    /// fit says so in `accel_lag`, where the first-order model alone would say "no lag".
    #[test]
    fn a_second_order_drive_s_lag_while_accelerating_is_found() {
        let (dt, tau, delay) = (0.005f64, 0.040, 3usize);
        let mut cmd = vec![0.0];
        // Speed ramps (trapezoids) both ways, as the spindle's speed steps.
        for (a, cycles) in [(0.0, 20), (2000.0, 80), (0.0, 100), (-3000.0, 110), (0.0, 100), (1000.0, 140), (0.0, 100)] {
            for _ in 0..cycles {
                let n = cmd.len();
                let v = if n > 1 { (cmd[n - 1] - cmd[n - 2]) / dt } else { 0.0 };
                cmd.push(cmd[n - 1] + (v + a * dt) * dt);
            }
        }
        let (mut y, mut w, mut act) = (0.0, 0.0, vec![0.0; delay]);
        for k in delay..cmd.len() {
            let (c0, c1) = (cmd[k - delay], cmd[(k + 1 - delay).min(cmd.len() - 1)]);
            act.push(y);
            let (h, rv) = (dt / 20.0, (c1 - c0) / dt);
            for j in 1..=20 {
                let r = c0 + (c1 - c0) * j as f64 / 20.0;
                w += (r + 2.0 * tau * rv - y - 2.0 * tau * w) / (tau * tau) * h;
                y += w * h;
            }
        }
        let r = identify(&cmd, &act, dt, 8).unwrap();
        eprintln!("accel lag {:.0} ms² for {:.0}", r.accel_lag * 1e6, tau * tau * 1e6);
        assert!((r.accel_lag / (tau * tau) - 1.0).abs() < 0.1, "{r:?}");
        assert!((r.velocity_lag - delay as f64 * dt).abs() < 0.1 * dt, "{r:?}");
    }

    /// A command with speed steps both ways, run through a known model (whole-cycle delay,
    /// feed-forward, first-order lag, no inner loops): the fit returns it.
    #[test]
    fn recovers_delay_feed_forward_and_time_constant() {
        let dt: f64 = 0.002;
        let mut cmd = vec![0.0];
        for (v, cycles) in [(0.0, 50), (10.0, 300), (0.0, 200), (-20.0, 150), (5.0, 300), (0.0, 300)] {
            for _ in 0..cycles {
                let last = *cmd.last().unwrap();
                cmd.push(last + v * dt);
            }
        }
        for (d, ff, tau) in [(2usize, 0.95, 0.040), (4, 0.8, 0.015), (3, 0.995, 0.05)] {
            let alpha = (-dt / tau).exp();
            // Exact for a speed constant over each period (the interpolating drive).
            let (mut w, mut act) = (0.0, vec![0.0]);
            for k in 1..cmd.len() {
                let v = if k > d { cmd[k - d] - cmd[k - d - 1] } else { 0.0 };
                let lagged = v + (w - v) * (tau / dt) * (1.0 - alpha);
                w = alpha * w + (1.0 - alpha) * v;
                let last = *act.last().unwrap();
                act.push(last + ff * v + (1.0 - ff) * lagged);
            }
            let r = identify(&cmd, &act, dt, 8).unwrap();
            let delay = r.delay_cycles as f64 + r.delay_fraction;
            assert!((delay - d as f64).abs() < 0.05, "{r:?}");
            assert!((r.feed_forward - ff).abs() < 0.005, "{r:?}");
            assert!((r.time_constant_s / tau - 1.0).abs() < 0.05, "{r:?}");
            assert!(r.vaf > 0.999, "{r:?}");
        }
    }
    /// Late samples of a constant acceleration come back exactly; a line where a neighbour
    /// is late too; runs at the ends stay held.
    #[test]
    fn late_actuals_are_filled_from_the_fresh_around_them() {
        let truth: Vec<f64> = (0..30).map(|k| 0.5 * 0.3 * (k as f64).powi(2) + 2.0 * k as f64).collect();
        let mut act = truth.clone();
        let mut fresh = vec![true; 30];
        for k in [0, 1, 7, 12, 13, 14, 20, 22, 29] {
            fresh[k] = false;
            act[k] = if k == 0 { -1.0 } else { act[k - 1] };
        }
        let held = act.clone();
        assert_eq!(fill_late(&mut act, &fresh), 6);
        for k in [7, 12, 13, 14] {
            assert!((act[k] - truth[k]).abs() < 1e-9, "sample {k}: {} for {}", act[k], truth[k]);
        }
        // 20 and 22 have only one fresh neighbour between them: a line, off by a·dt²/2.
        for k in [20, 22] {
            assert!((act[k] - truth[k]).abs() <= 0.5 * 0.3 + 1e-9, "sample {k}: {} for {}", act[k], truth[k]);
        }
        assert_eq!((act[0], act[1], act[29]), (held[0], held[1], held[29]));
    }
    /// A late frame, the unpaired frame after it and a held position while the demand moves
    /// are not fresh; standing still or starting from rest (the following error 0 while
    /// the delay passes) is.
    #[test]
    fn late_unpaired_and_held_actuals_are_not_fresh() {
        let cmd = [0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 8.0, 8.0];
        let act = [0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 2.0, 2.0, 5.0, 6.0, 8.0, 8.0];
        let ferr = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0];
        let age = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let f = fresh_samples(&cmd, &act, &ferr, &age);
        assert_eq!(f, [true, true, true, true, true, true, false, false, true, true, true, true]);
        // A drive that stalled answers its demand with its last position (paired all the same).
        let ferr = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 3.0, 1.0, 1.0, 0.0, 0.0];
        let age = [0.0; 12];
        let act = [0.0, 0.0, 0.0, 0.0, 1.0, 3.0, 3.0, 3.0, 5.0, 6.0, 8.0, 8.0];
        assert_eq!(fresh_samples(&cmd, &act, &ferr, &age)[5..8], [true, false, false]);
        // A coarse encoder at a crawl: its count repeats, one step at a time.
        let act = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 3.0, 3.0, 4.0, 4.0];
        assert!(fresh_samples(&cmd, &act, &ferr, &age).iter().all(|f| *f));
    }
}
