//! `cncgw preview PROGRAM -o part.svg`: the toolpath of a program in the Z–X plane as an SVG,
//! so that a programmer can see a cycle before cutting.
//!
//! Workpiece coordinates of each move (its own work offset), Z to the right, X up as a
//! **radius** (the true shape, one scale on both axes). Rapids are dashed grey; feeds, arcs
//! (drawn as chords of at most 2°) solid, blue outside cycles and in each cycle's own colour
//! ([`colour`]); threads and taps red; G12.1 polar moves cyan (their Z–X shadow). Drawn with
//! `plotters`' SVG backend only: no text through plotters (that needs fonts); the legend is
//! plain SVG `<text>` added afterwards.

use crate::canon::{Move, MoveKind, Pos};
use plotters::prelude::*;

/// Pixel size and the data window (workpiece Z and X radius, mm) of a preview.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    pub margin: u32,
    pub z: (f64, f64),
    pub x: (f64, f64),
}

impl View {
    /// A window around `pts` (z, x radius) with 5 % padding and one scale on both axes,
    /// `width` pixels wide (height from the aspect, 200–1200 px).
    pub fn fit(pts: &[(f64, f64)], width: u32) -> View {
        let margin = 30u32;
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
        let inner_w = (width.max(200) - 2 * margin) as f64;
        let inner_h = (inner_w * (x1 - x0) / (z1 - z0)).clamp(140.0, 1140.0);
        // One scale: widen whichever range is short for its pixels.
        let s = ((z1 - z0) / inner_w).max((x1 - x0) / inner_h);
        let (cz, cx) = ((z0 + z1) / 2.0, (x0 + x1) / 2.0);
        (z0, z1) = (cz - s * inner_w / 2.0, cz + s * inner_w / 2.0);
        (x0, x1) = (cx - s * inner_h / 2.0, cx + s * inner_h / 2.0);
        View { width: width.max(200), height: inner_h as u32 + 2 * margin, margin, z: (z0, z1), x: (x0, x1) }
    }

    /// The workpiece point of pixel (px, py), for checking a drawing.
    pub fn unmap(&self, px: f64, py: f64) -> (f64, f64) {
        let w = (self.width - 2 * self.margin) as f64;
        let h = (self.height - 2 * self.margin) as f64;
        let z = self.z.0 + (px - self.margin as f64) / w * (self.z.1 - self.z.0);
        let x = self.x.1 - (py - self.margin as f64) / h * (self.x.1 - self.x.0);
        (z, x)
    }

    /// mm per pixel.
    pub fn scale(&self) -> f64 {
        (self.z.1 - self.z.0) / (self.width - 2 * self.margin) as f64
    }
}

