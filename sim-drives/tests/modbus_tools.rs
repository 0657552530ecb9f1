//! Modbus peers we did not write against `sim-drives`' Modbus server: Debian's `mbpoll`
//! over TCP and over RTU through a `socat` pseudo-terminal pair, and tokio-modbus' RTU
//! client through the same kind of pair.
//!
//! Needs `socat` and `mbpoll` (`scripts/install-test-deps.sh` installs them). Without them
//! these tests FAIL, naming that command; set CNCGW_SKIP_MODBUS_TOOLS=1 to skip them on
//! purpose — except with CI=true, where a missing tool always fails.

use cncgw_bus::cia402::{cw, State};
use cncgw_bus::modbus::{Cia402Map, WordOrder};
use std::net::{TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use testkit::{have_tool as have, pty_pair, Kill};

fn tmp(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(name)
}

/// Start the `sim-drives` binary with `args`; wait until its log says it serves.
fn sim_drives(args: &[&str], tag: &str) -> (Kill, PathBuf) {
    let log = tmp(&format!("modbus_tools_{tag}_{}.log", std::process::id()));
    let c = Command::new(env!("CARGO_BIN_EXE_sim-drives"))
        .args(args)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("log file"))
        .spawn()
        .expect("start sim-drives");
    let mut k = Kill(c);
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        if text.contains("Modbus TCP on") || text.contains("Modbus RTU on") {
            break;
        }
        if let Ok(Some(st)) = k.0.try_wait() {
            panic!("sim-drives {args:?} exited ({st}): {text}");
        }
        assert!(Instant::now() < deadline, "sim-drives {args:?} not serving after 10 s: {text}");
        std::thread::sleep(Duration::from_millis(20));
    }
    // Boot-up of the drives (≤ 2.5 ms after the start).
    std::thread::sleep(Duration::from_millis(20));
    (k, log)
}

struct Poll {
    ok: bool,
    out: String,
    err: String,
}

impl Poll {
    /// The `[ref]: value` lines of mbpoll's output, raw 16-bit values.
    fn values(&self) -> Vec<(u32, i64)> {
        self.out
            .lines()
            .filter_map(|l| {
                let l = l.trim();
                let rest = l.strip_prefix('[')?;
                let (r, v) = rest.split_once("]:")?;
                let v = v.split_whitespace().next()?;
                Some((r.parse().ok()?, v.parse().ok()?))
            })
            .collect()
    }
}

fn mbpoll(args: &[&str]) -> Poll {
    let o = Command::new("mbpoll").args(args).stdin(Stdio::null()).output().expect("run mbpoll");
    Poll { ok: o.status.success(), out: String::from_utf8_lossy(&o.stdout).into_owned(), err: String::from_utf8_lossy(&o.stderr).into_owned() }
}

/// mbpoll against `link` (TCP: `-m tcp -p PORT HOST`; RTU: `-m rtu … DEVICE`, the host or
/// device last), unit `unit`, 0-based references; `rest` are options, then `--` and the
/// values to write, if any.
fn poll(link: &[&str], unit: u8, rest: &[&str]) -> Poll {
    let unit = unit.to_string();
    let (target, link_opts) = link.split_last().expect("link");
    let split = rest.iter().position(|x| *x == "--").unwrap_or(rest.len());
    // A generous timeout: a loaded machine stalls processes for 100s of ms.
    let mut a: Vec<&str> = vec!["-1", "-0", "-o", "3", "-a", &unit];
    a.extend_from_slice(link_opts);
    a.extend_from_slice(&rest[..split]);
    a.push(target);
    a.extend_from_slice(&rest[split..]);
    mbpoll(&a)
}

const M: Cia402Map = Cia402Map::SIM_DRIVES;

