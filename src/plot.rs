//! Pictures as SVG, shared by `cncgw preview`, `cncgw trace plot` and `cncgw tap-test`: tick
//! steps, plain SVG elements (text, lines, boxes), panels of series over time with their
//! legends in a column right of the data, and the output file (SVG, or PNG through
//! `rsvg-convert` when the name ends in `.png`).
//!
//! Text is plain SVG `<text>` laid out by the viewer, so no font library is needed (plotters
//! stays on its SVG backend without font features). Every element a test looks for carries a
//! `class` (`title`, `tick-x`, `tick-y`, `legend`, `verdict`, `span`, `band`, `series`…) and
//! numbers in `data-*` attributes, so the pictures can be checked by parsing them.

use std::fmt::Write as _;
use std::path::Path;

/// An sRGB colour.
pub type Rgb = (u8, u8, u8);

/// Distinct colours, also for most colour-blind readers (Okabe & Ito's palette, darkened
/// yellow): blue, vermilion, green, reddish purple, orange, sky blue.
pub const PALETTE: [Rgb; 6] = [(0, 114, 178), (213, 94, 0), (0, 158, 115), (204, 121, 167), (230, 159, 0), (86, 180, 233)];
/// Commanded positions: dark and dashed over the actual ones, which keep the axis colour.
pub const COMMAND: Rgb = (40, 40, 40);

/// `#RRGGBB`.
pub fn hex(c: Rgb) -> String {
    format!("#{:02X}{:02X}{:02X}", c.0, c.1, c.2)
}

/// Text for SVG content and attributes.
pub fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// A 1–2–5 step giving at most `max` intervals over `span`.
pub fn tick_step(span: f64, max: usize) -> f64 {
    let raw = (span.abs() / max.max(1) as f64).max(1e-9);
    let mag = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| *s >= raw * (1.0 - 1e-9)).unwrap_or(10.0 * mag)
}

/// Multiples of [`tick_step`] inside `lo..=hi`.
pub fn ticks(lo: f64, hi: f64, max: usize) -> (Vec<f64>, f64) {
    let step = tick_step(hi - lo, max);
    let mut v = Vec::new();
    let mut k = (lo / step).ceil();
    while k * step <= hi + step * 1e-9 && v.len() < 1000 {
        // `+ 0.0`: no "-0" label.
        v.push(k * step + 0.0);
        k += 1.0;
    }
    (v, step)
}

/// A tick label with as many decimals as the step needs.
pub fn tick_label(v: f64, step: f64) -> String {
    let d = (-step.log10().floor()).clamp(0.0, 6.0) as usize;
    let s = format!("{:.*}", d, v);
    match s.strip_prefix('-') {
        Some(p) if p.chars().all(|c| c == '0' || c == '.') => p.to_string(),
        _ => s,
    }
}

/// A `<text>` element; `anchor` is start, middle or end.
pub fn text(x: f64, y: f64, s: &str, size: u32, fill: Rgb, anchor: &str, class: &str) -> String {
    format!(
        "<text class=\"{class}\" x=\"{x:.1}\" y=\"{y:.1}\" font-family=\"sans-serif\" font-size=\"{size}\" fill=\"{}\" text-anchor=\"{anchor}\">{}</text>\n",
        hex(fill),
        esc(s)
    )
}

/// A line segment; `dash` as an SVG dash array ("" = solid).
pub fn line(a: (f64, f64), b: (f64, f64), c: Rgb, width: f64, dash: &str) -> String {
    let d = if dash.is_empty() { String::new() } else { format!(" stroke-dasharray=\"{dash}\"") };
    format!("<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"{}\" stroke-width=\"{width}\"{d}/>\n", a.0, a.1, b.0, b.1, hex(c))
}

/// The whole document: a white page, then `body`.
pub fn document(width: u32, height: u32, title: &str, body: &str) -> String {
    format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" height=\"{height}\" viewBox=\"0 0 {width} {height}\">\n<title>{}</title>\n<rect x=\"0\" y=\"0\" width=\"{width}\" height=\"{height}\" fill=\"#FFFFFF\"/>\n{body}</svg>\n",
        esc(title)
    )
}

