//! The fuzz entry functions: one per cargo-fuzz target (fuzz/fuzz_targets/*.rs) and the
//! same functions replayed over every corpus and crash input by the normal test suite
//! (tests/interp/fuzz_regress.rs includes this file with `#[path]`), so the harness exists once.
//!
//! Each takes arbitrary bytes and must return without panicking; errors (alarms, parse
//! errors) are the expected outcome for most inputs. Every entry bounds its own work, so no
//! input can hang the fuzzer: the interpreter by a block and a move budget, the others are
//! linear in the input.
//!
//! Only `cncgw` is used (its `bus` re-export is the `cncgw-bus` crate), so this file
//! compiles both inside the fuzz crate and as a module of a `cncgw` integration test.

use cncgw::bus::canopen::{eds::Eds, emcy, nmt, pdo, sdo};
use cncgw::bus::{cia402, modbus, socketcand, CanFrame};
use cncgw::config::MachineConfig;
use cncgw::interp::{parse_tool_table, Interpreter, ToolTable};
use std::sync::OnceLock;

/// A fuzz entry: arbitrary bytes in, no panic.
pub type Entry = fn(&[u8]);

/// The targets, by name (also their corpus directories under fuzz/corpus and fuzz/crashes).
pub const TARGETS: &[(&str, Entry)] = &[("interp", interp), ("config", config), ("eds", eds), ("frames", frames)];

/// Moves taken from one program at most.
pub const MAX_MOVES: usize = 1_000;
/// Blocks without a move before the endless-loop alarm (2500). The default, 2,000,000, is
/// right for a machine and takes seconds; the fuzzer wants thousands of inputs a second.
pub const MAX_IDLE_BLOCKS: u64 = 20_000;
/// Inputs longer than this are cut (libFuzzer is also run with -max_len=4096).
pub const MAX_INPUT: usize = 16 * 1024;

fn cfg() -> &'static MachineConfig {
    static CFG: OnceLock<MachineConfig> = OnceLock::new();
    CFG.get_or_init(|| {
        // Reference points 2–4 configured so that G30 P2–P4 run, not only alarm; a G22 area
        // in the parameters so that a bare G22 switches the stroke check on.
        let text = format!(
            "{}\n1241 = {{ x = 200.0, z = 50.0 }}\n1242 = {{ x = 100.0, z = 0.0 }}\n1243 = {{ x = 0.0, z = -10.0 }}\n1360 = 280000\n1362 = 0\n1370 = 200000\n1372 = -20000\n",
            cncgw::config::EMBEDDED_LATHE
        );
        MachineConfig::from_toml("fuzz.toml", &text).expect("fuzz config is valid")
    })
}

fn tools() -> &'static ToolTable {
    static T: OnceLock<ToolTable> = OnceLock::new();
    T.get_or_init(|| {
        parse_tool_table("tools.toml", "[1]\nx = -10.0\nz = 5.0\nr = 0.4\ntip = 3\n[2]\nx = 2.0\nz = -1.0").expect("fuzz tool table is valid")
    })
}

fn text(data: &[u8]) -> std::borrow::Cow<'_, str> {
    String::from_utf8_lossy(&data[..data.len().min(MAX_INPUT)])
}

/// Part program text → the whole canonical-move stream (bounded: [`MAX_MOVES`] moves,
/// [`MAX_IDLE_BLOCKS`] blocks without a move), then the pre-motion limit check of
/// `cncgw run` over the same program. Returns the number of moves taken.
pub fn interp_moves(data: &[u8]) -> usize {
    let text = text(data);
    let cfg = cfg();
    let Ok(mut it) = Interpreter::from_source("fuzz.nc", &text, cfg) else { return 0 };
    it.set_endless_loop_limit(MAX_IDLE_BLOCKS);
    it.set_tool_table(tools().clone());
    // Alternate the M91/M92 input so both branches are explored.
    let mut flip = false;
    it.set_input_source(move |_| {
        flip = !flip;
        flip
    });
    let mut n = 0;
    for m in it.by_ref().take(MAX_MOVES) {
        match m {
            Ok(_) => n += 1,
            Err(a) => {
                // Every alarm says where.
                assert!(a.number > 0, "alarm without a number: {a}");
                break;
            }
        }
    }
    // The same program through the check `cncgw run` makes before the first move.
    if let Ok(mut it) = Interpreter::from_source("fuzz.nc", &text, cfg) {
        it.set_endless_loop_limit(MAX_IDLE_BLOCKS);
        it.set_tool_table(tools().clone());
        let limits = cncgw::motion::Limits::from_config(cfg);
        let _ = cncgw::control::guard::check_program(it.by_ref().take(MAX_MOVES), &limits, cncgw::canon::Pos::ZERO);
    }
    n
}

