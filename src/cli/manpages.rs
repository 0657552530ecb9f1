//! Manual pages: one per command and subcommand (`cncgw man --dir DIR` writes them all,
//! `cncgw man` prints the top one). clap_mangen renders what clap knows (name, synopsis,
//! description, options, subcommands); the sections a man page has beyond that — EXIT
//! STATUS, ENVIRONMENT, FILES, EXAMPLES, SEE ALSO — are written here, the same on every page
//! but the examples, which are each command's own `Example:` lines.

use clap::CommandFactory;
use roff::{bold, italic, roman, Roff};
use std::io::Write;
use std::path::{Path, PathBuf};

/// (file name, roff text) of every page, the top command's first.
pub fn pages() -> std::io::Result<Vec<(String, Vec<u8>)>> {
    let mut cmd = super::Cli::command().disable_help_subcommand(true);
    cmd.build();
    let mut out = Vec::new();
    walk(&cmd, &mut out)?;
    Ok(out)
}

fn walk(cmd: &clap::Command, out: &mut Vec<(String, Vec<u8>)>) -> std::io::Result<()> {
    out.push((format!("{}.1", page_name(cmd)), render(cmd)?));
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()) {
        walk(sub, out)?;
    }
    Ok(())
}

fn page_name(cmd: &clap::Command) -> String {
    cmd.get_display_name().unwrap_or_else(|| cmd.get_name()).to_string()
}

/// Write every page into `dir` (created if needed); the files written.
pub fn write_all(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir)?;
    let mut files = Vec::new();
    for (name, text) in pages()? {
        let path = dir.join(name);
        std::fs::write(&path, text)?;
        files.push(path);
    }
    Ok(files)
}

/// The top page, on stdout.
pub fn print_top(w: &mut dyn Write) -> std::io::Result<()> {
    let pages = pages()?;
    w.write_all(&pages[0].1)
}

fn render(cmd: &clap::Command) -> std::io::Result<Vec<u8>> {
    let man = clap_mangen::Man::new(cmd.clone()).manual("cncgw manual").source(format!("cncgw {}", env!("CARGO_PKG_VERSION")));
    let mut buf = Vec::new();
    man.render_title(&mut buf)?;
    man.render_name_section(&mut buf)?;
    man.render_synopsis_section(&mut buf)?;
    man.render_description_section(&mut buf)?;
    if cmd.get_arguments().any(|a| !a.is_hide_set()) {
        man.render_options_section(&mut buf)?;
    }
    if cmd.has_subcommands() {
        man.render_subcommands_section(&mut buf)?;
    }
    buf.extend_from_slice(extra_sections(cmd).render().as_bytes());
    Ok(buf)
}

fn extra_sections(cmd: &clap::Command) -> Roff {
    let mut r = Roff::new();
    r.control("SH", ["EXIT STATUS"]);
    for (code, what) in super::exit::CODES {
        r.control("TP", []).text([bold(code.to_string())]).text([roman(what)]);
    }
    r.control("SH", ["ENVIRONMENT"]);
    for (name, what) in ENVIRONMENT {
        r.control("TP", []).text([bold(*name)]).text([roman(*what)]);
    }
    r.control("SH", ["FILES"]);
    for (name, what) in FILES {
        r.control("TP", []).text([italic(*name)]).text([roman(*what)]);
    }
    let examples = examples(cmd);
    if !examples.is_empty() {
        r.control("SH", ["EXAMPLES"]);
        for e in examples {
            r.control("TP", []).text([bold(e)]);
        }
    }
    r.control("SH", ["SEE ALSO"]);
    let name = page_name(cmd);
    let see: Vec<String> = match name.rsplit_once('-') {
        Some((parent, _)) => vec![format!("{parent}(1)")],
        None => cmd.get_subcommands().filter(|s| !s.is_hide_set()).map(|s| format!("{}(1)", page_name(s))).collect(),
    };
    r.text([roman(see.join(", ")), roman(". The README and docs/ of the cncgw sources.")]);
    r
}

/// The `cncgw …` commands quoted after "Example" in a command's help.
fn examples(cmd: &clap::Command) -> Vec<String> {
    let text = cmd.get_long_about().or(cmd.get_about()).map(|s| s.to_string()).unwrap_or_default();
    let Some(at) = text.find("Example") else { return Vec::new() };
    text[at..].split('`').skip(1).step_by(2).filter(|s| s.starts_with("cncgw")).map(str::to_string).collect()
}

/// The environment variables cncgw reads.
pub const ENVIRONMENT: &[(&str, &str)] = &[
    ("CNCGW_STATE_DIR", "Where the machine's power-off state (common variables #401–#600, the rigid-tap state) and its lock live; overrides XDG_STATE_HOME. `run --state-dir` overrides both."),
    ("XDG_STATE_HOME", "The state directory is $XDG_STATE_HOME/cncgw when CNCGW_STATE_DIR is not set (else ~/.local/state/cncgw)."),
    ("RUST_LOG", "Log filter (tracing's env-filter syntax, e.g. cncgw=debug); overrides -v."),
    ("NO_COLOR", "When set, no colour in the log or the operator panel, even on a terminal."),
];

/// The files cncgw reads or writes.
pub const FILES: &[(&str, &str)] = &[
    ("config/lathe.toml", "The embedded default machine configuration (--config FILE for another; `cncgw config check` validates one)."),
    (
        "$CNCGW_STATE_DIR/MACHINE@PLACE.common-vars.toml",
        "Common variables #401–#600 kept through power-off, per machine name and place (inproc, or the bus), written atomically.",
    ),
    (
        "$CNCGW_STATE_DIR/MACHINE@PLACE.tap-state.toml",
        "Where the tool is while it is in a rigidly tapped hole (G30 P99 brings it out after a stop), written atomically.",
    ),
    (
        "$CNCGW_STATE_DIR/MACHINE@PLACE.alarms.jsonl",
        "Every alarm `run` met on that machine and place, one JSON line each (`cncgw alarms` shows them).",
    ),
    ("$CNCGW_STATE_DIR/MACHINE@PLACE.lock", "Held while a run uses that state: a second controller on it is refused (alarm 2405)."),
    (
        "$CNCGW_STATE_DIR/MACHINE.tools.toml, MACHINE.work-offsets.toml",
        "The tool offsets and the work offsets G54–G59 and EXT of a machine (`cncgw offsets`), written atomically; run, plan, preview and mdi use them unless --tools FILE.",
    ),
    (
        "/run/lock/cncgw-bus-NAME.lock",
        "Held by every command that moves or writes the drives of bus NAME: a second controller on the bus is refused (alarm 2404).",
    ),
];
