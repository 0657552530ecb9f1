//! G-code interpreter for the Type A lathe dialect (ELESY-E3TA manual
//! 004_5038892017d8ae23.txt): part program text → [`crate::canon::Move`] stream.
//!
//! Two passes, so that a long program is never held in memory (streaming):
//! 1. [`Interpreter::from_file`] / [`Interpreter::from_source`] read every line once to
//!    collect **all** syntax and static errors of the program, and keep only an index: the
//!    programs (`O`), sequence numbers (`N`, for GOTO/M99 P) and DO/END pairs, as byte
//!    offsets with their line numbers (`Loc`).
//! 2. [`Interpreter::next_move`] reads and parses one block at a time as it executes it,
//!    from the file (a read window, seeks for jumps), into one reused buffer.
//!
//! Alarm numbers: the manual gives none for the program errors handled here, so they are
//! Fanuc 0i-TF PS numbers (3 too many digits, 4 address not found, 5 no data after address,
//! 6 illegal minus sign, 7 illegal decimal point, 9 improper address, 10 improper G code
//! (also: two codes of one group, "not supported yet"), 11 no feed rate, 30 offset number
//! not in the tool table, 46 G30 P other than 1–4 or reference point not configured, 20 arc radius
//! out of tolerance, 21 axis outside the arc plane, 22 R or I/K missing, 50 `,C`/`,R` in a
//! thread cutting block, 51 no G01/G02/G03
//! move after `,C`/`,R`, 52 the next move is not G01/G02/G03, 55 chamfer/corner does not
//! fit, 73 program number defined twice, 76 program not found, 77 subprogram nesting too
//! deep, 78 sequence number not found, 111–128 macro errors), plus 2500 (ours) for an
//! endless loop that produces no motion and 1000 for a bad work offset table.
//!
//! Subprograms (M98 P, packed `P00021000`, L repeats; G65 with local variables) are looked
//! up in the same file, then in the program directory (the main file's directory for
//! [`Interpreter::from_file`]); literal calls are resolved and the called files checked
//! before anything runs. M99 in the main program restarts it (manual §3.1.7), so such a
//! program streams moves forever.
//!
//! T codes select a tool and its offset from the tool table ([`tools`],
//! [`Interpreter::set_tool_table`]); G28/G30 go to the reference points of parameters
//! No.1240–1243; M91/M92 read the input given by [`Interpreter::set_input_source`].
//!
//! Speed: plain NC lines (letters and numbers, as CAM output is) take a byte-level fast path
//! ([`parse::fast_words`]) into a fixed word array and a decoder kept across blocks, so a
//! block allocates nothing. `scripts/bench-rs274.sh` compares `cncgw plan` with LinuxCNC's
//! `rs274 -g` on a 1,000,000-block G1 program (figures in its header).
//!
//! Numbers without a decimal point: the manual gives no increment-system rule for them, so we
//! follow Fanuc parameter No.3401#0 (DPI): 1 = calculator-type input, `X10` = 10 mm; 0 =
//! least input increment (IS-B), `X10` = 0.010 mm (0.0010 inch under G20). When No.3401 is
//! not in the configuration, calculator-type input applies (this project's convention).
//! F, S, P, T and M values are never scaled.

pub mod corner;
pub mod curves;
pub mod cycles;
pub mod gcode;
pub mod macros;
pub mod nosecomp;
pub mod parse;
pub mod plan;
pub mod restart;
pub mod tools;
pub mod vec2;

use crate::canon::{Feed, Move, MoveKind, Plane, Pos, SpindleCmd, SpindleDir, SrcPos};
use crate::config::MachineConfig;
use crate::Alarm;
use gcode::{Decoded, GCode, Val};
use macros::{MErr, Vars};
use parse::{Block, Expr, PErr, Stmt, Word};
pub use restart::{RestartAt, RestartScan};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
pub use tools::{load_tool_table, parse_tool_table, ActiveTool, ToolOffset, ToolTable};

/// The state of an external input signal, read by M91/M92 (manual §3.1.5). Called with the
/// M code (91 or 92) so that a machine may wire the two to different signals.
pub type InputSource = Box<dyn FnMut(u16) -> bool + Send>;

/// Our own alarm: this many blocks in a row without any move is taken as an endless loop.
pub const ENDLESS_LOOP_ALARM: u32 = crate::alarm::ENDLESS_LOOP;
/// Ours: the program ran more blocks than its budget (`--max-blocks`): a loop without end
/// (M99 in the main program, DO without WHILE) or a budget set too low.
pub const BLOCK_BUDGET_ALARM: u32 = crate::alarm::BLOCK_BUDGET;
/// `#3000 = k (MESSAGE)`: user alarm 3000 + k.
pub const USER_ALARM_VAR: u32 = crate::alarm::USER_ALARM;
/// The default block budget of `plan` and `run` (`--max-blocks`; 0 = none).
pub const DEFAULT_BLOCK_BUDGET: u64 = 10_000_000;
const ENDLESS_LOOP_BLOCKS: u64 = 2_000_000;
/// Chord tolerance (mm) of ellipses and parabolas emitted as chains of feed moves.
pub const CHORD_TOL: f64 = 0.002;
/// Fanuc/manual §3.1.6: 12 levels of subprogram/macro nesting.
pub const MAX_NESTING: usize = 12;

/// Where a line starts: byte offset in its source and 0-based line index. Jumps (GOTO, M99 P,
/// loops, calls) go to a `Loc`, so that no per-line table is needed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub(crate) struct Loc {
    pub(crate) off: u64,
    pub(crate) line: u32,
}

enum Text {
    /// A program given as text ([`Interpreter::from_source`]).
    Mem(Arc<str>),
    /// A program file, read as it runs (held open; the control does not expect a program to
    /// be edited while it runs, as a Fanuc locks the running program).
    File(std::fs::File),
}

/// Bytes read from a file at a time.
const WINDOW: usize = 64 * 1024;

/// One program file. Only a read window is kept in memory, never the whole file.
struct Source {
    file: Arc<str>,
    text: Text,
    len: u64,
    /// Read window of a file source: bytes `win_off .. win_off + win.len()`.
    win: Vec<u8>,
    win_off: u64,
    /// The window reaches the end of the file.
    win_eof: bool,
}

/// A line without its line end (`\n`, and any `\r` before it).
fn trim_eol(b: &[u8]) -> &[u8] {
    let mut n = b.len();
    while n > 0 && matches!(b[n - 1], b'\r' | b'\n') {
        n -= 1;
    }
    &b[..n]
}

impl Source {
    fn mem(file: &str, text: &str) -> Source {
        Source { file: Arc::from(file), text: Text::Mem(Arc::from(text)), len: text.len() as u64, win: Vec::new(), win_off: 0, win_eof: false }
    }

    /// A program file; `None` when `path` is not a readable regular file.
    fn open(path: &std::path::Path) -> std::io::Result<Source> {
        let f = std::fs::File::open(path)?;
        let meta = f.metadata()?;
        if !meta.is_file() {
            return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a regular file"));
        }
        Ok(Source { file: Arc::from(path.display().to_string()), text: Text::File(f), len: meta.len(), win: Vec::new(), win_off: 0, win_eof: false })
    }

    /// The line starting at `off`, without its line end, into `out` (cleared first); returns
    /// where the next line starts (`len` after the last one). A UTF-8 byte-order mark at the
    /// start of the file (Windows editors write one) is not part of the first line.
    fn read_line(&mut self, off: u64, out: &mut Vec<u8>) -> std::io::Result<u64> {
        let next = self.read_line_raw(off, out)?;
        if off == 0 && out.starts_with(b"\xEF\xBB\xBF") {
            out.drain(..3);
        }
        Ok(next)
    }

    /// [`Self::read_line`] without the byte-order mark rule. Sequential reads are served
    /// from the read window.
    fn read_line_raw(&mut self, off: u64, out: &mut Vec<u8>) -> std::io::Result<u64> {
        out.clear();
        if off >= self.len {
            return Ok(self.len);
        }
        let f = match &self.text {
            Text::Mem(t) => {
                let rest = &t.as_bytes()[off as usize..];
                let (line, next) = match parse::find_newline(rest) {
                    Some(i) => (&rest[..i], off + i as u64 + 1),
                    None => (rest, self.len),
                };
                out.extend_from_slice(trim_eol(line));
                return Ok(next);
            }
            Text::File(f) => f,
        };
        let mut want = WINDOW;
        loop {
            let win_end = self.win_off + self.win.len() as u64;
            if off >= self.win_off && off < win_end {
                let rest = &self.win[(off - self.win_off) as usize..];
                if let Some(i) = parse::find_newline(rest) {
                    out.extend_from_slice(trim_eol(&rest[..i]));
                    return Ok(off + i as u64 + 1);
                }
                if win_end >= self.len || self.win_eof {
                    // The last line, without a line end (or the file was cut short).
                    out.extend_from_slice(trim_eol(rest));
                    return Ok(self.len);
                }
                if off == self.win_off {
                    // A line longer than the window: widen it.
                    want = self.win.len() * 2;
                }
            }
            use std::os::unix::fs::FileExt;
            self.win.clear();
            self.win.resize(want, 0);
            let mut n = 0;
            while n < want {
                match f.read_at(&mut self.win[n..], off + n as u64) {
                    Ok(0) => break,
                    Ok(k) => n += k,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                    Err(e) => {
                        self.win.clear();
                        return Err(e);
                    }
                }
            }
            self.win.truncate(n);
            self.win_off = off;
            self.win_eof = n < want;
            if n == 0 {
                return Ok(self.len);
            }
        }
    }

    /// The text of the line at `at` and where the next one starts, read without the window
    /// (alarm texts and canned-cycle contours, off the hot path).
    fn line_at(&self, at: Loc) -> (String, Loc) {
        let mut bytes = Vec::new();
        let mut next = self.len;
        match &self.text {
            Text::Mem(t) => {
                let rest = t.as_bytes().get(at.off as usize..).unwrap_or(&[]);
                let i = rest.iter().position(|&c| c == b'\n');
                bytes.extend_from_slice(&rest[..i.unwrap_or(rest.len())]);
                if let Some(i) = i {
                    next = at.off + i as u64 + 1;
                }
            }
            Text::File(f) => {
                use std::os::unix::fs::FileExt;
                let mut chunk = [0u8; 256];
                let mut off = at.off;
                while off < self.len {
                    let k = match f.read_at(&mut chunk, off) {
                        Ok(0) | Err(_) => break,
                        Ok(k) => k,
                    };
                    if let Some(i) = chunk[..k].iter().position(|&c| c == b'\n') {
                        bytes.extend_from_slice(&chunk[..i]);
                        next = off + i as u64 + 1;
                        break;
                    }
                    bytes.extend_from_slice(&chunk[..k]);
                    off += k as u64;
                }
            }
        }
        let text = String::from_utf8_lossy(trim_eol(&bytes)).into_owned();
        (text, Loc { off: next.min(self.len), line: at.line + 1 })
    }
}

/// The end of a program not closed yet during pass 1.
const OPEN: Loc = Loc { off: u64::MAX, line: u32::MAX };

#[derive(Clone, Debug)]
struct ProgInfo {
    number: Option<u32>,
    /// Index into `sources`.
    src: usize,
    /// The first line after the `O` line.
    start: Loc,
    /// Where the program ends (the next `O` or `%` line, or the end of the file).
    end: Loc,
}

#[derive(Clone, Debug)]
struct Frame {
    /// Program and line to return to.
    prog: usize,
    line: Loc,
    /// Remaining repetitions (M98 L) including the current one.
    repeats: u32,
    /// G65 call: has its own local variables.
    macro_call: bool,
}

/// Modal state of the control.
#[derive(Clone, Debug)]
struct Modal {
    /// Group 01 code (×10).
    motion: GCode,
    per_rev: bool,
    inch: bool,
    css: bool,
    plane: Plane,
    wcs: usize,
    exact: bool,
    /// Last F under G98 (mm/min) and under G99 (mm/rev): manual §2.20 note 4.
    f_min: Option<f64>,
    f_rev: Option<f64>,
    dir: SpindleDir,
    rpm: f64,
    css_v: Option<f64>,
    max_rpm: Option<f64>,
}