pub fn interp(data: &[u8]) {
    interp_moves(data);
}

/// Machine configuration TOML → validated config, and what the run builds from it.
pub fn config(data: &[u8]) {
    let text = text(data);
    let Ok(cfg) = MachineConfig::from_toml("fuzz.toml", &text) else { return };
    // A validated config must be usable by everything that reads it.
    let _ = cncgw::motion::Limits::from_config(&cfg);
    let _ = cncgw::control::guard::Guard::from_limits(&cncgw::motion::Limits::from_config(&cfg));
    let _ = cncgw::control::cycle::Watchdog::from_config(&cfg);
    let _ = cncgw::drives::canopen::master::NodeSpec::from_config(&cfg);
    let _ = cfg.spindle();
    let _ = cfg.has_canopen();
    for a in cfg.axes.values() {
        let _ = a.pdo_cob_ids();
    }
    for (name, a) in &cfg.axes {
        if a.modbus.is_some() {
            let map = a.cia402_map.unwrap_or_default();
            let pr = a.pr_map.unwrap_or_default();
            let window = (a.following_error * a.counts_per_unit).abs().min(u32::MAX as f64) as u32;
            let mut d = cncgw::drives::modbus::plan::DrivePlan::new(name, a.node, a.modbus_profile, map, pr, false, window);
            let _ = d.timing_writes((cfg.machine.cycle_ms.ceil() as u16).max(1), 100);
        }
    }
    // Programs see the parameters (G22 area, reference points, increment system…).
    let _ = Interpreter::from_source("p.nc", "G22\nG28 U0 W0\nG30 P2 U0\nX10 Z-1\nM30\n", &cfg).map(|it| it.take(10).count());
}

/// EDS (CiA 306) text → parsed file, and the checks start-up runs against it.
pub fn eds(data: &[u8]) {
    let text = text(data);
    let Ok(e) = Eds::parse("fuzz.eds", &text) else { return };
    let keys: Vec<(u16, u8)> = e.entries.keys().take(64).copied().collect();
    for (ix, sub) in keys {
        let _ = e.describe(ix, sub);
        let _ = e.check_write(ix, sub, 4);
        let _ = e.check_map(ix, sub, 32, true);
        let _ = e.check_map(ix, sub, 16, false);
    }
    // What the master writes and maps at start-up, as `check_eds` does.
    let bus = cncgw::bus::transport::inproc::InprocBus::new();
    let master = cncgw::drives::canopen::master::CanOpenMaster::new(bus.endpoint(), cfg());
    for node in [1u8, 2, 3] {
        let _ = master.check_eds(node, &e);
    }
}

/// Little reader over the fuzz bytes; past the end it yields zeros.
struct Bytes<'a>(&'a [u8]);
impl Bytes<'_> {
    fn u8(&mut self) -> u8 {
        let (b, rest) = self.0.split_first().map_or((0, &[][..]), |(b, r)| (*b, r));
        self.0 = rest;
        b
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes([self.u8(), self.u8()])
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.u8(), self.u8(), self.u8(), self.u8()])
    }
}

/// One CAN frame through every decoder a master or a drive applies to received frames.
fn decode_frame(f: &CanFrame) {
    let _ = format!("{f}");
    if let Some(r) = sdo::SdoRequest::decode(f) {
        assert!(sdo::SdoRequest::decode(&r.encode(f.cob_id() as u8 & 0x7F)).is_some(), "{f}: re-encoded SDO request decodes");
    }
    if let Some(r) = sdo::SdoResponse::decode(f) {
        let _ = r.encode(1);
        if let sdo::SdoResponse::Abort { code, .. } = r {
            let _ = sdo::abort_text(code);
        }
    }
    if let Some(r) = sdo::BlockRequest::decode(f) {
        let _ = r.encode(1);
    }
    if let Some(r) = sdo::BlockResponse::decode(f) {
        let _ = r.encode(1);
    }
    if let Some(s) = sdo::BlockSegment::decode(f) {
        let _ = s.encode_request(1);
        let _ = sdo::crc16(&s.data);
    }
    if let Some((node, e)) = emcy::Emcy::decode(f) {
        let _ = e.frame(node);
        let _ = emcy::error_text(e.code);
        let _ = emcy::error_register_text(e.register);
    }
    if let Some((c, node)) = nmt::NmtCommand::decode(f) {
        let _ = c.frame(node);
    }
    if let Some((node, st)) = nmt::decode_heartbeat(f) {
        let _ = nmt::heartbeat_frame(node, st);
        let _ = st.name();
    }
    // PDO payloads: the master's TPDO1 layout (statusword, position actual) and a mapping entry.
    let d = f.data();
    if d.len() >= 6 {
        let sw = pdo::get_u16(d, 0);
        let _ = pdo::get_i32(d, 2);
        let st = cia402::State::from_statusword(sw);
        let _ = st.name();
        let _ = st.controlword_towards(cia402::State::OperationEnabled);
    }
    if d.len() >= 4 {
        let e = pdo::MapEntry::decode(u32::from_le_bytes([d[0], d[1], d[2], d[3]]));
        assert_eq!(pdo::MapEntry::decode(e.encode()), e);
        let _ = pdo::mapped_len(&[e, e]);
    }
    let _ = cncgw::bus::canopen::cob::split(f.cob_id());
}

