//! SINUMERIK drilling cycles in Type A programs (manual 003): CYCLE81, CYCLE82, CYCLE83,
//! CYCLE84, CYCLE840, CYCLE85, CYCLE86 called with positional parameters (empty slots and
//! missing trailing parameters are "not given"), and MCALL modal calls.
//!
//! The manual is a tutorial of the 828D input screens and shows one call
//! (`CYCLE81(100,0,1,,25,0.6,0,1,11)`); the parameter lists are the 828D / 840D sl ones:
//!
//! - `CYCLE81/82(RTP, RFP, SDIS, DP, DPR, DTB, _GMODE, _DMODE, _AMODE)`
//! - `CYCLE83(RTP, RFP, SDIS, DP, DPR, FDEP, FDPR, DAM, DTB, DTS, FRF, VARI, _AXN, _MDEP,
//!   _VRT, _DTD, _DIS1, …)`
//! - `CYCLE84(RTP, RFP, SDIS, DP, DPR, DTB, SDAC, MPIT, PIT, POSS, SST, SST1, _AXN, _PTAB,
//!   _TECHNO, _VARI, _DAM, _VRT, …)`
//! - `CYCLE840(RTP, RFP, SDIS, DP, DPR, DTB, SDR, SDAC, ENC, MPIT, PIT, …)`
//! - `CYCLE85(RTP, RFP, SDIS, DP, DPR, DTB, FFR, RFF, …)`
//! - `CYCLE86(RTP, RFP, SDIS, DP, DPR, DTB, SDIR, RPA, RPO, RPAP, POSS, …)`
//!
//! Geometry: the tool axis is Z (the tutorial: face drilling on a lathe is G17 with the tool
//! along Z), the hole is where the tool stands (X/Y/C). RTP, RFP and DP are absolute Z in
//! workpiece coordinates, SDIS and DPR unsigned distances; the hole goes from RFP away from
//! RTP (towards −Z when RTP = RFP). DPR wins over DP when both are given (Siemens). Every
//! cycle starts with a rapid to RFP + SDIS (the safety plane) and ends with a rapid to RTP.
//! Values are always millimetres (inch under G20), seconds, degrees, rpm: the Type A
//! increment rule (No.3401) does not apply inside a cycle call.
//!
//! Depth modes of CYCLE81/82: `_GMODE` = 1 gives the depth as a diameter (in DPR, else
//! DP): depth = Ø/2 / tan(α/2). `_AMODE` units digit 1 = the depth is DPR (incremental),
//! 2 = DP (absolute), 0 = as given; tens digit 2 = shank depth: the tip length r / tan(α/2)
//! is added, r the active tool's radius from the tool table. α is the drill point angle:
//! 90° for CYCLE81 (centre drill), 118° for CYCLE82 (twist drill), as the tutorial says.
//!
//! MCALL: `MCALL CYCLE8x(…)` checks the parameters, drills nothing in its own block and runs
//! the cycle after every following block that moves an axis, until a bare `MCALL`.
//!
//! Alarms: the SINUMERIK cycle alarm numbers: 61001 thread pitch wrong (none, or MPIT and
//! PIT disagree), 61002 type of machining wrong (VARI, ENC), 61003 no feed / speed in the
//! cycle, 61101 reference plane wrong (no depth, depth on the RTP side of RFP), 61102 no
//! spindle direction (SDIR/SDAC/SDR not 3/4/5), 61107 first drilling depth wrong; 12340
//! too many parameters; our 2510 for FRF outside 0.001–1 and a missing DAM; Fanuc 10 for a
//! cycle this control does not have.

use super::{CErr, RANGE_ALARM};
use crate::canon::{Feed, MoveKind, Pos, SpindleCmd, SpindleDir, SrcPos};
use crate::interp::Interpreter;
use std::sync::Arc;

pub const PITCH_ALARM: u32 = 61001;
pub const MACHINING_ALARM: u32 = 61002;
pub const FEED_ALARM: u32 = 61003;
pub const PLANE_ALARM: u32 = 61101;
pub const SPINDLE_DIR_ALARM: u32 = 61102;
pub const FIRST_DEPTH_ALARM: u32 = 61107;
pub const TOO_MANY_ALARM: u32 = 12340;

