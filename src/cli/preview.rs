//! `cncgw preview PROGRAM -o part.svg`: the toolpath of a program in the Z–X plane as an SVG
//! (or PNG), so that a programmer can see a cycle before cutting.
//!
//! Workpiece coordinates of each move (its own work offset) of the tool tip (a `--tools`
//! table's geometry and wear offsets are left out: they move the turret, not the tip), Z to
//! the right, X up as a **radius** (the true shape, one scale on both axes), with mm ticks on both axes and the
//! work zero marked (the usual quartered circle). Rapids are dashed grey; feeds, arcs (drawn
//! as chords of at most 2°) solid, blue outside cycles and in each cycle's own colour
//! ([`colour`]); threads and taps red; G12.1 polar moves cyan (their Z–X shadow). The legend,
//! right of the drawing, lists only the kinds the program has. `--stock DxL[+F]` draws the
//! bar; a path under G41/G42 gets the tool nose circle (its radius from `--tools`) at every
//! vertex and the nose centre's path dotted, so that the cut edge can be seen. Paths are drawn by
//! `plotters`' SVG backend, everything else is plain SVG ([`crate::plot`]).

use super::OrSetup;
use crate::canon::{Move, MoveKind, Pos};
use crate::plot::{self, Rgb};
use plotters::prelude::*;
use std::fmt::Write as _;

/// Pixel layout and the data window (workpiece Z and X radius, mm) of a preview.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    /// The drawing box: left and top edge, width and height, px.
    pub left: u32,
    pub top: u32,
    pub plot_w: u32,
    pub plot_h: u32,
    pub z: (f64, f64),
    pub x: (f64, f64),
}

/// Room for the title (top), tick labels (left, bottom) and the legend (right), px.
const TOP: u32 = 64;
const LEFT: u32 = 76;
const BOTTOM: u32 = 56;
const RIGHT: u32 = 230;

impl View {
    /// A window around `pts` (z, x radius) with 5 % padding and one scale on both axes,
    /// `width` pixels wide (the drawing 160–1000 px high).
    pub fn fit(pts: &[(f64, f64)], width: u32) -> View {
        let (mut z0, mut z1, mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for &(z, x) in pts {
            if z.is_finite() && x.is_finite() {
                z0 = z0.min(z);
                z1 = z1.max(z);
                x0 = x0.min(x);
                x1 = x1.max(x);
            }
        }
        if !z0.is_finite() {
            (z0, z1, x0, x1) = (-1.0, 1.0, -1.0, 1.0);
        }
        let pad = |a: f64, b: f64| {
            let p = ((b - a) * 0.05).max(1.0);
            (a - p, b + p)
        };
        let (mut z0, mut z1) = pad(z0, z1);
        let (mut x0, mut x1) = pad(x0, x1);
        let width = width.max(LEFT + RIGHT + 200);
        let plot_w = width - LEFT - RIGHT;
        let plot_h = (plot_w as f64 * (x1 - x0) / (z1 - z0)).clamp(160.0, 1000.0) as u32;
        // One scale: widen whichever range is short for its pixels (plotters maps a range
        // onto pixels 0 … n − 1).
        let (pw, ph) = ((plot_w - 1) as f64, (plot_h - 1) as f64);
        let s = ((z1 - z0) / pw).max((x1 - x0) / ph);
        let (cz, cx) = ((z0 + z1) / 2.0, (x0 + x1) / 2.0);
        (z0, z1) = (cz - s * pw / 2.0, cz + s * pw / 2.0);
        (x0, x1) = (cx - s * ph / 2.0, cx + s * ph / 2.0);
        View { width, height: TOP + plot_h + BOTTOM, left: LEFT, top: TOP, plot_w, plot_h, z: (z0, z1), x: (x0, x1) }
    }

    /// The pixel of workpiece point (z, x radius).
    pub fn map(&self, z: f64, x: f64) -> (f64, f64) {
        (
            self.left as f64 + (z - self.z.0) / (self.z.1 - self.z.0) * (self.plot_w - 1) as f64,
            self.top as f64 + (self.x.1 - x) / (self.x.1 - self.x.0) * (self.plot_h - 1) as f64,
        )
    }

    /// The workpiece point of pixel (px, py), for checking a drawing.
    pub fn unmap(&self, px: f64, py: f64) -> (f64, f64) {
        let z = self.z.0 + (px - self.left as f64) / (self.plot_w - 1) as f64 * (self.z.1 - self.z.0);
        let x = self.x.1 - (py - self.top as f64) / (self.plot_h - 1) as f64 * (self.x.1 - self.x.0);
        (z, x)
    }

    /// mm per pixel.
    pub fn scale(&self) -> f64 {
        (self.z.1 - self.z.0) / (self.plot_w - 1) as f64
    }
}

/// The bar the part is cut from: `--stock DxL` or `DxL+F` (diameter, length, face stock in
/// mm): from Z = F down to Z = F − L, X from the centre line to D/2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stock {
    pub diameter: f64,
    pub length: f64,
    pub face: f64,
}

