//! Drilling, boring and tapping cycles G80–G89 (manual 004 §2.21–§2.22) and rigid tapping
//! G84/G88 in full (manual 000), with G30 P99 rigid-tap return.
//!
//! # Mode and data
//! G83/G84/G85/G87/G88/G89 are modal (group 10) until G80 or a group-01 code. A block with
//! any axis word in that mode drills one hole (K holes) there; a cycle block without axis
//! words only stores its data. Hole position words (X/U, Y/V, C/H for G83/G84/G85, Z/W,
//! Y/V, C/H for G87/G88/G89) hold for their block; the bottom (Z/W or X/U), R, Q, P, D, the
//! clamp M and F are drilling data kept until G80 (Fanuc 0i-TF: the manual's "only in the
//! specified block" of the bottom would make its own `C120; C240;` example drill nothing).
//! The bottom written incrementally is the distance from the R point (kept as such).
//!
//! The **initial plane** is the drilling-axis coordinate when the mode is entered; **R** is
//! the signed distance (radius) from it to the R point: R point = initial + R. The manual's
//! G83 example comments "R point Z-4" for `G0 … Z-4; G83 … R4`, which contradicts its own
//! definition of R; we follow the definition (R point Z0 there).
//!
//! Drilling axis (No.5209#0 = 0, by plane): G83/G84/G85 G17 X, G18 Z, G19 Y; G87/G88/G89
//! G17 Y, G18 X, G19 Z. No.5209#0 = 1: Z for the face cycles, X for the side cycles.
//!
//! # Steps and tags
//! Every move is tagged with the cycle and the **action** 1–6 of manual 000 / 004 note 2
//! (the numbering downstream single block and feed hold work on): 1 positioning at the
//! initial plane, 2 rapid to R, 3 cutting / tapping in (with the pecks and their returns),
//! 4 dwell at the bottom, 5 return to R, 6 return to the initial plane. The step lists of the
//! manual map onto them as the functions below say.
//!
//! # Values
//! P: seconds in G83/G85/G87/G89 and flexible G84/G88 (004: "系统单位为秒", examples `P3`,
//! `P1`), milliseconds in rigid G84/G88 (000's examples `P3000` = 3 s; a decimal point there
//! is Fanuc PS0007). Q (cut per peck), R, D are lengths (radius). K 1–99 repetitions, K0
//! stores the data without drilling (Fanuc), K198 (rigid tapping only) stays at the bottom.
//!
//! # Alarms
//! The manuals name no numbers; Fanuc 0i-TF's: PS0200 illegal S in rigid tapping (none,
//! zero, above No.5241), PS0201 no feed rate in rigid tapping, PS0203 rigid tapping program
//! error (S between M29 and G84, M29 twice, G30 P99 with No.5200#0 = 1), PS0204 axis move
//! between M29 and G84, PS0010/0021 plane/axis; our [`RANGE_ALARM`] (2510) for values out of
//! the manual's ranges (K, Q, E, J) and [`TAP_RETURN_ALARM`] for G30 P99 without a tap to
//! return from.
//!
//! # Which manual wins
//! Manual 004 §2.22.2 names No.5102 for the tapping Q mode and No.5114 for the peck return d;
//! manual 000 (the rigid tapping specification) names No.5200#5 and No.5213 (D overriding
//! it). We follow 000. 004 gives the drilling cycles No.5101 and No.5113.
//!
//! # Parameters (from `[parameters]`)
//! No.5101 (0 high-speed peck / 1 peck; bit 2 as Fanuc RTR also counts), No.5113 d of G83/G87,
//! No.5110 clamp M code (used when the block has none, 0 = none), No.5111 dwell after unclamp
//! (ms), No.5155 (1 = keep the drilling mode through reset, see
//! [`Interpreter::drill_modal_after_reset`]), No.5170 reverse tapping, No.5200 bits #0 #4 #5
//! #7, No.5201 #3 #4, No.5202 #6, No.5209 #0, No.5210 M code (0 = M29), No.5211 override,
//! No.5213 d of G84/G88, No.5241 max tapping rpm, No.5282 extra return, No.5382 extra return
//! of G30 P99, No.7013 dwell at R (ms). No.5200#2 (000: the cancel of rigid tapping waits for
//! RGTAP = 0): an exact-stop wait point (a zero dwell, untagged) at the block that cancels
//! rigid tapping. No.5200#6, No.5261, No.5271 and the flexible-tapping parameters No.5275
//! (cycles the tapping axis lags the spindle encoder, compensated) and No.5276 (the spindle
//! speed, 0.1 rpm, detected before the retract) act in motion (`Motion::flex_tap_v`).
//!
//! # Spindle
//! The rigid tapping spindle (000 note 2) rides in every [`MoveKind::Tap`] and in
//! [`TapReturn`]: E1–E4 of the tapping mode (until G80); without E, No.5200#7 = 1 takes the
//! M24–M27 selection (held until the next), No.5200#7 = 0 the spindle selection signals, of
//! which this machine has none (spindle 1). Motion refuses a tap on a spindle it lacks.

use super::{CErr, RANGE_ALARM};
use crate::canon::{Feed, MoveKind, Plane, Pos, SpindleCmd, SpindleDir, SrcPos, TapReturn};
use crate::config::MachineConfig;
use crate::interp::gcode::{Decoded, GCode};
use crate::interp::Interpreter;
use std::sync::Arc;

