//! `cncgw identify` (issue 17.2) on the emulated drives of `tests/drive_models/`: the delay it
//! finds moves by exactly the transport delay a model adds, and the velocity lag it predicts
//! matches the lag measured in a separate run at constant speed within 10 %.

use std::path::PathBuf;

fn model(name: &str) -> String {
    format!("{}/tests/drive_models/{name}.toml", env!("CARGO_MANIFEST_DIR"))
}

fn cncgw(args: &[&str]) -> std::process::Output {
    testkit::cli!().output(args)
}

fn identify(axis: &str, m: &str) -> serde_json::Value {
    let o = cncgw(&["identify", axis, "--json", "--sim-config", &model(m)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// The lag of Z's actual behind its command in the middle of a 60 mm move at F1500, ms.
fn measured_lag_ms(m: &str) -> f64 {
    let dir = std::env::temp_dir().join(format!("cncgw-identify-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let prog = dir.join("lag.nc");
    std::fs::write(&prog, "G21\nG98\nG1 W-60 F1500\nM30\n").unwrap();
    let trace: PathBuf = dir.join(format!("{m}.csv"));
    let o = cncgw(&["run", "--batch", "--sim-config", &model(m), "--trace", trace.to_str().unwrap(), prog.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&trace).unwrap();
    let head: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    let (c, a) = (head.iter().position(|h| *h == "z_cmd").unwrap(), head.iter().position(|h| *h == "z_act").unwrap());
    let rows: Vec<Vec<f64>> = text.lines().skip(1).map(|l| l.split(',').map(|x| x.parse().unwrap_or(0.0)).collect()).collect();
    let mid = rows.len() / 2;
    let v = 1500.0 / 60.0;
    (rows[mid][c] - rows[mid][a]).abs() / v * 1e3
}

#[test]
fn identify_finds_the_delay_and_the_velocity_lag() {
    let base = identify("z", "default");
    for (m, extra) in [("delay1", 1.0), ("delay2", 2.0)] {
        let r = identify("z", m);
        let d = r["delay_cycles"].as_f64().unwrap() - base["delay_cycles"].as_f64().unwrap();
        assert!((d - extra).abs() < 0.15, "{m}: delay {} vs default {}", r["delay_cycles"], base["delay_cycles"]);
    }
    for m in ["default", "lowff_z", "belt_z", "delay2"] {
        let r = identify("z", m);
        let lag = r["velocity_lag_ms"].as_f64().unwrap();
        let meas = measured_lag_ms(m);
        eprintln!("{m}: identified velocity lag {lag:.2} ms, measured {meas:.2} ms, {r}");
        assert!((lag / meas - 1.0).abs() < 0.1, "{m}: identified {lag:.2} ms, measured {meas:.2} ms");
        assert!(r["vaf_pct"].as_f64().unwrap() > 99.0, "{r}");
    }
}
