//! `cncgw tap-test` as a service engineer runs it, against the embedded emulated machine
//! (default config, `inproc`, simulated time); and `--json` on the status commands, parsed.

use crate::svg_common;

use svg_common::{by_class, num, parse, texts};

use testkit::Out;

fn cncgw_in(dir: &std::path::Path, args: &[&str]) -> Out {
    testkit::cli!().dir(dir).run(args)
}

fn tmpdir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("cncgw_cli_taptest_{}_{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn json(o: &Out) -> serde_json::Value {
    serde_json::from_str(o.stdout.trim()).unwrap_or_else(|e| panic!("not JSON ({e}): {}\n{}", o.stdout, o.stderr))
}

#[test]
fn tap_test_measures_the_sync_error_and_draws_it() {
    let dir = tmpdir("run");
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "30", "--rpm", "3000", "--json", "-o", "tap.svg"]);
    assert_eq!(o.code, 0, "{}\n{}", o.stdout, o.stderr);
    let v = json(&o);
    // Planned from the embedded machine's position (X0 Z0): R 2 mm above, 30 mm down.
    assert_eq!(v["plan"]["r_z"], 2.0);
    assert_eq!(v["plan"]["bottom_z"], -28.0);
    assert_eq!(v["plan"]["signed_lead"], -1.5);
    assert!(v["plan"]["program"].as_str().unwrap().contains("M29 S3000\nG84 X0.0000 Z-28.0000 F1.5"));
    let se = &v["sync_error"];
    let max = se["max_um"].as_f64().unwrap();
    let rms = se["rms_um"].as_f64().unwrap();
    // The emulated drives track within a few µm (sync correction on); not zero either.
    assert!(max > 0.1 && max < 20.0 && rms > 0.0 && rms <= max, "{se}");
    for phase in ["entry", "reversal", "exit"] {
        let p = &se[phase];
        let pm = p["max_um"].as_f64().unwrap();
        assert!(pm <= max + 1e-9 && p["cycles"].as_u64().unwrap() > 10, "{phase}: {p}");
    }
    // 2 × 30 mm at up to 75 mm/s plus the ramps: several hundred 2 ms cycles.
    assert!(se["cycles"].as_u64().unwrap() > 500, "{se}");
    let sf = v["following_error"]["spindle_deg"].as_f64().unwrap();
    let zf = v["following_error"]["z_um"].as_f64().unwrap();
    assert!(sf > 0.0 && sf < 30.0 && zf > 0.0 && zf < 1000.0, "{}", v["following_error"]);
    // The depth is too short for S3000 on this spindle's ramp: the peak is reported as measured.
    let peak = v["peak_rpm"].as_f64().unwrap();
    assert!(peak > 1500.0 && peak <= 3050.0, "{peak}");
    assert_eq!(v["within_limit"], true);
    // The controller's own monitor sees the same error as the figure from the trace.
    assert!((v["monitor_max_um"].as_f64().unwrap() - max).abs() < 0.5 * max + 1.0, "{v}");

    // Recompute the figure from the CSV the command kept: (Z − 2) + 1.5·(θ − θ_R)/360, in µm,
    // over the cycles of the G84 block (line 6) from the first spindle motion on.
    let csv = std::fs::read_to_string(dir.join("tap.csv")).unwrap();
    let mut rows = csv.lines();
    let head: Vec<&str> = rows.next().unwrap().split(',').collect();
    let c = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let (cl, cs, csa, cza) = (c("line"), c("s1_cmd"), c("s1_act"), c("z_act"));
    let rows: Vec<Vec<f64>> = rows.map(|r| r.split(',').map(|x| x.parse().unwrap()).collect()).collect();
    let first = rows.iter().position(|r| r[cl] == 6.0).unwrap();
    let th0 = rows[first - 1][cs];
    let mut worst = 0.0f64;
    for r in rows.iter().filter(|r| r[cl] == 6.0).skip_while(|r| r[cs] == th0) {
        worst = worst.max((((r[cza] - 2.0) + 1.5 * (r[csa] - th0) / 360.0) * 1000.0).abs());
    }
    assert!((worst - max).abs() < 1e-6, "CSV {worst} vs reported {max}");
    let svg = std::fs::read_to_string(dir.join("tap.svg")).unwrap();
    let limit = v["sync_error_limit_um"].as_f64().unwrap();
    let doc = parse(&svg);
    check_picture(&doc, "PASS", limit, se);
    svg_common::renders(&dir.join("tap.svg"));
    // The same trace against a 0.3 µm limit: FAIL, and the band where it was exceeded.
    let data = cncgw::control::trace::TraceData::parse(&csv).unwrap();
    let s = cncgw::cli::taptest::series(&data, "s1", -1.5, &[6]).unwrap();
    let f = cncgw::cli::taptest::figures(&data, "s1", -1.5, &[6]).unwrap();
    assert_eq!(f.sync.max, max, "the picture's series is the figures' series");
    let svg = cncgw::cli::taptest::picture(&data, &s, &f, "t", 0.3, cncgw::cli::taptest::Verdict::Fail).unwrap();
    let doc = parse(&svg);
    check_picture(&doc, "FAIL", 0.3, se);
    let band = &by_class(&doc, "band")[0];
    let panel = band.parent().unwrap();
    // The error goes outside the band: the panel's scale runs past ±0.3 µm on both sides.
    assert!(num(&panel, "data-hi") > 0.3 + 0.2 && num(&panel, "data-lo") < -0.3 - 0.2, "{:?}", panel.attributes().collect::<Vec<_>>());

    // The table for a person says the same.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "30", "--rpm", "3000"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    for w in ["whole tap", "entry", "reversal", "exit", "following error: spindle", "PASS", "tap-test.svg"] {
        assert!(o.stdout.contains(w), "{w}: {}", o.stdout);
    }
}

