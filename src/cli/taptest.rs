//! `cncgw tap-test`: what a service engineer does at commissioning — a rigid tap in the air
//! on the configured machine, with the spindle–Z sync error measured from the drives' actual
//! positions and drawn.
//!
//! The program is the Type A dialect the interpreter runs (manual 000, rigid tapping with
//! No.5200#0 = 0: `M29 S` before `G84`, per-revolution feed so F is the lead):
//!
//! ```text
//! G21
//! G99
//! G0 X<present> Z<R>        (R = present Z + clearance, within the travel)
//! M29 S<rpm>
//! G84 X<present> Z<R − depth> F<lead>
//! G80
//! M30
//! ```
//!
//! X stays where it is and Z only goes up before the tap: the engineer places the tool with
//! `depth` of free air below it. With `--dry` nothing is enabled: the present position is
//! read over SDO, the program is written and run through the interpreter, and the travel,
//! the speeds and the feed are checked.

use super::exit;
use super::run::{ExecOpts, Job, OperatorArgs, RunExtras};
use super::MachineArgs;
use super::OrSetup;
use crate::canon::{MoveKind, Pos};
use crate::config::MachineConfig;
use crate::control::trace::TraceData;
use crate::interp::Interpreter;
use serde_json::json;
use std::cell::RefCell;
use std::path::{Path, PathBuf};

/// The tap cannot be done from the position the drives report (controller range 2400–2499).
pub const ALARM_TAP_PLAN: u32 = crate::alarm::TAP_PLAN;

/// The command line of `cncgw tap-test`.
#[derive(clap::Args, Debug, Clone)]
pub struct TapArgs {
    /// Thread lead, mm per revolution (right-hand: the spindle turns forward going in).
    #[arg(long)]
    pub lead: f64,
    /// Depth of the tap, mm, from its R point down (−Z).
    #[arg(long)]
    pub depth: f64,
    /// Spindle speed going in, rpm.
    #[arg(long)]
    pub rpm: f64,
    /// How far above the present Z the tap starts (its R point), mm; less where the travel
    /// ends sooner.
    #[arg(long, default_value_t = 2.0)]
    pub clearance: f64,
    /// Plan and check only: nothing is enabled, nothing moves.
    #[arg(long)]
    pub dry: bool,
    /// The plot to write (SVG, or PNG for a .png name through rsvg-convert); the trace goes
    /// next to it as .csv.
    #[arg(long, short = 'o', default_value = "tap-test.svg", value_name = "FILE.svg")]
    pub out: PathBuf,
    /// Print the figures as JSON.
    #[arg(long)]
    pub json: bool,
    /// Confirm the motion on a real bus.
    #[arg(long)]
    pub yes: bool,
}

/// The tap as planned from a start position.
#[derive(Clone, Debug)]
pub struct TapPlan {
    pub program: String,
    pub x_diameter: f64,
    pub r_z: f64,
    pub bottom_z: f64,
    /// Signed lead of the strokes (what the interpreter made of F: negative = Z goes down as
    /// the spindle angle grows).
    pub signed_lead: f64,
    /// Source lines of the tap strokes.
    pub tap_lines: Vec<u32>,
    /// Z feed at S, mm/min.
    pub feed_mm_min: f64,
}

/// How far above its + travel limit Z may stand for the tap to start at the limit: the
/// in-position width before a rigid tap ([`crate::motion::INPOS_MM`]) or one count
/// where a count is coarser; a small margin for the count's own rounding.
fn at_limit_width(counts_per_unit: f64) -> f64 {
    let count = 1.0 / counts_per_unit.abs().max(1e-9);
    count.max(crate::motion::INPOS_MM) * (1.0 + 1e-6)
}

fn spindle_name(cfg: &MachineConfig) -> Option<String> {
    // The work spindle (a polygon machine's tool spindle is a spindle too).
    cfg.spindle_index().and_then(|i| cfg.axes.keys().nth(i).cloned())
}

