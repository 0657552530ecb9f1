//! What start-up reads from a drive before it configures or moves it: the modes it has
//! (0x6502), whether it produces SYNC itself (0x1005), its position scaling (factor group
//! 0x608F / 0x6091 / 0x6092) and polarity (0x607E), checked against the axis config. Also the
//! same facts for `cncgw scan` (`DriveProbe`).

use super::explain::{is_absent, mode_short, supported_modes_text, supports};
use super::{CanOpenMaster, Sdo};
use crate::config::Polarity;
use crate::drives::canopen::sdo_client::SdoError;
use crate::Alarm;
use cncgw_bus::canopen::od;
use cncgw_bus::{CanBus, Clock};

/// Alarm: the drive lacks the mode, or did not confirm it (0x6061), or left it while running.
pub const ALARM_MODE: u32 = crate::alarm::DRIVE_MODE;
/// Alarm: the drive's position scaling or polarity disagrees with the axis config.
pub const ALARM_SCALING: u32 = crate::alarm::DRIVE_SCALING;
/// Alarm: another SYNC producer or master on the bus.
pub const ALARM_FOREIGN: u32 = crate::alarm::FOREIGN_MASTER;

/// 0x1005 bit 30: the node produces SYNC.
pub const SYNC_PRODUCER_BIT: u32 = 0x4000_0000;

/// A drive's factor group and polarity, each `None` where the drive lacks the object.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Scaling {
    /// 0x608F: encoder increments per motor revolutions.
    pub encoder: Option<(u32, u32)>,
    /// 0x6091: motor revolutions per shaft revolutions.
    pub gear: Option<(u32, u32)>,
    /// 0x6092: feed (position units) per shaft revolutions.
    pub feed: Option<(u32, u32)>,
    /// 0x607E.
    pub polarity: Option<u8>,
}

impl Scaling {
    /// Position units per motor revolution, where the drive says: from gear and feed, or
    /// (without them) its encoder resolution, positions then being increments.
    pub fn units_per_rev(&self) -> Option<f64> {
        match (self.gear, self.feed, self.encoder) {
            (Some((gm, gs)), Some((f, fr)), _) if gm > 0 && fr > 0 => Some(f as f64 / fr as f64 * gs as f64 / gm as f64),
            (None, None, Some((inc, rev))) if rev > 0 => Some(inc as f64 / rev as f64),
            _ => None,
        }
    }

    /// Encoder increments per position unit (1 = positions in increments).
    pub fn increments_per_unit(&self) -> Option<f64> {
        let (inc, rev) = self.encoder?;
        let upr = self.units_per_rev()?;
        (rev > 0 && upr > 0.0).then(|| inc as f64 / rev as f64 / upr)
    }

    /// 0x6092:1 that would make the position unit one encoder increment.
    fn feed_for_increments(&self) -> Option<f64> {
        let (inc, rev) = self.encoder?;
        let (gm, gs) = self.gear.unwrap_or((1, 1));
        let fr = self.feed.map_or(1, |f| f.1);
        (rev > 0 && gm > 0).then(|| inc as f64 / rev as f64 * gm as f64 / gs as f64 * fr as f64)
    }

    /// "0x608F 100000 inc / 1 rev, 0x6091 1:1, 0x6092 10000 / 1 rev, 0x607E 0x00".
    pub fn describe(&self) -> String {
        let mut v = Vec::new();
        if let Some((i, r)) = self.encoder {
            v.push(format!("0x608F {i} inc / {r} rev"));
        }
        if let Some((m, s)) = self.gear {
            v.push(format!("0x6091 gear {m}:{s}"));
        }
        if let Some((f, r)) = self.feed {
            v.push(format!("0x6092 feed {f} / {r} rev"));
        }
        if let Some(p) = self.polarity {
            v.push(format!("0x607E 0x{p:02X}"));
        }
        if v.is_empty() {
            "no factor group objects".into()
        } else {
            v.join(", ")
        }
    }

    /// The position unit in words, for `scan`.
    pub fn unit_text(&self) -> String {
        match self.increments_per_unit() {
            Some(f) if (f - 1.0).abs() < 1e-9 => "encoder increments".into(),
            Some(f) => format!("1 unit = {} increments", fmt_num(f)),
            None => match self.units_per_rev() {
                Some(u) => format!("{} units / motor rev", fmt_num(u)),
                None => "unknown (no factor group)".into(),
            },
        }
    }
}

