//! `sim_drives::modbus` over TCP against tokio-modbus's client: the CiA 402 register map
//! (enable, CSP streaming, CSV, following error, comm timeout), the PR profile, word order
//! and every exception code. Real time, in-process server on a free port.

use cncgw_bus::cia402::{cw, EnableProgress, Enabler, State};
use cncgw_bus::modbus::{pr_block, pr_status, Cia402Map, PrMap, Profile, WordOrder};
use sim_drives::modbus::{serve_tcp, ModbusServer, COMM_TIMEOUT_CODE};
use sim_drives::{DriveConfig, DriveKind, SimConfig};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_modbus::client::Context;
use tokio_modbus::prelude::*;

struct Srv {
    srv: Option<ModbusServer>,
    stop: Arc<AtomicBool>,
    addr: SocketAddr,
}

impl Drop for Srv {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(s) = self.srv.take() {
            let _ = s.join();
        }
    }
}

impl Srv {
    fn start(cfg: SimConfig) -> Srv {
        let stop = Arc::new(AtomicBool::new(false));
        let srv = serve_tcp("127.0.0.1:0".parse().unwrap(), cfg, stop.clone()).expect("serve_tcp");
        let addr = srv.local_addr().expect("bound address");
        Srv { srv: Some(srv), stop, addr }
    }
    fn server(&self) -> &ModbusServer {
        self.srv.as_ref().unwrap()
    }
    async fn client(&self, unit: u8) -> Context {
        tokio_modbus::client::tcp::connect_slave(self.addr, Slave(unit)).await.expect("connect")
    }
}

const M: Cia402Map = Cia402Map::SIM_DRIVES;

async fn read(c: &mut Context, addr: u16, n: u16) -> Vec<u16> {
    c.read_holding_registers(addr, n).await.expect("transport").unwrap_or_else(|e| panic!("read {addr}+{n}: {e:?}"))
}

async fn write(c: &mut Context, addr: u16, v: &[u16]) {
    c.write_multiple_registers(addr, v).await.expect("transport").unwrap_or_else(|e| panic!("write {addr} {v:?}: {e:?}"))
}

async fn write1(c: &mut Context, addr: u16, v: u16) {
    c.write_single_register(addr, v).await.expect("transport").unwrap_or_else(|e| panic!("write {addr} = {v}: {e:?}"))
}

async fn read_i32(c: &mut Context, addr: u16, o: WordOrder) -> i32 {
    let r = read(c, addr, 2).await;
    o.join_i32([r[0], r[1]])
}

/// Boot, then walk the drive to Operation Enabled with the shared master-side `Enabler`.
async fn enable(c: &mut Context) {
    tokio::time::sleep(Duration::from_millis(10)).await; // boot-up (≤ 2.5 ms)
    let mut e = Enabler::default();
    for _ in 0..20 {
        let s = read(c, M.statusword, 1).await[0];
        match e.step(s) {
            EnableProgress::Enabled => return,
            EnableProgress::ResetFailed => panic!("fault reset failed, statusword {s:#06x}"),
            EnableProgress::Walking => write1(c, M.controlword, e.controlword).await,
        }
    }
    panic!("not enabled after 20 steps");
}

fn state(sw: u16) -> State {
    State::from_statusword(sw)
}