/// Write the program for a tap from `start` (machine position, X a radius) and check it.
/// The program is in machine coordinates — the tap is made where the tool stands — so no
/// tool or work offset applies to it: the stored offsets (`cncgw offsets`) are not read.
pub fn plan(cfg: &MachineConfig, a: &TapArgs, start: Pos) -> Result<TapPlan, String> {
    let pos = |v: f64| v.is_finite() && v > 0.0;
    if !(pos(a.lead) && pos(a.depth) && pos(a.rpm) && a.clearance.is_finite() && a.clearance >= 0.0) {
        return Err("--lead, --depth and --rpm must be positive numbers, --clearance zero or more".into());
    }
    let Some(sname) = spindle_name(cfg) else {
        return Err("the configuration has no spindle (kind = \"spindle\"): a rigid tap needs one".into());
    };
    let Some(z) = cfg.axes.get("z") else {
        return Err("the configuration has no z axis: the tap runs along Z".into());
    };
    let sp = &cfg.axes[&sname];
    if a.rpm > sp.max_speed {
        return Err(format!("S{} is above the spindle's max_speed {} rpm (axes.{sname}.max_speed); lower --rpm", a.rpm, sp.max_speed));
    }
    let feed = a.lead * a.rpm;
    if feed > z.max_speed {
        return Err(format!(
            "lead {} × S{} = {feed:.0} mm/min is above Z's max_speed {} mm/min (axes.z.max_speed); lower --rpm to at most {:.0}",
            a.lead,
            a.rpm,
            z.max_speed,
            z.max_speed / a.lead
        ));
    }
    let mut r_z = start.z + a.clearance;
    if let Some(hi) = z.max {
        r_z = r_z.min(hi);
    }
    // Never below the present position: the tool only goes up before the tap.
    r_z = r_z.max(start.z);
    if let Some(hi) = z.max {
        // A drive comes to rest within a count or so of its set-point: after a tap that ended
        // at the + limit Z may stand just above it. Within the in-position width R is the
        // limit itself (a move of that width down); further out nothing moves.
        let width = at_limit_width(z.counts_per_unit);
        if r_z > hi && start.z - hi <= width {
            r_z = hi;
        } else if r_z > hi {
            return Err(format!(
                "Z stands at Z{:.4}, {:.4} mm above its travel limit {hi} (axes.z.max; the tap may start up to {width:.4} mm above it): the tool only goes up before a tap; jog Z into the travel (`cncgw jog z --to {hi}`) and run the tap-test again",
                start.z,
                start.z - hi
            ));
        }
    }
    let bottom = r_z - a.depth;
    if let Some(lo) = z.min {
        if bottom < lo {
            return Err(format!(
                "the tap's bottom Z{bottom:.3} is below Z's travel {lo} (axes.z.min): the tap starts at Z{r_z:.3} (present Z{:.3} + clearance); jog Z up (`cncgw jog z --to …`) or make --depth at most {:.3}",
                start.z,
                r_z - lo
            ));
        }
    }
    let xd = start.x * 2.0;
    let program = format!(
        "(cncgw tap-test: lead {lead} depth {depth} S{rpm}, in the air)\nG21\nG99\nG0 X{xd:.4} Z{r_z:.4}\nM29 S{rpm}\nG84 X{xd:.4} Z{bottom:.4} F{lead}\nG80\nM30\n",
        lead = a.lead,
        depth = a.depth,
        rpm = a.rpm,
    );
    let mut it =
        Interpreter::from_source("tap-test.nc", &program, cfg).map_err(|al| al.iter().map(|x| x.to_string()).collect::<Vec<_>>().join("\n"))?;
    it.set_start_position(start);
    let mut signed_lead = None;
    let mut tap_lines = Vec::new();
    for m in it.take(10_000) {
        let m = m.map_err(|al| al.to_string())?;
        if let MoveKind::Tap { lead, .. } = m.kind {
            signed_lead.get_or_insert(lead);
            if !tap_lines.contains(&m.src.line) {
                tap_lines.push(m.src.line);
            }
        }
    }
    let Some(signed_lead) = signed_lead else {
        return Err("the interpreter made no rigid-tap stroke of the program (is No.5210 the M29 code?)".into());
    };
    Ok(TapPlan { program, x_diameter: xd, r_z, bottom_z: bottom, signed_lead, tap_lines, feed_mm_min: feed })
}

