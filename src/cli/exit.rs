//! The exit codes of every `cncgw` command: one table, in `cncgw --help`, the man page and
//! the README.

/// Done, and the result is what was asked for.
pub const OK: i32 = 0;
/// Done, but the result is not what was asked for: `run` — an axis did not end within one
/// count of the program's end point; `tap-test` — the sync error reached the limit; the
/// service commands — a node aborted, did not answer, or needs attention; `config check` —
/// the configuration would be refused by `run`.
pub const NOT_MET: i32 = 1;
/// The input cannot be used: a file that is missing or unreadable, a program or trace with
/// errors, arguments that cannot be carried out as written. Nothing was moved.
pub const INPUT: i32 = 2;
/// An alarm stopped the machine, or refused motion at the machine (limits, the tap state,
/// a drive that is not what the configuration says).
pub const ALARM: i32 = 3;
/// Setup: the configuration is invalid, or the bus, a Modbus link, the state directory or
/// an output file cannot be opened.
pub const SETUP: i32 = 4;

/// Every exit status and what it means: the one table `--help`, the man pages and the README
/// show.
pub const CODES: [(i32, &str); 5] = [
    (OK, "done, with the result asked for"),
    (NOT_MET, "done, result not met: run — an axis not within its in-position width of the end point; tap-test — sync error over the limit; scan, sdo, nmt, drive — a node aborted or did not answer; config check — run would refuse this configuration"),
    (INPUT, "input cannot be used: missing or unreadable file, program or trace errors, bad arguments; nothing was moved"),
    (ALARM, "an alarm stopped the machine or refused motion at the machine"),
    (SETUP, "setup: invalid configuration; the bus, a Modbus link, the state directory or an output file cannot be opened"),
];

/// The table as `--help` shows it.
pub fn table() -> String {
    let mut t = String::from("Exit status (every command):");
    for (code, what) in CODES {
        t.push_str(&format!("\n  {code}  {what}"));
    }
    t
}