/// A stored cycle call (MCALL).
#[derive(Clone, Debug, PartialEq)]
pub struct SiemensCall {
    pub name: String,
    pub args: Vec<Option<f64>>,
}

/// ISO metric coarse threads: nominal size → pitch (MPIT 3–48).
pub const METRIC_COARSE: [(u32, f64); 21] = [
    (3, 0.5),
    (4, 0.7),
    (5, 0.8),
    (6, 1.0),
    (8, 1.25),
    (10, 1.5),
    (12, 1.75),
    (14, 2.0),
    (16, 2.0),
    (18, 2.5),
    (20, 2.5),
    (22, 2.5),
    (24, 3.0),
    (27, 3.0),
    (30, 3.5),
    (33, 3.5),
    (36, 4.0),
    (39, 4.0),
    (42, 4.5),
    (45, 4.5),
    (48, 5.0),
];

/// Parameter counts of the known cycles (the 828D SW4 lists above, with their tails).
fn max_args(name: &str) -> Option<usize> {
    Some(match name {
        "CYCLE81" | "CYCLE82" => 9,
        "CYCLE83" => 20,
        "CYCLE84" => 25,
        "CYCLE840" => 17,
        "CYCLE85" => 11,
        "CYCLE86" => 14,
        _ => return None,
    })
}

/// The checks of a call that need no values (pass 1, before the program runs): a known
/// cycle and not too many parameters. Returns (alarm, column, message).
pub fn static_check(name: &str, nargs: usize, cols: &[u32]) -> Option<(u32, Option<u32>, String)> {
    let Some(max) = max_args(name) else {
        return Some((10, None, format!("{name} is not a cycle of this control (CYCLE81–86, CYCLE840)")));
    };
    (nargs > max).then(|| (TOO_MANY_ALARM, cols.get(max).copied(), format!("{name} takes at most {max} parameters, {nargs} given")))
}

/// Z levels of one cycle in machine coordinates, and the direction into the hole.
#[derive(Clone, Copy, Debug)]
struct Geo {
    rtp: f64,
    safe: f64,
    rfp: f64,
    depth: f64,
    dir: f64,
}

impl Interpreter {
    /// A cycle call statement: `CYCLE8x(…)`, `MCALL CYCLE8x(…)` or a bare `MCALL`.
    /// `cols`: the column of each parameter, for the alarms of this block.
    pub(in crate::interp) fn siemens_stmt(
        &mut self,
        mcall: bool,
        name: Option<&str>,
        args: &[Option<f64>],
        cols: &[u32],
        src: &SrcPos,
    ) -> Result<(), CErr> {
        let Some(name) = name else {
            self.drill.mcall = None;
            return Ok(());
        };
        if let Some(e) = static_check(name, args.len(), cols) {
            return Err(e);
        }
        self.drill.call_cols = cols.to_vec();
        if let Some(bad) = args.iter().flatten().find(|v| !v.is_finite()) {
            return Err((RANGE_ALARM, None, format!("{name}: parameter value {bad} is not a number")));
        }
        let call = SiemensCall { name: name.to_string(), args: args.to_vec() };
        if mcall {
            // Check everything that does not depend on the position now, at the call.
            let here = self.pos;
            let saved = (self.queue.len(), self.st.dir, self.st.rpm);
            self.run_siemens(&call, src)?;
            self.queue.truncate(saved.0);
            self.pos = here;
            self.st.dir = saved.1;
            self.st.rpm = saved.2;
            self.drill.mcall = Some(call);
            self.drill.call_cols.clear();
            return Ok(());
        }
        let r = self.run_siemens(&call, src);
        self.drill.call_cols.clear();
        r
    }

    /// Column of parameter `i` of the call being executed (None for an MCALL run in a later
    /// block: the alarm then points at that block).
    fn pc(&self, i: usize) -> Option<u32> {
        self.drill.call_cols.get(i).copied()
    }

