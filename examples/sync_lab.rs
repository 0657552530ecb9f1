//! Lab: rigid tap on drive-model variants (simulated time). Scratch tool for the sync law.
use cncgw::config::{MachineConfig, EMBEDDED_LATHE};
use cncgw::motion::Limits;
use cncgw::sync::measure::{
    g92_1_moves, monitor_stats, phase_spread, rigid_tap_moves, run_moves_on, tap_sync_error, thread_pass_moves, thread_phases,
    CuttingLoad,
};
use sim_drives::SimConfig;

fn variant(name: &str) -> SimConfig {
    let mut c = SimConfig::from_machine_toml(EMBEDDED_LATHE).unwrap();
    for d in &mut c.drives {
        let p = &mut d.physics;
        match (name, d.axis.as_str()) {
            ("soft_spindle", "s1") => {
                p.kv = 12.0;
                p.velocity_ff = 0.99;
                p.load_inertia *= 2.0;
                p.coulomb_friction *= 3.0;
                p.viscous_friction *= 3.0;
            }
            ("heavy_spindle", "s1") => {
                p.load_inertia *= 4.0;
                p.vel_kp *= 1.0;
            }
            ("lowff_z", "z") => p.velocity_ff = 0.95,
            ("belt_z", "z") => {
                p.kv = 25.0;
                p.velocity_ff = 0.95;
            }
            ("slow_spindle", "s1") => {
                p.kv = 8.0;
                p.velocity_ff = 0.9;
            }
            ("soft_all", "s1") => {
                p.kv = 10.0;
                p.velocity_ff = 0.97;
                p.load_inertia *= 2.0;
            }
            ("soft_all", "z") => {
                p.kv = 20.0;
                p.velocity_ff = 0.9;
            }
            ("fric_z", "z") => {
                p.coulomb_friction *= 4.0;
                p.viscous_friction *= 4.0;
            }
            ("fric_s", "s1") => {
                p.coulomb_friction *= 4.0;
                p.viscous_friction *= 4.0;
            }
            ("delay1", _) => p.extra.transport_delay_cycles = 1,
            ("delay2", _) => p.extra.transport_delay_cycles = 2,
            ("delay2_s", "s1") => p.extra.transport_delay_cycles = 2,
            ("delay2_z", "z") => p.extra.transport_delay_cycles = 2,
            ("coarse_s", "s1") => {
                p.extra.encoder_counts_per_rev = 16384;
                p.load_inertia *= 2.0;
            }
            ("beltc_z", "z") => {
                p.kv = 25.0;
                p.velocity_ff = 0.95;
                p.extra.load_stiffness = 6.0;
                p.extra.load_damping = 0.005;
            }
            ("backlash_z", "z") => {
                p.extra.load_stiffness = 30.0;
                p.extra.load_damping = 0.01;
                p.extra.backlash_deg = 0.5;
            }
            ("fric_all", _) => {
                p.coulomb_friction *= 4.0;
                p.viscous_friction *= 4.0;
            }
            ("slowvel_z", "z") => {
                p.vel_kp *= 0.3;
                p.vel_ti_ms *= 3.0;
            }
            _ => {}
        }
    }
    c
}

fn main() {
    let mut cfg = MachineConfig::embedded();
    if let Ok(w) = std::env::var("SPINDLE_WINDOW") {
        cfg.axes.get_mut("s1").unwrap().following_error = w.parse().unwrap();
    }
    let names: Vec<String> = std::env::args().skip(1).collect();
    let names = if names.is_empty() {
        ["default", "soft_spindle", "heavy_spindle", "lowff_z", "belt_z", "slow_spindle"].map(String::from).to_vec()
    } else {
        names
    };
    for name in &names {
        for (rpm, bottom) in [(3000.0, -33.0), (6000.0, -198.0)] {
            let mut l = Limits::from_config(&cfg);
            l.sync_err_limit_um = f64::INFINITY;
            let run = run_moves_on(&cfg, variant(name), l, rigid_tap_moves(2.0, bottom, 1.5, rpm), Some(CuttingLoad::m10_tap(0.0)))
                .unwrap();
            let res = match &run.result {
                Ok(()) => "ok".to_string(),
                Err(a) => format!("alarm {}: {}", a.number, a.message.chars().take(200).collect::<String>()),
            };
            let (max, rms, n) = tap_sync_error(&run, 1.5, (2, 3)).unwrap_or((f64::NAN, f64::NAN, 0));
            let peak = run.rows.iter().map(|r| r.spindle_rpm.abs()).fold(0.0, f64::max);
            println!("{name:>14} S{rpm:<5} max {max:7.2} µm  rms {rms:6.2} µm  n {n:5}  peak {peak:5.0} rpm  {res}");
            if let Ok(dir) = std::env::var("SYNC_DUMP_X") {
                let (z, sp) = (run.drive("z").unwrap_or(0), run.drive("s1").unwrap_or(0));
                let mut out = String::from("t_s,line,z_cmd,z_act,s_cmd,s_act,rpm,sync_um\n");
                for r in &run.rows {
                    out += &format!(
                        "{:.4},{},{:.6},{:.6},{:.4},{:.4},{:.1},{:.2}\n",
                        r.t_s, r.line, r.cmd[z], r.act[z], r.cmd[sp], r.act[sp], r.spindle_rpm, r.sync_err_um
                    );
                }
                let _ = std::fs::write(format!("{dir}/{name}_{rpm}.csv"), out);
            }
        }
            let mut l = Limits::from_config(&cfg);
        l.sync_err_limit_um = f64::INFINITY;
        let g = run_moves_on(&cfg, variant(name), l.clone(), g92_1_moves(15.0, 5.0, -40.0, 2.0, 1000.0), None).unwrap();
        let (gm, gr, _) = monitor_stats(&g).unwrap_or((f64::NAN, f64::NAN, 0));
        if std::env::var("G921_DUMP").is_ok() {
            let (z, sp) = (g.drive("z").unwrap_or(0), g.drive("s1").unwrap_or(0));
            for (k, r) in g.rows.iter().enumerate().filter(|(_, r)| r.sync_err_um != 0.0).step_by(10) {
                println!("{k} {:.4} line {} z {:.4}/{:.4} s {:.2}/{:.2} rpm {:.0} err {:.2}", r.t_s, r.line, r.cmd[z], r.act[z], r.cmd[sp], r.act[sp], r.spindle_rpm, r.sync_err_um);
            }
        }
        println!("{name:>14} G92.1 S1000 max {gm:7.2} µm  rms {gr:6.2} µm  {:?}", g.result.as_ref().err().map(|a| a.number));
        let rpms = [500.0, 1000.0, 1500.0];
        let t = run_moves_on(&cfg, variant(name), l, thread_pass_moves(15.0, 5.0, -20.0, 1.5, &rpms), None).unwrap();
        match thread_phases(&t, -5.0, rpms.len()) {
            Some(ph) => println!("{name:>14} thread phases {:?} spread {:.4}°", ph.iter().map(|p| (p * 1000.0).round() / 1000.0).collect::<Vec<_>>(), phase_spread(&ph)),
            None => println!("{name:>14} thread: failed {:?}", t.result.as_ref().err().map(|a| a.number)),
        }
}
}
