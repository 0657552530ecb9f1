//! Canonical moves: the contract between the interpreter and everything after it.
//!
//! Units: millimetres, degrees, seconds. X is held as a **radius** (the interpreter converts
//! the programmed diameter). Positions are **machine coordinates**; each move also carries
//! the work offset in force so that tools (`cncgw plan`) can print workpiece coordinates
//! the way an operator reads them.

use std::fmt;
use std::sync::Arc;

/// Where a move came from: file, 1-based line and column of the block.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct SrcPos {
    pub file: Arc<str>,
    pub line: u32,
    pub col: u32,
}

impl SrcPos {
    pub fn new(file: Arc<str>, line: u32, col: u32) -> Self {
        Self { file, line, col }
    }
}

impl fmt::Display for SrcPos {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file, self.line, self.col)
    }
}

/// A point in machine coordinates. `x` is a radius in mm, `z`/`y` mm, `c` degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pos {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub c: f64,
}

impl Pos {
    pub const ZERO: Pos = Pos { x: 0.0, y: 0.0, z: 0.0, c: 0.0 };
    pub fn xz(x: f64, z: f64) -> Self {
        Pos { x, z, ..Pos::ZERO }
    }
    // Named methods rather than `ops::Sub`/`Add`: a Pos is a point, and point − point is
    // written out where it is meant.
    #[allow(clippy::should_implement_trait)]
    pub fn sub(self, o: Pos) -> Pos {
        Pos { x: self.x - o.x, y: self.y - o.y, z: self.z - o.z, c: self.c - o.c }
    }
    #[allow(clippy::should_implement_trait)]
    pub fn add(self, o: Pos) -> Pos {
        Pos { x: self.x + o.x, y: self.y + o.y, z: self.z + o.z, c: self.c + o.c }
    }
}

/// Feed rate as programmed (G98 per minute / G99 per revolution).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Feed {
    /// mm/min (G98).
    PerMin(f64),
    /// mm per spindle revolution (G99).
    PerRev(f64),
}

/// Interpolation plane (G17 XY, G18 ZX, G19 YZ).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Plane {
    Xy,
    #[default]
    Zx,
    Yz,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SpindleDir {
    /// M03
    Cw,
    /// M04
    Ccw,
    /// M05
    Stop,
}

/// A spindle state change. `rpm` is the commanded speed under G97; under G96 `css` holds the
/// surface speed (m/min) and the motion layer computes rpm from the actual X, clamped to
/// `max_rpm` (G50 S).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpindleCmd {
    pub dir: SpindleDir,
    pub rpm: f64,
    pub css: Option<f64>,
    pub max_rpm: Option<f64>,
}

/// G51.2 P Q R S (manual 004 §2.8): work spindle speed `rpm` (S), the tool spindle at
/// `tool_rpm` = S × Q / P clamped to No.721 (note 3), phase `phase` degrees (R, 0–359.999).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolygonCmd {
    pub p: u32,
    pub q: u32,
    pub phase: f64,
    pub rpm: f64,
    pub tool_rpm: f64,
}

/// The machine X (radius) and C (degrees) of the virtual polar-interpolation point `v`
/// ([x, c], mm): C is `c_zero` + the angle of `v`, taken as the one nearest `near_c` so that
/// C stays continuous along a path. At the centre the angle is undefined; `near_c` is kept.
pub fn polar_to_machine(v: [f64; 2], c_zero: f64, work_x: f64, near_c: f64) -> (f64, f64) {
    let r = v[0].hypot(v[1]);
    if r < 1e-12 {
        return (work_x, near_c);
    }
    let a = c_zero + v[1].atan2(v[0]).to_degrees();
    let c = a + ((near_c - a) / 360.0).round() * 360.0;
    (work_x + r, c)
}

/// A difference of angles (radians) as the sweep of an arc turning `cw` (≤ 0) or
/// counter-clockwise (≥ 0), within 1e-12 of zero kept as it is.
pub fn wrap_sweep(mut sweep: f64, cw: bool) -> f64 {
    let tau = std::f64::consts::TAU;
    if cw {
        while sweep > 1e-12 {
            sweep -= tau;
        }
    } else {
        while sweep < -1e-12 {
            sweep += tau;
        }
    }
    sweep
}

/// Start angle and signed sweep (radians) of an arc in a plane from `from` to `to` about
/// `c` (`cw`: clockwise, sweep ≤ 0); start = end is a full circle. Used by the interpreter's
/// polar chords and the motion layer's polar interpolation alike.
pub fn arc_sweep(from: [f64; 2], to: [f64; 2], c: [f64; 2], cw: bool) -> (f64, f64) {
    let a0 = (from[1] - c[1]).atan2(from[0] - c[0]);
    let a1 = (to[1] - c[1]).atan2(to[0] - c[0]);
    (a0, wrap_sweep(a1 - a0, cw))
}

