//! Bad input is refused with a position and a message a person can read (issue 20.5): an open
//! comment, text after the end-of-tape `%`, an empty program, a program that loops without
//! end (block budget), a runaway token and a non-printing byte in the echo.

use cncgw::config::MachineConfig;
use cncgw::interp::{Interpreter, BLOCK_BUDGET_ALARM};
use std::process::Command;

fn static_errors(src: &str) -> Vec<cncgw::Alarm> {
    match Interpreter::from_source("t.nc", src, &MachineConfig::embedded()) {
        Err(e) => e,
        Ok(_) => panic!("expected the program to be refused before it runs:\n{src}"),
    }
}

/// `cncgw plan` on `text`: exit code, stderr.
fn plan(text: &[u8], extra: &[&str]) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("p.nc");
    std::fs::write(&f, text).unwrap();
    let o =
        Command::new(env!("CARGO_BIN_EXE_cncgw")).env("CNCGW_STATE_DIR", dir.path().join("state")).arg("plan").arg(&f).args(extra).output().unwrap();
    (o.status.code().unwrap_or(-1), String::from_utf8_lossy(&o.stderr).into_owned())
}

#[test]
fn an_unclosed_comment_is_refused_at_its_column() {
    let e = static_errors("G0 X10 (unclosed\nM30\n");
    assert_eq!((e[0].number, e[0].pos.as_ref().unwrap().line, e[0].pos.as_ref().unwrap().col), (9, 1, 8), "{}", e[0]);
    // Closed comments and `;` comments stay fine.
    assert!(Interpreter::from_source("t.nc", "G0 X10 (ok) Z1 ; (open after ;\nM30\n", &MachineConfig::embedded()).is_ok());
}

#[test]
fn text_after_the_end_of_tape_percent_is_refused() {
    let e = static_errors("%\nG0 X10\nM30\n%\n\nG0 X99\n");
    assert_eq!((e[0].number, e[0].pos.as_ref().unwrap().line), (5010, 6), "{}", e[0]);
    assert!(e[0].message.contains("end-of-tape `%` of line 4"), "{}", e[0]);
    // Blank lines after it are nothing.
    assert!(Interpreter::from_source("t.nc", "%\nG0 X10\nM30\n%\n\n  \n", &MachineConfig::embedded()).is_ok());
}

#[test]
fn an_empty_program_or_one_without_m30_does_not_plan() {
    for (text, says) in [(&b""[..], "empty"), (b"%\n", "empty"), (b"%\n%\n", "empty"), (b"G0 X10\n", "without M02 or M30")] {
        let (code, err) = plan(text, &[]);
        assert_eq!(code, 2, "{err}");
        assert!(err.contains("alarm 5010") && err.contains(says), "{err}");
    }
    assert_eq!(plan(b"G0 X10\nM30\n", &[]).0, 0);
}

/// DO without WHILE (endless by 004's definition) and M99 in a main program stop at the block
/// budget with alarm 2501 instead of printing forever; 0 switches the budget off.
#[test]
fn endless_programs_stop_at_the_block_budget() {
    for src in ["DO1\nG0 X1\nEND1\nM30\n", "G0 X1\nM99\n"] {
        let (code, err) = plan(src.as_bytes(), &["--max-blocks", "5000"]);
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(&format!("alarm {BLOCK_BUDGET_ALARM}")) && err.contains("5000 blocks"), "{err}");
    }
    let cfg = MachineConfig::embedded();
    let mut it = Interpreter::from_source("t.nc", "DO1\nG0 X1\nEND1\nM30\n", &cfg).unwrap();
    it.set_block_budget(0);
    assert_eq!(it.by_ref().take(20_000).filter(|m| m.is_ok()).count(), 20_000, "no budget: it keeps going");
    assert!(it.blocks_run() > 20_000);
}

#[test]
fn a_runaway_token_and_a_nul_byte_are_not_echoed_raw() {
    let mut big = b"G0 X".to_vec();
    big.extend(std::iter::repeat_n(b'1', 2_000_000));
    big.extend(b"\nM30\n");
    let (code, err) = plan(&big, &[]);
    assert_eq!(code, 2);
    assert!(err.len() < 1000, "the alarm is {} bytes long", err.len());
    assert!(err.contains("alarm 0003") && err.contains("2000000 characters") && err.contains("characters cut]"), "{err}");

    let (code, err) = plan(b"G0 X1\0 Z2\nM30\n", &[]);
    assert_eq!(code, 2);
    assert!(!err.contains('\0'), "{err:?}");
    assert!(err.contains("p.nc:1:6: alarm 0009") && err.contains("\\u{0}"), "{err}");
}

/// The echo is cut around the alarm's column, so the offending word is in it.
#[test]
fn a_long_block_is_echoed_around_the_error() {
    let line = format!("G1 {} X1..5\n", "Z1 ".repeat(200));
    let (code, err) = plan(format!("{line}M30\n").as_bytes(), &[]);
    assert_eq!(code, 2, "{err}");
    let echo = err.lines().nth(1).unwrap();
    assert!(echo.contains("X1..5") && echo.contains("characters cut]"), "{err}");
}

/// A UTF-8 byte-order mark at the start of a file (Windows editors) is not an improper
/// character: the program runs as without it.
#[test]
fn a_byte_order_mark_is_accepted() {
    let (code, err) = plan("\u{feff}G0 X10 Z5\nM30\n".as_bytes(), &[]);
    assert_eq!(code, 0, "{err}");
    // Elsewhere it is still an improper character, shown escaped.
    let (code, err) = plan("G0 X10\n\u{feff}Z5\nM30\n".as_bytes(), &[]);
    assert_eq!(code, 2);
    assert!(err.contains("improper character") && err.contains("\\u{feff}"), "{err}");
}