/// A G01/G02/G03 move with `,C`/`,R`, held until the next move is known (§2.23).
#[derive(Clone, Debug)]
struct Corner {
    serial: u64,
    src: SrcPos,
    start: Pos,
    kind: MoveKind,
    exact: bool,
    offset: Pos,
    plane: Plane,
    chamfer: bool,
    value: f64,
    /// One G04 block may stand between the two moves.
    g04: bool,
}

pub struct Interpreter {
    /// The main file and the subprogram files loaded from `program_dir`.
    sources: Vec<Source>,
    program_dir: Option<std::path::PathBuf>,
    progs: Vec<ProgInfo>,
    /// The label index: block N`n` of program `p` at (p, n) (the first one in the program).
    labels: HashMap<(usize, u32), Loc>,
    /// DO line → the line after its END, and END line → its DO line, keyed by (source,
    /// offset of the DO/END line).
    do_end: HashMap<(usize, u64), Loc>,
    end_do: HashMap<(usize, u64), Loc>,
    // Machine facts.
    calculator: bool,
    arc_tol: f64,
    arc_missing_alarm: bool,
    has_y: bool,
    has_c: bool,
    /// The drilling cycles' tool turns in the tool spindle (machine.drilling_spindle = "tool").
    driven_tool_drilling: bool,
    // Execution state.
    prog: usize,
    /// The next line to execute.
    line: Loc,
    /// The block executed last (source, line) and its text in `line_buf`, for alarms raised
    /// between blocks.
    cur: (usize, Loc),
    line_buf: Vec<u8>,
    /// Reused buffer for the moves nose radius compensation lets through.
    nrc_scratch: Vec<Move>,
    /// The words and the decoded block of the fast path, kept across blocks (not initialised
    /// or copied per block).
    fast_ev: [parse::FastWord; parse::FAST_WORDS],
    dec: Option<Box<gcode::BlockDecoder>>,
    stack: Vec<Frame>,
    vars: Vars,
    st: Modal,
    pos: Pos,
    wcs_table: [Pos; 6],
    /// G50 shift, common to all workpiece coordinate systems (manual §2.12.2 note 4).
    shift: Pos,
    /// G52 local coordinate system.
    local: Pos,
    queue: VecDeque<Move>,
    ended: bool,
    /// A block with words other than G20/G21 has run: the unit can no longer be switched.
    unit_fixed: bool,
    block_skip: bool,
    idle_blocks: u64,
    idle_limit: u64,
    /// Blocks executed so far, and the budget (0 = none).
    blocks_run: u64,
    block_budget: u64,
    corner: Option<Corner>,
    corner_serial: u64,
    /// Moves made while a corner is pending; they follow the inserted chamfer/corner.
    held: Vec<Move>,
    // Tools (see [`tools`]).
    tool_table: ToolTable,
    /// Fanuc No.5002#1 LGN = 0: geometry offset by tool number (else by offset number).
    geo_by_tool: bool,
    tool: ActiveTool,
    /// Shift of the selected offset (machine units), and the part of it the axes have taken
    /// up (only that part is in [`Interpreter::offset`]).
    tool_shift: Pos,
    tool_applied: Pos,
    /// Added to incremental axis words of the block that takes up a new tool offset.
    tool_delta: Pos,
    /// Reference points 1–4 (machine coordinates, X as a radius) from No.1240–1243.
    ref_points: [Option<Pos>; 4],
    input: Option<InputSource>,
    /// Canned-cycle state (thread lead, retained cycle values, G76 parameters).
    cyc: cycles::CycleState,
    /// G40/G41/G42 tool nose radius compensation of the moves leaving `queue`.
    nrc: nosecomp::NoseComp,
    nrc_out: VecDeque<Move>,
    /// G12.1 polar coordinate interpolation in force.
    polar: Option<cycles::polar::PolarState>,
    /// G80–G89 drilling / tapping mode and rigid tapping state.
    drill: cycles::drill::DrillState,
}

fn perr_alarm(file: &Arc<str>, line_no: usize, text: &str, e: PErr) -> Alarm {
    Alarm::new(e.number, e.message).at(SrcPos::new(file.clone(), line_no as u32 + 1, e.col)).with_block(text.trim_end())
}

impl Interpreter {
    /// Parse and statically check the whole program (syntax errors for the WHOLE file are
    /// collected before anything runs), then return an interpreter positioned at its start.
    pub fn from_source(file_name: &str, text: &str, cfg: &MachineConfig) -> Result<Interpreter, Vec<Alarm>> {
        Self::with_program_dir(file_name, text, cfg, None)
    }

    fn build(source: Source, cfg: &MachineConfig) -> Interpreter {
        let calculator = cfg.param(3401).map(|v| (v as i64) & 1 == 1).unwrap_or(true);
        Interpreter {
            sources: vec![source],
            program_dir: None,
            progs: Vec::new(),
            labels: HashMap::new(),
            do_end: HashMap::new(),
            end_do: HashMap::new(),
            calculator,
            // Fanuc No.3410: arc end-point radius tolerance (mm); 0.01 mm when not configured.
            arc_tol: cfg.param(3410).filter(|v| *v > 0.0).unwrap_or(0.01),
            // Manual §2.3 note 2 / No.3403: G02/G03 without R and I/K → alarm (bit 5 set, or
            // parameter absent) or a straight line (bit 5 = 0, Fanuc CIR).
            arc_missing_alarm: cfg.param(3403).map(|_| cfg.param_bit(3403, 5)).unwrap_or(true),
            has_y: cfg.axes.contains_key("y"),
            has_c: cfg.spindle().is_some() || cfg.axes.contains_key("c"),
            driven_tool_drilling: cfg.machine.drilling_spindle == crate::config::DrillingSpindle::Tool,
            prog: 0,
            line: Loc::default(),
            cur: (0, Loc::default()),
            line_buf: Vec::new(),
            nrc_scratch: Vec::new(),
            fast_ev: [parse::NO_WORD; parse::FAST_WORDS],
            dec: None,
            stack: Vec::new(),
            vars: Vars::new(),
            st: Modal {
                motion: if cfg.param(5153).unwrap_or(0.0) as i64 == 1 { 10 } else { 0 },
                per_rev: cfg.param(5154).unwrap_or(0.0) as i64 == 1,
                inch: cfg.param(10).unwrap_or(0.0) as i64 & 1 == 1,
                css: false,
                plane: Plane::Zx,
                wcs: 0,
                exact: false,
                f_min: None,
                f_rev: None,
                dir: SpindleDir::Stop,
                rpm: 0.0,
                css_v: None,
                max_rpm: None,
            },
            pos: Pos::ZERO,
            wcs_table: [Pos::ZERO; 6],
            shift: Pos::ZERO,
            local: Pos::ZERO,
            queue: VecDeque::new(),
            ended: false,
            unit_fixed: false,
            block_skip: false,
            idle_blocks: 0,
            idle_limit: ENDLESS_LOOP_BLOCKS,
            blocks_run: 0,
            block_budget: 0,
            corner: None,
            corner_serial: 0,
            held: Vec::new(),
            tool_table: ToolTable::default(),
            geo_by_tool: cfg.param(5002).is_some() && !cfg.param_bit(5002, 1),
            tool: ActiveTool::default(),
            tool_shift: Pos::ZERO,
            tool_applied: Pos::ZERO,
            tool_delta: Pos::ZERO,
            ref_points: std::array::from_fn(|k| ref_point(cfg, k)),
            input: None,
            cyc: cycles::CycleState::new(cfg),
            nrc: nosecomp::NoseComp::default(),
            nrc_out: VecDeque::new(),
            polar: None,
            drill: cycles::drill::DrillState::new(cfg),
        }
    }

    fn check(mut self) -> Result<Interpreter, Vec<Alarm>> {
        self.progs.clear();
        self.sources.truncate(1);
        self.labels.clear();
        self.do_end.clear();
        self.end_do.clear();
        let mut errors = Vec::new();
        self.index_source(0, &mut errors);
        // In file order (main file first), then by line and column.
        let order = |a: &Alarm| a.pos.as_ref().map(|p| (self.sources.iter().position(|s| s.file == p.file).unwrap_or(usize::MAX), p.line, p.col));
        errors.sort_by_key(order);
        self.prog = 0;
        self.line = self.progs[0].start;
        if errors.is_empty() {
            Ok(self)
        } else {
            Err(errors)
        }
    }

    /// Like [`Interpreter::from_source`] for a program file, which is read as the program
    /// runs (streaming: memory does not grow with its length, apart from the label index);
    /// the program directory for M98/G65 is the file's directory.
    pub fn from_file(path: &std::path::Path, cfg: &MachineConfig) -> Result<Interpreter, Vec<Alarm>> {
        let source = Source::open(path).map_err(|e| vec![Alarm::new(76, format!("{}: cannot read the program: {e}", path.display()))])?;
        let dir = path.parent().map(|p| if p.as_os_str().is_empty() { std::path::Path::new(".") } else { p });
        let mut it = Self::build(source, cfg);
        it.program_dir = dir.map(|d| d.to_path_buf());
        it.check()
    }

    /// Like [`Interpreter::from_source`], with a program directory where M98/G65 look for
    /// programs not in this text (files `O0012`, `O0012.nc`, `O12.nc` or `0012.nc`).
    pub fn with_program_dir(file_name: &str, text: &str, cfg: &MachineConfig, dir: Option<&std::path::Path>) -> Result<Interpreter, Vec<Alarm>> {
        let mut it = Self::build(Source::mem(file_name, text), cfg);
        it.program_dir = dir.map(|d| d.to_path_buf());
        it.check()
    }

    /// Machine position of the axes when the program starts (default all zero).
    pub fn set_start_position(&mut self, p: Pos) {
        self.pos = p;
        self.nrc.set_start(p);
        self.cyc.stroke.set_start(p);
    }

    /// Common variables #401–#600, which the control keeps through power-off (§2.24.1):
    /// read them after a run to store them, give them back before the next.
    pub fn common_vars(&self) -> &HashMap<u32, f64> {
        &self.vars.common
    }

    pub fn set_common_vars(&mut self, vars: HashMap<u32, f64>) {
        self.vars.common = vars.into_iter().filter(|(n, v)| macros::is_common(*n) && v.is_finite()).collect();
    }

    /// How many blocks in a row may run without producing a move before alarm
    /// [`ENDLESS_LOOP_ALARM`] (default 2,000,000; the fuzz target lowers it).
    pub fn set_endless_loop_limit(&mut self, blocks: u64) {
        self.idle_limit = blocks.max(1);
    }

    /// At most `blocks` blocks run before alarm [`BLOCK_BUDGET_ALARM`] (0 = no budget, the
    /// default of the library; the CLI's `--max-blocks` defaults to [`DEFAULT_BLOCK_BUDGET`]).
    pub fn set_block_budget(&mut self, blocks: u64) {
        self.block_budget = blocks;
    }

    /// Blocks executed so far.
    pub fn blocks_run(&self) -> u64 {
        self.blocks_run
    }

    /// Block skip switch (`/` blocks are skipped when on). Default off.
    pub fn set_block_skip(&mut self, on: bool) {
        self.block_skip = on;
    }

    /// Workpiece zero offsets of G54…G59 in machine coordinates (X as a radius, mm), e.g.
    /// from [`parse_work_offsets`].
    pub fn set_work_offsets(&mut self, table: [Pos; 6]) {
        self.wcs_table = table;
    }

    /// The tool offset page (see [`tools::parse_tool_table`]). Without one, every offset reads
    /// as zero.
    pub fn set_tool_table(&mut self, table: ToolTable) {
        self.tool_table = table;
    }

    /// The tool selected by the last T code, with its nose radius and imaginary tip.
    pub fn active_tool(&self) -> ActiveTool {
        self.tool
    }

    /// Where M91/M92 read their input signal; without one every input is off (0).
    pub fn set_input_source(&mut self, f: impl FnMut(u16) -> bool + Send + 'static) {
        self.input = Some(Box::new(f));
    }

    /// The text of line `at` of the current program's source (canned-cycle contours read
    /// their blocks with it) and where the next line starts.
    fn line_text(&self, at: Loc) -> String {
        self.line_after(at).0
    }

    /// Line `at` of the current program's source and the location of the line after it.
    fn line_after(&self, at: Loc) -> (String, Loc) {
        self.sources[self.progs[self.prog].src].line_at(at)
    }

    fn cur_file(&self) -> Arc<str> {
        self.sources[self.progs[self.prog].src].file.clone()
    }

