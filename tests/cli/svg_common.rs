//! The pictures' SVG parsed back (roxmltree) for the preview, trace plot and tap-test tests:
//! texts by class, attributes as numbers, and a rendering through rsvg-convert when it is
//! installed.
#![allow(dead_code)]

use roxmltree::{Document, Node};

/// Parse, failing the test on malformed XML.
pub fn parse(svg: &str) -> Document<'_> {
    Document::parse(svg).unwrap_or_else(|e| panic!("not well-formed SVG: {e}"))
}

/// Elements with `class`, in document order.
pub fn by_class<'a, 'i>(doc: &'a Document<'i>, class: &str) -> Vec<Node<'a, 'i>> {
    doc.descendants().filter(|n| n.attribute("class") == Some(class)).collect()
}

/// The text of every element with `class`.
pub fn texts(doc: &Document, class: &str) -> Vec<String> {
    by_class(doc, class).iter().map(|n| n.text().unwrap_or("").to_string()).collect()
}

/// Attribute `name` as a number.
pub fn num(n: &Node, name: &str) -> f64 {
    let v = n.attribute(name).unwrap_or_else(|| panic!("<{}> has no {name}", n.tag_name().name()));
    v.parse().unwrap_or_else(|_| panic!("{name}={v:?} is not a number"))
}

/// The SVG's width and height attributes.
pub fn size(doc: &Document) -> (f64, f64) {
    let r = doc.root_element();
    (num(&r, "width"), num(&r, "height"))
}

/// Render `svg_path` to PNG with rsvg-convert and check the PNG's size against the SVG's;
/// false (with a note) when rsvg-convert is not installed (Debian: librsvg2-bin), a failure
/// under CI.
pub fn renders(svg_path: &std::path::Path) -> bool {
    let png = svg_path.with_extension("render.png");
    match std::process::Command::new("rsvg-convert").arg(svg_path).arg("-o").arg(&png).output() {
        Err(e) => {
            // CI installs it (scripts/install-test-deps.sh): there a missing renderer fails.
            assert!(std::env::var("CI").as_deref() != Ok("true"), "rsvg-convert: {e} (scripts/install-test-deps.sh installs librsvg2-bin)");
            eprintln!("note: rsvg-convert is not installed: {} not rendered", svg_path.display());
            false
        }
        Ok(o) => {
            assert!(o.status.success(), "rsvg-convert {}: {}", svg_path.display(), String::from_utf8_lossy(&o.stderr));
            let text = std::fs::read_to_string(svg_path).unwrap();
            let (w, h) = size(&parse(&text));
            assert_eq!(png_size(&png), (w as u32, h as u32), "{}", png.display());
            true
        }
    }
}

/// Width and height from a PNG's IHDR.
pub fn png_size(path: &std::path::Path) -> (u32, u32) {
    let b = std::fs::read(path).unwrap();
    assert_eq!(&b[..8], b"\x89PNG\r\n\x1a\n", "{} is not a PNG", path.display());
    let be = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    (be(16), be(20))
}

/// The data box of a time panel (its last unfilled rect): left and right edge, px.
pub fn frame_x(panel: &Node) -> (f64, f64) {
    let f = panel.children().rfind(|n| n.has_tag_name("rect") && n.attribute("fill") == Some("none")).expect("panel frame");
    (num(&f, "x"), num(&f, "x") + num(&f, "width"))
}
