//! `cncgw preview`: the SVG is parsed back and its polylines checked against the program's
//! path (through the view's pixel ↔ workpiece mapping).

use cncgw::canon::{Move, Pos};
use cncgw::cli::preview::{render_svg, View};
use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;

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
    let (svg, view) = render_svg(&m, Pos::ZERO, "t.nc", 800).expect("render");
    assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
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
    let sx = (view.z.1 - view.z.0) / (view.width - 2 * view.margin) as f64;
    let sy = (view.x.1 - view.x.0) / (view.height - 2 * view.margin) as f64;
    assert!((sx - sy).abs() < 1e-9 * sx.max(1.0), "{sx} {sy}");
}

#[test]
fn cli_writes_the_file() {
    let dir = std::env::temp_dir().join(format!("cncgw-preview-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("p.nc");
    std::fs::write(&prog, PROG).unwrap();
    let out = dir.join("p.svg");
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["preview", prog.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .status()
        .expect("run cncgw");
    assert!(st.success());
    let svg = std::fs::read_to_string(&out).expect("svg written");
    assert!(polylines(&svg).iter().any(|l| l.0 == "#1E50DC"));
    // An alarm: exit code 2, the path up to it still drawn.
    std::fs::write(&prog, "G98 G00 X40 Z2\nG01 Z-20 F100\nG41 Z-30\nG42 Z-40\nM30\n").unwrap();
    let st = std::process::Command::new(env!("CARGO_BIN_EXE_cncgw"))
        .env("CNCGW_STATE_DIR", std::env::temp_dir().join(format!("cncgw-test-state-{}", std::process::id())))
        .args(["preview", prog.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .output()
        .expect("run cncgw");
    assert_eq!(st.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&st.stderr).contains("3576"));
    assert!(std::fs::read_to_string(&out).unwrap().contains("<polyline"));
    let _ = std::fs::remove_dir_all(&dir);
}