impl std::str::FromStr for Stock {
    type Err = String;
    fn from_str(s: &str) -> Result<Stock, String> {
        let bad = || format!("--stock {s:?}: write DIAMETERxLENGTH or DIAMETERxLENGTH+FACE in mm, e.g. 60x80 or 60x80+1");
        let (d, rest) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
        let (l, f) = rest.split_once('+').unwrap_or((rest, "0"));
        let num = |v: &str| v.trim().parse::<f64>().ok().filter(|x| x.is_finite());
        match (num(d), num(l), num(f)) {
            (Some(diameter), Some(length), Some(face)) if diameter > 0.0 && length > 0.0 && face >= 0.0 => Ok(Stock { diameter, length, face }),
            _ => Err(bad()),
        }
    }
}

/// What is drawn besides the path.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Extras {
    pub stock: Option<Stock>,
    /// Per move: its nose when it is a compensated (G41/G42) motion ([`compensated`]);
    /// empty = none.
    pub nose: Vec<Option<Nose>>,
}

/// Colour of a move: (r, g, b), by kind and cycle.
pub fn colour(m: &Move) -> Rgb {
    kind(m).1
}

/// Legend name and colour of a move.
fn kind(m: &Move) -> (String, Rgb) {
    let (n, c): (&str, Rgb) = match &m.kind {
        MoveKind::Rapid { .. } => ("rapid", (150, 150, 150)),
        MoveKind::Thread { .. } | MoveKind::Tap { .. } | MoveKind::RigidThread { .. } => ("thread / tap", (220, 30, 30)),
        MoveKind::Polar { .. } => ("G12.1 polar (Z–X shadow)", (0, 170, 200)),
        _ => match m.tag.as_ref().map(|t| &*t.cycle) {
            None => ("feed G01–G03", (30, 80, 220)),
            Some("G70") => ("G70 finishing", (20, 150, 40)),
            Some("G71") | Some("G72") => ("G71/G72 roughing", (240, 140, 0)),
            Some("G73") => ("G73 pattern repeat", (150, 60, 190)),
            Some("G74") | Some("G75") => ("G74/G75 pecking", (0, 140, 140)),
            Some("G90") | Some("G94") => ("G90/G94 single cycle", (130, 130, 0)),
            Some(other) => return (other.to_string(), (200, 60, 120)),
        },
    };
    (n.to_string(), c)
}

/// The polyline of a motion from `start` (machine) in workpiece (z, x radius).
fn path(start: Pos, m: &Move) -> Option<Vec<(f64, f64)>> {
    let end = m.kind.end()?;
    let w = |p: Pos| {
        let q = p.sub(m.work_offset);
        (q.z, q.x)
    };
    let mut v = vec![w(start)];
    if let MoveKind::Arc { center, cw, plane: crate::canon::Plane::Zx, .. } = &m.kind {
        v.extend(crate::canon::zx_arc_chord_points(start, end, *center, *cw).into_iter().map(w));
    }
    v.push(w(end));
    Some(v)
}

/// The nose of one compensated move: radius (mm) and the nose centre's path (workpiece
/// Z, X radius).
#[derive(Clone, Debug, PartialEq)]
pub struct Nose {
    pub r: f64,
    pub centre: Vec<(f64, f64)>,
}

