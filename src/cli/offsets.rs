//! `cncgw offsets`: the operator's offset pages (tool offsets, work offsets G54–G59 and EXT)
//! kept in the state directory (`crate::offsets`): list, set, import, export.

use super::exit;
use crate::interp::{ToolOffset, ToolTable};
use crate::offsets::{OffsetStore, ToolEdit, WORK_NAMES};
use std::path::{Path, PathBuf};

/// Which machine's offsets and where they are kept.
#[derive(clap::Args, Debug, Clone)]
pub struct Where {
    /// Machine configuration (TOML), for its name. Default: the embedded config/lathe.toml.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Where the machine's state lives (as for `run`). Default: $CNCGW_STATE_DIR, else
    /// $XDG_STATE_HOME/cncgw, else ~/.local/state/cncgw.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
}

#[derive(clap::Subcommand, Debug)]
pub enum OffsetsCmd {
    /// Show the tool offsets and the work offsets (X as a diameter).
    ///
    /// Example: `cncgw offsets list`, `cncgw offsets list --json`
    List {
        #[command(flatten)]
        at: Where,
        /// Print JSON: {"tools": {"1": {x, z, wear_x, wear_z, r, tip}}, "work": {"G54": {x, z, y, c}, …, "EXT": …}}.
        #[arg(long)]
        json: bool,
    },
    /// Set values of one tool offset (T01…T99) or one work offset (G54…G59, EXT).
    ///
    /// Values not given are kept; a new offset number starts at zero. X is a diameter.
    /// Nothing is stored if a value is refused.
    ///
    /// Example: `cncgw offsets set T01 --x -152.3 --z -310.45 --r 0.8 --tip 3`,
    /// `cncgw offsets set T01 --wear-x 0.02 --add`, `cncgw offsets set G54 --z -312.5`
    Set {
        /// T01…T99 (offset number; T0101 uses offset 01), G54…G59, or EXT (the external
        /// offset, added to every work offset).
        target: String,
        /// Geometry X (tool; diameter) or the work offset's X (diameter), mm.
        #[arg(long, allow_hyphen_values = true)]
        x: Option<f64>,
        /// Geometry Z (tool) or the work offset's Z, mm.
        #[arg(long, allow_hyphen_values = true)]
        z: Option<f64>,
        /// Wear X (diameter, mm); tool offsets only.
        #[arg(long, allow_hyphen_values = true)]
        wear_x: Option<f64>,
        /// Wear Z (mm); tool offsets only.
        #[arg(long, allow_hyphen_values = true)]
        wear_z: Option<f64>,
        /// Nose radius (mm, ≥ 0); tool offsets only.
        #[arg(long, allow_hyphen_values = true)]
        r: Option<f64>,
        /// Imaginary tool tip 0–9; tool offsets only.
        #[arg(long, allow_hyphen_values = true)]
        tip: Option<f64>,
        /// Y (mm); work offsets only.
        #[arg(long, allow_hyphen_values = true)]
        y: Option<f64>,
        /// C (degrees); work offsets only.
        #[arg(long, allow_hyphen_values = true)]
        c: Option<f64>,
        /// Add the values to the stored ones instead of replacing them (Fanuc's +INPUT, for wear).
        #[arg(long)]
        add: bool,
        #[command(flatten)]
        at: Where,
    },
    /// Replace the stored tool table (or with --work the work offsets) by FILE's.
    ///
    /// FILE is in the format of docs/TOOL_TABLE.md (config/tools.toml); with --work, `[G54]`…`[G59]`,
    /// `[EXT]` sections with x (diameter), z, y, c. The whole file is checked first: one bad
    /// value and nothing is stored.
    ///
    /// Example: `cncgw offsets import config/tools.toml`
    Import {
        /// The table to read.
        file: PathBuf,
        /// The file holds work offsets.
        #[arg(long)]
        work: bool,
        #[command(flatten)]
        at: Where,
    },
    /// Write the stored tool table (or with --work the work offsets) to FILE (`-`: stdout),
    /// in the format `import` and `run --tools` read.
    ///
    /// Example: `cncgw offsets export tools-backup.toml`
    Export {
        /// The file to write (`-`: standard output).
        file: PathBuf,
        /// Write the work offsets instead of the tool table.
        #[arg(long)]
        work: bool,
        #[command(flatten)]
        at: Where,
    },
}

