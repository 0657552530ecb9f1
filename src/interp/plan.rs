//! `cncgw plan` output: one line per canonical move, as JSON or as text, in WORKPIECE
//! coordinates as an operator reads them (machine − work offset, X as a diameter).

use crate::canon::{Feed, Move, MoveKind, Pos, SpindleDir};

/// Round to 0.1 µm so that float noise (12.000000000001) does not show.
fn r(v: f64) -> f64 {
    let x = crate::interp::gcode::round(v * 1e4) / 1e4;
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

/// A JSON value of a `plan` line, written without building a `serde_json::Value` (the
/// listing of a million-block program spends most of its time here).
#[derive(Clone, Copy)]
enum J<'a> {
    Num(f64),
    Int(u32),
    Bool(bool),
    Str(&'a str),
    Code(char, f64),
    /// `{"x": …, "z": …}`
    Xz(f64, f64),
}

struct Obj<'a> {
    f: [(&'static str, J<'a>); 16],
    n: usize,
}

impl<'a> Obj<'a> {
    fn put(&mut self, k: &'static str, v: J<'a>) {
        if self.n < self.f.len() {
            self.f[self.n] = (k, v);
            self.n += 1;
        }
    }
}

/// `num(out, r(v))` in one step: the value rounded to 0.0001 as a scaled integer. The text
/// is the same: below 1e15 the decimal `int.frac` is the shortest form of `r(v)`.
fn num_r(out: &mut Vec<u8>, v: f64) {
    let scaled = crate::interp::gcode::round(v * 1e4);
    if scaled.is_finite() && scaled.abs() < 1e15 {
        scaled_num(out, scaled as i64);
    } else {
        num(out, r(v));
    }
}

fn num(out: &mut Vec<u8>, v: f64) {
    use std::io::Write;
    // Values are rounded to 0.0001 by `r`: print them as a scaled integer, which gives the
    // same text as the shortest round-trip form (`20.05`, `54.0`, `-0.025`) much faster.
    let scaled = v * 1e4;
    if v.is_finite() && scaled.abs() < 1e15 && scaled == crate::interp::gcode::round(scaled) {
        scaled_num(out, scaled as i64);
        return;
    }
    if v.is_finite() {
        // Debug of f64 is the shortest round-trip form with a `.0` on integers, like serde_json.
        let _ = write!(out, "{v:?}");
    } else {
        out.extend_from_slice(b"null");
    }
}

/// "00" "01" … "99": numbers are written two digits per division.
const PAIRS: &[u8; 200] = b"0001020304050607080910111213141516171819\
2021222324252627282930313233343536373839\
4041424344454647484950515253545556575859\
6061626364656667686970717273747576777879\
8081828384858687888990919293949596979899";

/// The digits of `k` written right to left ending at `buf[i]` (exclusive); the new start.
fn digits_back(buf: &mut [u8; 32], mut i: usize, mut k: u64) -> usize {
    while k >= 100 {
        let r = (k % 100) as usize * 2;
        k /= 100;
        i -= 2;
        buf[i..i + 2].copy_from_slice(&PAIRS[r..r + 2]);
    }
    if k >= 10 {
        let r = k as usize * 2;
        i -= 2;
        buf[i..i + 2].copy_from_slice(&PAIRS[r..r + 2]);
    } else {
        i -= 1;
        buf[i] = b'0' + k as u8;
    }
    i
}

/// `n` / 10⁴ as a decimal with at least one fractional digit (`20.05`, `54.0`, `-0.025`).
fn scaled_num(out: &mut Vec<u8>, n: i64) {
    let a = n.unsigned_abs();
    let (int, frac) = (a / 10_000, (a % 10_000) as usize);
    // Built right to left in a stack buffer, appended once.
    let mut buf = [0u8; 32];
    let mut i = buf.len();
    if frac == 0 {
        i -= 1;
        buf[i] = b'0';
    } else {
        let (hi, lo) = (frac / 100 * 2, frac % 100 * 2);
        let d = [PAIRS[hi], PAIRS[hi + 1], PAIRS[lo], PAIRS[lo + 1]];
        // Trailing zeros dropped (frac ≠ 0: at least one digit stays).
        let k = 4 - d.iter().rev().take_while(|&&c| c == b'0').count();
        i -= k;
        buf[i..i + k].copy_from_slice(&d[..k]);
    }
    i -= 1;
    buf[i] = b'.';
    i = digits_back(&mut buf, i, int);
    if n < 0 {
        i -= 1;
        buf[i] = b'-';
    }
    out.extend_from_slice(&buf[i..]);
}