    /// Fanuc stops reading at the end-of-tape `%`; text after it would be dropped without a
    /// word, so the first non-blank line after it is PS5010 (end of record) before anything runs.
    fn after_tape_end(&mut self, si: usize, mut next: Loc, pct: Loc, buf: &mut Vec<u8>, errors: &mut Vec<Alarm>) {
        let file = self.sources[si].file.clone();
        while next.off < self.sources[si].len {
            let i = next;
            let Ok(off) = self.sources[si].read_line(i.off, buf) else { return };
            next = Loc { off, line: i.line + 1 };
            if buf.iter().any(|b| !b.is_ascii_whitespace()) {
                let text = String::from_utf8_lossy(buf).into_owned();
                errors.push(
                    Alarm::new(
                        5010,
                        format!("this line comes after the end-of-tape `%` of line {} and would never run: remove it, or the `%`", pct.line + 1),
                    )
                    .at(SrcPos::new(file, i.line + 1, 1))
                    .with_block(text.trim_end()),
                );
                return;
            }
        }
    }

    /// Pass 1 over source `si`, read line by line: parse every line, collect all errors,
    /// index its programs, labels and loops (as locations, no per-line memory); then load
    /// (and check) the subprograms it calls from the program directory. Jump targets and
    /// calls not known yet when they are met (forward references) are kept until the end of
    /// the pass.
    fn index_source(&mut self, si: usize, errors: &mut Vec<Alarm>) {
        let file = self.sources[si].file.clone();
        let first_prog = self.progs.len();
        self.progs.push(ProgInfo { number: None, src: si, start: Loc::default(), end: OPEN });
        let mut content = false;
        let mut loop_stack: Vec<(u8, Loc)> = Vec::new();
        let mut gotos: Vec<(usize, Loc, u32, u32)> = Vec::new(); // prog, line, target, col
        let mut calls: Vec<(Loc, u32, u32)> = Vec::new(); // line, program, col
        let mut buf = std::mem::take(&mut self.line_buf);
        let mut ev = [parse::NO_WORD; parse::FAST_WORDS];
        let mut dec = self.dec.take().unwrap_or_default();
        let mut next = Loc::default();
        while next.off < self.sources[si].len {
            let i = next;
            next = match self.sources[si].read_line(i.off, &mut buf) {
                Ok(off) => Loc { off, line: i.line + 1 },
                Err(e) => {
                    errors.push(Alarm::new(76, format!("{file}: cannot read the program: {e}")).at(SrcPos::new(file.clone(), i.line + 1, 1)));
                    break;
                }
            };
            // NC words straight from the bytes (most lines), else the full parser.
            let fast = parse::fast_words_static(&buf, &mut ev);
            let valid = match fast {
                // Only the `;` comment can hold anything but ASCII.
                Some(fb) => buf[fb.comment..].is_ascii() || std::str::from_utf8(&buf[fb.comment..]).is_ok(),
                None => std::str::from_utf8(&buf).is_ok(),
            };
            // The text itself is needed by the full parser and by alarms only.
            let text = if valid && fast.is_none() { std::str::from_utf8(&buf).unwrap_or("") } else { "" };
            if !valid {
                errors.push(Alarm::new(76, format!("{file}: cannot read the program: line {} is not UTF-8 text", i.line + 1)).at(SrcPos::new(
                    file.clone(),
                    i.line + 1,
                    1,
                )));
                content = true;
                continue;
            }
            let p = self.progs.len() - 1;
            let at = |col: u32| SrcPos::new(file.clone(), i.line + 1, col);
            let block;
            let (n, bcol, stmt) = match fast {
                Some(fb) => (fb.n, fb.col, None),
                None => match parse::parse_line(text) {
                    Ok(b) => {
                        block = b;
                        (block.n, block.col, Some(&block.stmt))
                    }
                    Err(e) => {
                        errors.push(perr_alarm(&file, i.line as usize, text, e));
                        content = true;
                        continue;
                    }
                },
            };
            match stmt {
                None if fast.is_some_and(|f| f.len == 0) && n.is_none() => continue,
                Some(Stmt::Percent) => {
                    if content {
                        // End of tape: the rest of the file is not part of the program.
                        if let Some(last) = self.progs.last_mut() {
                            last.end = i;
                        }
                        self.after_tape_end(si, next, i, &mut buf, errors);
                        break;
                    }
                    continue;
                }
                Some(Stmt::Program(num)) => {
                    self.close_loops(si, &mut loop_stack, errors);
                    if self.progs.iter().any(|q| q.number == Some(*num)) {
                        errors.push(Alarm::new(73, format!("program O{num:04} is defined twice")).at(at(bcol)).with_block(text.trim_end()));
                    }
                    if !content && self.progs.len() == first_prog + 1 {
                        self.progs[first_prog] = ProgInfo { number: Some(*num), src: si, start: next, end: OPEN };
                    } else {
                        if let Some(last) = self.progs.last_mut() {
                            last.end = i;
                        }
                        self.progs.push(ProgInfo { number: Some(*num), src: si, start: next, end: OPEN });
                    }
                    content = true;
                    continue;
                }
                Some(Stmt::Empty) if n.is_none() => continue,
                _ => {}
            }
            content = true;
            let (ngotos, ncalls) = (gotos.len(), calls.len());
            if let Some(n) = n {
                self.labels.entry((p, n)).or_insert(i);
            }
            let decoded = match (fast, stmt) {
                (Some(fb), _) if fb.len > 0 => Some(dec.decode(&ev[..fb.len], self.has_y, self.has_c).map_err(|(n, col, m)| col_alarm(n, col, m))),
                (_, Some(Stmt::Nc(words))) if words.iter().all(|w| w.value.is_literal()) => {
                    Some(self.decode_words(words, &Vars::new()).map(|d| dec.set(d)))
                }
                _ => None,
            };
            match decoded {
                Some(Err(a)) => {
                    let col = a_col(&a);
                    errors.push(a.at(at(col)).with_block(String::from_utf8_lossy(&buf).trim_end()));
                }
                Some(Ok(())) => {
                    let d = &dec.d;
                    if let Some(pv) = d.get('P') {
                        if d.m.iter().any(|m| m.0 == 98) {
                            let v = pv.v.round() as u64;
                            calls.push((i, if v > 9999 { (v % 10000) as u32 } else { v as u32 }, pv.col));
                        } else if d.has_g(650) {
                            calls.push((i, pv.v.round() as u32, pv.col));
                        } else if d.m.iter().any(|m| m.0 == 91 || m.0 == 92) && pv.v >= 1.0 {
                            // M91/M92 jump targets are checked like GOTO's.
                            gotos.push((p, i, pv.v.round() as u32, pv.col));
                        }
                    }
                }
                None => {}
            }
            if let Some(stmt) = stmt {
                self.index_stmt(stmt, (si, p), (i, next), (&at(bcol), text), &mut loop_stack, &mut gotos, errors);
            }
            // A backward reference is resolved now; only forward ones wait for the end.
            if gotos.len() > ngotos && gotos.last().is_some_and(|g| self.labels.contains_key(&(g.0, g.2))) {
                gotos.pop();
            }
            if calls.len() > ncalls && calls.last().is_some_and(|c| self.progs.iter().any(|q| q.number == Some(c.1))) {
                calls.pop();
            }
        }
        for q in &mut self.progs[first_prog..] {
            if q.end == OPEN {
                q.end = next;
            }
        }
        self.line_buf = buf;
        self.dec = Some(dec);
        self.close_loops(si, &mut loop_stack, errors);
        self.check_forward_refs(si, gotos, calls, errors);
    }

    /// [`Self::index_source`] for one statement: DO/END pairs, static checks of SINUMERIK
    /// cycle calls, and GOTO targets (kept in `gotos` until the end of the pass). `pos` is
    /// the block's position (its first column), `text` its line.
    #[allow(clippy::too_many_arguments)]
    fn index_stmt(
        &mut self,
        stmt: &Stmt,
        (si, p): (usize, usize),
        (i, next): (Loc, Loc),
        (pos, text): (&SrcPos, &str),
        loop_stack: &mut Vec<(u8, Loc)>,
        gotos: &mut Vec<(usize, Loc, u32, u32)>,
        errors: &mut Vec<Alarm>,
    ) {
        match stmt {
            Stmt::Do { n, .. } => {
                if loop_stack.len() >= 3 {
                    errors.push(Alarm::new(126, "DO loops nest at most 3 deep").at(pos.clone()).with_block(text.trim_end()));
                }
                loop_stack.push((*n, i));
            }
            Stmt::End(n) => match loop_stack.pop() {
                Some((m, d)) if m == *n => {
                    self.do_end.insert((si, d.off), next);
                    self.end_do.insert((si, i.off), d);
                }
                Some((m, d)) => {
                    errors.push(
                        Alarm::new(126, format!("END{n} does not match DO{m} of line {} (DO ranges may not cross)", d.line + 1))
                            .at(pos.clone())
                            .with_block(text.trim_end()),
                    );
                }
                None => errors.push(Alarm::new(126, format!("END{n} without a DO{n}")).at(pos.clone()).with_block(text.trim_end())),
            },
            Stmt::Call { name: Some(name), args, cols, .. } => {
                if let Some((n, col, m)) = cycles::siemens::static_check(name, args.len(), cols) {
                    errors.push(
                        Alarm::new(n, m)
                            .at(col.map_or_else(|| pos.clone(), |c| SrcPos::new(pos.file.clone(), pos.line, c)))
                            .with_block(text.trim_end()),
                    );
                }
            }
            Stmt::Goto(Expr::Num { v, .. }) | Stmt::IfGoto { target: Expr::Num { v, .. }, .. } => {
                gotos.push((p, i, *v as u32, pos.col));
            }
            _ => {}
        }
    }

    /// End of [`Self::index_source`]: the forward GOTO targets and subprogram calls that were
    /// still unknown when met.
    fn check_forward_refs(&mut self, si: usize, gotos: Vec<(usize, Loc, u32, u32)>, calls: Vec<(Loc, u32, u32)>, errors: &mut Vec<Alarm>) {
        let file = self.sources[si].file.clone();
        for (p, i, n, col) in gotos {
            if !self.labels.contains_key(&(p, n)) {
                let text = self.sources[si].line_at(i).0;
                errors.push(
                    Alarm::new(78, format!("GOTO {n}: there is no block N{n} in this program"))
                        .at(SrcPos::new(file.clone(), i.line + 1, col))
                        .with_block(text.trim_end()),
                );
            }
        }
        for (i, n, col) in calls {
            if let Err(m) = self.find_program(n, errors) {
                let text = self.sources[si].line_at(i).0;
                errors.push(Alarm::new(76, m).at(SrcPos::new(file.clone(), i.line + 1, col)).with_block(text.trim_end()));
            }
        }
    }

    /// Index of program O`n`: in the sources read so far, else from a file of the program
    /// directory named `O0012`, `O0012.nc`, `O12.nc`, `0012.nc` (tried in this order), which
    /// is then checked like the main file (its errors go to `errors`).
    fn find_program(&mut self, n: u32, errors: &mut Vec<Alarm>) -> Result<usize, String> {
        if let Some(p) = self.progs.iter().position(|q| q.number == Some(n)) {
            return Ok(p);
        }
        let Some(dir) = self.program_dir.clone() else {
            return Err(format!("program O{n:04} not found (no program directory)"));
        };
        let names = [format!("O{n:04}"), format!("O{n:04}.nc"), format!("O{n}.nc"), format!("{n:04}.nc")];
        for name in names {
            let path = dir.join(&name);
            if let Ok(source) = Source::open(&path) {
                let si = self.sources.len();
                self.sources.push(source);
                let before = self.progs.len();
                self.index_source(si, errors);
                // A file without an O line holds the program its name gives.
                if self.progs[before].number.is_none() {
                    self.progs[before].number = Some(n);
                }
                return self
                    .progs
                    .iter()
                    .position(|q| q.number == Some(n))
                    .ok_or_else(|| format!("{} does not hold program O{n:04}", path.display()));
            }
        }
        Err(format!("program O{n:04} not found in this file or in {}", dir.display()))
    }

    fn close_loops(&self, si: usize, stack: &mut Vec<(u8, Loc)>, errors: &mut Vec<Alarm>) {
        for (n, d) in stack.drain(..) {
            let text = self.sources[si].line_at(d).0;
            errors.push(
                Alarm::new(124, format!("DO{n} has no END{n}"))
                    .at(SrcPos::new(self.sources[si].file.clone(), d.line + 1, 1))
                    .with_block(text.trim_end()),
            );
        }
    }