/// CANopen frames (12-byte records: id, flags, length, 8 data bytes) through every decoder
/// and the CiA 402 words, and to sim-drives' emulated drives; then the rest of the input as
/// a socketcand byte stream and as a Modbus register map with the registers read back.
pub fn frames(data: &[u8]) {
    let data = &data[..data.len().min(MAX_INPUT)];
    let split = (data.first().copied().unwrap_or(0) as usize * 12).min(data.len().saturating_sub(1));
    let (can, rest) = data.get(1..).map_or((&[][..], &[][..]), |d| d.split_at(split.min(d.len())));
    // CAN: a frame never has more than 8 bytes (the transports guarantee it).
    let mut enabler = cia402::Enabler::default();
    let mut state = cia402::State::SwitchOnDisabled;
    let mut prev_cw = 0u16;
    for rec in can.chunks(12) {
        let mut b = Bytes(rec);
        let id = b.u32();
        let flags = b.u8();
        let len = b.u8() % 9;
        let mut d = [0u8; 8];
        for x in d.iter_mut() {
            *x = b.u8();
        }
        let extended = flags & 1 != 0;
        let f = CanFrame { id: if extended { id & 0x1FFF_FFFF } else { id & 0x7FF }, extended, rtr: flags & 2 != 0, len, data: d };
        decode_frame(&f);
        // The CiA 402 words: a statusword into the master's enable walk, a controlword into
        // the drive's state machine.
        let sw = u16::from_le_bytes([d[0], d[1]]);
        let _ = enabler.step(sw);
        let cw = u16::from_le_bytes([d[2], d[3]]);
        state = cia402::device_transition(state, cw, prev_cw);
        prev_cw = cw;
        let _ = cia402::QuickStopOption::from_code(i16::from_le_bytes([d[4], d[5]]));
        let _ = cia402::mode::name(d[6] as i8);
    }
    to_emulated_drives(can);
    socketcand_stream(rest);
    modbus_map(rest);
}

/// The same frames sent to sim-drives' emulated drives (SDO server, NMT, RPDOs, SYNC, the
/// 0x2100 fault object): a bad request is an SDO abort, never a panic; every SDO answer
/// must decode.
fn to_emulated_drives(can: &[u8]) {
    use cncgw::bus::Clock;
    static SIM: OnceLock<sim_drives::SimConfig> = OnceLock::new();
    let sim = SIM.get_or_init(|| sim_drives::SimConfig::from_machine_toml(cncgw::config::EMBEDDED_LATHE).expect("embedded config"));
    let wire = cncgw::bus::transport::inproc::InprocBus::new();
    let mut world = sim_drives::SimWorld::new(&wire, sim.clone());
    let mut ep = wire.endpoint();
    // Let the drives boot (their boot-up message comes at once).
    let mut t = world.now_ns() + 1_000_000;
    world.wait_until(t);
    for rec in can.chunks(12).take(64) {
        let mut b = Bytes(rec);
        let id = b.u32() & 0x7FF;
        let _flags = b.u8();
        let len = b.u8() % 9;
        let mut d = [0u8; 8];
        for x in d.iter_mut() {
            *x = b.u8();
        }
        let f = CanFrame { id, extended: false, rtr: false, len, data: d };
        let _ = cncgw::bus::CanBus::send(&mut ep, &f);
        t += 1_000_000;
        world.wait_until(t);
        while let Ok(Some(r)) = cncgw::bus::CanBus::try_recv(&mut ep) {
            let (func, _) = cncgw::bus::canopen::cob::split(r.cob_id());
            if func == cncgw::bus::canopen::cob::SDO_TX && r.len == 8 {
                assert!(
                    sdo::SdoResponse::decode(&r).is_some() || sdo::BlockResponse::decode(&r).is_some() || sdo::BlockSegment::decode(&r).is_some(),
                    "the emulated drive answered {f} with {r}, which no SDO decoder reads"
                );
            }
        }
    }
}

