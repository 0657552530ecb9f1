//! Real-time scheduling of the calling thread, shared by the cycle thread (`cncgw::motion::rt`)
//! and the threads that feed it (the Modbus link threads).

/// Put the calling thread on SCHED_FIFO at `priority` (1–99). The OS's refusal (no root,
/// no CAP_SYS_NICE, no rtprio limit) as its text.
#[cfg(target_os = "linux")]
pub fn fifo_current_thread(priority: i32) -> Result<(), String> {
    if !(1..=99).contains(&priority) {
        return Err(format!("SCHED_FIFO priorities are 1–99, got {priority}"));
    }
    let param = libc::sched_param { sched_priority: priority };
    // SAFETY: pthread_self is always valid for the calling thread; param lives across the call.
    let r = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if r == 0 {
        Ok(())
    } else {
        Err(std::io::Error::from_raw_os_error(r).to_string())
    }
}

#[cfg(not(target_os = "linux"))]
pub fn fifo_current_thread(priority: i32) -> Result<(), String> {
    Err(format!("SCHED_FIFO is implemented for Linux only; priority {priority} ignored"))
}