    /// Evaluate the words of an NC block and decode it. Errors carry the column in `pos`
    /// (filled by the caller) via [`a_col`].
    fn decode_words(&self, words: &[Word], vars: &Vars) -> Result<Decoded, Alarm> {
        // Evaluated words, on the stack for ordinary blocks.
        let mut stack = [('\0', false, Val::default()); 24];
        let mut heap = Vec::new();
        let mut n = 0;
        for w in words {
            // A plain number (nearly every word) needs no evaluation.
            let (mut v, literal, decimal) = match w.value {
                Expr::Num { v, decimal } => (v, true, decimal),
                _ => {
                    let v = vars.eval_nc(&w.value).map_err(|e| col_alarm(e.number, w.col, e.message))?;
                    let Some(v) = v else { continue }; // null variable: the word is ignored
                    let literal = w.value.is_literal();
                    (v, literal, if literal { has_decimal(&w.value) } else { true })
                }
            };
            if !literal && is_length(w.letter, w.comma) {
                // §2.24.1: variable values are rounded to the least setting unit (0.001 mm).
                v = (v * 1000.0).round() / 1000.0;
            }
            let e = (w.letter, w.comma, Val { v, decimal, col: w.col, literal });
            if n < stack.len() {
                stack[n] = e;
                n += 1;
            } else {
                if heap.is_empty() {
                    heap.extend_from_slice(&stack);
                }
                heap.push(e);
            }
        }
        let ev = if heap.is_empty() { &stack[..n] } else { &heap[..] };
        Decoded::build(ev, self.has_y, self.has_c).map_err(|(n, col, m)| col_alarm(n, col, m))
    }

    /// Execute until the next canonical move. Ok(None) after M02/M30 has been returned or at
    /// the end of the text.
    pub fn next_move(&mut self) -> Result<Option<Move>, Alarm> {
        loop {
            if let Some(m) = self.nrc_out.pop_front() {
                self.idle_blocks = 0;
                return Ok(Some(m));
            }
            if let Some(m) = self.queue.pop_front() {
                // G22 stroke check on the programmed path, then the nose radius
                // compensation, which may hold the move for one motion.
                let mut out = std::mem::take(&mut self.nrc_scratch);
                let r = self.cyc.stroke.check(&m).and_then(|_| self.nrc.feed(m, &mut out));
                if let Err(a) = r {
                    out.clear();
                    self.nrc_scratch = out;
                    self.ended = true;
                    self.queue.clear();
                    self.nrc_out.clear();
                    return Err(a);
                }
                // One move in, one out (no compensation pending): hand it on directly.
                let direct = if out.len() == 1 { out.pop() } else { None };
                self.nrc_out.extend(out.drain(..));
                self.nrc_scratch = out;
                if let Some(m) = direct {
                    self.idle_blocks = 0;
                    return Ok(Some(m));
                }
                continue;
            }
            if self.ended {
                if self.corner.take().is_some() {
                    self.held.clear();
                    return Err(self.alarm_here(51, 1, "the program ends after a block with ,C/,R: a G01/G02/G03 move must follow it"));
                }
                let mut out = Vec::new();
                self.nrc.finish(&mut out)?;
                if !out.is_empty() {
                    self.nrc_out.extend(out);
                    continue;
                }
                return Ok(None);
            }
            self.idle_blocks += 1;
            if self.idle_blocks > self.idle_limit {
                self.ended = true;
                return Err(self.alarm_here(
                    ENDLESS_LOOP_ALARM,
                    1,
                    format!("{} blocks without any move: endless loop? Check the GOTO/WHILE logic", self.idle_limit),
                ));
            }
            self.blocks_run += 1;
            if self.block_budget > 0 && self.blocks_run > self.block_budget {
                self.ended = true;
                return Err(self.alarm_here(
                    BLOCK_BUDGET_ALARM,
                    1,
                    format!("the program has run {} blocks, its budget (--max-blocks): it loops without end (M99 in the main program, DO without WHILE)? End it with M30, or raise --max-blocks (0 = no budget)", self.block_budget),
                ));
            }
            if let Err(a) = self.step() {
                self.ended = true;
                return Err(a);
            }
        }
    }

    /// An alarm at the block executed last.
    fn alarm_here(&self, number: u32, col: u32, msg: impl Into<String>) -> Alarm {
        let (si, at) = self.cur;
        Alarm::new(number, msg)
            .at(SrcPos::new(self.sources[si].file.clone(), at.line + 1, col))
            .with_block(std::str::from_utf8(&self.line_buf).unwrap_or("").trim_end())
    }

    /// Execute one block (or handle the end of the current program). The line is read into
    /// `line_buf` (no allocation per block).
    fn step(&mut self) -> Result<(), Alarm> {
        if self.line.off >= self.progs[self.prog].end.off {
            // End of a program without M30/M99: a subprogram returns, the main program ends.
            if self.stack.is_empty() {
                self.ended = true;
            } else {
                self.ret(None).map_err(|e| self.alarm_here(e.number, 1, e.message))?;
            }
            return Ok(());
        }
        let i = self.line;
        let si = self.progs[self.prog].src;
        let mut buf = std::mem::take(&mut self.line_buf);
        let r = match self.sources[si].read_line(i.off, &mut buf) {
            Ok(next) => {
                self.line = Loc { off: next, line: i.line + 1 };
                self.cur = (si, i);
                self.exec_line(si, i, &buf)
            }
            Err(e) => Err(Alarm::new(76, format!("cannot read the program: {e}")).at(SrcPos::new(self.sources[si].file.clone(), i.line + 1, 1))),
        };
        self.line_buf = buf;
        r
    }

    /// `#n = v` of the block `text`. `#3000 = k (MESSAGE)` is a user alarm, as on the Fanuc
    /// family (the manual has no system variables): the program stops with alarm 3000 + k
    /// (k 0–200) and the comment of the block as its message.
    fn assign(&mut self, n: u32, v: macros::Value, text: &str) -> Result<(), MErr> {
        if n != USER_ALARM_VAR {
            return self.vars.set(n, v);
        }
        let k = v.unwrap_or(0.0);
        if !(k.fract() == 0.0 && (0.0..=200.0).contains(&k)) {
            return Err(MErr { number: 119, message: format!("#3000 = {k}: a user alarm number is 0–200 (alarm 3000–3200)") });
        }
        let msg = text.split_once('(').and_then(|(_, r)| r.split_once(')')).map_or("", |(m, _)| m.trim());
        let msg = if msg.is_empty() { "user alarm from the program (#3000; no message in parentheses)" } else { msg };
        Err(MErr { number: USER_ALARM_VAR + k as u32, message: msg.to_string() })
    }

    /// Execute the block `bytes` of line `i` of source `si`.
    fn exec_line(&mut self, si: usize, i: Loc, bytes: &[u8]) -> Result<(), Alarm> {
        let file = self.sources[si].file.clone();
        let line_no = i.line + 1;
        // Plain NC words (CAM output): decoded straight from the bytes, nothing allocated
        // (the text is needed for an alarm only).
        if let Some(fb) = parse::fast_words(bytes, &mut self.fast_ev) {
            let text = || String::from_utf8_lossy(bytes);
            if fb.len == 0 {
                return Ok(());
            }
            let mut d = self.dec.take().unwrap_or_default();
            let r = match d.decode(&self.fast_ev[..fb.len], self.has_y, self.has_c) {
                Err((n, col, m)) => Err(Alarm::new(n, m).at(SrcPos::new(file, line_no, col)).with_block(text().trim_end())),
                Ok(()) => {
                    let src = SrcPos::new(file, line_no, fb.col);
                    self.exec(&d.d, &src).map_err(|(n, col, m)| {
                        Alarm::new(n, m).at(SrcPos { col: col.unwrap_or(fb.col), ..src.clone() }).with_block(text().trim_end())
                    })
                }
            };
            self.dec = Some(d);
            return r;
        }
        let Ok(text) = std::str::from_utf8(bytes) else {
            return Err(Alarm::new(76, "the program file changed while it runs: this line is not UTF-8 text").at(SrcPos::new(file, line_no, 1)));
        };
        let b: Block = parse::parse_line(text).map_err(|e| perr_alarm(&file, i.line as usize, text, e))?;
        if b.skip && self.block_skip {
            return Ok(());
        }
        let src = SrcPos::new(file.clone(), line_no, b.col);
        let wrap = |e: MErr, col: u32| Alarm::new(e.number, e.message).at(SrcPos::new(file.clone(), line_no, col)).with_block(text.trim_end());
        match b.stmt {
            Stmt::Empty | Stmt::Percent => {}
            Stmt::Program(_) => {
                // Reaching the next program's O line ends the current program.
                self.line = i;
                if self.stack.is_empty() {
                    self.ended = true;
                } else {
                    self.ret(None).map_err(|e| wrap(e, b.col))?;
                }
            }
            Stmt::Assign { var, value } => {
                let n = self.vars.target(&var).map_err(|e| wrap(e, b.col))?;
                let v = self.vars.eval(&value).map_err(|e| wrap(e, b.col))?;
                self.assign(n, v, text).map_err(|e| wrap(e, b.col))?;
            }
            Stmt::IfThen { cond, var, value } => {
                if truth(self.vars.eval(&cond).map_err(|e| wrap(e, b.col))?) {
                    let n = self.vars.target(&var).map_err(|e| wrap(e, b.col))?;
                    let v = self.vars.eval(&value).map_err(|e| wrap(e, b.col))?;
                    self.assign(n, v, text).map_err(|e| wrap(e, b.col))?;
                }
            }
            Stmt::IfGoto { cond, target } => {
                if truth(self.vars.eval(&cond).map_err(|e| wrap(e, b.col))?) {
                    self.goto(&target).map_err(|e| wrap(e, b.col))?;
                }
            }
            Stmt::Goto(target) => self.goto(&target).map_err(|e| wrap(e, b.col))?,
            Stmt::Do { cond, .. } => {
                let go = match cond {
                    Some(c) => truth(self.vars.eval(&c).map_err(|e| wrap(e, b.col))?),
                    None => true,
                };
                if !go {
                    match self.do_end.get(&(si, i.off)) {
                        Some(&e) => self.line = e,
                        None => return Err(wrap(MErr { number: 124, message: "DO without END".into() }, b.col)),
                    }
                }
            }
            Stmt::End(_) => match self.end_do.get(&(si, i.off)) {
                Some(&d) => self.line = d,
                None => return Err(wrap(MErr { number: 126, message: "END without DO".into() }, b.col)),
            },
            Stmt::Call { mcall, name, args, cols } => {
                let mut vals = Vec::with_capacity(args.len());
                for a in &args {
                    vals.push(match a {
                        Some(e) => self.vars.eval(e).map_err(|e| wrap(e, b.col))?,
                        None => None,
                    });
                }
                self.siemens_stmt(mcall, name.as_deref(), &vals, &cols, &src).map_err(|(n, col, m)| {
                    Alarm::new(n, m).at(SrcPos::new(file.clone(), line_no, col.unwrap_or(b.col))).with_block(text.trim_end())
                })?;
            }
            Stmt::Nc(words) => {
                let d = self.decode_words(&words, &self.vars).map_err(|a| {
                    let col = a_col(&a);
                    a.at(SrcPos::new(file.clone(), line_no, col)).with_block(text.trim_end())
                })?;
                self.exec(&d, &src).map_err(|(n, col, m)| {
                    Alarm::new(n, m).at(SrcPos::new(file.clone(), line_no, col.unwrap_or(b.col))).with_block(text.trim_end())
                })?;
            }
        }
        Ok(())
    }

    fn goto(&mut self, target: &Expr) -> Result<(), MErr> {
        let v = self.vars.eval(target)?.unwrap_or(0.0);
        let n = v.round();
        if !(1.0..=99999.0).contains(&n) {
            return Err(MErr { number: 128, message: format!("GOTO {v}: the sequence number must be 1–99999") });
        }
        match self.labels.get(&(self.prog, n as u32)) {
            Some(&l) => {
                self.line = l;
                Ok(())
            }
            None => Err(MErr { number: 78, message: format!("GOTO {n}: there is no block N{n} in this program") }),
        }
    }