/// Which canned cycle made a move, and which step of it (the manuals' numbering), so that
/// feed hold and single block can be applied per step downstream.
#[derive(Clone, Debug, PartialEq)]
pub struct CycleTag {
    pub cycle: Arc<str>,
    pub step: u8,
}

#[derive(Clone, Debug, PartialEq)]
pub enum MoveKind {
    /// G00 positioning at rapid rate.
    Rapid { end: Pos },
    /// G01 linear interpolation.
    Feed { end: Pos, feed: Feed },
    /// G02/G03 circular interpolation in `plane`; `center` in machine coordinates.
    Arc { end: Pos, center: Pos, cw: bool, plane: Plane, feed: Feed },
    /// Spindle-synchronized thread cut (G32/G92/G76/G78): the feed axes are slaved to the
    /// spindle. `lead` is mm per revolution along the long axis; `start_angle` the spindle
    /// angle (degrees) after the one-revolution signal at which the cut starts.
    /// `continuous`: this thread directly follows another thread move (consecutive G32
    /// blocks, or a cycle's run-out), so it starts without waiting for the one-revolution
    /// signal (manual 004 §2.17.1 note 2) and `start_angle` does not apply.
    /// `lead_inc`: G34 variable lead, the lead grows by this much (mm, signed) per spindle
    /// revolution from `lead` at the start; 0 for a constant lead.
    Thread { end: Pos, lead: f64, start_angle: f64, continuous: bool, lead_inc: f64 },
    /// Rigid tap stroke along the tapping axis (Z for G84 in G18; X for G88, a radius, the
    /// lead along it): spindle angle and feed axis interpolated together, angle =
    /// θ_ref + 360·(axis − axis_ref)/`lead`. `lead` mm per revolution, signed so that the
    /// spindle turns forward (M03 sense) while the tool moves towards the sign of `lead`;
    /// consecutive strokes of one hole share it (in and out, pecks). `rpm` is this stroke's
    /// spindle speed: S going in, S × the pull-out override coming out. `spindle` is the
    /// tapping spindle 1–4 (manual 000 note 2: E, or M24–M27 with No.5200#7; 1 when none is
    /// selected); a machine that lacks it refuses the stroke before moving.
    Tap { end: Pos, lead: f64, rpm: f64, spindle: u8 },
    /// G92.1 rigid thread (manual 001 §3.24.10): the spindle works as a position axis (Cs)
    /// and is interpolated with the feed axes, from the start's `c` to `end.c` (degrees,
    /// cumulative; increasing for a right-hand thread, decreasing for a left-hand one) while
    /// X/Z go to `end`. `lead` mm per revolution along the long axis (negative = left hand),
    /// `rpm` the spindle speed. Both stop at the end (no run-out).
    RigidThread { end: Pos, lead: f64, rpm: f64 },
    /// G12.1 polar coordinate interpolation (manual 004 §2.7): a G01 line or G02/G03 arc
    /// programmed in the virtual plane of the linear axis X and the hypothetical axis C (both
    /// mm, X as a radius, the origin on the rotation centre; G03 counter-clockwise from +X
    /// towards +C), from `from` to `to` ([x, c]); `center` is the arc centre (None = a line).
    /// `feed` is the tangential speed in that plane (§2.7 note 5). The motion layer
    /// interpolates the virtual point and converts it every cycle with [`polar_to_machine`]:
    /// machine X = work_offset.x + √(x² + c²), C = `c_zero` + the angle of (x, c) in degrees,
    /// continuous along the path; `end` is the machine end point so converted. Z (and Y) move
    /// linearly with the path.
    Polar { end: Pos, from: [f64; 2], to: [f64; 2], center: Option<[f64; 2]>, cw: bool, c_zero: f64, feed: Feed },
    /// G51.2 polygon turning (manual 004 §2.8), `Some`: the tool spindle runs synchronised
    /// with the work spindle at Q/P of its speed with phase `phase`; `None` = G50.2 cancel.
    Polygon(Option<PolygonCmd>),
    /// G04: wait `seconds`.
    Dwell { seconds: f64 },
    /// Spindle start/stop/speed change.
    Spindle(SpindleCmd),
    /// An auxiliary code passed through: letter (`M`, `T`, `S`, `B`) and value.
    Aux { letter: char, value: f64 },
    /// M00 (optional = false) or M01 (optional = true).
    Stop { optional: bool },
    /// M02 or M30.
    End { code: u16 },
    /// G22 (`Some`: stored stroke check 2 on with this area) or G23 (`None`: off), in program
    /// order, so that whoever checks set-points switches it when execution reaches the block.
    /// A G22 whose corners are in the wrong order disables the check (§2.10 note 8): `None`.
    StrokeCheck { area: Option<StrokeArea> },
}