/// Our alarm: G30 P99 with no interrupted tap to return from.
pub const TAP_RETURN_ALARM: u32 = crate::alarm::TAP_RETURN;
/// Fanuc PS0200: illegal S code in rigid tapping.
pub const RIGID_S_ALARM: u32 = crate::alarm::RIGID_S;
/// Fanuc PS0201: no feed rate in rigid tapping.
pub const RIGID_F_ALARM: u32 = crate::alarm::RIGID_F;
/// Fanuc PS0203: rigid tapping program error.
pub const RIGID_PROGRAM_ALARM: u32 = crate::alarm::RIGID_PROGRAM;
/// Fanuc PS0204: illegal axis operation (a move between M29 and G84).
pub const RIGID_AXIS_ALARM: u32 = crate::alarm::RIGID_AXIS;
/// Upper bound on the pecks of one block (all its K holes), so that a tiny Q cannot flood
/// the move queue (a block's moves are queued at once).
pub const MAX_PECKS: f64 = 20_000.0;

/// The hole bottom as programmed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Depth {
    /// Machine coordinate along the drilling axis.
    Abs(f64),
    /// Distance from the R point (signed).
    Inc(f64),
}

/// The drilling mode and its data: what No.5155 keeps through a reset.
#[derive(Clone, Debug, PartialEq)]
pub struct DrillModal {
    /// G83/G84/G85/G87/G88/G89 ×10.
    pub code: GCode,
    /// Drilling axis: 'X', 'Y' or 'Z'.
    pub axis: char,
    /// Initial plane (machine coordinate along `axis`).
    pub initial: f64,
    pub r: f64,
    pub depth: Option<Depth>,
    pub q: f64,
    /// Dwell at the bottom, seconds.
    pub dwell: f64,
    /// D of G84/G88 (None = No.5213).
    pub d: Option<f64>,
    /// C-axis clamp M code.
    pub clamp: Option<u32>,
    /// Rigid (true) or flexible tapping, for G84/G88.
    pub rigid: bool,
}

/// Cycle parameters read once from the configuration.
#[derive(Clone, Debug)]
pub struct DrillParams {
    peck_5101: bool,
    d_5113: f64,
    clamp_5110: Option<u32>,
    dwell_5111: f64,
    keep_5155: bool,
    reverse_5170: bool,
    b5200: [bool; 8],
    b5201_3: bool,
    b5201_4: bool,
    b5202_6: bool,
    fixed_5209: bool,
    m_5210: u32,
    ovr_5211: f64,
    d_5213: f64,
    max_5241: f64,
    extra_5282: f64,
    extra_5382: f64,
    dwell_7013: f64,
}

impl DrillParams {
    pub fn new(cfg: &MachineConfig) -> DrillParams {
        let p = |n| cfg.param(n).filter(|v: &f64| v.is_finite());
        let bit = |n, b| cfg.param_bit(n, b);
        DrillParams {
            peck_5101: p(5101) == Some(1.0) || bit(5101, 2),
            d_5113: p(5113).unwrap_or(0.0).abs(),
            clamp_5110: p(5110).filter(|v| *v > 0.0).map(|v| v as u32),
            dwell_5111: p(5111).unwrap_or(0.0).max(0.0) / 1000.0,
            keep_5155: p(5155).is_some_and(|v| v as i64 & 1 == 1),
            reverse_5170: p(5170).is_some_and(|v| v as i64 & 1 == 1),
            b5200: std::array::from_fn(|b| bit(5200, b as u8)),
            b5201_3: bit(5201, 3),
            b5201_4: bit(5201, 4),
            b5202_6: bit(5202, 6),
            fixed_5209: bit(5209, 0),
            m_5210: p(5210).filter(|v| *v > 0.0 && *v <= 255.0).map(|v| v as u32).unwrap_or(29),
            ovr_5211: p(5211).unwrap_or(0.0),
            d_5213: p(5213).unwrap_or(0.0).abs(),
            max_5241: p(5241).unwrap_or(0.0),
            extra_5282: p(5282).unwrap_or(0.0).abs(),
            extra_5382: p(5382).unwrap_or(0.0).abs(),
            dwell_7013: p(7013).unwrap_or(0.0).max(0.0) / 1000.0,
        }
    }
}

/// Drilling and tapping state held by the interpreter.
#[derive(Clone, Debug)]
pub struct DrillState {
    pub modal: Option<DrillModal>,
    pub par: DrillParams,
    /// M29 S given (No.5200#0 = 0), waiting for G84/G88.
    m29_pending: bool,
    /// Rigid tapping S (signed: negative = reverse thread), cleared by G80 (000 note 5).
    tap_s: Option<f64>,
    /// J pull-out speed, kept until G80.
    tap_j: Option<f64>,
    /// Spindle state before rigid tapping, restored after each hole (004 step ⑦); kept
    /// until G80.
    spindle_before: Option<(SpindleDir, f64)>,
    /// E of the tapping mode (1–4), kept until G80.
    tap_e: Option<u8>,
    /// M24–M27 (No.5200#7 = 1, the RGTSP signals): the selection holds until another one.
    rgtsp: u8,
    /// The direction signal G61.2 (reverse-thread tapping with a positive S).
    pub reverse_signal: bool,
    /// What G30 P99 returns along.
    pub tap_return: Option<TapReturn>,
    /// The tap cycle last expanded (R plane, lead, speeds).
    pub last_tap: Option<TapReturn>,
    /// Flexible tapping: the tapping direction of the first hole, turned on again at every
    /// following hole (004 §2.22.3 note 2); cleared by G80.
    flex_dir: Option<SpindleDir>,
    /// MCALL: the SINUMERIK cycle run after every positioning block.
    pub mcall: Option<super::siemens::SiemensCall>,
    /// Columns of the parameters of the cycle call being executed (for its alarms).
    pub call_cols: Vec<u32>,
}