/// Decimal digits of `n` (no allocation, no formatter).
fn uint(out: &mut Vec<u8>, n: u64) {
    let mut buf = [0u8; 32];
    let i = digits_back(&mut buf, 32, n);
    out.extend_from_slice(&buf[i..]);
}

/// [`json_str`] of a move's file name: every move of a program carries the same `Arc`, so
/// the last one found to need no escaping is kept (holding it keeps its address unique).
fn json_file(out: &mut Vec<u8>, f: &std::sync::Arc<str>) {
    thread_local! {
        static PLAIN: std::cell::RefCell<Option<std::sync::Arc<str>>> = const { std::cell::RefCell::new(None) };
    }
    let known = PLAIN.with(|c| c.borrow().as_ref().is_some_and(|p| std::sync::Arc::ptr_eq(p, f)));
    if known {
        out.push(b'"');
        out.extend_from_slice(f.as_bytes());
        out.push(b'"');
        return;
    }
    if !f.bytes().any(|b| b == b'"' || b == b'\\' || b < 0x20) {
        PLAIN.with(|c| *c.borrow_mut() = Some(f.clone()));
    }
    json_str(out, f);
}

fn json_str(out: &mut Vec<u8>, s: &str) {
    use std::io::Write;
    out.push(b'"');
    if !s.bytes().any(|b| b == b'"' || b == b'\\' || b < 0x20) {
        out.extend_from_slice(s.as_bytes());
        out.push(b'"');
        return;
    }
    for ch in s.chars() {
        match ch {
            '"' => out.extend_from_slice("\\\"".as_bytes()),
            '\\' => out.extend_from_slice("\\\\".as_bytes()),
            '\n' => out.extend_from_slice("\\n".as_bytes()),
            '\r' => out.extend_from_slice("\\r".as_bytes()),
            '\t' => out.extend_from_slice("\\t".as_bytes()),
            c if (c as u32) < 0x20 => {
                let _ = write!(out, "\\u{:04x}", c as u32);
            }
            c => out.extend_from_slice(c.encode_utf8(&mut [0; 4]).as_bytes()),
        }
    }
    out.push(b'"');
}

fn key_rank(k: &str) -> u8 {
    match k {
        "c" => 0,
        "center" => 1,
        "code" => 2,
        "continuous" => 3,
        "css" => 4,
        "cw" => 5,
        "cycle" => 6,
        "dir" => 7,
        "dwell_s" => 8,
        "feed" => 9,
        "feed_per_rev" => 10,
        "file" => 11,
        "forbid" => 12,
        "hi" => 13,
        "kind" => 14,
        "lead" => 15,
        "lead_inc" => 16,
        "line" => 17,
        "lo" => 18,
        "max_rpm" => 19,
        "phase" => 20,
        "rpm" => 21,
        "start_angle" => 22,
        "step" => 23,
        "tool_rpm" => 24,
        "x" => 25,
        "y" => 26,
        "z" => 27,
        _ => u8::MAX,
    }
}

fn put_end<'a>(o: &mut Obj<'a>, m: &Move, end: Pos) {
    let w = work(m, end);
    o.put("x", J::Num(r(w.x * 2.0)));
    o.put("z", J::Num(r(w.z)));
    // Y and C are printed when they are in use (non-zero end point or offset).
    if end.y != 0.0 || m.work_offset.y != 0.0 {
        o.put("y", J::Num(r(w.y)));
    }
    if end.c != 0.0 || m.work_offset.c != 0.0 {
        o.put("c", J::Num(r(w.c)));
    }
}

fn put_feed(o: &mut Obj<'_>, f: &Feed) {
    match f {
        Feed::PerMin(v) => o.put("feed", J::Num(r(*v))),
        Feed::PerRev(v) => o.put("feed_per_rev", J::Num(r(*v))),
    };
}

/// The move as a JSON object (no trailing newline), keys in alphabetical order.
pub fn move_to_json(m: &Move) -> String {
    let mut s = Vec::with_capacity(128);
    write_json(&mut s, m);
    // Only ASCII and whole `&str`s were written: always UTF-8.
    String::from_utf8(s).unwrap_or_else(|e| String::from_utf8_lossy(e.as_bytes()).into_owned())
}