    /// Return from a subprogram (M99 [P]).
    fn ret(&mut self, p: Option<u32>) -> Result<(), MErr> {
        let Some(top) = self.stack.last_mut() else {
            // M99 in the main program: repeat it from the start (manual §3.1.7; P ignored).
            self.line = self.progs[self.prog].start;
            return Ok(());
        };
        if top.repeats > 1 {
            top.repeats -= 1;
            self.line = self.progs[self.prog].start;
            return Ok(());
        }
        let f = self.stack.pop().expect("checked above");
        if f.macro_call {
            self.vars.locals.pop();
        }
        self.prog = f.prog;
        self.line = f.line;
        if let Some(n) = p {
            match self.labels.get(&(self.prog, n)) {
                Some(&l) => self.line = l,
                None => return Err(MErr { number: 78, message: format!("M99 P{n}: no block N{n} in the calling program") }),
            }
        }
        Ok(())
    }

    /// Call program O`number` `repeats` times; `Ok(true)` when a frame was pushed.
    fn call(&mut self, number: u32, repeats: u32, macro_call: bool, col: u32) -> Result<bool, (u32, Option<u32>, String)> {
        let mut errors = Vec::new();
        let p = self.find_program(number, &mut errors).map_err(|m| (76, Some(col), m))?;
        if let Some(e) = errors.first() {
            return Err((76, Some(col), format!("program O{number:04} has errors: {e}")));
        }
        if p == self.prog {
            return Err((76, Some(col), format!("O{number:04} cannot call itself (manual §3.1.6 note 3)")));
        }
        if self.stack.len() >= MAX_NESTING {
            return Err((77, Some(col), format!("subprogram/macro calls nest deeper than {MAX_NESTING} levels")));
        }
        if repeats == 0 {
            return Ok(false);
        }
        self.stack.push(Frame { prog: self.prog, line: self.line, repeats, macro_call });
        self.prog = p;
        self.line = self.progs[p].start;
        Ok(true)
    }

    fn offset(&self) -> Pos {
        self.wcs_table[self.st.wcs].add(self.shift).add(self.local).add(self.tool_applied)
    }

    /// T code: select tool □□ and offset △△ (T0101). The shift is taken up by each axis with
    /// its next move ([`Interpreter::take_up_tool_offset`]).
    fn select_tool(&mut self, t: Val) -> Result<(), (u32, Option<u32>, String)> {
        if t.v < 0.0 || t.v > 9999.0 || t.v.fract() != 0.0 {
            return Err((3, Some(t.col), format!("T{}: a T code is T□□△△ (tool, offset), 0–9999", t.v)));
        }
        let v = t.v as u32;
        let (tool, off) = (v / 100, v % 100);
        let geo = if self.geo_by_tool && off != 0 { tool } else { off };
        let shift = self.tool_table.shift(geo, off).ok_or_else(|| {
            let n = if self.tool_table.get(geo).is_none() { geo } else { off };
            (tools::ILLEGAL_OFFSET_ALARM, Some(t.col), format!("T{v:04}: offset number {n} is not in the tool table"))
        })?;
        let o = self.tool_table.get(off).copied().unwrap_or_default();
        self.tool = ActiveTool { tool, offset: off, nose_radius: o.r, tip: o.tip };
        self.tool_shift = shift;
        Ok(())
    }

    /// Before a block that moves the axes: the axes it programs take up the selected tool
    /// offset (Fanuc LWM = 1). Absolute words then land on the offset position through
    /// [`Interpreter::offset`], incremental words through `tool_delta`. A canned cycle that
    /// computes its points with [`Interpreter::target`] calls this first.
    fn take_up_tool_offset(&mut self, d: &Decoded) {
        self.tool_delta = Pos::ZERO;
        if d.has('X') || d.has('U') {
            self.tool_delta.x = self.tool_shift.x - self.tool_applied.x;
            self.tool_applied.x = self.tool_shift.x;
        }
        if d.has('Z') || d.has('W') {
            self.tool_delta.z = self.tool_shift.z - self.tool_applied.z;
            self.tool_applied.z = self.tool_shift.z;
        }
    }

    fn push(&mut self, src: &SrcPos, kind: MoveKind, exact_stop: bool) {
        let m = Move { src: src.clone(), kind, exact_stop, work_offset: self.offset(), tag: None };
        if self.corner.is_some() {
            self.held.push(m);
        } else {
            self.queue.push_back(m);
        }
    }

    /// Emit a G01/G02/G03 move starting at `start`: completes a pending chamfer/corner R,
    /// and holds this move back if it carries `,C`/`,R` itself.
    fn emit_path(
        &mut self,
        src: &SrcPos,
        start: Pos,
        kind: MoveKind,
        exact: bool,
        req: Option<(bool, f64)>,
    ) -> Result<(), (u32, Option<u32>, String)> {
        let mut start = start;
        if let Some(c) = self.corner.take() {
            let plane = c.plane;
            let seg1 = seg_of(plane, c.start, &c.kind);
            let seg2 = seg_of(plane, start, &kind);
            let cut = if c.chamfer { corner::chamfer(&seg1, &seg2, c.value) } else { corner::round(&seg1, &seg2, c.value) };
            let cut = cut.map_err(|m| (55, None, format!("{} {}: {m}", if c.chamfer { ",C" } else { ",R" }, c.value)))?;
            let mut k1 = c.kind.clone();
            let mut ins = None;
            if let Some(cut) = cut {
                let p1 = from_uv(plane, start, cut.p1);
                let p2 = from_uv(plane, start, cut.p2);
                let feed = match &c.kind {
                    MoveKind::Feed { feed, .. } | MoveKind::Arc { feed, .. } => *feed,
                    _ => Feed::PerMin(0.0),
                };
                match &mut k1 {
                    MoveKind::Feed { end, .. } | MoveKind::Arc { end, .. } => *end = p1,
                    _ => {}
                }
                ins = Some(match cut.arc {
                    None => MoveKind::Feed { end: p2, feed },
                    Some((o, cw)) => MoveKind::Arc { end: p2, center: from_uv(plane, start, o), cw, plane, feed },
                });
                start = p2;
            }
            let _ = start;
            let mk = |kind| Move { src: c.src.clone(), kind, exact_stop: c.exact, work_offset: c.offset, tag: None };
            self.queue.push_back(mk(k1));
            if let Some(k) = ins {
                self.queue.push_back(mk(k));
            }
            self.queue.extend(self.held.drain(..));
        }
        match req {
            Some((chamfer, value)) => {
                self.corner_serial += 1;
                self.corner = Some(Corner {
                    serial: self.corner_serial,
                    src: src.clone(),
                    start,
                    kind,
                    exact,
                    offset: self.offset(),
                    plane: self.st.plane,
                    chamfer,
                    value,
                    g04: false,
                });
            }
            None => self.push(src, kind, exact),
        }
        Ok(())
    }

    /// 004 §2.23 note 8: `,C`/`,R` in a thread cutting block (G32, G34, G92, G76, G78) is an
    /// alarm, not ignored as in other non-G01/G02/G03 blocks (note 1). The manual gives no
    /// number; Fanuc's is PS0050 (chamfer/corner R commanded in a thread block).
    fn no_corner_in_thread(d: &Decoded, g: GCode) -> Result<(), (u32, Option<u32>, String)> {
        match d.comma_c.or(d.comma_r) {
            Some(v) => Err((
                50,
                Some(v.col),
                format!("{}: a chamfer or corner R (,C/,R) cannot be commanded in a thread cutting block (004 §2.23 note 8); remove it or cut the chamfer with G01", gcode::gname(g)),
            )),
            None => Ok(()),
        }
    }

    /// `,C` / `,R` of the block (the last one written wins, §2.23 note 9).
    fn corner_req(&self, d: &Decoded) -> Option<(bool, f64)> {
        match (d.comma_c, d.comma_r) {
            (Some(c), Some(r)) => Some(if c.col > r.col { (true, self.len(c)) } else { (false, self.len(r)) }),
            (Some(c), None) => Some((true, self.len(c))),
            (None, Some(r)) => Some((false, self.len(r))),
            (None, None) => None,
        }
    }

    /// Length scale of a word: inch → mm, and the least input increment without a decimal
    /// point when No.3401#0 = 0.
    fn len(&self, v: Val) -> f64 {
        if !self.calculator && !v.decimal {
            self.increment_len(v)
        } else {
            v.v * self.unit_mm()
        }
    }

    /// mm per program unit (25.4 under G20).
    fn unit_mm(&self) -> f64 {
        if self.st.inch {
            25.4
        } else {
            1.0
        }
    }

    /// A word written without a decimal point in least input increments (0.001 mm, 0.0001 inch)
    /// whatever No.3401#0 says: Fanuc's rule for the addresses that take no decimal point, such
    /// as G74/G75 P(Δi)/Q(Δk). With a decimal point the value is in mm (inch).
    fn increment_len(&self, v: Val) -> f64 {
        if v.decimal {
            return v.v * self.unit_mm();
        }
        let inc = if self.st.inch { 0.0001 } else { 0.001 };
        v.v * inc * self.unit_mm()
    }

    /// Target of the axis words in machine coordinates; `None` when no axis word is given.
    fn target(&self, d: &Decoded) -> Option<Pos> {
        let off = self.offset();
        let work = self.pos.sub(off);
        let mut t = work;
        let mut any = false;
        let mut axis = |abs: char, inc: char, cur: f64, scale: f64, angle: bool, out: &mut f64| {
            let conv = |v: Val| if angle { v.v } else { self.len(v) * scale };
            if let Some(v) = d.get(abs) {
                *out = conv(v);
                any = true;
            } else if let Some(v) = d.get(inc) {
                *out = cur + conv(v);
                any = true;
            }
        };
        // An incremental word of the block that takes up a new tool offset moves by it too.
        axis('X', 'U', work.x + self.tool_delta.x, 0.5, false, &mut t.x);
        axis('Z', 'W', work.z + self.tool_delta.z, 1.0, false, &mut t.z);
        if self.has_y {
            axis('Y', 'V', work.y, 1.0, false, &mut t.y);
        }
        if self.has_c {
            axis('C', 'H', work.c, 1.0, true, &mut t.c);
        }
        any.then(|| t.add(off))
    }

    fn feed(&self, col: Option<u32>) -> Result<Feed, (u32, Option<u32>, String)> {
        let f = if self.st.per_rev { self.st.f_rev.map(Feed::PerRev) } else { self.st.f_min.map(Feed::PerMin) };
        match f {
            Some(Feed::PerRev(v) | Feed::PerMin(v)) if v > 0.0 => Ok(f.expect("matched Some")),
            Some(_) => Err((11, col, "feed rate F is zero; program F before a cutting move".into())),
            None => Err((
                11,
                col,
                format!(
                    "no feed rate commanded: program F ({}) before the first cutting move",
                    if self.st.per_rev { "mm/rev under G99" } else { "mm/min under G98" }
                ),
            )),
        }
    }

    fn spindle_cmd(&self, dir: SpindleDir) -> SpindleCmd {
        let css = if self.st.css { Some(self.st.css_v.unwrap_or(0.0)) } else { None };
        let rpm = match css {
            Some(v) => self.css_rpm(v),
            None => self.st.rpm,
        };
        SpindleCmd { dir, rpm, css, max_rpm: self.st.max_rpm }
    }

    /// Spindle speed that surface speed `v` (m/min) gives at the current X, clamped to G50 S.
    fn css_rpm(&self, v: f64) -> f64 {
        let d = 2.0 * (self.pos.x - self.offset().x).abs();
        let max = self.st.max_rpm.unwrap_or(f64::INFINITY);
        if d < 1e-9 {
            return if max.is_finite() { max } else { 0.0 };
        }
        (v * 1000.0 / (std::f64::consts::PI * d)).min(max)
    }

