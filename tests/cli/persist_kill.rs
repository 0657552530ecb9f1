//! Power-off state is written atomically: a writer killed with SIGKILL at random instants,
//! again and again, always leaves the old or the new file — never a torn or empty one.

use std::collections::HashMap;
use std::process::Command;
use std::time::Duration;

const CHILD_ENV: &str = "CNCGW_PERSIST_KILL_CHILD";

/// Every generation writes all of #401–#600 with the generation number, so a torn or mixed
/// file shows up as a missing variable or two different values.
fn generation(n: u64) -> HashMap<u32, f64> {
    (401..=600).map(|v| (v, n as f64)).collect()
}

#[test]
fn writer_child() {
    // Only does something when started by the test below.
    let Some(path) = std::env::var_os(CHILD_ENV) else { return };
    let f = cncgw::persist::CommonVarsFile { path: path.into() };
    let mut n = f.load().ok().and_then(|v| v.get(&401).copied()).unwrap_or(0.0) as u64;
    loop {
        n += 1;
        f.save(&generation(n)).expect("save");
    }
}

#[test]
fn sigkill_mid_write_leaves_old_or_new_state() {
    let dir = std::env::temp_dir().join(format!("cncgw-kill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("m.common-vars.toml");
    let exe = std::env::current_exe().unwrap();
    let mut last = 0.0;
    let mut seed = 0x2545_F491_4F6C_DD1Du64;
    // Rounds that found the state torn, mixed or gone back (each one item of data lost).
    let mut lost: Vec<String> = Vec::new();
    let rounds = 25;
    for round in 0..rounds {
        let mut child = Command::new(&exe)
            .args(["--exact", "persist_kill::writer_child", "--nocapture", "--test-threads=1"])
            .env(CHILD_ENV, &path)
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap();
        // 20–80 ms: many writes in flight, the kill lands at a different point each time.
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        std::thread::sleep(Duration::from_millis(20 + seed % 60));
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        let f = cncgw::persist::CommonVarsFile { path: path.clone() };
        let v = match f.load() {
            Ok(v) => v,
            Err(a) => {
                lost.push(format!("round {round}: {a}"));
                continue;
            }
        };
        if v.is_empty() {
            // Killed before its first write completed: the file must then not exist at all.
            if path.exists() && last != 0.0 {
                lost.push(format!("round {round}: empty state after a completed write"));
            }
            continue;
        }
        if v.len() != 200 {
            lost.push(format!("round {round}: {} variables", v.len()));
            continue;
        }
        let g = v[&401];
        if !v.values().all(|x| *x == g) {
            lost.push(format!("round {round}: mixed generations"));
        } else if g < last {
            lost.push(format!("round {round}: went back from {last} to {g}"));
        }
        last = g.max(last);
    }
    let mut s = sim_drives::report::Scenario::new("persist_kill/sigkill_mid_write");
    s.faults_injected = rounds;
    s.data_lost = lost.len() as u64;
    s.record();
    assert!(lost.is_empty(), "{}", lost.join("\n"));
    assert!(last > 0.0, "the writer never completed a write");
    let _ = std::fs::remove_dir_all(&dir);
}
