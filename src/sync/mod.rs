//! Spindle–axis synchronization (threading, rigid tapping) and its error monitor.

pub mod link_check;
pub mod thread;

pub use thread::ThreadSync;