    /// Execute a decoded NC block: modal changes, then S/T/M before the motion, the motion,
    /// then M05/M09/M00/M01/M02/M30. The manual leaves the order of M codes and motion in one
    /// block to the machine (PMC); we start things (spindle, coolant, tool) before the motion
    /// and stop them after it, as a Fanuc ladder usually does.
    fn exec(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), (u32, Option<u32>, String)> {
        let before = self.corner.as_ref().map(|c| (c.serial, c.g04));
        if before.is_some() {
            if let Some(g) = d.group(16) {
                let col = d.g.iter().find(|x| x.0 == g).map(|x| x.1);
                return Err((51, col, "plane selection (G17/G18/G19) right after a block with ,C/,R".into()));
            }
            if let Some(g) = d.group(0).filter(|g| *g != 40) {
                let col = d.g.iter().find(|x| x.0 == g).map(|x| x.1);
                return Err((51, col, format!("{} cannot follow a block with ,C/,R (only G01/G02/G03, or one G04)", gcode::gname(g))));
            }
        }
        self.exec_block(d, src)?;
        if let Some((serial, g04)) = before {
            if let Some(c) = self.corner.as_mut().filter(|c| c.serial == serial) {
                if d.group(0) == Some(40) && !g04 {
                    c.g04 = true;
                } else {
                    return Err((
                        51,
                        None,
                        "no move after a block with ,C/,R: the next block must be a G01/G02/G03 move (one G04 may come between)".into(),
                    ));
                }
            }
        }
        Ok(())
    }

    /// G20/G21 (004 §2.9 note 2): a code that *switches* the unit must come at the start of
    /// the program (before any block with other words) and alone in its block; a code that
    /// switches nothing is accepted anywhere, alone or not (the `G21 G40 G99` header CAM
    /// post-processors write). A switch elsewhere is PS0010, as Fanuc refuses it.
    fn unit_block(&mut self, d: &Decoded) -> Result<(), (u32, Option<u32>, String)> {
        let only_unit = d.g.len() == 1 && d.group(6).is_some() && d.letters().next().is_none() && d.m.is_empty();
        if let Some(g) = d.group(6) {
            let inch = g == 200;
            if inch != self.st.inch {
                let col = d.g.iter().find(|x| x.0 == g).map(|x| x.1);
                let (from, to) = if inch { ("mm", "inch") } else { ("inch", "mm") };
                if self.unit_fixed {
                    return Err((10, col, format!("{} switches the unit from {from} to {to} in the middle of the program: a unit switch must be the first block of the program (004 §2.9 note 2)", gcode::gname(g))));
                }
                if !only_unit {
                    return Err((
                        10,
                        col,
                        format!("{} switches the unit from {from} to {to}: it must be alone in its block (004 §2.9 note 2)", gcode::gname(g)),
                    ));
                }
                self.st.inch = inch;
            }
        }
        if !only_unit && (!d.g.is_empty() || d.letters().next().is_some() || !d.m.is_empty()) {
            self.unit_fixed = true;
        }
        Ok(())
    }

    /// Runs one decoded block. Order of effects (as LinuxCNC's `execute_block` documents
    /// its own); every step sees the state the steps before it left:
    /// 1. block start: tool-offset delta cleared, cycle block state;
    /// 2. modal groups ([`Self::modal_groups`]): unit (G20/G21), plane, feed mode, work
    ///    system G54–G59, G61/G64 (from the next block), G96/G97, motion group, G40–G42;
    /// 3. special modes (polar, polygon) and G22/G23 (a G22 block ends here);
    /// 4. F, then S (after the rigid tapping S is taken; G50 S = maximum speed);
    /// 5. M codes before motion: spindle M03/M04 and aux M codes pushed, M00/M01/M02/M30,
    ///    M05, M09 kept for after the motion; a changed spindle speed re-sent;
    /// 6. T (tool selection, then the T code to the turret);
    /// 7. drilling cycle modal state (G80–G89);
    /// 8. one-shot group 00 (G04, G50, G52, G53, G28/G30, G65, G70–G78) or the motion
    ///    ([`Self::one_shot_or_motion`]); G65 ends the block here;
    /// 9. the M codes kept in 5 (an M02/M30 ends the program here);
    /// 10. subprogram call / return and M91/M92 jumps last (§3.1.6).
    fn exec_block(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), (u32, Option<u32>, String)> {
        self.tool_delta = Pos::ZERO;
        self.cycle_block_start(d);
        let (exact_mode, was_css) = self.modal_groups(d)?;
        self.special_modes(d, src)?;
        if self.stroke_block(d, src)? {
            return Ok(());
        }
        self.feed_word(d)?;
        let spindle_changed = self.spindle_word(d, src, was_css)?;
        let after = self.m_codes_before_motion(d, src, spindle_changed);
        self.tool_word(d, src)?;
        let exact = exact_mode || d.has_g(gcode::G_EXACT_STOP);
        self.drill_modal(d, src)?;
        if !self.one_shot_or_motion(d, src, exact)? {
            return Ok(());
        }
        if self.m_codes_after_motion(after, src) {
            return Ok(());
        }
        self.program_flow_m_codes(d)
    }

    /// Step 2 of [`Self::exec_block`]: the modal groups. Returns the G61/G64 mode in force
    /// for this block and whether G96 was on before it.
    fn modal_groups(&mut self, d: &Decoded) -> Result<(bool, bool), (u32, Option<u32>, String)> {
        self.unit_block(d)?;
        if let Some(g) = d.group(16) {
            self.st.plane = match g {
                gcode::G_PLANE_XY => Plane::Xy,
                gcode::G_PLANE_YZ => Plane::Yz,
                _ => Plane::Zx,
            };
        }
        if let Some(g) = d.group(5) {
            self.st.per_rev = g == gcode::G_PER_REV;
        }
        if let Some(g) = d.group(14) {
            self.st.wcs = ((g - gcode::G_WCS_FIRST) / 10) as usize;
        }
        // §2.14 item 5: G61/G64 take effect from the next block.
        let exact_mode = self.st.exact;
        if let Some(g) = d.group(15) {
            self.st.exact = g == gcode::G_EXACT_MODE;
        }
        let was_css = self.st.css;
        if let Some(g) = d.group(2) {
            if g == gcode::G_CONST_RPM && was_css && !d.has('S') {
                // §2.19 note 3: G97 without S keeps the last G96 speed.
                self.st.rpm = self.css_rpm(self.st.css_v.unwrap_or(0.0)).round();
            }
            self.st.css = g == gcode::G_CSS;
        }
        if let Some(g) = d.group(1) {
            self.st.motion = g;
        }
        if let Some(g) = d.group(7) {
            let side = match g {
                gcode::G_NRC_LEFT => Some(nosecomp::Side::Left),
                gcode::G_NRC_RIGHT => Some(nosecomp::Side::Right),
                _ => None,
            };
            let (r, tip) = (self.tool.nose_radius, self.tool.tip);
            // Tips 1–8 are for G18; in the polar plane the nose centre is offset (tip 0).
            let tip = if self.polar_active() { 0 } else { tip };
            let at = self.nrc.fed() + self.queue.len() as u64;
            self.nrc.set_mode(side, r, tip, self.st.plane, at).map_err(|(n, m)| (n, gcol(d, g), m))?;
        }
        Ok((exact_mode, was_css))
    }

    /// Step 4 of [`Self::exec_block`]: the F word, in mm (per minute or per revolution).
    fn feed_word(&mut self, d: &Decoded) -> Result<(), (u32, Option<u32>, String)> {
        if let Some(f) = d.get('F') {
            // G92.1: a negative F is a left-hand lead (manual 001), not a feed rate.
            if f.v < 0.0 && self.st.motion != gcode::G_RIGID_THREAD {
                return Err((6, Some(f.col), "F cannot be negative".into()));
            }
            let v = if self.st.inch { f.v * 25.4 } else { f.v }.abs();
            if self.st.per_rev {
                self.st.f_rev = Some(v);
            } else {
                self.st.f_min = Some(v);
            }
        }
        Ok(())
    }

    /// Step 4 of [`Self::exec_block`]: the S word (G50 S = maximum spindle speed); rigid
    /// tapping takes its own S (M29 S, G84 S). Returns whether the spindle command changed.
    fn spindle_word(&mut self, d: &Decoded, src: &SrcPos, was_css: bool) -> Result<bool, (u32, Option<u32>, String)> {
        let s_taken = self.tap_block_start(d, src)?;
        let mut spindle_changed = d.group(2).is_some() && self.st.css != was_css;
        if let Some(s) = d.get('S').filter(|_| !s_taken) {
            if s.v < 0.0 {
                return Err((6, Some(s.col), "S cannot be negative".into()));
            }
            if d.group(0) == Some(gcode::G_SET_COORD) {
                self.st.max_rpm = Some(s.v);
                spindle_changed |= self.st.css;
            } else if self.st.css {
                // Surface speed in m/min (ft/min under G20).
                self.st.css_v = Some(if self.st.inch { s.v * 0.3048 } else { s.v });
                spindle_changed = true;
            } else {
                self.st.rpm = s.v;
                spindle_changed = true;
            }
        }
        Ok(spindle_changed)
    }

    /// Step 5 of [`Self::exec_block`]: spindle and aux M codes before motion; returns the
    /// moves that go after the motion (stops, ends, M05, M09).
    fn m_codes_before_motion(&mut self, d: &Decoded, src: &SrcPos, spindle_changed: bool) -> Vec<MoveKind> {
        let mut after: Vec<MoveKind> = Vec::new();
        let mut started = false;
        // In a G83–G89 block the M code is the cycle's C-axis clamp code.
        let clamp_block = self.drill_clamp_block(d);
        for &(m, _) in d.m.iter().filter(|_| !clamp_block) {
            match m {
                3 | 4 => {
                    self.st.dir = if m == 3 { SpindleDir::Cw } else { SpindleDir::Ccw };
                    let c = self.spindle_cmd(self.st.dir);
                    self.push(src, MoveKind::Spindle(c), false);
                    started = true;
                }
                5 => {
                    self.st.dir = SpindleDir::Stop;
                    after.push(MoveKind::Spindle(self.spindle_cmd(SpindleDir::Stop)));
                }
                0 => after.push(MoveKind::Stop { optional: false }),
                1 => after.push(MoveKind::Stop { optional: true }),
                2 | 30 => after.push(MoveKind::End { code: m as u16 }),
                91 | 92 | 98 | 99 => {}
                // Coolant off after the motion, like M05.
                9 => after.push(MoveKind::Aux { letter: 'M', value: 9.0 }),
                _ => self.push(src, MoveKind::Aux { letter: 'M', value: m as f64 }, false),
            }
        }
        if spindle_changed && !started && self.st.dir != SpindleDir::Stop && !d.m.iter().any(|m| m.0 == 5) {
            let c = self.spindle_cmd(self.st.dir);
            self.push(src, MoveKind::Spindle(c), false);
        }
        after
    }

    /// Step 6 of [`Self::exec_block`]: the T word.
    fn tool_word(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), (u32, Option<u32>, String)> {
        if let Some(t) = d.get('T') {
            if self.nrc.active() {
                return Err((
                    nosecomp::T_ALARM,
                    Some(t.col),
                    "T code during tool nose radius compensation: cancel it with G40 before changing the tool (§2.18.4 note 3)".into(),
                ));
            }
            self.select_tool(t)?;
            // The turret still sees the T code.
            self.push(src, MoveKind::Aux { letter: 'T', value: t.v }, false);
        }
        Ok(())
    }

    /// Step 8 of [`Self::exec_block`]: the one-shot (group 00) code, or else the motion of
    /// the block. Returns false when the block ends here (G65).
    fn one_shot_or_motion(&mut self, d: &Decoded, src: &SrcPos, exact: bool) -> Result<bool, (u32, Option<u32>, String)> {
        let one_shot = d.group(0);
        match one_shot {
            Some(gcode::G_DWELL) => self.g04(d, src)?,
            Some(gcode::G_SET_COORD) => {
                // G50 IP: set the current position's workpiece coordinates (§2.12.1). G50 S
                // alone only sets the maximum spindle speed.
                if self.target(d).is_some() {
                    // The commanded axes take up the tool offset first, so that the current
                    // position reads the G50 values with the offset in force.
                    self.take_up_tool_offset(d);
                    self.tool_delta = Pos::ZERO;
                    self.g50(d);
                }
            }
            Some(gcode::G_LOCAL_COORD) => self.g52(d),
            Some(gcode::G_MACHINE_COORD) => self.g53(d, src)?,
            Some(gcode::G_REF_RETURN_2) if d.get('P').is_some_and(|p| p.v == 99.0) => self.g30_p99(d, src, gcol(d, gcode::G_REF_RETURN_2))?,
            Some(gcode::G_REF_RETURN) | Some(gcode::G_REF_RETURN_2) => {
                self.reference_return(d, src, one_shot == Some(gcode::G_REF_RETURN_2), gcol(d, gcode::G_REF_RETURN_2))?
            }
            Some(gcode::G_EXACT_STOP) | None => {
                self.take_up_tool_offset(d);
                if self.drill_active(d) {
                    self.drill_block(d, src)?
                } else {
                    self.motion(d, src, exact)?;
                    // MCALL: the SINUMERIK modal cycle after a positioning block.
                    self.mcall_after(self.target(d).is_some(), src)?
                }
            }
            Some(gcode::G_MACRO_CALL) => {
                self.g65(d)?;
                return Ok(false);
            }
            Some(
                g @ (gcode::G_FINISHING
                | gcode::G_STOCK_TURNING
                | gcode::G_STOCK_FACING
                | gcode::G_PATTERN_REPEAT
                | gcode::G_FACE_GROOVING
                | gcode::G_OD_GROOVING
                | gcode::G_THREAD_MULTI
                | gcode::G_THREAD_MULTI_ENH),
            ) => {
                if matches!(g, gcode::G_THREAD_MULTI | gcode::G_THREAD_MULTI_ENH) {
                    Self::no_corner_in_thread(d, g)?;
                }
                self.cycle_oneshot(g, d, src)?
            }
            Some(g) => {
                return Err((10, gcol(d, g), format!("{} is not supported yet", gcode::gname(g))));
            }
        }
        Ok(true)
    }

