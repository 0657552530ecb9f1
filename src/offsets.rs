//! The operator's offset pages kept in the state directory: the tool offset table (geometry
//! X/Z, wear X/Z, nose radius, tip per offset number, docs/TOOL_TABLE.md) and the work
//! offsets G54–G59 with the external (common) work zero offset (manual 004 §2.12.2 note 2).
//! `cncgw offsets` edits them; `run`, `plan` and `preview` use them unless `--tools FILE`
//! names another tool table.
//!
//! They are kept per machine (`MACHINE.tools.toml`, `MACHINE.work-offsets.toml`), not per
//! place as the common variables are: they describe the tools in the turret and the
//! workpiece, not where the axes stand, so a rehearsal on the embedded machine
//! (`--bus inproc`) follows the real machine's path — as a Fanuc in machine lock / dry run
//! uses its offset memory. Written atomically (`persist::atomic_write`).

use crate::canon::Pos;
use crate::interp::{parse_tool_table, parse_work_offsets, Interpreter, ToolOffset, ToolTable};
use crate::persist::{atomic_write, slug, STATE_ALARM};
use crate::Alarm;
use std::path::{Path, PathBuf};

/// Work offsets as on the offset page, in machine units (X as a radius).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WorkOffsets {
    /// G54…G59.
    pub g5x: [Pos; 6],
    /// The external work zero offset ("外部工件零点偏移", Fanuc EXOFS): added to all six.
    pub ext: Pos,
}

/// The names of the work offset systems as `offsets set` and the file take them.
pub const WORK_NAMES: [&str; 7] = ["G54", "G55", "G56", "G57", "G58", "G59", "EXT"];

impl WorkOffsets {
    /// What the interpreter selects with G54…G59: each system's offset plus the external
    /// offset (manual §2.12.2 note 2: the external offset moves all six systems). G50 and
    /// G52 act on top of it as before.
    pub fn for_interpreter(&self) -> [Pos; 6] {
        self.g5x.map(|p| p.add(self.ext))
    }

    /// The system called `name` (G54…G59, EXT).
    pub fn get_mut(&mut self, name: &str) -> Option<&mut Pos> {
        match WORK_NAMES.iter().position(|n| n.eq_ignore_ascii_case(name))? {
            6 => Some(&mut self.ext),
            i => Some(&mut self.g5x[i]),
        }
    }

    pub fn get(&self, i: usize) -> Pos {
        if i == 6 {
            self.ext
        } else {
            self.g5x[i]
        }
    }
}

/// A float as TOML keeps it: every bit (`{:?}`), and `nan`/`inf` spelt as TOML spells them
/// (so that the parser, not the writer, refuses them with its message).
fn num(v: f64) -> String {
    if v.is_nan() {
        "nan".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf" } else { "-inf" }.into()
    } else {
        format!("{v:?}")
    }
}

/// The tool table in the format of docs/TOOL_TABLE.md (every key written).
pub fn format_tool_table(t: &ToolTable) -> String {
    let mut s = String::from("# cncgw tool offset table (docs/TOOL_TABLE.md); X values are diameters\n");
    for (n, o) in &t.offsets {
        s.push_str(&format!(
            "\n[{n}]\nx = {}\nz = {}\nwear_x = {}\nwear_z = {}\nr = {}\ntip = {}\n",
            num(o.x),
            num(o.z),
            num(o.wear_x),
            num(o.wear_z),
            num(o.r),
            o.tip
        ));
    }
    s
}

/// The work offsets as `[G54]`…`[G59]`, `[EXT]` sections, X as a diameter; systems that are
/// all zero are left out.
pub fn format_work_offsets(w: &WorkOffsets) -> String {
    let mut s = String::from("# cncgw work offsets G54-G59 and EXT (the external offset, added to all); X values are diameters\n");
    for (i, name) in WORK_NAMES.iter().enumerate() {
        let p = w.get(i);
        if p != Pos::ZERO {
            s.push_str(&format!("\n[{name}]\nx = {}\nz = {}\ny = {}\nc = {}\n", num(p.x * 2.0), num(p.z), num(p.y), num(p.c)));
        }
    }
    s
}