#[tokio::test(flavor = "current_thread")]
async fn csp_streaming_for_one_second_is_followed() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(1).await;
    write1(&mut c, M.mode, 8).await;
    write1(&mut c, M.interpolation_ms.unwrap(), 4).await;
    assert_eq!(read(&mut c, M.mode_display, 1).await[0], 8);
    enable(&mut c).await;
    let p0 = read_i32(&mut c, M.position_actual, M.word_order).await;
    // A smooth 1 s move of 20 000 counts (2 mm) and back, one target per 4 ms cycle; every
    // other cycle the target goes with the statusword read in one FC23.
    let period = Duration::from_millis(4);
    let start = Instant::now();
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let amp = 10_000.0;
    let target_at = |t: f64| p0 + (amp * (1.0 - (2.0 * std::f64::consts::PI * t).cos())).round() as i32;
    let mut worst_lag = 0i64;
    let mut k = 0u32;
    loop {
        tick.tick().await;
        let t = start.elapsed().as_secs_f64();
        if t > 1.0 {
            break;
        }
        let target = target_at(t);
        let w = M.word_order.split_i32(target);
        let block = [cw::ENABLE_OPERATION_CMD, w[0], w[1]];
        let actual = if k % 2 == 0 {
            write(&mut c, M.controlword, &block).await;
            read_i32(&mut c, M.position_actual, M.word_order).await
        } else {
            let r = c.read_write_multiple_registers(M.statusword, 7, M.controlword, &block).await.expect("transport").expect("FC23");
            assert_eq!(state(r[0]), State::OperationEnabled, "statusword {:#06x}", r[0]);
            M.word_order.join_i32([r[2], r[3]])
        };
        // The drive reaches a target one interpolation period after it was written.
        if t > 0.05 {
            worst_lag = worst_lag.max((target as i64 - actual as i64).abs());
        }
        k += 1;
    }
    assert!(k > 150, "only {k} cycles in 1 s");
    // Peak speed 2π·10 000 ≈ 63 000 counts/s: one 4 ms period plus the loop's lag is
    // ≈ 250–500 counts; a drive that did not follow would lag by the whole 20 000.
    assert!(worst_lag < 2_000, "worst lag {worst_lag} counts");
    // A CSP master keeps sending the final target (a drive extrapolates a missing one).
    let last = target_at(1.0);
    let w = M.word_order.split_i32(last);
    for _ in 0..3 {
        write(&mut c, M.controlword, &[cw::ENABLE_OPERATION_CMD, w[0], w[1]]).await;
        tick.tick().await;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let end = read_i32(&mut c, M.position_actual, M.word_order).await;
    assert!((end - last).abs() <= 10, "ended at {end}, target {last}");
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::OperationEnabled);
    assert_eq!(r[6], 0, "error code");
    assert_eq!(s.server().with_drive(1, |d| d.error_code()), Some(0));
}

#[tokio::test(flavor = "current_thread")]
async fn csv_runs_at_the_target_velocity() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(3).await; // the spindle
    write1(&mut c, M.mode, 9).await;
    enable(&mut c).await;
    let v = 360_000; // 1 rev/s
    write(&mut c, M.target_velocity, &M.word_order.split_i32(v)).await;
    tokio::time::sleep(Duration::from_millis(600)).await;
    let va = read_i32(&mut c, M.velocity_actual, M.word_order).await;
    assert!((va - v).abs() < v / 50, "velocity actual {va}");
    let sw = read(&mut c, M.statusword, 1).await[0];
    assert!(sw & (1 << 10) != 0, "target reached, statusword {sw:#06x}");
}

#[tokio::test(flavor = "current_thread")]
async fn following_error_window_faults_8611() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(2).await;
    write1(&mut c, M.mode, 8).await;
    enable(&mut c).await;
    write(&mut c, M.following_error_window, &M.word_order.split_i32(50)).await;
    assert_eq!(read_i32(&mut c, M.following_error_window, M.word_order).await, 50);
    let p = read_i32(&mut c, M.position_actual, M.word_order).await;
    // A 5 mm jump in one (default 1 ms) period: the motor cannot follow.
    write(&mut c, M.target_position, &M.word_order.split_i32(p + 50_000)).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::Fault, "statusword {:#06x}", r[0]);
    assert_eq!(r[6], 0x8611);
}

