//! Turning and threading canned cycles: manual 004 §2.15–§2.17 (G32, G34, G90, G92, G94,
//! G70–G76), manual 002 (G78) and manual 001 (G92.1). Each cycle expands into canonical moves
//! tagged with `CycleTag { cycle, step }`, `step` being the manual's ①②③… numbering of the
//! cycle (where the numbers live only in a figure missing from the text, the module of the
//! cycle says which numbering it uses).
//!
//! Files: `single.rs` G90/G92/G94, `g76.rs` G76/G78, `stock.rs` G70–G73, `typeii.rs` G71/G72
//! type II, `groove.rs` G74/G75, `polar.rs` G12.1/G13.1 and G51.2/G50.2, `stroke.rs`
//! G22/G23, `rigid.rs` G92.1, `drill.rs` G80–G89 and G30 P99, `siemens.rs` CYCLE81–86/840
//! and MCALL; G32/G34 and the shared helpers are here.
//!
//! The cycles are `impl Interpreter` blocks (a child module sees the interpreter's private
//! state); the interpreter calls [`Interpreter::cycle_block_start`] at the start of every NC
//! block, [`Interpreter::cycle_modal`] for a group-01 cycle code with axis words, and
//! [`Interpreter::cycle_oneshot`] for G70–G78.
//!
//! State kept here (the interpreter's state, not the machine's parameter file): the modal
//! thread lead, the G90/G92/G94/G92.1 retained X/Z/R (§2.15 note 2), whether the previous
//! block was a thread (continuous threads, §2.17.1 note 2), and the parameters the cycles
//! write back (No.5130 run-out, No.5139 e, No.5140 Δdmin, No.5141 d, No.5142 m, No.5143 a,
//! No.5144–5146 G73, No.5147/5148 G71/G72 Δd/e, G78's infeed and depth modes). They start
//! from the configuration's `[parameters]`; writes last for the interpreter's life.
//!
//! Alarm numbers: the manuals say "alarm" without a number; we use Fanuc 0i-TF PS numbers
//! (7 decimal point in packed P, 10 wrong plane / not supported, 11 no lead or feed, 14
//! illegal G34 lead, 21 axis outside the ZX plane, 51 contour ends with ,C/,R, 61 P/Q
//! missing, 62 bad cycle value, 63 N(ns)/N(nf) not found, 64 contour not monotonic, 65 ns
//! block not G00/G01, 66 code not allowed in the contour) and our own [`RANGE_ALARM`] (2510)
//! for the out-of-range values the manual names and Fanuc has no number for (Q start angle,
//! run-out longer than the thread, R taper crossing the start point, H/L starts, no S).

use super::gcode::{Decoded, GCode, Val};
use super::Interpreter;
use crate::canon::{CycleTag, Move, MoveKind, Plane, Pos, SrcPos};
use crate::config::MachineConfig;
use std::sync::Arc;

pub mod drill;
pub mod g76;
pub mod groove;
pub mod polar;
pub mod rigid;
pub mod siemens;
pub mod single;
pub mod stock;
pub mod stroke;
pub mod typeii;

/// Our alarm for values outside the ranges the manual states (Fanuc has no number for them).
pub const RANGE_ALARM: u32 = crate::alarm::VALUE_RANGE;
/// Fanuc PS0062: illegal value in a multiple repetitive cycle (G76 depth, Δdmin, d, m, W=0).
pub const G76_VALUE_ALARM: u32 = 62;
/// Largest thread lead (mm/rev): Fanuc's F range for threads, 0.0001–500 mm.
pub const MAX_LEAD: f64 = 500.0;
/// Upper bound on the passes of one G76, so that a tiny Δd cannot flood the move queue.
pub const MAX_PASSES: usize = 2000;

pub(super) type CErr = (u32, Option<u32>, String);