/// Read work offsets: [`parse_work_offsets`]'s `[G54]`…`[G59]` and an `[EXT]` section read
/// by the same rules. Errors are alarm 1000 naming the file and key.
pub fn parse_work_file(file: &str, text: &str) -> Result<WorkOffsets, Alarm> {
    let bad = |m: String| Alarm::new(crate::config::ConfigError::ALARM, format!("{file}: {m}"));
    let mut t: toml::Table = toml::from_str(text).map_err(|e| bad(e.to_string()))?;
    let ext = match t.remove("EXT") {
        Some(v) => {
            let mut one = toml::Table::new();
            one.insert("G54".into(), v);
            // The EXT section's messages say G54; say EXT.
            parse_work_offsets(file, &one.to_string()).map_err(|a| Alarm::new(a.number, a.message.replace("G54", "EXT")))?[0]
        }
        None => Pos::ZERO,
    };
    let g5x = parse_work_offsets(file, &t.to_string()).map_err(|a| Alarm::new(a.number, a.message.replace("G54 … G59", "G54 … G59 and EXT")))?;
    Ok(WorkOffsets { g5x, ext })
}

/// The stored offset files of one machine.
#[derive(Clone, Debug)]
pub struct OffsetStore {
    pub dir: PathBuf,
    pub tools: PathBuf,
    pub work: PathBuf,
    /// For the lock that serialises edits.
    pub key: String,
}

impl OffsetStore {
    pub fn new(dir: &Path, machine_name: &str) -> OffsetStore {
        let s = slug(machine_name);
        OffsetStore {
            dir: dir.to_path_buf(),
            tools: dir.join(format!("{s}.tools.toml")),
            work: dir.join(format!("{s}.work-offsets.toml")),
            key: format!("{s}.offsets"),
        }
    }