/// Max |e| and RMS e of a series.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Stat {
    pub max: f64,
    pub rms: f64,
    pub cycles: usize,
}

fn stat(v: &[f64]) -> Stat {
    if v.is_empty() {
        return Stat::default();
    }
    let max = v.iter().fold(0.0f64, |m, e| m.max(e.abs()));
    let rms = (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt();
    Stat { max, rms, cycles: v.len() }
}

/// The figures of one tap.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TapFigures {
    /// (Z − Z_R) − lead·(θ − θ_R)/360 from the actual positions, µm, over the whole tap.
    pub sync: Stat,
    /// The spindle accelerating into the hole (to its top speed going in).
    pub entry: Stat,
    /// From top speed going in, through the stop at the bottom, to top speed coming out.
    pub reversal: Stat,
    /// From top speed coming out to the stop at R.
    pub exit: Stat,
    /// Largest following error of the spindle, degrees, and of Z, µm, during the tap.
    pub spindle_ferr_deg: f64,
    pub z_ferr_um: f64,
    /// Highest spindle speed measured, rpm.
    pub peak_rpm: f64,
    /// The controller's own sync monitor (`sync_err_um` of the trace): max |e|, µm.
    pub monitor_max_um: f64,
}

/// The sync error of a tap over its cycles, and where its phases are.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TapSeries {
    /// Trace rows of the tap: from the first cycle the spindle turns to the last of the tap.
    pub first: usize,
    pub last: usize,
    /// (Z − Z_R) − lead·(θ − θ_R)/360 from the actual positions, µm, per row `first..=last`.
    pub err_um: Vec<f64>,
    /// The spindle turned back out (a tap stopped on the way in has no reversal or exit).
    pub reversed: bool,
    /// Inclusive index ranges into `err_um`: entry, reversal, exit.
    pub entry: (usize, usize),
    pub reversal: (usize, usize),
    pub exit: (usize, usize),
}

/// The tap's sync error and phases from a trace (`spindle`: the spindle's drive name).
pub fn series(data: &TraceData, spindle: &str, lead: f64, tap_lines: &[u32]) -> Result<TapSeries, String> {
    let col = |n: &str| data.column(n).ok_or_else(|| format!("the trace has no column {n}"));
    let (line, s_cmd, s_act) = (col("line")?, col(&format!("{spindle}_cmd"))?, col(&format!("{spindle}_act"))?);
    let (z_cmd, z_act, t) = (col("z_cmd")?, col("z_act")?, col("t_s")?);
    let in_tap = |i: usize| tap_lines.iter().any(|&l| line[i] as u32 == l);
    let first = (0..line.len()).find(|&i| in_tap(i)).ok_or("the trace holds no cycle of the tap: did it run?")?;
    let last = (0..line.len()).rfind(|&i| in_tap(i)).unwrap_or(first);
    // The commanded R point and spindle angle the tap starts from.
    let r0 = first.checked_sub(1).ok_or("the trace starts inside the tap")?;
    let (z0, th0) = (z_cmd[r0], s_cmd[r0]);
    let first = (first..=last).find(|&i| s_cmd[i] != th0).ok_or("the spindle never turned in the tap")?;
    let err_um: Vec<f64> = (first..=last).map(|i| ((z_act[i] - z0) - lead * (s_act[i] - th0) / 360.0) * 1000.0).collect();
    // Commanded spindle speed per cycle, rpm, signed.
    let v: Vec<f64> = (first..=last)
        .map(|i| {
            let dt = (t[i] - t[i - 1]).max(1e-6);
            (s_cmd[i] - s_cmd[i - 1]) / 360.0 / dt * 60.0
        })
        .collect();
    let dir = v.iter().copied().find(|x| *x != 0.0).unwrap_or(1.0).signum();
    let peak_in = v.iter().filter(|x| **x * dir > 0.0).fold(0.0f64, |m, x| m.max(x.abs()));
    let peak_out = v.iter().filter(|x| **x * dir < 0.0).fold(0.0f64, |m, x| m.max(x.abs()));
    let near = |x: f64, p: f64| x.abs() >= 0.98 * p && p > 0.0;
    let top_in_first = v.iter().position(|x| *x * dir > 0.0 && near(*x, peak_in)).unwrap_or(0);
    let top_in_last = v.iter().rposition(|x| *x * dir > 0.0 && near(*x, peak_in)).unwrap_or(top_in_first);
    let top_out_first = v.iter().position(|x| *x * dir < 0.0 && near(*x, peak_out)).unwrap_or(v.len().saturating_sub(1));
    let top_out_last = v.iter().rposition(|x| *x * dir < 0.0 && near(*x, peak_out)).unwrap_or(top_out_first);
    let end = err_um.len().saturating_sub(1);
    Ok(TapSeries {
        first,
        last,
        err_um,
        reversed: peak_out > 0.0,
        entry: (0, top_in_first.min(end)),
        reversal: (top_in_last.min(end), top_out_first.min(end)),
        exit: (top_out_last.min(end), end),
    })
}