/// Cycle state held by the interpreter.
#[derive(Clone, Debug)]
pub struct CycleState {
    /// Modal thread lead (mm/rev), set by F or E in a thread block. Fanuc shares F with the
    /// feed rate; the manual (§2.17.1, F) says the lead stays until the next thread F, so a
    /// G01 F does not change it.
    pub lead: Option<f64>,
    /// The current block / the previous NC block made a thread move.
    this_thread: bool,
    prev_thread: bool,
    /// Start angle of the chain of continuous threads in progress (Q rule 2).
    chain_angle: f64,
    /// §2.15 note 2: X/Z (work coordinates, X radius) and R retained by G90/G92/G94.
    retained: Option<Retained>,
    /// No.5130 run-out amount (units of 0.1 × lead), 0–99.
    pub p5130: u32,
    /// No.5131 run-out angle in degrees; 0 = 45°.
    pub p5131: f64,
    /// No.5140 Δdmin, No.5141 d (mm, radius).
    pub p5140: f64,
    pub p5141: f64,
    /// No.5142 m finishing passes, No.5143 a tool angle (degrees).
    pub p5142: u32,
    pub p5143: u32,
    /// No.5147 Δd and No.5148 e of G71 (mm, radius), written back by `G71 U R`.
    pub p5147: f64,
    pub p5148: f64,
    /// No.5144 Δi, No.5145 Δk (mm, radius, signed), No.5146 d passes of G73.
    pub p5144: f64,
    pub p5145: f64,
    pub p5146: u32,
    /// G78 (manual 002): infeed mode P(r) 0–4 (No.5144 there), depth mode D 0/1 (No.5145
    /// there), run-out J/K (modal; None = No.5130/5131). Manual 004 gives No.5144/5145 to
    /// G73's Δi/Δk, so G78's values are kept apart and start from 0 (centre infeed) and 1
    /// (decreasing depth, as G76) unless `[parameters]` has G78-valid values (0–4, 0–1).
    pub g78_mode: u32,
    pub g78_decreasing: bool,
    pub g78_jk: (Option<f64>, Option<f64>),
    /// G92.1 modal lead (mm/rev, signed: negative = left hand) and number of starts L.
    pub rigid_lead: Option<f64>,
    pub rigid_starts: u32,
    /// No.5139 e of G74/G75 (mm), the retract after each peck.
    pub p5139: f64,
    /// G51.2 polygon turning in force.
    pub polygon: bool,
    /// No.721: the tool spindle's clamp speed in polygon turning (rpm).
    pub p721: Option<f64>,
    /// The machine has a tool spindle (`role = "tool_spindle"`) for G51.2.
    pub tool_spindle: bool,
    /// The C axis' speed limit (degrees/min) for §2.7 note 9: axis `c`'s max_speed, else the
    /// spindle's max_speed (rpm) × 360.
    pub c_max_deg_min: Option<f64>,
    /// G22/G23 stored stroke check 2.
    pub stroke: stroke::Stroke2,
}

#[derive(Clone, Debug)]
struct Retained {
    code: GCode,
    x: Option<f64>,
    z: Option<f64>,
    r: Option<f64>,
}

impl CycleState {
    /// Parameters absent from the configuration take Fanuc's cleared values, except
    /// m (No.5142) = 1 since the manual's range is 01–99.
    pub fn new(cfg: &MachineConfig) -> CycleState {
        let p = |n| cfg.param(n).filter(|v| v.is_finite());
        CycleState {
            lead: None,
            this_thread: false,
            prev_thread: false,
            chain_angle: 0.0,
            retained: None,
            p5130: p(5130).map(|v| v.clamp(0.0, 99.0) as u32).unwrap_or(0),
            p5131: p(5131).unwrap_or(0.0),
            p5140: p(5140).unwrap_or(0.0).abs(),
            p5141: p(5141).unwrap_or(0.0).abs(),
            p5142: p(5142).map(|v| v.clamp(1.0, 99.0) as u32).unwrap_or(1),
            p5143: p(5143).map(|v| v.clamp(0.0, 99.0) as u32).unwrap_or(0),
            p5147: p(5147).unwrap_or(0.0).abs(),
            p5148: p(5148).unwrap_or(0.0).abs(),
            p5144: p(5144).unwrap_or(0.0),
            p5139: p(5139).unwrap_or(0.0).abs(),
            g78_mode: p(5144).filter(|v| v.fract() == 0.0 && (0.0..=4.0).contains(v)).map(|v| v as u32).unwrap_or(0),
            g78_decreasing: p(5145).filter(|v| *v == 0.0 || *v == 1.0).map(|v| v == 1.0).unwrap_or(true),
            g78_jk: (None, None),
            rigid_lead: None,
            rigid_starts: 1,
            p5145: p(5145).unwrap_or(0.0),
            p5146: p(5146).map(|v| v.clamp(0.0, 99999.0) as u32).unwrap_or(0),
            polygon: false,
            p721: p(721),
            tool_spindle: cfg.tool_spindle().is_some(),
            c_max_deg_min: cfg
                .axes
                .get("c")
                .map(|a| a.max_speed)
                .or_else(|| cfg.spindle().map(|(_, a)| a.max_speed * 360.0))
                .filter(|v| v.is_finite() && *v > 0.0),
            stroke: stroke::Stroke2::new(cfg),
        }
    }
}