/// Which moves of `moves` are nose-compensated (G41/G42), and where the nose centre goes.
/// `centre` is the same program run with every tip set to 0 (the tool point is then the
/// nose centre), `plain` with every radius set to 0 (the programmed path): a compensated
/// motion of `centre` ends R off the programmed path, so at no end of the same block of
/// `plain` (the tool point itself can lie on the programmed path: tip 3 along Z). The
/// radius is that of the offset the last T code selected (a T code cannot come under
/// G41/G42: alarm 3577). Empty when the runs do not pair move for move.
pub fn compensated(moves: &[Move], centre: &[Move], plain: &[Move], table: &crate::interp::ToolTable) -> Vec<Option<Nose>> {
    if centre.len() != moves.len() || centre.iter().zip(moves).any(|(a, b)| a.src.line != b.src.line) {
        return Vec::new();
    }
    let mut ends: std::collections::HashMap<(&str, u32), Vec<Pos>> = Default::default();
    for m in plain {
        if let Some(e) = m.kind.end() {
            ends.entry((&*m.src.file, m.src.line)).or_default().push(e);
        }
    }
    let mut r = 0.0;
    let mut cur = Pos::ZERO;
    moves
        .iter()
        .zip(centre)
        .map(|(m, c)| {
            if let MoveKind::Aux { letter: 'T', value } = m.kind {
                r = table.get(value as u32 % 100).map_or(0.0, |o| o.r);
            }
            let end = c.kind.end()?;
            let start = std::mem::replace(&mut cur, end);
            let on_path =
                ends.get(&(&*c.src.file, c.src.line)).is_some_and(|v| v.iter().any(|p| (p.z - end.z).abs() < 1e-6 && (p.x - end.x).abs() < 1e-6));
            if on_path || r <= 0.0 {
                None
            } else {
                Some(Nose { r, centre: path(start, c)? })
            }
        })
        .collect()
}

/// The mm grid under the drawing, the ticks, their labels and the axis names over it.
fn grid(view: &View) -> (String, String) {
    let (mut under, mut over) = (String::new(), String::new());
    let (zt, zstep) = plot::ticks(view.z.0, view.z.1, (view.plot_w / 70).max(2) as usize);
    let (xt, xstep) = plot::ticks(view.x.0, view.x.1, (view.plot_h / 50).max(2) as usize);
    let (l, t, r, b) = (view.left as f64, view.top as f64, (view.left + view.plot_w) as f64, (view.top + view.plot_h) as f64);
    for z in &zt {
        let (px, _) = view.map(*z, 0.0);
        under += &plot::line((px, t), (px, b), (232, 232, 232), 1.0, "");
        over += &plot::line((px, b), (px, b + 5.0), (0, 0, 0), 1.0, "");
        over += &plot::text(px, b + 19.0, &plot::tick_label(*z, zstep), 11, (0, 0, 0), "middle", "tick-z");
    }
    for x in &xt {
        let (_, py) = view.map(0.0, *x);
        under += &plot::line((l, py), (r, py), (232, 232, 232), 1.0, "");
        over += &plot::line((l - 5.0, py), (l, py), (0, 0, 0), 1.0, "");
        over += &plot::text(l - 8.0, py + 4.0, &plot::tick_label(*x, xstep), 11, (0, 0, 0), "end", "tick-x");
    }
    over += &plot::text(r, b + 40.0, "Z (mm) →", 13, (0, 0, 0), "end", "axis-label");
    let _ = writeln!(
        over,
        "<text class=\"axis-label\" x=\"{:.1}\" y=\"{:.1}\" font-family=\"sans-serif\" font-size=\"13\" text-anchor=\"end\" transform=\"rotate(-90 {:.1} {:.1})\">X radius (mm) = Ø/2 →</text>",
        l - 48.0,
        t,
        l - 48.0,
        t
    );
    let _ = writeln!(over, "<rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#000000\"/>", view.plot_w, view.plot_h);
    (under, over)
}

/// One move as drawn: its points (Z, X radius), the move, its tool nose if compensated.
type Drawn<'m> = (Vec<(f64, f64)>, &'m Move, Option<Nose>);

