//! `cncgw run PROG --restart-at LINE | --restart-seq N`: program restart (issue 24.4).
//!
//! The interpreter scans the program to the block without motion (`interp::restart`), then
//! the machine is given what the scan withheld and brought to where the program would have
//! the tool, before the program goes on from that block:
//! G22 in force → M00 (on a terminal: cycle start `s` confirms the move; in batch it goes
//! on) → the last T code → the axes in a safe order → the last spindle command → the block.
//! The safe order is that of an outside-turning lathe (the manual is silent; Fanuc leaves it
//! to No.7310): X away from the work first — to the larger of the present and the restart
//! X —, then Z (and Y), then X to the restart X; so the tool never crosses the part sideways
//! below its present diameter. A bore or an internal contour needs a restart block where the
//! tool is out of the hole.

use super::run::MoveFeed;
use crate::canon::{Move, MoveKind, Pos, SrcPos};
use crate::interp::{Interpreter, RestartAt, RestartScan};
use crate::Alarm;
use std::collections::{HashMap, VecDeque};

/// The restart options of `run`.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RestartArgs {
    /// Restart the program at this source line (1-based) of the main program: the blocks
    /// before it are scanned for the modal state without motion, the axes go there (X away
    /// first), the spindle starts, the program goes on.
    #[arg(long, value_name = "LINE", conflicts_with = "restart_seq")]
    pub restart_at: Option<u32>,
    /// Restart at the first block of the main program numbered N (its N word), as --restart-at.
    #[arg(long, value_name = "N")]
    pub restart_seq: Option<u32>,
}

impl RestartArgs {
    pub fn at(&self) -> Option<RestartAt> {
        self.restart_at.map(RestartAt::Line).or(self.restart_seq.map(RestartAt::Seq))
    }
}

/// Why the program cannot be restarted at `at`, found before the drives are enabled: the
/// scan from machine zero (it runs again from the drives' real position in the run; the
/// reasons do not depend on it) or a tool still in a tapped hole.
pub fn precheck(
    at: RestartAt,
    pre: Result<Interpreter, Vec<Alarm>>,
    tables: &crate::offsets::Tables,
    vars: &HashMap<u32, f64>,
    in_hole: bool,
) -> Option<Alarm> {
    if in_hole {
        return Some(Alarm::new(
            crate::alarm::RESTART,
            "cannot restart: the tool is in a tapped hole; bring it out with a program that starts with G30 P99 first; nothing was moved",
        ));
    }
    match pre {
        Err(a) => a.into_iter().next(),
        Ok(mut i) => {
            tables.apply(&mut i);
            i.set_common_vars(vars.clone());
            i.scan_to(at).err()
        }
    }
}

/// The moves that bring the machine from `start` to the scan's restart point, in the safe
/// order of the module doc (machine coordinates; unchanged steps left out).
pub fn approach(start: Pos, scan: &RestartScan) -> Vec<Pos> {
    let p = scan.pos;
    let away = start.x.max(p.x);
    let steps = [Pos { x: away, ..start }, Pos { x: away, y: p.y, z: p.z, c: start.c }, p];
    let mut out: Vec<Pos> = Vec::new();
    let mut cur = start;
    for s in steps {
        if s != cur {
            out.push(s);
            cur = s;
        }
    }
    out
}

/// The restart's moves ahead of the program's, then the program.
struct RestartFeed {
    head: VecDeque<Result<Move, Alarm>>,
    interp: Interpreter,
}

impl Iterator for RestartFeed {
    type Item = Result<Move, Alarm>;
    fn next(&mut self) -> Option<Self::Item> {
        self.head.pop_front().or_else(|| self.interp.next())
    }
}

impl MoveFeed for RestartFeed {
    fn common_vars(&self) -> HashMap<u32, f64> {
        self.interp.common_vars().clone()
    }
}

/// One axis' positions as the operator reads them (X as a diameter).
fn show(p: Pos) -> String {
    format!("X {:.4} Z {:.4}", p.x * 2.0, p.z)
}

