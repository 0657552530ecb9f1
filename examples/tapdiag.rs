//! scratch: per-cycle sync error of one model's tap
use cncgw::config::MachineConfig;
use cncgw::control::embedded::measure::*;
use cncgw::motion::Limits;

fn main() {
    let a: Vec<String> = std::env::args().skip(1).collect();
    let text = std::fs::read_to_string(&a[0]).unwrap();
    let rpm: f64 = a.get(1).map_or(3000.0, |s| s.parse().unwrap());
    let bottom: f64 = a.get(2).map_or(-33.0, |s| s.parse().unwrap());
    let cfg = MachineConfig::embedded();
    let sim = sim_drives::SimConfig::from_toml(&text).unwrap();
    let r = run_moves_on(&cfg, sim, Limits::from_config(&cfg), rigid_tap_moves(2.0, bottom, 1.5, rpm), Some(CuttingLoad::m10_tap(0.0))).unwrap();
    let (z, s) = (r.drive("z").unwrap(), r.names.iter().position(|n| n.starts_with('s')).unwrap());
    let first = r.rows.iter().position(|x| x.line == 2).unwrap();
    let r0 = &r.rows[first - 1];
    let (z0, th0) = (r0.cmd[z], r0.cmd[s]);
    println!("t line zcmd zact scmd sact err_um monitor_um rpm");
    for x in &r.rows[first..] {
        if x.line > 3 { break; }
        let e = ((x.act[z] - z0) - 1.5 * (x.act[s] - th0) / 360.0) * 1000.0;
        println!("{:.3} {} {:.5} {:.5} {:.3} {:.3} {:.3} {:.3} {:.1}", x.t_s, x.line, x.cmd[z], x.act[z], x.cmd[s], x.act[s], e, x.sync_err_um, x.spindle_rpm);
    }
    eprintln!("{:?}", tap_sync_error(&r, 1.5, (2, 3)));
}
