//! EDS files (CiA 306 electronic data sheets, the INI-style files vendors ship with their
//! drives): a small parser, enough to check a drive's object dictionary and what a master
//! writes and maps against the file, naming the file and line that disagree.
//!
//! Read: `[XXXX]` and `[XXXXsubN]` sections with ObjectType, DataType, AccessType,
//! PDOMapping, DefaultValue, ParameterName, SubNumber. `CompactSubObj` arrays are
//! expanded (sub 0 U8 plus `CompactSubObj` entries of the section's type). Other sections
//! (FileInfo, DeviceInfo, Comments, …) are skipped.

use std::collections::BTreeMap;

/// Access as an EDS states it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdsAccess {
    Ro,
    Wo,
    Rw,
    /// rw, mapped into an RPDO preferably (rww) or a TPDO (rwr).
    Rww,
    Rwr,
    Const,
}

impl EdsAccess {
    fn parse(s: &str) -> Option<EdsAccess> {
        Some(match s.to_ascii_lowercase().as_str() {
            "ro" => EdsAccess::Ro,
            "wo" => EdsAccess::Wo,
            "rw" => EdsAccess::Rw,
            "rww" => EdsAccess::Rww,
            "rwr" => EdsAccess::Rwr,
            "const" => EdsAccess::Const,
            _ => return None,
        })
    }
    pub fn readable(self) -> bool {
        self != EdsAccess::Wo
    }
    pub fn writable(self) -> bool {
        matches!(self, EdsAccess::Wo | EdsAccess::Rw | EdsAccess::Rww | EdsAccess::Rwr)
    }
    pub fn name(self) -> &'static str {
        match self {
            EdsAccess::Ro => "ro",
            EdsAccess::Wo => "wo",
            EdsAccess::Rw => "rw",
            EdsAccess::Rww => "rww",
            EdsAccess::Rwr => "rwr",
            EdsAccess::Const => "const",
        }
    }
}

/// Size in bytes of a CiA 301 basic data type; None for strings and domains.
pub fn data_type_size(dt: u16) -> Option<usize> {
    Some(match dt {
        0x0001 | 0x0002 | 0x0005 => 1,
        0x0003 | 0x0006 => 2,
        0x0010 | 0x0016 => 3,
        0x0004 | 0x0007 | 0x0008 => 4,
        0x0011 | 0x0015 | 0x001B => 8,
        _ => return None,
    })
}

/// A CiA 301 data type's name.
pub fn data_type_name(dt: u16) -> &'static str {
    match dt {
        0x0001 => "BOOLEAN",
        0x0002 => "INTEGER8",
        0x0003 => "INTEGER16",
        0x0004 => "INTEGER32",
        0x0005 => "UNSIGNED8",
        0x0006 => "UNSIGNED16",
        0x0007 => "UNSIGNED32",
        0x0008 => "REAL32",
        0x0009 => "VISIBLE_STRING",
        0x000A => "OCTET_STRING",
        0x000B => "UNICODE_STRING",
        0x000F => "DOMAIN",
        0x0010 => "INTEGER24",
        0x0011 => "REAL64",
        0x0015 => "INTEGER64",
        0x0016 => "UNSIGNED24",
        0x001B => "UNSIGNED64",
        _ => "unknown type",
    }
}

/// One object (VAR) of the file.
#[derive(Clone, Debug, PartialEq)]
pub struct EdsEntry {
    pub index: u16,
    pub sub: u8,
    pub name: String,
    pub data_type: u16,
    pub access: EdsAccess,
    pub pdo_mapping: bool,
    pub default: Option<String>,
    /// LowLimit / HighLimit, where the file gives them as numbers.
    pub low_limit: Option<i64>,
    pub high_limit: Option<i64>,
    /// Line of the section header (1-based).
    pub line: usize,
}

impl EdsEntry {
    pub fn size(&self) -> Option<usize> {
        data_type_size(self.data_type)
    }
}

/// A parsed EDS.
#[derive(Clone, Debug, Default)]
pub struct Eds {
    /// The file name, for messages.
    pub file: String,
    pub entries: BTreeMap<(u16, u8), EdsEntry>,
    /// Indices that exist as ARRAY / RECORD (their subs are in `entries`).
    pub composites: BTreeMap<u16, usize>,
}

