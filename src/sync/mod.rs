//! Spindle–axis synchronization (threading, rigid tapping) and its error monitor.

pub mod angle_filter;
pub mod correction;
pub mod governor;
pub mod identify;
pub mod lag;
pub mod lag_tracker;
pub mod link_check;
pub mod monitor;
pub mod overload;
pub mod ring_guard;
pub mod sample_time;
pub mod thread;
pub mod torque_margin;

pub use thread::ThreadSync;