/// Figures from a trace of the tap (`spindle`: the spindle's drive name).
pub fn figures(data: &TraceData, spindle: &str, lead: f64, tap_lines: &[u32]) -> Result<TapFigures, String> {
    let s = series(data, spindle, lead, tap_lines)?;
    let col = |n: &str| data.column(n).ok_or_else(|| format!("the trace has no column {n}"));
    let (s_ferr, z_ferr, rpm, mon) = (col(&format!("{spindle}_ferr"))?, col("z_ferr")?, col("spindle_rpm")?, col("sync_err_um")?);
    let seg = |(a, b): (usize, usize)| stat(s.err_um.get(a..=b).unwrap_or(&[]));
    let range = s.first..=s.last;
    Ok(TapFigures {
        sync: stat(&s.err_um),
        entry: seg(s.entry),
        reversal: seg(s.reversal),
        exit: seg(s.exit),
        spindle_ferr_deg: range.clone().map(|i| s_ferr[i].abs()).fold(0.0, f64::max),
        z_ferr_um: range.clone().map(|i| z_ferr[i].abs() * 1000.0).fold(0.0, f64::max),
        peak_rpm: range.clone().map(|i| rpm[i].abs()).fold(0.0, f64::max),
        monitor_max_um: range.map(|i| mon[i].abs()).fold(0.0, f64::max),
    })
}

/// The verdict a tap-test shows and prints.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    Pass,
    Fail,
    Stopped,
}

impl Verdict {
    pub fn word(self) -> &'static str {
        match self {
            Verdict::Pass => "PASS",
            Verdict::Fail => "FAIL",
            Verdict::Stopped => "STOPPED BY AN ALARM",
        }
    }
}

/// Phase colours: entry, reversal, exit.
const PHASES: [(&str, crate::plot::Rgb); 3] = [("entry", (0, 114, 178)), ("reversal", (230, 159, 0)), ("exit", (204, 121, 167))];

