//! Random drive models of the kinds issue 17 lists, for the drive matrix beyond the models the
//! sync law was developed on: the sim-drives configurations are written to a directory, and
//! `drive_matrix` measures them.
//!
//! Run: `cargo run --release --example random_drive_models -- --seed 20261201 --count 48
//! --out /tmp/rnd && cargo run --release --example drive_matrix -- --air /tmp/rnd/*.toml`.
//!
//! Kinds, in turn (ranges around the listed models of `tests/drive_models/`): a soft spindle
//! (Kv 8–16/s, feed-forward 95–99.5 %, load 0.03–0.1 kg·m², friction 1–5 N·m), a heavy one
//! (load 0.06–0.15 kg·m² on 70–160 N·m), a coarse spindle encoder (4096, 8192 or 16384 counts,
//! load 0.03–0.08), a low-feed-forward Z (Kv 25–60/s, 90–98 %), a belt-driven Z (Kv 20–50/s,
//! 93–99 %, stiffness 3–20 N·m/rad, damping 0.002–0.03, lost motion 0–0.4°), one or two cycles
//! of transport delay on every drive, high friction (spindle 2–6 N·m, X and Z 0.3–0.8 N·m), and
//! a mix of two of them. Everything else is sim-drives' default. The same seed writes the same
//! models.
//!
//! `--loops`: each model's spindle, Z or both also get other inner loops than sim-drives' —
//! velocity loop gain 0.35–1.6× and integral time 0.6–4× the default, speed filter 1–5× and
//! current loop 1–4× as slow (sim-drives' defaults: spindle Kp 12.57 N·m·s/rad, Ti 20 ms,
//! 0.5 ms, 0.4 ms; feed axes 0.377, 5 ms, 0.2 ms, 0.15 ms): the "other gains" of drives we did
//! not write.

use std::fmt::Write as _;
use std::path::PathBuf;

/// splitmix64: a small, well-mixed generator (the models need no more).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [a, b), rounded to `places` decimals.
    fn uniform(&mut self, a: f64, b: f64, places: i32) -> f64 {
        let u = (self.next() >> 11) as f64 / (1u64 << 53) as f64;
        let p = 10f64.powi(places);
        ((a + (b - a) * u) * p).round() / p
    }
    fn pick<T: Copy>(&mut self, xs: &[T]) -> T {
        xs[(self.next() % xs.len() as u64) as usize]
    }
}