/// The tap-test picture: the verdict, the limit band at ±limit in the first panel (its scale
/// covering the band), the three phases in order and named with the figures' maxima, and a
/// legend right of every panel's data.
fn check_picture(doc: &roxmltree::Document, verdict: &str, limit: f64, se: &serde_json::Value) {
    assert_eq!(texts(doc, "verdict"), [verdict]);
    let detail = texts(doc, "verdict-detail").join("");
    assert!(detail.contains(&format!("max {:.2} µm", se["max_um"].as_f64().unwrap())) && detail.contains(&format!("limit {limit} µm")), "{detail}");
    let panels = by_class(doc, "panel");
    assert_eq!(panels.len(), 4);
    let bands = by_class(doc, "band");
    assert_eq!(bands.len(), 1);
    assert_eq!((num(&bands[0], "data-lo"), num(&bands[0], "data-hi")), (-limit, limit));
    assert_eq!(bands[0].parent(), Some(panels[0]));
    assert!(num(&panels[0], "data-lo") < -limit && num(&panels[0], "data-hi") > limit);
    assert!(texts(doc, "legend").contains(&format!("limit ±{limit} µm")));
    // Phases: entry, reversal, exit in time order, shaded in the three lower panels, named once.
    let spans: Vec<_> = by_class(doc, "span").into_iter().filter(|n| n.parent() == Some(panels[1])).collect();
    let names: Vec<&str> = spans.iter().map(|n| n.attribute("data-name").unwrap()).collect();
    assert_eq!(names.len(), 3, "{names:?}");
    for ((n, phase), sp) in names.iter().zip(["entry", "reversal", "exit"]).zip(&spans) {
        assert_eq!(*n, format!("{phase}: max {:.2} µm", se[phase]["max_um"].as_f64().unwrap()));
        assert!(num(sp, "data-t0") < num(sp, "data-t1"), "{n}");
    }
    assert!(num(&spans[0], "data-t1") <= num(&spans[1], "data-t0") && num(&spans[1], "data-t1") <= num(&spans[2], "data-t0"));
    assert_eq!(by_class(doc, "span").len(), 9, "phases shaded in the detail, speed and Z panels");
    for n in names {
        assert_eq!(texts(doc, "legend").iter().filter(|l| *l == n).count(), 1, "{n} named once in the legends");
    }
    for p in &panels {
        let (_, right) = svg_common::frame_x(p);
        for l in p.descendants().filter(|n| n.attribute("class") == Some("legend")) {
            assert!(num(&l, "x") > right, "legend {:?} over the data", l.text());
        }
    }
}

