//! The default feed-axis and spindle models: position and velocity step responses, and the
//! following error at constant speed, as a table and a small plot for the notes.
//!
//!     cargo run -p sim-drives --example step_response

use sim_drives::config::{DriveConfig, DriveKind};
use sim_drives::servo::{step_response, step_trace, velocity_step_response, Command, Servo};

fn main() {
    let dt = 50e-6;
    let axes = [DriveConfig::new(1, DriveKind::Linear, "x", 10000.0), DriveConfig::new(3, DriveKind::Spindle, "s1", 1000.0)];
    println!("Default servo models (control step {} µs)\n", dt * 1e6);
    println!(
        "{:<8} {:>10} {:>6} {:>9} {:>11} {:>9} {:>11} {:>10} {:>9}",
        "kind", "J kg·m²", "Kv 1/s", "pos rise", "overshoot", "settle", "final err", "vel rise", "vel ovs"
    );
    for c in &axes {
        let p = &c.physics;
        let step = 1000.0;
        let (rise, ovs, settle, fin) = step_response(p, c.counts_per_rev, step, dt, 2.0);
        // Speed step: 100 rpm.
        let v = 100.0 / 60.0 * c.counts_per_rev as f64;
        let (vrise, vovs) = velocity_step_response(p, c.counts_per_rev, v, dt, 1.0);
        println!(
            "{:<8} {:>10.2e} {:>6.0} {:>6.1} ms {:>9.1} % {:>6.1} ms {:>5} cnt {:>7.2} ms {:>7.1} %",
            c.kind.name(),
            p.inertia(),
            p.kv,
            rise * 1e3,
            ovs,
            settle * 1e3,
            fin,
            vrise * 1e3,
            vovs
        );
    }
    println!("\nposition step of 1000 counts, no feed-forward (fraction of the step):");
    let traces: Vec<Vec<(f64, f64)>> = axes.iter().map(|c| step_trace(&c.physics, c.counts_per_rev, 1000.0, dt, 0.3, 0.01)).collect();
    println!("{:>7}  {:>7}  {:>7}   (L = linear, S = spindle; 0 … 1.2)", "t ms", "linear", "spindle");
    for (&(t, a), &(_, b)) in traces[0].iter().zip(&traces[1]) {
        let mut line = [b' '; 49];
        let col = |x: f64| ((x / 1000.0 / 1.2 * 48.0).round().clamp(0.0, 48.0)) as usize;
        line[col(1000.0)] = b'|';
        line[col(b)] = b'S';
        line[col(a)] = b'L';
        println!("{:>7.0}  {:>7.3}  {:>7.3}   {}", t * 1e3, a / 1000.0, b / 1000.0, String::from_utf8_lossy(&line));
    }
    println!("\nfollowing error at constant speed, simulated (analytic (1 − ff)·v / Kv in brackets):");
    for c in &axes {
        let p = &c.physics;
        let (unit, speeds): (&str, &[f64]) = match c.kind {
            DriveKind::Linear => ("mm/min", &[1000.0, 5000.0, 10000.0]),
            DriveKind::Spindle => ("rpm", &[100.0, 1000.0, 3000.0]),
        };
        for &sp in speeds {
            let v = match c.kind {
                DriveKind::Linear => sp / 60.0 * c.counts_per_unit,
                DriveKind::Spindle => sp / 60.0 * c.counts_per_rev as f64,
            };
            // Ramp up at a moderate acceleration, then cruise 1 s and average the error.
            let mut s = Servo::new(p.clone(), c.counts_per_rev);
            let acc = v / 0.2;
            let (mut x, mut vv, mut sum, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
            for i in 0..((1.5 / dt) as usize) {
                // Demand and actual at the same instant, as the drive compares them.
                s.control(Command::Position { demand: x, vff: vv }, dt);
                if i as f64 * dt > 0.5 {
                    sum += x - s.position_counts() as f64;
                    n += 1;
                }
                s.integrate(dt);
                vv = (vv + acc * dt).min(v);
                x += vv * dt;
            }
            let e = sum / n as f64;
            let analytic = (1.0 - p.velocity_ff) * v / p.kv;
            let u = if c.kind == DriveKind::Linear { "mm" } else { "°" };
            println!("  {:<8} {:>6} {:<6} → {:>7.0} counts = {:.4} {u}  [{:.0}]", c.kind.name(), sp, unit, e, e / c.counts_per_unit, analytic);
        }
    }
}