#[tokio::test(flavor = "current_thread")]
async fn comm_timeout_faults_8130_and_stops_the_motor() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(1).await;
    write1(&mut c, M.mode, 9).await;
    write1(&mut c, M.comm_timeout_ms.unwrap(), 50).await;
    assert_eq!(read(&mut c, M.comm_timeout_ms.unwrap(), 1).await[0], 50);
    enable(&mut c).await;
    // 20 000 counts/s (2 mm/s), kept alive by writes every 20 ms for 300 ms.
    for _ in 0..15 {
        write(&mut c, M.target_velocity, &M.word_order.split_i32(20_000)).await;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::OperationEnabled, "kept alive: {:#06x}", r[0]);
    assert!(M.word_order.join_i32([r[4], r[5]]) > 15_000, "moving: {r:?}");
    // Silence (reads do not count): the watchdog trips 50 ms after the last write and the
    // motor stops.
    write(&mut c, M.target_velocity, &M.word_order.split_i32(20_000)).await;
    let t0 = Instant::now();
    let mut faulted_at = None;
    while t0.elapsed() < Duration::from_millis(500) {
        let r = read(&mut c, M.statusword, 7).await;
        if matches!(state(r[0]), State::Fault | State::FaultReactionActive) && faulted_at.is_none() {
            faulted_at = Some(t0.elapsed());
            assert_eq!(r[6], COMM_TIMEOUT_CODE);
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let at = faulted_at.expect("no comm-timeout fault");
    assert!(at >= Duration::from_millis(40) && at < Duration::from_millis(150), "faulted after {at:?}");
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::Fault);
    let v_end = M.word_order.join_i32([r[4], r[5]]);
    assert!(v_end.abs() < 100, "motor still turning: {v_end} counts/s");
    // Fault reset on a rising edge of bit 7; the error code clears.
    write1(&mut c, M.controlword, 0).await;
    write1(&mut c, M.controlword, cw::FAULT_RESET_CMD).await;
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::SwitchOnDisabled, "{:#06x}", r[0]);
    assert_eq!(r[6], 0);
}

async fn exception<T: std::fmt::Debug>(r: tokio_modbus::Result<T>) -> ExceptionCode {
    match r {
        Ok(Err(e)) => e,
        other => panic!("expected an exception, got {other:?}"),
    }
}

