//! cargo-fuzz target `config`: see `cncgw_fuzz::config` (fuzz/src/lib.rs), which
//! tests/interp/fuzz_regress.rs replays over the corpus in the normal test suite.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| cncgw_fuzz::config(data));
