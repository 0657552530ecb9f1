//! The object dictionary: entries with data type, access, PDO mappability and value range,
//! and the generic SDO-level checks a real drive applies before any object-specific rule.

use cncgw_bus::canopen::sdo::abort;
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DType {
    U8,
    U16,
    U32,
    I8,
    I16,
    I32,
    /// VISIBLE_STRING, read as a whole (length = current content).
    Str,
    /// DOMAIN: any bytes up to the entry's `max` length (large objects, block transfer).
    Domain,
}

impl DType {
    /// Size in bytes for fixed-size types.
    pub fn size(self) -> Option<usize> {
        match self {
            DType::U8 | DType::I8 => Some(1),
            DType::U16 | DType::I16 => Some(2),
            DType::U32 | DType::I32 => Some(4),
            DType::Str | DType::Domain => None,
        }
    }
    fn range(self) -> (i64, i64) {
        match self {
            DType::U8 => (0, u8::MAX as i64),
            DType::U16 => (0, u16::MAX as i64),
            DType::U32 => (0, u32::MAX as i64),
            DType::I8 => (i8::MIN as i64, i8::MAX as i64),
            DType::I16 => (i16::MIN as i64, i16::MAX as i64),
            DType::I32 => (i32::MIN as i64, i32::MAX as i64),
            DType::Str | DType::Domain => (0, 0),
        }
    }
    /// Little-endian bytes → value, sign-extended for signed types.
    pub fn decode(self, b: &[u8]) -> i64 {
        let mut buf = [0u8; 8];
        let n = b.len().min(8);
        buf[..n].copy_from_slice(&b[..n]);
        let u = u64::from_le_bytes(buf);
        match self {
            DType::U8 => (u & 0xFF) as i64,
            DType::U16 => (u & 0xFFFF) as i64,
            DType::U32 => (u & 0xFFFF_FFFF) as i64,
            DType::I8 => (u as u8) as i8 as i64,
            DType::I16 => (u as u16) as i16 as i64,
            DType::I32 => (u as u32) as i32 as i64,
            DType::Str | DType::Domain => 0,
        }
    }
    pub fn encode(self, v: i64) -> Vec<u8> {
        let n = self.size().unwrap_or(0);
        v.to_le_bytes()[..n].to_vec()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Constant: read-only, never changes.
    Const,
    /// Read-only, changed by the device.
    Ro,
    Rw,
    Wo,
}

impl Access {
    pub fn readable(self) -> bool {
        !matches!(self, Access::Wo)
    }
    pub fn writable(self) -> bool {
        matches!(self, Access::Rw | Access::Wo)
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    Int(i64),
    Str(String),
    Bytes(Vec<u8>),
}

#[derive(Clone, Debug)]
pub struct Entry {
    pub dtype: DType,
    pub access: Access,
    pub pdo: bool,
    /// Allowed value range (inclusive), checked on SDO download.
    pub min: i64,
    pub max: i64,
    pub value: Value,
    pub default: Value,
}

fn key(index: u16, sub: u8) -> u32 {
    ((index as u32) << 8) | sub as u32
}

#[derive(Clone, Debug, Default)]
pub struct Od {
    entries: BTreeMap<u32, Entry>,
}

impl Od {
    pub fn new() -> Od {
        Od::default()
    }

    /// Add an integer entry with the full range of its type.
    pub fn add(&mut self, index: u16, sub: u8, dtype: DType, access: Access, pdo: bool, value: i64) {
        let (min, max) = dtype.range();
        self.add_range(index, sub, dtype, access, pdo, value, min, max);
    }

    #[allow(clippy::too_many_arguments)]
    pub fn add_range(&mut self, index: u16, sub: u8, dtype: DType, access: Access, pdo: bool, value: i64, min: i64, max: i64) {
        let e = Entry { dtype, access, pdo, min, max, value: Value::Int(value), default: Value::Int(value) };
        self.entries.insert(key(index, sub), e);
    }

    /// Make an existing entry read-only (a fixed PDO mapping).
    pub fn make_read_only(&mut self, index: u16, sub: u8) {
        if let Some(e) = self.entries.get_mut(&key(index, sub)) {
            e.access = Access::Ro;
        }
    }

    pub fn add_str(&mut self, index: u16, sub: u8, access: Access, s: &str) {
        let v = Value::Str(s.to_string());
        let e = Entry { dtype: DType::Str, access, pdo: false, min: 0, max: 0, value: v.clone(), default: v };
        self.entries.insert(key(index, sub), e);
    }

    /// A DOMAIN entry holding up to `max_len` bytes, empty at first.
    pub fn add_domain(&mut self, index: u16, sub: u8, access: Access, max_len: usize) {
        let v = Value::Bytes(Vec::new());
        let e = Entry { dtype: DType::Domain, access, pdo: false, min: 0, max: max_len as i64, value: v.clone(), default: v };
        self.entries.insert(key(index, sub), e);
    }

    /// Every entry, by index and sub-index.
    pub fn iter(&self) -> impl Iterator<Item = ((u16, u8), &Entry)> {
        self.entries.iter().map(|(k, e)| (((k >> 8) as u16, *k as u8), e))
    }

    pub fn get(&self, index: u16, sub: u8) -> Option<&Entry> {
        self.entries.get(&key(index, sub))
    }

    pub fn has_index(&self, index: u16) -> bool {
        self.entries.range(key(index, 0)..=key(index, 0xFF)).next().is_some()
    }

