//! The reliability report: every fault-injection scenario of the test suite appends one line
//! to `$CNCGW_REPORT_DIR/reliability.jsonl` (nothing is written when the variable is unset),
//! and `scripts/test.sh` prints the totals at the end (scenarios run, faults injected, stops
//! within bound, data lost, panics, fuzz executions per target).
//!
//! One writer for every test binary, so that the figures are counted the same way everywhere.

use std::io::Write;

/// The outcome of one scenario.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scenario {
    /// Short unique name, e.g. `fault_matrix/emcy_during_tap`.
    pub name: String,
    /// Faults injected (a lost frame, an EMCY, a killed process… each counts one).
    pub faults_injected: u64,
    /// Cycles from the fault to every axis at rest, when the scenario stops the machine.
    pub stop_cycles: Option<u64>,
    /// The bound the test asserts for `stop_cycles`.
    pub bound_cycles: Option<u64>,
    /// Items of persistent state lost or torn (must be 0).
    pub data_lost: u64,
    /// Panics seen (in-process or a child's exit code 101; must be 0).
    pub panics: u64,
}

impl Scenario {
    pub fn new(name: impl Into<String>) -> Self {
        Scenario { name: name.into(), ..Default::default() }
    }

    /// True when the stop (if any) came within its bound.
    pub fn within_bound(&self) -> bool {
        match (self.stop_cycles, self.bound_cycles) {
            (Some(s), Some(b)) => s <= b,
            _ => true,
        }
    }

    /// The JSON line (hand-formatted: names are plain ASCII test names).
    pub fn to_json(&self) -> String {
        let opt = |v: Option<u64>| v.map_or("null".to_string(), |v| v.to_string());
        format!(
            "{{\"scenario\":\"{}\",\"faults_injected\":{},\"stop_cycles\":{},\"bound_cycles\":{},\"within_bound\":{},\"data_lost\":{},\"panics\":{}}}",
            self.name.replace(['"', '\\'], "_"),
            self.faults_injected,
            opt(self.stop_cycles),
            opt(self.bound_cycles),
            self.within_bound(),
            self.data_lost,
            self.panics
        )
    }

    /// Append the line to the report, if `CNCGW_REPORT_DIR` is set. A failure to write is
    /// printed, not fatal: the report is a summary, the test's assertions are the verdict.
    pub fn record(&self) {
        let Some(dir) = std::env::var_os("CNCGW_REPORT_DIR") else { return };
        let dir = std::path::PathBuf::from(dir);
        let res = std::fs::create_dir_all(&dir).and_then(|_| {
            let mut f = std::fs::OpenOptions::new().create(true).append(true).open(dir.join("reliability.jsonl"))?;
            // One write per line: lines from parallel test processes do not interleave.
            f.write_all(format!("{}\n", self.to_json()).as_bytes())
        });
        if let Err(e) = res {
            eprintln!("reliability report: cannot write to {}: {e}", dir.display());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_line_and_bound() {
        let mut s = Scenario::new("fault_matrix/x\"y");
        s.faults_injected = 2;
        s.stop_cycles = Some(12);
        s.bound_cycles = Some(10);
        assert!(!s.within_bound());
        assert_eq!(
            s.to_json(),
            "{\"scenario\":\"fault_matrix/x_y\",\"faults_injected\":2,\"stop_cycles\":12,\"bound_cycles\":10,\"within_bound\":false,\"data_lost\":0,\"panics\":0}"
        );
        s.stop_cycles = Some(10);
        assert!(s.within_bound());
    }
}
