//! Per-cycle trace of a run (`cncgw run --trace FILE.csv`): setpoint, actual position,
//! following error and the actual's age of every drive, spindle speed, sync error and block
//! line.
//!
//! The cycle thread must not allocate after start, so rows go into preallocated chunks: a
//! full chunk is handed to a writer thread over a bounded channel and comes back empty over
//! another one. If the writer falls behind and no empty chunk is available, rows are dropped
//! and counted (never a stall or an allocation in the cycle).

use std::io::{self, Write};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::thread::JoinHandle;

/// Drives a trace row has room for.
pub const MAX_TRACE_AXES: usize = 8;
/// Rows per chunk (about 2 s at 2 ms).
const CHUNK_ROWS: usize = 1024;
/// Chunks in the pool: how far the writer may fall behind (≈ 16 s at 2 ms).
const CHUNKS: usize = 8;

/// One cycle. Positions in machine units (mm, X as a radius; the spindle in degrees,
/// continuous).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TraceRow {
    /// Time since the start of the program, s.
    pub t_s: f64,
    /// Source line of the block being executed.
    pub line: u32,
    /// Setpoint sent this cycle, per drive.
    pub cmd: [f64; MAX_TRACE_AXES],
    /// Actual position read this cycle, per drive.
    pub act: [f64; MAX_TRACE_AXES],
    /// Following error: the demand this actual belongs to minus the actual (0 when the
    /// feedback was stale or the cycle late, see `CycleLoop`).
    pub ferr: [f64; MAX_TRACE_AXES],
    /// Age of the actual position in SYNC cycles: 0 fresh, n when the drive's frame of this
    /// SYNC had not come and the actual is the one of n cycles before (a late TPDO).
    pub age: [u32; MAX_TRACE_AXES],
    /// Measured spindle speed, rpm.
    pub spindle_rpm: f64,
    /// Spindle–axis sync error, µm (0 outside synchronised moves).
    pub sync_err_um: f64,
}

/// Where the writer thread puts the rows.
pub trait TraceSink: Send + 'static {
    fn header(&mut self, names: &[String]) -> io::Result<()>;
    fn rows(&mut self, names: &[String], rows: &[TraceRow]) -> io::Result<()>;
    fn finish(&mut self) -> io::Result<()>;
}

/// CSV: `t_s,line,NAME_cmd,NAME_act,NAME_ferr,NAME_age,…,spindle_rpm,sync_err_um`.
pub struct CsvSink<W: Write + Send + 'static>(pub W);