    /// After a block that moved an axis: the modal call, if any.
    pub(in crate::interp) fn mcall_after(&mut self, moved: bool, src: &SrcPos) -> Result<(), CErr> {
        if !moved {
            return Ok(());
        }
        match self.drill.mcall.clone() {
            Some(c) => self.run_siemens(&c, src),
            None => Ok(()),
        }
    }

    fn sarg(a: &[Option<f64>], i: usize) -> Option<f64> {
        a.get(i).copied().flatten()
    }

    fn unit(&self) -> f64 {
        if self.st.inch {
            25.4
        } else {
            1.0
        }
    }

    /// RTP, RFP, SDIS and the depth (DP absolute or DPR relative, `depth` overriding both).
    fn geo(&self, a: &[Option<f64>], depth: Option<f64>) -> Result<Geo, CErr> {
        let u = self.unit();
        let oz = self.offset().z;
        let rtp = Self::sarg(a, 0).unwrap_or(0.0) * u + oz;
        let rfp = Self::sarg(a, 1).unwrap_or(0.0) * u + oz;
        let sdis = Self::sarg(a, 2).unwrap_or(0.0).abs() * u;
        let dir = if rtp != rfp { -(rtp - rfp).signum() } else { -1.0 };
        let depth = match (depth, Self::sarg(a, 4), Self::sarg(a, 3)) {
            (Some(d), _, _) => rfp + dir * d.abs() * u,
            (None, Some(dpr), _) => rfp + dir * dpr.abs() * u,
            (None, None, Some(dp)) => dp * u + oz,
            _ => return Err((PLANE_ALARM, self.pc(3), "no final drilling depth: give DP (absolute) or DPR (relative to RFP)".into())),
        };
        if (depth - rfp) * dir <= 0.0 {
            let col = if Self::sarg(a, 4).is_some() { self.pc(4) } else { self.pc(3) };
            return Err((
                PLANE_ALARM,
                col,
                format!(
                    "the final depth Z{:.3} is not beyond the reference plane Z{:.3} seen from the retract plane Z{:.3}",
                    depth - oz,
                    rfp - oz,
                    rtp - oz
                ),
            ));
        }
        Ok(Geo { rtp, safe: rfp - dir * sdis, rfp, depth, dir })
    }

    fn zpos(&self, z: f64) -> Pos {
        Pos { z, ..self.pos }
    }

    fn sfeed(&self) -> Result<Feed, CErr> {
        self.feed(None).map_err(|(_, c, m)| (FEED_ALARM, c, m))
    }

    fn feed_value(&self, v: f64) -> Feed {
        let v = v.abs() * self.unit();
        if self.st.per_rev {
            Feed::PerRev(v)
        } else {
            Feed::PerMin(v)
        }
    }

    /// The pitch from MPIT (metric coarse size) and/or PIT; negative = left hand.
    fn pitch(&self, a: &[Option<f64>], mpit_i: usize, pit_i: usize, unit: f64) -> Result<Option<f64>, CErr> {
        let table = match Self::sarg(a, mpit_i).filter(|v| *v != 0.0) {
            None => None,
            Some(m) => {
                let p = METRIC_COARSE.iter().find(|(size, _)| *size as f64 == m.abs()).map(|(_, p)| *p).ok_or((
                    PITCH_ALARM,
                    self.pc(mpit_i),
                    format!("MPIT {m}: not a metric coarse thread size (3–48: M3, M4, M5, M6, M8, M10 … M48)"),
                ))?;
                Some(p.copysign(m))
            }
        };
        let pit = Self::sarg(a, pit_i).filter(|v| *v != 0.0).map(|p| p * unit);
        match (table, pit) {
            (Some(t), Some(p)) if (t - p).abs() > 1e-9 => {
                Err((PITCH_ALARM, self.pc(pit_i), format!("MPIT gives pitch {t} mm but PIT is {p} mm: give one of them")))
            }
            (Some(t), _) => Ok(Some(t)),
            (None, p) => Ok(p),
        }
    }