#[test]
fn tap_test_stopped_by_the_sync_monitor_says_so_in_the_picture() {
    let dir = tmpdir("stopped");
    // A 1 µm limit (the least the config takes) with the friction feed-forward off (about
    // 2 µm then): the controller's monitor (alarm 2307) stops the tap on the way in.
    let cfg = cncgw::config::EMBEDDED_LATHE
        .replace("[machine]", "[machine]\nsync_error_limit_um = 1")
        .replace("friction_compensation = true", "friction_compensation = false");
    std::fs::write(dir.join("tight.toml"), cfg).unwrap();
    let o = cncgw_in(&dir, &["tap-test", "--config", "tight.toml", "--lead", "1.5", "--depth", "30", "--rpm", "3000", "-o", "t.svg"]);
    assert_eq!(o.code, 3, "{}\n{}", o.stdout, o.stderr);
    assert!(o.stderr.contains("2307") && o.stdout.contains("STOPPED BY AN ALARM"), "{}\n{}", o.stdout, o.stderr);
    let svg = std::fs::read_to_string(dir.join("t.svg")).unwrap();
    let doc = parse(&svg);
    assert_eq!(texts(&doc, "verdict"), ["STOPPED BY AN ALARM"]);
    assert!(texts(&doc, "verdict-detail").join("").contains("no reversal, no exit"));
    // Only the phase the tap reached.
    let names: Vec<String> = by_class(&doc, "span").iter().map(|n| n.attribute("data-name").unwrap().to_string()).collect();
    assert!(!names.is_empty() && names.iter().all(|n| n.starts_with("entry")), "{names:?}");
    let band = &by_class(&doc, "band")[0];
    assert_eq!((num(band, "data-lo"), num(band, "data-hi")), (-1.0, 1.0));
}

#[test]
fn tap_test_dry_moves_nothing_and_refuses_the_impossible() {
    let dir = tmpdir("dry");
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "30", "--rpm", "3000", "--dry", "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    assert_eq!(v["dry"], true);
    assert_eq!(v["feasible"], true);
    assert_eq!(v["plan"]["feed_mm_min"], 4500.0);
    assert!(!dir.join("tap-test.csv").exists() && !dir.join("tap-test.svg").exists(), "a dry run wrote a trace");
    assert!(!o.stderr.contains("cycles written"), "{}", o.stderr);
    // Deeper than Z's travel (min -400) allows from Z0.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "450", "--rpm", "1000", "--dry"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("below Z's travel -400") && o.stderr.contains("--depth at most 402"), "{}", o.stderr);
    // Faster than the spindle: refused before anything is opened, with or without --dry.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1", "--depth", "10", "--rpm", "9000"]);
    assert_eq!(o.code, 2);
    assert!(o.stderr.contains("max_speed 6000 rpm"), "{}", o.stderr);
    // Z feed over Z's max speed.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "3", "--depth", "10", "--rpm", "5000", "--json", "--dry"]);
    assert_eq!(o.code, 2, "{}", o.stdout);
}

#[test]
fn tap_test_on_a_real_bus_needs_yes() {
    let dir = tmpdir("yes");
    // No terminal here: refused before the (absent) bus is opened.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "30", "--rpm", "3000", "--bus", "nosuchcan0"]);
    assert_eq!(o.code, 2, "{}", o.stderr);
    assert!(o.stderr.contains("can set a motor in motion on nosuchcan0") && o.stderr.contains("--yes"), "{}", o.stderr);
    // With --yes it gets as far as the bus.
    let o = cncgw_in(&dir, &["tap-test", "--lead", "1.5", "--depth", "30", "--rpm", "3000", "--bus", "nosuchcan0", "--yes"]);
    assert_eq!(o.code, 4, "{}", o.stderr);
}