/// One thread segment produced by [`thread_path`]: end point and lead (mm/rev along the
/// segment's long axis).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThreadSeg {
    pub end: Pos,
    pub lead: f64,
}

/// The thread cut `from` → `to` with a run-out (G92 note 1, G76 r): the cut follows the line
/// until `runout` mm before `to` on the long axis, then the short axis retracts by
/// `runout × tan(angle)` (45° when `angle_deg` is 0 or outside 1–89°, Fanuc No.5131) towards
/// `away` (the start point's coordinate on the short axis) while the long axis finishes,
/// clamped to the distance to `away` (G92 note 6). Errors when the run-out is longer than the
/// thread (G92 note 5, G76 note 8).
pub fn thread_path(from: Pos, to: Pos, lead: f64, runout: f64, angle_deg: f64, away: Pos) -> Result<Vec<ThreadSeg>, String> {
    let angle = if (1.0..=89.0).contains(&angle_deg) { angle_deg } else { 45.0 };
    thread_path_js(from, to, lead, runout, runout * angle.to_radians().tan(), away)
}

/// [`thread_path`] with the run-out given as its long-axis length and short-axis amount
/// (G78 K and J).
pub fn thread_path_js(from: Pos, to: Pos, lead: f64, runout: f64, short: f64, away: Pos) -> Result<Vec<ThreadSeg>, String> {
    if runout <= 0.0 {
        return Ok(vec![ThreadSeg { end: to, lead }]);
    }
    let (dz, dx) = (to.z - from.z, to.x - from.x);
    let z_long = dz.abs() > dx.abs();
    let long = if z_long { dz.abs() } else { dx.abs() };
    if runout > long + 1e-9 {
        return Err(format!(
            "the thread run-out ({runout:.3} mm on the long axis) is longer than the thread ({long:.3} mm): reduce the run-out (No.5130 / P(r) / K) or lengthen the thread"
        ));
    }
    let f = 1.0 - runout / long;
    let p1 = Pos { x: from.x + dx * f, z: from.z + dz * f, ..to };
    let mut short = short;
    let mut end = to;
    if z_long {
        short = short.min((away.x - to.x).abs());
        end.x = to.x + short * (away.x - to.x).signum();
    } else {
        short = short.min((away.z - to.z).abs());
        end.z = to.z + short * (away.z - to.z).signum();
    }
    // Keep `lead` per revolution on the long axis of the run-out segment itself: when the
    // short axis moves further than the long one, it becomes that segment's long axis.
    let seg_lead = if short > runout { lead * short / runout } else { lead };
    let mut v = Vec::new();
    if f > 0.0 {
        v.push(ThreadSeg { end: p1, lead });
    }
    v.push(ThreadSeg { end, lead: seg_lead });
    Ok(v)
}

impl Interpreter {
    /// Called at the start of every NC block: the previous-thread flag, and §2.15 note 2
    /// (a group-00 code other than G04, or another group-01 code, clears the retained X/Z/R).
    pub(super) fn cycle_block_start(&mut self, d: &Decoded) {
        self.cyc.prev_thread = std::mem::take(&mut self.cyc.this_thread);
        if let Some(r) = &self.cyc.retained {
            if d.group(1).is_some_and(|g| g != r.code) || d.group(0).is_some_and(|g| g != 40) {
                self.cyc.retained = None;
            }
        }
    }

