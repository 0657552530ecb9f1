//! Spindle–axis synchronization (threading, rigid tapping) and its error monitor.

pub mod thread;

pub use thread::ThreadSync;
