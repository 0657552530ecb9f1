//! PDO payload helpers: little-endian packing of mapped objects, and the mapping-entry
//! encoding of 0x1600/0x1A00 (index << 16 | sub << 8 | bit length).

/// One mapped object: index, sub-index, length in bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MapEntry {
    pub index: u16,
    pub sub: u8,
    pub bits: u8,
}

impl MapEntry {
    pub const fn new(index: u16, sub: u8, bits: u8) -> Self {
        MapEntry { index, sub, bits }
    }
    pub fn encode(self) -> u32 {
        ((self.index as u32) << 16) | ((self.sub as u32) << 8) | self.bits as u32
    }
    pub fn decode(v: u32) -> Self {
        MapEntry { index: (v >> 16) as u16, sub: (v >> 8) as u8, bits: v as u8 }
    }
}

/// Total mapped length in bytes, or `None` if it exceeds the 8 bytes of a CAN frame or a
/// length is not whole bytes.
pub fn mapped_len(entries: &[MapEntry]) -> Option<usize> {
    let bits: u32 = entries.iter().map(|e| e.bits as u32).sum();
    if bits > 64 || entries.iter().any(|e| e.bits % 8 != 0 || e.bits == 0) {
        None
    } else {
        Some((bits / 8) as usize)
    }
}

pub fn put_u16(d: &mut [u8], off: usize, v: u16) {
    d[off..off + 2].copy_from_slice(&v.to_le_bytes());
}
pub fn put_i32(d: &mut [u8], off: usize, v: i32) {
    d[off..off + 4].copy_from_slice(&v.to_le_bytes());
}
pub fn get_u16(d: &[u8], off: usize) -> u16 {
    u16::from_le_bytes([d[off], d[off + 1]])
}
pub fn get_i32(d: &[u8], off: usize) -> i32 {
    i32::from_le_bytes([d[off], d[off + 1], d[off + 2], d[off + 3]])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mapping_entries() {
        assert_eq!(MapEntry::new(0x6040, 0, 16).encode(), 0x6040_0010);
        assert_eq!(MapEntry::new(0x607A, 0, 32).encode(), 0x607A_0020);
        assert_eq!(MapEntry::decode(0x6064_0020), MapEntry::new(0x6064, 0, 32));
        assert_eq!(mapped_len(&[MapEntry::new(0x6040, 0, 16), MapEntry::new(0x607A, 0, 32)]), Some(6));
        let too_long = [MapEntry::new(0x607A, 0, 32), MapEntry::new(0x607A, 0, 32), MapEntry::new(0x6040, 0, 16)];
        assert_eq!(mapped_len(&too_long), None);
    }
}
