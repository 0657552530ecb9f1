//! Every fuzz corpus input and every kept crash input, replayed through the same entry
//! functions the cargo-fuzz targets call (fuzz/src/lib.rs, included here), on the stable
//! toolchain in the normal test suite. An input that once crashed stays fixed.
//!
//! Corpora: fuzz/corpus/TARGET/ (seeds and what fuzzing found, minimized); crash inputs:
//! fuzz/crashes/TARGET/ (scripts/fuzz.sh copies them there).

#[path = "../../fuzz/src/lib.rs"]
#[allow(dead_code)]
mod entries;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

fn inputs(target: &str) -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut v = Vec::new();
    for dir in [root.join("corpus").join(target), root.join("crashes").join(target)] {
        if let Ok(rd) = std::fs::read_dir(&dir) {
            v.extend(rd.flatten().map(|e| e.path()).filter(|p| p.is_file()));
        }
    }
    v.sort();
    v
}

/// Replays one target's inputs; returns how many there were. Panics name every input that
/// panicked.
fn replay(target: &str) -> usize {
    let (_, entry) = *entries::TARGETS.iter().find(|t| t.0 == target).expect("target exists");
    let files = inputs(target);
    let crashes = files.iter().filter(|f| f.parent().is_some_and(|d| d.ends_with(Path::new("crashes").join(target)))).count();
    let mut failed = Vec::new();
    for f in &files {
        let data = std::fs::read(f).expect("readable input");
        if catch_unwind(AssertUnwindSafe(|| entry(&data))).is_err() {
            failed.push(f.display().to_string());
        }
    }
    let mut s = sim_drives::report::Scenario::new(format!("fuzz_regress/{target}"));
    // The inputs that once crashed are the injected faults; the corpus is ordinary input.
    s.faults_injected = crashes as u64;
    s.panics = failed.len() as u64;
    s.record();
    assert!(failed.is_empty(), "{target}: {} input(s) panicked:\n{}", failed.len(), failed.join("\n"));
    files.len()
}

#[test]
fn interp_corpus() {
    assert!(replay("interp") >= 3, "the interp corpus holds the example programs");
}

#[test]
fn config_corpus() {
    assert!(replay("config") >= 2, "the config corpus holds config/*.toml");
}

#[test]
fn eds_corpus() {
    assert!(replay("eds") >= 1, "the eds corpus holds tests/python/sim_drive.eds");
}

#[test]
fn frames_corpus() {
    assert!(replay("frames") >= 1);
}

/// Every fuzz target has a test here and a corpus (a new target must not go unreplayed).
#[test]
fn every_target_is_replayed() {
    let names: Vec<&str> = entries::TARGETS.iter().map(|t| t.0).collect();
    assert_eq!(names, ["interp", "config", "eds", "frames"]);
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/fuzz_targets");
    for e in std::fs::read_dir(dir).expect("fuzz/fuzz_targets").flatten() {
        let stem = e.path().file_stem().unwrap().to_string_lossy().into_owned();
        assert!(names.contains(&stem.as_str()), "fuzz target {stem} has no entry in fuzz/src/lib.rs TARGETS");
    }
}

/// The example programs run to the end with the fuzz target's bounds (the bound must not
/// cut a real program short of its first moves).
#[test]
fn example_programs_produce_moves_within_the_bounds() {
    for f in ["examples/first_part.nc", "examples/macro_grooves.nc"] {
        let data = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join(f)).unwrap();
        assert!(entries::interp_moves(&data) > 10, "{f}");
    }
    // An endless macro loop without motion ends at the block bound, not never.
    assert_eq!(entries::interp_moves(b"N1 #1=#1+1\nGOTO 1\n"), 0);
    // WHILE with motion ends at the move bound.
    assert_eq!(entries::interp_moves(b"G98 G01 F1000\nWHILE [1 EQ 1] DO 1\nU1\nU-1\nEND 1\nM30\n"), entries::MAX_MOVES);
}