#[tokio::test(flavor = "current_thread")]
async fn exceptions_cia402() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(1).await;
    tokio::time::sleep(Duration::from_millis(10)).await;
    // 0x02: a register outside the map (the gaps 6–9, 17–19, past 34), alone or in a block.
    assert_eq!(exception(c.read_holding_registers(6, 1).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_holding_registers(0, 24).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_holding_registers(35, 1).await).await, ExceptionCode::IllegalDataAddress);
    // 0x60FD (digital inputs) is read only.
    assert_eq!(exception(c.write_multiple_registers(33, &[0, 0]).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_input_registers(17, 2).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_holding_registers(65535, 2).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.write_single_register(7, 1).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.write_multiple_registers(3, &[0, 0, 8, 0]).await).await, ExceptionCode::IllegalDataAddress);
    // 0x02: a read-only register, alone or inside a write.
    assert_eq!(exception(c.write_single_register(M.statusword, 0).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.write_multiple_registers(M.position_actual, &[0, 0]).await).await, ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_write_multiple_registers(M.statusword, 1, M.mode_display, &[8]).await).await, ExceptionCode::IllegalDataAddress);
    // 0x03: values out of range; nothing of a refused request takes effect.
    assert_eq!(exception(c.write_single_register(M.mode, 3).await).await, ExceptionCode::IllegalDataValue);
    assert_eq!(exception(c.write_single_register(M.mode, 0).await).await, ExceptionCode::IllegalDataValue);
    assert_eq!(exception(c.write_multiple_registers(M.controlword, &[6, 0, 0, 0, 0, 7]).await).await, ExceptionCode::IllegalDataValue);
    assert_eq!(read(&mut c, M.controlword, 1).await[0], 0, "refused request wrote the controlword");
    assert_eq!(exception(c.write_single_register(M.interpolation_ms.unwrap(), 256).await).await, ExceptionCode::IllegalDataValue);
    // The homing registers are the drive's 0x6098 / 0x607C / 0x6099 / 0x609A: a method it
    // has reads back, one it lacks (36, reserved) or outside INTEGER8 is refused.
    let hm = M.homing_method.unwrap();
    assert_eq!(read(&mut c, hm, 1).await, [35]);
    write1(&mut c, hm, 17).await;
    assert_eq!(read(&mut c, hm, 1).await, [17]);
    assert_eq!(exception(c.write_single_register(hm, 36).await).await, ExceptionCode::IllegalDataValue);
    assert_eq!(exception(c.write_single_register(hm, 200).await).await, ExceptionCode::IllegalDataValue);
    write(&mut c, M.home_offset.unwrap(), &M.word_order.split_i32(-20_000)).await;
    let r = read(&mut c, M.home_offset.unwrap(), 2).await;
    assert_eq!(M.word_order.join_i32([r[0], r[1]]), -20_000);
    assert_eq!(exception(c.write_multiple_registers(M.homing_zero_speed.unwrap(), &[0, 0]).await).await, ExceptionCode::IllegalDataValue);
    // 0x03: quantity 0 or above 125 registers.
    assert_eq!(exception(c.read_holding_registers(0, 126).await).await, ExceptionCode::IllegalDataValue);
    assert_eq!(exception(c.read_holding_registers(0, 0).await).await, ExceptionCode::IllegalDataValue);
    // 0x01: functions the drive does not have.
    assert_eq!(exception(c.read_coils(0, 1).await).await, ExceptionCode::IllegalFunction);
    assert_eq!(exception(c.write_single_coil(0, true).await).await, ExceptionCode::IllegalFunction);
    assert_eq!(exception(c.masked_write_register(0, 0xFFFF, 0).await).await, ExceptionCode::IllegalFunction);
    // Valid requests still work after all that, on the same connection.
    assert_eq!(read(&mut c, M.mode, 1).await, vec![0]);
    // 0x0B: a unit id no drive has (the TCP server is a gateway to units 1, 2, 3).
    let mut c9 = s.client(9).await;
    assert_eq!(exception(c9.read_holding_registers(M.statusword, 1).await).await, ExceptionCode::GatewayTargetDevice);
    assert_eq!(s.server().units().len(), 3);
}

fn one_drive(node: u8, f: impl FnOnce(&mut DriveConfig)) -> SimConfig {
    let mut d = DriveConfig::new(node, DriveKind::Linear, "x", 10_000.0);
    f(&mut d);
    SimConfig { drives: vec![d], step_us: 50 }
}

#[tokio::test(flavor = "current_thread")]
async fn word_order_high_and_low_first() {
    let mut cfg = one_drive(1, |_| {});
    let mut low = DriveConfig::new(2, DriveKind::Linear, "z", 10_000.0);
    low.cia402_map.word_order = WordOrder::LowFirst;
    cfg.drives.push(low);
    let s = Srv::start(cfg);
    for (unit, order) in [(1u8, WordOrder::HighFirst), (2, WordOrder::LowFirst)] {
        let mut c = s.client(unit).await;
        // Target position (not enabled: stored, not acted on) and the following-error window.
        let v = -0x1234_5678;
        let regs = order.split_i32(v);
        write(&mut c, M.target_position, &regs).await;
        assert_eq!(read(&mut c, M.target_position, 2).await, regs.to_vec());
        assert_eq!(s.server().with_drive(unit, |d| d.object(0x607A, 0)).flatten(), Some(v as i64), "{order:?}");
        write(&mut c, M.following_error_window, &order.split_i32(0x0001_0002)).await;
        assert_eq!(s.server().with_drive(unit, |d| d.object(0x6065, 0)).flatten(), Some(0x0001_0002), "{order:?}");
        // Half of a 32-bit register keeps the other half.
        write1(&mut c, M.target_position + if order == WordOrder::HighFirst { 1 } else { 0 }, 0x9999).await;
        assert_eq!(s.server().with_drive(unit, |d| d.object(0x607A, 0)).flatten(), Some(((v as u32 & 0xFFFF_0000) | 0x9999) as i32 as i64));
    }
    assert_eq!(WordOrder::LowFirst.split_i32(-0x1234_5678), [0xA988, 0xEDCB]);
}