/// A limit: decimal (possibly negative) or hex; `None` for what is neither (`$NODEID+…`).
fn parse_limit(s: &str) -> Option<i64> {
    let s = s.trim();
    match s.strip_prefix('-') {
        Some(r) => parse_num(r).and_then(|v| i64::try_from(v).ok()).map(|v| -v),
        None => parse_num(s).and_then(|v| i64::try_from(v).ok()),
    }
}

fn parse_num(s: &str) -> Option<u64> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(h) => u64::from_str_radix(h, 16).ok(),
        None => s.parse().ok(),
    }
}

/// `[1018]` → (0x1018, None); `[1018sub4]` → (0x1018, Some(4)); other names → None.
fn section_key(name: &str) -> Option<(u16, Option<u8>)> {
    let lower = name.to_ascii_lowercase();
    let (ix, sub) = match lower.split_once("sub") {
        Some((i, s)) => (i, Some(u8::from_str_radix(s, 16).ok()?)),
        None => (lower.as_str(), None),
    };
    if ix.len() != 4 {
        return None;
    }
    Some((u16::from_str_radix(ix, 16).ok()?, sub))
}

impl Eds {
    /// Parse `text` (the contents of `file`). Errors name the line.
    pub fn parse(file: &str, text: &str) -> Result<Eds, String> {
        struct Section {
            index: u16,
            sub: Option<u8>,
            line: usize,
            keys: BTreeMap<String, (String, usize)>,
        }
        let mut sections: Vec<Section> = Vec::new();
        let mut current: Option<usize> = None;
        for (n, raw) in text.lines().enumerate() {
            let line = raw.trim();
            let ln = n + 1;
            if line.is_empty() || line.starts_with(';') || line.starts_with('#') {
                continue;
            }
            if let Some(name) = line.strip_prefix('[') {
                let Some(name) = name.strip_suffix(']') else {
                    return Err(format!("{file}:{ln}: section header without ']': {line}"));
                };
                current = section_key(name.trim()).map(|(index, sub)| {
                    sections.push(Section { index, sub, line: ln, keys: BTreeMap::new() });
                    sections.len() - 1
                });
                continue;
            }
            let Some((k, v)) = line.split_once('=') else {
                return Err(format!("{file}:{ln}: expected KEY=VALUE, got {line:?}"));
            };
            if let Some(i) = current {
                sections[i].keys.insert(k.trim().to_ascii_lowercase(), (v.trim().to_string(), ln));
            }
        }
        let mut eds = Eds { file: file.to_string(), ..Eds::default() };
        let by_key: BTreeMap<(u16, Option<u8>), usize> = sections.iter().enumerate().map(|(i, s)| ((s.index, s.sub), i)).collect();
        for s in &sections {
            let get = |k: &str| s.keys.get(k);
            let num = |k: &str| -> Result<Option<u64>, String> {
                match get(k) {
                    None => Ok(None),
                    Some((v, ln)) => parse_num(v).map(Some).ok_or_else(|| format!("{file}:{ln}: {k} = {v:?} is not a number")),
                }
            };
            let object_type = num("objecttype")?.unwrap_or(0x7);
            let here = match s.sub {
                Some(sub) => format!("[{:04X}sub{:X}]", s.index, sub),
                None => format!("[{:04X}]", s.index),
            };
            match (object_type, s.sub) {
                (0x7, sub) => {
                    let dt = match get("datatype") {
                        Some((v, ln)) => parse_num(v).ok_or_else(|| format!("{file}:{ln}: DataType {v:?} is not a number"))?,
                        None => return Err(format!("{file}:{}: {here} has no DataType", s.line)),
                    };
                    let access = match get("accesstype") {
                        Some((v, ln)) => EdsAccess::parse(v).ok_or_else(|| format!("{file}:{ln}: AccessType {v:?} is not ro/wo/rw/rww/rwr/const"))?,
                        None => return Err(format!("{file}:{}: {here} has no AccessType", s.line)),
                    };
                    let pdo = num("pdomapping")?.unwrap_or(0) != 0;
                    let e = EdsEntry {
                        index: s.index,
                        sub: sub.unwrap_or(0),
                        name: get("parametername").map(|v| v.0.clone()).unwrap_or_default(),
                        data_type: dt as u16,
                        access,
                        pdo_mapping: pdo,
                        default: get("defaultvalue").map(|v| v.0.clone()),
                        low_limit: get("lowlimit").and_then(|v| parse_limit(&v.0)),
                        high_limit: get("highlimit").and_then(|v| parse_limit(&v.0)),
                        line: s.line,
                    };
                    eds.entries.insert((e.index, e.sub), e);
                }
                (0x8 | 0x9, None) => {
                    eds.composites.insert(s.index, s.line);
                    if let Some(n) = num("compactsubobj")?.filter(|&n| n > 0) {
                        // All subs alike, described by this section.
                        let dt = num("datatype")?.unwrap_or(0x7) as u16;
                        let access = get("accesstype").and_then(|v| EdsAccess::parse(&v.0)).unwrap_or(EdsAccess::Rw);
                        let pdo = num("pdomapping")?.unwrap_or(0) != 0;
                        let name = get("parametername").map(|v| v.0.clone()).unwrap_or_default();
                        let mk = |sub: u8, dt: u16, access: EdsAccess, pdo: bool| EdsEntry {
                            index: s.index,
                            sub,
                            name: name.clone(),
                            data_type: dt,
                            access,
                            pdo_mapping: pdo,
                            default: None,
                            low_limit: None,
                            high_limit: None,
                            line: s.line,
                        };
                        eds.entries.insert((s.index, 0), mk(0, 0x0005, EdsAccess::Ro, false));
                        for sub in 1..=n.min(254) as u8 {
                            eds.entries.insert((s.index, sub), mk(sub, dt, access, pdo));
                        }
                    } else if !by_key.keys().any(|&(i, sub)| i == s.index && sub.is_some()) {
                        return Err(format!("{file}:{}: {here} is an array/record without sub-index sections", s.line));
                    }
                }
                (0x8 | 0x9, Some(_)) => return Err(format!("{file}:{}: {here}: a sub-index cannot be an array or record", s.line)),
                (t, _) => {
                    // DEFTYPE (5), DEFSTRUCT (6), DOMAIN (2): only DOMAIN matters to a master.
                    if t == 0x2 {
                        let access = get("accesstype").and_then(|v| EdsAccess::parse(&v.0)).unwrap_or(EdsAccess::Rw);
                        let e = EdsEntry {
                            index: s.index,
                            sub: s.sub.unwrap_or(0),
                            name: get("parametername").map(|v| v.0.clone()).unwrap_or_default(),
                            data_type: 0x000F,
                            access,
                            pdo_mapping: false,
                            default: None,
                            low_limit: None,
                            high_limit: None,
                            line: s.line,
                        };
                        eds.entries.insert((e.index, e.sub), e);
                    }
                }
            }
        }
        Ok(eds)
    }

