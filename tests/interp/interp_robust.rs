//! The interpreter never panics on any input, and streams long programs.

use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;
use proptest::prelude::*;

fn drain(src: &str, limit: usize) -> usize {
    let cfg = MachineConfig::embedded();
    match Interpreter::from_source("fuzz.nc", src, &cfg) {
        Err(e) => {
            assert!(!e.is_empty());
            for a in &e {
                assert!(a.pos.is_some(), "static errors carry a position: {a}");
            }
            0
        }
        Ok(it) => it.take(limit).take_while(|m| m.is_ok()).count(),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, .. ProptestConfig::default() })]

    #[test]
    fn arbitrary_text_never_panics(s in "\\PC{0,200}") {
        drain(&s, 200);
    }

    #[test]
    fn gcode_like_text_never_panics(
        lines in proptest::collection::vec(
            "(N[0-9]{1,3} )?([GMXZUWIKRFSPQTABLC,#\\[\\]=+*/.0-9 -]|IF|GOTO|WHILE|DO|END|EQ|SIN){0,14}",
            0..12,
        )
    ) {
        drain(&lines.join("\n"), 500);
    }
}

/// A long program runs block by block: the interpreter keeps only the text and a line index.
/// (Measured: `cargo test -j2 --test interp_robust -- --ignored --nocapture`.)
#[test]
#[ignore = "slow in debug builds; run explicitly to measure"]
fn million_blocks_stream() {
    let n = 1_000_000;
    let mut src = String::with_capacity(n * 24);
    src.push_str("G99 G00 X100 Z5\nM03 S1000\n");
    for i in 0..n {
        let z = -((i % 300) as f64) * 0.1;
        src.push_str(&format!("N{} G01 X{:.1} Z{:.1} F0.2\n", i % 99999 + 1, 60.0 + (i % 7) as f64, z));
    }
    src.push_str("M30\n");
    let t = std::time::Instant::now();
    let it = Interpreter::from_source("big.nc", &src, &MachineConfig::embedded()).expect("valid");
    let checked = t.elapsed();
    let moves = it.inspect(|m| assert!(m.is_ok(), "runs: {m:?}")).count();
    println!("{n} blocks: static check {:?}, total with execution {:?}, {moves} moves", checked, t.elapsed());
    assert_eq!(moves, n + 3);
}

/// Inputs that once made `cargo fuzz` (scripts/fuzz.sh) crash; each must now run without a
/// panic. The directory may be empty.
#[test]
fn fuzz_regression_cases() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interp_fuzz_cases");
    let Ok(entries) = std::fs::read_dir(&dir) else { return };
    let mut s = sim_drives::report::Scenario::new("interp_robust/fuzz_regression_cases");
    let mut panicked = Vec::new();
    for e in entries.flatten() {
        let bytes = std::fs::read(e.path()).expect("readable case");
        s.faults_injected += 1;
        if std::panic::catch_unwind(|| drain(&String::from_utf8_lossy(&bytes), 2_000)).is_err() {
            panicked.push(e.path().display().to_string());
        }
    }
    s.panics = panicked.len() as u64;
    s.record();
    assert!(panicked.is_empty(), "panicked: {panicked:?}");
}

/// The fuzz seed corpus (fuzz/corpus/interp/*.nc) are valid programs that run to M30.
#[test]
fn fuzz_seeds_run_to_the_end() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/interp");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).expect("fuzz/corpus/interp exists").flatten() {
        if e.path().extension().is_some_and(|x| x == "nc") {
            let text = std::fs::read_to_string(e.path()).expect("text");
            let it = Interpreter::with_program_dir("seed.nc", &text, &MachineConfig::embedded(), Some(&dir))
                .unwrap_or_else(|a| panic!("{}: {a:?}", e.path().display()));
            let last = it.map(|m| m.unwrap_or_else(|a| panic!("{}: {a}", e.path().display()))).last();
            assert!(matches!(last.map(|m| m.kind), Some(cncgw::canon::MoveKind::End { .. })), "{}", e.path().display());
            n += 1;
        }
    }
    assert!(n >= 3, "seed corpus has {n} programs");
}

#[test]
fn hundred_thousand_blocks_stream() {
    let n = 100_000;
    let mut src = String::from("G98 G01 F1000\n");
    for i in 0..n {
        src.push_str(&format!("X{} Z-{}\n", 10 + i % 50, i % 100));
    }
    src.push_str("M30\n");
    let it = Interpreter::from_source("big.nc", &src, &MachineConfig::embedded()).expect("valid");
    assert_eq!(it.inspect(|m| assert!(m.is_ok(), "runs: {m:?}")).count(), n + 1);
}

#[test]
fn endless_loop_limit_is_adjustable() {
    let mut it = Interpreter::from_source("loop.nc", "N1 #1=#1+1\nGOTO 1\n", &MachineConfig::embedded()).expect("valid");
    it.set_endless_loop_limit(1000);
    let a = it.next_move().expect_err("endless loop alarm");
    assert_eq!(a.number, cncgw::interp::ENDLESS_LOOP_ALARM);
    assert!(a.message.contains("1000 blocks"), "{a}");
}
