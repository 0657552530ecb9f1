//! What the machine-I/O tests (io_run in simulated time, io_process with sim-drives as a
//! process) share: the safety inputs and the M codes of their machines' `[io]`.

/// `[io.safety]` on the inputs `estop_ok`, `door_closed`, `chuck_clamped`; M08/M09 switching
/// `coolant`; M10 clamping the chuck and waiting for its switch.
pub const SAFETY_AND_M_CODES: &str = r#"[io.safety]
estop = "estop_ok"
door = "door_closed"
chuck = "chuck_clamped"
[io.m.8]
set = ["coolant"]
[io.m.9]
clear = ["coolant"]
[io.m.10]
set = ["chuck_clamp"]
wait_on = ["chuck_clamped"]"#;
