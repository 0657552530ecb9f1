//! sim-drives' socketcand server against cncgw's socketcand client transport and against a
//! raw TCP peer that checks the bytes on the wire.

use cncgw_bus::transport::socketcand::Socketcand;
use cncgw_bus::{CanBus, CanFrame};
use sim_drives::socketcand::SocketcandServer;
use sim_drives::{run_realtime, SimConfig};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn recv_until(c: &mut dyn CanBus, want: impl Fn(&CanFrame) -> bool) -> Option<CanFrame> {
    let deadline = Instant::now() + Duration::from_secs(3);
    while Instant::now() < deadline {
        if let Ok(Some(f)) = c.recv_timeout(Duration::from_millis(50)) {
            if want(&f) {
                return Some(f);
            }
        }
    }
    None
}

fn wait_clients(s: &SocketcandServer, n: usize) {
    let deadline = Instant::now() + Duration::from_secs(3);
    while s.clients() < n && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(s.clients(), n);
    // Frames flow after the join settle time.
    std::thread::sleep(Duration::from_millis(40));
}

#[test]
fn two_cncgw_clients_and_the_drives_side_see_each_others_frames() {
    let mut server = SocketcandServer::bind("127.0.0.1:0", "can0").unwrap();
    let addr = server.local_addr().to_string();
    let mut a = Socketcand::connect(&addr, "can0").unwrap();
    let mut b = Socketcand::connect(&addr, "can0").unwrap();
    wait_clients(&server, 2);

    let f = CanFrame::new(0x201, &[1, 2, 3, 4, 5, 6]);
    a.send(&f).unwrap();
    assert_eq!(recv_until(&mut b, |x| x.id == 0x201), Some(f), "client b sees client a's frame");
    assert_eq!(recv_until(&mut server, |x| x.id == 0x201), Some(f), "the drives see it");
    let sync = CanFrame::new(0x80, &[]);
    b.send(&sync).unwrap();
    assert_eq!(recv_until(&mut a, |x| x.id == 0x80), Some(sync), "zero-length frames survive");
    // A sender does not get its own frame back (as on a CAN socket without loopback).
    let t = Instant::now();
    let mut echoed = false;
    while t.elapsed() < Duration::from_millis(300) {
        echoed |= matches!(b.recv_timeout(Duration::from_millis(20)), Ok(Some(x)) if x.id == 0x80);
    }
    assert!(!echoed);

    let tpdo = CanFrame::new(0x181, &[0x37, 0x02, 0xE8, 0x03, 0, 0]);
    server.send(&tpdo).unwrap();
    assert_eq!(recv_until(&mut a, |x| x.id == 0x181), Some(tpdo));
    assert_eq!(recv_until(&mut b, |x| x.id == 0x181), Some(tpdo));
}