/// [`move_to_json`] appended to `out` (bytes: numbers are written without UTF-8 checks).
pub fn write_json(out: &mut Vec<u8>, m: &Move) {
    if write_json_straight(out, m) {
        return;
    }
    let mut o = Obj { f: [("", J::Int(0)); 16], n: 0 };
    o.put("file", J::Str(&m.src.file));
    o.put("line", J::Int(m.src.line));
    o.put("kind", J::Str(m.kind.name()));
    match &m.kind {
        MoveKind::Rapid { end } => put_end(&mut o, m, *end),
        MoveKind::Feed { end, feed } => {
            put_end(&mut o, m, *end);
            put_feed(&mut o, feed);
        }
        MoveKind::Arc { end, center, cw, feed, .. } => {
            put_end(&mut o, m, *end);
            put_feed(&mut o, feed);
            o.put("cw", J::Bool(*cw));
            let c = work(m, *center);
            o.put("center", J::Xz(r(c.x * 2.0), r(c.z)));
        }
        MoveKind::Thread { end, lead, start_angle, continuous, lead_inc } => {
            put_end(&mut o, m, *end);
            o.put("lead", J::Num(r(*lead)));
            o.put("start_angle", J::Num(r(*start_angle)));
            if *continuous {
                o.put("continuous", J::Bool(true));
            }
            if *lead_inc != 0.0 {
                o.put("lead_inc", J::Num(r(*lead_inc)));
            }
        }
        MoveKind::Tap { end, lead, rpm, spindle } => {
            put_end(&mut o, m, *end);
            o.put("lead", J::Num(r(*lead)));
            o.put("rpm", J::Num(r(*rpm)));
            o.put("spindle", J::Int(u32::from(*spindle)));
        }
        MoveKind::RigidThread { end, lead, rpm } => {
            put_end(&mut o, m, *end);
            o.put("lead", J::Num(r(*lead)));
            o.put("rpm", J::Num(r(*rpm)));
        }
        MoveKind::Dwell { seconds } => o.put("dwell_s", J::Num(r(*seconds))),
        MoveKind::Spindle(s) => {
            let dir = match s.dir {
                SpindleDir::Cw => "cw",
                SpindleDir::Ccw => "ccw",
                SpindleDir::Stop => "stop",
            };
            o.put("dir", J::Str(dir));
            o.put("rpm", J::Num(r(s.rpm)));
            if let Some(c) = s.css {
                o.put("css", J::Num(r(c)));
            }
            if let Some(x) = s.max_rpm {
                o.put("max_rpm", J::Num(r(x)));
            }
        }
        MoveKind::Aux { letter, value } => o.put("code", J::Code(*letter, *value)),
        MoveKind::Stop { optional } => o.put("code", J::Str(if *optional { "M01" } else { "M00" })),
        MoveKind::End { code: c } => o.put("code", J::Code('M', *c as f64)),
        MoveKind::Polar { end, center, cw, feed, .. } => {
            put_end(&mut o, m, *end);
            put_feed(&mut o, feed);
            if center.is_some() {
                o.put("cw", J::Bool(*cw));
            }
        }
        MoveKind::Polygon(p) => match p {
            Some(p) => {
                o.put("rpm", J::Num(r(p.rpm)));
                o.put("tool_rpm", J::Num(r(p.tool_rpm)));
                o.put("phase", J::Num(r(p.phase)));
            }
            None => o.put("code", J::Str("G50.2")),
        },
        // The G22 area in machine coordinates (X diameter), not work coordinates.
        MoveKind::StrokeCheck { area } => match area {
            Some(a) => {
                o.put("forbid", J::Str(if a.outside { "outside" } else { "inside" }));
                o.put("lo", J::Xz(r(a.lo.x * 2.0), r(a.lo.z)));
                o.put("hi", J::Xz(r(a.hi.x * 2.0), r(a.hi.z)));
            }
            None => o.put("forbid", J::Str("none")),
        },
    }
    if let Some(t) = &m.tag {
        o.put("cycle", J::Str(&t.cycle));
        o.put("step", J::Int(t.step as u32));
    }
    write_obj(out, &o);
}