#[tokio::test(flavor = "current_thread")]
async fn moved_map_serves_its_addresses() {
    let s = Srv::start(one_drive(5, |d| {
        d.cia402_map = Cia402Map { controlword: 100, statusword: 200, ..Cia402Map::default() };
    }));
    let mut c = s.client(5).await;
    tokio::time::sleep(Duration::from_millis(10)).await;
    assert_eq!(state(read(&mut c, 200, 1).await[0]), State::SwitchOnDisabled);
    write1(&mut c, 100, cw::SHUTDOWN).await;
    assert_eq!(state(read(&mut c, 200, 1).await[0]), State::ReadyToSwitchOn);
    assert_eq!(exception(c.read_holding_registers(10, 1).await).await, ExceptionCode::IllegalDataAddress);
}

const P: PrMap = PrMap {
    block: 0x6200,
    trigger: 0x6002,
    trigger_value: 0x0010,
    servo_on: 0x0405,
    status: 0x6003,
    position_actual: 0x602A,
    alarm_code: Some(0x2203),
    alarm_reset: 0x0033,
    comm_timeout_ms: Some(0x0050),
    word_order: WordOrder::HighFirst,
    reads: cncgw_bus::modbus::ReadBlocks::Auto,
    // Master side only (rpm ↔ counts); the drive uses its own counts per revolution.
    counts_per_rev: 100_000,
};

async fn pr_move(c: &mut Context, pos: i32, rpm: u16) {
    write(c, P.block, &pr_block(pos, rpm, 50, 50, 0, P.word_order)).await;
    write1(c, P.trigger, P.trigger_value).await;
}