impl DrillState {
    pub fn new(cfg: &MachineConfig) -> DrillState {
        DrillState {
            modal: None,
            par: DrillParams::new(cfg),
            m29_pending: false,
            tap_s: None,
            tap_j: None,
            spindle_before: None,
            tap_e: None,
            rgtsp: 1,
            reverse_signal: false,
            tap_return: None,
            last_tap: None,
            flex_dir: None,
            mcall: None,
            call_cols: Vec::new(),
        }
    }
}

pub fn axis_of(p: &Pos, a: char) -> f64 {
    match a {
        'X' => p.x,
        'Y' => p.y,
        _ => p.z,
    }
}

pub fn set_axis(p: &mut Pos, a: char, v: f64) {
    match a {
        'X' => p.x = v,
        'Y' => p.y = v,
        _ => p.z = v,
    }
}

/// (absolute letter, incremental letter, scale to machine units) of a drilling axis.
fn letters(a: char) -> (char, char, f64) {
    match a {
        'X' => ('X', 'U', 0.5),
        'Y' => ('Y', 'V', 1.0),
        _ => ('Z', 'W', 1.0),
    }
}

fn is_cycle(g: GCode) -> bool {
    matches!(g, 830 | 840 | 850 | 870 | 880 | 890)
}

fn name(g: GCode) -> &'static str {
    match g {
        830 => "G83",
        840 => "G84",
        850 => "G85",
        870 => "G87",
        880 => "G88",
        _ => "G89",
    }
}

impl Interpreter {
    /// The rigid tapping M code (No.5210, default M29).
    fn rigid_m(&self) -> u32 {
        self.drill.par.m_5210
    }

    /// A block whose M code is the cycle's C-axis clamp code rather than an ordinary M
    /// code: a block with G83/G84/G85/G87/G88/G89.
    pub(in crate::interp) fn drill_clamp_block(&self, d: &Decoded) -> bool {
        d.group(10).is_some_and(is_cycle)
    }

    /// Before the block's S is applied (rigid tapping owns S in M29 blocks and, with
    /// No.5200#0 = 1, in G84/G88 blocks). Returns true when the S word was taken here.
    /// Also checks the rules between M29 and G84 (manual 004 §2.22.1).
    pub(in crate::interp) fn tap_block_start(&mut self, d: &Decoded, src: &SrcPos) -> Result<bool, CErr> {
        let rm = self.rigid_m();
        let m29 = d.m.iter().find(|m| m.0 == rm).map(|m| m.1);
        let g10 = d.group(10);
        let tapping = matches!(g10, Some(840 | 880));
        let gmode = self.drill.par.b5200[0];
        // E / M24–M27: the tapping spindle (000 note 2).
        if let Some(e) = d.get('E').filter(|_| tapping) {
            if !(1.0..=4.0).contains(&e.v) || e.v.fract() != 0.0 {
                return Err((RANGE_ALARM, Some(e.col), format!("E{}: the rigid tapping spindle is 1–4", e.v)));
            }
            self.drill.tap_e = Some(e.v as u8);
        }
        if self.drill.par.b5200[7] {
            if let Some(&(m, _)) = d.m.iter().find(|m| (24..=27).contains(&m.0)) {
                self.drill.rgtsp = (m - 23) as u8;
            }
        }
        if let Some(col) = m29 {
            if gmode {
                return Err((
                    RIGID_PROGRAM_ALARM,
                    Some(col),
                    format!("M{rm}: rigid tapping is selected by G84/G88 with S here (No.5200#0 = 1); remove M{rm}"),
                ));
            }
            let rigid_on = self.drill.modal.as_ref().is_some_and(|m| m.rigid);
            if self.drill.m29_pending || rigid_on {
                return Err((RIGID_PROGRAM_ALARM, Some(col), format!("M{rm} given twice: it may not be repeated in rigid tapping (G80 first)")));
            }
            let s = d.get('S').ok_or((RIGID_S_ALARM, Some(col), format!("M{rm} needs the tapping speed in its block: M{rm} S…")))?;
            self.check_tap_s(s.v, s.col)?;
            self.drill.tap_s = Some(s.v);
            self.drill.m29_pending = true;
            // The spindle does not turn at M29 (its output is S0); remember what it did.
            self.drill.spindle_before = Some((self.st.dir, self.st.rpm));
            if self.st.dir != SpindleDir::Stop {
                self.st.dir = SpindleDir::Stop;
                let c = SpindleCmd { dir: SpindleDir::Stop, rpm: 0.0, css: None, max_rpm: self.st.max_rpm };
                self.push(src, MoveKind::Spindle(c), false);
            }
            return Ok(true);
        }
        if self.drill.m29_pending && !tapping {
            if g10 == Some(800) {
                self.drill.m29_pending = false;
            } else if let Some(s) = d.get('S') {
                return Err((RIGID_PROGRAM_ALARM, Some(s.col), format!("S between M{rm} and G84/G88: give the tapping speed in the M{rm} block")));
            } else if let Some(l) = ['X', 'U', 'Z', 'W', 'Y', 'V', 'C', 'H'].into_iter().find(|l| d.has(*l)) {
                return Err((RIGID_AXIS_ALARM, d.get(l).map(|v| v.col), format!("axis move between M{rm} and G84/G88: position before M{rm}")));
            }
        }
        let rigid_now = self.drill.modal.as_ref().is_some_and(|m| m.rigid);
        if let Some(s) = d.get('S') {
            if (tapping && (gmode || self.drill.m29_pending)) || rigid_now {
                self.check_tap_s(s.v, s.col)?;
                self.drill.tap_s = Some(s.v);
                return Ok(true);
            }
        }
        Ok(false)
    }