#[test]
fn status_commands_speak_json() {
    let dir = tmpdir("json");
    // config check
    let o = cncgw_in(&dir, &["config", "check", "--json"]);
    assert_eq!(o.code, 0);
    let v = json(&o);
    assert_eq!(v["ok"], true);
    assert_eq!(v["cycle_ms"], 2.0);
    assert_eq!(v["axes"].as_array().unwrap().len(), 3);
    let load = v["canopen_bus_load"].as_f64().unwrap();
    assert!(load > 0.1 && load < 0.8, "{load}");
    std::fs::write(dir.join("bad.toml"), "[machine]\ncycle_ms = -1\n").unwrap();
    let o = cncgw_in(&dir, &["config", "check", "bad.toml", "--json"]);
    assert_eq!(o.code, 1, "exit 1: run would refuse it");
    let v = json(&o);
    assert_eq!(v["ok"], false);
    assert!(v["error"].as_str().unwrap().contains("bad.toml"), "{v}");
    // monitor --once
    let o = cncgw_in(&dir, &["monitor", "--once", "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    let drives = v["drives"].as_array().unwrap();
    assert_eq!(drives.len(), 3);
    for d in drives {
        assert_eq!(d["state"], "Switch On Disabled", "{d}");
        assert_eq!(d["position"], 0.0);
        assert!(d["error"].is_null());
    }
    assert!(v["bus_load"].as_f64().unwrap() > 0.0);
    // monitor over a while: one JSON object per refresh.
    let o = cncgw_in(&dir, &["monitor", "--seconds", "1.2", "--interval-ms", "500", "--json"]);
    assert_eq!(o.code, 0);
    let ts: Vec<f64> = o.stdout.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["t_s"].as_f64().unwrap()).collect();
    assert_eq!(ts.len(), 3, "{}", o.stdout);
    assert!(ts.windows(2).all(|w| (w[1] - w[0] - 0.5).abs() < 0.05), "{ts:?}");
    // od check
    let eds = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds");
    let o = cncgw_in(&dir, &["od", "check", "1", "--eds", eds, "--json"]);
    assert_eq!(o.code, 0, "{}", o.stdout);
    let v = json(&o);
    assert_eq!(v["agrees"], true);
    assert!(v["objects"].as_u64().unwrap() > 10);
    // scan, drive status, nmt already had it; still JSON.
    for args in [&["scan", "--json"][..], &["drive", "status", "2", "--json"], &["nmt", "preop", "all", "--json"]] {
        let o = cncgw_in(&dir, args);
        assert_eq!(o.code, 0, "{args:?}: {}", o.stderr);
        json(&o);
    }
}

#[test]
fn od_dump_shows_the_dictionary_and_checks_it_against_the_eds() {
    let dir = tmpdir("od");
    let o = cncgw_in(&dir, &["od", "dump", "1", "--json"]);
    assert_eq!(o.code, 0, "{}", o.stderr);
    let v = json(&o);
    let objs = v["objects"].as_array().unwrap();
    let find = |i: &str, sub: u64| objs.iter().find(|x| x["index"] == i && x["sub"] == sub).unwrap_or_else(|| panic!("{i}:{sub}"));
    assert_eq!(find("0x6041", 0)["value"], 0x0250);
    assert_eq!(find("0x1008", 0)["value"], "SIM-SERVO X");
    assert_eq!(find("0x1018", 1)["raw"], "A7 0C 00 00");
    assert_eq!(v["disagreements"], 0);
    // Against the EDS: every object, by its DataType.
    let eds = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/sim_drive.eds");
    let o = cncgw_in(&dir, &["od", "dump", "1", "--eds", eds]);
    assert_eq!(o.code, 0, "{}", o.stdout);
    assert!(o.stdout.contains("0x6041:00 Statusword") && o.stdout.contains("agrees with the EDS"), "{}", o.stdout);
    // An EDS that says the statusword is UNSIGNED32: the disagreement is named.
    let text = std::fs::read_to_string(eds).unwrap().replace(
        "[6041]\nParameterName=Statusword\nObjectType=0x7\nDataType=0x0006",
        "[6041]\nParameterName=Statusword\nObjectType=0x7\nDataType=0x0007",
    );
    std::fs::write(dir.join("wrong.eds"), text).unwrap();
    let o = cncgw_in(&dir, &["od", "dump", "1", "--eds", "wrong.eds", "--json"]);
    assert_eq!(o.code, 1, "{}", o.stdout);
    let v = json(&o);
    assert_eq!(v["disagreements"], 1);
    let sw = v["objects"].as_array().unwrap().iter().find(|x| x["index"] == "0x6041").unwrap().clone();
    assert!(sw["problem"].as_str().unwrap().contains("answered 2 byte(s)"), "{sw}");
}