impl<W: Write + Send + 'static> TraceSink for CsvSink<W> {
    fn header(&mut self, names: &[String]) -> io::Result<()> {
        write!(self.0, "t_s,line")?;
        for n in names {
            write!(self.0, ",{n}_cmd,{n}_act,{n}_ferr,{n}_age")?;
        }
        writeln!(self.0, ",spindle_rpm,sync_err_um")
    }

    fn rows(&mut self, names: &[String], rows: &[TraceRow]) -> io::Result<()> {
        for r in rows {
            write!(self.0, "{:.6},{}", r.t_s, r.line)?;
            for d in 0..names.len() {
                write!(self.0, ",{:.6},{:.6},{:.6},{}", r.cmd[d], r.act[d], r.ferr[d], r.age[d])?;
            }
            writeln!(self.0, ",{:.3},{:.3}", r.spindle_rpm, r.sync_err_um)?;
        }
        Ok(())
    }

    fn finish(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

/// Collects the rows in memory (tests, benches).
pub struct VecSink(pub std::sync::Arc<std::sync::Mutex<Vec<TraceRow>>>);

impl TraceSink for VecSink {
    fn header(&mut self, _: &[String]) -> io::Result<()> {
        Ok(())
    }
    fn rows(&mut self, _: &[String], rows: &[TraceRow]) -> io::Result<()> {
        self.0.lock().map_err(|_| io::Error::other("trace buffer poisoned"))?.extend_from_slice(rows);
        Ok(())
    }
    fn finish(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// What a finished trace wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraceStats {
    pub rows: u64,
    /// Rows lost because the writer fell behind.
    pub dropped: u64,
}

/// The cycle-side end of a trace. Everything is allocated in [`Trace::spawn`].
pub struct Trace {
    n: usize,
    cur: Vec<TraceRow>,
    full_tx: Option<SyncSender<Vec<TraceRow>>>,
    free_rx: Receiver<Vec<TraceRow>>,
    rows: u64,
    dropped: u64,
    writer: Option<JoinHandle<io::Result<()>>>,
}

impl Trace {
    /// Start the writer thread for drives named `names` (at most [`MAX_TRACE_AXES`]; more
    /// are left out of the trace).
    pub fn spawn(names: Vec<String>, mut sink: impl TraceSink) -> io::Result<Trace> {
        let mut names = names;
        names.truncate(MAX_TRACE_AXES);
        let n = names.len();
        let (full_tx, full_rx) = sync_channel::<Vec<TraceRow>>(CHUNKS);
        let (free_tx, free_rx) = sync_channel::<Vec<TraceRow>>(CHUNKS);
        for _ in 0..CHUNKS - 1 {
            // Capacity CHUNKS: these sends cannot block.
            let _ = free_tx.send(Vec::with_capacity(CHUNK_ROWS));
        }
        let writer = std::thread::Builder::new().name("trace".into()).spawn(move || {
            sink.header(&names)?;
            let mut res = Ok(());
            while let Ok(mut chunk) = full_rx.recv() {
                // After a write error keep recycling chunks (the cycle must not notice), report
                // the error at the end.
                if res.is_ok() {
                    res = sink.rows(&names, &chunk);
                }
                chunk.clear();
                let _ = free_tx.try_send(chunk);
            }
            res?;
            sink.finish()
        })?;
        Ok(Trace { n, cur: Vec::with_capacity(CHUNK_ROWS), full_tx: Some(full_tx), free_rx, rows: 0, dropped: 0, writer: Some(writer) })
    }

    /// A CSV file at `path`.
    pub fn csv(path: &std::path::Path, names: Vec<String>) -> io::Result<Trace> {
        let f = std::fs::File::create(path)?;
        Trace::spawn(names, CsvSink(io::BufWriter::with_capacity(1 << 16, f)))
    }

    /// Number of drives traced.
    pub fn axes(&self) -> usize {
        self.n
    }

    /// Append one row. Never allocates, never blocks.
    pub fn record(&mut self, row: &TraceRow) {
        if self.cur.len() == self.cur.capacity() {
            if !self.cur.is_empty() {
                let full = std::mem::take(&mut self.cur);
                if let Some(tx) = &self.full_tx {
                    // At most CHUNKS chunks exist, so the channel has room; a dead writer
                    // just loses the chunk.
                    let _ = tx.try_send(full);
                }
            }
            match self.free_rx.try_recv() {
                Ok(v) => self.cur = v,
                Err(_) => {
                    self.dropped += 1;
                    return;
                }
            }
            if self.cur.capacity() == 0 {
                self.dropped += 1;
                return;
            }
        }
        self.cur.push(*row);
        self.rows += 1;
    }

    /// Hand the last rows to the writer and wait for it to finish.
    pub fn finish(mut self) -> io::Result<TraceStats> {
        let tail = std::mem::take(&mut self.cur);
        if let Some(tx) = self.full_tx.take() {
            if !tail.is_empty() {
                // Blocking is fine here: the run is over.
                let _ = tx.send(tail);
            }
        }
        let stats = TraceStats { rows: self.rows, dropped: self.dropped };
        match self.writer.take().map(|w| w.join()) {
            Some(Ok(r)) => r.map(|_| stats),
            Some(Err(_)) => Err(io::Error::other("the trace writer thread panicked")),
            None => Ok(stats),
        }
    }
}

/// A trace read back from CSV (for `cncgw trace plot`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TraceData {
    pub columns: Vec<String>,
    /// Column-major values.
    pub values: Vec<Vec<f64>>,
}

impl TraceData {
    pub fn parse(text: &str) -> Result<TraceData, String> {
        let mut lines = text.lines();
        let header = lines.next().ok_or("empty trace file")?;
        let columns: Vec<String> = header.split(',').map(|s| s.trim().to_string()).collect();
        if columns.first().map(String::as_str) != Some("t_s") {
            return Err(format!("not a cncgw trace: the header must start with t_s, got {header:?}"));
        }
        let mut values = vec![Vec::new(); columns.len()];
        for (i, l) in lines.enumerate() {
            if l.trim().is_empty() {
                continue;
            }
            let mut n = 0;
            for (c, f) in l.split(',').enumerate() {
                let v: f64 = f.trim().parse().map_err(|_| format!("line {}: {f:?} is not a number", i + 2))?;
                if let Some(col) = values.get_mut(c) {
                    col.push(v);
                }
                n += 1;
            }
            if n != columns.len() {
                return Err(format!("line {}: {n} fields, the header has {}", i + 2, columns.len()));
            }
        }
        Ok(TraceData { columns, values })
    }

    pub fn column(&self, name: &str) -> Option<&[f64]> {
        self.columns.iter().position(|c| c == name).map(|i| self.values[i].as_slice())
    }

    /// Drive names (from the `NAME_cmd` columns), in file order.
    pub fn axes(&self) -> Vec<String> {
        self.columns.iter().filter_map(|c| c.strip_suffix("_cmd").map(str::to_string)).collect()
    }
}

/// Draw a trace (`cncgw trace plot`) to `out`: SVG, or PNG for a `.png` name
/// ([`crate::plot::save`]).
pub fn plot_svg(data: &TraceData, out: &std::path::Path) -> Result<(), String> {
    let name = out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    crate::plot::save(out, &plot_document(data, &name)?)
}

/// Moved: the command changed by more than 1 µm (or 0.001°) over the run.
fn moved(v: &[f64]) -> bool {
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(*x), b.max(*x)));
    hi - lo > 1e-3
}

