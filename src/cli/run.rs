//! `cncgw run`: run a part program on the embedded emulated machine or on a real bus.

use super::{load_config, MachineArgs};
use crate::canon::Pos;
use crate::config::{AxisKind, MachineConfig};
use crate::drives::DriveBus;
use crate::interp::Interpreter;
use crate::motion::cycle::{CycleLoop, RunSummary};
use crate::motion::rt::{RtOptions, RtStep};
use crate::motion::trace::{Trace, TraceData};
use crate::motion::{Limits, AX_S, AX_X, AX_Y, AX_Z};
use cncgw_bus::Clock;
use std::path::Path;

/// Exit codes.
pub const EXIT_OK: i32 = 0;
pub const EXIT_NOT_AT_END: i32 = 1;
pub const EXIT_PROGRAM_ERROR: i32 = 2;
pub const EXIT_ALARM: i32 = 3;
pub const EXIT_SETUP: i32 = 4;

/// Real-time setup of the cycle thread (real drives on a real PC). Each is optional; one the
/// system refuses is a warning, not an error.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct RtArgs {
    /// Run the cycle thread at this SCHED_FIFO priority (1–99; needs root, CAP_SYS_NICE or an
    /// rtprio limit).
    #[arg(long, value_name = "1-99")]
    pub rt_priority: Option<i32>,
    /// Lock all memory (mlockall) so that no page fault delays a cycle.
    #[arg(long)]
    pub mlock: bool,
    /// Pin the cycle thread to this CPU (e.g. one isolated with isolcpus=).
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
}

/// What `cncgw run` does besides running: the per-cycle trace and the real-time setup.
#[derive(Clone, Debug, Default)]
pub struct RunExtras<'a> {
    pub trace: Option<&'a Path>,
    pub rt: RtOptions,
}

pub fn run(program: &Path, machine: &MachineArgs, json: bool, state_dir: Option<&Path>, trace: Option<&Path>, rt: &RtArgs) -> i32 {
    let (cfg, cfg_text) = match load_config(machine.config.as_deref()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return EXIT_SETUP;
        }
    };
    // The whole program is checked before anything moves.
    let interp = match Interpreter::from_file(program, &cfg) {
        Ok(i) => i,
        Err(alarms) => {
            for a in &alarms {
                eprintln!("{a}");
            }
            eprintln!("{} error(s); nothing was moved", alarms.len());
            return EXIT_PROGRAM_ERROR;
        }
    };
    let lines = std::fs::read_to_string(program).map(|t| t.lines().count() as u64).unwrap_or(0);
    // Common variables #401–#600 survive power-off: load them, store them after the run.
    let vars_file = state_dir.map(Path::to_path_buf).or_else(crate::persist::default_state_dir).map(|d| crate::persist::CommonVarsFile::new(&d, &cfg.machine.name));
    let mut interp = interp;
    if let Some(f) = &vars_file {
        match f.load() {
            Ok(v) => interp.set_common_vars(v),
            Err(a) => {
                eprintln!("{a}");
                return EXIT_SETUP;
            }
        }
    }
    let mut modbus = crate::drives::modbus::ModbusDrives::new(&cfg);
    let bus_name = machine.bus.clone().unwrap_or_else(|| cfg.bus.interface.clone());
    // The CANopen bus is opened only if an axis is on it.
    let mut can = None;
    let mut clock: Box<dyn Clock> = Box::new(cncgw_bus::RealClock::new());
    let mut what = Vec::new();
    if cfg.has_canopen() {
        if !modbus.is_empty() && bus_name == "inproc" {
            eprintln!(
                "error: the embedded emulated bus (inproc) is CANopen only and runs in simulated time; a machine with Modbus axes runs in real time: give the CANopen axes a real bus (--bus vcan0, --bus socketcand://HOST:PORT/can0) and start the Modbus drives (e.g. sim-drives --modbus-tcp ADDR)"
            );
            return EXIT_SETUP;
        }
        match super::open_bus(&cfg, &cfg_text, machine.bus.as_deref()) {
            Ok((m, c, _, w)) => {
                can = Some(m);
                clock = c;
                what.push(w);
            }
            Err(e) => {
                eprintln!("error: {e}");
                return EXIT_SETUP;
            }
        }
    }
    for (name, l) in &cfg.modbus {
        what.push(format!("Modbus link {name} ({})", match l.transport {
            crate::config::LinkTransport::Tcp => format!("TCP {}", l.address.as_deref().unwrap_or("")),
            crate::config::LinkTransport::Rtu => format!("RTU {} {} baud", l.device.as_deref().unwrap_or(""), l.baud),
        }));
    }
    let mut parts: Vec<&mut dyn DriveBus> = Vec::new();
    if let Some(m) = can.as_mut() {
        parts.push(m);
    }
    if !modbus.is_empty() {
        parts.push(&mut modbus);
    }
    let order: Vec<String> = cfg.axes.keys().cloned().collect();
    let mut drives = match crate::drives::multi::MultiBus::new(parts, &order) {
        Ok(d) => d,
        Err(a) => {
            eprintln!("{a}");
            return EXIT_SETUP;
        }
    };
    eprintln!("cncgw: {} on {}", program.display(), what.join(" + "));
    let extras = RunExtras { trace, rt: RtOptions { priority: rt.rt_priority, mlock: rt.mlock, cpu: rt.cpu } };
    let (code, vars) = execute(&mut drives, &mut *clock, &cfg, program, interp, lines, json, &extras);
    if let (Some(f), Some(v)) = (&vars_file, vars) {
        if let Err(a) = f.save(&v) {
            eprintln!("{a}");
            return if code == EXIT_OK { EXIT_SETUP } else { code };
        }
    }
    code
}