    fn check_tap_s(&self, s: f64, col: u32) -> Result<(), CErr> {
        if s == 0.0 {
            return Err((RIGID_S_ALARM, Some(col), "S0: rigid tapping needs a spindle speed".into()));
        }
        let max = self.drill.par.max_5241;
        if max > 0.0 && s.abs() > max {
            return Err((RIGID_S_ALARM, Some(col), format!("S{s}: more than the rigid tapping maximum No.5241 = {max} rpm")));
        }
        Ok(())
    }

    /// Group 10 (and group 01 cancelling it) at the start of the block's motion part.
    pub(in crate::interp) fn drill_modal(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        let g10 = d.group(10);
        if g10 == Some(800) || (d.group(1).is_some() && self.drill.modal.is_some() && g10.is_none()) {
            self.drill_cancel(src);
            return Ok(());
        }
        let Some(g) = g10.filter(|g| is_cycle(*g)) else {
            return Ok(());
        };
        let face = matches!(g, 830 | 840 | 850);
        let axis = match (self.drill.par.fixed_5209, face, self.st.plane) {
            (true, true, _) => 'Z',
            (true, false, _) => 'X',
            (false, true, Plane::Xy) => 'X',
            (false, true, Plane::Zx) => 'Z',
            (false, true, Plane::Yz) => 'Y',
            (false, false, Plane::Xy) => 'Y',
            (false, false, Plane::Zx) => 'X',
            (false, false, Plane::Yz) => 'Z',
        };
        if axis == 'Y' && !self.has_y {
            return Err((10, Self::gcol(d), format!("{}: the drilling axis of this plane is Y, which this machine lacks", name(g))));
        }
        let tapping = matches!(g, 840 | 880);
        let prev = self.drill.modal.take();
        let same_axis = prev.as_ref().filter(|m| m.axis == axis);
        let was_rigid = prev.as_ref().is_some_and(|m| m.rigid);
        let rigid = tapping && (self.drill.m29_pending || self.drill.par.b5200[0] || was_rigid);
        if rigid && !was_rigid && !self.drill.m29_pending {
            // No.5200#0 = 1: G84 itself enters rigid mode; the spindle stops like at M29.
            self.drill.spindle_before = Some((self.st.dir, self.st.rpm));
            if self.st.dir != SpindleDir::Stop {
                self.st.dir = SpindleDir::Stop;
                let c = SpindleCmd { dir: SpindleDir::Stop, rpm: 0.0, css: None, max_rpm: self.st.max_rpm };
                self.push(src, MoveKind::Spindle(c), false);
            }
        }
        if was_rigid && !rigid {
            // Another cycle without G80 ends rigid tapping as G80 would.
            self.drill.modal = prev.clone();
            self.drill_cancel(src);
        }
        self.drill.m29_pending = false;
        let mut m = DrillModal {
            code: g,
            axis,
            initial: same_axis.map(|m| m.initial).unwrap_or(axis_of(&self.pos, axis)),
            r: same_axis.map(|m| m.r).unwrap_or(0.0),
            depth: same_axis.and_then(|m| m.depth),
            q: prev.as_ref().map(|m| m.q).unwrap_or(0.0),
            dwell: prev.as_ref().map(|m| m.dwell).unwrap_or(0.0),
            d: prev.as_ref().and_then(|m| m.d),
            clamp: prev.as_ref().and_then(|m| m.clamp),
            rigid,
        };
        if rigid && self.drill.tap_s.is_none() {
            return Err((
                RIGID_S_ALARM,
                Self::gcol(d),
                format!("{}: no tapping speed: give S with M{} (or in the G84/G88 block when No.5200#0 = 1)", name(g), self.rigid_m()),
            ));
        }
        if let Some(r) = d.get('R') {
            m.r = self.len(r);
        }
        if let Some(q) = d.get('Q') {
            if q.v < 0.0 {
                return Err((RANGE_ALARM, Some(q.col), format!("Q{}: the cut per peck is unsigned", q.v)));
            }
            m.q = self.len(q);
        }
        if let Some(p) = d.get('P') {
            if p.v < 0.0 {
                return Err((RANGE_ALARM, Some(p.col), "P: the dwell cannot be negative".into()));
            }
            m.dwell = if rigid {
                if p.literal && p.decimal {
                    return Err((7, Some(p.col), "rigid tapping P is in milliseconds without a decimal point (P3000 = 3 s)".into()));
                }
                p.v / 1000.0
            } else {
                p.v
            };
        }
        if let Some(dv) = d.get('D').filter(|_| tapping) {
            if dv.v < 0.0 {
                return Err((RANGE_ALARM, Some(dv.col), "D: the peck return is unsigned".into()));
            }
            m.d = Some(self.len(dv));
        }
        if let Some(j) = d.get('J').filter(|_| tapping) {
            if j.v <= 0.0 {
                return Err((RANGE_ALARM, Some(j.col), format!("J{}: the pull-out spindle speed must be positive", j.v)));
            }
            self.drill.tap_j = Some(j.v);
        }
        let rm = self.rigid_m();
        let sel = self.drill.par.b5200[7];
        if let Some(&(mc, _)) = d.m.iter().find(|m| m.0 != rm && !(sel && (24..=27).contains(&m.0))) {
            m.clamp = Some(mc);
        }
        self.drill.modal = Some(m);
        Ok(())
    }