    /// A group-01 cycle code (G32, G90, G92, G94) in a block with axis words.
    pub(super) fn cycle_modal(&mut self, d: &Decoded, src: &SrcPos, end: Pos, exact: bool) -> Result<(), CErr> {
        match self.st.motion {
            320 | 340 => self.g32(d, src, end, exact),
            900 | 940 => self.g90_g94(d, src),
            920 => self.g92(d, src),
            921 => self.g92_1(d, src),
            g => Err((10, None, format!("{} is not supported yet", super::gcode::gname(g)))),
        }
    }

    /// A group-00 cycle code (G76).
    pub(super) fn cycle_oneshot(&mut self, g: GCode, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        match g {
            700 => self.g70(d, src),
            710 => self.rough(d, src, false),
            720 => self.rough(d, src, true),
            730 => self.g73(d, src),
            740 => self.groove(d, src, false),
            750 => self.groove(d, src, true),
            760 => self.g76(d, src),
            780 => self.g78(d, src),
            g => Err((10, None, format!("{} is not supported yet", super::gcode::gname(g)))),
        }
    }

    pub(super) fn gcol(d: &Decoded) -> Option<u32> {
        d.g.first().map(|g| g.1)
    }

    /// §2.15 note 1: cycles work in the ZX plane with X and Z only.
    pub(super) fn cycle_plane_check(&self, d: &Decoded, name: &str) -> Result<(), CErr> {
        if self.st.plane != Plane::Zx {
            return Err((10, Self::gcol(d), format!("{name} works in the ZX plane only: command G18 first")));
        }
        if let Some(l) = ['Y', 'V', 'C', 'H'].into_iter().find(|l| d.has(*l) && !(*l == 'H' && name == "G92")) {
            return Err((
                21,
                d.get(l).map(|v| v.col),
                format!("{name}: address {l} moves an axis outside the ZX plane; only X/U and Z/W are allowed"),
            ));
        }
        Ok(())
    }

    /// Thread lead of the block (F mm or inch per rev, E threads per inch), or the modal one.
    pub(super) fn thread_lead(&mut self, d: &Decoded) -> Result<f64, CErr> {
        if let Some(e) = d.get('E') {
            if e.v <= 0.0 {
                return Err((11, Some(e.col), "E (threads per inch) must be positive".into()));
            }
            self.cyc.lead = Some(25.4 / e.v);
        } else if let Some(f) = d.get('F') {
            if f.v <= 0.0 {
                return Err((11, Some(f.col), "F (thread lead) must be positive".into()));
            }
            self.cyc.lead = Some(if self.st.inch { f.v * 25.4 } else { f.v });
        }
        self.cyc.lead.ok_or((11, Self::gcol(d), "no thread lead: program F (lead per revolution) or E (threads per inch)".into()))
    }

    /// Q start angle in degrees, 0–360 (§2.17.1 Q rule 3); absent = 0 (rule 1).
    pub(super) fn start_angle(&self, d: &Decoded) -> Result<f64, CErr> {
        match d.get('Q') {
            None => Ok(0.0),
            Some(q) if (0.0..=360.0).contains(&q.v) => Ok(q.v),
            Some(q) => Err((RANGE_ALARM, Some(q.col), format!("Q{}: the thread start angle must be 0–360 degrees", q.v))),
        }
    }

    /// Push a cycle move (rapids always stop exactly, like G00). Zero-length motions are
    /// skipped.
    pub(super) fn cpush(&mut self, src: &SrcPos, cycle: &Arc<str>, step: u8, kind: MoveKind, exact: bool) {
        if let Some(end) = kind.end() {
            if end == self.pos {
                return;
            }
            self.pos = end;
        }
        let exact_stop = exact || matches!(kind, MoveKind::Rapid { .. });
        let m = Move { src: src.clone(), kind, exact_stop, work_offset: self.offset(), tag: Some(CycleTag { cycle: cycle.clone(), step }) };
        if self.corner.is_some() {
            self.held.push(m);
        } else {
            self.queue.push_back(m);
        }
    }

    /// Emit thread segments; the first waits for the one-revolution signal unless
    /// `continuous`, the following ones never do. The last one stops exactly.
    pub(super) fn push_threads(&mut self, src: &SrcPos, cycle: &Arc<str>, step: u8, segs: &[ThreadSeg], angle: f64) {
        let n = segs.len();
        let mut first = true;
        for (i, s) in segs.iter().enumerate() {
            if s.end == self.pos {
                continue;
            }
            let kind = MoveKind::Thread { end: s.end, lead: s.lead, start_angle: angle, continuous: !first, lead_inc: 0.0 };
            first = false;
            self.cpush(src, cycle, step, kind, i + 1 == n);
        }
    }

