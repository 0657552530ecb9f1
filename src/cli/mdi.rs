//! `cncgw mdi` (manual data input) and `cncgw run -`: blocks typed or piped on standard input.
//!
//! MDI runs one job (`run::run_job`) for the whole session, so the drives stay enabled and
//! the spindle keeps turning between blocks; the moves come from [`MdiFeed`] instead of a
//! program file. Each line is one block. The modal state (G codes, F, S, T, offsets, macro
//! variables, position) is kept between blocks by the same interpreter: the session's blocks
//! so far plus the new one are interpreted from the session's start (no motion), and only
//! the new block's moves go to the machine — so a block is decoded exactly as it would be in
//! a program after the blocks before it. Each block is checked as a run is before motion
//! (`control::guard::check_program_with`: travel, G22, feeds, threads and taps, program
//! alarms): a refused block moves nothing, is not kept, and the session goes on with the
//! modal state as before it. An alarm of the machine itself (a drive, the watchdog) ends the
//! session, as it ends a run. As on a Fanuc in MDI mode each block runs on its own: tool
//! nose radius compensation sees no next block (the last block ends as at a program end).
//! M02/M30 ends the session; so does the end of input (Ctrl-D).

use super::exit;
use super::run::{self, ExecOpts, Job, MoveFeed, RunExtras, TapSetup};
use super::MachineArgs;
use super::OrSetup;
use crate::canon::{Move, MoveKind, Pos};
use crate::config::MachineConfig;
use crate::interp::Interpreter;
use crate::Alarm;
use std::collections::HashMap;
use std::io::{BufRead, IsTerminal, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::mpsc::Receiver;

/// `run -`: the program text from standard input (None for a program file).
pub fn program_from_stdin(program: &Path) -> Result<Option<String>, String> {
    if program != Path::new("-") {
        return Ok(None);
    }
    let mut text = String::new();
    std::io::stdin().read_to_string(&mut text).map_err(|e| format!("cannot read the program from standard input: {e}"))?;
    Ok(Some(text))
}

/// What `cncgw mdi` takes.
#[derive(clap::Args, Debug, Clone)]
pub struct MdiArgs {
    #[command(flatten)]
    pub machine: MachineArgs,
    /// Where the machine's state lives (as for `run`).
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// Tool offset table instead of the stored one (as for `run`).
    #[arg(long, value_name = "FILE")]
    pub tools: Option<PathBuf>,
    /// Print the session's summary as JSON at the end.
    #[arg(long)]
    pub json: bool,
}

/// The session's blocks and what the interpreter needs to decode the next one as the
/// session so far left it.
pub struct MdiFeed {
    lines: Receiver<String>,
    /// The blocks run so far, in order (one line each).
    history: Vec<String>,
    cfg: MachineConfig,
    tables: crate::offsets::Tables,
    /// Machine position and common variables at the session's start.
    start: Pos,
    vars0: HashMap<u32, f64>,
    /// Common variables after the last block that ran, shared with `mdi`, which stores them:
    /// `run_job` does not wait for a feed that may be waiting for input (after an alarm or
    /// Ctrl-C the session ends without another line).
    vars: std::sync::Arc<std::sync::Mutex<HashMap<u32, f64>>>,
    pending: std::collections::VecDeque<Result<Move, Alarm>>,
    done: bool,
    prompt: bool,
    history_file: Option<crate::persist::AlarmHistory>,
}

/// The name of the session's "program" in alarms and the alarm history.
pub const MDI_NAME: &str = "MDI";

impl MdiFeed {
    fn interpreter(&self, text: &str) -> Result<Interpreter, Vec<Alarm>> {
        let mut i = Interpreter::with_program_dir(MDI_NAME, text, &self.cfg, Some(Path::new(".")))?;
        self.tables.apply(&mut i);
        i.set_common_vars(self.vars0.clone());
        i.set_start_position(self.start);
        // A block that loops without end is stopped as a program is (alarm 2501).
        i.set_block_budget(crate::interp::DEFAULT_BLOCK_BUDGET);
        Ok(i)
    }

    fn refuse(&self, a: &Alarm) {
        eprintln!("{a}");
        eprintln!("MDI: the block was not run (nothing moved); the modal state is as before it");
        if let Some(h) = &self.history_file {
            let _ = h.append(a, MDI_NAME);
        }
    }

    /// Decode `line` after the session's blocks; its moves into `pending`, or refused.
    fn block(&mut self, line: &str) {
        let n = self.history.len() as u32 + 1;
        let mut text = String::new();
        for b in &self.history {
            text.push_str(b);
            text.push('\n');
        }
        text.push_str(line);
        // The check refuses a program without an end; the session's end is not this block's.
        text.push_str("\nM30\n");
        let pre = match self.interpreter(&text) {
            Ok(i) => i,
            Err(alarms) => {
                for a in &alarms[..alarms.len().saturating_sub(1)] {
                    eprintln!("{a}");
                }
                if let Some(a) = alarms.last() {
                    self.refuse(a);
                }
                return;
            }
        };
        let limits = crate::motion::Limits::from_config(&self.cfg);
        let tool = crate::motion::polygon::ToolSpindle::from_config(&self.cfg);
        if let Err(a) = crate::control::guard::check_program_with(pre, &limits, self.start, tool.as_ref(), 2_000_000) {
            self.refuse(&a);
            return;
        }
        let Ok(mut it) = self.interpreter(&text) else { return };
        let mut out = Vec::new();
        for m in it.by_ref() {
            match m {
                // The blocks before this one ran already: their moves are the scan's, not sent.
                Ok(m) if m.src.line != n => {}
                Ok(m) => {
                    self.done |= matches!(m.kind, MoveKind::End { .. });
                    out.push(Ok(m));
                }
                Err(a) => {
                    // The check ran the same text from the same state: not expected, but
                    // never send half a block.
                    self.refuse(&a);
                    return;
                }
            }
        }
        if let Ok(mut v) = self.vars.lock() {
            *v = it.common_vars().clone();
        }
        self.history.push(line.to_string());
        if !self.prompt {
            eprintln!("MDI {n}: {line}");
        }
        self.pending.extend(out);
    }
}

impl Iterator for MdiFeed {
    type Item = Result<Move, Alarm>;
    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(m) = self.pending.pop_front() {
                return Some(m);
            }
            if self.done {
                return None;
            }
            if self.prompt {
                eprint!("MDI> ");
                let _ = std::io::stderr().flush();
            }
            let Ok(line) = self.lines.recv() else {
                // The end of input ends the session as M30 ends a program (spindle stopped,
                // the end point checked), once.
                self.block("M30");
                self.done = true;
                continue;
            };
            let line = line.trim_end_matches(['\r', '\n']).trim();
            if !line.is_empty() {
                self.block(line);
            }
        }
    }
}