    /// Integer value (0 for a missing entry: callers only ask for entries they created).
    pub fn int(&self, index: u16, sub: u8) -> i64 {
        match self.get(index, sub).map(|e| &e.value) {
            Some(Value::Int(v)) => *v,
            _ => 0,
        }
    }

    /// Set a value from the device side (no access check).
    pub fn set(&mut self, index: u16, sub: u8, v: i64) {
        if let Some(e) = self.entries.get_mut(&key(index, sub)) {
            e.value = Value::Int(v);
        }
    }

    /// Restore defaults of every entry whose index is in `range` (NMT resets).
    pub fn reset_range(&mut self, lo: u16, hi: u16) {
        for e in self.entries.range_mut(key(lo, 0)..=key(hi, 0xFF)).map(|(_, e)| e) {
            e.value = e.default.clone();
        }
    }

    /// SDO upload: the object's bytes, or the abort code.
    pub fn read_bytes(&self, index: u16, sub: u8) -> Result<Vec<u8>, u32> {
        let e = self.lookup(index, sub)?;
        if !e.access.readable() {
            return Err(abort::WRITE_ONLY);
        }
        Ok(match &e.value {
            Value::Int(v) => e.dtype.encode(*v),
            Value::Str(s) => s.as_bytes().to_vec(),
            Value::Bytes(b) => b.clone(),
        })
    }

    /// Existence, sub-index existence.
    pub fn lookup(&self, index: u16, sub: u8) -> Result<&Entry, u32> {
        match self.get(index, sub) {
            Some(e) => Ok(e),
            None if self.has_index(index) => Err(abort::NO_SUBINDEX),
            None => Err(abort::NO_OBJECT),
        }
    }

    /// The generic checks of an SDO download, in the order a real drive applies them:
    /// existence, sub-index, access, length, range. Returns the decoded value.
    pub fn check_write(&self, index: u16, sub: u8, data: &[u8]) -> Result<Value, u32> {
        let e = self.lookup(index, sub)?;
        if !e.access.writable() {
            return Err(abort::READ_ONLY);
        }
        match e.dtype.size() {
            None if e.dtype == DType::Domain => {
                if data.len() as i64 > e.max {
                    return Err(abort::TOO_LONG);
                }
                Ok(Value::Bytes(data.to_vec()))
            }
            None => Ok(Value::Str(String::from_utf8_lossy(data).into_owned())),
            Some(n) => {
                if data.len() > n {
                    return Err(abort::TOO_LONG);
                }
                if data.len() < n {
                    return Err(abort::TOO_SHORT);
                }
                let v = e.dtype.decode(data);
                if v > e.max {
                    return Err(abort::VALUE_TOO_HIGH);
                }
                if v < e.min {
                    return Err(abort::VALUE_TOO_LOW);
                }
                Ok(Value::Int(v))
            }
        }
    }

    /// Store a value that passed `check_write` and the object-specific rules.
    pub fn store(&mut self, index: u16, sub: u8, v: Value) {
        if let Some(e) = self.entries.get_mut(&key(index, sub)) {
            e.value = v;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generic_checks_in_order() {
        let mut od = Od::new();
        od.add(0x1000, 0, DType::U32, Access::Const, false, 0x20192);
        od.add_range(0x605A, 0, DType::I16, Access::Rw, false, 2, 0, 8);
        od.add(0x2000, 0, DType::U32, Access::Wo, false, 0);
        assert_eq!(od.read_bytes(0x1000, 0), Ok(vec![0x92, 0x01, 0x02, 0x00]));
        assert_eq!(od.read_bytes(0x1000, 1), Err(abort::NO_SUBINDEX));
        assert_eq!(od.read_bytes(0x1001, 0), Err(abort::NO_OBJECT));
        assert_eq!(od.read_bytes(0x2000, 0), Err(abort::WRITE_ONLY));
        assert_eq!(od.check_write(0x1000, 0, &[0; 4]), Err(abort::READ_ONLY));
        assert_eq!(od.check_write(0x605A, 0, &[1]), Err(abort::TOO_SHORT));
        assert_eq!(od.check_write(0x605A, 0, &[1, 0, 0]), Err(abort::TOO_LONG));
        assert_eq!(od.check_write(0x605A, 0, &[9, 0]), Err(abort::VALUE_TOO_HIGH));
        assert_eq!(od.check_write(0x605A, 0, &[0xFF, 0xFF]), Err(abort::VALUE_TOO_LOW));
        assert_eq!(od.check_write(0x605A, 0, &[5, 0]), Ok(Value::Int(5)));
    }

    #[test]
    fn domain_holds_bytes_up_to_its_length() {
        let mut od = Od::new();
        od.add_domain(0x2200, 0, Access::Rw, 16);
        assert_eq!(od.read_bytes(0x2200, 0), Ok(vec![]));
        assert_eq!(od.check_write(0x2200, 0, &[0xAA; 17]), Err(abort::TOO_LONG));
        let v = od.check_write(0x2200, 0, &[0, 0xFF, 7]).unwrap();
        od.store(0x2200, 0, v);
        assert_eq!(od.read_bytes(0x2200, 0), Ok(vec![0, 0xFF, 7]));
        od.reset_range(0x2200, 0x2200);
        assert_eq!(od.read_bytes(0x2200, 0), Ok(vec![]));
    }
}