/// The socketcand protocol as received from a TCP peer (split anywhere).
fn socketcand_stream(data: &[u8]) {
    let mut s = socketcand::Splitter::default();
    for chunk in data.chunks(7) {
        s.push(chunk);
        while let Some(m) = s.next_msg() {
            let t = socketcand::format(&m);
            // What we format must parse back to the same message (socketcand peers echo).
            if let (socketcand::Msg::Send(_) | socketcand::Msg::Frame(..), Some(body)) = (&m, t.strip_prefix('<').and_then(|t| t.strip_suffix('>'))) {
                assert_eq!(socketcand::parse(body), m, "{t}");
            }
        }
    }
}

/// A Modbus drive's register map (from the bytes) and its cyclic exchange decoded from
/// registers (the rest of the bytes).
fn modbus_map(data: &[u8]) {
    use cncgw::drives::modbus::link::Command;
    use cncgw::drives::modbus::plan::{pr_statusword, DrivePlan};
    let mut b = Bytes(data);
    let flags = b.u8();
    let order = if flags & 1 == 0 { modbus::WordOrder::HighFirst } else { modbus::WordOrder::LowFirst };
    // The same bytes as before the split reads and the optional registers: the corpus
    // stays meaningful; 0xFFFF is an optional register's "none".
    let reads =
        [modbus::ReadBlocks::Auto, modbus::ReadBlocks::Span, modbus::ReadBlocks::Contiguous, modbus::ReadBlocks::Single][(flags as usize >> 1) & 3];
    let opt = |v: u16| (v != u16::MAX).then_some(v);
    let cia = modbus::Cia402Map {
        controlword: b.u16(),
        target_position: b.u16(),
        target_velocity: b.u16(),
        mode: b.u16(),
        statusword: b.u16(),
        mode_display: b.u16(),
        position_actual: b.u16(),
        velocity_actual: b.u16(),
        error_code: opt(b.u16()),
        interpolation_ms: opt(b.u16()),
        following_error_window: b.u16(),
        comm_timeout_ms: opt(b.u16()),
        word_order: order,
        reads,
        // The homing registers are not in the cycle: the default ones (no bytes taken, so
        // the corpus keeps its meaning).
        ..modbus::Cia402Map::default()
    };
    let pr = modbus::PrMap {
        block: b.u16(),
        trigger: b.u16(),
        trigger_value: b.u16(),
        servo_on: b.u16(),
        status: b.u16(),
        position_actual: b.u16(),
        alarm_code: opt(b.u16()),
        alarm_reset: b.u16(),
        comm_timeout_ms: opt(b.u16()),
        word_order: order,
        reads,
        counts_per_rev: b.u32(),
    };
    let sel = b.u8();
    let profile = if sel & 1 == 0 { modbus::Profile::Cia402 } else { modbus::Profile::Pr };
    let mut d = DrivePlan::new("x", 1, profile, cia, pr, sel & 2 != 0, b.u32());
    let _ = d.timing_writes(b.u16(), b.u32());
    let t = modbus::SerialTiming { baud: b.u32(), parity: sel & 4 != 0, stop_bits: b.u8() };
    let _ = t.transaction_s(b.u16() as usize, b.u16() as usize, 0.001);
    let mut prev = None;
    for _ in 0..4 {
        let cmd = Command {
            controlword: b.u16(),
            servo_on: sel & 8 != 0,
            alarm_reset_seq: b.u8() as u32,
            target: b.u32() as i32,
            stream: sel & 16 != 0,
            ..Command::default()
        };
        for (x, w) in d.cyclic_writes(&cmd) {
            let _ = x.describe();
            let _ = x.rtu_bytes();
            let _ = w.len();
            let n = b.u8() as usize % 32;
            let regs: Vec<u16> = (0..n).map(|_| b.u16()).collect();
            prev = d.decode(&x, &regs, prev);
        }
        let _ = pr_statusword(b.u16());
    }
}
