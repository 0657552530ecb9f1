//! `cncgw plan` output: one line per canonical move, as JSON or as text, in WORKPIECE
//! coordinates as an operator reads them (machine − work offset, X as a diameter).

use crate::canon::{Feed, Move, MoveKind, Pos, SpindleDir};
use serde_json::{json, Map, Value};

/// Round to 0.1 µm so that float noise (12.000000000001) does not show.
fn r(v: f64) -> f64 {
    let x = (v * 1e4).round() / 1e4;
    if x == 0.0 {
        0.0
    } else {
        x
    }
}

fn work(m: &Move, p: Pos) -> Pos {
    p.sub(m.work_offset)
}

fn code(letter: char, value: f64) -> String {
    match letter {
        'M' => format!("M{:02}", value as i64),
        'T' => format!("T{:04}", value as i64),
        _ if value.fract() == 0.0 => format!("{letter}{}", value as i64),
        _ => format!("{letter}{value}"),
    }
}

fn put_end(o: &mut Map<String, Value>, m: &Move, end: Pos) {
    let w = work(m, end);
    o.insert("x".into(), json!(r(w.x * 2.0)));
    o.insert("z".into(), json!(r(w.z)));
    // Y and C are printed when they are in use (non-zero end point or offset).
    if end.y != 0.0 || m.work_offset.y != 0.0 {
        o.insert("y".into(), json!(r(w.y)));
    }
    if end.c != 0.0 || m.work_offset.c != 0.0 {
        o.insert("c".into(), json!(r(w.c)));
    }
}

fn put_feed(o: &mut Map<String, Value>, f: &Feed) {
    match f {
        Feed::PerMin(v) => o.insert("feed".into(), json!(r(*v))),
        Feed::PerRev(v) => o.insert("feed_per_rev".into(), json!(r(*v))),
    };
}

/// The move as a JSON object (no trailing newline).
pub fn move_to_json(m: &Move) -> String {
    let mut o = Map::new();
    o.insert("file".into(), json!(&*m.src.file));
    o.insert("line".into(), json!(m.src.line));
    o.insert("kind".into(), json!(m.kind.name()));
    match &m.kind {
        MoveKind::Rapid { end } => put_end(&mut o, m, *end),
        MoveKind::Feed { end, feed } => {
            put_end(&mut o, m, *end);
            put_feed(&mut o, feed);
        }
        MoveKind::Arc { end, center, cw, feed, .. } => {
            put_end(&mut o, m, *end);
            put_feed(&mut o, feed);
            o.insert("cw".into(), json!(cw));
            let c = work(m, *center);
            o.insert("center".into(), json!({"x": r(c.x * 2.0), "z": r(c.z)}));
        }
        MoveKind::Thread { end, lead, start_angle, .. } => {
            put_end(&mut o, m, *end);
            o.insert("lead".into(), json!(r(*lead)));
            o.insert("start_angle".into(), json!(r(*start_angle)));
        }
        MoveKind::Tap { end, lead, rpm } | MoveKind::RigidThread { end, lead, rpm } => {
            put_end(&mut o, m, *end);
            o.insert("lead".into(), json!(r(*lead)));
            o.insert("rpm".into(), json!(r(*rpm)));
        }
        MoveKind::Dwell { seconds } => {
            o.insert("dwell_s".into(), json!(r(*seconds)));
        }
        MoveKind::Spindle(s) => {
            let dir = match s.dir {
                SpindleDir::Cw => "cw",
                SpindleDir::Ccw => "ccw",
                SpindleDir::Stop => "stop",
            };
            o.insert("dir".into(), json!(dir));
            o.insert("rpm".into(), json!(r(s.rpm)));
            if let Some(c) = s.css {
                o.insert("css".into(), json!(r(c)));
            }
            if let Some(x) = s.max_rpm {
                o.insert("max_rpm".into(), json!(r(x)));
            }
        }
        MoveKind::Aux { letter, value } => {
            o.insert("code".into(), json!(code(*letter, *value)));
        }
        MoveKind::Stop { optional } => {
            o.insert("code".into(), json!(if *optional { "M01" } else { "M00" }));
        }
        MoveKind::End { code: c } => {
            o.insert("code".into(), json!(format!("M{c:02}")));
        }
    }
    if let Some(t) = &m.tag {
        o.insert("cycle".into(), json!(&*t.cycle));
        o.insert("step".into(), json!(t.step));
    }
    Value::Object(o).to_string()
}

fn f4(v: f64) -> String {
    format!("{:.3}", r(v))
}

/// The move as one line of text, e.g. `first.nc:12 feed X40.000 Z-20.000 F0.2/rev`.
pub fn move_to_text(m: &Move) -> String {
    let mut s = format!("{}:{} {}", m.src.file, m.src.line, m.kind.name());
    let end = |s: &mut String, p: Pos| {
        let w = work(m, p);
        s.push_str(&format!(" X{} Z{}", f4(w.x * 2.0), f4(w.z)));
        if p.y != 0.0 || m.work_offset.y != 0.0 {
            s.push_str(&format!(" Y{}", f4(w.y)));
        }
        if p.c != 0.0 || m.work_offset.c != 0.0 {
            s.push_str(&format!(" C{}", f4(w.c)));
        }
    };
    let feed = |s: &mut String, f: &Feed| match f {
        Feed::PerMin(v) => s.push_str(&format!(" F{}/min", r(*v))),
        Feed::PerRev(v) => s.push_str(&format!(" F{}/rev", r(*v))),
    };
    match &m.kind {
        MoveKind::Rapid { end: e } => end(&mut s, *e),
        MoveKind::Feed { end: e, feed: f } => {
            end(&mut s, *e);
            feed(&mut s, f);
        }
        MoveKind::Arc { end: e, center, cw, feed: f, .. } => {
            end(&mut s, *e);
            let c = work(m, *center);
            s.push_str(&format!(" {} centre X{} Z{}", if *cw { "CW" } else { "CCW" }, f4(c.x * 2.0), f4(c.z)));
            feed(&mut s, f);
        }
        MoveKind::Thread { end: e, lead, start_angle, .. } => {
            end(&mut s, *e);
            s.push_str(&format!(" lead {} start {}°", r(*lead), r(*start_angle)));
        }
        MoveKind::Tap { end: e, lead, rpm } | MoveKind::RigidThread { end: e, lead, rpm } => {
            end(&mut s, *e);
            s.push_str(&format!(" lead {} S{}", r(*lead), r(*rpm)));
        }
        MoveKind::Dwell { seconds } => s.push_str(&format!(" {} s", r(*seconds))),
        MoveKind::Spindle(sp) => {
            let dir = match sp.dir {
                SpindleDir::Cw => "M03",
                SpindleDir::Ccw => "M04",
                SpindleDir::Stop => "M05",
            };
            s.push_str(&format!(" {dir} S{}", r(sp.rpm)));
            if let Some(c) = sp.css {
                s.push_str(&format!(" css {} m/min", r(c)));
            }
            if let Some(x) = sp.max_rpm {
                s.push_str(&format!(" max {} rpm", r(x)));
            }
        }
        MoveKind::Aux { letter, value } => s.push_str(&format!(" {}", code(*letter, *value))),
        MoveKind::Stop { optional } => s.push_str(if *optional { " M01" } else { " M00" }),
        MoveKind::End { code: c } => s.push_str(&format!(" M{c:02}")),
    }
    if let Some(t) = &m.tag {
        s.push_str(&format!(" [{} step {}]", t.cycle, t.step));
    }
    s
}