/// The store of the machine `at` names.
fn store(at: &Where) -> Result<OffsetStore, i32> {
    let (cfg, _) = super::load_config(at.config.as_deref()).map_err(|e| {
        eprintln!("error: {e}");
        exit::SETUP
    })?;
    let Some(dir) = at.state_dir.clone().or_else(crate::persist::default_state_dir) else {
        eprintln!("error: no state directory: give --state-dir or set CNCGW_STATE_DIR");
        return Err(exit::SETUP);
    };
    Ok(OffsetStore::new(&dir, &cfg.machine.name))
}

/// `T01`, `t1`, `1` → 1 (1–99).
fn offset_number(s: &str) -> Option<u32> {
    let d = s.strip_prefix(['T', 't']).unwrap_or(s);
    d.parse::<u32>().ok().filter(|n| (1..=99).contains(n) && !d.is_empty())
}

pub fn main(cmd: OffsetsCmd) -> i32 {
    match cmd {
        OffsetsCmd::List { at, json } => store(&at).map_or_else(|c| c, |s| list(&s, json)),
        OffsetsCmd::Set { target, x, z, wear_x, wear_z, r, tip, y, c, add, at } => {
            let edit = ToolEdit { x, z, wear_x, wear_z, r, tip };
            store(&at).map_or_else(|c| c, |s| set(&s, &target, edit, y, c, add))
        }
        OffsetsCmd::Import { file, work, at } => store(&at).map_or_else(|c| c, |s| import(&s, &file, work)),
        OffsetsCmd::Export { file, work, at } => store(&at).map_or_else(|c| c, |s| export(&s, &file, work)),
    }
}

fn tool_json(o: &ToolOffset) -> serde_json::Value {
    serde_json::json!({"x": o.x, "z": o.z, "wear_x": o.wear_x, "wear_z": o.wear_z, "r": o.r, "tip": o.tip})
}

fn list(s: &OffsetStore, json: bool) -> i32 {
    let (tools, work) = match (s.load_tools(), s.load_work()) {
        (Ok(t), Ok(w)) => (t, w),
        (Err(a), _) | (_, Err(a)) => {
            eprintln!("{a}");
            return exit::SETUP;
        }
    };
    if json {
        let t: serde_json::Map<String, serde_json::Value> = tools.offsets.iter().map(|(n, o)| (n.to_string(), tool_json(o))).collect();
        let w: serde_json::Map<String, serde_json::Value> = WORK_NAMES
            .iter()
            .enumerate()
            .map(|(i, n)| {
                let p = work.get(i);
                (n.to_string(), serde_json::json!({"x": p.x * 2.0, "z": p.z, "y": p.y, "c": p.c}))
            })
            .collect();
        println!("{}", serde_json::json!({"tools": t, "work": w, "tools_file": s.tools, "work_file": s.work}));
        return exit::OK;
    }
    println!("tool offsets ({}; X diameter, mm)", s.tools.display());
    if tools.offsets.is_empty() {
        println!("  none stored: every T code's offset reads as zero");
    } else {
        println!("  {:<4} {:>11} {:>11} {:>9} {:>9} {:>7} {:>3}", "no.", "X", "Z", "wear X", "wear Z", "R", "tip");
        for (n, o) in &tools.offsets {
            println!("  T{n:02}  {:>11.4} {:>11.4} {:>9.4} {:>9.4} {:>7.4} {:>3}", o.x, o.z, o.wear_x, o.wear_z, o.r, o.tip);
        }
    }
    println!("work offsets ({}; X diameter, mm; EXT is added to every system)", s.work.display());
    println!("  {:<4} {:>11} {:>11} {:>11} {:>11}", "", "X", "Z", "Y", "C");
    for (i, n) in WORK_NAMES.iter().enumerate() {
        let p = work.get(i);
        println!("  {n:<4} {:>11.4} {:>11.4} {:>11.4} {:>11.4}", p.x * 2.0, p.z, p.y, p.c);
    }
    exit::OK
}

/// Edits are read-modify-write: serialised by a lock beside the files. Another edit holds it
/// for milliseconds, so wait for it (up to 5 s) rather than refuse.
fn edit_lock(s: &OffsetStore) -> Result<super::lock::Lock, i32> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
    loop {
        match super::lock::state(&s.dir, &s.key) {
            Ok(l) => return Ok(l),
            Err(a) if std::time::Instant::now() >= deadline => {
                eprintln!("error: the offsets in {} are being edited by another process: {}", s.dir.display(), a.message);
                return Err(exit::SETUP);
            }
            Err(_) => std::thread::sleep(std::time::Duration::from_millis(20)),
        }
    }
}