impl MoveFeed for MdiFeed {
    fn common_vars(&self) -> HashMap<u32, f64> {
        self.vars.lock().map(|v| v.clone()).unwrap_or_default()
    }
}

/// Standard input's lines on a channel (a thread reads them, so that the feed can wait).
fn stdin_lines() -> Receiver<String> {
    let (tx, rx) = std::sync::mpsc::channel();
    let _ = std::thread::Builder::new().name("mdi-input".into()).spawn(move || {
        for l in std::io::stdin().lock().lines() {
            let Ok(l) = l else { break };
            if tx.send(l).is_err() {
                break;
            }
        }
    });
    rx
}

/// `cncgw mdi`.
pub fn mdi(a: &MdiArgs) -> i32 {
    let machine = &a.machine;
    let (cfg, cfg_text) = match super::machine_config(machine).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    let state_root = a.state_dir.clone().or_else(crate::persist::default_state_dir);
    let tables = match super::resolve_tables(state_root.as_deref(), &cfg.machine.name, a.tools.as_deref()) {
        Ok(t) => t,
        Err(code) => return code,
    };
    eprintln!("cncgw: {}", tables.source);
    // The machine's state as for a run: locked, common variables loaded, alarms kept.
    let state = state_root.as_ref().map(|d| crate::persist::StatePlace::new(d, &cfg.machine.name, &run::run_place(&cfg, machine)));
    let mut _lock = None;
    let mut vars0 = HashMap::new();
    let mut tap = None;
    if let Some(st) = &state {
        if let Err(al) = st.check_writable() {
            eprintln!("{al}");
            return exit::SETUP;
        }
        match super::lock::state(&st.dir, &st.key).and_then(|l| st.common_vars().load().map(|v| (l, v))) {
            Ok((l, v)) => {
                _lock = Some(l);
                vars0 = v;
            }
            Err(al) => {
                eprintln!("{al}");
                return exit::SETUP;
            }
        }
        let f = st.tap_state();
        match f.load() {
            Ok(Some(t)) if t.in_hole => {
                eprintln!(
                    "{}",
                    Alarm::new(
                        crate::control::tapstate::TAP_IN_HOLE,
                        format!("the tool is in the hole of the rigid tap of line {}: bring it out with a program that starts with G30 P99 (`cncgw run`) before MDI; nothing was moved", t.line)
                    )
                );
                return exit::ALARM;
            }
            Ok(loaded) => tap = Some(TapSetup { file: f.path, loaded }),
            Err(al) => {
                eprintln!("{al}");
                return exit::SETUP;
            }
        }
    }
    let first = match Interpreter::from_source(MDI_NAME, "", &cfg) {
        Ok(mut i) => {
            tables.apply(&mut i);
            i.set_common_vars(vars0.clone());
            i
        }
        Err(al) => {
            for x in &al {
                eprintln!("{x}");
            }
            return exit::INPUT;
        }
    };
    let prompt = std::io::stdin().is_terminal() && std::io::stderr().is_terminal();
    if prompt {
        eprintln!("MDI: one block per line, Enter runs it; Ctrl-D or M30 ends, Ctrl-C stops the machine");
    }
    let history_file = state.as_ref().map(|s| s.alarm_history());
    let feed_cfg = cfg.clone();
    let feed_vars = vars0.clone();
    let vars_now = std::sync::Arc::new(std::sync::Mutex::new(vars0.clone()));
    let feed_vars_now = vars_now.clone();
    let feed_history = history_file.clone();
    let job = Job {
        name: "MDI".into(),
        source: String::new(),
        first: Some(first),
        // Each block is checked by the feed before it moves; there is no whole program to
        // check at the start.
        make: Box::new(|_| Err(Vec::new())),
        feed: Some(Box::new(move |_, start| {
            Box::new(MdiFeed {
                lines: stdin_lines(),
                history: Vec::new(),
                cfg: feed_cfg,
                tables,
                start,
                vars: feed_vars_now,
                vars0: feed_vars,
                pending: Default::default(),
                done: false,
                prompt,
                history_file: feed_history,
            })
        })),
    };
    let mut opts = ExecOpts {
        json: a.json,
        print_summary: true,
        extras: RunExtras { tap, history: history_file, reference: run::RefSetup::new(&cfg, state.as_ref()), ..RunExtras::default() },
        operator: None,
        pace: true,
        live: true,
    };
    // No panel: standard input carries the blocks, not keys (Ctrl-C stops the machine).
    let batch = run::OperatorArgs { batch: true, realtime: false };
    let (code, _, summary) = run::with_operator(&batch, &mut opts, |o| run::run_job(&cfg, &cfg_text, machine, job, o));
    // Nothing to store when the drives never started (the feed was never made).
    let vars = if summary.cycles > 0 { vars_now.lock().ok().map(|v| v.clone()) } else { None };
    if let (Some(st), Some(v)) = (&state, vars) {
        if let Err(al) = st.common_vars().save(&v) {
            eprintln!("{al}");
            return if code == exit::OK { exit::SETUP } else { code };
        }
    }
    code
}
