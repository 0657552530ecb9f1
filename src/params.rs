//! The manuals' parameters this controller reads (`[parameters]` of the machine
//! configuration, keyed by number): the one list, so that a number it does not know — a typo
//! such as 5621 for 5261 — is refused instead of silently ignored, and the values that have a
//! range are checked before anything runs.

/// (number, what it sets, allowed range of the value or of every bit field: None = any
/// finite number).
pub type Param = (u32, &'static str, Option<(f64, f64)>);

/// Every parameter this controller reads.
pub const KNOWN: &[Param] = &[
    (10, "0: G21 metric at power-on, 1: G20 inch", Some((0.0, 1.0))),
    (721, "largest tool spindle speed in polygon turning, rpm", Some((0.0, 1e5))),
    (1002, "bit 0: G22 forbids the outside (1) or the inside (0) of the area", None),
    (1240, "reference point 1 (G28), per axis: { x = …, z = … }, X a diameter", None),
    (1241, "reference point 2 (G30 P2), per axis", None),
    (1242, "reference point 3 (G30 P3), per axis", None),
    (1243, "reference point 4 (G30 P4), per axis", None),
    (1421, "rapid rate at rapid override F0, mm/min (unset: rapids stand at F0)", Some((0.0, 1e6))),
    (1360, "stored stroke limit 2 (G22), + boundary X, 0.001 mm from the reference point", None),
    (1361, "stored stroke limit 2, + boundary Y", None),
    (1362, "stored stroke limit 2, + boundary Z", None),
    (1370, "stored stroke limit 2, − boundary X", None),
    (1371, "stored stroke limit 2, − boundary Y", None),
    (1372, "stored stroke limit 2, − boundary Z", None),
    (1772, "bell-shaped acc/dec time constant before interpolation, ms (0 = off)", Some((0.0, 1000.0))),
    (3401, "bit 0: calculator-type decimal input (1) or least increment (0)", None),
    (3403, "bit 5: G02/G03 without R or I/K is an alarm (1)", None),
    (3410, "arc radius error limit, mm", Some((0.0, 100.0))),
    (5002, "tool offset bits (#4 LGT, #6 LWM)", None),
    (5101, "G83/G87 peck mode (0 high-speed peck, 1 peck)", None),
    (5110, "drilling clamp M code (0 = none)", Some((0.0, 999.0))),
    (5111, "dwell after unclamp, ms", Some((0.0, 1e6))),
    (5113, "G83/G87 return d, mm", Some((0.0, 1e3))),
    (5130, "G92/G76 run-out, 0.1 × lead", Some((0.0, 127.0))),
    (5131, "G92/G76 run-out angle, degrees (0 = 45°)", Some((0.0, 89.0))),
    (5139, "G76 e: finishing allowance, mm", Some((0.0, 1e3))),
    (5140, "G76 Δdmin: minimum cut, mm", Some((0.0, 1e3))),
    (5141, "G76 d: finishing allowance, mm", Some((0.0, 1e3))),
    (5142, "G76 m: finishing passes", Some((0.0, 99.0))),
    (5143, "G76 a: tool angle, degrees", Some((0.0, 99.0))),
    (5144, "G73 Δi / G78 infeed mode", None),
    (5145, "G73 Δk / G78 depth mode", None),
    (5146, "G73 d: passes", Some((0.0, 1e4))),
    (5147, "G71/G72 Δd: depth of cut, mm", Some((0.0, 1e3))),
    (5148, "G71/G72 e: retract, mm", Some((0.0, 1e3))),
    (5153, "power-on motion mode: 0 G00, 1 G01", Some((0.0, 1.0))),
    (5154, "power-on feed mode: 0 G98, 1 G99", Some((0.0, 1.0))),
    (5155, "bit 0: drilling mode kept through reset", None),
    (5170, "reverse rigid tapping", None),
    (5200, "rigid tapping bits (#0 mode selection, #2 exact stop, #4 pull-out override, #6 feed hold, #7 E/M24–M27)", None),
    (5201, "rigid tapping bits (#3 override unit, #4)", None),
    (5202, "rigid tapping bits (#6)", None),
    (5209, "rigid tapping bits (#0)", None),
    (5210, "rigid tapping M code (0 = M29)", Some((0.0, 255.0))),
    (5211, "rigid tapping pull-out override, %", Some((0.0, 2000.0))),
    (5213, "high-speed peck return d of G84/G88, mm", Some((0.0, 1e3))),
    (5241, "largest rigid tapping speed, rpm", Some((0.0, 1e5))),
    (5261, "rigid tapping acceleration: ms for the spindle to reach 1000 rpm", Some((0.0, 4000.0))),
    (5271, "rigid tapping retract acceleration, ms to 1000 rpm", Some((0.0, 4000.0))),
    (5275, "flexible tapping: cycles of encoder lag compensated", Some((0.0, 100.0))),
    (5276, "flexible tapping: retract speed check, 0.1 rpm", Some((0.0, 1e6))),
    (5282, "rigid tapping extra return beyond R, mm", Some((0.0, 1e3))),
    (5382, "G30 P99 extra return beyond R, mm", Some((0.0, 1e3))),
    (6023, "cutting feed clamp, mm/min", Some((f64::MIN_POSITIVE, 1e6))),
    (7013, "rigid tapping dwell at R, ms", Some((0.0, 1e6))),
];

/// What parameter `no` sets, if this controller reads it.
pub fn describe(no: u32) -> Option<&'static str> {
    KNOWN.iter().find(|k| k.0 == no).map(|k| k.1)
}

/// Problems with a `[parameters]` entry `key = value`, each naming the key.
pub fn check(key: &str, value: &toml::Value) -> Vec<String> {
    let Ok(no) = key.trim().parse::<u32>() else {
        return vec![format!("parameters.{key}: a parameter is a number, e.g. 5261 = 200")];
    };
    let Some(&(_, what, range)) = KNOWN.iter().find(|k| k.0 == no) else {
        return vec![format!(
            "parameters.{no}: not a parameter this controller reads (a typo? it would be ignored); the ones it reads: {}",
            KNOWN.iter().map(|k| k.0.to_string()).collect::<Vec<_>>().join(", ")
        )];
    };
    let num = match value {
        toml::Value::Integer(i) => Some(*i as f64),
        toml::Value::Float(f) => Some(*f),
        toml::Value::Boolean(b) => Some(*b as u8 as f64),
        toml::Value::Table(_) if (1240..=1243).contains(&no) => return Vec::new(),
        _ => return vec![format!("parameters.{no} ({what}): must be a number")],
    };
    match (num, range) {
        (Some(v), _) if !v.is_finite() => vec![format!("parameters.{no} ({what}): must be a finite number, got {v}")],
        (Some(v), Some((lo, hi))) if v < lo || v > hi => {
            let lo = if lo == f64::MIN_POSITIVE { "> 0".to_string() } else { format!("{lo}") };
            vec![format!("parameters.{no} ({what}): must be {lo} … {hi}, got {v}")]
        }
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typos_and_bad_values_are_named() {
        assert!(check("5261", &toml::Value::Integer(200)).is_empty());
        assert!(check("5621", &toml::Value::Integer(200))[0].contains("not a parameter this controller reads"));
        assert!(check("6023", &toml::Value::Integer(-5))[0].contains("parameters.6023 (cutting feed clamp, mm/min): must be > 0"));
        assert!(check("5261", &toml::Value::String("x".into()))[0].contains("must be a number"));
        assert_eq!(describe(5210), Some("rigid tapping M code (0 = M29)"));
    }
}