    /// G80 (or a group-01 code): drilling data cleared, rigid tapping left, its S cleared
    /// (000 note 5); the spindle state from before rigid tapping is restored if no hole did
    /// it already (004 step ⑦).
    fn drill_cancel(&mut self, src: &SrcPos) {
        let was_rigid = self.drill.modal.take().is_some_and(|m| m.rigid) || self.drill.m29_pending;
        self.drill.m29_pending = false;
        self.drill.tap_s = None;
        self.drill.tap_j = None;
        self.drill.tap_e = None;
        self.drill.flex_dir = None;
        if was_rigid && self.drill.par.b5200[2] {
            // No.5200#2 = 1: the cancel waits for RGTAP = 0, i.e. for the spindle to have left
            // rigid (position) control. Without a PLC that is the end of the last stroke: an
            // exact-stop wait point that nothing after the cancel passes before motion is
            // there (Fanuc 0i-TF: the next block starts after the signal drops).
            self.push(src, MoveKind::Dwell { seconds: 0.0 }, true);
        }
        if was_rigid {
            if let Some((dir, rpm)) = self.drill.spindle_before.take() {
                if dir != SpindleDir::Stop && self.st.dir != dir {
                    self.st.dir = dir;
                    self.st.rpm = rpm;
                    let c = self.spindle_cmd(dir);
                    self.push(src, MoveKind::Spindle(c), false);
                }
            }
        }
    }

    /// True when the block drills: drilling mode on and an axis word present.
    pub(in crate::interp) fn drill_active(&self, d: &Decoded) -> bool {
        self.drill.modal.is_some() && ['X', 'U', 'Z', 'W', 'Y', 'V', 'C', 'H'].iter().any(|l| d.has(*l))
    }

    /// Drill the block's hole(s).
    pub(in crate::interp) fn drill_block(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), CErr> {
        let Some(mut m) = self.drill.modal.clone() else { return Ok(()) };
        let gc = Self::gcol(d);
        let (abs, inc, scale) = letters(m.axis);
        let off = self.offset();
        if let Some(v) = d.get(abs) {
            m.depth = Some(Depth::Abs(self.len(v) * scale + axis_of(&off, m.axis)));
        } else if let Some(v) = d.get(inc) {
            m.depth = Some(Depth::Inc(self.len(v) * scale));
        }
        self.drill.modal = Some(m.clone());
        let k = match d.get('K') {
            None => 1,
            Some(k) => {
                let ok = k.v.fract() == 0.0 && ((0.0..=99.0).contains(&k.v) || (k.v == 198.0 && matches!(m.code, 840 | 880)));
                if !ok {
                    return Err((
                        RANGE_ALARM,
                        Some(k.col),
                        format!("K{}: the repeat count is 0–99 (K198 stays at the bottom, rigid tapping only)", k.v),
                    ));
                }
                k.v as u32
            }
        };
        let stay = k == 198 && m.rigid;
        let holes = if stay { 1 } else { k };
        if m.q > 0.0 && holes > 0 {
            let per_hole = (self.drill_span(&m, d)? / m.q).ceil();
            if per_hole * holes as f64 > MAX_PECKS {
                return Err((
                    RANGE_ALARM,
                    d.get('Q').map(|q| q.col).or(gc),
                    format!("Q{}: {} pecks in this block; increase Q", m.q, per_hole * holes as f64),
                ));
            }
        }
        let depth = m.depth.ok_or((RANGE_ALARM, gc, format!("{}: no hole bottom: program {abs}({inc}) once in the drilling mode", name(m.code))))?;
        let feed = if m.rigid { self.feed(gc).map_err(|(_, c, msg)| (RIGID_F_ALARM, c, msg))? } else { self.feed(d.get('F').map(|f| f.col).or(gc))? };
        let rpoint = m.initial + m.r;
        let bottom = match depth {
            Depth::Abs(b) => b,
            Depth::Inc(w) => rpoint + w,
        };
        let tag: Arc<str> = Arc::from(name(m.code));
        for _ in 0..holes {
            let mut hole = self.target(d).unwrap_or(self.pos);
            self.tool_delta = Pos::ZERO;
            set_axis(&mut hole, m.axis, m.initial);
            let at = |v: f64| {
                let mut p = hole;
                set_axis(&mut p, m.axis, v);
                p
            };
            // Action 1: the hole position on the initial plane. A C move rapids the spindle
            // (Cs) to its angle.
            if axis_of(&self.pos, m.axis) != m.initial {
                // Not on the initial plane (a K198 hole left the tool at its bottom): back
                // there along the drilling axis first.
                let mut up = self.pos;
                set_axis(&mut up, m.axis, m.initial);
                self.cpush(src, &tag, 1, MoveKind::Rapid { end: up }, true);
            }
            self.cpush(src, &tag, 1, MoveKind::Rapid { end: hole }, true);
            if let Some(c) = m.clamp.or(self.drill.par.clamp_5110) {
                self.cpush(src, &tag, 1, MoveKind::Aux { letter: 'M', value: c as f64 }, false);
            }
            self.cpush(src, &tag, 2, MoveKind::Rapid { end: at(rpoint) }, true);
            match m.code {
                830 | 870 => self.drill_cut(src, &tag, &m, rpoint, bottom, feed, &at)?,
                850 | 890 => {
                    // Boring (figure 2.76, steps as Fanuc 0i-TF): ③ feed to the bottom,
                    // ④ dwell, ⑤ feed back to R, ⑥ rapid to the initial plane.
                    self.cpush(src, &tag, 3, MoveKind::Feed { end: at(bottom), feed }, true);
                    self.dwell(src, &tag, 4, m.dwell);
                    self.cpush(src, &tag, 5, MoveKind::Feed { end: at(rpoint), feed }, true);
                }
                _ if m.rigid => {
                    let done = self.rigid_tap(src, &tag, &m, rpoint, bottom, feed, stay, gc, &at)?;
                    if !done {
                        return Ok(());
                    }
                }
                _ => self.flexible_tap(src, &tag, &m, rpoint, bottom, feed, &at)?,
            }
            if let Some(c) = m.clamp.or(self.drill.par.clamp_5110) {
                self.cpush(src, &tag, 5, MoveKind::Aux { letter: 'M', value: c as f64 + 1.0 }, false);
                if self.drill.par.dwell_5111 > 0.0 {
                    self.dwell(src, &tag, 5, self.drill.par.dwell_5111);
                }
            }
            self.cpush(src, &tag, 6, MoveKind::Rapid { end: at(m.initial) }, true);
        }
        Ok(())
    }

