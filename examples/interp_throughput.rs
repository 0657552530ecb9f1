//! The interpreter alone, from file bytes to canonical moves (no output): the CPU-bound
//! figure of `scripts/bench-rs274.sh`, next to `cncgw plan --format jsonl > /dev/null`.
//!
//! Run: `cargo run --release --example interp_throughput -- PROGRAM` → moves, seconds and
//! blocks (lines) per second on stderr.

use cncgw::config::MachineConfig;
use cncgw::interp::Interpreter;

fn main() {
    let Some(path) = std::env::args_os().nth(1) else {
        eprintln!("usage: interp_throughput PROGRAM");
        std::process::exit(2);
    };
    let path = std::path::PathBuf::from(path);
    let t = std::time::Instant::now();
    let it = match Interpreter::from_file(&path, &MachineConfig::embedded()) {
        Ok(it) => it,
        Err(alarms) => {
            for a in alarms {
                eprintln!("{a}");
            }
            std::process::exit(2);
        }
    };
    let checked = t.elapsed();
    let mut moves = 0u64;
    let mut last_line = 0u32;
    for m in it {
        match m {
            Ok(m) => {
                moves += 1;
                last_line = last_line.max(m.src.line);
            }
            Err(a) => {
                eprintln!("{a}");
                std::process::exit(2);
            }
        }
    }
    let s = t.elapsed().as_secs_f64();
    eprintln!("{moves} moves from {last_line} lines in {s:.3} s (static check {:.3} s): {:.0} blocks/s", checked.as_secs_f64(), last_line as f64 / s);
}