    /// Read and parse a file.
    pub fn load(path: &std::path::Path) -> Result<Eds, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Eds::parse(&path.display().to_string(), &text)
    }

    pub fn get(&self, index: u16, sub: u8) -> Option<&EdsEntry> {
        self.entries.get(&(index, sub))
    }

    fn where_(&self, e: &EdsEntry) -> String {
        format!(
            "{}:{} [{:04X}{}] {:?}",
            self.file,
            e.line,
            e.index,
            if self.composites.contains_key(&e.index) { format!("sub{:X}", e.sub) } else { String::new() },
            e.name
        )
    }

    fn lookup(&self, index: u16, sub: u8) -> Result<&EdsEntry, String> {
        self.get(index, sub).ok_or_else(|| {
            if let Some(line) = self.composites.get(&index) {
                format!("{}:{line}: 0x{index:04X} has no sub-index {sub} in the EDS", self.file)
            } else {
                format!("{}: object 0x{index:04X}:{sub:02X} is not in the EDS", self.file)
            }
        })
    }

    /// A master is about to write `len` bytes to `index:sub`: the object must exist, be
    /// writable and, for a fixed-size type, have that size.
    pub fn check_write(&self, index: u16, sub: u8, len: usize) -> Result<(), String> {
        let e = self.lookup(index, sub)?;
        if !e.access.writable() {
            return Err(format!("{}: AccessType={} but the master writes 0x{index:04X}:{sub:02X}", self.where_(e), e.access.name()));
        }
        if let Some(n) = e.size() {
            if n != len {
                return Err(format!("{}: DataType {} is {n} bytes but the master writes {len}", self.where_(e), data_type_name(e.data_type)));
            }
        }
        Ok(())
    }

    /// A master maps `index:sub` with `bits` into an RPDO (`rpdo`) or a TPDO.
    pub fn check_map(&self, index: u16, sub: u8, bits: u8, rpdo: bool) -> Result<(), String> {
        let e = self.lookup(index, sub)?;
        if !e.pdo_mapping {
            return Err(format!("{}: PDOMapping=0 but the master maps 0x{index:04X}:{sub:02X}", self.where_(e)));
        }
        let dir_ok = if rpdo { e.access.writable() } else { e.access.readable() };
        if !dir_ok {
            return Err(format!("{}: AccessType={} cannot go in a {}", self.where_(e), e.access.name(), if rpdo { "RPDO" } else { "TPDO" }));
        }
        if e.size().map(|n| n * 8) != Some(bits as usize) {
            return Err(format!("{}: DataType {} is not {bits} bits", self.where_(e), data_type_name(e.data_type)));
        }
        Ok(())
    }

    /// Where the file describes `index:sub`, for messages ("file:line [XXXXsubN] name").
    pub fn describe(&self, index: u16, sub: u8) -> Option<String> {
        self.get(index, sub).map(|e| self.where_(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "\
[FileInfo]
FileName=x.eds

; a comment
[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00020192
PDOMapping=0

[1018]
ParameterName=Identity
ObjectType=0x9
SubNumber=2

[1018sub0]
ParameterName=Highest sub-index
ObjectType=0x7
DataType=0x0005
AccessType=ro
DefaultValue=1

[1018sub1]
ParameterName=Vendor-ID
DataType=0x0007
AccessType=ro

[1016]
ParameterName=Consumer heartbeat
ObjectType=0x8
CompactSubObj=2
DataType=0x0007
AccessType=rw

[6040]
ParameterName=Controlword
ObjectType=0x7
DataType=0x0006
AccessType=rww
PDOMapping=1
";

    #[test]
    fn parses_vars_records_and_compact_arrays() {
        let e = Eds::parse("x.eds", TEXT).unwrap();
        let dt = e.get(0x1000, 0).unwrap();
        assert_eq!((dt.data_type, dt.access, dt.pdo_mapping, dt.line), (7, EdsAccess::Ro, false, 5));
        assert_eq!(e.get(0x1018, 1).unwrap().name, "Vendor-ID");
        assert_eq!(e.get(0x1016, 2).unwrap().access, EdsAccess::Rw);
        assert_eq!(e.get(0x1016, 0).unwrap().data_type, 5);
        assert!(e.get(0x1016, 3).is_none());
        assert_eq!(e.get(0x6040, 0).unwrap().access, EdsAccess::Rww);
    }

    #[test]
    fn checks_name_the_file_and_line() {
        let e = Eds::parse("x.eds", TEXT).unwrap();
        assert_eq!(e.check_write(0x6040, 0, 2), Ok(()));
        assert_eq!(
            e.check_write(0x6040, 0, 4).unwrap_err(),
            "x.eds:37 [6040] \"Controlword\": DataType UNSIGNED16 is 2 bytes but the master writes 4"
        );
        assert_eq!(e.check_write(0x1000, 0, 4).unwrap_err(), "x.eds:5 [1000] \"Device type\": AccessType=ro but the master writes 0x1000:00");
        assert_eq!(e.check_write(0x6060, 0, 1).unwrap_err(), "x.eds: object 0x6060:00 is not in the EDS");
        assert_eq!(e.check_write(0x1018, 7, 4).unwrap_err(), "x.eds:13: 0x1018 has no sub-index 7 in the EDS");
        assert_eq!(e.check_map(0x6040, 0, 16, true), Ok(()));
        assert!(e.check_map(0x1000, 0, 32, false).unwrap_err().contains("PDOMapping=0"));
        assert!(e.check_map(0x6040, 0, 32, true).unwrap_err().contains("is not 32 bits"));
    }

    #[test]
    fn malformed_files_are_refused_with_the_line() {
        assert_eq!(Eds::parse("b.eds", "[1000\nX=1").unwrap_err(), "b.eds:1: section header without ']': [1000");
        assert_eq!(
            Eds::parse("b.eds", "[1000]\nDataType=0x0007\nAccessType=xx").unwrap_err(),
            "b.eds:3: AccessType \"xx\" is not ro/wo/rw/rww/rwr/const"
        );
        assert_eq!(Eds::parse("b.eds", "[1000]\nAccessType=ro").unwrap_err(), "b.eds:1: [1000] has no DataType");
        assert_eq!(
            Eds::parse("b.eds", "[2000]\nObjectType=0x9\nSubNumber=2").unwrap_err(),
            "b.eds:1: [2000] is an array/record without sub-index sections"
        );
        assert!(Eds::parse("b.eds", "[1000]\nnot a key").unwrap_err().starts_with("b.eds:2: expected KEY=VALUE"));
    }
}