    /// |bottom − R point| of the block's hole.
    fn drill_span(&self, m: &DrillModal, _d: &Decoded) -> Result<f64, CErr> {
        let rp = m.initial + m.r;
        Ok(match m.depth {
            Some(Depth::Abs(b)) => (b - rp).abs(),
            Some(Depth::Inc(w)) => w.abs(),
            None => 0.0,
        })
    }

    fn dwell(&mut self, src: &SrcPos, tag: &Arc<str>, step: u8, s: f64) {
        if s > 0.0 {
            self.cpush(src, tag, step, MoveKind::Dwell { seconds: s }, true);
        }
    }

    /// G83/G87 from the R point. No Q: ③ feed to the bottom. High-speed peck (No.5101 = 0):
    /// ③ feed q, ④ rapid back d (No.5113), ③ feed q + d, … to the bottom. Peck (No.5101 = 1):
    /// ③ feed q, ④ rapid to R, ⑤ rapid to d short of the last depth, ⑥ feed q + d, … Then
    /// ⑥/⑧ dwell P, ⑦/⑨ rapid to R (our actions 3 cut, 4 dwell, 5 R; the manual's ④⑤ of
    /// the peck cycle are tagged 3, being inside the hole).
    #[allow(clippy::too_many_arguments)]
    fn drill_cut(
        &mut self,
        src: &SrcPos,
        tag: &Arc<str>,
        m: &DrillModal,
        rp: f64,
        bottom: f64,
        feed: Feed,
        at: &dyn Fn(f64) -> Pos,
    ) -> Result<(), CErr> {
        let total = (bottom - rp).abs();
        let dir = (bottom - rp).signum();
        let q = m.q;
        let dd = self.drill.par.d_5113;
        if q <= 0.0 || q >= total {
            self.cpush(src, tag, 3, MoveKind::Feed { end: at(bottom), feed }, true);
        } else {
            let mut depth = 0.0;
            loop {
                let next = (depth + q).min(total);
                if depth > 0.0 {
                    if self.drill.par.peck_5101 {
                        self.cpush(src, tag, 3, MoveKind::Rapid { end: at(rp) }, true);
                        self.cpush(src, tag, 3, MoveKind::Rapid { end: at(rp + dir * (depth - dd).max(0.0)) }, true);
                    } else {
                        self.cpush(src, tag, 3, MoveKind::Rapid { end: at(rp + dir * (depth - dd).max(0.0)) }, true);
                    }
                }
                self.cpush(src, tag, 3, MoveKind::Feed { end: at(rp + dir * next), feed }, true);
                if next >= total - 1e-9 {
                    break;
                }
                depth = next;
            }
        }
        self.dwell(src, tag, 4, m.dwell);
        self.cpush(src, tag, 5, MoveKind::Rapid { end: at(rp) }, true);
        Ok(())
    }

    /// The pull-out override in % (manual 000 table): No.5200#4 = 0 → 100; else J/S × 100
    /// when No.5201#4 = 1 and J is given and within 100–200 % (No.5202#6 = 1: 100–2000 %),
    /// 100 when J is out of that range; No.5211 otherwise (unit 1 %, 10 % with No.5201#3),
    /// 100 when No.5211 is unset (0) or below 100 %.
    pub fn pull_out_override(&self, s: f64) -> f64 {
        let p = &self.drill.par;
        if !p.b5200[4] {
            return 100.0;
        }
        let max = if p.b5202_6 { 2000.0 } else { 200.0 };
        if p.b5201_4 {
            if let Some(j) = self.drill.tap_j {
                let o = j / s.abs() * 100.0;
                return if (100.0..=max + 1e-9).contains(&o) { o } else { 100.0 };
            }
        }
        let o = p.ovr_5211 * if p.b5201_3 { 10.0 } else { 1.0 };
        if (100.0..=max).contains(&o) {
            o
        } else {
            100.0
        }
    }