/// Colour of a move: (r, g, b), by kind and cycle.
pub fn colour(m: &Move) -> (u8, u8, u8) {
    match &m.kind {
        MoveKind::Rapid { .. } => (150, 150, 150),
        MoveKind::Thread { .. } | MoveKind::Tap { .. } | MoveKind::RigidThread { .. } => (220, 30, 30),
        MoveKind::Polar { .. } => (0, 170, 200),
        _ => match m.tag.as_ref().map(|t| &*t.cycle) {
            None => (30, 80, 220),
            Some("G70") => (20, 150, 40),
            Some("G71") | Some("G72") => (240, 140, 0),
            Some("G73") => (150, 60, 190),
            Some("G74") | Some("G75") => (0, 140, 140),
            Some("G90") | Some("G94") => (130, 130, 0),
            Some(_) => (200, 60, 120),
        },
    }
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

/// Render `moves` (starting from machine `start`) as SVG text; the view used comes back too.
pub fn render_svg(moves: &[Move], start: Pos, title: &str, width: u32) -> Result<(String, View), String> {
    let mut paths = Vec::new();
    let mut cur = start;
    for m in moves {
        if let Some(p) = path(cur, m) {
            paths.push((p, m));
            cur = m.kind.end().unwrap_or(cur);
        }
    }
    let all: Vec<(f64, f64)> = paths.iter().flat_map(|(p, _)| p.iter().copied()).collect();
    let view = View::fit(&all, width);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (view.width, view.height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let mut chart =
            ChartBuilder::on(&root).margin(view.margin).build_cartesian_2d(view.z.0..view.z.1, view.x.0..view.x.1).map_err(|e| e.to_string())?;
        // The spindle centre line, when in view.
        if view.x.0 < 0.0 && view.x.1 > 0.0 {
            chart
                .draw_series(DashedLineSeries::new(vec![(view.z.0, 0.0), (view.z.1, 0.0)], 12, 4, RGBColor(200, 200, 200).stroke_width(1)))
                .map_err(|e| e.to_string())?;
        }
        for (p, m) in &paths {
            let (r, g, b) = colour(m);
            let c = RGBColor(r, g, b);
            if matches!(m.kind, MoveKind::Rapid { .. }) {
                chart.draw_series(DashedLineSeries::new(p.clone(), 6, 4, c.stroke_width(1))).map_err(|e| e.to_string())?;
            } else {
                chart.draw_series(LineSeries::new(p.clone(), c.stroke_width(2))).map_err(|e| e.to_string())?;
            }
        }
        root.present().map_err(|e| e.to_string())?;
    }
    // Title and legend as plain SVG text (plotters would need fonts for it).
    let esc = |s: &str| s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;");
    let mut extra = format!(
        "<title>{}</title>\n<text x=\"{}\" y=\"18\" font-family=\"sans-serif\" font-size=\"13\">{} — Z →, X ↑ (radius), {:.3} mm/px</text>\n",
        esc(title),
        view.margin,
        esc(title),
        view.scale()
    );
    let legend = [
        ("rapid", (150, 150, 150)),
        ("feed", (30, 80, 220)),
        ("thread/tap", (220, 30, 30)),
        ("G70", (20, 150, 40)),
        ("G71/G72", (240, 140, 0)),
        ("G73", (150, 60, 190)),
        ("G74/G75", (0, 140, 140)),
        ("G90/G94", (130, 130, 0)),
        ("polar", (0, 170, 200)),
    ];
    for (i, (name, (r, g, b))) in legend.iter().enumerate() {
        let x = view.margin as usize + i * 90;
        let y = view.height - 8;
        extra.push_str(&format!(
            "<text x=\"{x}\" y=\"{y}\" font-family=\"sans-serif\" font-size=\"11\" fill=\"#{r:02X}{g:02X}{b:02X}\">{name}</text>\n"
        ));
    }
    match svg.rfind("</svg>") {
        Some(i) => svg.insert_str(i, &extra),
        None => return Err("the SVG backend produced no document".into()),
    }
    Ok((svg, view))
}

/// The `preview` command: exit code 0, or 2 on a program alarm / unwritable output.
pub fn preview(
    program: &std::path::Path,
    config: Option<&std::path::Path>,
    tools: Option<&std::path::Path>,
    state_dir: Option<&std::path::Path>,
    out: &std::path::Path,
    width: u32,
) -> i32 {
    let (cfg, _) = match super::load_config(config) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: {e}");
            return super::exit::SETUP;
        }
    };
    let mut interp = match crate::interp::Interpreter::from_file(program, &cfg) {
        Ok(i) => i,
        Err(alarms) => {
            for a in &alarms {
                eprintln!("{a}");
            }
            return super::exit::INPUT;
        }
    };
    // The same offsets as `run`: --tools FILE, else the stored table; the stored work offsets.
    let state_root = state_dir.map(std::path::Path::to_path_buf).or_else(crate::persist::default_state_dir);
    match crate::offsets::resolve(state_root.as_deref(), &cfg.machine.name, tools) {
        Ok(t) => {
            eprintln!("{}", t.source);
            t.apply(&mut interp);
        }
        Err(a) => {
            eprintln!("{a}");
            return super::exit::INPUT;
        }
    }
    let mut moves = Vec::new();
    let mut code = 0;
    for m in interp {
        match m {
            Ok(m) => moves.push(m),
            Err(a) => {
                // Draw what came before the alarm: that is where the program stops.
                eprintln!("{a}");
                code = super::exit::INPUT;
                break;
            }
        }
    }
    let (svg, _) = match render_svg(&moves, Pos::ZERO, &program.display().to_string(), width) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: cannot draw the preview: {e}");
            return super::exit::SETUP;
        }
    };
    if let Err(e) = std::fs::write(out, svg) {
        eprintln!("error: cannot write {}: {e}", out.display());
        return super::exit::SETUP;
    }
    let upto = if code == 0 { "" } else { " (up to the alarm)" };
    eprintln!("{}: {} moves drawn{upto}", out.display(), moves.len());
    code
}