/// A number without a useless fraction.
pub fn fmt_num(x: f64) -> String {
    if (x - x.round()).abs() < 1e-9 {
        format!("{}", x.round() as i64)
    } else {
        format!("{x:.6}").trim_end_matches('0').to_string()
    }
}

/// Check a drive's scaling against the axis config: `counts_per_unit` (position units per
/// mm or degree), `travel_per_rev` (mm or degrees per motor revolution, optional) and the
/// polarity. Err: the alarm text (without the node prefix). Ok: a note for the log.
pub fn check_scaling(
    s: &Scaling,
    axis: &str,
    counts_per_unit: f64,
    travel_per_rev: Option<f64>,
    polarity: Polarity,
    spindle: bool,
) -> Result<String, String> {
    let pos_inverted = s.polarity.map(|p| p & 0x80 != 0);
    let want_inverted = polarity == Polarity::Inverted;
    if let Some(inv) = pos_inverted {
        if inv != want_inverted {
            return Err(if inv {
                format!("the drive inverts positions (0x607E = 0x{:02X}, bit 7): the axis would move against the programmed direction. Clear bit 7 of 0x607E in the drive, or, if the machine was commissioned so, set axes.{axis}.polarity = \"inverted\"", s.polarity.unwrap_or(0))
            } else {
                format!("axes.{axis}.polarity = \"inverted\" but the drive does not invert positions (0x607E = 0x{:02X}): the axis would move against the programmed direction. Set bit 7 of 0x607E in the drive, or remove the key", s.polarity.unwrap_or(0))
            });
        }
        if spindle && s.polarity.is_some_and(|p| (p & 0x40 != 0) != inv) {
            return Err(format!(
                "the drive's velocity polarity (0x607E bit 6) differs from its position polarity (bit 7), 0x607E = 0x{:02X}: in speed mode the spindle would turn the other way. Set bit 6 equal to bit 7",
                s.polarity.unwrap_or(0)
            ));
        }
    }
    let unit = if spindle { "°" } else { " mm" };
    match travel_per_rev {
        Some(t) => {
            let Some(upr) = s.units_per_rev() else {
                return Ok(format!("axes.{axis}.travel_per_rev is set but the drive has no factor group to check it against ({})", s.describe()));
            };
            let want = upr / t;
            if ((counts_per_unit - want) / want).abs() > 1e-6 {
                return Err(format!(
                    "the drive counts {} position units per motor revolution ({}), that is {} per{unit} with axes.{axis}.travel_per_rev = {}{unit}; counts_per_unit = {} would move the axis {}× the programmed travel. Set axes.{axis}.counts_per_unit = {}",
                    fmt_num(upr),
                    s.describe(),
                    fmt_num(want),
                    fmt_num(t),
                    fmt_num(counts_per_unit),
                    fmt_num(counts_per_unit / want),
                    fmt_num(want)
                ));
            }
            Ok(format!("scaling checked: {} units / motor rev = {} × {}{unit}", fmt_num(upr), fmt_num(counts_per_unit), fmt_num(t)))
        }
        None => match s.increments_per_unit() {
            Some(f) if (f - 1.0).abs() > 1e-9 => {
                let fix = s
                    .feed_for_increments()
                    .map(|fi| format!(", or set the drive's feed constant 0x6092:1 = {} so that it counts increments", fmt_num(fi)))
                    .unwrap_or_default();
                let upr = s.units_per_rev().unwrap_or(0.0);
                Err(format!(
                    "the drive scales positions: 1 position unit = {} encoder increments ({}), so its positions are not the encoder counts counts_per_unit = {} assumes; the axis would move {}× the programmed travel. Set axes.{axis}.counts_per_unit = {} (the drive's units per{unit}){fix}. If counts_per_unit is already in the drive's units, say so with axes.{axis}.travel_per_rev = {} ({}{unit} per motor revolution) and start-up checks it",
                    fmt_num(f),
                    s.describe(),
                    fmt_num(counts_per_unit),
                    fmt_num(f),
                    fmt_num(counts_per_unit / f),
                    fmt_num(upr / counts_per_unit),
                    fmt_num(upr / counts_per_unit)
                ))
            }
            Some(_) => Ok(format!("positions in encoder increments ({})", s.describe())),
            None => Ok(format!("position scaling not checkable ({}); counts_per_unit is taken as given", s.describe())),
        },
    }
}

