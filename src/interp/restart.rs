//! Program restart (issue 24.4): run the program from its start up to a block *without
//! motion*, so that the interpreter stands at that block with the modal state the program
//! gives it there — G codes, F, S, T and its offset, work offsets, G50/G52 shifts, macro
//! variables — and the position the tool would have. The manual has no restart; this is a
//! Fanuc 0i-TF "P-type" restart (search by block, the modal state of the blocks before it
//! rebuilt), with the restart block given by its line or by its sequence number (the first
//! time the main program reaches it, as Fanuc searches).
//!
//! Refused, with the reason (alarm [`RESTART_ALARM`]): a block the program never reaches
//! from its start (inside the finishing contour of a G70–G73 cycle, whose strokes that
//! cycle's block makes; jumped over; after M30), a block that continues a thread (the cut
//! before it ended on a thread move: the spindle phase cannot be picked up), and a block
//! with tool nose radius compensation (G41/G42) or G12.1 polar interpolation in force (the
//! compensated path before it is not known without the blocks after it).

use super::{Interpreter, Loc};
use crate::canon::{Move, MoveKind, Pos};
use crate::Alarm;

/// Alarm: the program cannot be restarted at that block.
pub const RESTART_ALARM: u32 = crate::alarm::RESTART;

/// Where to restart.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RestartAt {
    /// Source line (1-based) of the main program.
    Line(u32),
    /// The first block of the main program with this sequence number (N word).
    Seq(u32),
}

/// What the scan left: where the restart block is and what the machine must be given
/// before it runs (the moves the scan withheld that set machine state).
#[derive(Clone, Debug)]
pub struct RestartScan {
    /// The restart block's program file, line (1-based) and text.
    pub file: std::sync::Arc<str>,
    pub line: u32,
    pub text: String,
    /// Where the tool is at the restart block (machine coordinates, X as a radius).
    pub pos: Pos,
    /// The work offset in force there (machine = work + offset).
    pub work_offset: Pos,
    /// The last spindle command of the scan (M03/M04/M05, S, G96/G97), if any.
    pub spindle: Option<Move>,
    /// The last G22/G23 of the scan (the stored stroke check in force), if any.
    pub stroke: Option<Move>,
    /// The last T code passed on (turret index), if any.
    pub tool: Option<Move>,
    /// Blocks executed and moves withheld by the scan.
    pub blocks: u64,
    pub moves_skipped: u64,
}

impl Interpreter {
    /// Execute the program from where it stands up to the restart block, withholding every
    /// move (see the module doc). On success the interpreter's next move is the restart
    /// block's first.
    pub fn scan_to(&mut self, at: RestartAt) -> Result<RestartScan, Alarm> {
        let what = match at {
            RestartAt::Line(l) => format!("line {l}"),
            RestartAt::Seq(n) => format!("N{n}"),
        };
        let refuse = |m: String| Alarm::new(RESTART_ALARM, format!("cannot restart at {what}: {m}; nothing was moved"));
        let mut scan = RestartScan {
            file: self.sources[self.progs[0].src].file.clone(),
            line: 0,
            text: String::new(),
            pos: self.pos,
            work_offset: self.offset(),
            spindle: None,
            stroke: None,
            tool: None,
            blocks: 0,
            moves_skipped: 0,
        };
        let mut last_motion: Option<Move> = None;
        // The first block that carried execution past the restart line (a jump, a cycle that
        // skips its contour), for the reason if the line is never reached.
        let mut jumped_by: Option<(u32, String)> = None;
        loop {
            let main = self.stack.is_empty() && self.prog == 0;
            if main && !self.ended {
                let next = self.line;
                let text = self.line_text(next);
                let hit = match at {
                    RestartAt::Line(l) => next.line + 1 == l,
                    RestartAt::Seq(n) => seq_number(&text) == Some(n),
                };
                if hit {
                    scan.line = next.line + 1;
                    scan.text = text.trim_end().to_string();
                    break;
                }
            }
            if self.ended {
                let m = match (jumped_by, at) {
                    (Some((l, t)), _) if is_stock_cycle(&t) => format!(
                        "it is inside the finishing contour of the cycle at line {l} ({}): that block makes its strokes; restart at line {l} or after the contour",
                        t.trim()
                    ),
                    (Some((l, t)), _) => format!("the program jumps over it at line {l} ({}) and never executes it", t.trim()),
                    (None, RestartAt::Line(l)) if l == 0 || self.progs[0].end.line < l => "the main program has no such line".to_string(),
                    (None, RestartAt::Seq(_)) => "no block of the main program with that sequence number is executed from the start".to_string(),
                    (None, _) => "the program never executes it from its start (after M02/M30, or a subprogram's line)".to_string(),
                };
                return Err(refuse(m));
            }
            let before: Loc = self.line;
            let was_main = main;
            self.blocks_run += 1;
            scan.blocks += 1;
            // The scan has no moves to end an endless loop: the run's block budget bounds it.
            let budget = if self.block_budget > 0 { self.block_budget } else { super::DEFAULT_BLOCK_BUDGET };
            if scan.blocks > budget {
                return Err(refuse(format!("the scan ran {budget} blocks without reaching it (an endless loop before it?)")));
            }
            self.step()?;
            if let (true, RestartAt::Line(l)) = (was_main && self.stack.is_empty() && self.prog == 0, at) {
                // A block that carried the next line from before the restart line to past it
                // without executing it.
                if before.line + 1 < l && self.line.line + 1 > l && before.line + 1 != self.line.line && jumped_by.is_none() {
                    let (si, loc) = self.cur;
                    jumped_by = Some((loc.line + 1, self.sources[si].line_at(loc).0));
                }
            }
            // Withhold what the block made, through the same checks the moves pass in a run
            // (G22, nose radius compensation), remembering what sets machine state.
            while let Some(m) = self.queue.pop_front() {
                let mut out = Vec::new();
                self.cyc.stroke.check(&m).and_then(|_| self.nrc.feed(m, &mut out))?;
                self.nrc_out.extend(out);
            }
            for m in self.nrc_out.drain(..) {
                scan.moves_skipped += 1;
                match &m.kind {
                    MoveKind::Spindle(_) => scan.spindle = Some(m),
                    MoveKind::StrokeCheck { .. } => scan.stroke = Some(m),
                    MoveKind::Aux { letter: 'T', .. } => scan.tool = Some(m),
                    k if k.end().is_some() => last_motion = Some(m),
                    _ => {}
                }
            }
        }
        if self.nrc.active() {
            return Err(refuse(
                "tool nose radius compensation (G41/G42) is in force there; restart at a block before the G41/G42 or after G40".into(),
            ));
        }
        if self.polar.is_some() {
            return Err(refuse("G12.1 polar coordinate interpolation is in force there; restart at a block before the G12.1 or after G13.1".into()));
        }
        if let Some(m) = last_motion.as_ref().filter(|m| matches!(m.kind, MoveKind::Thread { .. } | MoveKind::RigidThread { .. })) {
            return Err(refuse(format!(
                "the block before it ends in a thread (line {}): a thread cannot be picked up in its middle; restart at the block that positions for the thread's first pass",
                m.src.line
            )));
        }
        scan.pos = self.pos;
        scan.work_offset = self.offset();
        Ok(scan)
    }
}

