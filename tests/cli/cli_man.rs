//! Manual pages (issue 25): `cncgw man --dir DIR` writes one page per command and subcommand,
//! each renders with `man -l` without a warning and has the sections a man page needs.

use std::process::Command;

#[test]
fn every_command_has_a_page_that_renders() {
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_cncgw")).args(["man", "--dir"]).arg(dir.path()).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut pages: Vec<String> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    pages.sort();
    // Every command of `cncgw --help` has its page, and the nested ones too.
    let help = Command::new(env!("CARGO_BIN_EXE_cncgw")).arg("--help").output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout).into_owned();
    let commands: Vec<&str> = help
        .split("Commands:")
        .nth(1)
        .unwrap()
        .lines()
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter_map(|l| l.split_whitespace().next())
        .filter(|c| *c != "help")
        .collect();
    assert!(commands.len() > 15, "{help}");
    for c in &commands {
        assert!(pages.contains(&format!("cncgw-{c}.1")), "no page for {c}: {pages:?}");
    }
    for sub in ["cncgw-sdo-read.1", "cncgw-drive-status.1", "cncgw-config-check.1", "cncgw-trace-plot.1", "cncgw.1"] {
        assert!(pages.contains(&sub.to_string()), "{sub}: {pages:?}");
    }
    for p in &pages {
        let r = Command::new("man")
            .args(["-l", "-P", "cat"])
            .arg(dir.path().join(p))
            .env("MANWIDTH", "80")
            .env("LC_ALL", "C.UTF-8")
            .output()
            .expect("man (man-db) is installed by scripts/install-test-deps.sh");
        let text = String::from_utf8_lossy(&r.stdout);
        let err = String::from_utf8_lossy(&r.stderr);
        assert!(r.status.success() && err.trim().is_empty(), "{p}: {err}");
        for section in ["NAME", "SYNOPSIS", "EXIT STATUS", "ENVIRONMENT", "FILES", "SEE ALSO"] {
            assert!(text.contains(section), "{p} has no {section}:\n{text}");
        }
        assert!(text.contains("CNCGW_STATE_DIR") && text.contains("NO_COLOR"), "{p}");
    }
    // A command's own examples are on its page.
    let run = Command::new("man").args(["-l", "-P", "cat"]).arg(dir.path().join("cncgw-run.1")).output().unwrap();
    let run = String::from_utf8_lossy(&run.stdout);
    assert!(run.contains("EXAMPLES") && run.contains("cncgw run examples/first_part.nc"), "{run}");
}

/// `--help` teaches every argument: none without its help text.
#[test]
fn every_argument_has_help() {
    use clap::CommandFactory;
    fn walk(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
        for a in cmd.get_arguments().filter(|a| !a.is_hide_set()) {
            if a.get_help().is_none() && a.get_long_help().is_none() {
                missing.push(format!("{path} {}", a.get_id()));
            }
        }
        for s in cmd.get_subcommands() {
            walk(s, &format!("{path} {}", s.get_name()), missing);
        }
    }
    let mut missing = Vec::new();
    let mut cmd = cncgw::cli::Cli::command();
    cmd.build();
    walk(&cmd, "cncgw", &mut missing);
    assert!(missing.is_empty(), "arguments without help: {missing:#?}");
}