/// The elements inside a plotters SVG document (its own `<svg>` wrapper left out).
pub fn inner(svg: &str) -> Result<&str, String> {
    let start = svg.find("<svg").and_then(|i| svg[i..].find('>').map(|j| i + j + 1));
    match (start, svg.rfind("</svg>")) {
        (Some(a), Some(b)) if a <= b => Ok(&svg[a..b]),
        _ => Err("the SVG backend produced no document".into()),
    }
}

/// One legend entry: a line sample (or a filled box) and its name.
pub fn legend_entry(x: f64, y: f64, name: &str, c: Rgb, dash: &str, filled: bool) -> String {
    let sample = if filled {
        format!(
            "<rect x=\"{x:.1}\" y=\"{:.1}\" width=\"24\" height=\"10\" fill=\"{}\" fill-opacity=\"0.35\" stroke=\"{}\"/>\n",
            y - 9.0,
            hex(c),
            hex(c)
        )
    } else {
        line((x, y - 4.0), (x + 24.0, y - 4.0), c, 2.5, dash)
    };
    sample + &text(x + 30.0, y, name, 12, (0, 0, 0), "start", "legend")
}

/// Write `svg` to `out`: as it is, or as PNG when `out` ends in `.png` (through
/// `rsvg-convert`, librsvg's converter, when it is installed).
pub fn save(out: &Path, svg: &str) -> Result<(), String> {
    let png = out.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !png {
        return std::fs::write(out, svg).map_err(|e| format!("cannot write {}: {e}", out.display()));
    }
    use std::io::Write;
    use std::process::{Command, Stdio};
    let mut child = Command::new("rsvg-convert")
        .args(["--format", "png", "--background-color", "white", "--output"])
        .arg(out)
        .stdin(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("a PNG needs rsvg-convert ({e}): install librsvg2-bin (Debian/Ubuntu) or write an .svg"))?;
    let fed = child.stdin.take().map(|mut i| i.write_all(svg.as_bytes()));
    let done = child.wait_with_output().map_err(|e| format!("rsvg-convert: {e}"))?;
    if let Some(Err(e)) = fed {
        return Err(format!("rsvg-convert: {e}"));
    }
    if !done.status.success() {
        return Err(format!("rsvg-convert could not write {}: {}", out.display(), String::from_utf8_lossy(&done.stderr).trim()));
    }
    Ok(())
}

/// A line over time.
#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub v: Vec<f64>,
    pub colour: Rgb,
    pub dashed: bool,
    pub width: f64,
}

/// A shaded stretch of time (a phase).
#[derive(Clone, Debug)]
pub struct Span {
    pub t0: f64,
    pub t1: f64,
    pub name: String,
    pub colour: Rgb,
}

/// A shaded range of values (a limit band), always inside the panel's scale.
#[derive(Clone, Debug)]
pub struct Band {
    pub lo: f64,
    pub hi: f64,
    pub name: String,
    pub colour: Rgb,
}

/// One panel: series over the shared time axis.
#[derive(Clone, Debug, Default)]
pub struct Panel {
    /// Title, with the unit.
    pub title: String,
    pub series: Vec<Series>,
    pub bands: Vec<Band>,
    pub spans: Vec<Span>,
    /// Name the spans in this panel (label and legend); else they are only shaded, so that
    /// a page names its phases once.
    pub span_names: bool,
}

