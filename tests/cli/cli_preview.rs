//! `cncgw preview`: the SVG is parsed back and its polylines checked against the program's
//! path (through the view's pixel ↔ workpiece mapping); its ticks, work zero, legend, stock
//! and nose circles read back with an XML parser.

use crate::svg_common;

use cncgw::canon::{Move, Pos};
use cncgw::cli::preview::{render_svg, Extras, Stock, View};
use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;
use svg_common::{by_class, num, parse, texts};

/// Stroke colour, stroke width, points.
type Polyline = (String, u32, Vec<(f64, f64)>);

/// (stroke colour, stroke width, points) of every `<polyline>`.
fn polylines(svg: &str) -> Vec<Polyline> {
    let mut out = Vec::new();
    for el in svg.split("<polyline").skip(1) {
        let el = &el[..el.find("/>").expect("closed element")];
        let attr = |name: &str| -> Option<String> {
            let k = format!("{name}=\"");
            let i = el.find(&k)? + k.len();
            Some(el[i..i + el[i..].find('"')?].to_string())
        };
        let pts = attr("points")
            .expect("points")
            .split_whitespace()
            .map(|p| {
                let (x, y) = p.split_once(',').expect("x,y");
                (x.parse::<f64>().expect("x"), y.parse::<f64>().expect("y"))
            })
            .collect();
        out.push((attr("stroke").expect("stroke"), attr("stroke-width").and_then(|w| w.parse().ok()).unwrap_or(1), pts));
    }
    out
}

fn moves(src: &str) -> Vec<Move> {
    Interpreter::from_source("t.nc", src, &MachineConfig::embedded())
        .unwrap_or_else(|e| panic!("{e:?}"))
        .map(|m| m.unwrap_or_else(|a| panic!("{a}")))
        .collect()
}

fn near(v: &View, px: (f64, f64), z: f64, x: f64) -> bool {
    let (pz, pxr) = v.unmap(px.0, px.1);
    let tol = 1.5 * v.scale();
    (pz - z).abs() <= tol && (pxr - x).abs() <= tol
}

const PROG: &str = "G98 G00 X40 Z2\nG01 Z-20 F100\nG02 X60 Z-30 R10\nG00 X80\nZ10\nG90 X70 Z-15 F150\nG00 X100\nM30\n";

#[test]
fn svg_holds_the_path() {
    let m = moves(PROG);
    let (svg, view) = render_svg(&m, Pos::ZERO, "t.nc", 800, &Extras::default()).expect("render");
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
    parse(&svg);
    assert!(svg.contains("<title>t.nc</title>"));
    let lines = polylines(&svg);
    let feed: Vec<_> = lines.iter().filter(|l| l.0 == "#1E50DC" && l.1 == 2).collect();
    // The G01 and the G02, solid blue.
    assert_eq!(feed.len(), 2, "{feed:?}");
    let g1 = &feed[0].2;
    assert_eq!(g1.len(), 2);
    assert!(near(&view, g1[0], 2.0, 20.0) && near(&view, g1[1], -20.0, 20.0), "{g1:?} {view:?}");
    // The arc: from (Z-20, X radius 20) to (Z-30, 30), centre (Z-20, X radius 30) for a CW R10 (X up,
    // Z right), every chord point on the circle.
    let arc = &feed[1].2;
    assert!(arc.len() > 10);
    assert!(near(&view, arc[0], -20.0, 20.0) && near(&view, *arc.last().unwrap(), -30.0, 30.0));
    for p in arc {
        let (z, x) = view.unmap(p.0, p.1);
        assert!(((z + 20.0).hypot(x - 30.0) - 10.0).abs() < 2.0 * view.scale(), "{p:?} → {z} {x}");
    }
    // Rapids dashed grey: many short pieces, all on the rapid lines. The first rapid runs
    // from machine zero to (Z2, X20).
    let rapid: Vec<_> = lines.iter().filter(|l| l.0 == "#969696").collect();
    assert!(rapid.len() > 5, "{}", rapid.len());
    assert!(rapid.iter().all(|l| l.2.len() == 2));
    let first = &rapid[0].2[0];
    assert!(near(&view, *first, 0.0, 0.0), "{first:?}");
    // G90: its moves in the cycle colour (the feed steps solid, its rapids dashed grey).
    let g90: Vec<_> = lines.iter().filter(|l| l.0 == "#828200").collect();
    assert_eq!(g90.len(), 2, "{g90:?}"); // ② cut along Z, ③ out along X
    assert!(near(&view, g90[0].2[0], 10.0, 35.0) && near(&view, g90[0].2[1], -15.0, 35.0), "{g90:?}");
    // One scale on both axes.
    let sx = (view.z.1 - view.z.0) / (view.plot_w - 1) as f64;
    let sy = (view.x.1 - view.x.0) / (view.plot_h - 1) as f64;
    assert!((sx - sy).abs() < 1e-9 * sx.max(1.0), "{sx} {sy}");
}

