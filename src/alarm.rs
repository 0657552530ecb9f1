//! Alarms: every failure a user can cause or meet is a numbered alarm with a message that
//! says what to do and, where there is one, the source position and block text.
//!
//! Numbers: the manuals' numbers where they give one (e.g. 3605). Where they are silent we
//! use Fanuc 0i-TF numbers (PS0010 "improper G-code" → 10, …) and our own ranges:
//! 1000–1099 configuration, 2000–2199 CANopen / drives, 2200–2299 Modbus, 2300–2399 sync and
//! motion, 2400–2499 controller (watchdog, E-stop).

use crate::canon::SrcPos;

/// A thread of the controller (interpreter, state writer) could not be started.
pub const NO_THREAD: u32 = 2406;
/// G51.2/G50.2 on a machine without a tool spindle (Fanuc: PS0218-class "polygon axis not
/// set"; ours in the motion range).
pub const NO_TOOL_SPINDLE: u32 = 2308;
use std::fmt;

#[derive(Clone, Debug, PartialEq)]
pub struct Alarm {
    pub number: u32,
    pub message: String,
    pub pos: Option<SrcPos>,
    /// The offending block's text, for program errors.
    pub block: Option<String>,
}

impl Alarm {
    pub fn new(number: u32, message: impl Into<String>) -> Self {
        Alarm { number, message: message.into(), pos: None, block: None }
    }
    pub fn at(mut self, pos: SrcPos) -> Self {
        self.pos = Some(pos);
        self
    }
    pub fn with_block(mut self, block: impl Into<String>) -> Self {
        self.block = Some(block.into());
        self
    }
}

impl fmt::Display for Alarm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(p) = &self.pos {
            write!(f, "{p}: ")?;
        }
        write!(f, "alarm {:04}: {}", self.number, self.message)?;
        if let Some(b) = &self.block {
            let col = self.pos.as_ref().map_or(1, |p| p.col as usize);
            write!(f, "\n    {}", echo(b.trim_end(), col))?;
        }
        Ok(())
    }
}

/// At most this many characters of a block are echoed in an alarm.
pub const ECHO_CHARS: usize = 120;

/// The block as an alarm shows it: non-printing characters escaped (`\x00`), and a block
/// longer than [`ECHO_CHARS`] cut to a window around the alarm's column, the cuts marked
/// with how much was left out (a 2 MB line must not flood the terminal or the log).
pub fn echo(block: &str, col: usize) -> String {
    let n = block.chars().count();
    let start = if n <= ECHO_CHARS { 0 } else { col.saturating_sub(1 + ECHO_CHARS / 2).min(n - ECHO_CHARS) };
    let end = (start + ECHO_CHARS).min(n);
    let mut out = String::new();
    if start > 0 {
        out.push_str(&format!("[{start} characters cut] …"));
    }
    for ch in block.chars().skip(start).take(end - start) {
        if ch == '\t' {
            out.push(' ');
        } else if ch.is_control() {
            out.extend(ch.escape_default());
        } else {
            out.push(ch);
        }
    }
    if end < n {
        out.push_str(&format!("… [{} characters cut]", n - end));
    }
    out
}

impl std::error::Error for Alarm {}