/// The `[drive.physics]` keys of spindle, X and Z.
#[derive(Default)]
struct Model {
    s1: Vec<(&'static str, f64)>,
    x: Vec<(&'static str, f64)>,
    z: Vec<(&'static str, f64)>,
}

const KINDS: [&str; 8] = ["soft", "heavy", "coarse", "lowff", "belt", "delay", "friction", "mix"];

fn add(m: &mut Model, kind: &str, r: &mut Rng) {
    match kind {
        "soft" => m.s1.extend([
            ("kv", r.uniform(8.0, 16.0, 1)),
            ("velocity_ff", r.uniform(0.95, 0.995, 3)),
            ("load_inertia", r.uniform(0.03, 0.1, 3)),
            ("coulomb_friction", r.uniform(1.0, 5.0, 2)),
            ("viscous_friction", r.uniform(0.005, 0.03, 4)),
        ]),
        "heavy" => m.s1.extend([("load_inertia", r.uniform(0.06, 0.15, 3)), ("torque_limit", r.uniform(70.0, 160.0, 0))]),
        "coarse" => m.s1.extend([("encoder_counts_per_rev", r.pick(&[4096.0, 8192.0, 16384.0])), ("load_inertia", r.uniform(0.03, 0.08, 3))]),
        "lowff" => m.z.extend([("kv", r.uniform(25.0, 60.0, 1)), ("velocity_ff", r.uniform(0.9, 0.98, 3))]),
        "belt" => m.z.extend([
            ("kv", r.uniform(20.0, 50.0, 1)),
            ("velocity_ff", r.uniform(0.93, 0.99, 3)),
            ("load_stiffness", r.uniform(3.0, 20.0, 1)),
            ("load_damping", r.uniform(0.002, 0.03, 4)),
            ("backlash_deg", r.uniform(0.0, 0.4, 2)),
        ]),
        "delay" => {
            let d = r.pick(&[1.0, 2.0]);
            for v in [&mut m.s1, &mut m.x, &mut m.z] {
                v.push(("transport_delay_cycles", d));
            }
        }
        "friction" => {
            m.s1.extend([("coulomb_friction", r.uniform(2.0, 6.0, 2)), ("viscous_friction", r.uniform(0.01, 0.03, 4))]);
            let (c, v) = (r.uniform(0.3, 0.8, 2), r.uniform(0.0003, 0.001, 5));
            m.x.extend([("coulomb_friction", c), ("viscous_friction", v)]);
            m.z.extend([("coulomb_friction", c), ("viscous_friction", v)]);
        }
        _ => {
            // Two different kinds; a key both set keeps the later value (sim-drives reads the last).
            let a = r.pick(&KINDS[..7]);
            let b = loop {
                let b = r.pick(&KINDS[..7]);
                if b != a {
                    break b;
                }
            };
            add(m, a, r);
            add(m, b, r);
        }
    }
}

/// Other velocity and current loops on the spindle, Z or both (`--loops`; module doc).
fn vary_loops(m: &mut Model, r: &mut Rng) -> &'static str {
    let which = r.pick(&["s1", "z", "both"]);
    for (axis, keys) in [("s1", &mut m.s1), ("z", &mut m.z)] {
        if which != axis && which != "both" {
            continue;
        }
        let (kp, ti, filt, cur) = if axis == "s1" { (12.566, 20.0, 0.5, 0.4) } else { (0.377, 5.0, 0.2, 0.15) };
        let mut scaled = |base: f64, a: f64, b: f64| (base * r.uniform(a, b, 3) * 1e4).round() / 1e4;
        let v = [scaled(kp, 0.35, 1.6), scaled(ti, 0.6, 4.0), scaled(filt, 1.0, 5.0), scaled(cur, 1.0, 4.0)];
        keys.extend([("vel_kp", v[0]), ("vel_ti_ms", v[1]), ("speed_filter_ms", v[2]), ("current_loop_tc_ms", v[3])]);
    }
    which
}

fn toml_of(m: &Model, note: &str) -> String {
    let mut s = format!("# {note}\n");
    let drives =
        [(3, "spindle", "s1", 1000.0, 360_000, &m.s1), (1, "linear", "x", 10000.0, 100_000, &m.x), (2, "linear", "z", 10000.0, 100_000, &m.z)];
    for (node, kind, axis, cpu, cpr, keys) in drives {
        let _ = write!(s, "\n[[drive]]\nnode = {node}\nkind = \"{kind}\"\naxis = \"{axis}\"\ncounts_per_unit = {cpu:.1}\ncounts_per_rev = {cpr}\n");
        // A key set twice (a mix) keeps its last value: TOML refuses duplicates.
        let mut seen: Vec<&str> = vec![];
        let last: Vec<_> = keys
            .iter()
            .rev()
            .filter(|(k, _)| {
                !seen.contains(k) && {
                    seen.push(k);
                    true
                }
            })
            .collect();
        if !last.is_empty() {
            s.push_str("[drive.physics]\n");
        }
        for (k, v) in last.into_iter().rev() {
            let int = matches!(*k, "transport_delay_cycles" | "encoder_counts_per_rev");
            let _ = if int { writeln!(s, "{k} = {}", *v as i64) } else { writeln!(s, "{k} = {v}") };
        }
    }
    s
}

fn main() {
    let (mut seed, mut count, mut out, mut loops) = (20261201u64, 48usize, None::<PathBuf>, false);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        if a == "--loops" {
            loops = true;
            continue;
        }
        let v = args.next().unwrap_or_default();
        match a.as_str() {
            "--seed" => seed = v.parse().unwrap_or_else(|_| usage(&format!("--seed wants a number, got {v:?}"))),
            "--count" => count = v.parse().unwrap_or_else(|_| usage(&format!("--count wants a number, got {v:?}"))),
            "--out" => out = Some(PathBuf::from(v)),
            _ => usage(&format!("unknown argument {a:?}")),
        }
    }
    let Some(out) = out else { usage("--out DIR is needed") };
    if let Err(e) = std::fs::create_dir_all(&out) {
        usage(&format!("{}: {e}", out.display()));
    }
    let mut r = Rng(seed);
    for i in 0..count {
        let kind = KINDS[i % KINDS.len()];
        let mut m = Model::default();
        add(&mut m, kind, &mut r);
        let kind = if loops { format!("{kind}_loops_{}", vary_loops(&mut m, &mut r)) } else { kind.to_string() };
        let flag = if loops { " --loops" } else { "" };
        let note = format!("Random drive model {i} ({kind}), seed {seed}{flag}: examples/random_drive_models.rs.");
        let path = out.join(format!("m{i:02}_{kind}.toml"));
        if let Err(e) = std::fs::write(&path, toml_of(&m, &note)) {
            usage(&format!("{}: {e}", path.display()));
        }
    }
    println!("{count} models written to {}", out.display());
}

fn usage(why: &str) -> ! {
    eprintln!("error: {why}\nusage: random_drive_models --out DIR [--seed N] [--count N] [--loops]");
    std::process::exit(2);
}