#[test]
fn cli_writes_the_file() {
    let dir = std::env::temp_dir().join(format!("cncgw-preview-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("p.nc");
    std::fs::write(&prog, PROG).unwrap();
    let out = dir.join("p.svg");
    let st = testkit::cli!().command::<&str>(&[]).args(["preview", prog.to_str().unwrap(), "-o", out.to_str().unwrap()]).status().expect("run cncgw");
    assert!(st.success());
    let svg = std::fs::read_to_string(&out).expect("svg written");
    assert!(polylines(&svg).iter().any(|l| l.0 == "#1E50DC"));
    // An alarm: exit code 2, the path up to it still drawn.
    std::fs::write(&prog, "G98 G00 X40 Z2\nG01 Z-20 F100\nG41 Z-30\nG42 Z-40\nM30\n").unwrap();
    let st = testkit::cli!().command::<&str>(&[]).args(["preview", prog.to_str().unwrap(), "-o", out.to_str().unwrap()]).output().expect("run cncgw");
    assert_eq!(st.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&st.stderr).contains("3576"));
    assert!(std::fs::read_to_string(&out).unwrap().contains("<polyline"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Numbers of the tick labels of `class` with their pixel positions (x for Z, y for X).
fn tick_values(doc: &roxmltree::Document, class: &str) -> Vec<(f64, f64)> {
    by_class(doc, class)
        .iter()
        .map(|n| {
            let v: f64 = n.text().unwrap().parse().unwrap_or_else(|_| panic!("tick label {:?}", n.text()));
            (v, if class == "tick-z" { num(n, "x") } else { num(n, "y") - 4.0 })
        })
        .collect()
}

#[test]
fn preview_has_mm_ticks_over_the_part_the_work_zero_and_a_legend_of_what_occurs() {
    let m = moves(PROG);
    let (svg, view) = render_svg(&m, Pos::ZERO, "t.nc", 1000, &Extras::default()).expect("render");
    let doc = parse(&svg);
    // Ticks: round steps, each label at its value's pixel, covering the path (Z −30…10, X
    // radius 0…50 for X100).
    for (class, lo, hi) in [("tick-z", -30.0, 10.0), ("tick-x", 0.0, 50.0)] {
        let t = tick_values(&doc, class);
        assert!(t.len() >= 4, "{class}: {t:?}");
        let step = t[1].0 - t[0].0;
        assert!(t.windows(2).all(|w| ((w[1].0 - w[0].0) - step).abs() < 1e-9), "{class}: uneven {t:?}");
        assert!([1.0, 2.0, 5.0, 10.0, 20.0, 50.0].contains(&step), "{class}: step {step}");
        assert!(t[0].0 <= lo && t[t.len() - 1].0 >= hi, "{class}: {t:?} does not cover {lo}…{hi}");
        for (v, px) in &t {
            let (z, x) = if class == "tick-z" { view.unmap(*px, 0.0) } else { view.unmap(0.0, *px) };
            let got = if class == "tick-z" { z } else { x };
            assert!((got - v).abs() < 1.5 * view.scale(), "{class} {v} drawn at {got}");
        }
    }
    let axis = texts(&doc, "axis-label").join(" | ");
    assert!(axis.contains("Z (mm)") && axis.contains("X radius (mm)"), "{axis}");
    // The work zero mark sits at Z0 X0.
    let w = by_class(&doc, "work-zero");
    assert_eq!(w.len(), 1);
    let tr = w[0].attribute("transform").unwrap();
    let xy: Vec<f64> = tr.trim_start_matches("translate(").trim_end_matches(')').split(' ').map(|v| v.parse().unwrap()).collect();
    let (z, x) = view.unmap(xy[0], xy[1]);
    assert!(z.abs() < 1.5 * view.scale() && x.abs() < 1.5 * view.scale(), "work zero drawn at Z{z} X{x}");
    // The legend: exactly the kinds this program has, and the zero.
    let legend = texts(&doc, "legend");
    assert_eq!(legend, ["rapid", "feed G01–G03", "G90/G94 single cycle", "work zero W"]);
    // Legends outside the drawing: right of its box.
    for n in by_class(&doc, "legend") {
        assert!(num(&n, "x") > (view.left + view.plot_w) as f64, "legend over the data");
    }
    let title = texts(&doc, "title");
    assert_eq!(title, ["t.nc"]);
    let extent = texts(&doc, "extent").join("");
    assert!(extent.contains("Z -30.000 … 10.000 mm") && extent.contains("Ø0.000 … Ø100.000"), "{extent}");
    // A thread adds its own entry, a program without cycles has none.
    let m = moves("G98 G00 X30 Z5\nM03 S500\nG32 Z-20 F1.5\nG00 X40\nM30\n");
    let (svg, _) = render_svg(&m, Pos::ZERO, "th.nc", 800, &Extras::default()).unwrap();
    assert_eq!(texts(&parse(&svg), "legend"), ["rapid", "thread / tap", "work zero W"]);
}

const COMP: &str = "G21\nG99\nT0101\nG0 X16 Z2\nG42 G1 Z0 F0.1\nG1 X20 Z-2\nZ-12\nG2 X30 Z-17 R5\nG1 X36\nZ-30\nG40 G0 X44\nZ2\nM30\n";

fn cncgw(args: &[&std::ffi::OsStr]) -> std::process::Output {
    testkit::cli!().command::<&str>(&[]).args(args).output().expect("run cncgw")
}

#[test]
fn preview_draws_the_stock_and_the_tool_nose_on_compensated_paths() {
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("comp.nc");
    std::fs::write(&prog, COMP).unwrap();
    let tools = dir.path().join("tools.toml");
    // Geometry offsets too: they move the turret, the picture is the tool tip's.
    std::fs::write(&tools, "[1]\nx = -152.3\nz = -310.45\nr = 0.8\ntip = 3\n").unwrap();
    let out = dir.path().join("comp.svg");
    let o = cncgw(&[
        "preview".as_ref(),
        prog.as_os_str(),
        "-o".as_ref(),
        out.as_os_str(),
        "--tools".as_ref(),
        tools.as_os_str(),
        "--stock".as_ref(),
        "40x40+0.5".as_ref(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let svg = std::fs::read_to_string(&out).unwrap();
    let doc = parse(&svg);
    // The stock: Ø40 × 40 from Z0.5, drawn from Z0.5 to Z−39.5 and from X0 to radius 20 (its
    // pixel box read back through the tick labels' scale).
    let st = by_class(&doc, "stock");
    assert_eq!(st.len(), 1);
    assert_eq!((num(&st[0], "data-diameter"), num(&st[0], "data-length"), num(&st[0], "data-face")), (40.0, 40.0, 0.5));
    let zt = tick_values(&doc, "tick-z");
    let mm_per_px = (zt[1].0 - zt[0].0) / (zt[1].1 - zt[0].1);
    assert!((num(&st[0], "width") * mm_per_px - 40.0).abs() < 0.2, "stock width {} px", num(&st[0], "width"));
    assert!((num(&st[0], "height") * mm_per_px - 20.0).abs() < 0.2, "stock height {} px", num(&st[0], "height"));
    let z_at = |px: f64| zt[0].0 + (px - zt[0].1) * mm_per_px;
    assert!((z_at(num(&st[0], "x")) + 39.5).abs() < 0.2, "stock starts at Z{}", z_at(num(&st[0], "x")));
    // The nose: R0.8 tip 3 circles on the compensated blocks only (lines 5–10): their
    // centres R above the Z-parallel cuts (X20 → radius 10 + 0.8) and inside the
    // compensated stretch, never on the rapids before G42 or after G40.
    let noses = by_class(&doc, "nose");
    assert!(noses.len() >= 8, "{}", noses.len());
    for n in &noses {
        assert_eq!(num(n, "data-r"), 0.8);
        let (z, x) = (num(n, "data-z"), num(n, "data-x"));
        assert!((-30.0 - 1e-6..=0.8 + 1e-6).contains(&z), "nose at Z{z} X{x}: outside G42…G40");
        assert!(x > 8.0 && x < 18.8 + 1e-6, "nose at Z{z} X{x}");
    }
    assert!(noses.iter().any(|n| (num(n, "data-z") + 12.0).abs() < 1e-3 && (num(n, "data-x") - 10.8).abs() < 1e-3), "no nose at the end of Z-12");
    assert_eq!(by_class(&doc, "nose-path").len(), 5, "one dotted centre path per compensated move after the start-up");
    let legend = texts(&doc, "legend");
    assert!(legend.iter().any(|l| l.starts_with("tool nose R0.8")) && legend.iter().any(|l| l == "stock Ø40×40 mm"), "{legend:?}");
    let extent = texts(&doc, "extent").join("");
    assert!(extent.starts_with("path Z -30.000 … 2.000 mm, X Ø0.000 … Ø44.000 mm"), "{extent}");
    svg_common::renders(&out);
    // Without the tool table: no radius, no nose.
    let o = cncgw(&["preview".as_ref(), prog.as_os_str(), "-o".as_ref(), out.as_os_str()]);
    assert!(o.status.success());
    let svg = std::fs::read_to_string(&out).unwrap();
    let doc = parse(&svg);
    assert!(by_class(&doc, "nose").is_empty() && !texts(&doc, "legend").iter().any(|l| l.contains("nose")));
    assert!(by_class(&doc, "stock").is_empty());
    // A bad --stock is refused by the argument parser, nothing written.
    let o = cncgw(&["preview".as_ref(), prog.as_os_str(), "-o".as_ref(), dir.path().join("x.svg").as_os_str(), "--stock".as_ref(), "40".as_ref()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("DIAMETERxLENGTH"), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!dir.path().join("x.svg").exists());
    assert_eq!("60x80+1".parse::<Stock>(), Ok(Stock { diameter: 60.0, length: 80.0, face: 1.0 }));
}

#[test]
fn preview_writes_png_through_rsvg_convert() {
    let dir = tempfile::tempdir().unwrap();
    let prog = dir.path().join("p.nc");
    std::fs::write(&prog, PROG).unwrap();
    let png = dir.path().join("p.png");
    let o = cncgw(&["preview".as_ref(), prog.as_os_str(), "-o".as_ref(), png.as_os_str(), "--width".as_ref(), "900".as_ref()]);
    let have = std::process::Command::new("rsvg-convert").arg("--version").output().is_ok();
    if have {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert_eq!(svg_common::png_size(&png).0, 900);
    } else {
        assert_eq!(o.status.code(), Some(4));
        assert!(String::from_utf8_lossy(&o.stderr).contains("librsvg2-bin"));
    }
}