/// The tap-test picture: the verdict on top; the sync error against the limit band; the
/// same error at its own scale; spindle speed; Z command and actual — each with the entry,
/// reversal and exit phases shaded, over the tap (plus 0.1 s either side).
pub fn picture(data: &TraceData, s: &TapSeries, f: &TapFigures, heading: &str, limit_um: f64, verdict: Verdict) -> Result<String, String> {
    use crate::plot::{Band, Panel, Series, Span, COMMAND, PALETTE};
    let t = data.column("t_s").ok_or("the trace has no t_s column")?;
    let col = |n: &str| data.column(n).ok_or_else(|| format!("the trace has no column {n}"));
    let (z_cmd, z_act, rpm) = (col("z_cmd")?, col("z_act")?, col("spindle_rpm")?);
    let (tf, tl) = (t[s.first], t[s.last]);
    let a = t.iter().position(|x| *x >= tf - 0.1).unwrap_or(0);
    let b = t.iter().rposition(|x| *x <= tl + 0.1).unwrap_or(t.len() - 1);
    let tw = &t[a..=b];
    // The error is defined inside the tap only; outside it the line is left out (NaN).
    let err: Vec<f64> = (a..=b).map(|i| if (s.first..=s.last).contains(&i) { s.err_um[i - s.first] } else { f64::NAN }).collect();
    let stats = [&f.entry, &f.reversal, &f.exit];
    let reached = if s.reversed { 3 } else { 1 };
    let spans: Vec<Span> = [s.entry, s.reversal, s.exit]
        .iter()
        .zip(PHASES)
        .zip(stats)
        .take(reached)
        .map(|((&(i, j), (n, c)), st)| Span { t0: t[s.first + i], t1: t[s.first + j], name: format!("{n}: max {:.2} µm", st.max), colour: c })
        .collect();
    let e_line = |w: f64| Series { name: "sync error".into(), v: err.clone(), colour: (0, 0, 0), dashed: false, width: w };
    let panels = vec![
        Panel {
            title: format!("sync error (Z − Z_R) − lead·(θ − θ_R)/360, µm, against the limit ±{limit_um} µm"),
            series: vec![e_line(1.5)],
            bands: vec![Band { lo: -limit_um, hi: limit_um, name: format!("limit ±{limit_um} µm"), colour: (0, 158, 115) }],
            ..Panel::default()
        },
        Panel {
            title: "sync error, detail, by phase (µm)".into(), series: vec![e_line(1.2)], bands: vec![], spans: spans.clone(), span_names: true
        },
        Panel {
            title: "spindle speed, measured (rpm)".into(),
            series: vec![Series { name: "spindle rpm".into(), v: rpm[a..=b].to_vec(), colour: PALETTE[2], dashed: false, width: 1.5 }],
            bands: vec![],
            spans: spans.clone(),
            span_names: false,
        },
        Panel {
            title: "Z position (mm)".into(),
            series: vec![
                Series { name: "z actual".into(), v: z_act[a..=b].to_vec(), colour: PALETTE[0], dashed: false, width: 2.5 },
                Series { name: "z command".into(), v: z_cmd[a..=b].to_vec(), colour: COMMAND, dashed: true, width: 1.2 },
            ],
            bands: vec![],
            spans,
            span_names: false,
        },
    ];
    let (vc, detail) = match verdict {
        Verdict::Pass => ((0, 140, 60), format!("max {:.2} µm < limit {limit_um} µm ({:.0} % of it)", f.sync.max, 100.0 * f.sync.max / limit_um)),
        Verdict::Fail => ((200, 0, 0), format!("max {:.2} µm ≥ limit {limit_um} µm", f.sync.max)),
        Verdict::Stopped => ((200, 0, 0), format!("figures up to the stop: max {:.2} µm, limit {limit_um} µm", f.sync.max)),
    };
    let stopped_in = if s.reversed { "" } else { "; stopped on the way in: no reversal, no exit" };
    let header = vec![
        (heading.to_string(), 14, (0, 0, 0), "title"),
        (verdict.word().to_string(), 22, vc, "verdict"),
        (format!("sync error {detail}; RMS {:.2} µm over {} cycles{stopped_in}", f.sync.rms, f.sync.cycles), 13, vc, "verdict-detail"),
    ];
    crate::plot::time_panels(tw, &header, &panels, heading)
}

fn stat_json(s: &Stat) -> serde_json::Value {
    json!({"max_um": s.max, "rms_um": s.rms, "cycles": s.cycles})
}

fn plan_json(p: &TapPlan) -> serde_json::Value {
    json!({
        "program": p.program,
        "x_diameter": p.x_diameter,
        "r_z": p.r_z,
        "bottom_z": p.bottom_z,
        "signed_lead": p.signed_lead,
        "feed_mm_min": p.feed_mm_min,
    })
}