    /// Rigid tapping G84/G88 from the R point (manual 000). Lead = F/S (G98) or F (G99);
    /// the strokes are [`MoveKind::Tap`] with the lead signed so that the spindle turns
    /// forward (M03 sense) going in: lead sign = direction into the hole, negated for a
    /// reverse thread (negative S, No.5170 = 1 or the direction signal). In-strokes run at S,
    /// retracts (and the standard peck's return to d above the last depth) at S × override.
    ///
    /// Standard (no Q): 000 (3) tap to the bottom, (4) dwell P, (5) tap back to R. High-speed
    /// peck (No.5200#5 = 0): (4) q, (5) back d (D or No.5213), (6) q + d, … (8) dwell, (9)
    /// back to R. Peck (No.5200#5 = 1): (4) q, (5) back to R, (6) in to d short of the last
    /// depth, (7) q + d, … (9) dwell, (10) back to R. Then No.5282 further and No.7013
    /// dwell at R, and the spindle state from before rigid tapping back (004 ⑦, when it
    /// was turning). Tags: in-strokes and peck returns 3, dwell 4, return 5.
    ///
    /// K198: stops after the dwell at the bottom; the tap state is kept for `G30 P99` and
    /// the next block starts there. Returns false then.
    #[allow(clippy::too_many_arguments)]
    fn rigid_tap(
        &mut self,
        src: &SrcPos,
        tag: &Arc<str>,
        m: &DrillModal,
        rp: f64,
        bottom: f64,
        feed: Feed,
        stay: bool,
        gc: Option<u32>,
        at: &dyn Fn(f64) -> Pos,
    ) -> Result<bool, CErr> {
        let s = self.drill.tap_s.ok_or((RIGID_S_ALARM, gc, "rigid tapping without S".to_string()))?;
        let rpm = s.abs();
        let lead_abs = match feed {
            Feed::PerMin(f) => f / rpm,
            Feed::PerRev(f) => f,
        };
        if !(lead_abs > 0.0 && lead_abs <= super::MAX_LEAD) {
            return Err((RIGID_F_ALARM, gc, format!("rigid tapping lead {lead_abs:.4} mm: check F and S")));
        }
        let dir = (bottom - rp).signum();
        if dir == 0.0 {
            return Ok(true);
        }
        let reverse = (s < 0.0) ^ self.drill.par.reverse_5170 ^ self.drill.reverse_signal;
        let lead = dir * lead_abs * if reverse { -1.0 } else { 1.0 };
        let ovr = self.pull_out_override(s);
        let out = rpm * ovr / 100.0;
        let total = (bottom - rp).abs();
        let spindle = self.tap_spindle();
        let tap = |end: Pos, rpm: f64| MoveKind::Tap { end, lead, rpm, spindle };
        let info = TapReturn { axis: m.axis, r_plane: rp, lead, rpm, override_pct: ovr, spindle };
        self.drill.last_tap = Some(info);
        let q = m.q;
        if q <= 0.0 || q >= total {
            self.cpush(src, tag, 3, tap(at(bottom), rpm), true);
        } else {
            let standard = self.drill.par.b5200[5];
            let d = m.d.unwrap_or(self.drill.par.d_5213);
            let mut depth = 0.0;
            loop {
                let next = (depth + q).min(total);
                if depth > 0.0 {
                    if standard {
                        self.cpush(src, tag, 3, tap(at(rp), out), true);
                        self.cpush(src, tag, 3, tap(at(rp + dir * (depth - d).max(0.0)), out), true);
                    } else {
                        self.cpush(src, tag, 3, tap(at(rp + dir * (depth - d).max(0.0)), out), true);
                    }
                }
                self.cpush(src, tag, 3, tap(at(rp + dir * next), rpm), true);
                if next >= total - 1e-9 {
                    break;
                }
                depth = next;
            }
        }
        self.dwell(src, tag, 4, m.dwell);
        if stay {
            self.drill.tap_return = Some(info);
            return Ok(false);
        }
        self.cpush(src, tag, 5, tap(at(rp), out), true);
        let extra = self.drill.par.extra_5282;
        if extra > 0.0 {
            self.cpush(src, tag, 5, tap(at(rp - dir * extra), out), true);
        }
        let d7013 = self.drill.par.dwell_7013;
        self.dwell(src, tag, 5, d7013);
        // 004 step ⑦: the spindle turns again as it did before rigid tapping (the next hole's
        // first stroke stops it again).
        if let Some((dir, rpm)) = self.drill.spindle_before.filter(|b| b.0 != SpindleDir::Stop) {
            self.st.dir = dir;
            self.st.rpm = rpm;
            let c = self.spindle_cmd(dir);
            self.cpush(src, tag, 5, MoveKind::Spindle(c), false);
        }
        Ok(true)
    }

    /// Flexible (normal) tapping, G84/G88 without M29 (manual 004 §2.22.3): ③ the spindle
    /// starts forward (its programmed direction if it runs, else M03; not output when already
    /// turning), ④ feed to the bottom following the spindle encoder (a per-revolution feed of
    /// one lead; lead = F/S under G98, F under G99, S the modal speed) and M05, ⑤ dwell P,
    /// ⑥ the spindle reversed, ⑦ feed back to R, ⑧ M05. Tags: ③④ → 3, ⑤ → 4, ⑥⑦⑧ → 5.
    /// Motion runs the strokes following the spindle encoder (one lead per revolution, no
    /// feed override: note 3), with the encoder lag No.5275 compensated and the retract
    /// waiting for the reversed spindle at No.5276 (see `Motion::flex_tap_v`).
    #[allow(clippy::too_many_arguments)]
    fn flexible_tap(
        &mut self,
        src: &SrcPos,
        tag: &Arc<str>,
        m: &DrillModal,
        rp: f64,
        bottom: f64,
        feed: Feed,
        at: &dyn Fn(f64) -> Pos,
    ) -> Result<(), CErr> {
        let rpm = self.st.rpm;
        let lead = match feed {
            Feed::PerMin(f) => {
                if rpm <= 0.0 {
                    return Err((
                        RANGE_ALARM,
                        None,
                        format!("{}: lead = F/S needs a spindle speed: program S before the tapping cycle", name(m.code)),
                    ));
                }
                f / rpm
            }
            Feed::PerRev(f) => f,
        };
        let fwd = self.drill.flex_dir.unwrap_or(if self.st.dir == SpindleDir::Ccw { SpindleDir::Ccw } else { SpindleDir::Cw });
        let rev = if fwd == SpindleDir::Cw { SpindleDir::Ccw } else { SpindleDir::Cw };
        let max_rpm = self.st.max_rpm;
        let cmd = |dir| SpindleCmd { dir, rpm, css: None, max_rpm };
        if self.st.dir != fwd {
            self.cpush(src, tag, 3, MoveKind::Spindle(cmd(fwd)), false);
        }
        self.cpush(src, tag, 3, MoveKind::Feed { end: at(bottom), feed: Feed::PerRev(lead) }, true);
        self.cpush(src, tag, 3, MoveKind::Spindle(cmd(SpindleDir::Stop)), false);
        self.dwell(src, tag, 4, m.dwell);
        self.cpush(src, tag, 5, MoveKind::Spindle(cmd(rev)), false);
        self.cpush(src, tag, 5, MoveKind::Feed { end: at(rp), feed: Feed::PerRev(lead) }, true);
        self.cpush(src, tag, 5, MoveKind::Spindle(cmd(SpindleDir::Stop)), false);
        // The spindle stands still now; the next hole turns it on the same way (note 2).
        self.st.dir = SpindleDir::Stop;
        self.drill.flex_dir = Some(fwd);
        Ok(())
    }