/// The colour of the tool nose marks.
const NOSE_COLOUR: Rgb = (150, 0, 170);

/// The tool nose at every vertex of a compensated path: centre = tool point − R·tip vector.
/// Returns the radii drawn (for the legend).
fn draw_noses(view: &View, paths: &[Drawn], over: &mut String) -> Vec<f64> {
    let mut noses = Vec::new();
    let mut before = false;
    for (_, m, n) in paths {
        let Some(Nose { r: rad, centre }) = n else {
            before = false;
            continue;
        };
        // A start-up move starts from an uncompensated point: its nose only at its end.
        let from = if std::mem::replace(&mut before, true) { 0 } else { centre.len() - 1 };
        let c = &centre[from..];
        let at: Vec<(f64, f64)> =
            if matches!(m.kind, MoveKind::Arc { .. }) { vec![c[0], c[c.len() / 2], c[c.len() - 1]] } else { vec![c[0], c[c.len() - 1]] };
        // The nose-centre path, dotted.
        if c.len() > 1 {
            let pts: String = c.iter().map(|&(z, x)| view.map(z, x)).map(|(a, b)| format!("{a:.1},{b:.1} ")).collect();
            let _ = writeln!(
                over,
                "<polyline class=\"nose-path\" fill=\"none\" stroke=\"{}\" stroke-width=\"1\" stroke-dasharray=\"2 3\" points=\"{}\"/>",
                plot::hex(NOSE_COLOUR),
                pts.trim_end()
            );
        }
        for (cz, cx) in at {
            let (px, py) = view.map(cz, cx);
            let _ = writeln!(
                over,
                "<circle class=\"nose\" data-r=\"{rad}\" data-z=\"{cz:.4}\" data-x=\"{cx:.4}\" cx=\"{px:.1}\" cy=\"{py:.1}\" r=\"{:.2}\" fill=\"none\" stroke=\"{}\" stroke-width=\"1\"/>",
                (rad / view.scale()).max(1.5),
                plot::hex(NOSE_COLOUR)
            );
        }
        if !noses.contains(rad) {
            noses.push(*rad);
        }
    }
    noses
}

/// The legend right of the drawing: only what the program has.
fn legend(paths: &[Drawn], noses: &[f64], stock: Option<Stock>, (lx, top): (f64, f64)) -> String {
    let mut over = String::new();
    let mut entries: Vec<(String, Rgb, bool)> = Vec::new();
    for (_, m, _) in paths {
        let (n, c) = kind(m);
        if !entries.iter().any(|e| e.0 == n) {
            entries.push((n, c, matches!(m.kind, MoveKind::Rapid { .. })));
        }
    }
    let mut ly = top + 14.0;
    for (n, c, dashed) in &entries {
        over += &plot::legend_entry(lx, ly, n, *c, if *dashed { "6 4" } else { "" }, false);
        ly += 18.0;
    }
    for rad in noses {
        over += &format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"5\" fill=\"none\" stroke=\"{}\"/>\n", lx + 12.0, ly - 4.0, plot::hex(NOSE_COLOUR));
        over += &plot::text(lx + 30.0, ly, &format!("tool nose R{rad} (centre dotted)"), 12, (0, 0, 0), "start", "legend");
        ly += 18.0;
    }
    if let Some(s) = stock {
        over += &plot::legend_entry(lx, ly, &format!("stock Ø{}×{} mm", s.diameter, s.length), (140, 109, 63), "", true);
        ly += 18.0;
    }
    let _ = writeln!(
        over,
        "<g transform=\"translate({:.1} {:.1})\"><circle r=\"6\" fill=\"#FFFFFF\" stroke=\"#000000\"/><path d=\"M0,0 L6,0 A6,6 0 0,1 0,6 Z M0,0 L-6,0 A6,6 0 0,1 0,-6 Z\"/></g>",
        lx + 12.0,
        ly - 4.0
    );
    over += &plot::text(lx + 30.0, ly, "work zero W", 12, (0, 0, 0), "start", "legend");
    over
}