/// The present machine position of x and z, read without enabling anything: over SDO
/// (CANopen) or from the position registers (Modbus).
fn present_position(machine: &MachineArgs, cfg: &MachineConfig) -> Result<Pos, String> {
    let mut p = Pos::ZERO;
    let mut session = None;
    let mut links = std::collections::BTreeMap::new();
    for (name, slot) in [("x", &mut p.x), ("z", &mut p.z)] {
        let Some(ax) = cfg.axes.get(name) else { continue };
        if let Some(l) = &ax.modbus {
            if !links.contains_key(l) {
                let link = cfg.modbus.get(l).ok_or_else(|| format!("no Modbus link {l}"))?;
                links.insert(l.clone(), super::mbus::Client::connect(link).map_err(|e| format!("Modbus link {l}: {e}"))?);
            }
            let c = links.get_mut(l).ok_or("Modbus link")?;
            *slot = super::mbus::read_drive(c, name, ax).map_err(|e| format!("axis {name}: {e}"))?.position;
            continue;
        }
        if session.is_none() {
            session = Some(super::open_session(machine)?);
        }
        let s = session.as_mut().ok_or("no session")?;
        let d = s
            .master
            .sdo_upload(&mut *s.clock, ax.node, cncgw_bus::canopen::od::POSITION_ACTUAL, 0)
            .map_err(|e| format!("node {}: reading the position 0x6064: {}", ax.node, super::diag::sdo_error_text(&e)))?;
        if d.len() < 4 {
            return Err(format!("node {}: the position 0x6064 answered {} byte(s)", ax.node, d.len()));
        }
        *slot = i32::from_le_bytes([d[0], d[1], d[2], d[3]]) as f64 / ax.counts_per_unit;
    }
    Ok(p)
}

fn print_plan(p: &TapPlan, a: &TapArgs) {
    println!(
        "rigid tap in the air: lead {} mm, depth {} mm, S{} (Z feed {:.0} mm/min), X{:.3} from Z{:.3} (R) to Z{:.3}",
        a.lead, a.depth, a.rpm, p.feed_mm_min, p.x_diameter, p.r_z, p.bottom_z
    );
}

/// `cncgw tap-test`.
pub fn tap_test(machine: &MachineArgs, a: &TapArgs, op: &OperatorArgs) -> i32 {
    let (cfg, cfg_text) = match super::machine_config(machine).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    // The arguments are checked against the machine before anything is opened.
    if let Err(e) = plan(&cfg, a, Pos::ZERO).map(|_| ()).or_else(|e| if e.contains("travel") { Ok(()) } else { Err(e) }) {
        eprintln!("error: {e}");
        return exit::INPUT;
    }
    if a.dry {
        let start = match present_position(machine, &cfg).or_setup() {
            Ok(p) => p,
            Err(code) => return code,
        };
        return match plan(&cfg, a, start) {
            Ok(p) => {
                if a.json {
                    println!(
                        "{}",
                        json!({"dry": true, "feasible": true, "plan": plan_json(&p), "sync_error_limit_um": cfg.machine.sync_error_limit_um})
                    );
                } else {
                    print_plan(&p, a);
                    println!("feasible: within the travel, the spindle's and Z's speeds; the interpreter accepts the program:");
                    print!("{}", p.program);
                    println!("(dry run: nothing was enabled or moved)");
                }
                exit::OK
            }
            Err(e) => {
                if a.json {
                    println!("{}", json!({"dry": true, "feasible": false, "error": e}));
                } else {
                    eprintln!("error: {e}");
                }
                exit::INPUT
            }
        };
    }
    if let Err(c) = super::service::confirm_motion(machine, a.yes, "a rigid tap in the air (spindle and Z)") {
        return c;
    }
    let csv = a.out.with_extension("csv");
    let planned: RefCell<Option<Result<TapPlan, String>>> = RefCell::new(None);
    let job = Job {
        name: format!("tap-test (lead {} depth {} S{})", a.lead, a.depth, a.rpm),
        source: String::new(),
        first: None,
        make: Box::new(|start| {
            let p = plan(&cfg, a, start);
            let r = match &p {
                Ok(p) => Interpreter::from_source("tap-test.nc", &p.program, &cfg),
                Err(e) => Err(vec![crate::Alarm::new(ALARM_TAP_PLAN, format!("tap-test: {e}"))]),
            };
            planned.borrow_mut().get_or_insert(p);
            r
        }),
        feed: None,
    };
    let mut opts = ExecOpts {
        json: false,
        print_summary: false,
        extras: RunExtras { trace: Some(&csv), ..RunExtras::default() },
        operator: None,
        pace: op.realtime,
        live: false,
    };
    let (code, _, _) = super::run::with_operator(op, &mut opts, |o| super::run::run_job(&cfg, &cfg_text, machine, job, o));
    let Some(Ok(p)) = planned.into_inner() else {
        return if code == exit::OK { exit::INPUT } else { code };
    };
    // After an alarm in the tap (the sync monitor's 2307, typically) the figures up to the
    // stop are what the engineer needs most: report them too.
    if !matches!(code, exit::OK | exit::NOT_MET | exit::ALARM) {
        if a.json {
            println!("{}", json!({"dry": false, "plan": plan_json(&p), "exit_code": code, "trace": csv}));
        }
        return code;
    }
    report(&cfg, a, &p, &csv, code)
}