/// The sequence number a block starts with (`N120 G01 …`, `/N120 …`).
fn seq_number(text: &str) -> Option<u32> {
    let t = text.trim_start();
    let t = t.strip_prefix('/').unwrap_or(t).trim_start();
    let t = t.strip_prefix(['N', 'n'])?;
    let digits: String = t.chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

/// A G70–G73 block (its P–Q contour is made by the block itself).
fn is_stock_cycle(text: &str) -> bool {
    let u = text.to_ascii_uppercase();
    let mut rest = u.as_str();
    while let Some(i) = rest.find('G') {
        rest = &rest[i + 1..];
        let n: String = rest.chars().take_while(|c| c.is_ascii_digit() || *c == '.').collect();
        if matches!(n.as_str(), "70" | "71" | "72" | "73") {
            return true;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{MachineConfig, EMBEDDED_LATHE};

    fn interp(text: &str) -> Interpreter {
        let cfg = MachineConfig::from_toml("m.toml", EMBEDDED_LATHE).unwrap();
        Interpreter::from_source("p.nc", text, &cfg).unwrap()
    }

    fn rest(mut it: Interpreter) -> Vec<Move> {
        it.by_ref().map(|m| m.unwrap()).collect()
    }

    #[test]
    fn the_scan_moves_nothing_and_the_rest_is_the_programs_tail() {
        let prog = "G21 G98\nG0 X40 Z2 M3 S800\nG1 Z-10 F200\n#100=5\nG0 X50\nN60 G1 U-[#100*2]\nZ-20\nM30\n";
        let full = rest(interp(prog));
        let mut it = interp(prog);
        let scan = it.scan_to(RestartAt::Seq(60)).unwrap();
        assert_eq!((scan.line, scan.text.as_str()), (6, "N60 G1 U-[#100*2]"));
        assert_eq!((scan.pos.x, scan.pos.z), (25.0, -10.0), "X50 (diameter) Z-10");
        assert!(matches!(scan.spindle.as_ref().map(|m| &m.kind), Some(MoveKind::Spindle(s)) if s.rpm == 800.0));
        let tail = rest(it);
        // The same moves as the program's from that block on: modal G01, F200 and #100 kept.
        let from = full.iter().position(|m| m.src.line == 6).unwrap();
        assert_eq!(tail, full[from..].to_vec());
        assert!(matches!(tail[0].kind, MoveKind::Feed { end, .. } if end.x == 20.0));
    }

    #[test]
    fn refusals_say_why() {
        let thread = "G21 G97 S500 M3\nG0 X30 Z5\nG32 Z-10 F1.5\nZ-20\nG0 X40\nM30\n";
        let e = interp(thread).scan_to(RestartAt::Line(4)).unwrap_err();
        assert!(e.number == RESTART_ALARM && e.message.contains("thread (line 3)"), "{e}");
        assert!(interp(thread).scan_to(RestartAt::Line(5)).is_err(), "the retract after the thread too");
        assert!(interp(thread).scan_to(RestartAt::Line(2)).is_ok());
        let g71 = "G21 G98 M3 S500\nG0 X50 Z2\nG71 U1 R0.5\nG71 P10 Q20 U0.2 W0.1 F200\nN10 G0 X20\nG1 Z-10\nN20 X50\nG0 X60 Z5\nM30\n";
        let e = interp(g71).scan_to(RestartAt::Line(6)).unwrap_err();
        assert!(e.message.contains("finishing contour of the cycle at line 4"), "{e}");
        assert!(interp(g71).scan_to(RestartAt::Line(8)).is_ok());
        let e = interp("G0 X10\nM30\n").scan_to(RestartAt::Line(9)).unwrap_err();
        assert!(e.message.contains("no such line"), "{e}");
        let e = interp("G0 X10\nN5 Z1\nM30\n").scan_to(RestartAt::Seq(7)).unwrap_err();
        assert!(e.message.contains("sequence number"), "{e}");
        let e = interp("G0 X40 Z2\nG42 G1 X30 F100\nZ-10\nG40 G0 X50\nM30\n").scan_to(RestartAt::Line(3)).unwrap_err();
        assert!(e.message.contains("G41/G42"), "{e}");
    }
}
