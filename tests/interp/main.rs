//! The interpreter and the canned cycles, without drives: program text → canonical moves
//! (`cncgw plan`), bad input refused, the fuzz corpus replayed. One test binary for the folder
//! (one link of the crate instead of one per file); each file is a module, its tests are
//! `FILE::test_name` (`cargo nextest run --test interp cycles_threads::`).

mod cycles_common;

mod before_motion;
mod cycles_drill;
mod cycles_groove;
mod cycles_rigid;
mod cycles_stock;
mod cycles_tap;
mod cycles_threads;
mod cycles_turning;
mod cycles_typeii;
mod fuzz_regress;
mod interp_bad_input;
mod interp_nosecomp;
mod interp_plan;
mod interp_polar;
mod interp_robust;
mod interp_stroke;
mod interp_tools;