    /// G04: §2.6: P in ms (no decimal point), X/U in seconds; none or zero = exact stop.
    fn g04(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), (u32, Option<u32>, String)> {
        let secs = if let Some(p) = d.get('P') {
            p.v / 1000.0
        } else if let Some(x) = d.get('X').or(d.get('U')) {
            if !self.calculator && !x.decimal {
                x.v / 1000.0
            } else {
                x.v
            }
        } else {
            0.0
        };
        if secs < 0.0 {
            return Err((6, gcol(d, gcode::G_DWELL), "G04: the dwell time cannot be negative".into()));
        }
        self.push(src, MoveKind::Dwell { seconds: secs }, true);
        Ok(())
    }

    /// G52: local coordinate system origin in workpiece coordinates; U/W are the same
    /// origin written incrementally from the workpiece zero (G52 U0 W0 cancels).
    fn g52(&mut self, d: &Decoded) {
        let mut l = self.local;
        for (a, u, scale, out) in [('X', 'U', 0.5, &mut l.x as &mut f64), ('Z', 'W', 1.0, &mut l.z)] {
            if let Some(v) = d.get(a).or(d.get(u)) {
                *out = self.len(v) * scale;
            }
        }
        self.local = l;
        // §2.12.3 note 2: G52 cancels the nose radius offset for a moment.
        let at = self.nrc.fed() + self.queue.len() as u64;
        self.nrc.suspend(at);
    }

    /// G53: rapid to machine coordinates, absolute words only.
    fn g53(&mut self, d: &Decoded, src: &SrcPos) -> Result<(), (u32, Option<u32>, String)> {
        if let Some(u) = d.letters().find(|l| matches!(l, 'U' | 'W' | 'V' | 'H')) {
            return Err((9, d.get(u).map(|v| v.col), format!("G53 takes absolute coordinates only, not {u}")));
        }
        let mut t = self.pos;
        if let Some(v) = d.get('X') {
            t.x = self.len(v) * 0.5;
        }
        if let Some(v) = d.get('Z') {
            t.z = self.len(v);
        }
        if let Some(v) = d.get('Y') {
            t.y = self.len(v);
        }
        if let Some(v) = d.get('C') {
            t.c = v.v;
        }
        if t != self.pos {
            self.pos = t;
            self.push(src, MoveKind::Rapid { end: t }, true);
        }
        Ok(())
    }

    /// G65 P L: macro call with argument specification I (Fanuc): A→#1 B→#2 C→#3 I→#4 J→#5
    /// K→#6 D→#7 E→#8 F→#9 H→#11 M→#13 Q→#17 R→#18 S→#19 T→#20 U→#21 V→#22 W→#23 X→#24
    /// Y→#25 Z→#26.
    fn g65(&mut self, d: &Decoded) -> Result<(), (u32, Option<u32>, String)> {
        let p = d.get('P').ok_or((9, gcol(d, gcode::G_MACRO_CALL), "G65 needs P (the macro program number)".to_string()))?;
        let l = d.get('L').map(|l| l.v as u32).unwrap_or(1);
        let mut locals = HashMap::new();
        for (l, n) in [
            ('A', 1),
            ('B', 2),
            ('C', 3),
            ('I', 4),
            ('J', 5),
            ('K', 6),
            ('D', 7),
            ('E', 8),
            ('F', 9),
            ('H', 11),
            ('Q', 17),
            ('R', 18),
            ('S', 19),
            ('T', 20),
            ('U', 21),
            ('V', 22),
            ('W', 23),
            ('X', 24),
            ('Y', 25),
            ('Z', 26),
        ] {
            if let Some(v) = d.get(l) {
                locals.insert(n, v.v);
            }
        }
        if let Some(&(m, _)) = d.m.first() {
            locals.insert(13, m as f64);
        }
        if self.call(p.v.round() as u32, l, true, p.col)? {
            self.vars.locals.push(locals);
        }
        Ok(())
    }

    /// Step 9 of [`Self::exec_block`]: the M codes kept for after the motion. Returns true
    /// when the program ended (M02/M30).
    fn m_codes_after_motion(&mut self, after: Vec<MoveKind>, src: &SrcPos) -> bool {
        for k in after {
            let exact = matches!(k, MoveKind::Stop { .. } | MoveKind::End { .. });
            let is_end = matches!(k, MoveKind::End { .. });
            self.push(src, k, exact);
            if is_end {
                self.ended = true;
                return true;
            }
        }
        false
    }

    /// Step 10 of [`Self::exec_block`]: subprogram call / return last, the block's other
    /// codes run first (§3.1.6); M91/M92 jumps likewise.
    fn program_flow_m_codes(&mut self, d: &Decoded) -> Result<(), (u32, Option<u32>, String)> {
        for &(m, col) in &d.m {
            if m == 98 {
                let p = d.get('P').ok_or((9, Some(col), "M98 needs P (the subprogram number)".to_string()))?;
                let pv = p.v.round() as u64;
                // Packed P: last four digits = program, leading digits = repeat count.
                let (count, prog) = if pv > 9999 { ((pv / 10000) as u32, (pv % 10000) as u32) } else { (1, pv as u32) };
                let l = d.get('L').map(|l| l.v.round() as u32).unwrap_or(count);
                self.call(prog, l, false, p.col)?;
            } else if m == 99 {
                let p = d.get('P').map(|p| p.v.round() as u32);
                self.ret(p).map_err(|e| (e.number, Some(col), e.message))?;
            } else if m == 91 || m == 92 {
                self.input_jump(m, col, d)?;
            }
        }
        Ok(())
    }

    /// M91/M92 P: jump to block N`P` of the current program when the input signal is 0
    /// (M91) or 1 (M92), else go on with the next block (manual §3.1.5). Runs after the
    /// block's other codes, like M98. The signal is read when the block is interpreted; a
    /// caller that plans ahead of the machine must stop reading ahead at an M91/M92 block.
    fn input_jump(&mut self, m: u32, col: u32, d: &Decoded) -> Result<(), (u32, Option<u32>, String)> {
        let p = d.get('P').ok_or((9, Some(col), format!("M{m} needs P (the sequence number to jump to)")))?;
        let n = p.v.round();
        if !(1.0..=99999.0).contains(&n) {
            return Err((128, Some(p.col), format!("M{m} P{}: the sequence number must be 1–99999 (note 1)", p.v)));
        }
        let signal = self.input.as_mut().map(|f| f(m as u16)).unwrap_or(false);
        if signal == (m == 92) {
            match self.labels.get(&(self.prog, n as u32)) {
                Some(&l) => self.line = l,
                None => return Err((78, Some(p.col), format!("M{m} P{n}: there is no block N{n} in this program"))),
            }
        }
        Ok(())
    }

    /// G28 / G30 P1–P4 (manual §2.11): rapid to the intermediate point of the programmed
    /// axes, then rapid on those axes to the reference point; axes not programmed stay.
    /// Reference point n is parameter No.1239+n (Fanuc No.1240–1243; the manual's note 1
    /// names the range No.1290–1328 without saying which is which), machine coordinates
    /// written per axis, X as a diameter: `1241 = { x = 200.0, z = 100.0 }`. No.1240 absent
    /// = machine zero (the manual: "参考点(机械零点)"); G30 P2–P4 whose parameter is absent
    /// is alarm 46. P other than 1–4 is alarm 46 (Fanuc PS0046 "illegal reference return
    /// command"); G30 without P is P2 (note 3).
    fn reference_return(&mut self, d: &Decoded, src: &SrcPos, g30: bool, col: Option<u32>) -> Result<(), (u32, Option<u32>, String)> {
        let k = if g30 {
            let p = d.get('P').map(|p| p.v).unwrap_or(2.0);
            if !matches!(p, 1.0 | 2.0 | 3.0 | 4.0) {
                return Err((46, d.get('P').map(|p| p.col).or(col), format!("G30 P{p}: the reference point is P1, P2, P3 or P4")));
            }
            p as usize - 1
        } else {
            0
        };
        let Some(refp) = self.ref_points[k] else {
            return Err((
                46,
                col,
                format!("G30 P{}: reference point {} is not configured (set parameter {} = {{ x = …, z = … }})", k + 1, k + 1, 1240 + k),
            ));
        };
        self.take_up_tool_offset(d);
        if let Some(mid) = self.target(d) {
            self.pos = mid;
            self.push(src, MoveKind::Rapid { end: mid }, true);
            let mut r = mid;
            for (a, u, out, v) in
                [('X', 'U', &mut r.x as &mut f64, refp.x), ('Z', 'W', &mut r.z, refp.z), ('Y', 'V', &mut r.y, refp.y), ('C', 'H', &mut r.c, refp.c)]
            {
                if d.has(a) || d.has(u) {
                    *out = v;
                }
            }
            self.pos = r;
            self.push(src, MoveKind::Rapid { end: r }, true);
        }
        Ok(())
    }

    fn g50(&mut self, d: &Decoded) {
        let work_now = self.pos.sub(self.offset());
        let set = |a: char, u: char, cur: f64, scale: f64, angle: bool| -> Option<f64> {
            let conv = |v: Val| if angle { v.v } else { self.len(v) * scale };
            d.get(a).map(conv).or_else(|| d.get(u).map(|v| cur + conv(v)))
        };
        let nx = set('X', 'U', work_now.x, 0.5, false);
        let nz = set('Z', 'W', work_now.z, 1.0, false);
        let ny = if self.has_y { set('Y', 'V', work_now.y, 1.0, false) } else { None };
        let nc = if self.has_c { set('C', 'H', work_now.c, 1.0, true) } else { None };
        // The commanded axes lose their local (G52) offset (§2.12.3 note 3) and the shift is
        // chosen so that the current position reads the new value.
        let wcs = self.wcs_table[self.st.wcs];
        macro_rules! apply {
            ($v:expr, $f:ident) => {
                if let Some(v) = $v {
                    self.local.$f = 0.0;
                    self.shift.$f = self.pos.$f - v - wcs.$f;
                }
            };
        }
        apply!(nx, x);
        apply!(nz, z);
        apply!(ny, y);
        apply!(nc, c);
    }

    /// Modal motion (group 01) with the block's axis words.
    fn motion(&mut self, d: &Decoded, src: &SrcPos, exact: bool) -> Result<(), (u32, Option<u32>, String)> {
        if self.polar_active() {
            return self.polar_motion(d, src, exact);
        }
        let Some(end) = self.target(d) else {
            return Ok(());
        };
        if self.corner.is_some() && !matches!(self.st.motion, 10 | 20 | 30) {
            return Err((
                52,
                d.g.first().map(|g| g.1),
                format!("{} after a block with ,C/,R: the next move must be G01/G02/G03", gcode::gname(self.st.motion)),
            ));
        }
        if matches!(self.st.motion, 320 | 340 | 920) {
            Self::no_corner_in_thread(d, self.st.motion)?;
        }
        match self.st.motion {
            0 => {
                self.pos = end;
                self.push(src, MoveKind::Rapid { end }, true);
            }
            10 => {
                let feed = self.feed(d.get('F').map(|f| f.col))?;
                let start = self.pos;
                self.pos = end;
                self.emit_path(src, start, MoveKind::Feed { end, feed }, exact, self.corner_req(d))?;
            }
            20 | 30 => self.arc(d, src, end, self.st.motion == 20, exact)?,
            21 | 31 | 22 | 32 => self.conic(d, src, end, exact)?,
            320 | 340 | 900 | 920 | 921 | 940 => self.cycle_modal(d, src, end, exact)?,
            g => return Err((10, None, format!("{} is not supported yet", gcode::gname(g)))),
        }
        Ok(())
    }

