//! Tool offsets (the operator's "offset" page) and the T code `T□□△△`: □□ = tool
//! (turret station), △△ = offset number, so T0101 selects tool 1 with offset 1 and T0100 or
//! T0 cancels the offset (the manual's examples: `G00 X176 Z10 M3 S500 T0202` "换2号刀,
//! 执行2号刀偏"; it has no T code section of its own).
//!
//! The manual does not say how the offset moves the axes; we do what a Fanuc 0i-TF does with
//! No.5002#4 LGT = 0 (geometry and wear both applied by shifting the coordinates) and
//! No.5002#6 LWM = 1 (the offset is applied with axis movement): the T block itself moves
//! nothing, and each axis takes up the new offset with the next block that programs it
//! (X/U, Z/W, Y/V). A T in a block with motion therefore applies in that block. Geometry and
//! wear are both taken from the offset number (Fanuc No.5002#1 LGN = 1); with No.5002
//! configured and #1 = 0 the geometry is taken from the tool number instead, as Fanuc does.

use crate::canon::Pos;
use crate::Alarm;
use std::collections::BTreeMap;

/// Fanuc PS0030 "illegal offset number": the T code names an offset that is not in the table.
pub const ILLEGAL_OFFSET_ALARM: u32 = 30;

/// One offset number of the tool table. X values are diameters, as on the offset page.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ToolOffset {
    /// Geometry X (diameter, mm) and Z (mm).
    pub x: f64,
    pub z: f64,
    /// Wear X (diameter, mm) and Z (mm), added to the geometry.
    pub wear_x: f64,
    pub wear_z: f64,
    /// Nose radius R (mm) for tool nose radius compensation (G41/G42).
    pub r: f64,
    /// Imaginary tool tip 0–9 (manual figs. 2.63/2.64).
    pub tip: u8,
}

/// The tool offset table, by offset number (1–99).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ToolTable {
    pub offsets: BTreeMap<u32, ToolOffset>,
}

/// The tool selected by the last T code, for tool nose radius compensation.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ActiveTool {
    /// T□□: tool (turret station) number.
    pub tool: u32,
    /// T△△: offset number; 0 = no offset.
    pub offset: u32,
    /// Nose radius (mm) and imaginary tip of the offset number (0 and 0 without offset).
    pub nose_radius: f64,
    pub tip: u8,
}

impl ToolTable {
    /// Machine shift (X as a radius) for geometry number `geo` and wear number `wear`;
    /// number 0 contributes nothing. `None` if a non-zero number is not in a non-empty
    /// table. An empty table (none loaded) reads as all zeros, like a fresh offset memory.
    pub fn shift(&self, geo: u32, wear: u32) -> Option<Pos> {
        let get = |n: u32| -> Option<ToolOffset> {
            if n == 0 || self.offsets.is_empty() {
                Some(ToolOffset::default())
            } else {
                self.offsets.get(&n).copied()
            }
        };
        let g = get(geo)?;
        let w = get(wear)?;
        Some(Pos { x: (g.x + w.wear_x) / 2.0, z: g.z + w.wear_z, ..Pos::ZERO })
    }

    pub fn get(&self, n: u32) -> Option<&ToolOffset> {
        self.offsets.get(&n)
    }
}

/// Read a tool table from TOML text, one section per offset number:
///
/// ```toml
/// [1]            # offset number (T0101 uses it)
/// x = -152.300   # geometry X, diameter (mm)
/// z = -310.450   # geometry Z (mm)
/// wear_x = 0.02  # wear X, diameter (mm)
/// wear_z = -0.01
/// r = 0.4        # nose radius (mm)
/// tip = 3        # imaginary tool tip 0–9
/// ```
/// Missing keys are zero. Errors are configuration alarms (1000) naming the key.
pub fn parse_tool_table(file: &str, text: &str) -> Result<ToolTable, Alarm> {
    let bad = |m: String| Alarm::new(crate::config::ConfigError::ALARM, format!("{file}: {m}"));
    let v: toml::Table = toml::from_str(text).map_err(|e| bad(e.to_string()))?;
    let mut out = ToolTable::default();
    for (k, val) in &v {
        let n = k
            .parse::<u32>()
            .ok()
            .filter(|n| (1..=99).contains(n))
            .ok_or_else(|| bad(format!("[{k}]: sections are offset numbers 1–99, e.g. [1] for T0101")))?;
        let t = val.as_table().ok_or_else(|| bad(format!("{k}: must be a table like [{k}] x = -150.0 z = -300.0")))?;
        let mut o = ToolOffset::default();
        for (key, nv) in t {
            let x = match nv {
                toml::Value::Float(f) => *f,
                toml::Value::Integer(i) => *i as f64,
                other => return Err(bad(format!("{k}.{key}: must be a number, got {other}"))),
            };
            if !x.is_finite() {
                return Err(bad(format!("{k}.{key}: must be finite")));
            }
            match key.as_str() {
                "x" => o.x = x,
                "z" => o.z = x,
                "wear_x" => o.wear_x = x,
                "wear_z" => o.wear_z = x,
                "r" if x >= 0.0 => o.r = x,
                "r" => return Err(bad(format!("{k}.r: the nose radius must be >= 0, got {x}"))),
                "tip" if x.fract() == 0.0 && (0.0..=9.0).contains(&x) => o.tip = x as u8,
                "tip" => return Err(bad(format!("{k}.tip: the imaginary tool tip is 0–9, got {x}"))),
                _ => return Err(bad(format!("{k}.{key}: the keys are x, z (diameter/length), wear_x, wear_z, r, tip"))),
            }
        }
        out.offsets.insert(n, o);
    }
    Ok(out)
}

/// [`parse_tool_table`] from a file.
pub fn load_tool_table(path: &std::path::Path) -> Result<ToolTable, Alarm> {
    let text =
        std::fs::read_to_string(path).map_err(|e| Alarm::new(crate::config::ConfigError::ALARM, format!("{}: cannot read: {e}", path.display())))?;
    parse_tool_table(&path.display().to_string(), &text)
}
