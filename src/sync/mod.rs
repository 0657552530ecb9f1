//! Spindle–axis synchronization (threading, rigid tapping) and its error monitor.