    /// G02.1/G03.1 ellipse (A, B, Q) and G02.2/G03.2 parabola (P, Q), emitted as a chain of
    /// Feed moves within [`CHORD_TOL`]. Q is the angle from +Z to the major axis / axis of
    /// symmetry, clockwise seen from +Y, in 0.001° without a decimal point (§2.4), degrees
    /// with one. ZX plane only (§2.5).
    fn conic(&mut self, d: &Decoded, src: &SrcPos, end: Pos, exact: bool) -> Result<(), (u32, Option<u32>, String)> {
        let g = self.st.motion;
        let gc = d.g.first().map(|x| x.1);
        if self.st.plane != Plane::Zx {
            return Err((10, gc, format!("{} works in the ZX plane only (G18)", gcode::gname(g))));
        }
        if let Some(l) = ['Y', 'V', 'C', 'H'].into_iter().find(|l| d.has(*l)) {
            return Err((21, d.get(l).map(|v| v.col), format!("address {l} is outside the ZX plane")));
        }
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let q = d.get('Q').map(|q| if q.decimal { q.v } else { q.v / 1000.0 }).unwrap_or(0.0);
        let phi = (-q).to_radians();
        let (s, e) = ((self.pos.z, self.pos.x), (end.z, end.x));
        let cw = g == 21 || g == 22;
        let need = |l: char| d.get(l).map(|v| self.len(v)).ok_or((9, gc, format!("{} needs {l}", gcode::gname(g))));
        let pts = if g == 21 || g == 31 {
            curves::ellipse(s, e, need('A')?, need('B')?, phi, cw, CHORD_TOL)
        } else {
            curves::parabola(s, e, need('P')?, phi, cw, CHORD_TOL)
        }
        .map_err(|m| (20, gc, m))?;
        let n = pts.len();
        for (i, (z, x)) in pts.into_iter().enumerate() {
            let p = Pos { x, z, ..end };
            self.pos = p;
            self.push(src, MoveKind::Feed { end: p, feed }, exact && i + 1 == n);
        }
        Ok(())
    }

    fn arc(&mut self, d: &Decoded, src: &SrcPos, end: Pos, cw: bool, exact: bool) -> Result<(), (u32, Option<u32>, String)> {
        let feed = self.feed(d.get('F').map(|f| f.col))?;
        let plane = self.st.plane;
        // In-plane coordinates (u, v) such that G03 is counter-clockwise in (u, v):
        // G18 (Z, X), G17 (X, Y), G19 (Y, Z). I/J/K are signed radius-valued distances.
        let (outside, ci, cj): (&[char], char, char) = match plane {
            Plane::Zx => (&['Y', 'V', 'J', 'C', 'H'], 'K', 'I'),
            Plane::Xy => (&['Z', 'W', 'K', 'C', 'H'], 'I', 'J'),
            Plane::Yz => (&['X', 'U', 'I', 'C', 'H'], 'J', 'K'),
        };
        if let Some(l) = outside.iter().find(|l| d.has(**l)) {
            return Err((
                21,
                d.get(*l).map(|v| v.col),
                format!("address {l} is outside the arc plane {plane:?} (select the plane with G17/G18/G19)"),
            ));
        }
        let uv = |p: Pos| match plane {
            Plane::Zx => (p.z, p.x),
            Plane::Xy => (p.x, p.y),
            Plane::Yz => (p.y, p.z),
        };
        let (su, sv) = uv(self.pos);
        let (eu, ev) = uv(end);
        let tol = self.arc_tol;
        let center = if let Some(r) = d.get('R') {
            // §2.3 note 4: R wins over I/J/K.
            let r = self.len(r);
            let (du, dv) = (eu - su, ev - sv);
            let chord = du.hypot(dv);
            if chord < 1e-9 {
                // §2.3 note 5: same start and end with R is a 0° arc: no motion.
                return Ok(());
            }
            let half = chord / 2.0;
            if half > r.abs() + tol {
                return Err((
                    20,
                    d.get('R').map(|v| v.col),
                    format!("R{:.4}: the end point is {:.4} mm away, more than the diameter", r.abs(), chord),
                ));
            }
            let h = (r * r - half * half).max(0.0).sqrt();
            // Left normal of the chord: centre side of a CCW arc ≤ 180°; CW and R<0 flip it.
            let (nu, nv) = (-dv / chord, du / chord);
            let side = if cw { -1.0 } else { 1.0 } * if r < 0.0 { -1.0 } else { 1.0 };
            let (cu, cv) = ((su + eu) / 2.0 + side * h * nu, (sv + ev) / 2.0 + side * h * nv);
            from_uv(plane, self.pos, (cu, cv))
        } else if d.has(ci) || d.has(cj) {
            let oi = d.get(ci).map(|v| self.len(v)).unwrap_or(0.0);
            let oj = d.get(cj).map(|v| self.len(v)).unwrap_or(0.0);
            if oi == 0.0 && oj == 0.0 {
                // §2.3 note 3: I = K = 0 is a straight line.
                let start = self.pos;
                self.pos = end;
                return self.emit_path(src, start, MoveKind::Feed { end, feed }, exact, self.corner_req(d));
            }
            let (cu, cv) = (su + oi, sv + oj);
            let rs = (su - cu).hypot(sv - cv);
            let re = (eu - cu).hypot(ev - cv);
            if (rs - re).abs() > tol {
                let col = d.get(ci).or(d.get(cj)).map(|v| v.col);
                return Err((
                    20,
                    col,
                    format!("the end point is not on the arc: start radius {rs:.4} mm, end radius {re:.4} mm (tolerance {tol} mm, No.3410)"),
                ));
            }
            from_uv(plane, self.pos, (cu, cv))
        } else if self.arc_missing_alarm {
            return Err((22, None, "circular interpolation needs R or I/K (the centre)".into()));
        } else {
            let start = self.pos;
            self.pos = end;
            return self.emit_path(src, start, MoveKind::Feed { end, feed }, exact, self.corner_req(d));
        };
        // The centre carries the start's coordinates on the axes outside the plane.
        let start = self.pos;
        self.pos = end;
        self.emit_path(src, start, MoveKind::Arc { end, center, cw, plane, feed }, exact, self.corner_req(d))
    }
}

/// Read a work offset table (the operator's offset page) from TOML text:
///
/// ```toml
/// [G54]
/// x = 0.0      # diameter, mm (as entered on the offset page)
/// z = -312.5
/// [G55]
/// z = -200.0
/// ```
/// Keys `x` (diameter), `z`, `y` (mm) and `c` (degrees); missing systems and keys are zero.
/// Returns the table in machine units (X as a radius) for [`Interpreter::set_work_offsets`].
/// Errors are configuration alarms (1000) naming the key.
pub fn parse_work_offsets(file: &str, text: &str) -> Result<[Pos; 6], Alarm> {
    let bad = |m: String| Alarm::new(crate::config::ConfigError::ALARM, format!("{file}: {m}"));
    let v: toml::Table = toml::from_str(text).map_err(|e| bad(e.to_string()))?;
    let mut out = [Pos::ZERO; 6];
    for (k, val) in &v {
        let i = match k.as_str() {
            "G54" => 0,
            "G55" => 1,
            "G56" => 2,
            "G57" => 3,
            "G58" => 4,
            "G59" => 5,
            _ => return Err(bad(format!("{k}: work offset tables have the sections G54 … G59"))),
        };
        let t = val.as_table().ok_or_else(|| bad(format!("{k}: must be a table like [{k}] x = 0.0 z = -300.0")))?;
        for (ax, n) in t {
            let x = match n {
                toml::Value::Float(f) => *f,
                toml::Value::Integer(i) => *i as f64,
                other => return Err(bad(format!("{k}.{ax}: must be a number, got {other}"))),
            };
            if !x.is_finite() {
                return Err(bad(format!("{k}.{ax}: must be finite")));
            }
            match ax.as_str() {
                "x" => out[i].x = x / 2.0,
                "z" => out[i].z = x,
                "y" => out[i].y = x,
                "c" => out[i].c = x,
                _ => return Err(bad(format!("{k}.{ax}: the axes are x (diameter), z, y, c"))),
            }
        }
    }
    Ok(out)
}

/// [`parse_work_offsets`] from a file.
pub fn load_work_offsets(path: &std::path::Path) -> Result<[Pos; 6], Alarm> {
    let text =
        std::fs::read_to_string(path).map_err(|e| Alarm::new(crate::config::ConfigError::ALARM, format!("{}: cannot read: {e}", path.display())))?;
    parse_work_offsets(&path.display().to_string(), &text)
}

impl Iterator for Interpreter {
    type Item = Result<Move, Alarm>;
    fn next(&mut self) -> Option<Self::Item> {
        self.next_move().transpose()
    }
}

/// Column stored temporarily in an alarm's message-less position: we use `pos` only after
/// the caller knows the line, so carry the column in a side channel.
fn col_alarm(number: u32, col: u32, message: String) -> Alarm {
    let mut a = Alarm::new(number, message);
    a.pos = Some(SrcPos::new(Arc::from(""), 0, col));
    a
}

fn a_col(a: &Alarm) -> u32 {
    a.pos.as_ref().map(|p| p.col).unwrap_or(1)
}

/// Plane coordinates (u, v) in which G03 is counter-clockwise: G18 (Z, X), G17 (X, Y),
/// G19 (Y, Z).
fn to_uv(plane: Plane, p: Pos) -> (f64, f64) {
    match plane {
        Plane::Zx => (p.z, p.x),
        Plane::Xy => (p.x, p.y),
        Plane::Yz => (p.y, p.z),
    }
}

fn from_uv(plane: Plane, base: Pos, (u, v): (f64, f64)) -> Pos {
    let mut p = base;
    match plane {
        Plane::Zx => {
            p.z = u;
            p.x = v
        }
        Plane::Xy => {
            p.x = u;
            p.y = v
        }
        Plane::Yz => {
            p.y = u;
            p.z = v
        }
    }
    p
}

fn seg_of(plane: Plane, start: Pos, k: &MoveKind) -> corner::Seg {
    let a = to_uv(plane, start);
    match k {
        MoveKind::Arc { end, center, cw, .. } => corner::Seg::Arc { a, b: to_uv(plane, *end), c: to_uv(plane, *center), cw: *cw },
        other => corner::Seg::Line { a, b: to_uv(plane, other.end().unwrap_or(start)) },
    }
}

/// Reference point `k` (0-based) from No.1240+k, machine coordinates with X as a radius.
fn ref_point(cfg: &MachineConfig, k: usize) -> Option<Pos> {
    let no = 1240 + k as u32;
    let any = ["x", "z", "y", "c"].iter().any(|a| cfg.param_axis(no, a).is_some());
    if !any {
        return (k == 0).then_some(Pos::ZERO);
    }
    let a = |n: &str| cfg.param_axis(no, n).filter(|v| v.is_finite()).unwrap_or(0.0);
    Some(Pos { x: a("x") / 2.0, z: a("z"), y: a("y"), c: a("c") })
}

fn has_decimal(e: &Expr) -> bool {
    match e {
        Expr::Num { decimal, .. } => *decimal,
        Expr::Neg(e) => has_decimal(e),
        _ => true,
    }
}

fn is_length(l: char, comma: bool) -> bool {
    comma || matches!(l, 'X' | 'Y' | 'Z' | 'U' | 'V' | 'W' | 'I' | 'J' | 'K' | 'R')
}

fn truth(v: macros::Value) -> bool {
    v.is_some_and(|x| x != 0.0)
}

#[cfg(test)]
mod tests;

/// The column of G code `g` in block `d` (for alarms).
fn gcol(d: &Decoded, g: GCode) -> Option<u32> {
    d.g.iter().find(|x| x.0 == g).map(|x| x.1)
}
