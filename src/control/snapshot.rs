//! The machine's state as the cycle thread last saw it, for observers that must never delay
//! it (the OPC UA server, `src/opcua/`): a seqlock over a fixed-size `Copy` record kept in
//! atomics. The cycle thread [`Snapshot::publish`]es every cycle — a sequence increment, one
//! relaxed store per word, a release store: no lock, no allocation, no system call, no wait on
//! a reader. A reader copies the words and retries when the sequence says a publish ran
//! meanwhile (a few hundred ns; the writer never waits for it).
//!
//! What does not fit a fixed record (the program's name, an alarm's text) is set outside the
//! cycle, before the run and after it, behind a mutex the cycle thread never touches
//! ([`Snapshot::set_program`], [`Snapshot::set_alarm`]).

use std::sync::atomic::{fence, AtomicU64, Ordering};
use std::sync::Mutex;

/// Drives the record has room for (the machine's axes, spindles included).
pub const SNAP_AXES: usize = 8;

/// The machine's state, as OPC 40501-1's MachineTool/Channel state reads it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(u8)]
pub enum MachineState {
    /// Not running a program (before the run, after its end).
    #[default]
    Idle = 0,
    Running = 1,
    /// Feed hold or a program stop (M00/M01) waiting for cycle start.
    Held = 2,
    /// The run stopped on an alarm.
    Alarm = 3,
    /// The run stopped on E-stop.
    EStop = 4,
}

impl MachineState {
    fn from_u8(v: u8) -> MachineState {
        match v {
            1 => MachineState::Running,
            2 => MachineState::Held,
            3 => MachineState::Alarm,
            4 => MachineState::EStop,
            _ => MachineState::Idle,
        }
    }

    /// "Idle", "Running", … (the OPC UA string variable).
    pub fn name(self) -> &'static str {
        match self {
            MachineState::Idle => "Idle",
            MachineState::Running => "Running",
            MachineState::Held => "Held",
            MachineState::Alarm => "Alarm",
            MachineState::EStop => "EStop",
        }
    }
}

/// One drive in the record.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AxisSnap {
    /// Commanded position (the last set-point), mm or degrees.
    pub cmd: f64,
    /// Actual position the drive reported, mm or degrees.
    pub act: f64,
    /// Following error of the last cycle that measured it, mm or degrees.
    pub ferr: f64,
    /// CiA 402 statusword.
    pub statusword: u16,
}

/// The record the cycle thread publishes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MachineSnap {
    /// Cycles published (0: nothing yet).
    pub cycle: u64,
    pub state: MachineState,
    /// Line of the block in execution.
    pub line: u32,
    /// Blocks executed in this run.
    pub blocks: u64,
    /// Time since the run's first cycle, s.
    pub elapsed_s: f64,
    pub axes: [AxisSnap; SNAP_AXES],
    /// Drives in `axes`.
    pub n_axes: u8,
    /// Spindle speed commanded (override applied) and measured, rpm.
    pub spindle_cmd_rpm: f64,
    pub spindle_act_rpm: f64,
    /// Spindle load: torque actual 0x6077 of the spindle drive in percent of its rated
    /// torque, as the bus last read it (NaN: not reported).
    pub spindle_load_pct: f64,
    /// Spindle override, 0.5 … 1.2.
    pub spindle_override: f64,
    /// Feed override, 0 … 2.
    pub feed_override: f64,
    /// Path feed, mm/min.
    pub feed: f64,
    /// Spindle–axis sync error of the thread or tap in progress, µm (0 outside one).
    pub sync_err_um: f64,
    /// Program ends (M02/M30) reached by this process: the part counter.
    pub parts: u64,
    /// Number of the alarm the run stopped on (0: none).
    pub alarm: u32,
}

/// Words of a [`MachineSnap`] in the seqlock.
const HEAD_WORDS: usize = 13;
const WORDS: usize = HEAD_WORDS + 4 * SNAP_AXES;

impl MachineSnap {
    fn to_words(self) -> [u64; WORDS] {
        let mut w = [0u64; WORDS];
        w[0] = self.cycle;
        w[1] = self.state as u64 | (self.n_axes as u64) << 8 | (self.line as u64) << 32;
        w[2] = self.blocks;
        w[3] = self.elapsed_s.to_bits();
        w[4] = self.spindle_cmd_rpm.to_bits();
        w[5] = self.spindle_act_rpm.to_bits();
        w[6] = self.spindle_override.to_bits();
        w[7] = self.feed_override.to_bits();
        w[8] = self.feed.to_bits();
        w[9] = self.sync_err_um.to_bits();
        w[10] = self.parts;
        w[11] = self.alarm as u64;
        w[12] = self.spindle_load_pct.to_bits();
        for (k, a) in self.axes.iter().enumerate() {
            let b = HEAD_WORDS + 4 * k;
            w[b] = a.cmd.to_bits();
            w[b + 1] = a.act.to_bits();
            w[b + 2] = a.ferr.to_bits();
            w[b + 3] = a.statusword as u64;
        }
        w
    }