/// The feed of a restarted run: scan `interp` (its start position already set) to `at`,
/// say where each axis will go, then the restart's moves and the program from the block.
/// A refusal comes out as the feed's only item, an alarm before any motion.
pub fn feed(at: RestartAt, mut interp: Interpreter, start: Pos) -> Box<dyn MoveFeed> {
    let scan = match interp.scan_to(at) {
        Ok(s) => s,
        Err(a) => return Box::new(RestartFeed { head: VecDeque::from([Err(a)]), interp }),
    };
    let path = approach(start, &scan);
    eprintln!(
        "cncgw: restart at line {} ({}): {} block(s) scanned without motion, {} move(s) withheld",
        scan.line, scan.text, scan.blocks, scan.moves_skipped
    );
    // Each step by the axes it moves.
    let mut prev = start;
    let order: Vec<String> = path
        .iter()
        .map(|p| {
            let mut parts = Vec::new();
            for (name, a, b, scale) in [("X", prev.x, p.x, 2.0), ("Y", prev.y, p.y, 1.0), ("Z", prev.z, p.z, 1.0), ("C", prev.c, p.c, 1.0)] {
                if a != b {
                    parts.push(format!("{name} {:.4}", b * scale));
                }
            }
            prev = *p;
            parts.join(" ")
        })
        .collect();
    eprintln!(
        "cncgw: the axes go from {} to {} (machine; work {}; X as a diameter){}",
        show(start),
        show(scan.pos),
        show(scan.pos.sub(scan.work_offset)),
        if path.is_empty() { ": already there".to_string() } else { format!(", in this order: {}", order.join(" → ")) }
    );
    eprintln!("cncgw: the approach waits at an M00: on the panel, cycle start (s) confirms it; without a terminal it goes on");
    match scan.spindle.as_ref().map(|m| &m.kind) {
        Some(MoveKind::Spindle(s)) => {
            let m = match s.dir {
                crate::canon::SpindleDir::Cw => "M03",
                crate::canon::SpindleDir::Ccw => "M04",
                crate::canon::SpindleDir::Stop => "M05",
            };
            eprintln!("cncgw: then the spindle: {m} S{}{}", s.rpm, s.css.map_or(String::new(), |v| format!(" (G96, {v} m/min)")))
        }
        _ => eprintln!("cncgw: then no spindle command (the program gave none before the block)"),
    }
    let src = SrcPos::new(scan.file.clone(), scan.line, 1);
    let mk = |kind| Ok(Move { src: src.clone(), kind, exact_stop: true, work_offset: scan.work_offset, tag: None });
    // What the scan withheld is given at the restart block (the display and the trace show
    // the restart line, not the line far back that programmed it).
    let at_restart = |m: &Option<Move>| m.clone().map(|m| Ok(Move { src: src.clone(), ..m }));
    let mut head = VecDeque::new();
    head.extend(at_restart(&scan.stroke));
    // The operator's confirmation: cycle start on a terminal (M00), nothing in batch.
    head.push_back(mk(MoveKind::Stop { optional: false }));
    head.extend(at_restart(&scan.tool));
    head.extend(path.iter().map(|p| mk(MoveKind::Rapid { end: *p })));
    head.extend(at_restart(&scan.spindle));
    Box::new(RestartFeed { head, interp })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan_at(x: f64, z: f64) -> RestartScan {
        RestartScan {
            file: "t.nc".into(),
            line: 1,
            text: String::new(),
            pos: Pos::xz(x, z),
            work_offset: Pos::ZERO,
            spindle: None,
            stroke: None,
            tool: None,
            blocks: 0,
            moves_skipped: 0,
        }
    }

    #[test]
    fn x_goes_away_first_then_z_then_x_in() {
        // From a small diameter to a larger one further out: X out first, then Z.
        assert_eq!(approach(Pos::xz(10.0, -30.0), &scan_at(25.0, 2.0)), vec![Pos::xz(25.0, -30.0), Pos::xz(25.0, 2.0)]);
        // Down to a smaller diameter: Z first at the present (larger) X, X in last.
        assert_eq!(approach(Pos::xz(50.0, 5.0), &scan_at(20.0, -10.0)), vec![Pos::xz(50.0, -10.0), Pos::xz(20.0, -10.0)]);
        assert!(approach(Pos::xz(20.0, 1.0), &scan_at(20.0, 1.0)).is_empty());
    }
}
