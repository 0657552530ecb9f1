//! What the command line says (issue 19.11): `--bus` values that cannot be a bus are named
//! for what is wrong with them; a kernel without SocketCAN is said so; no colour codes go into
//! a file or a pipe (and NO_COLOR switches them off on a terminal too).

fn cncgw(args: &[&str]) -> (i32, String) {
    let o = testkit::cli!().run(args);
    (o.code, o.stderr)
}

#[test]
fn malformed_bus_values_say_what_is_wrong() {
    for (bus, says) in [
        ("can0:1", "not a SocketCAN interface name"),
        ("a-name-longer-than-fifteen", "not a SocketCAN interface name"),
        ("foo://bar", "unknown kind of bus `foo://`"),
        ("socketcand://host-only", "socketcand://HOST:PORT/IFACE"),
    ] {
        let (code, err) = cncgw(&["scan", "--bus", bus]);
        assert_eq!(code, 4, "{bus}: {err}");
        assert!(err.contains(says), "{bus}: {err}");
        assert!(!err.contains("ip link"), "no advice for a CAN interface that does not apply: {err}");
    }
}

#[test]
fn a_kernel_without_socketcan_is_named() {
    // SAFETY: a probe socket, closed at once.
    let fd = unsafe { libc::socket(libc::AF_CAN, libc::SOCK_RAW, 1) };
    let no_can = fd < 0 && std::io::Error::last_os_error().raw_os_error() == Some(libc::EAFNOSUPPORT);
    if fd >= 0 {
        unsafe { libc::close(fd) };
    }
    let (code, err) = cncgw(&["scan", "--bus", "vcan9"]);
    assert_eq!(code, 4, "{err}");
    if no_can {
        assert!(err.contains("this kernel has no SocketCAN"), "{err}");
    } else {
        assert!(err.contains("vcan9") && err.contains("ip link"), "{err}");
    }
}

#[test]
fn no_colour_codes_go_into_a_pipe() {
    let (_, err) = cncgw(&["-v", "run", "--batch", concat!(env!("CARGO_MANIFEST_DIR"), "/examples/first_part.nc")]);
    assert!(err.contains("INFO"), "the log is there: {err}");
    assert!(!err.contains('\u{1b}'), "escape codes in a pipe: {err:?}");
}

#[test]
fn a_missing_file_is_exit_2_for_every_command() {
    for args in [
        &["run", "--batch", "/nonexistent/part.nc"][..],
        &["plan", "/nonexistent/part.nc"],
        &["trace", "plot", "/nonexistent/t.csv", "-o", "/tmp/never.svg"],
        &["preview", "/nonexistent/part.nc", "-o", "/tmp/never.svg"],
        &["config", "check", "/nonexistent/machine.toml"],
    ] {
        let (code, err) = cncgw(args);
        assert_eq!(code, 2, "{args:?}: {err}");
    }
}
