//! The service commands that change state or move iron (`drive enable|disable|fault-reset|
//! home`, `jog`) and the bus tools (`buslog`, `monitor`): the real binary against the
//! embedded emulated drives (default config, `inproc`), plus the CiA 402 walk in-process
//! where one command's fresh emulator cannot show it (a fault raised, then reset).

use cncgw::cli::service::{power_walk, PowerGoal};
use cncgw::cli::{open_session, MachineArgs, Session};
use cncgw_bus::cia402::State;
use std::process::Command;

use testkit::Out;

fn cncgw(args: &[&str]) -> Out {
    testkit::cli!().run(args)
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("cncgw_cli_service_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn session() -> Session {
    open_session(&MachineArgs { config: None, bus: Some("inproc".into()), sim_config: None }).expect("inproc session")
}

fn statusword(s: &mut Session, node: u8) -> u16 {
    let d = s.master.sdo_upload(&mut *s.clock, node, 0x6041, 0).expect("read 0x6041");
    u16::from_le_bytes([d[0], d[1]])
}

#[test]
fn drive_enable_walks_to_operation_enabled() {
    let o = cncgw(&["drive", "enable", "1"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    let first = o.stdout.lines().next().unwrap();
    assert_eq!(first, "node 1 (axis x): Switch On Disabled → Operation Enabled (statusword 0x0637)");
    // A fresh drive: nothing to disable or reset, and it says so.
    let o = cncgw(&["drive", "disable", "2"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.starts_with("node 2 (axis z): Switch On Disabled (statusword 0x0250); already there"), "{}", o.stdout);
    let o = cncgw(&["drive", "fault-reset", "3"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("not in fault, nothing to reset"), "{}", o.stdout);
    // A node that does not answer.
    let o = cncgw(&["drive", "enable", "9"]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("node 9") && o.stderr.contains("0x6041"), "{}", o.stderr);
}

#[test]
fn motion_on_a_real_bus_needs_yes() {
    for args in [
        &["drive", "enable", "1", "--bus", "can7"][..],
        &["drive", "home", "1", "--bus", "can7"][..],
        &["jog", "x", "--by", "1", "--bus", "can7"][..],
    ] {
        let o = cncgw(args);
        assert_eq!(o.code, 2, "{args:?}: {}", o.stderr);
        assert!(o.stderr.contains("can set a motor in motion on can7") && o.stderr.contains("--yes"), "{}", o.stderr);
    }
    // With --yes the check passes and the (absent) bus is what fails.
    let o = cncgw(&["drive", "enable", "1", "--bus", "can7", "--yes"]);
    assert_eq!(o.code, 4, "{}", o.stderr);
    assert!(o.stderr.contains("can7") && !o.stderr.contains("--yes"), "{}", o.stderr);
    // Disabling and resetting take torque off: no --yes needed (refused only as a bus error).
    let o = cncgw(&["drive", "disable", "1", "--bus", "can7"]);
    assert_eq!(o.code, 4, "{}", o.stderr);
}

#[test]
fn disable_and_fault_reset_walk_the_state_machine() {
    let mut s = session();
    // A stale target left by someone (5 mm away) in cyclic synchronous position.
    s.master.sdo_download(&mut *s.clock, 1, 0x607A, 0, &50_000i32.to_le_bytes()).unwrap();
    s.master.sdo_download(&mut *s.clock, 1, 0x6060, 0, &[8]).unwrap();
    let (from, to) = power_walk(&mut s, 1, PowerGoal::Enable, 2000).unwrap();
    assert_eq!((from, to), (State::SwitchOnDisabled, State::OperationEnabled));
    // The target 0x607A was set to the present position first: nothing to jump to.
    let d = s.master.sdo_upload(&mut *s.clock, 1, 0x607A, 0).unwrap();
    let p = s.master.sdo_upload(&mut *s.clock, 1, 0x6064, 0).unwrap();
    assert_eq!(d, p);
    s.master.listen(&mut *s.clock, 100);
    let p = s.master.sdo_upload(&mut *s.clock, 1, 0x6064, 0).unwrap();
    assert!(i32::from_le_bytes([p[0], p[1], p[2], p[3]]).abs() < 10, "moved to {p:?}");
    let (from, to) = power_walk(&mut s, 1, PowerGoal::Disable, 2000).unwrap();
    assert_eq!((from, to), (State::OperationEnabled, State::SwitchOnDisabled));
    assert_eq!(State::from_statusword(statusword(&mut s, 1)), State::SwitchOnDisabled);

    // Raise a fault (emulator: 0x2100:1 = error code), reset it.
    s.master.sdo_download(&mut *s.clock, 2, 0x2100, 1, &0x5530u16.to_le_bytes()).unwrap();
    s.master.listen(&mut *s.clock, 50);
    assert_eq!(State::from_statusword(statusword(&mut s, 2)), State::Fault);
    let e = power_walk(&mut s, 2, PowerGoal::Disable, 2000).unwrap_err();
    assert!(e.contains("Fault") && e.contains("fault-reset 2"), "{e}");
    let (from, to) = power_walk(&mut s, 2, PowerGoal::FaultReset, 2000).unwrap();
    assert_eq!((from, to), (State::Fault, State::SwitchOnDisabled));
    // Controlword bit 7 left low: the next reset is a rising edge again.
    let d = s.master.sdo_upload(&mut *s.clock, 2, 0x6040, 0).unwrap();
    assert_eq!(u16::from_le_bytes([d[0], d[1]]) & 0x80, 0);

    // A cause that persists (undervoltage stays until cleared): the reset fails, in words.
    s.master.sdo_download(&mut *s.clock, 3, 0x2100, 3, &[1]).unwrap();
    s.master.listen(&mut *s.clock, 50);
    let e = power_walk(&mut s, 3, PowerGoal::FaultReset, 500).unwrap_err();
    assert!(e.contains("still in Fault") && e.contains("0x3220"), "{e}");
    // Enabling resets faults on the way, and gives up on one that persists.
    let e = power_walk(&mut s, 3, PowerGoal::Enable, 3000).unwrap_err();
    assert!(e.contains("stays in Fault") && e.contains("0x3220"), "{e}");
}

#[test]
fn home_sets_the_position_read_back() {
    let o = cncgw(&["drive", "home", "1", "--method", "37", "--offset", "12.5"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert_eq!(o.stdout.trim(), "node 1 (axis x): homed with method 37; position now 12.5000 mm");
    let o = cncgw(&["drive", "home", "2", "--method", "35", "--offset", "-3"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!(o.stdout.contains("position now -3.0000 mm"), "{}", o.stdout);
    // The emulated Z has no limit switch fitted: method 17 ends in a homing error.
    let o = cncgw(&["drive", "home", "2", "--method", "17"]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("alarm 2017") && o.stderr.contains("homing error"), "{}", o.stderr);
    // Method 6 (home switch, index pulse): the emulated Z has no home switch either.
    let o = cncgw(&["drive", "home", "2", "--method", "6"]);
    assert_eq!(o.code, 1);
    assert!(o.stderr.contains("alarm 2017") && o.stderr.contains("homing error"), "{}", o.stderr);
    let o = cncgw(&["drive", "home", "2", "--method", "36"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("homing method 36 is not a CiA 402 method"), "{}", o.stderr);
}

fn jog_end(stdout: &str) -> f64 {
    // "axis x (node 1): 0.0000 → 10.0002 mm (target 10.0000)"
    let after = stdout.split('→').nth(1).expect("an arrow");
    after.split_whitespace().next().unwrap().parse().unwrap()
}

#[test]
fn jog_moves_to_and_by() {
    let o = cncgw(&["jog", "x", "--to", "10"]);
    assert_eq!(o.code, 0, "{}{}", o.stdout, o.stderr);
    assert!(o.stdout.starts_with("axis x (node 1): 0.0000 → "), "{}", o.stdout);
    let p = jog_end(&o.stdout);
    assert!((p - 10.0).abs() < 0.005, "x ended at {p}");
    let o = cncgw(&["jog", "z", "--by", "-20", "--speed", "3000"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let p = jog_end(&o.stdout);
    assert!((p + 20.0).abs() < 0.005, "z ended at {p}");
    // The spindle in degrees: the master holds the move's target after "target reached"
    // and lets the loop settle for up to 0.2 s (1000 counts per degree; the spindle's heavy
    // inertia is still some 20 counts short then — it was 80 when the master held the
    // actual position instead of the target).
    let o = cncgw(&["jog", "s1", "--by", "90", "--speed", "60"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert!((jog_end(&o.stdout) - 90.0).abs() <= 0.03, "{}", o.stdout);
}

#[test]
fn jog_refuses_what_it_cannot_do() {
    let o = cncgw(&["jog", "x", "--to", "500"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("outside axis x's travel -2 … 150 mm"), "{}", o.stderr);
    let o = cncgw(&["jog", "q", "--to", "1"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("no axis `q`") && o.stderr.contains("s1, x, z"), "{}", o.stderr);
    let o = cncgw(&["jog", "z", "--by", "1", "--speed", "99999"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("at most the axis's max_speed 12000"), "{}", o.stderr);
    // Exactly one of --to and --by (clap).
    let o = cncgw(&["jog", "z"]);
    assert_eq!(o.code, 2);
    let o = cncgw(&["jog", "z", "--to", "1", "--by", "1"]);
    assert_eq!(o.code, 2);
}

#[test]
fn buslog_writes_candump_format() {
    let f = tmp("boot.log");
    let before = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64();
    let o = cncgw(&["buslog", "-o", f.to_str().unwrap(), "--seconds", "1"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.stdout.trim(), format!("3 frame(s) logged to {}", f.display()));
    let text = std::fs::read_to_string(&f).unwrap();
    let mut ids = Vec::new();
    let mut last_t = 0.0;
    for line in text.lines() {
        // (1700000000.123456) iface ID#DATA
        let (t, rest) = line.strip_prefix('(').and_then(|l| l.split_once(") ")).unwrap_or_else(|| panic!("{line}"));
        let (sec, usec) = t.split_once('.').unwrap();
        assert_eq!(usec.len(), 6, "{line}");
        let t: f64 = format!("{sec}.{usec}").parse().unwrap();
        assert!(t >= last_t && (t - before).abs() < 60.0, "{line}");
        last_t = t;
        let mut parts = rest.split(' ');
        assert_eq!(parts.next(), Some("inproc"));
        let frame = parts.next().unwrap();
        assert_eq!(parts.next(), None);
        let (id, data) = frame.split_once('#').unwrap();
        ids.push((u16::from_str_radix(id, 16).unwrap(), data.to_string()));
    }
    // The three emulated drives' boot-up messages (NMT error control 0x700 + node, 0x00).
    assert_eq!(ids, vec![(0x701, "00".to_string()), (0x702, "00".into()), (0x703, "00".into())]);
    let o = cncgw(&["buslog", "-o", "/nonexistent-dir/x.log", "--seconds", "1"]);
    assert_eq!(o.code, 4);
    assert!(o.stderr.contains("cannot create"), "{}", o.stderr);
}

#[test]
fn monitor_once_prints_one_table() {
    let o = cncgw(&["monitor", "--once"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let lines: Vec<&str> = o.stdout.lines().collect();
    assert_eq!(lines.len(), 5, "{}", o.stdout);
    assert!(lines[0].contains("state") && lines[0].contains("position") && lines[0].contains("speed") && lines[0].contains("follow. error"));
    for (l, (node, axis)) in lines[1..4].iter().zip([(1, "x"), (2, "z"), (3, "s1")]) {
        let cols: Vec<&str> = l.split_whitespace().collect();
        assert_eq!(cols[0], node.to_string(), "{l}");
        assert_eq!(cols[1], axis, "{l}");
        assert_eq!(cols[2], "0x0250", "{l}");
        assert!(l.contains("Switch On Disabled"), "{l}");
        // Each figure with its unit: mm and mm/min, degrees and rpm for the spindle.
        let (pu, vu) = if axis == "s1" { ("deg", "rpm") } else { ("mm", "mm/min") };
        assert_eq!(&cols[cols.len() - 6..], ["0.0000", pu, "0.0000", vu, "0.0000", pu], "{l}");
    }
    assert!(lines[4].starts_with("bus inproc load "), "{}", lines[4]);
    let load: f64 = lines[4]["bus inproc load ".len()..].split(' ').next().unwrap().parse().unwrap();
    // Its own SDO traffic: 3 drives × 5 objects × 2 frames in about 0.1 s at 1 Mbit/s.
    assert!(load > 0.5 && load < 20.0, "{load}");
    // Not a terminal: one plain table after another, no escape codes.
    let o = cncgw(&["monitor", "--seconds", "1.2", "--interval-ms", "500"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    assert_eq!(o.stdout.matches("node axis").count(), 3, "{}", o.stdout);
    assert!(!o.stdout.contains('\x1b'));
}

#[test]
fn monitor_on_a_terminal_redraws_in_place() {
    // util-linux `script` gives the command a pseudo-terminal (bsdutils is essential in Debian).
    let cmd = format!("{} monitor --seconds 1.2 --interval-ms 500", env!("CARGO_BIN_EXE_cncgw"));
    let o = Command::new("script").args(["-qec", &cmd, "/dev/null"]).output().expect("util-linux `script`");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    // Three tables of five lines: the second and third go back up five lines first, and every
    // line is cleared before it is written.
    assert_eq!(out.matches("node axis").count(), 3, "{out}");
    assert_eq!(out.matches("\x1b[5A").count(), 2, "{out}");
    assert_eq!(out.matches("\x1b[2K").count(), 15, "{out}");
    assert!(out.starts_with("\x1b[2Knode axis"), "{out}");
}