/// Poll the PR status until `f` holds (or panic after `ms`).
async fn pr_wait(c: &mut Context, ms: u64, what: &str, f: impl Fn(u16) -> bool) -> u16 {
    let t0 = Instant::now();
    loop {
        let s = read(c, P.status, 1).await[0];
        if f(s) {
            return s;
        }
        assert!(t0.elapsed() < Duration::from_millis(ms), "{what}: status {s:#06x} after {ms} ms");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

#[tokio::test(flavor = "current_thread")]
async fn pr_profile_moves_retargets_and_times_out() {
    let s = Srv::start(one_drive(4, |d| d.modbus_profile = Profile::Pr));
    let mut c = s.client(4).await;
    tokio::time::sleep(Duration::from_millis(10)).await;
    assert_eq!(read(&mut c, P.status, 1).await[0], 0);
    write1(&mut c, P.servo_on, 1).await;
    pr_wait(&mut c, 100, "servo on", |s| s & pr_status::ENABLED != 0).await;
    let p0 = read_i32(&mut c, P.position_actual, P.word_order).await;

    // 50 000 counts (half a motor turn) at 600 rpm = 1 000 000 counts/s … capped by the
    // distance: a triangle. It runs, then is in position.
    pr_move(&mut c, p0 + 50_000, 600).await;
    let st = read(&mut c, P.status, 1).await[0];
    assert!(st & pr_status::RUNNING != 0, "status {st:#06x}");
    pr_wait(&mut c, 2000, "in position", |s| s & pr_status::IN_POSITION != 0 && s & pr_status::RUNNING == 0).await;
    let p = read_i32(&mut c, P.position_actual, P.word_order).await;
    assert!((p - (p0 + 50_000)).abs() <= 10, "at {p}");

    // Streaming: a new block + trigger every 4 ms retargets the running move.
    let t0 = Instant::now();
    let mut k = 0;
    while t0.elapsed() < Duration::from_millis(300) {
        let target = p + 200 * k;
        pr_move(&mut c, target, 3000).await;
        k += 1;
        tokio::time::sleep(Duration::from_millis(4)).await;
    }
    let last = p + 200 * (k - 1);
    pr_wait(&mut c, 2000, "streamed target", |s| s & pr_status::IN_POSITION != 0).await;
    let pe = read_i32(&mut c, P.position_actual, P.word_order).await;
    assert!((pe - last).abs() <= 10, "at {pe}, last target {last}");
    // A retarget behind a running move brakes and comes back.
    pr_move(&mut c, pe + 400_000, 3000).await;
    tokio::time::sleep(Duration::from_millis(60)).await;
    pr_move(&mut c, pe - 1000, 3000).await;
    pr_wait(&mut c, 3000, "retarget back", |s| s & pr_status::IN_POSITION != 0).await;
    let pb = read_i32(&mut c, P.position_actual, P.word_order).await;
    assert!((pb - (pe - 1000)).abs() <= 10, "at {pb}");

    // Comm timeout: no write for 50 ms while on → alarm 0x8130, power stage off.
    write1(&mut c, P.comm_timeout_ms.unwrap(), 50).await;
    let st = pr_wait(&mut c, 500, "comm timeout alarm", |s| s & pr_status::FAULT != 0).await;
    assert_eq!(st & pr_status::ENABLED, 0);
    assert_eq!(read(&mut c, P.alarm_code.unwrap(), 1).await[0], COMM_TIMEOUT_CODE);
    // A trigger while in alarm does nothing.
    pr_move(&mut c, pb + 10_000, 3000).await;
    assert_eq!(read(&mut c, P.status, 1).await[0] & pr_status::RUNNING, 0);
    // Servo-on is a level, as the servo-on input: still 1, it enables again after the reset.
    assert_eq!(read(&mut c, P.servo_on, 1).await[0], 1);
    write1(&mut c, P.comm_timeout_ms.unwrap(), 0).await;
    tokio::time::sleep(Duration::from_millis(100)).await; // the fault reaction's stop
    write1(&mut c, P.alarm_reset, 1).await;
    let st = pr_wait(&mut c, 500, "alarm reset", |s| s & pr_status::FAULT == 0).await;
    assert_eq!(read(&mut c, P.alarm_code.unwrap(), 1).await[0], 0);
    pr_wait(&mut c, 100, "enabled again", |s| s & pr_status::ENABLED != 0).await;
    let _ = st;
    write1(&mut c, P.servo_on, 0).await;
    pr_wait(&mut c, 100, "servo off", |s| s & pr_status::ENABLED == 0).await;
    // Servo off while in alarm: the reset leaves it off.
    write1(&mut c, P.comm_timeout_ms.unwrap(), 30).await;
    write1(&mut c, P.servo_on, 1).await;
    pr_wait(&mut c, 500, "alarm again", |s| s & pr_status::FAULT != 0).await;
    write1(&mut c, P.servo_on, 0).await;
    write1(&mut c, P.comm_timeout_ms.unwrap(), 0).await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    write1(&mut c, P.alarm_reset, 1).await;
    tokio::time::sleep(Duration::from_millis(20)).await;
    assert_eq!(read(&mut c, P.status, 1).await[0], 0);
}

#[tokio::test(flavor = "current_thread")]
async fn exceptions_pr() {
    let s = Srv::start(one_drive(4, |d| d.modbus_profile = Profile::Pr));
    let mut c = s.client(4).await;
    let ex = |r: tokio_modbus::Result<()>| match r {
        Ok(Err(e)) => e,
        other => panic!("expected an exception, got {other:?}"),
    };
    assert_eq!(ex(c.write_single_register(P.servo_on, 2).await), ExceptionCode::IllegalDataValue);
    assert_eq!(ex(c.write_single_register(P.trigger, 0x11).await), ExceptionCode::IllegalDataValue);
    assert_eq!(ex(c.write_single_register(P.alarm_reset, 7).await), ExceptionCode::IllegalDataValue);
    // Block: mode must be absolute (1), speed 1…rated (3000 rpm).
    let mut b = pr_block(1000, 100, 50, 50, 0, P.word_order);
    b[0] = 2;
    assert_eq!(ex(c.write_multiple_registers(P.block, &b).await), ExceptionCode::IllegalDataValue);
    let b = pr_block(1000, 3001, 50, 50, 0, P.word_order);
    assert_eq!(ex(c.write_multiple_registers(P.block, &b).await), ExceptionCode::IllegalDataValue);
    let b = pr_block(1000, 0, 50, 50, 0, P.word_order);
    assert_eq!(ex(c.write_multiple_registers(P.block, &b).await), ExceptionCode::IllegalDataValue);
    // Read-only and unmapped registers; the block plus one register past it.
    assert_eq!(ex(c.write_single_register(P.status, 0).await), ExceptionCode::IllegalDataAddress);
    assert_eq!(ex(c.write_single_register(P.alarm_code.unwrap(), 0).await), ExceptionCode::IllegalDataAddress);
    assert_eq!(ex(c.write_multiple_registers(P.block, &[1, 0, 0, 100, 50, 50, 0, 0]).await), ExceptionCode::IllegalDataAddress);
    assert_eq!(exception(c.read_holding_registers(P.block, 8).await).await, ExceptionCode::IllegalDataAddress);
    // The CiA 402 addresses are not there on a PR drive.
    assert_eq!(exception(c.read_holding_registers(10, 1).await).await, ExceptionCode::IllegalDataAddress);
    // A good block reads back.
    let b = pr_block(-5, 1500, 20, 30, 40, P.word_order);
    write(&mut c, P.block, &b).await;
    assert_eq!(read(&mut c, P.block, 7).await, b.to_vec());
}

#[tokio::test(flavor = "current_thread")]
async fn scheduled_faults_show_in_the_error_code() {
    let stop = Arc::new(AtomicBool::new(false));
    let fault = sim_drives::parse_fault("2:raise=0x4310@300").unwrap();
    let t0 = Instant::now();
    let srv =
        sim_drives::modbus::serve_tcp_with_faults("127.0.0.1:0".parse().unwrap(), SimConfig::default_lathe(), vec![fault], stop.clone()).unwrap();
    let s = Srv { addr: srv.local_addr().unwrap(), srv: Some(srv), stop };
    let mut c = s.client(2).await;
    let before = read(&mut c, M.error_code.unwrap(), 1).await[0];
    // (A loaded machine may have taken the 300 ms already.)
    if t0.elapsed() < Duration::from_millis(250) {
        assert_eq!(before, 0);
    }
    tokio::time::sleep(Duration::from_millis(400).saturating_sub(t0.elapsed())).await;
    let r = read(&mut c, M.statusword, 7).await;
    assert_eq!(state(r[0]), State::Fault, "{:#06x}", r[0]);
    assert_eq!(r[6], 0x4310);
}

/// Transactions per second a client achieves against the server over TCP (loopback):
/// `cargo test --release -p sim-drives --test modbus_server -- --ignored --nocapture`.
#[tokio::test(flavor = "current_thread")]
#[ignore = "measurement; prints figures"]
async fn tcp_transaction_rate() {
    let s = Srv::start(SimConfig::default_lathe());
    for units in [1u8, 3] {
        let mut cs = Vec::new();
        for u in 1..=units {
            cs.push(s.client(u).await);
        }
        let n = 2000;
        let t0 = Instant::now();
        for _ in 0..n {
            for c in cs.iter_mut() {
                // The cyclic exchange of a CSP master: controlword + target, statusword … error code.
                c.read_write_multiple_registers(M.statusword, 7, M.controlword, &[0, 0, 0]).await.unwrap().unwrap();
            }
        }
        let dt = t0.elapsed().as_secs_f64();
        println!(
            "Modbus TCP, {units} drive(s): {:.0} FC23 transactions/s, one cycle for all drives {:.3} ms",
            (n * units as u32) as f64 / dt,
            dt / n as f64 * 1e3
        );
    }
}

/// A master on a slow or stalled link: each CSP target comes long after the previous one
/// (more than the 10 periods the drive extrapolates). Each is reached and held; the
/// catch-up step's speed is not extrapolated (it once was: every late target multiplied the
/// error by 10 until the following error tripped).
#[tokio::test(flavor = "current_thread")]
async fn csp_targets_far_apart_are_reached_without_runaway() {
    let s = Srv::start(SimConfig::default_lathe());
    let mut c = s.client(2).await;
    write1(&mut c, M.mode, 8).await;
    write1(&mut c, M.interpolation_ms.unwrap(), 2).await;
    enable(&mut c).await;
    let p0 = read_i32(&mut c, M.position_actual, M.word_order).await;
    for k in 1..=6 {
        let t = p0 + 10 * k;
        write(&mut c, M.target_position, &M.word_order.split_i32(t)).await;
        tokio::time::sleep(Duration::from_millis(50)).await;
        let r = read(&mut c, M.statusword, 7).await;
        assert_eq!(state(r[0]), State::OperationEnabled, "target {k}: statusword {:#06x}, error {:#06x}", r[0], r[6]);
        let p = M.word_order.join_i32([r[2], r[3]]);
        assert!((p - t).abs() <= 10, "target {k}: at {p}, target {t}");
    }
    let demand = s.server().with_drive(2, |d| d.position_demand()).unwrap();
    assert!((demand - (p0 + 60) as f64).abs() < 1.0, "demand {demand}, last target {}", p0 + 60);
}

/// PR streaming as cncgw's master does it: every link cycle one block to the cycle's target,
/// at the speed that covers the step in one cycle (+1 rpm) with ramps of one cycle, then the
/// trigger. The drive follows a 1 s move without an alarm and ends on the last target.
#[tokio::test(flavor = "current_thread")]
async fn pr_streamed_every_cycle_is_followed() {
    let s = Srv::start(one_drive(4, |d| d.modbus_profile = Profile::Pr));
    let mut c = s.client(4).await;
    tokio::time::sleep(Duration::from_millis(10)).await;
    write1(&mut c, P.servo_on, 1).await;
    pr_wait(&mut c, 100, "servo on", |s| s & pr_status::ENABLED != 0).await;
    let p0 = read_i32(&mut c, P.position_actual, P.word_order).await;
    let cycle_ms = 4.0;
    let mut tick = tokio::time::interval(Duration::from_millis(4));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let start = Instant::now();
    let target_at = |t: f64| p0 + (20_000.0 * (1.0 - (2.0 * std::f64::consts::PI * t.min(1.0)).cos())).round() as i32;
    let mut last = p0;
    let mut worst = 0i64;
    loop {
        tick.tick().await;
        let t = start.elapsed().as_secs_f64();
        let target = target_at(t);
        let delta = (target as i64 - last as i64).unsigned_abs() as f64;
        let rpm = (delta / 100_000.0 / (cycle_ms * 1e-3) * 60.0).ceil() + 1.0;
        write(&mut c, P.block, &pr_block(target, rpm.min(3000.0) as u16, 4, 4, 0, P.word_order)).await;
        write1(&mut c, P.trigger, P.trigger_value).await;
        last = target;
        let st = read(&mut c, P.status, 1).await[0];
        assert_eq!(st & pr_status::FAULT, 0, "alarm {:#06x} at {t:.3} s", read(&mut c, P.alarm_code.unwrap(), 1).await[0]);
        let a = read_i32(&mut c, P.position_actual, P.word_order).await;
        worst = worst.max((target as i64 - a as i64).abs());
        if t > 1.1 {
            break;
        }
    }
    pr_wait(&mut c, 1000, "in position", |s| s & pr_status::IN_POSITION != 0).await;
    let a = read_i32(&mut c, P.position_actual, P.word_order).await;
    assert!((a - last).abs() <= 10, "at {a}, last target {last}");
    // Peak 126 000 counts/s: ~1–2 cycles of travel behind the streamed target.
    assert!(worst < 3_000, "worst lag {worst} counts");
    println!("PR streamed at 4 ms: worst lag {worst} counts");
}
