//! `cncgw plan`: the canonical moves of a program without running anything, then the checks
//! `run` makes before motion (unless `--no-machine`) and a closing summary on stderr.

use super::OrSetup;
use super::{exit, load_config};
use crate::canon::{Move, MoveKind, Pos};
use std::io::Write;
use std::path::PathBuf;

/// The arguments of `cncgw plan` (its help is the `Command::Plan` variant's).
#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    /// The part program (Type A G code or SINUMERIK cycles).
    pub program: PathBuf,
    /// Machine configuration (TOML). Default: the embedded config/lathe.toml.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Output format: one JSON object per line, or text.
    #[arg(long, default_value = "jsonl", value_parser = ["jsonl", "text"])]
    pub format: String,
    /// Stop with alarm 2501 after this many blocks (a program that loops without end:
    /// M99 in the main program, DO without WHILE). 0 = no budget.
    #[arg(long, value_name = "N", default_value_t = crate::interp::DEFAULT_BLOCK_BUDGET)]
    pub max_blocks: u64,
    /// Tool offset table (docs/TOOL_TABLE.md), as `run --tools` and `preview --tools`.
    #[arg(long, value_name = "FILE")]
    pub tools: Option<PathBuf>,
    /// Where the stored offsets are (`cncgw offsets`; as for `run`). Default:
    /// $CNCGW_STATE_DIR, else $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// Only the moves: skip the machine checks `run` makes before motion (travel, G22,
    /// feeds, threads and taps against the axes and the spindle).
    #[arg(long)]
    pub no_machine: bool,
}

/// Exit 0, 2 for a program error (5010 without M02/M30, 2501 over the budget), 3 when the
/// machine would refuse it (as `run` does before motion).
pub fn plan(a: &PlanArgs) -> i32 {
    let (cfg, _) = match load_config(a.config.as_deref()).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    // The same offsets as `run`: --tools FILE, else the stored table; the stored work offsets.
    let state_root = a.state_dir.clone().or_else(crate::persist::default_state_dir);
    let tables = match super::resolve_tables(state_root.as_deref(), &cfg.machine.name, a.tools.as_deref()) {
        Ok(t) => t,
        Err(code) => return code,
    };
    let make = || -> Result<crate::interp::Interpreter, i32> {
        let mut i = crate::interp::Interpreter::from_file(&a.program, &cfg).map_err(|alarms| {
            for al in &alarms {
                eprintln!("{al}");
            }
            exit::INPUT
        })?;
        i.set_block_budget(a.max_blocks);
        tables.apply(&mut i);
        Ok(i)
    };
    let interp = match make() {
        Ok(i) => i,
        Err(code) => return code,
    };
    let mut sum = Summary::default();
    if let Err(code) = list(interp, &a.format, &mut sum) {
        return code;
    }
    if !sum.ended {
        eprintln!("{}: {}", a.program.display(), crate::control::guard::end_of_record(sum.moves == 0));
        return exit::INPUT;
    }
    eprintln!("{}", sum.describe());
    // After the listing's summary: an alarm's first lines stay the alarm and its echo.
    eprintln!("{}", tables.source);
    if a.no_machine {
        eprintln!("machine checks: skipped (--no-machine)");
        return exit::OK;
    }
    let Ok(pre) = make() else { return exit::INPUT };
    let tool = crate::motion::polygon::ToolSpindle::from_config(&cfg);
    let limits = crate::motion::Limits::from_config(&cfg);
    match crate::control::guard::check_program_with(pre, &limits, Pos::ZERO, tool.as_ref(), 2_000_000) {
        Ok(()) => {
            eprintln!("machine checks: ok for {} from machine zero (travel, G22, feeds, threads and taps against the axes)", cfg.machine.name);
            exit::OK
        }
        Err(al) => {
            eprintln!("{al}");
            exit::ALARM
        }
    }
}

/// Every move to stdout (one reused line buffer: a million-block program prints a million
/// lines), counted into `sum`.
fn list(interp: crate::interp::Interpreter, format: &str, sum: &mut Summary) -> Result<(), i32> {
    let out = std::io::stdout();
    let mut out = std::io::BufWriter::with_capacity(1 << 16, out.lock());
    let mut line = Vec::with_capacity(256);
    for m in interp {
        match m {
            Ok(m) => {
                sum.add(&m);
                line.clear();
                if format == "text" {
                    line.extend_from_slice(crate::interp::plan::move_to_text(&m).as_bytes());
                } else {
                    crate::interp::plan::write_json(&mut line, &m);
                }
                line.push(b'\n');
                if out.write_all(&line).is_err() {
                    return Err(exit::OK); // stdout closed (e.g. piped into head)
                }
            }
            Err(al) => {
                let _ = out.flush();
                eprintln!("{al}");
                return Err(exit::INPUT);
            }
        }
    }
    let _ = out.flush();
    Ok(())
}

/// What the listing covered: moves, whether it ended at M02/M30, and the extents of the
/// programmed end points in work coordinates (X as a diameter).
#[derive(Default)]
struct Summary {
    moves: u64,
    ended: bool,
    x: Option<(f64, f64)>,
    z: Option<(f64, f64)>,
}

impl Summary {
    fn add(&mut self, m: &Move) {
        self.moves += 1;
        self.ended |= matches!(m.kind, MoveKind::End { .. });
        if let Some(e) = m.kind.end() {
            let w = e.sub(m.work_offset);
            let grow = |r: &mut Option<(f64, f64)>, v: f64| *r = Some(r.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))));
            grow(&mut self.x, w.x * 2.0);
            grow(&mut self.z, w.z);
        }
    }

    fn describe(&self) -> String {
        let range = |r: Option<(f64, f64)>| r.map_or("-".to_string(), |(lo, hi)| format!("{lo:.3} … {hi:.3} mm"));
        format!("{} moves, ends at M02/M30; end points X {} (diameter), Z {} (work coordinates)", self.moves, range(self.x), range(self.z))
    }
}
