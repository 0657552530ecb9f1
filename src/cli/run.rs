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

pub fn run(program: &Path, machine: &MachineArgs, json: bool, trace: Option<&Path>, rt: &RtArgs) -> i32 {
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
    let (mut master, mut clock, _, what) = match super::open_bus(&cfg, &cfg_text, machine.bus.as_deref()) {
        Ok(b) => b,
        Err(e) => {
            eprintln!("error: {e}");
            return EXIT_SETUP;
        }
    };
    eprintln!("cncgw: {} on {what}", program.display());
    let rt = RtOptions { priority: rt.rt_priority, mlock: rt.mlock, cpu: rt.cpu };
    execute(&mut master, &mut *clock, &cfg, interp, lines, json, trace, &rt)
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

#[allow(clippy::too_many_arguments)] // one call site; the options are the CLI's
fn execute(
    drives: &mut dyn DriveBus,
    clock: &mut dyn Clock,
    cfg: &MachineConfig,
    mut interp: Interpreter,
    lines: u64,
    json: bool,
    trace: Option<&Path>,
    rt: &RtOptions,
) -> i32 {
    let spindle_drive = cfg.axes.values().position(|a| a.kind == AxisKind::Spindle);
    let cycle_ns = (cfg.machine.cycle_ms * 1e6).round() as u64;
    let mut lp = CycleLoop::new(drives, clock, Limits::from_config(cfg), spindle_drive, cycle_ns);
    if let Some(path) = trace {
        match Trace::csv(path, lp.drive_names()) {
            Ok(t) => lp.set_trace(t),
            Err(e) => {
                eprintln!("error: cannot write the trace {}: {e}", path.display());
                return EXIT_SETUP;
            }
        }
    }
    let mut summary = RunSummary::default();
    let start = match lp.start(&mut summary) {
        Ok(s) => s,
        Err(a) => {
            eprintln!("{a}");
            return EXIT_ALARM;
        }
    };
    interp.set_start_position(Pos { x: start[AX_X], y: start[AX_Y], z: start[AX_Z], c: start[AX_S] });
    let (tx, rx) = std::sync::mpsc::sync_channel(256);
    let producer = std::thread::Builder::new().name("interp".into()).spawn(move || {
        for m in interp {
            let stop = m.is_err();
            if tx.send(m).is_err() || stop {
                break;
            }
        }
    });
    if let Err(e) = producer {
        eprintln!("error: cannot start the interpreter thread: {e}");
        return EXIT_SETUP;
    }
    let bar = indicatif::ProgressBar::new(lines.max(1));
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} {elapsed_precise} line {pos}/{len} {wide_bar} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    // The cycle loop runs on this thread; set it up only now, so that the interpreter and
    // trace threads (already started) do not inherit the real-time policy or the pinning.
    for step in crate::motion::rt::apply(rt) {
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
    match r {
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
    }
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