/// `cncgw trace plot FILE.csv -o FILE.svg`.
pub fn trace_plot(file: &Path, out: &Path) -> i32 {
    let text = match std::fs::read_to_string(file) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: cannot read {}: {e}", file.display());
            return EXIT_SETUP;
        }
    };
    let data = match TraceData::parse(&text) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: {}: {e}", file.display());
            return EXIT_PROGRAM_ERROR;
        }
    };
    match crate::motion::trace::plot_svg(&data, out) {
        Ok(()) => {
            eprintln!("wrote {}", out.display());
            EXIT_OK
        }
        Err(e) => {
            eprintln!("error: cannot draw {}: {e}", out.display());
            EXIT_SETUP
        }
    }
}

#[allow(clippy::too_many_arguments)] // one call site, from `run`
fn execute(
    drives: &mut dyn DriveBus,
    clock: &mut dyn Clock,
    cfg: &MachineConfig,
    program: &Path,
    mut interp: Interpreter,
    lines: u64,
    json: bool,
    extras: &RunExtras,
) -> (i32, Option<std::collections::HashMap<u32, f64>>) {
    let spindle_drive = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
    let cycle_ns = (cfg.machine.cycle_ms * 1e6).round() as u64;
    let mut lp = CycleLoop::new(drives, clock, Limits::from_config(cfg), spindle_drive, cycle_ns);
    lp.set_watchdog(crate::motion::cycle::Watchdog::from_config(cfg));
    if let Some(path) = extras.trace {
        match Trace::csv(path, lp.drive_names()) {
            Ok(t) => lp.set_trace(t),
            Err(e) => {
                eprintln!("error: cannot write the trace {}: {e}", path.display());
                return (EXIT_SETUP, None);
            }
        }
    }
    let mut summary = RunSummary::default();
    let start = match lp.start(&mut summary) {
        Ok(s) => s,
        Err(a) => {
            eprintln!("{a}");
            return (EXIT_ALARM, None);
        }
    };
    let start_pos = Pos { x: start[AX_X], y: start[AX_Y], z: start[AX_Z], c: start[AX_S] };
    interp.set_start_position(start_pos);
    // Axes on links with their own cycle (Modbus): every spindle-synchronised move of the
    // program is checked against their cycle before anything moves.
    let mut slow = Vec::new();
    for d in 0..lp.drives.axis_count() {
        if let Some((link, link_what, cycle_s)) = lp.drives.link_cycle(d) {
            let name = lp.drives.axis_name(d).to_string();
            eprintln!("cncgw: axis {name}: Modbus link {link} ({link_what}), link cycle {:.0} ms", cycle_s * 1e3);
            let axis = if Some(d) == spindle_drive { "s".to_string() } else { name };
            slow.push(crate::sync::link_check::SlowAxis { axis, link, cycle_s });
        }
    }
    if !slow.is_empty() {
        if let Err(a) = check_links(program, cfg, &slow, start_pos) {
            lp.finish();
            eprintln!("{a}");
            return (EXIT_ALARM, None);
        }
    }
    // Limits before motion: a program whose path leaves the travel or enters the G22 area
    // is refused before the first move.
    if let Err(a) = crate::motion::guard::check_program_file(program, cfg, start_pos, interp.common_vars()) {
        lp.finish();
        eprintln!("{a}");
        eprintln!("nothing was moved");
        return (EXIT_ALARM, None);
    }
    let (tx, rx) = std::sync::mpsc::sync_channel(256);
    // The interpreter runs ahead of motion, macro statements included (as on a Fanuc, where
    // macro statements are executed while the blocks before them are buffered); it hands
    // back the common variables when it ends, to be stored.
    let producer = std::thread::Builder::new().name("interp".into()).spawn(move || {
        let mut it = interp;
        for m in it.by_ref() {
            let stop = m.is_err();
            if tx.send(m).is_err() || stop {
                break;
            }
        }
        it.common_vars().clone()
    });
    let producer = match producer {
        Ok(h) => h,
        Err(e) => {
            eprintln!("error: cannot start the interpreter thread: {e}");
            lp.finish();
            return (EXIT_SETUP, None);
        }
    };
    let bar = indicatif::ProgressBar::new(lines.max(1));
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {elapsed_precise} line {pos}/{len} {wide_bar} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    // The cycle loop runs on this thread; set it up only now, so that the interpreter and
    // trace threads (already started) do not inherit the real-time policy or the pinning.
    for step in crate::motion::rt::apply(&extras.rt) {
        match step {
            RtStep::Done(m) => eprintln!("cncgw: {m}"),
            RtStep::Refused(m) => eprintln!("warning: {m}"),
        }
    }
    let r = lp.run(start, rx, &mut summary, &mut |p| {
        bar.set_position(p.line as u64);
        bar.set_message(format!(
            "X{:.3} Z{:.3} F{:.0} S{:.0}",
            p.pos[AX_X] * 2.0,
            p.pos[AX_Z],
            p.feed,
            p.spindle_rpm
        ));
    });
    bar.finish_and_clear();
    lp.finish();
    if let Some(t) = lp.take_trace() {
        match t.finish() {
            Ok(st) if st.dropped > 0 => {
                eprintln!("trace: {} cycles written, {} lost (the disk was too slow)", st.rows, st.dropped)
            }
            Ok(st) => eprintln!("trace: {} cycles written", st.rows),
            Err(e) => eprintln!("error: writing the trace: {e}"),
        }
    }
    let vars = producer.join().ok();
    let code = match r {
        Err(a) => {
            print_summary(&summary, json);
            eprintln!("{a}");
            eprintln!("the program stopped at this alarm; the axes were brought to a controlled stop");
            EXIT_ALARM
        }
        Ok(()) => {
            print_summary(&summary, json);
            if summary.at_program_end() {
                EXIT_OK
            } else {
                eprintln!("error: an axis did not reach the program's end point within one count");
                EXIT_NOT_AT_END
            }
        }
    };
    (code, vars)
}