/// Render `moves` (starting from machine `start`) as SVG text; the view used comes back too.
pub fn render_svg(moves: &[Move], start: Pos, title: &str, width: u32, extras: &Extras) -> Result<(String, View), String> {
    let mut paths = Vec::new();
    let mut cur = start;
    for (k, m) in moves.iter().enumerate() {
        if let Some(p) = path(cur, m) {
            paths.push((p, m, extras.nose.get(k).cloned().flatten()));
            cur = m.kind.end().unwrap_or(cur);
        }
    }
    let mut all: Vec<(f64, f64)> = paths.iter().flat_map(|(p, _, _)| p.iter().copied()).collect();
    let part = all.clone();
    // The work zero is always in the picture.
    all.push((0.0, 0.0));
    if let Some(s) = extras.stock {
        all.extend([(s.face, s.diameter / 2.0), (s.face - s.length, 0.0)]);
    }
    let view = View::fit(&all, width);
    let (mut under, mut over) = grid(&view);
    let (l, t, r, _) = (view.left as f64, view.top as f64, (view.left + view.plot_w) as f64, (view.top + view.plot_h) as f64);
    if let Some(s) = extras.stock {
        let (a, c) = (view.map(s.face - s.length, s.diameter / 2.0), view.map(s.face, 0.0));
        let _ = writeln!(
            under,
            "<rect class=\"stock\" data-diameter=\"{}\" data-length=\"{}\" data-face=\"{}\" x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"#EFE4CF\" stroke=\"#8C6D3F\" stroke-width=\"1.5\"/>",
            s.diameter,
            s.length,
            s.face,
            a.0,
            a.1,
            c.0 - a.0,
            c.1 - a.1
        );
    }
    // The spindle centre line (dash-dot), when in view.
    if view.x.0 < 0.0 && view.x.1 > 0.0 {
        let (_, py) = view.map(0.0, 0.0);
        under += &plot::line((l, py), (r, py), (120, 120, 120), 1.0, "14 4 2 4");
    }
    let mut body = String::new();
    {
        let root = SVGBackend::with_string(&mut body, (view.width, view.height)).into_drawing_area();
        let area = root.shrink((view.left, view.top), (view.plot_w, view.plot_h));
        let mut chart = ChartBuilder::on(&area).build_cartesian_2d(view.z.0..view.z.1, view.x.0..view.x.1).map_err(|e| e.to_string())?;
        for (p, m, _) in &paths {
            let (r, g, b) = colour(m);
            let c = RGBColor(r, g, b);
            if matches!(m.kind, MoveKind::Rapid { .. }) {
                chart.draw_series(DashedLineSeries::new(p.clone(), 6, 4, c.stroke_width(1))).map_err(|e| e.to_string())?;
            } else {
                chart.draw_series(LineSeries::new(p.clone(), c.stroke_width(2))).map_err(|e| e.to_string())?;
            }
        }
        area.present().map_err(|e| e.to_string())?;
    }
    let noses = draw_noses(&view, &paths, &mut over);
    // The work zero: a quartered circle at Z0 X0.
    let (zx, zy) = view.map(0.0, 0.0);
    let _ = writeln!(
        over,
        "<g class=\"work-zero\" data-z=\"0\" data-x=\"0\" transform=\"translate({zx:.1} {zy:.1})\"><circle r=\"8\" fill=\"#FFFFFF\" stroke=\"#000000\" stroke-width=\"1.5\"/><path d=\"M0,0 L8,0 A8,8 0 0,1 0,8 Z M0,0 L-8,0 A8,8 0 0,1 0,-8 Z\" fill=\"#000000\"/></g>"
    );
    over += &plot::text(zx + 11.0, zy - 10.0, "W (Z0 X0)", 12, (0, 0, 0), "start", "work-zero-label");
    // Title: the program, the extents and the scale.
    let (mut pz0, mut pz1, mut px0, mut px1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for (z, x) in &part {
        (pz0, pz1, px0, px1) = (pz0.min(*z), pz1.max(*z), px0.min(*x), px1.max(*x));
    }
    over += &plot::text(l, 22.0, title, 15, (0, 0, 0), "start", "title");
    let extent = if part.is_empty() {
        "no motion".to_string()
    } else {
        format!("path Z {pz0:.3} … {pz1:.3} mm, X Ø{:.3} … Ø{:.3} mm (radius {px0:.3} … {px1:.3})", 2.0 * px0, 2.0 * px1)
    };
    over += &plot::text(l, 42.0, &format!("{extent}; scale {:.3} mm/px, workpiece coordinates", view.scale()), 12, (70, 70, 70), "start", "extent");
    over += &legend(&paths, &noses, extras.stock, (r + 18.0, t));
    let svg = plot::document(view.width, view.height, title, &format!("{under}{}{over}", plot::inner(&body)?));
    Ok((svg, view))
}

/// The moves of `program` up to its end or its first alarm (printed).
fn moves_of(
    program: &std::path::Path,
    cfg: &crate::config::MachineConfig,
    tables: &crate::offsets::Tables,
    quiet: bool,
) -> Result<(Vec<Move>, bool), i32> {
    let mut interp = match crate::interp::Interpreter::from_file(program, cfg) {
        Ok(i) => i,
        Err(alarms) => {
            for a in &alarms {
                eprintln!("{a}");
            }
            return Err(super::exit::INPUT);
        }
    };
    tables.apply(&mut interp);
    let mut moves = Vec::new();
    for m in interp {
        match m {
            Ok(m) => moves.push(m),
            Err(a) => {
                // Draw what came before the alarm: that is where the program stops.
                if !quiet {
                    eprintln!("{a}");
                }
                return Ok((moves, false));
            }
        }
    }
    Ok((moves, true))
}

/// The `preview` command: exit code 0, or 2 on a program alarm / unwritable output.
pub fn preview(
    program: &std::path::Path,
    config: Option<&std::path::Path>,
    tools: Option<&std::path::Path>,
    state_dir: Option<&std::path::Path>,
    out: &std::path::Path,
    width: u32,
    stock: Option<Stock>,
) -> i32 {
    let (cfg, _) = match super::load_config(config).or_setup() {
        Ok(c) => c,
        Err(code) => return code,
    };
    // The same tables as `run`: --tools FILE, else the stored tool table; the stored work
    // offsets.
    let state_root = state_dir.map(std::path::Path::to_path_buf).or_else(crate::persist::default_state_dir);
    let mut tables = match super::resolve_tables(state_root.as_deref(), &cfg.machine.name, tools) {
        Ok(t) => t,
        Err(code) => return code,
    };
    eprintln!("{}", tables.source);
    // The tool tip's path in workpiece coordinates (as a Fanuc's path graphics draws it): the
    // table's geometry and wear offsets move the turret, not the tip, so they are left out
    // here; radii and tips stay.
    tables.tools.offsets.values_mut().for_each(|o| (o.x, o.z, o.wear_x, o.wear_z) = (0.0, 0.0, 0.0, 0.0));
    let (moves, complete) = match moves_of(program, &cfg, &tables, false) {
        Ok(m) => m,
        Err(code) => return code,
    };
    let code = if complete { 0 } else { super::exit::INPUT };
    // Which moves are nose-compensated: the same program with every radius 0 beside it.
    let mut extras = Extras { stock, nose: Vec::new() };
    if tables.tools.offsets.values().any(|o| o.r > 0.0) {
        let (mut centre, mut plain) = (tables.clone(), tables.clone());
        centre.tools.offsets.values_mut().for_each(|o| o.tip = 0);
        plain.tools.offsets.values_mut().for_each(|o| o.r = 0.0);
        if let (Ok((c, _)), Ok((p, _))) = (moves_of(program, &cfg, &centre, true), moves_of(program, &cfg, &plain, true)) {
            extras.nose = compensated(&moves, &c, &p, &tables.tools);
        }
    }
    let (svg, _) = match render_svg(&moves, Pos::ZERO, &program.display().to_string(), width, &extras) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: cannot draw the preview: {e}");
            return super::exit::SETUP;
        }
    };
    if let Err(e) = plot::save(out, &svg) {
        eprintln!("error: {e}");
        return super::exit::SETUP;
    }
    let upto = if code == 0 { "" } else { " (up to the alarm)" };
    eprintln!("{}: {} moves drawn{upto}", out.display(), moves.len());
    code
}