    fn spindle_dir(code: f64, what: &str, allow_stop: bool, col: Option<u32>) -> Result<SpindleDir, CErr> {
        if code == 3.0 {
            Ok(SpindleDir::Cw)
        } else if code == 4.0 {
            Ok(SpindleDir::Ccw)
        } else if code == 5.0 && allow_stop {
            Ok(SpindleDir::Stop)
        } else {
            Err((
                SPINDLE_DIR_ALARM,
                col,
                format!("{what} {code}: the spindle direction is 3 (M3) or 4 (M4){}", if allow_stop { " or 5 (M5)" } else { "" }),
            ))
        }
    }

    fn spin(&mut self, src: &SrcPos, tag: &Arc<str>, step: u8, dir: SpindleDir) {
        self.st.dir = dir;
        let c = SpindleCmd { dir, rpm: self.st.rpm, css: None, max_rpm: self.st.max_rpm };
        self.cpush(src, tag, step, MoveKind::Spindle(c), false);
    }

    fn run_siemens(&mut self, call: &SiemensCall, src: &SrcPos) -> Result<(), CErr> {
        let a = &call.args[..];
        let tag: Arc<str> = Arc::from(call.name.as_str());
        let arg = |i| Self::sarg(a, i);
        let dtb = arg(5).unwrap_or(0.0).max(0.0);
        match call.name.as_str() {
            "CYCLE81" | "CYCLE82" => {
                let alpha: f64 = if call.name == "CYCLE81" { 90.0 } else { 118.0 };
                let half = (alpha / 2.0).to_radians().tan();
                let amode = arg(8).unwrap_or(0.0).abs() as u32;
                let mut depth = None;
                if arg(6) == Some(1.0) {
                    let dia = arg(4).or(arg(3)).ok_or((PLANE_ALARM, self.pc(6), format!("{}: diameter mode needs the diameter (DPR)", call.name)))?;
                    depth = Some(dia.abs() / 2.0 / half);
                }
                let mut a2 = a.to_vec();
                match amode % 10 {
                    1 if depth.is_none() => {
                        a2.resize(5, None);
                        a2[3] = None;
                    }
                    2 if depth.is_none() => {
                        a2.resize(5, None);
                        a2[4] = None;
                    }
                    _ => {}
                }
                let mut g = self.geo(&a2, depth)?;
                if (amode / 10) % 10 == 2 {
                    // Shank depth: the tip is deeper by r / tan(α/2).
                    g.depth += g.dir * self.tool.nose_radius.abs() / half;
                }
                let feed = self.sfeed()?;
                self.cpush(src, &tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
                self.cpush(src, &tag, 3, MoveKind::Feed { end: self.zpos(g.depth), feed }, true);
                self.dwell_s(src, &tag, 4, dtb);
                self.cpush(src, &tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
            }
            "CYCLE85" => {
                let g = self.geo(a, None)?;
                let ffr = arg(6).filter(|v| *v != 0.0).ok_or((FEED_ALARM, self.pc(6), "CYCLE85: no feed in (FFR)".to_string()))?;
                let rff = arg(7).filter(|v| *v != 0.0).ok_or((FEED_ALARM, self.pc(7), "CYCLE85: no feed out (RFF)".to_string()))?;
                let (fin, fout) = (self.feed_value(ffr), self.feed_value(rff));
                self.cpush(src, &tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
                self.cpush(src, &tag, 3, MoveKind::Feed { end: self.zpos(g.depth), feed: fin }, true);
                self.dwell_s(src, &tag, 4, dtb);
                self.cpush(src, &tag, 5, MoveKind::Feed { end: self.zpos(g.safe), feed: fout }, true);
                self.cpush(src, &tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
            }
            "CYCLE86" => {
                self.work_spindle_drilling("CYCLE86 stops the boring tool oriented at POSS")?;
                let g = self.geo(a, None)?;
                let sdir = Self::spindle_dir(arg(6).unwrap_or(0.0), "SDIR", false, self.pc(6))?;
                let u = self.unit();
                let (rpa, rpo, rpap) = (arg(7).unwrap_or(0.0) * u, arg(8).unwrap_or(0.0) * u, arg(9).unwrap_or(0.0) * u);
                if rpo != 0.0 && !self.has_y {
                    return Err((21, self.pc(8), "CYCLE86 RPO retracts along Y, which this machine lacks".into()));
                }
                let poss = arg(10).unwrap_or(0.0);
                let feed = self.sfeed()?;
                if self.st.rpm <= 0.0 {
                    return Err((FEED_ALARM, None, "CYCLE86 needs a spindle speed: program S before the cycle".into()));
                }
                self.cpush(src, &tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
                self.spin(src, &tag, 3, sdir);
                self.cpush(src, &tag, 3, MoveKind::Feed { end: self.zpos(g.depth), feed }, true);
                self.dwell_s(src, &tag, 4, dtb);
                // SPOS: stop the spindle oriented at POSS (the spindle as a Cs axis).
                self.st.dir = SpindleDir::Stop;
                let stop = SpindleCmd { dir: SpindleDir::Stop, rpm: self.st.rpm, css: None, max_rpm: self.st.max_rpm };
                self.cpush(src, &tag, 4, MoveKind::Spindle(stop), false);
                let c = super::rigid::forward_angle(self.pos.c, poss + self.offset().c, 1.0);
                self.cpush(src, &tag, 4, MoveKind::Rapid { end: Pos { c, ..self.pos } }, true);
                let off = Pos { x: rpa, y: rpo, z: rpap, c: 0.0 };
                self.cpush(src, &tag, 5, MoveKind::Rapid { end: self.pos.add(off) }, true);
                self.cpush(src, &tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
                self.cpush(src, &tag, 6, MoveKind::Rapid { end: Pos { x: self.pos.x - rpa, y: self.pos.y - rpo, ..self.pos } }, true);
                self.spin(src, &tag, 6, sdir);
            }
            "CYCLE83" => self.cycle83(a, src, &tag)?,
            "CYCLE84" => self.cycle84(a, src, &tag)?,
            "CYCLE840" => self.cycle840(a, src, &tag)?,
            n => return Err((10, None, format!("{n} is not a cycle of this control"))),
        }
        Ok(())
    }

    fn dwell_s(&mut self, src: &SrcPos, tag: &Arc<str>, step: u8, s: f64) {
        if s > 0.0 {
            self.cpush(src, tag, step, MoveKind::Dwell { seconds: s }, true);
        }
    }

    /// Depth amounts of the stages: the first, then less by DAM each time (DAM > 0, not
    /// below DAM), a percentage of the last (DAM < 0, not below _MDEP), or the first again
    /// (DAM = 0); the last stage ends at the final depth.
    fn stages(first: f64, total: f64, dam: f64, mdep: f64) -> Result<Vec<f64>, CErr> {
        let mut out = Vec::new();
        let mut done = 0.0;
        let mut amount = first;
        while done < total - 1e-9 {
            if amount <= 1e-6 {
                return Err((RANGE_ALARM, None, "the drilling depth per stage is zero: check DAM / _MDEP".into()));
            }
            done = (done + amount).min(total);
            out.push(done);
            if out.len() > super::drill::MAX_PECKS as usize {
                return Err((RANGE_ALARM, None, "more than 10000 drilling stages: increase the depths".into()));
            }
            amount = if dam > 0.0 {
                (amount - dam).max(dam)
            } else if dam < 0.0 {
                (amount * -dam / 100.0).max(mdep.max(0.001))
            } else {
                first
            };
        }
        Ok(out)
    }

    /// CYCLE83 deep-hole drilling. Chip breaking (VARI 0): ③ feed to each stage, DTB, rapid
    /// back _VRT (V2; 0 = 1 mm). Chip removal (VARI 1): ③ feed to each stage, DTB, rapid out
    /// to the safety plane, DTS, rapid back to _DIS1 (V3; 0 = the automatic 1 mm) short of
    /// the last depth. The first stage (FDPR relative / FDEP absolute, else the whole depth)
    /// at F × FRF; then ④ _DTD (0 = DTB) at the final depth and ⑥ rapid to RTP.
    fn cycle83(&mut self, a: &[Option<f64>], src: &SrcPos, tag: &Arc<str>) -> Result<(), CErr> {
        let g = self.geo(a, None)?;
        let arg = |i| Self::sarg(a, i);
        let u = self.unit();
        let oz = self.offset().z;
        let total = (g.depth - g.rfp).abs();
        let first = match (arg(6).filter(|v| *v != 0.0), arg(5)) {
            (Some(r), _) => {
                if r < 0.0 {
                    return Err((FIRST_DEPTH_ALARM, self.pc(6), format!("FDPR {r}: the first depth relative to RFP is unsigned")));
                }
                r * u
            }
            (None, Some(f)) => {
                let d = (f * u + oz - g.rfp) * g.dir;
                if d <= 0.0 {
                    return Err((FIRST_DEPTH_ALARM, self.pc(5), format!("FDEP {f}: the first drilling depth is not beyond the reference plane")));
                }
                d
            }
            (None, None) => total,
        };
        let first = first.min(total);
        let vari = arg(11).unwrap_or(0.0);
        if vari != 0.0 && vari != 1.0 {
            return Err((MACHINING_ALARM, self.pc(11), format!("VARI {vari}: 0 = chip breaking, 1 = chip removal")));
        }
        // FRF empty or 0 = 1 (full feed).
        let frf = arg(10).filter(|v| *v != 0.0).unwrap_or(1.0);
        if !(0.001..=1.0).contains(&frf) {
            return Err((RANGE_ALARM, self.pc(10), format!("FRF {frf}: the first-depth feed factor is 0.001–1")));
        }
        let dam = arg(7).unwrap_or(0.0) * if arg(7).unwrap_or(0.0) > 0.0 { u } else { 1.0 };
        let mdep = arg(13).unwrap_or(0.0).abs() * u;
        let dtb = arg(8).unwrap_or(0.0).max(0.0);
        let dts = arg(9).unwrap_or(0.0).max(0.0);
        let dtd = arg(15).filter(|v| *v > 0.0).unwrap_or(dtb);
        let vrt = arg(14).filter(|v| *v > 0.0).map(|v| v * u).unwrap_or(1.0);
        let dis1 = arg(16).filter(|v| *v > 0.0).map(|v| v * u).unwrap_or(1.0);
        let feed = self.sfeed()?;
        let first_feed = match feed {
            Feed::PerMin(f) => Feed::PerMin(f * frf),
            Feed::PerRev(f) => Feed::PerRev(f * frf),
        };
        let stages = Self::stages(first, total, dam, mdep)?;
        self.cpush(src, tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
        let at = |d: f64| g.rfp + g.dir * d;
        let n = stages.len();
        for (k, d) in stages.iter().enumerate() {
            if k > 0 {
                let last = stages[k - 1];
                if vari == 0.0 {
                    self.cpush(src, tag, 3, MoveKind::Rapid { end: self.zpos(at((last - vrt).max(0.0))) }, true);
                } else {
                    self.cpush(src, tag, 3, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
                    self.dwell_s(src, tag, 3, dts);
                    self.cpush(src, tag, 3, MoveKind::Rapid { end: self.zpos(at((last - dis1).max(0.0))) }, true);
                }
            }
            let f = if k == 0 { first_feed } else { feed };
            self.cpush(src, tag, 3, MoveKind::Feed { end: self.zpos(at(*d)), feed: f }, true);
            if k + 1 < n {
                self.dwell_s(src, tag, 3, dtb);
            }
        }
        self.dwell_s(src, tag, 4, dtd);
        self.cpush(src, tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
        Ok(())
    }

    /// The spindle CYCLE84 taps with, that CYCLE84/CYCLE86 orient at POSS and that CYCLE840/
    /// CYCLE86 start and stop is the one that
    /// turns the tool (SINUMERIK's master spindle): on a machine whose drilling tool is a
    /// driven tool (machine.drilling_spindle = "tool") that is the tool spindle, which this
    /// controller neither taps with nor orients; turning the work spindle (C) instead would
    /// turn the part under a driven tool, so such a cycle is refused before anything moves.
    fn work_spindle_drilling(&self, what: &str) -> Result<(), CErr> {
        if self.driven_tool_drilling {
            return Err((
                10,
                None,
                format!("{what} with the spindle that turns the tool, here the tool spindle (machine.drilling_spindle = \"tool\"): this controller turns, taps with and orients the work spindle only: here use a cycle that does not command a spindle (CYCLE81–CYCLE83, CYCLE85), or set drilling_spindle = \"work\" if the work spindle turns the tool"),
            ));
        }
        Ok(())
    }

    /// CYCLE84 rigid tapping: ② rapid to the safety plane and, with POSS, the spindle
    /// oriented there (aS); ③ tap to the depth at SST ([`MoveKind::Tap`], lead PIT or MPIT,
    /// negative = left hand) in one cut (_VARI 0), with chip breaking (1: stages of _DAM,
    /// back _VRT, 0 = 1 mm, at SST1) or chip removal (2: stages of _DAM, out to the safety
    /// plane at SST1 and back in at SST); ④ DTB; ⑤ tap out to the safety plane at SST1
    /// (0 = SST); ⑥ rapid to RTP and the spindle as SDAC says (3/4/5, at the modal S).
    fn cycle84(&mut self, a: &[Option<f64>], src: &SrcPos, tag: &Arc<str>) -> Result<(), CErr> {
        self.work_spindle_drilling("CYCLE84 taps (and orients the spindle at POSS)")?;
        let g = self.geo(a, None)?;
        let arg = |i| Self::sarg(a, i);
        let u = self.unit();
        let pitch =
            self.pitch(a, 7, 8, u)?.ok_or((PITCH_ALARM, self.pc(8).or(self.pc(7)), "CYCLE84: no thread pitch: give PIT or MPIT".to_string()))?;
        let sdac = arg(6).map(|v| Self::spindle_dir(v, "SDAC", true, self.pc(6))).transpose()?;
        let sst = arg(10).filter(|v| *v > 0.0).ok_or((FEED_ALARM, self.pc(10), "CYCLE84: no tapping speed SST".to_string()))?;
        let sst1 = arg(11).filter(|v| *v > 0.0).unwrap_or(sst);
        let vari = arg(15).unwrap_or(0.0);
        if ![0.0, 1.0, 2.0].contains(&vari) {
            return Err((MACHINING_ALARM, self.pc(15), format!("_VARI {vari}: 0 one cut, 1 chip breaking, 2 chip removal")));
        }
        let lead = g.dir * pitch.abs() * pitch.signum();
        let total = (g.depth - g.rfp).abs();
        let stages = if vari == 0.0 {
            vec![total]
        } else {
            let dam = arg(16).filter(|v| *v > 0.0).ok_or((
                RANGE_ALARM,
                self.pc(16).or(self.pc(15)),
                "CYCLE84 chip breaking / removal needs the depth per cut _DAM (D)".to_string(),
            ))?;
            Self::stages(dam * u, total, 0.0, 0.0)?
        };
        let vrt = arg(17).filter(|v| *v > 0.0).map(|v| v * u).unwrap_or(1.0);
        let at = |d: f64| g.rfp + g.dir * d;
        self.cpush(src, tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
        if let Some(poss) = arg(9) {
            self.st.dir = SpindleDir::Stop;
            let c = super::rigid::forward_angle(self.pos.c, poss + self.offset().c, 1.0);
            self.cpush(src, tag, 2, MoveKind::Rapid { end: Pos { c, ..self.pos } }, true);
        }
        let tap = |z: f64, rpm: f64, p: Pos| MoveKind::Tap { end: Pos { z, ..p }, lead, rpm, spindle: 1 };
        for (k, d) in stages.iter().enumerate() {
            if k > 0 {
                let last = stages[k - 1];
                if vari == 1.0 {
                    self.cpush(src, tag, 3, tap(at((last - vrt).max(0.0)), sst1, self.pos), true);
                } else {
                    self.cpush(src, tag, 3, tap(g.safe, sst1, self.pos), true);
                    self.cpush(src, tag, 3, tap(at(last), sst, self.pos), true);
                }
            }
            self.cpush(src, tag, 3, tap(at(*d), sst, self.pos), true);
        }
        self.drill.last_tap =
            Some(crate::canon::TapReturn { axis: 'Z', r_plane: g.safe, lead, rpm: sst, override_pct: sst1 / sst * 100.0, spindle: 1 });
        self.dwell_s(src, tag, 4, arg(5).unwrap_or(0.0).max(0.0));
        self.cpush(src, tag, 5, tap(g.safe, sst1, self.pos), true);
        self.cpush(src, tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
        if let Some(dir) = sdac {
            self.spin(src, tag, 6, dir);
        }
        Ok(())
    }

    /// CYCLE840 tapping with a compensating chuck: ② rapid to the safety plane, ③ spindle
    /// SDAC and feed to the depth, ④ DTB, ⑤ spindle SDR (0 = reversed automatically) and
    /// feed back to the safety plane, the spindle SDAC again, ⑥ rapid to RTP. With encoder
    /// (ENC 0): the feed is one pitch (MPIT/PIT) per revolution, following the encoder.
    /// Without (ENC 1): the pitch given, or else the feed in force before the cycle.
    fn cycle840(&mut self, a: &[Option<f64>], src: &SrcPos, tag: &Arc<str>) -> Result<(), CErr> {
        self.work_spindle_drilling("CYCLE840 turns the spindle (SDAC, SDR)")?;
        let g = self.geo(a, None)?;
        let arg = |i| Self::sarg(a, i);
        let u = self.unit();
        let sdac = Self::spindle_dir(arg(7).unwrap_or(0.0), "SDAC", false, self.pc(7))?;
        let sdr_code = arg(6).unwrap_or(0.0);
        let sdr = if sdr_code == 0.0 {
            if sdac == SpindleDir::Cw {
                SpindleDir::Ccw
            } else {
                SpindleDir::Cw
            }
        } else {
            Self::spindle_dir(sdr_code, "SDR", false, self.pc(6))?
        };
        let enc = arg(8).unwrap_or(0.0);
        if ![0.0, 1.0, 10.0, 11.0].contains(&enc) {
            return Err((MACHINING_ALARM, self.pc(8), format!("ENC {enc}: 0 with encoder, 1 without (10/11 the same without dwell check)")));
        }
        let pitch = self.pitch(a, 9, 10, u)?;
        let feed = match (enc as u32 % 10, pitch) {
            (0, None) => return Err((PITCH_ALARM, self.pc(10).or(self.pc(9)), "CYCLE840 with encoder needs the pitch: give PIT or MPIT".into())),
            (_, Some(p)) => Feed::PerRev(p.abs()),
            (_, None) => self.sfeed()?,
        };
        if self.st.rpm <= 0.0 {
            return Err((FEED_ALARM, None, "CYCLE840 needs a spindle speed: program S before the cycle".into()));
        }
        self.cpush(src, tag, 2, MoveKind::Rapid { end: self.zpos(g.safe) }, true);
        if self.st.dir != sdac {
            self.spin(src, tag, 3, sdac);
        }
        self.cpush(src, tag, 3, MoveKind::Feed { end: self.zpos(g.depth), feed }, true);
        self.dwell_s(src, tag, 4, arg(5).unwrap_or(0.0).max(0.0));
        self.spin(src, tag, 5, sdr);
        self.cpush(src, tag, 5, MoveKind::Feed { end: self.zpos(g.safe), feed }, true);
        self.spin(src, tag, 5, sdac);
        self.cpush(src, tag, 6, MoveKind::Rapid { end: self.zpos(g.rtp) }, true);
        Ok(())
    }
}