/// What every link must show: registers read and written, the 402 machine driven by
/// controlword writes, 32-bit values, and the exception codes for bad requests.
fn common_checks(link: &[&str]) {
    let r = |reg: u16| reg.to_string();
    // Statusword of unit 1 after boot: Switch On Disabled.
    let p = poll(link, 1, &["-r", &r(M.statusword), "-c", "7"]);
    assert!(p.ok, "{} {}", p.out, p.err);
    let v = p.values();
    assert_eq!(v.len(), 7, "{}", p.out);
    assert_eq!(State::from_statusword(v[0].1 as u16), State::SwitchOnDisabled, "{}", p.out);
    // Controlword 6 → Ready to Switch On.
    let p = poll(link, 1, &["-r", &r(M.controlword), "--", &cw::SHUTDOWN.to_string()]);
    assert!(p.ok && p.out.contains("Written 1 references"), "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", &r(M.statusword)]);
    assert_eq!(State::from_statusword(p.values()[0].1 as u16), State::ReadyToSwitchOn, "{}", p.out);
    // A 32-bit write, high word first (-B), read back as two raw registers.
    let p = poll(link, 1, &["-t", "4:int", "-B", "-r", &r(M.target_position), "--", "-123456"]);
    assert!(p.ok, "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", &r(M.target_position), "-c", "2"]);
    let v: Vec<u16> = p.values().iter().map(|x| x.1 as u16).collect();
    assert_eq!(v, WordOrder::HighFirst.split_i32(-123_456).to_vec(), "{}", p.out);
    let p = poll(link, 1, &["-t", "4:int", "-B", "-r", &r(M.target_position)]);
    assert!(p.out.contains("-123456"), "{}", p.out);
    // Input registers (FC04) are the same map.
    let p = poll(link, 1, &["-t", "3", "-r", &r(M.statusword)]);
    assert_eq!(State::from_statusword(p.values()[0].1 as u16), State::ReadyToSwitchOn, "{}", p.out);
    // Exceptions: 0x02 for an address outside the map and for a read-only register, 0x03
    // for a bad value, 0x01 for a function the drive has not.
    let p = poll(link, 1, &["-r", "6"]);
    assert!(!p.ok && p.err.contains("Illegal data address"), "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", "0", "-c", "24"]);
    assert!(!p.ok && p.err.contains("Illegal data address"), "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", &r(M.statusword), "--", "0"]);
    assert!(!p.ok && p.err.contains("Illegal data address"), "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", &r(M.mode), "--", "3"]);
    assert!(!p.ok && p.err.contains("Illegal data value"), "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-t", "0", "-r", "0"]);
    assert!(!p.ok && p.err.contains("Illegal function"), "{} {}", p.out, p.err);
    // The mode write that is valid goes through and shows in the display.
    let p = poll(link, 1, &["-r", &r(M.mode), "--", "8"]);
    assert!(p.ok, "{} {}", p.out, p.err);
    let p = poll(link, 1, &["-r", &r(M.mode_display)]);
    assert_eq!(p.values()[0].1, 8, "{}", p.out);
}

#[test]
fn mbpoll_over_tcp() {
    if !have("mbpoll") {
        return;
    }
    let cfg = tmp(&format!("modbus_tools_tcp_{}.toml", std::process::id()));
    std::fs::write(
        &cfg,
        "[[drive]]\nnode = 1\nkind = \"linear\"\n\n[[drive]]\nnode = 2\nkind = \"linear\"\n[drive.cia402_map]\nword_order = \"low_first\"\n\n\
         [[drive]]\nnode = 4\nkind = \"linear\"\nmodbus_profile = \"pr\"\n",
    )
    .unwrap();
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let (_sim, log) = sim_drives(&["--modbus-tcp", &addr, "--config", cfg.to_str().unwrap()], "tcp");
    assert!(TcpStream::connect(&addr).is_ok());
    let ps = port.to_string();
    let link = ["-m", "tcp", "-p", &ps, "127.0.0.1"];
    common_checks(&link);
    // Unit 2 keeps 32-bit values low word first: mbpoll's default word order.
    let p = poll(&link, 2, &["-t", "4:int", "-r", "1", "--", "-123456"]);
    assert!(p.ok, "{} {}", p.out, p.err);
    let p = poll(&link, 2, &["-r", "1", "-c", "2"]);
    let v: Vec<u16> = p.values().iter().map(|x| x.1 as u16).collect();
    assert_eq!(v, WordOrder::LowFirst.split_i32(-123_456).to_vec(), "{}", p.out);
    // Unit 4 speaks the PR profile: servo on, and its status says enabled.
    let p = poll(&link, 4, &["-r", &0x0405.to_string(), "--", "1"]);
    assert!(p.ok, "{} {}", p.out, p.err);
    let p = poll(&link, 4, &["-r", &0x6003.to_string()]);
    assert_eq!(p.values()[0].1 & 0b10, 0b10, "{}", p.out);
    let p = poll(&link, 4, &["-r", &0x0405.to_string(), "--", "2"]);
    assert!(!p.ok && p.err.contains("Illegal data value"), "{} {}", p.out, p.err);
    // A unit no drive has: the gateway's exception 0x0B.
    let p = poll(&link, 9, &["-r", "10"]);
    assert!(!p.ok && p.err.contains("Target device failed to respond"), "{} {}", p.out, p.err);
    let _ = log;
}