/// Run the interpreter over the whole program once and check each synchronised move
/// against the slow links (bounded: a program that never ends is checked as it runs up to
/// two million moves).
fn check_links(program: &Path, cfg: &MachineConfig, slow: &[crate::sync::link_check::SlowAxis], start: Pos) -> Result<(), crate::Alarm> {
    let Ok(mut pre) = Interpreter::from_file(program, cfg) else { return Ok(()) };
    pre.set_start_position(start);
    let mut check = crate::sync::link_check::LinkCheck::new(slow, cfg.machine.sync_error_limit_um, start);
    for m in pre.take(2_000_000) {
        match m {
            Ok(m) => check.check(&m)?,
            Err(_) => break, // the run itself reports program alarms at their block
        }
    }
    Ok(())
}

fn print_summary(s: &RunSummary, json: bool) {
    if json {
        let axes: Vec<_> = s
            .axes
            .iter()
            .map(|a| {
                serde_json::json!({
                    "axis": a.name,
                    "max_following_error": a.max_following_error,
                    "final_actual_counts": a.final_actual_counts,
                    "final_target_counts": a.final_target_counts,
                    "program_end_counts": a.program_end_counts,
                })
            })
            .collect();
        let v = serde_json::json!({
            "blocks": s.blocks,
            "moves": s.moves,
            "machining_time_s": s.machining_time_s,
            "enable_time_s": s.enable_time_s,
            "cycles": s.cycles,
            "overruns": s.overruns,
            "simulated": s.simulated,
            "at_program_end": s.at_program_end(),
            "axes": axes,
        });
        println!("{v}");
        return;
    }
    println!(
        "blocks {}  moves {}  machining time {:.3} s{}  cycles {} (overruns {})  drives enabled after {:.3} s",
        s.blocks,
        s.moves,
        s.machining_time_s,
        if s.simulated { " (simulated)" } else { "" },
        s.cycles,
        s.overruns,
        s.enable_time_s
    );
    println!("{:<5} {:>18} {:>14} {:>14} {:>14}  result", "axis", "max follow. error", "final actual", "final target", "program end");
    for a in &s.axes {
        let unit = if a.name.starts_with('s') { "deg" } else { "mm" };
        let (end, ok) = match a.program_end_counts {
            Some(e) => (e.to_string(), if (a.final_actual_counts - e).abs() <= 1 { "ok (within 1 count)" } else { "NOT AT END POINT" }),
            None => ("-".to_string(), "-"),
        };
        println!(
            "{:<5} {:>14.4} {:<3} {:>14} {:>14} {:>14}  {}",
            a.name,
            a.max_following_error,
            unit,
            a.final_actual_counts,
            a.final_target_counts,
            end,
            ok
        );
    }
}