    fn read(path: &Path) -> Result<Option<String>, Alarm> {
        match std::fs::read_to_string(path) {
            Ok(t) => Ok(Some(t)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(Alarm::new(STATE_ALARM, format!("{}: cannot read the stored offsets: {e}", path.display()))),
        }
    }

    /// A stored file that does not parse is a state alarm (not a configuration one): the
    /// operator fixes it with `offsets import` or by removing the file.
    fn damaged(path: &Path, a: Alarm) -> Alarm {
        Alarm::new(
            STATE_ALARM,
            format!("{} (stored offsets) is damaged: {}; correct it with `cncgw offsets import`, or remove the file", path.display(), a.message),
        )
    }

    /// The stored tool table; empty if none was stored (every offset reads as zero).
    pub fn load_tools(&self) -> Result<ToolTable, Alarm> {
        match Self::read(&self.tools)? {
            Some(t) => parse_tool_table(&self.tools.display().to_string(), &t).map_err(|a| Self::damaged(&self.tools, a)),
            None => Ok(ToolTable::default()),
        }
    }

    /// The stored work offsets; all zero if none were stored.
    pub fn load_work(&self) -> Result<WorkOffsets, Alarm> {
        match Self::read(&self.work)? {
            Some(t) => parse_work_file(&self.work.display().to_string(), &t).map_err(|a| Self::damaged(&self.work, a)),
            None => Ok(WorkOffsets::default()),
        }
    }

    fn write(path: &Path, text: &str) -> Result<(), Alarm> {
        atomic_write(path, text.as_bytes()).map_err(|e| {
            Alarm::new(STATE_ALARM, format!("{}: cannot store the offsets: {e}; check the state directory (--state-dir)", path.display()))
        })
    }

    /// Store `t` after checking it reads back as the same table (the reader is the one set
    /// of rules for what a valid table is: a bad value is refused and nothing is written).
    pub fn save_tools(&self, t: &ToolTable) -> Result<(), Alarm> {
        let text = format_tool_table(t);
        let back = parse_tool_table("the new tool table", &text)?;
        if back != *t {
            return Err(Alarm::new(STATE_ALARM, "the new tool table does not read back as written; nothing was stored"));
        }
        Self::write(&self.tools, &text)
    }

    pub fn save_work(&self, w: &WorkOffsets) -> Result<(), Alarm> {
        let text = format_work_offsets(w);
        let back = parse_work_file("the new work offsets", &text)?;
        if back != *w {
            return Err(Alarm::new(STATE_ALARM, "the new work offsets do not read back as written; nothing was stored"));
        }
        Self::write(&self.work, &text)
    }
}

/// The offsets a program runs with, and where they came from (said to the operator).
#[derive(Clone, Debug, Default)]
pub struct Tables {
    pub tools: ToolTable,
    pub work: WorkOffsets,
    /// One line: which tool table and which work offsets.
    pub source: String,
}

impl Tables {
    /// Give the interpreter the tool table and the work offsets.
    pub fn apply(&self, it: &mut Interpreter) {
        it.set_tool_table(self.tools.clone());
        it.set_work_offsets(self.work.for_interpreter());
    }
}

/// The tables of a run, plan or preview of machine `machine_name`: the tool table from
/// `tools_file` if given (it wins), else the stored one; the work offsets from the state
/// directory `state_dir` (none: all zero).
pub fn resolve(state_dir: Option<&Path>, machine_name: &str, tools_file: Option<&Path>) -> Result<Tables, Alarm> {
    let store = state_dir.map(|d| OffsetStore::new(d, machine_name));
    let (tools, tools_from) = match (tools_file, &store) {
        (Some(f), _) => (crate::interp::load_tool_table(f)?, format!("tool offsets from {} (--tools)", f.display())),
        (None, Some(s)) if s.tools.exists() => (s.load_tools()?, format!("tool offsets stored in {}", s.tools.display())),
        _ => (ToolTable::default(), "no tool offsets stored (all zero)".to_string()),
    };
    let (work, work_from) = match &store {
        Some(s) if s.work.exists() => (s.load_work()?, format!("work offsets stored in {}", s.work.display())),
        _ => (WorkOffsets::default(), "no work offsets stored (all zero)".to_string()),
    };
    Ok(Tables { tools, work, source: format!("{tools_from}; {work_from}") })
}

/// One offset number's values, for `offsets set`: each `Some` replaces (or with `add`, is
/// added to) the stored value.
#[derive(Clone, Copy, Debug, Default)]
pub struct ToolEdit {
    pub x: Option<f64>,
    pub z: Option<f64>,
    pub wear_x: Option<f64>,
    pub wear_z: Option<f64>,
    pub r: Option<f64>,
    pub tip: Option<f64>,
}

impl ToolEdit {
    /// `o` edited. `add` adds the values (Fanuc's "+INPUT", used for wear); the tip is
    /// always set, never added. The result is checked when it is stored.
    pub fn apply(&self, o: ToolOffset, add: bool) -> Result<ToolOffset, String> {
        let f = |old: f64, v: Option<f64>| v.map_or(old, |v| if add { old + v } else { v });
        let tip = match self.tip {
            None => o.tip,
            Some(t) if t.fract() == 0.0 && (0.0..=9.0).contains(&t) => t as u8,
            Some(t) => return Err(format!("--tip {t}: the imaginary tool tip is a whole number 0–9")),
        };
        Ok(ToolOffset {
            x: f(o.x, self.x),
            z: f(o.z, self.z),
            wear_x: f(o.wear_x, self.wear_x),
            wear_z: f(o.wear_z, self.wear_z),
            r: f(o.r, self.r),
            tip,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tool_table_text_round_trip_is_exact() {
        let mut t = ToolTable::default();
        t.offsets.insert(1, ToolOffset { x: -152.3, z: 1.0 / 3.0, wear_x: 0.02, wear_z: -0.0, r: 0.8, tip: 3 });
        t.offsets.insert(99, ToolOffset { tip: 9, ..Default::default() });
        let back = parse_tool_table("t", &format_tool_table(&t)).unwrap();
        assert_eq!(back, t);
        assert_eq!(back.offsets[&1].z.to_bits(), (1.0f64 / 3.0).to_bits());
    }

    #[test]
    fn work_offsets_with_ext_round_trip_and_add_up() {
        let mut w = WorkOffsets::default();
        w.g5x[0] = Pos::xz(-10.0, -312.5);
        w.g5x[2].z = -200.0;
        w.ext = Pos::xz(0.5, -1.25);
        let back = parse_work_file("w", &format_work_offsets(&w)).unwrap();
        assert_eq!(back, w);
        let t = back.for_interpreter();
        assert_eq!((t[0].x, t[0].z), (-9.5, -313.75));
        assert_eq!((t[1].x, t[1].z), (0.5, -1.25), "EXT moves every system, an unset one too");
        let e = parse_work_file("w", "[EXT]\nq = 1.0\n").unwrap_err();
        assert!(e.message.contains("EXT.q") && e.message.contains("x (diameter), z"), "{}", e.message);
        assert!(parse_work_file("w", "[G60]\nx = 1.0\n").unwrap_err().message.contains("G54 … G59 and EXT"));
    }

    #[test]
    fn edits_add_or_replace_and_refuse_a_bad_tip() {
        let o = ToolOffset { x: -100.0, wear_x: 0.02, tip: 3, ..Default::default() };
        let e = ToolEdit { wear_x: Some(0.01), ..Default::default() };
        assert!((e.apply(o, true).unwrap().wear_x - 0.03).abs() < 1e-12);
        assert_eq!(e.apply(o, false).unwrap().wear_x, 0.01);
        assert_eq!(e.apply(o, false).unwrap().x, -100.0, "values not given are kept");
        assert!(ToolEdit { tip: Some(10.0), ..Default::default() }.apply(o, false).is_err());
        assert!(ToolEdit { tip: Some(2.5), ..Default::default() }.apply(o, false).is_err());
    }
}