#[test]
fn mbpoll_over_rtu_through_a_socat_pty_pair() {
    if !have("socat") || !have("mbpoll") {
        return;
    }
    for (parity, mb_parity) in [("none", "none"), ("even", "even")] {
        let (_socat, a, b) = pty_pair();
        let (_sim, _log) = sim_drives(&["--modbus-rtu", &a, "--baud", "115200", "--parity", parity, "--stop-bits", "1"], "rtu");
        let link = ["-m", "rtu", "-b", "115200", "-P", mb_parity, "-s", "1", b.as_str()];
        common_checks(&link);
        // A unit no drive has: silence on the line (a timeout), as on a real RS-485 bus.
        let p = poll(&link, 9, &["-o", "0.3", "-r", "10"]);
        assert!(!p.ok && p.err.contains("timed out"), "{} {}", p.out, p.err);
        // The line still works after that.
        let p = poll(&link, 2, &["-r", "10"]);
        assert!(p.ok, "{} {}", p.out, p.err);
    }
}

#[test]
fn tokio_modbus_rtu_client_through_a_socat_pty_pair() {
    if !have("socat") {
        return;
    }
    use tokio_modbus::prelude::*;
    // The drives' warnings (a fault says why) in the test's output.
    let _ = tracing_subscriber::fmt().with_env_filter(std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into())).with_test_writer().try_init();
    let (_socat, a, b) = pty_pair();
    let stop = Arc::new(AtomicBool::new(false));
    let line = sim_drives::modbus::RtuLine::default();
    let srv = sim_drives::modbus::serve_rtu(&a, line, sim_drives::SimConfig::default_lathe(), stop.clone()).expect("serve_rtu");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        tokio::time::sleep(Duration::from_millis(20)).await;
        let port = tokio_serial::SerialStream::open(&tokio_serial::new(&b, 115_200)).expect("open pty");
        let mut c = tokio_modbus::client::rtu::attach_slave(port, Slave(2));
        let sw = c.read_holding_registers(M.statusword, 1).await.unwrap().unwrap()[0];
        assert_eq!(State::from_statusword(sw), State::SwitchOnDisabled);
        // Enable in CSP and move 1000 counts in 100 targets, 2 ms apart, each one FC23.
        c.write_single_register(M.mode, 8).await.unwrap().unwrap();
        c.write_single_register(M.interpolation_ms.unwrap(), 2).await.unwrap().unwrap();
        for w in [cw::SHUTDOWN, cw::ENABLE_OPERATION_CMD] {
            c.write_single_register(M.controlword, w).await.unwrap().unwrap();
        }
        let p0 = {
            let r = c.read_holding_registers(M.position_actual, 2).await.unwrap().unwrap();
            M.word_order.join_i32([r[0], r[1]])
        };
        let mut tick = tokio::time::interval(Duration::from_millis(2));
        for k in 1..=110 {
            tick.tick().await;
            let t = M.word_order.split_i32(p0 + 10 * k.min(100));
            let r = c.read_write_multiple_registers(M.statusword, 7, M.controlword, &[cw::ENABLE_OPERATION_CMD, t[0], t[1]]).await.unwrap().unwrap();
            assert_eq!(State::from_statusword(r[0]), State::OperationEnabled, "{:#06x}", r[0]);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        let r = c.read_holding_registers(M.position_actual, 2).await.unwrap().unwrap();
        let p = M.word_order.join_i32([r[0], r[1]]);
        assert!((p - (p0 + 1000)).abs() <= 10, "at {p}, target {}", p0 + 1000);
        // Exceptions over RTU.
        assert_eq!(c.read_holding_registers(6, 1).await.unwrap(), Err(ExceptionCode::IllegalDataAddress));
        assert_eq!(c.write_single_register(M.mode, 77).await.unwrap(), Err(ExceptionCode::IllegalDataValue));
        // Unit 9: no answer at all.
        c.set_slave(Slave(9));
        let r = tokio::time::timeout(Duration::from_millis(300), c.read_holding_registers(M.statusword, 1)).await;
        assert!(r.is_err(), "unit 9 answered: {r:?}");
    });
    stop.store(true, Ordering::Relaxed);
    srv.join().expect("RTU server");
}