fn set(s: &OffsetStore, target: &str, edit: ToolEdit, y: Option<f64>, c: Option<f64>, add: bool) -> i32 {
    let _lock = match edit_lock(s) {
        Ok(l) => l,
        Err(c) => return c,
    };
    let refuse = |m: String| {
        eprintln!("error: offsets set {target}: {m}; nothing was stored");
        exit::INPUT
    };
    if let Some(n) = offset_number(target) {
        if y.is_some() || c.is_some() {
            return refuse("--y and --c are for work offsets (G54…G59, EXT); a tool offset has x, z, wear-x, wear-z, r, tip".into());
        }
        let mut t = match s.load_tools() {
            Ok(t) => t,
            Err(a) => {
                eprintln!("{a}");
                return exit::SETUP;
            }
        };
        let old = t.offsets.get(&n).copied().unwrap_or_default();
        let new = match edit.apply(old, add) {
            Ok(o) => o,
            Err(m) => return refuse(m),
        };
        t.offsets.insert(n, new);
        if let Err(a) = s.save_tools(&t) {
            return refuse(a.message.replace("the new tool table: ", ""));
        }
        println!(
            "T{n:02}: X {:.4} Z {:.4} wear X {:.4} wear Z {:.4} R {:.4} tip {} (stored in {})",
            new.x,
            new.z,
            new.wear_x,
            new.wear_z,
            new.r,
            new.tip,
            s.tools.display()
        );
        return exit::OK;
    }
    let mut w = match s.load_work() {
        Ok(w) => w,
        Err(a) => {
            eprintln!("{a}");
            return exit::SETUP;
        }
    };
    let Some(p) = w.get_mut(target) else {
        return refuse("name T01…T99 (a tool offset number), G54…G59 or EXT".into());
    };
    if edit.wear_x.is_some() || edit.wear_z.is_some() || edit.r.is_some() || edit.tip.is_some() {
        return refuse("--wear-x, --wear-z, --r and --tip are for tool offsets (T01…T99); a work offset has x, z, y, c".into());
    }
    let f = |old: f64, v: Option<f64>, scale: f64| v.map_or(old, |v| if add { old + v * scale } else { v * scale });
    // X is entered as a diameter and kept as a radius.
    *p = crate::canon::Pos { x: f(p.x, edit.x, 0.5), z: f(p.z, edit.z, 1.0), y: f(p.y, y, 1.0), c: f(p.c, c, 1.0) };
    let shown = *p;
    if let Err(a) = s.save_work(&w) {
        return refuse(a.message.replace("the new work offsets: ", ""));
    }
    println!("{}: X {:.4} Z {:.4} Y {:.4} C {:.4} (stored in {})", target.to_uppercase(), shown.x * 2.0, shown.z, shown.y, shown.c, s.work.display());
    exit::OK
}

fn import(s: &OffsetStore, file: &Path, work: bool) -> i32 {
    let _lock = match edit_lock(s) {
        Ok(l) => l,
        Err(c) => return c,
    };
    let text = match std::fs::read_to_string(file) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: {}: cannot read: {e}", file.display());
            return exit::INPUT;
        }
    };
    let name = file.display().to_string();
    let r = if work {
        crate::offsets::parse_work_file(&name, &text).and_then(|w| s.save_work(&w).map(|_| format!("work offsets stored in {}", s.work.display())))
    } else {
        crate::interp::parse_tool_table(&name, &text)
            .and_then(|t: ToolTable| s.save_tools(&t).map(|_| format!("{} tool offset(s) stored in {}", t.offsets.len(), s.tools.display())))
    };
    match r {
        Ok(m) => {
            println!("{m} (from {name})");
            exit::OK
        }
        Err(a) => {
            eprintln!("{a}");
            eprintln!("nothing was stored");
            exit::INPUT
        }
    }
}

fn export(s: &OffsetStore, file: &Path, work: bool) -> i32 {
    let text = if work {
        s.load_work().map(|w| crate::offsets::format_work_offsets(&w))
    } else {
        s.load_tools().map(|t| crate::offsets::format_tool_table(&t))
    };
    let text = match text {
        Ok(t) => t,
        Err(a) => {
            eprintln!("{a}");
            return exit::SETUP;
        }
    };
    if file == Path::new("-") {
        print!("{text}");
        return exit::OK;
    }
    match crate::persist::atomic_write(file, text.as_bytes()) {
        Ok(()) => {
            eprintln!("{} written", file.display());
            exit::OK
        }
        Err(e) => {
            eprintln!("error: cannot write {}: {e}", file.display());
            exit::SETUP
        }
    }
}