/// The G22 area: a box in machine coordinates (X a radius; Y ±∞ when not programmed or on a
/// machine without Y), `lo` the negative corner (I J K), `hi` the positive one (X Y Z).
/// `outside`: No.1002#0 = 1, the outside of the box is forbidden; else the inside.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StrokeArea {
    pub lo: Pos,
    pub hi: Pos,
    pub outside: bool,
}

/// One canonical move, with where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct Move {
    pub src: SrcPos,
    pub kind: MoveKind,
    /// Exact stop at the end of this move (G09 in the block, G61 modal, or required by the
    /// manual, e.g. the end of every rapid).
    pub exact_stop: bool,
    /// Work offset in force (machine = work + offset), for printing workpiece coordinates.
    pub work_offset: Pos,
    /// Canned cycle and step, when a cycle made this move.
    pub tag: Option<CycleTag>,
}

impl MoveKind {
    /// The end point of a motion, if this move moves the axes.
    pub fn end(&self) -> Option<Pos> {
        match self {
            MoveKind::Rapid { end }
            | MoveKind::Feed { end, .. }
            | MoveKind::Arc { end, .. }
            | MoveKind::Thread { end, .. }
            | MoveKind::Tap { end, .. }
            | MoveKind::RigidThread { end, .. }
            | MoveKind::Polar { end, .. } => Some(*end),
            _ => None,
        }
    }

    /// The `kind` name used by `cncgw plan`.
    pub fn name(&self) -> &'static str {
        match self {
            MoveKind::Rapid { .. } => "rapid",
            MoveKind::Feed { .. } => "feed",
            MoveKind::Arc { .. } => "arc",
            MoveKind::Thread { .. } => "thread",
            MoveKind::Tap { .. } => "tap",
            MoveKind::RigidThread { .. } => "rigid_thread",
            MoveKind::Polar { .. } => "polar",
            MoveKind::Polygon(_) => "polygon",
            MoveKind::Dwell { .. } => "dwell",
            MoveKind::Spindle(_) => "spindle",
            MoveKind::Aux { .. } => "aux",
            MoveKind::Stop { .. } => "stop",
            MoveKind::End { .. } => "end",
            MoveKind::StrokeCheck { .. } => "stroke_check",
        }
    }
}

/// What `G30 P99` needs to pull a rigid tap out of an interrupted hole (manual 000,
/// "刚性攻丝返回"): kept on disk by whoever watches the tap while its [`MoveKind::Tap`]
/// strokes run, and given back to the interpreter after a restart. The tool's position is the
/// interpreter's start position; the spindle angle is motion's (the return takes the angle
/// it finds as the thread's reference).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TapReturn {
    /// Tapping axis: `'X'`, `'Y'` or `'Z'`.
    pub axis: char,
    /// The R plane along that axis (machine mm, X as a radius): where the return ends.
    pub r_plane: f64,
    /// Lead as in [`MoveKind::Tap`] (signed: the spindle turns forward going into the hole).
    pub lead: f64,
    /// Tapping spindle speed (rpm), used when `G30 P99` has no S.
    pub rpm: f64,
    /// Pull-out override in force (%), applied to the return.
    pub override_pct: f64,
    /// The tapping spindle (1–4) of the interrupted tap; state files written before it
    /// existed read as spindle 1.
    #[serde(default = "spindle_one")]
    pub spindle: u8,
}

fn spindle_one() -> u8 {
    1
}

/// The points strictly between `start` and `end` of a ZX-plane arc about `center` (G02 when
/// `cw`), at most 2° apart: for drawing and checking a lathe arc as chords. In (z, x) a G03
/// is counter-clockwise (G18: u = Z, v = X). A full circle (start = end) sweeps 360°.
pub fn zx_arc_chord_points(start: Pos, end: Pos, center: Pos, cw: bool) -> Vec<Pos> {
    let a0 = (start.x - center.x).atan2(start.z - center.z);
    let a1 = (end.x - center.x).atan2(end.z - center.z);
    let r = (start.x - center.x).hypot(start.z - center.z);
    let sweep = wrap_sweep(a1 - a0, cw);
    let n = ((sweep.abs() / 2f64.to_radians()).ceil() as usize).clamp(1, 720);
    (1..n)
        .map(|j| {
            let t = a0 + sweep * j as f64 / n as f64;
            Pos { x: center.x + r * t.sin(), z: center.z + r * t.cos(), ..end }
        })
        .collect()
}