    fn from_words(w: &[u64; WORDS]) -> MachineSnap {
        let mut s = MachineSnap {
            cycle: w[0],
            state: MachineState::from_u8(w[1] as u8),
            n_axes: (w[1] >> 8) as u8,
            line: (w[1] >> 32) as u32,
            blocks: w[2],
            elapsed_s: f64::from_bits(w[3]),
            spindle_cmd_rpm: f64::from_bits(w[4]),
            spindle_act_rpm: f64::from_bits(w[5]),
            spindle_override: f64::from_bits(w[6]),
            feed_override: f64::from_bits(w[7]),
            feed: f64::from_bits(w[8]),
            sync_err_um: f64::from_bits(w[9]),
            parts: w[10],
            alarm: w[11] as u32,
            spindle_load_pct: f64::from_bits(w[12]),
            axes: [AxisSnap::default(); SNAP_AXES],
        };
        for (k, a) in s.axes.iter_mut().enumerate() {
            let b = HEAD_WORDS + 4 * k;
            *a = AxisSnap { cmd: f64::from_bits(w[b]), act: f64::from_bits(w[b + 1]), ferr: f64::from_bits(w[b + 2]), statusword: w[b + 3] as u16 };
        }
        s
    }
}

/// What is set outside the cycle: the run's program and the last alarm's text.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunInfo {
    /// The program's file name (`<stdin>` for `run -`).
    pub program: String,
    /// Lines in the program (progress = line / lines).
    pub lines: u32,
    /// Drive names, in the record's order.
    pub axes: Vec<String>,
    /// Alarms set so far (`set_alarm`), so that a reader sees each once.
    pub alarm_seq: u64,
    pub alarm_number: u32,
    pub alarm_text: String,
}

/// The seqlock the cycle thread writes and observers read; share it in an `Arc`.
pub struct Snapshot {
    seq: AtomicU64,
    words: [AtomicU64; WORDS],
    info: Mutex<RunInfo>,
}

impl Default for Snapshot {
    fn default() -> Self {
        Snapshot { seq: AtomicU64::new(0), words: std::array::from_fn(|_| AtomicU64::new(0)), info: Mutex::new(RunInfo::default()) }
    }
}

impl Snapshot {
    pub fn new() -> Snapshot {
        Snapshot::default()
    }

    /// Publish `s` (the cycle thread; one writer only). Never blocks, never allocates.
    pub fn publish(&self, s: &MachineSnap) {
        let w = s.to_words();
        // Odd while writing: a reader that saw it, or sees the sequence move, retries.
        let seq = self.seq.load(Ordering::Relaxed);
        self.seq.store(seq.wrapping_add(1), Ordering::Relaxed);
        fence(Ordering::Release);
        for (a, v) in self.words.iter().zip(w) {
            a.store(v, Ordering::Relaxed);
        }
        self.seq.store(seq.wrapping_add(2), Ordering::Release);
    }

    /// The last complete record (observers). Spins only while a publish is under way.
    pub fn read(&self) -> MachineSnap {
        loop {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 & 1 == 1 {
                std::hint::spin_loop();
                continue;
            }
            let mut w = [0u64; WORDS];
            for (v, a) in w.iter_mut().zip(&self.words) {
                *v = a.load(Ordering::Relaxed);
            }
            fence(Ordering::Acquire);
            if self.seq.load(Ordering::Relaxed) == s1 {
                return MachineSnap::from_words(&w);
            }
        }
    }

    /// The program of the run about to start, its line count and the drive names (before
    /// the run, not from the cycle thread).
    pub fn set_program(&self, program: &str, lines: u32, axes: Vec<String>) {
        let mut i = self.info.lock().unwrap_or_else(|e| e.into_inner());
        i.program = program.to_string();
        i.lines = lines;
        i.axes = axes;
    }

    /// The alarm the run stopped on, with its text (after the run, not from the cycle thread).
    pub fn set_alarm(&self, a: &crate::Alarm) {
        let mut i = self.info.lock().unwrap_or_else(|e| e.into_inner());
        i.alarm_seq += 1;
        i.alarm_number = a.number;
        i.alarm_text = a.message.clone();
    }

    /// A copy of what was set outside the cycle.
    pub fn info(&self) -> RunInfo {
        self.info.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn a_record_round_trips_through_the_words() {
        let mut s =
            MachineSnap { cycle: 7, state: MachineState::Held, line: 123_456, blocks: 9, n_axes: 3, alarm: 2010, parts: 2, ..Default::default() };
        s.elapsed_s = 1.5;
        s.spindle_override = 1.2;
        s.spindle_load_pct = -12.5;
        s.axes[2] = AxisSnap { cmd: -3.25, act: -3.5, ferr: 0.001, statusword: 0x1237 };
        assert_eq!(MachineSnap::from_words(&s.to_words()), s);
    }

    /// A reader racing a writer never sees a torn record: every field of a record it reads
    /// comes from the same publish.
    #[test]
    fn readers_never_see_a_torn_record() {
        let snap = Arc::new(Snapshot::new());
        let w = snap.clone();
        let writer = std::thread::spawn(move || {
            for k in 1..=200_000u64 {
                let mut s = MachineSnap { cycle: k, blocks: k, parts: k, n_axes: 8, ..Default::default() };
                for a in s.axes.iter_mut() {
                    *a = AxisSnap { cmd: k as f64, act: k as f64, ferr: k as f64, statusword: k as u16 };
                }
                w.publish(&s);
            }
        });
        let mut last = 0;
        while last < 200_000 {
            let s = snap.read();
            assert!(s.blocks == s.cycle && s.parts == s.cycle, "{s:?}");
            assert!(s.axes.iter().all(|a| a.cmd == s.cycle as f64 && a.act == a.cmd && a.ferr == a.cmd && a.statusword == s.cycle as u16), "{s:?}");
            assert!(s.cycle >= last, "went back from {last} to {}", s.cycle);
            last = s.cycle;
            if writer.is_finished() && last < 200_000 {
                last = snap.read().cycle;
                assert_eq!(last, 200_000);
            }
        }
        writer.join().unwrap();
    }
}