    /// `G30 P99 S_` (manual 000): pull the tap back along the thread to the R plane (plus
    /// No.5382), the spindle counter-rotating in sync, at S (or the stored speed) × the
    /// pull-out override. The state comes from [`Interpreter::set_tap_return`] (an
    /// interrupted tap, restored after a restart) or from a K198 hole of this program.
    /// Afterwards the drilling mode is G80 (note 3).
    pub(in crate::interp) fn g30_p99(&mut self, d: &Decoded, src: &SrcPos, col: Option<u32>) -> Result<(), CErr> {
        if self.drill.par.b5200[0] {
            return Err((RIGID_PROGRAM_ALARM, col, "G30 P99 needs No.5200#0 = 0 (note 1)".into()));
        }
        let t = self.drill.tap_return.ok_or((TAP_RETURN_ALARM, col, "G30 P99: there is no interrupted rigid tap to return from".to_string()))?;
        let rpm = match d.get('S') {
            Some(s) if s.v > 0.0 => s.v,
            Some(s) => return Err((RIGID_S_ALARM, Some(s.col), format!("G30 P99 S{}: the speed must be positive", s.v))),
            None => t.rpm,
        };
        self.check_tap_s(rpm, col.unwrap_or(1))?;
        let out = rpm * t.override_pct / 100.0;
        let here = axis_of(&self.pos, t.axis);
        // The direction out of the hole: from the tool towards the R plane.
        let out_dir = (t.r_plane - here).signum();
        let mut end = self.pos;
        let extra = self.drill.par.extra_5382;
        let target = t.r_plane + if out_dir != 0.0 { out_dir * extra } else { -t.lead.signum() * extra };
        set_axis(&mut end, t.axis, target);
        let tag: Arc<str> = Arc::from("G30 P99");
        self.cpush(src, &tag, 5, MoveKind::Tap { end, lead: t.lead, rpm: out, spindle: t.spindle }, true);
        self.drill.tap_return = None;
        self.drill_cancel(src);
        Ok(())
    }

    /// The drilling mode and data to keep through a reset or emergency stop: all of it when
    /// No.5155#0 = 1, none otherwise (004 §2.21.4 note 1; Fanuc clears to G80).
    pub fn drill_modal_after_reset(&self) -> Option<DrillModal> {
        if self.drill.par.keep_5155 {
            self.drill.modal.clone()
        } else {
            None
        }
    }

    /// The drilling mode in force (None = G80).
    pub fn drill_mode(&self) -> Option<&DrillModal> {
        self.drill.modal.as_ref()
    }

    /// Give back a drilling mode kept through a reset (see
    /// [`Interpreter::drill_modal_after_reset`]).
    pub fn set_drill_modal(&mut self, m: Option<DrillModal>) {
        self.drill.modal = m;
    }

    /// The state G30 P99 returns along: an interrupted tap, restored after a restart (the
    /// tool's position is the interpreter's start position).
    /// The interrupted tap G30 P99 returns from, as set with [`Self::set_tap_return`].
    pub fn tap_return(&self) -> Option<TapReturn> {
        self.drill.tap_return
    }

    pub fn set_tap_return(&mut self, t: Option<TapReturn>) {
        self.drill.tap_return = t;
    }

    /// The rigid tap cycle the interpreter last expanded (R plane, signed lead, speed,
    /// override): what a watcher persists while that cycle's [`MoveKind::Tap`] strokes run.
    pub fn last_tap(&self) -> Option<TapReturn> {
        self.drill.last_tap
    }

    /// The rigid-tapping direction signal (G61.2): true = reverse thread with a positive S.
    pub fn set_tap_reverse_signal(&mut self, on: bool) {
        self.drill.reverse_signal = on;
    }

    /// The rigid tapping spindle (1–4, manual 000 note 2): E of the tapping mode (kept until
    /// G80); without E, by No.5200#7: 1 = the M24–M27 selection (held until another one,
    /// "状态保持"), 0 = the spindle selection signals SWS1–SWS4, which this machine does not
    /// have: its one spindle, 1.
    pub fn tap_spindle(&self) -> u8 {
        self.drill.tap_e.unwrap_or(if self.drill.par.b5200[7] { self.drill.rgtsp } else { 1 })
    }
}