/// What to do about a drive without the cyclic mode asked for: the other cyclic position
/// mode where 0x6502 lists it, else another drive.
fn mode_advice(axis: &str, bits: u32, want: i8) -> String {
    use cncgw_bus::cia402::mode;
    match want {
        mode::CYCLIC_SYNC_POSITION if supports(bits, mode::INTERPOLATED_POSITION) => {
            format!("it has interpolated position: set axes.{axis}.mode = \"ip\"")
        }
        mode::INTERPOLATED_POSITION if supports(bits, mode::CYCLIC_SYNC_POSITION) => {
            format!("it has CSP: remove axes.{axis}.mode (or set \"csp\")")
        }
        _ => "cncgw runs a position axis in CSP (8) or IP (7, axes.NAME.mode = \"ip\"): use a drive (or firmware) with one of them".into(),
    }
}

/// What `cncgw scan` shows of a node beyond its identity. `Err` texts are the failure in
/// words ("absent" for a missing object).
#[derive(Clone, Debug, Default)]
pub struct DriveProbe {
    pub supported_modes: Option<Result<u32, String>>,
    pub mode_display: Option<Result<i8, String>>,
    pub sync_cob: Option<Result<u32, String>>,
    pub scaling: Scaling,
    pub producer_heartbeat_ms: Option<Result<u16, String>>,
    /// 0x1016 entries (producer node, ms) that are set.
    pub consumer_heartbeat: Option<Result<Vec<(u8, u16)>, String>>,
    pub guard_time_ms: Option<Result<u16, String>>,
    pub life_time_factor: Option<Result<u8, String>>,
}

fn absent_or<T>(r: Result<T, SdoError>) -> Option<Result<T, String>> {
    match r {
        Err(SdoError::Abort { code }) if is_absent(code) => None,
        r => Some(r.map_err(|e| e.to_string())),
    }
}

impl<B: CanBus> CanOpenMaster<B> {
    fn read_uint(&mut self, clock: &mut dyn Clock, i: usize, ix: u16, sub: u8) -> Result<u32, SdoError> {
        self.read_u32(clock, i, ix, sub)
    }

    /// The factor group and polarity of node `i`; absent objects stay `None`, other
    /// failures are errors.
    pub(super) fn read_scaling(&mut self, clock: &mut dyn Clock, i: usize) -> Result<Scaling, (u16, u8, SdoError)> {
        let mut s = Scaling::default();
        let mut pair = |m: &mut Self, ix: u16| -> Result<Option<(u32, u32)>, (u16, u8, SdoError)> {
            let a = match m.read_uint(clock, i, ix, 1) {
                Err(SdoError::Abort { code }) if is_absent(code) => return Ok(None),
                r => r.map_err(|e| (ix, 1, e))?,
            };
            let b = m.read_uint(clock, i, ix, 2).map_err(|e| (ix, 2, e))?;
            Ok(Some((a, b)))
        };
        s.encoder = pair(self, od::ENCODER_RESOLUTION)?;
        s.gear = pair(self, od::GEAR_RATIO)?;
        s.feed = pair(self, od::FEED_CONSTANT)?;
        s.polarity = match self.read_uint(clock, i, od::POLARITY, 0) {
            Err(SdoError::Abort { code }) if is_absent(code) => None,
            r => Some(r.map_err(|e| (od::POLARITY, 0, e))? as u8),
        };
        Ok(s)
    }

    /// Start-up: node `i` has the mode the master will ask for (0x6502, where present).
    pub(super) fn check_supported_mode(&mut self, clock: &mut dyn Clock, i: usize, want: i8) -> Result<(), Alarm> {
        match self.read_uint(clock, i, od::SUPPORTED_MODES, 0) {
            Ok(bits) if !supports(bits, want) => Err(self.node_alarm(
                i,
                ALARM_MODE,
                format!(
                    "this drive has no {} mode: its supported drive modes 0x6502 = 0x{bits:08X} list {}; {}",
                    mode_short(want),
                    supported_modes_text(bits),
                    mode_advice(&self.nodes[i].spec.axis, bits, want)
                ),
            )),
            Ok(_) => Ok(()),
            Err(SdoError::Abort { code }) if is_absent(code) => {
                tracing::info!(
                    node = self.nodes[i].spec.node,
                    "no 0x6502 (supported drive modes): the mode is checked by writing it and reading 0x6061"
                );
                Ok(())
            }
            Err(e) => {
                tracing::warn!(node = self.nodes[i].spec.node, "reading 0x6502 failed ({e}); the mode is checked by writing it and reading 0x6061");
                Ok(())
            }
        }
    }