/// The fast path of [`write_json`]: straight lines without Y/C or a cycle tag (nearly
/// every line of a CAM program), keys written in their sorted order directly. Returns
/// false (nothing written) for any other move.
fn write_json_straight(out: &mut Vec<u8>, m: &Move) -> bool {
    if let (MoveKind::Rapid { end } | MoveKind::Feed { end, .. }, None) = (&m.kind, &m.tag) {
        if end.y == 0.0 && m.work_offset.y == 0.0 && end.c == 0.0 && m.work_offset.c == 0.0 {
            out.push(b'{');
            match &m.kind {
                MoveKind::Feed { feed: Feed::PerMin(v), .. } => {
                    out.extend_from_slice("\"feed\":".as_bytes());
                    num_r(out, *v);
                    out.push(b',');
                }
                MoveKind::Feed { feed: Feed::PerRev(v), .. } => {
                    out.extend_from_slice("\"feed_per_rev\":".as_bytes());
                    num_r(out, *v);
                    out.push(b',');
                }
                _ => {}
            }
            out.extend_from_slice("\"file\":".as_bytes());
            json_file(out, &m.src.file);
            out.extend_from_slice(",\"kind\":\"".as_bytes());
            out.extend_from_slice(m.kind.name().as_bytes());
            out.extend_from_slice("\",\"line\":".as_bytes());
            uint(out, m.src.line as u64);
            let w = work(m, *end);
            out.extend_from_slice(",\"x\":".as_bytes());
            num_r(out, w.x * 2.0);
            out.extend_from_slice(",\"z\":".as_bytes());
            num_r(out, w.z);
            out.push(b'}');
            return true;
        }
    }
    false
}

/// The fields of `o` as a JSON object, keys in alphabetical order.
fn write_obj(out: &mut Vec<u8>, o: &Obj) {
    let fields = &o.f[..o.n];
    // Alphabetical key order by a precomputed rank (string comparisons cost more than the
    // rest of the line).
    let mut ranked = [(0u8, 0usize); 16];
    for (i, f) in fields.iter().enumerate() {
        ranked[i] = (key_rank(f.0), i);
    }
    let ranked = &mut ranked[..fields.len()];
    ranked.sort_unstable();
    out.push(b'{');
    for (i, &(_, fi)) in ranked.iter().enumerate() {
        let (k, v) = &fields[fi];
        if i > 0 {
            out.push(b',');
        }
        out.push(b'"');
        out.extend_from_slice(k.as_bytes());
        out.extend_from_slice("\":".as_bytes());
        match *v {
            J::Num(x) => num(out, x),
            J::Int(x) => uint(out, x as u64),
            J::Bool(b) => out.extend_from_slice(if b { b"true" } else { b"false" }),
            J::Str(t) => json_str(out, t),
            J::Code(l, x) => json_str(out, &code(l, x)),
            J::Xz(x, z) => {
                out.extend_from_slice("{\"x\":".as_bytes());
                num(out, x);
                out.extend_from_slice(",\"z\":".as_bytes());
                num(out, z);
                out.push(b'}');
            }
        }
    }
    out.push(b'}');
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
        MoveKind::Tap { end: e, lead, rpm, .. } | MoveKind::RigidThread { end: e, lead, rpm } => {
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
        MoveKind::Polar { end: e, from, to, center, cw, feed: f, .. } => {
            end(&mut s, *e);
            s.push_str(&format!(" virtual X{} C{} → X{} C{}", f4(from[0] * 2.0), f4(from[1]), f4(to[0] * 2.0), f4(to[1])));
            if center.is_some() {
                s.push_str(if *cw { " CW" } else { " CCW" });
            }
            feed(&mut s, f);
        }
        MoveKind::Polygon(Some(p)) => s.push_str(&format!(" P{} Q{} R{} S{} tool {} rpm", p.p, p.q, r(p.phase), r(p.rpm), r(p.tool_rpm))),
        MoveKind::Polygon(None) => s.push_str(" G50.2"),
        MoveKind::StrokeCheck { area: Some(a) } => s.push_str(&format!(
            " forbid {} X{}…{} Z{}…{} (machine, X diameter)",
            if a.outside { "outside" } else { "inside" },
            f4(a.lo.x * 2.0),
            f4(a.hi.x * 2.0),
            f4(a.lo.z),
            f4(a.hi.z)
        )),
        MoveKind::StrokeCheck { area: None } => s.push_str(" off"),
    }
    if let Some(t) = &m.tag {
        s.push_str(&format!(" [{} step {}]", t.cycle, t.step));
    }
    s
}