#[test]
fn wire_format_is_socketcands_exactly() {
    let server = SocketcandServer::bind("127.0.0.1:0", "can0").unwrap();
    let mut s = TcpStream::connect(server.local_addr()).unwrap();
    assert!(s.nodelay().is_ok());
    s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let mut buf = [0u8; 256];
    let mut read = |s: &mut TcpStream| {
        let n = s.read(&mut buf).unwrap();
        String::from_utf8_lossy(&buf[..n]).into_owned()
    };
    assert_eq!(read(&mut s), "< hi >");
    s.write_all(b"< open vcan9 >").unwrap();
    assert!(read(&mut s).starts_with("< error "), "another bus name is refused");
    s.write_all(b"< send 080 0  >").unwrap();
    assert!(read(&mut s).starts_with("< error "), "no frames before open + rawmode");
    s.write_all(b"< open can0 >").unwrap();
    assert_eq!(read(&mut s), "< ok >");
    s.write_all(b"< rawmode >").unwrap();
    assert_eq!(read(&mut s), "< ok >", "the < ok > comes alone");

    // A second client sends a SYNC and an SDO response with lowercase, unpadded bytes
    // (python-can's format); the first sees them in socketcand's.
    let mut peer = Socketcand::connect(&server.local_addr().to_string(), "can0").unwrap();
    std::thread::sleep(Duration::from_millis(40));
    peer.send(&CanFrame::new(0x80, &[])).unwrap();
    let mut raw = TcpStream::connect(server.local_addr()).unwrap();
    raw.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let mut b2 = [0u8; 64];
    let _ = raw.read(&mut b2).unwrap();
    raw.write_all(b"< open can0 >").unwrap();
    let _ = raw.read(&mut b2).unwrap();
    raw.write_all(b"< rawmode >").unwrap();
    let _ = raw.read(&mut b2).unwrap();
    raw.write_all(b"< send 581 8 43 18 10 1 a7 c 0 0 >").unwrap();

    let mut text = String::new();
    let deadline = Instant::now() + Duration::from_secs(2);
    while text.matches('>').count() < 2 && Instant::now() < deadline {
        text.push_str(&read(&mut s));
    }
    let mut msgs: Vec<&str> = text.split_inclusive('>').collect();
    assert_eq!(msgs.len(), 2, "{text}");
    // Two clients' frames: the server keeps each client's order, not the order between them.
    msgs.sort();
    let sync = msgs[0];
    assert!(sync.starts_with("< frame 080 ") && sync.ends_with("  >"), "{sync}");
    let ts = &sync["< frame 080 ".len()..sync.len() - 3];
    let (sec, usec) = ts.split_once('.').unwrap();
    assert!(sec.len() >= 10 && usec.len() == 6 && ts.chars().all(|c| c.is_ascii_digit() || c == '.'), "{ts}");
    let sdo = msgs[1];
    assert!(sdo.starts_with("< frame 581 ") && sdo.ends_with(" 43181001A70C0000 >"), "{sdo}");
}

#[test]
fn drives_answer_through_the_server() {
    let server = SocketcandServer::bind("127.0.0.1:0", "can0").unwrap();
    let addr = server.local_addr().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let st = stop.clone();
    let sim = std::thread::spawn(move || run_realtime(Box::new(server), SimConfig::default_lathe(), st));
    let mut c = Socketcand::connect(&addr, "can0").unwrap();
    std::thread::sleep(Duration::from_millis(50));
    // Read 0x1000 of node 1 (expedited upload).
    c.send(&CanFrame::new(0x601, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0])).unwrap();
    let r = recv_until(&mut c, |f| f.id == 0x581).expect("SDO response from node 1");
    assert_eq!(r.data(), &[0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]);
    stop.store(true, Ordering::Relaxed);
    sim.join().unwrap().unwrap();
}

#[test]
fn a_client_that_speaks_at_once_gets_the_answers_at_once() {
    // cncgw's master resets the nodes right after the handshake and waits for the boot-ups
    // (1–3 ms later): the join settle time must not swallow them.
    let server = SocketcandServer::bind("127.0.0.1:0", "can0").unwrap();
    let addr = server.local_addr().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let st = stop.clone();
    let sim = std::thread::spawn(move || run_realtime(Box::new(server), SimConfig::default_lathe(), st));
    std::thread::sleep(Duration::from_millis(20)); // the drives' own boot
    let mut c = Socketcand::connect(&addr, "can0").unwrap();
    c.send(&CanFrame::new(0x000, &[0x82, 0x00])).unwrap(); // NMT reset communication, all
    let t0 = Instant::now();
    let mut boot = Vec::new();
    while boot.len() < 3 && t0.elapsed() < Duration::from_secs(1) {
        if let Ok(Some(f)) = c.recv_timeout(Duration::from_millis(10)) {
            if (0x701..=0x703).contains(&f.id) && f.data() == [0] {
                boot.push(f.id);
            }
        }
    }
    // Frames held back for the settle time would be lost, not late: all three must come.
    assert_eq!(boot, vec![0x701, 0x702, 0x703]);
    stop.store(true, Ordering::Relaxed);
    sim.join().unwrap().unwrap();
}