    /// Start-up: node `i` must not produce SYNC (0x1005 bit 30): this master does.
    pub(super) fn check_not_sync_producer(&mut self, clock: &mut dyn Clock, i: usize) -> Result<(), Alarm> {
        match self.read_uint(clock, i, od::COB_ID_SYNC, 0) {
            Ok(v) if v & SYNC_PRODUCER_BIT != 0 => Err(self.sync_producer_alarm(clock, i, v)),
            Ok(_) => Ok(()),
            Err(SdoError::Abort { code }) if is_absent(code) => Ok(()),
            Err(e) => {
                Err(self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("reading 0x1005 (COB-ID SYNC: does the drive produce SYNC?) failed: {e}")))
            }
        }
    }

    /// Alarm 2007 for node `i` that produces SYNC (0x1005 = `cob`), naming its period.
    pub(super) fn sync_producer_alarm(&mut self, clock: &mut dyn Clock, i: usize, cob: u32) -> Alarm {
        let period = self
            .read_uint(clock, i, od::COMM_CYCLE_PERIOD, 0)
            .ok()
            .filter(|&p| p > 0)
            .map(|p| format!(", every {} ms (0x1006)", fmt_num(p as f64 / 1000.0)))
            .unwrap_or_default();
        let node = self.nodes[i].spec.node;
        self.node_alarm(
            i,
            ALARM_FOREIGN,
            format!(
                "the drive produces SYNC itself (0x1005 = 0x{cob:08X}, bit 30{period}); with this master's SYNC the drives would see two and fault. Make it a SYNC consumer: clear bit 30 (`cncgw sdo write {node} 0x1005 0 --type u32 0x{:X}`, and store it in the drive, 0x1010) — nothing was enabled",
                cob & !SYNC_PRODUCER_BIT
            ),
        )
    }

    /// Start-up: the factor group and polarity of node `i` fit its axis config.
    pub(super) fn check_node_scaling(&mut self, clock: &mut dyn Clock, i: usize) -> Result<Scaling, Alarm> {
        let s = self.read_scaling(clock, i).map_err(|(ix, sub, e)| {
            self.node_alarm(i, crate::alarm::SDO_CONFIG, format!("reading the factor group 0x{ix:04X}:{sub:02X} failed: {e}"))
        })?;
        let spec = &self.nodes[i].spec;
        match check_scaling(&s, &spec.axis, spec.counts_per_unit, spec.travel_per_rev, spec.polarity, spec.spindle) {
            Ok(note) => {
                tracing::info!(node = spec.node, axis = %spec.axis, "{note}");
                Ok(s)
            }
            Err(msg) => Err(self.node_alarm(i, ALARM_SCALING, msg)),
        }
    }

    /// Modes, SYNC producer, factor group, heartbeat and guarding of `node` for `cncgw scan`.
    /// Reads only.
    pub fn probe(&mut self, clock: &mut dyn Clock, node: u8) -> DriveProbe {
        self.ensure_node(node);
        let Some(i) = self.index_of(node) else {
            return DriveProbe::default();
        };
        let mut p = DriveProbe {
            supported_modes: absent_or(self.read_uint(clock, i, od::SUPPORTED_MODES, 0)),
            mode_display: absent_or(self.read_uint(clock, i, od::MODES_DISPLAY, 0).map(|v| v as u8 as i8)),
            sync_cob: absent_or(self.read_uint(clock, i, od::COB_ID_SYNC, 0)),
            producer_heartbeat_ms: absent_or(self.read_uint(clock, i, od::PRODUCER_HEARTBEAT, 0).map(|v| v as u16)),
            guard_time_ms: absent_or(self.read_uint(clock, i, od::GUARD_TIME, 0).map(|v| v as u16)),
            life_time_factor: absent_or(self.read_uint(clock, i, od::LIFE_TIME_FACTOR, 0).map(|v| v as u8)),
            ..DriveProbe::default()
        };
        p.scaling = self.read_scaling(clock, i).unwrap_or_default();
        p.consumer_heartbeat = match self.read_uint(clock, i, od::CONSUMER_HEARTBEAT, 0) {
            Err(SdoError::Abort { code }) if is_absent(code) => None,
            Err(e) => Some(Err(e.to_string())),
            Ok(n) => {
                let mut v = Vec::new();
                for s in 1..=(n.min(127) as u8) {
                    if let Ok(x) = self.sdo(clock, i, Sdo::Up(od::CONSUMER_HEARTBEAT, s)).map(|d| super::le_u32(&d)) {
                        if x & 0xFFFF != 0 && (x >> 16) & 0xFF != 0 {
                            v.push((((x >> 16) & 0xFF) as u8, (x & 0xFFFF) as u16));
                        }
                    }
                }
                Some(Ok(v))
            }
        };
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fg(inc: u32, gear: (u32, u32), feed: u32, pol: u8) -> Scaling {
        Scaling { encoder: Some((inc, 1)), gear: Some(gear), feed: Some((feed, 1)), polarity: Some(pol) }
    }

    #[test]
    fn scaling_in_increments_passes_and_user_units_are_refused_with_the_fix() {
        // 100000 increments per revolution, feed = increments: positions in increments.
        let inc = fg(100_000, (1, 1), 100_000, 0);
        assert_eq!(inc.increments_per_unit(), Some(1.0));
        assert!(check_scaling(&inc, "x", 10_000.0, None, Polarity::Normal, false).is_ok());
        // Feed 10000 per revolution on a 10 mm screw: 1 unit = 1 µm = 10 increments.
        let um = fg(100_000, (1, 1), 10_000, 0);
        let e = check_scaling(&um, "x", 10_000.0, None, Polarity::Normal, false).unwrap_err();
        assert!(e.starts_with("the drive scales positions: 1 position unit = 10 encoder increments (0x608F 100000 inc / 1 rev, 0x6091 gear 1:1, 0x6092 feed 10000 / 1 rev, 0x607E 0x00)"), "{e}");
        assert!(e.contains("move 10× the programmed travel. Set axes.x.counts_per_unit = 1000"), "{e}");
        assert!(e.contains("0x6092:1 = 100000"), "{e}");
        assert!(e.contains("axes.x.travel_per_rev = 1 "), "{e}");
        // With the travel per revolution the check is exact both ways.
        assert!(check_scaling(&um, "x", 1000.0, Some(10.0), Polarity::Normal, false).is_ok());
        let e = check_scaling(&um, "x", 10_000.0, Some(10.0), Polarity::Normal, false).unwrap_err();
        assert!(
            e.contains("counts 10000 position units per motor revolution")
                && e.contains("move the axis 10× the programmed travel. Set axes.x.counts_per_unit = 1000"),
            "{e}"
        );
        // A gearbox 3:1 in front of a 5 mm screw, positions in increments (feed = 3 × 131072
        // increments per shaft revolution): 131072 per motor revolution of 5/3 mm.
        let geared = fg(131_072, (3, 1), 393_216, 0);
        assert_eq!(geared.increments_per_unit(), Some(1.0));
        assert!(check_scaling(&geared, "z", 131_072.0 * 3.0 / 5.0, Some(5.0 / 3.0), Polarity::Normal, false).is_ok());
        // The gear forgotten in counts_per_unit: 3× the travel.
        let e = check_scaling(&geared, "z", 131_072.0 / 5.0, Some(5.0 / 3.0), Polarity::Normal, false).unwrap_err();
        assert!(e.contains("move the axis 0.333333× the programmed travel"), "{e}");
    }

    #[test]
    fn polarity_is_checked() {
        let inv = fg(100_000, (1, 1), 100_000, 0x80);
        let e = check_scaling(&inv, "z", 10_000.0, None, Polarity::Normal, false).unwrap_err();
        assert!(e.starts_with("the drive inverts positions (0x607E = 0x80, bit 7)"), "{e}");
        assert!(check_scaling(&inv, "z", 10_000.0, None, Polarity::Inverted, false).is_ok());
        let e = check_scaling(&inv, "s1", 1000.0, None, Polarity::Inverted, true).unwrap_err();
        assert!(e.contains("velocity polarity"), "{e}");
        let none = Scaling::default();
        assert!(check_scaling(&none, "x", 10_000.0, None, Polarity::Normal, false).unwrap().contains("not checkable"));
    }
}