/// A header line: text, size, colour, class.
pub type HeaderLine = (String, u32, Rgb, &'static str);

/// Page width of the time plots, px; the legend column is the right [`LEGEND_W`].
pub const PAGE_W: f64 = 1100.0;
pub const LEGEND_W: f64 = 220.0;
const PANEL_H: f64 = 240.0;
const LEFT: f64 = 80.0;
/// Points per line at most: min and max of each bucket, so that short spikes stay visible.
const MAX_POINTS: usize = 3000;

/// Indices to draw of a series of `n` values: per bucket its first, min, max and last.
fn decimate(v: &[f64]) -> Vec<usize> {
    let n = v.len();
    let bucket = (n / (MAX_POINTS / 4)).max(1);
    if bucket == 1 {
        return (0..n).collect();
    }
    let mut out = Vec::with_capacity(MAX_POINTS + 4);
    let mut i = 0;
    while i < n {
        let j = (i + bucket).min(n);
        let (mut lo, mut hi) = (i, i);
        for k in i..j {
            if v[k] < v[lo] {
                lo = k;
            }
            if v[k] > v[hi] {
                hi = k;
            }
        }
        let mut ks = [i, lo, hi, j - 1];
        ks.sort_unstable();
        for k in ks {
            if out.last() != Some(&k) {
                out.push(k);
            }
        }
        i = j;
    }
    out
}

/// Panels of series over time `t` under a header, one time axis (s) for all; the legend of
/// each panel right of its data.
pub fn time_panels(t: &[f64], header: &[HeaderLine], panels: &[Panel], title: &str) -> Result<String, String> {
    if t.len() < 2 {
        return Err("fewer than two samples to draw".into());
    }
    let (t0, t1) = (t[0], t[t.len() - 1].max(t[0] + 1e-6));
    let head_h = 14.0 + 22.0 * header.len() as f64;
    let height = head_h + PANEL_H * panels.len() as f64 + 10.0;
    let plot_w = PAGE_W - LEFT - LEGEND_W - 20.0;
    let mut b = String::new();
    for (k, (s, size, c, class)) in header.iter().enumerate() {
        b += &text(LEFT, 24.0 + 22.0 * k as f64, s, *size, *c, "start", class);
    }
    let (tt, tstep) = ticks(t0, t1, 10);
    for (k, p) in panels.iter().enumerate() {
        let top = head_h + PANEL_H * k as f64 + 26.0;
        let h = PANEL_H - 26.0 - 40.0;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for s in &p.series {
            for x in s.v.iter().filter(|x| x.is_finite()) {
                lo = lo.min(*x);
                hi = hi.max(*x);
            }
        }
        for band in &p.bands {
            lo = lo.min(band.lo);
            hi = hi.max(band.hi);
        }
        if !(lo.is_finite() && hi.is_finite()) {
            (lo, hi) = (-1.0, 1.0);
        }
        let pad = ((hi - lo) * 0.06).max(1e-3 * hi.abs().max(lo.abs()).max(1.0));
        let (lo, hi) = (lo - pad, hi + pad);
        let px = |tv: f64| LEFT + (tv - t0) / (t1 - t0) * plot_w;
        let py = |v: f64| top + (hi - v) / (hi - lo) * h;
        let _ = writeln!(b, "<g class=\"panel\" data-title=\"{}\" data-lo=\"{lo}\" data-hi=\"{hi}\">", esc(&p.title));
        b += &text(LEFT, top - 8.0, &p.title, 14, (0, 0, 0), "start", "panel-title");
        for sp in &p.spans {
            let (a, z) = (px(sp.t0.max(t0)), px(sp.t1.min(t1)));
            let _ = writeln!(
                b,
                "<rect class=\"span\" data-name=\"{}\" data-t0=\"{}\" data-t1=\"{}\" x=\"{a:.1}\" y=\"{top:.1}\" width=\"{:.1}\" height=\"{h:.1}\" fill=\"{}\" fill-opacity=\"0.18\"/>",
                esc(&sp.name),
                sp.t0,
                sp.t1,
                (z - a).max(1.0),
                hex(sp.colour)
            );
            // Named in place where the name fits (≈ 6.5 px a character at 12 px), always in the legend.
            if p.span_names && z - a > 6.5 * sp.name.chars().count() as f64 {
                b += &text((a + z) / 2.0, top + 14.0, &sp.name, 12, sp.colour, "middle", "span-label");
            }
        }
        for band in &p.bands {
            let _ = writeln!(
                b,
                "<rect class=\"band\" data-lo=\"{}\" data-hi=\"{}\" x=\"{LEFT:.1}\" y=\"{:.1}\" width=\"{plot_w:.1}\" height=\"{:.1}\" fill=\"{}\" fill-opacity=\"0.12\"/>",
                band.lo,
                band.hi,
                py(band.hi),
                py(band.lo) - py(band.hi),
                hex(band.colour)
            );
            for v in [band.lo, band.hi] {
                b += &line((LEFT, py(v)), (LEFT + plot_w, py(v)), band.colour, 1.5, "8 4");
            }
        }
        // Grid and ticks.
        let (yt, ystep) = ticks(lo, hi, 6);
        for v in &yt {
            b += &line((LEFT, py(*v)), (LEFT + plot_w, py(*v)), (225, 225, 225), 1.0, "");
            b += &line((LEFT - 5.0, py(*v)), (LEFT, py(*v)), (0, 0, 0), 1.0, "");
            b += &text(LEFT - 8.0, py(*v) + 4.0, &tick_label(*v, ystep), 11, (0, 0, 0), "end", "tick-y");
        }
        for v in &tt {
            b += &line((px(*v), top), (px(*v), top + h), (235, 235, 235), 1.0, "");
            b += &line((px(*v), top + h), (px(*v), top + h + 5.0), (0, 0, 0), 1.0, "");
            b += &text(px(*v), top + h + 18.0, &tick_label(*v, tstep), 11, (0, 0, 0), "middle", "tick-x");
        }
        b += &text(LEFT + plot_w, top + h + 34.0, "t (s)", 12, (0, 0, 0), "end", "axis-label");
        for s in &p.series {
            let dash = if s.dashed { " stroke-dasharray=\"7 4\"" } else { "" };
            let _ = write!(
                b,
                "<polyline class=\"series\" data-name=\"{}\" fill=\"none\" stroke=\"{}\" stroke-width=\"{}\"{dash} points=\"",
                esc(&s.name),
                hex(s.colour),
                s.width
            );
            for i in decimate(&s.v[..s.v.len().min(t.len())]) {
                if s.v[i].is_finite() {
                    let _ = write!(b, "{:.1},{:.1} ", px(t[i]), py(s.v[i]));
                }
            }
            b += "\"/>\n";
        }
        let _ = writeln!(b, "<rect x=\"{LEFT}\" y=\"{top:.1}\" width=\"{plot_w:.1}\" height=\"{h:.1}\" fill=\"none\" stroke=\"#000000\"/>");
        // The legend, right of the data.
        let lx = LEFT + plot_w + 16.0;
        let mut ly = top + 12.0;
        for s in &p.series {
            b += &legend_entry(lx, ly, &s.name, s.colour, if s.dashed { "7 4" } else { "" }, false);
            ly += 17.0;
        }
        for band in &p.bands {
            b += &legend_entry(lx, ly, &band.name, band.colour, "", true);
            ly += 17.0;
        }
        for sp in p.spans.iter().filter(|_| p.span_names) {
            b += &legend_entry(lx, ly, &sp.name, sp.colour, "", true);
            ly += 17.0;
        }
        b += "</g>\n";
    }
    Ok(document(PAGE_W as u32, height as u32, title, &b))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_and_cover_the_range() {
        assert_eq!(tick_step(100.0, 10), 10.0);
        assert_eq!(tick_step(7.0, 10), 1.0);
        assert_eq!(tick_step(0.03, 6), 0.005);
        let (v, s) = ticks(-31.5, 42.0, 8);
        assert_eq!(s, 10.0);
        assert_eq!(v, [-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 40.0]);
        assert_eq!(tick_label(-0.0, 1.0), "0");
        assert_eq!(tick_label(-2.5, 0.5), "-2.5");
        assert_eq!(tick_label(2.0, 0.005), "2.000");
    }

    #[test]
    fn decimation_keeps_spikes() {
        let mut v = vec![0.0; 100_000];
        v[54_321] = 9.0;
        v[77_777] = -4.0;
        let k = decimate(&v);
        assert!(k.len() <= MAX_POINTS + 4, "{}", k.len());
        assert!(k.contains(&54_321) && k.contains(&77_777));
        assert!(k.windows(2).all(|w| w[0] < w[1]));
    }
}