/// The picture of a trace: one panel per thing the run did — positions (command dashed dark
/// over actual in the axis' colour) and following errors of the feed axes that moved, the
/// spindle speed when it turned, the sync error when a move was synchronised; what stood
/// still is named in the header instead of drawn flat.
pub fn plot_document(data: &TraceData, name: &str) -> Result<String, String> {
    use crate::plot::{Panel, Series, COMMAND, PALETTE};
    let t = data.column("t_s").ok_or("the trace has no t_s column")?;
    if t.len() < 2 {
        return Err("the trace has fewer than two cycles".into());
    }
    let col = |n: &str| data.column(n).map(|c| c.to_vec());
    let mut pos = Panel { title: "feed axes: position (mm, X as a radius)".into(), ..Panel::default() };
    let mut ferr = Panel { title: "feed axes: following error (µm)".into(), ..Panel::default() };
    let mut still = Vec::new();
    // Drives named s… are spindles (their angle is not a position to plot against mm).
    for (k, a) in data.axes().iter().filter(|a| !a.starts_with('s')).enumerate() {
        let c = PALETTE[k % PALETTE.len()];
        let (Some(cmd), Some(act)) = (col(&format!("{a}_cmd")), col(&format!("{a}_act"))) else { continue };
        if !moved(&cmd) && !moved(&act) {
            still.push(a.clone());
            continue;
        }
        pos.series.push(Series { name: format!("{a} actual"), v: act, colour: c, dashed: false, width: 2.5 });
        pos.series.push(Series { name: format!("{a} command"), v: cmd, colour: COMMAND, dashed: true, width: 1.2 });
        if let Some(f) = col(&format!("{a}_ferr")) {
            ferr.series.push(Series {
                name: format!("{a} following error"),
                v: f.iter().map(|v| v * 1000.0).collect(),
                colour: c,
                dashed: false,
                width: 1.2,
            });
        }
    }
    let mut panels = Vec::new();
    if !pos.series.is_empty() {
        panels.push(pos);
        panels.push(ferr);
    }
    let mut notes = Vec::new();
    match col("spindle_rpm") {
        Some(r) if r.iter().any(|v| v.abs() >= 0.5) => panels.push(Panel {
            title: "spindle speed, measured (rpm)".into(),
            series: vec![Series { name: "spindle rpm".into(), v: r, colour: PALETTE[2], dashed: false, width: 1.5 }],
            ..Panel::default()
        }),
        _ => notes.push("the spindle did not turn".to_string()),
    }
    match col("sync_err_um") {
        Some(e) if e.iter().any(|v| *v != 0.0) => panels.push(Panel {
            title: "spindle–axis sync error (µm)".into(),
            series: vec![Series { name: "sync error".into(), v: e, colour: PALETTE[1], dashed: false, width: 1.2 }],
            ..Panel::default()
        }),
        _ => notes.push("no synchronised move".to_string()),
    }
    if !still.is_empty() {
        notes.insert(0, format!("not moved: {}", still.join(", ")));
    }
    if panels.is_empty() {
        notes.insert(0, "nothing moved: no panel to draw".into());
    }
    let dt = if t.len() > 1 { (t[t.len() - 1] - t[0]) / (t.len() - 1) as f64 } else { 0.0 };
    let mut header =
        vec![(format!("trace {name}: {} cycles over {:.2} s ({:.1} ms each)", t.len(), t[t.len() - 1] - t[0], dt * 1000.0), 16, (0, 0, 0), "title")];
    if !notes.is_empty() {
        header.push((notes.join("; "), 12, (90, 90, 90), "note"));
    }
    crate::plot::time_panels(t, &header, &panels, &format!("cncgw trace {name}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::{Arc, Mutex};

    #[derive(Clone)]
    struct Shared(Arc<Mutex<Vec<u8>>>);
    impl Write for Shared {
        fn write(&mut self, b: &[u8]) -> io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn rows_round_trip_through_csv_across_chunks() {
        let buf = Shared(Arc::new(Mutex::new(Vec::new())));
        let mut t = Trace::spawn(vec!["x".into(), "s1".into()], CsvSink(buf.clone())).unwrap();
        let n = 3 * CHUNK_ROWS + 17;
        for k in 0..n {
            let mut r = TraceRow { t_s: k as f64 * 0.002, line: k as u32 / 100, ..Default::default() };
            r.cmd[0] = k as f64;
            r.act[1] = -(k as f64);
            r.age[1] = (k % 3) as u32;
            r.sync_err_um = 0.5;
            t.record(&r);
            // Give the writer time now and then, as the cycle period does.
            if k % CHUNK_ROWS == 0 {
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        }
        let st = t.finish().unwrap();
        assert_eq!(st, TraceStats { rows: n as u64, dropped: 0 });
        let text = String::from_utf8(buf.0.lock().unwrap().clone()).unwrap();
        let d = TraceData::parse(&text).unwrap();
        assert_eq!(d.columns[..6], ["t_s", "line", "x_cmd", "x_act", "x_ferr", "x_age"]);
        assert_eq!(d.axes(), ["x", "s1"]);
        assert_eq!(d.column("x_cmd").unwrap().len(), n);
        assert_eq!(d.column("x_cmd").unwrap()[n - 1], (n - 1) as f64);
        assert_eq!(d.column("s1_act").unwrap()[5], -5.0);
        assert_eq!(d.column("s1_age").unwrap()[5], 2.0);
        assert_eq!(d.column("sync_err_um").unwrap()[7], 0.5);
    }

    #[test]
    fn a_stalled_writer_drops_rows_instead_of_blocking() {
        struct Stall(Arc<Mutex<()>>);
        impl TraceSink for Stall {
            fn header(&mut self, _: &[String]) -> io::Result<()> {
                Ok(())
            }
            fn rows(&mut self, _: &[String], _: &[TraceRow]) -> io::Result<()> {
                drop(self.0.lock());
                Ok(())
            }
            fn finish(&mut self) -> io::Result<()> {
                Ok(())
            }
        }
        let gate = Arc::new(Mutex::new(()));
        let held = gate.lock().unwrap();
        let mut t = Trace::spawn(vec!["z".into()], Stall(gate.clone())).unwrap();
        let n = (CHUNKS + 2) * CHUNK_ROWS;
        for _ in 0..n {
            t.record(&TraceRow::default());
        }
        drop(held);
        let st = t.finish().unwrap();
        assert!(st.dropped > 0, "{st:?}");
        assert_eq!(st.rows + st.dropped, n as u64);
    }

    #[test]
    fn the_plot_has_panels_only_for_what_moved() {
        // x moves, z stands, the spindle never turns, nothing is synchronised.
        let mut csv = String::from("t_s,line,x_cmd,x_act,x_ferr,z_cmd,z_act,z_ferr,s1_cmd,s1_act,s1_ferr,spindle_rpm,sync_err_um\n");
        for k in 0..50 {
            let x = k as f64 * 0.1;
            csv += &format!("{},{},{x},{},0.001,5,5,0,0,0,0,0,0\n", k as f64 * 0.002, 3, x - 0.001);
        }
        let svg = plot_document(&TraceData::parse(&csv).unwrap(), "t").unwrap();
        let titles: Vec<&str> = svg.split("data-title=\"").skip(1).map(|s| &s[..s.find('"').unwrap()]).collect();
        assert_eq!(titles, ["feed axes: position (mm, X as a radius)", "feed axes: following error (µm)"]);
        assert!(svg.contains("not moved: z; the spindle did not turn; no synchronised move"), "{svg}");
        assert!(svg.contains("data-name=\"x command\"") && !svg.contains("data-name=\"z command\""));
        // Nothing at all: a page that says so, no empty panel.
        let still = csv.lines().take(1).chain(std::iter::repeat_n("0.1,1,0,0,0,5,5,0,0,0,0,0,0", 3)).collect::<Vec<_>>().join("\n");
        let mut d = TraceData::parse(&still).unwrap();
        d.values[0] = vec![0.0, 0.002, 0.004];
        let svg = plot_document(&d, "t").unwrap();
        assert!(!svg.contains("class=\"panel\"") && svg.contains("nothing moved"), "{svg}");
    }

    #[test]
    fn malformed_trace_files_are_errors() {
        assert!(TraceData::parse("").is_err());
        assert!(TraceData::parse("a,b\n1,2\n").is_err());
        assert!(TraceData::parse("t_s,line\n0.1,x\n").is_err());
        assert!(TraceData::parse("t_s,line\n0.1\n").is_err());
    }
}