/// Figures from the trace, the plot, the verdict.
fn report(cfg: &MachineConfig, a: &TapArgs, p: &TapPlan, csv: &Path, run_code: i32) -> i32 {
    let data = match std::fs::read_to_string(csv).map_err(|e| e.to_string()).and_then(|t| TraceData::parse(&t)) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: the trace {}: {e}", csv.display());
            return exit::SETUP;
        }
    };
    let spindle = spindle_name(cfg).unwrap_or_default();
    let f = match figures(&data, &spindle, p.signed_lead, &p.tap_lines) {
        Ok(f) => f,
        Err(e) => {
            if run_code != exit::OK {
                return run_code; // stopped before the tap: the alarm said why
            }
            eprintln!("error: {}: {e}", csv.display());
            return exit::ALARM;
        }
    };
    let limit = cfg.machine.sync_error_limit_um;
    let ok = f.sync.max < limit;
    let verdict = if run_code == exit::ALARM {
        Verdict::Stopped
    } else if ok {
        Verdict::Pass
    } else {
        Verdict::Fail
    };
    let heading = format!("tap-test: rigid tap in the air, lead {} mm, depth {} mm, S{} — trace {}", a.lead, a.depth, a.rpm, csv.display());
    let plot = series(&data, &spindle, p.signed_lead, &p.tap_lines)
        .and_then(|s| picture(&data, &s, &f, &heading, limit, verdict))
        .and_then(|svg| crate::plot::save(&a.out, &svg));
    if let Err(e) = &plot {
        eprintln!("error: cannot draw {}: {e}", a.out.display());
    }
    let code = if plot.is_err() {
        exit::SETUP
    } else if run_code != exit::OK {
        run_code
    } else if ok {
        exit::OK
    } else {
        exit::NOT_MET
    };
    if a.json {
        println!(
            "{}",
            json!({
                "dry": false,
                "plan": plan_json(p),
                "sync_error": {
                    "max_um": f.sync.max, "rms_um": f.sync.rms, "cycles": f.sync.cycles,
                    "entry": stat_json(&f.entry), "reversal": stat_json(&f.reversal), "exit": stat_json(&f.exit),
                },
                "following_error": {"spindle_deg": f.spindle_ferr_deg, "z_um": f.z_ferr_um},
                "peak_rpm": f.peak_rpm,
                "monitor_max_um": f.monitor_max_um,
                "sync_error_limit_um": limit,
                "within_limit": ok,
                "stopped_by_alarm": run_code == exit::ALARM,
                "trace": csv,
                "plot": a.out,
                "exit_code": code,
            })
        );
    } else {
        print_plan(p, a);
        println!("sync error Z − lead·θ/360 from the actual positions ({} cycles):", f.sync.cycles);
        println!("  {:<9} {:>10} {:>10}", "", "max µm", "RMS µm");
        for (n, s) in [("whole tap", &f.sync), ("entry", &f.entry), ("reversal", &f.reversal), ("exit", &f.exit)] {
            println!("  {n:<9} {:>10.2} {:>10.2}", s.max, s.rms);
        }
        println!(
            "following error: spindle {:.3}°, Z {:.1} µm; peak speed {:.0} rpm; sync monitor max {:.2} µm",
            f.spindle_ferr_deg, f.z_ferr_um, f.peak_rpm, f.monitor_max_um
        );
        if f.peak_rpm < 0.97 * a.rpm {
            println!(
                "  (S{} was not reached: {} mm is too short for the spindle's acceleration (No.5261); a deeper tap or a lower S runs at full speed)",
                a.rpm, a.depth
            );
        }
        println!(
            "{} (limit {limit} µm, machine.sync_error_limit_um); trace {}, plot {}",
            match verdict {
                Verdict::Stopped => format!("{} (above): figures up to the stop", verdict.word()),
                Verdict::Pass => verdict.word().to_string(),
                Verdict::Fail => format!("{}: the sync error reached the limit — check the drives' tuning, or lower S", verdict.word()),
            },
            csv.display(),
            a.out.display()
        );
    }
    code
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(lead: f64, depth: f64, rpm: f64) -> TapArgs {
        TapArgs { lead, depth, rpm, clearance: 2.0, dry: true, out: "t.svg".into(), json: false, yes: false }
    }

    #[test]
    fn plan_starts_above_and_checks_the_machine() {
        let cfg = MachineConfig::embedded();
        let p = plan(&cfg, &args(1.5, 30.0, 3000.0), Pos::xz(10.0, 0.0)).unwrap();
        assert_eq!((p.r_z, p.bottom_z, p.x_diameter), (2.0, -28.0, 20.0));
        assert_eq!(p.signed_lead, -1.5, "right-hand: Z goes down as the angle grows");
        assert_eq!(p.feed_mm_min, 4500.0);
        assert!(p.program.contains("M29 S3000\nG84 X20.0000 Z-28.0000 F1.5\n"), "{}", p.program);
        // Near the top of the travel (Z max 5) the clearance shrinks.
        let p = plan(&cfg, &args(1.5, 30.0, 3000.0), Pos::xz(0.0, 4.0)).unwrap();
        assert_eq!(p.r_z, 5.0);
        let e = plan(&cfg, &args(1.5, 30.0, 7000.0), Pos::ZERO).unwrap_err();
        assert!(e.contains("max_speed 6000"), "{e}");
        let e = plan(&cfg, &args(3.0, 30.0, 5000.0), Pos::ZERO).unwrap_err();
        assert!(e.contains("15000 mm/min") && e.contains("at most 4000"), "{e}");
        let e = plan(&cfg, &args(1.5, 30.0, 1000.0), Pos::xz(0.0, -390.0)).unwrap_err();
        assert!(e.contains("below Z's travel -400") && e.contains("at most 12.000"), "{e}");
        assert!(plan(&cfg, &args(-1.5, 30.0, 1000.0), Pos::ZERO).is_err());
    }

    /// Z at rest one count above its + limit (5.0001 against 5) after a tap that ended there:
    /// the tap starts at the limit; further above it is refused before anything moves.
    #[test]
    fn plan_from_just_above_the_travel_limit() {
        let cfg = MachineConfig::embedded();
        assert_eq!(cfg.axes["z"].max, Some(5.0));
        for z in [5.0001, 5.001] {
            let p = plan(&cfg, &args(1.5, 30.0, 3000.0), Pos::xz(10.0, z)).unwrap_or_else(|e| panic!("Z{z}: {e}"));
            assert_eq!((p.r_z, p.bottom_z), (5.0, -25.0), "Z{z}");
            assert!(p.program.contains("G0 X20.0000 Z5.0000\n"), "{}", p.program);
        }
        for z in [5.0012, 5.1] {
            let e = plan(&cfg, &args(1.5, 30.0, 3000.0), Pos::xz(10.0, z)).unwrap_err();
            assert!(e.contains("above its travel limit 5 (axes.z.max") && e.contains("cncgw jog z --to 5"), "Z{z}: {e}");
        }
        // A coarse axis (100 counts per mm): one count is the width.
        let mut coarse = cfg.clone();
        coarse.axes.get_mut("z").unwrap().counts_per_unit = 100.0;
        assert_eq!(plan(&coarse, &args(1.5, 30.0, 3000.0), Pos::xz(10.0, 5.01)).unwrap().r_z, 5.0);
        assert!(plan(&coarse, &args(1.5, 30.0, 3000.0), Pos::xz(10.0, 5.02)).is_err());
    }
}