/// Transactions per second through a socat pty pair (a pty does not pace bytes at the baud
/// rate: this is the server's and the pty's turnaround, not a 115200-baud line):
/// `cargo test -p sim-drives --test modbus_tools -- --ignored --nocapture`.
#[test]
#[ignore = "measurement; prints figures"]
fn rtu_pty_transaction_rate() {
    if !have("socat") {
        return;
    }
    use tokio_modbus::prelude::*;
    let (_socat, a, b) = pty_pair();
    let stop = Arc::new(AtomicBool::new(false));
    let srv = sim_drives::modbus::serve_rtu(&a, sim_drives::modbus::RtuLine::default(), sim_drives::SimConfig::default_lathe(), stop.clone())
        .expect("serve_rtu");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let port = tokio_serial::SerialStream::open(&tokio_serial::new(&b, 115_200)).expect("open pty");
        let mut c = tokio_modbus::client::rtu::attach_slave(port, Slave(1));
        for units in [1u8, 3] {
            let n = 500;
            let t0 = Instant::now();
            for _ in 0..n {
                for u in 1..=units {
                    c.set_slave(Slave(u));
                    c.read_write_multiple_registers(M.statusword, 7, M.controlword, &[0, 0, 0]).await.unwrap().unwrap();
                }
            }
            let dt = t0.elapsed().as_secs_f64();
            println!(
                "Modbus RTU over a pty, {units} drive(s): {:.0} FC23 transactions/s, one cycle {:.3} ms",
                (n * units as u32) as f64 / dt,
                dt / n as f64 * 1e3
            );
        }
    });
    stop.store(true, Ordering::Relaxed);
    srv.join().expect("RTU server");
}

/// A mixed machine config: `sim-drives --modbus-tcp` serves the axes of one Modbus link
/// (`--modbus-link`), not the CANopen ones, even where their ids are the same.
#[test]
fn machine_config_link_selects_the_drives() {
    use tokio_modbus::prelude::*;
    let cfg = tmp(&format!("modbus_tools_mixed_{}.toml", std::process::id()));
    std::fs::write(
        &cfg,
        "[axes.x]\nkind = \"linear\"\nnode = 1\ncounts_per_unit = 10000.0\n\n\
         [axes.w]\nkind = \"linear\"\nnode = 1\nmodbus = \"tcp\"\nmodbus_profile = \"pr\"\ncounts_per_unit = 10000.0\n\n\
         [axes.t]\nkind = \"linear\"\nnode = 5\nmodbus = \"rs485\"\ncounts_per_unit = 10000.0\n",
    )
    .unwrap();
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let addr = format!("127.0.0.1:{port}");
    let (_sim, _log) = sim_drives(&["--modbus-tcp", &addr, "--config", cfg.to_str().unwrap(), "--modbus-link", "tcp"], "mixed");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let mut c = tokio_modbus::client::tcp::connect_slave(addr.parse().unwrap(), Slave(1)).await.unwrap();
        // Unit 1 is the PR axis w, not the CANopen axis x with the same id.
        assert!(c.read_holding_registers(0x6003, 1).await.unwrap().is_ok());
        assert_eq!(c.read_holding_registers(10, 1).await.unwrap(), Err(ExceptionCode::IllegalDataAddress));
        // Unit 5 is on the other link.
        c.set_slave(Slave(5));
        assert_eq!(c.read_holding_registers(10, 1).await.unwrap(), Err(ExceptionCode::GatewayTargetDevice));
    });
    let out = Command::new(env!("CARGO_BIN_EXE_sim-drives"))
        .args(["--modbus-tcp", "127.0.0.1:0", "--config", cfg.to_str().unwrap(), "--modbus-link", "line9"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no drive is on Modbus link \"line9\" (links in the config: rs485, tcp)"), "{err}");
}
