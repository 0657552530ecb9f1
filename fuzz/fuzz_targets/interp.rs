//! Arbitrary bytes as a part program: parsing, the static check and up to 1,000 moves of
//! execution must never panic (alarms are fine).
#![no_main]

use cncgw::config::MachineConfig;
use cncgw::interp::{parse_tool_table, Interpreter, ToolTable};
use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;

const MAX_MOVES: usize = 1_000;

fn cfg() -> &'static MachineConfig {
    static CFG: OnceLock<MachineConfig> = OnceLock::new();
    CFG.get_or_init(|| {
        // Reference points 2–4 configured so that G30 P2–P4 run, not only alarm.
        let text = format!(
            "{}\n1241 = {{ x = 200.0, z = 50.0 }}\n1242 = {{ x = 100.0, z = 0.0 }}\n1243 = {{ x = 0.0, z = -10.0 }}\n",
            cncgw::config::EMBEDDED_LATHE
        );
        MachineConfig::from_toml("fuzz.toml", &text).expect("fuzz config is valid")
    })
}

fn tools() -> &'static ToolTable {
    static T: OnceLock<ToolTable> = OnceLock::new();
    T.get_or_init(|| {
        parse_tool_table("tools.toml", "[1]\nx = -10.0\nz = 5.0\nr = 0.4\ntip = 3\n[2]\nx = 2.0\nz = -1.0")
            .expect("fuzz tool table is valid")
    })
}

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let Ok(mut it) = Interpreter::from_source("fuzz.nc", &text, cfg()) else { return };
    // A GOTO loop without motion would otherwise run 2,000,000 blocks before its alarm.
    it.set_endless_loop_limit(20_000);
    it.set_tool_table(tools().clone());
    // Alternate the M91/M92 input so both branches are explored.
    let mut flip = false;
    it.set_input_source(move |_| {
        flip = !flip;
        flip
    });
    for m in it.take(MAX_MOVES) {
        if m.is_err() {
            break;
        }
    }
});