    /// G32: constant-lead thread from the current position to `end`; G34 (§2.17.2): the
    /// same with the lead changing by K per revolution. The block right after another thread
    /// block continues without waiting for the one-revolution signal and its Q is ignored
    /// (§2.17.1 note 2, Q rule 2).
    ///
    /// G34 checks: |K| within 0.01–499.99 mm (0.01–9.98 inch under G20) per revolution, and
    /// the lead must stay positive and at most [`MAX_LEAD`] over the whole thread (lead at
    /// the end = √(F² + 2·K·L), L the long-axis length); Fanuc PS0014 otherwise.
    fn g32(&mut self, d: &Decoded, src: &SrcPos, end: Pos, exact: bool) -> Result<(), CErr> {
        let g34 = self.st.motion == 340;
        let lead = self.thread_lead(d)?;
        let q = self.start_angle(d)?;
        let mut lead_inc = 0.0;
        if g34 {
            let k = d.get('K').ok_or((14, Self::gcol(d), "G34 needs K, the lead change per revolution".to_string()))?;
            let (lo, hi) = if self.st.inch { (0.01, 9.98) } else { (0.01, 499.99) };
            if !(lo..=hi).contains(&k.v.abs()) {
                return Err((14, Some(k.col), format!("G34 K{}: |K| must be {lo}–{hi} per revolution", k.v)));
            }
            lead_inc = self.len(k);
            let long = (end.x - self.pos.x).abs().max((end.z - self.pos.z).abs());
            let sq = lead * lead + 2.0 * lead_inc * long;
            if sq <= 0.0 {
                return Err((14, Some(k.col), format!("G34: with F{} and K{} the lead reaches zero before the end of the thread", lead, k.v)));
            }
            if sq.sqrt() > MAX_LEAD {
                return Err((14, Some(k.col), format!("G34: the lead grows to {:.3} mm, more than {MAX_LEAD} mm", sq.sqrt())));
            }
        }
        if lead > MAX_LEAD {
            return Err((14, d.get('F').or(d.get('E')).map(|v| v.col), format!("thread lead {lead:.3} mm is more than {MAX_LEAD} mm")));
        }
        let continuous = self.cyc.prev_thread;
        if !continuous {
            self.cyc.chain_angle = q;
        }
        let kind = MoveKind::Thread { end, lead, start_angle: self.cyc.chain_angle, continuous, lead_inc };
        if end != self.pos {
            self.pos = end;
            self.push(src, kind, exact);
            self.cyc.this_thread = true;
        }
        Ok(())
    }

    /// End point of a single cycle (G90/G92/G94) in machine coordinates, with the retained
    /// X/Z of §2.15 note 2 for omitted axes, and the block's R (or the retained one).
    pub(super) fn single_target(&mut self, d: &Decoded) -> (Pos, f64) {
        let off = self.offset();
        let work = self.pos.sub(off);
        let same = self.cyc.retained.as_ref().filter(|r| r.code == self.st.motion).cloned();
        let axis = |abs: char, inc: char, cur: f64, scale: f64, kept: Option<f64>| -> Option<f64> {
            if let Some(v) = d.get(abs) {
                Some(self.len(v) * scale)
            } else if let Some(v) = d.get(inc) {
                Some(cur + self.len(v) * scale)
            } else {
                kept
            }
        };
        let x = axis('X', 'U', work.x, 0.5, same.as_ref().and_then(|r| r.x));
        let z = axis('Z', 'W', work.z, 1.0, same.as_ref().and_then(|r| r.z));
        let r = d.get('R').map(|v: Val| self.len(v)).or(same.as_ref().and_then(|r| r.r));
        self.cyc.retained = Some(Retained { code: self.st.motion, x, z, r });
        let mut t = work;
        if let Some(x) = x {
            t.x = x;
        }
        if let Some(z) = z {
            t.z = z;
        }
        (t.add(off), r.unwrap_or(0.0))
    }
}
