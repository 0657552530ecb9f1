//! SDO frame codec (CiA 301 §7.2.4): expedited, segmented and block transfers, abort codes.
//! Requests travel on 0x600 + node (client → server), responses on 0x580 + node.
//!
//! Block transfer frames (`BlockRequest`, `BlockResponse`, `BlockSegment`) cannot be told
//! apart from segmented ones by their first byte alone (a block segment's first byte is its
//! sequence number): the side that knows the transfer state decides which decoder applies.

use super::cob;
use crate::CanFrame;

/// A client → server SDO frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SdoRequest {
    /// Initiate download. Expedited when `size` ≤ 4 and `data` holds the value; otherwise
    /// segmented, and `size` (if indicated) is the total byte count.
    InitiateDownload {
        index: u16,
        sub: u8,
        expedited: bool,
        size: Option<u32>,
        data: [u8; 4],
    },
    /// Download segment: toggle bit, up to 7 bytes, last-segment flag.
    DownloadSegment {
        toggle: bool,
        len: u8,
        data: [u8; 7],
        last: bool,
    },
    InitiateUpload {
        index: u16,
        sub: u8,
    },
    UploadSegment {
        toggle: bool,
    },
    Abort {
        index: u16,
        sub: u8,
        code: u32,
    },
}

/// A server → client SDO frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SdoResponse {
    InitiateDownload {
        index: u16,
        sub: u8,
    },
    DownloadSegment {
        toggle: bool,
    },
    /// Initiate upload response: expedited carries the data (`size` bytes of `data`).
    InitiateUpload {
        index: u16,
        sub: u8,
        expedited: bool,
        size: Option<u32>,
        data: [u8; 4],
    },
    UploadSegment {
        toggle: bool,
        len: u8,
        data: [u8; 7],
        last: bool,
    },
    Abort {
        index: u16,
        sub: u8,
        code: u32,
    },
}

fn mux(d: &[u8]) -> (u16, u8) {
    (u16::from_le_bytes([d[1], d[2]]), d[3])
}

fn put_mux(d: &mut [u8; 8], index: u16, sub: u8) {
    d[1..3].copy_from_slice(&index.to_le_bytes());
    d[3] = sub;
}

/// Initiate-frame size fields: (n, e, s) bits → (expedited, size).
fn initiate_bits(cmd: u8, d: &[u8; 8]) -> (bool, Option<u32>, [u8; 4]) {
    let e = cmd & 0x02 != 0;
    let s = cmd & 0x01 != 0;
    let data = [d[4], d[5], d[6], d[7]];
    let size = match (e, s) {
        (true, true) => Some(4 - ((cmd >> 2) & 0x03) as u32),
        (true, false) => None,
        (false, true) => Some(u32::from_le_bytes(data)),
        (false, false) => None,
    };
    (e, size, data)
}

fn initiate_cmd(base: u8, expedited: bool, size: Option<u32>) -> u8 {
    match (expedited, size) {
        (true, Some(n)) => base | ((4 - n.clamp(1, 4) as u8) << 2) | 0x03,
        (true, None) => base | 0x02,
        (false, Some(_)) => base | 0x01,
        (false, None) => base,
    }
}

/// An initiate frame (download request, upload response): command, multiplexer, and the
/// value (expedited) or the indicated size.
fn put_initiate(d: &mut [u8; 8], base: u8, index: u16, sub: u8, expedited: bool, size: Option<u32>, data: [u8; 4]) {
    d[0] = initiate_cmd(base, expedited, size);
    put_mux(d, index, sub);
    if expedited {
        d[4..8].copy_from_slice(&data);
    } else if let Some(n) = size {
        d[4..8].copy_from_slice(&n.to_le_bytes());
    }
}

/// A data segment (download request, upload response): toggle, n (bytes unused), c (last).
fn put_segment(d: &mut [u8; 8], toggle: bool, len: u8, data: [u8; 7], last: bool) {
    d[0] = ((toggle as u8) << 4) | ((7 - len.min(7)) << 1) | last as u8;
    d[1..8].copy_from_slice(&data);
}

/// A data segment's (toggle, len, data, last).
fn segment_bits(cmd: u8, d: &[u8; 8]) -> (bool, u8, [u8; 7], bool) {
    let mut data = [0u8; 7];
    data.copy_from_slice(&d[1..8]);
    (cmd & 0x10 != 0, 7 - ((cmd >> 1) & 0x07), data, cmd & 0x01 != 0)
}

fn put_abort(d: &mut [u8; 8], index: u16, sub: u8, code: u32) {
    d[0] = 0x80;
    put_mux(d, index, sub);
    d[4..8].copy_from_slice(&code.to_le_bytes());
}

fn abort_code(d: &[u8; 8]) -> u32 {
    u32::from_le_bytes([d[4], d[5], d[6], d[7]])
}

impl SdoRequest {
    pub fn encode(&self, node: u8) -> CanFrame {
        let mut d = [0u8; 8];
        match *self {
            SdoRequest::InitiateDownload { index, sub, expedited, size, data } => put_initiate(&mut d, 0x20, index, sub, expedited, size, data),
            SdoRequest::DownloadSegment { toggle, len, data, last } => put_segment(&mut d, toggle, len, data, last),
            SdoRequest::InitiateUpload { index, sub } => {
                d[0] = 0x40;
                put_mux(&mut d, index, sub);
            }
            SdoRequest::UploadSegment { toggle } => d[0] = 0x60 | ((toggle as u8) << 4),
            SdoRequest::Abort { index, sub, code } => put_abort(&mut d, index, sub, code),
        }
        CanFrame::new(cob::SDO_RX + node as u16, &d)
    }

    /// Decode a request frame (any COB-ID; the caller routes by 0x600 + node). SDO frames
    /// are always 8 bytes; shorter ones are refused like a real server does.
    pub fn decode(f: &CanFrame) -> Option<Self> {
        if f.len != 8 || f.rtr {
            return None;
        }
        let d = &f.data;
        let cmd = d[0];
        Some(match cmd >> 5 {
            1 => {
                let (index, sub) = mux(d);
                let (expedited, size, data) = initiate_bits(cmd, d);
                SdoRequest::InitiateDownload { index, sub, expedited, size, data }
            }
            0 => {
                let (toggle, len, data, last) = segment_bits(cmd, d);
                SdoRequest::DownloadSegment { toggle, len, data, last }
            }
            2 => {
                let (index, sub) = mux(d);
                SdoRequest::InitiateUpload { index, sub }
            }
            3 => SdoRequest::UploadSegment { toggle: cmd & 0x10 != 0 },
            4 => {
                let (index, sub) = mux(d);
                SdoRequest::Abort { index, sub, code: abort_code(d) }
            }
            _ => return None,
        })
    }
}

impl SdoResponse {
    pub fn encode(&self, node: u8) -> CanFrame {
        let mut d = [0u8; 8];
        match *self {
            SdoResponse::InitiateDownload { index, sub } => {
                d[0] = 0x60;
                put_mux(&mut d, index, sub);
            }
            SdoResponse::DownloadSegment { toggle } => d[0] = 0x20 | ((toggle as u8) << 4),
            SdoResponse::InitiateUpload { index, sub, expedited, size, data } => put_initiate(&mut d, 0x40, index, sub, expedited, size, data),
            SdoResponse::UploadSegment { toggle, len, data, last } => put_segment(&mut d, toggle, len, data, last),
            SdoResponse::Abort { index, sub, code } => put_abort(&mut d, index, sub, code),
        }
        CanFrame::new(cob::SDO_TX + node as u16, &d)
    }

    pub fn decode(f: &CanFrame) -> Option<Self> {
        if f.len != 8 || f.rtr {
            return None;
        }
        let d = &f.data;
        let cmd = d[0];
        Some(match cmd >> 5 {
            3 => {
                let (index, sub) = mux(d);
                SdoResponse::InitiateDownload { index, sub }
            }
            1 => SdoResponse::DownloadSegment { toggle: cmd & 0x10 != 0 },
            2 => {
                let (index, sub) = mux(d);
                let (expedited, size, data) = initiate_bits(cmd, d);
                SdoResponse::InitiateUpload { index, sub, expedited, size, data }
            }
            0 => {
                let (toggle, len, data, last) = segment_bits(cmd, d);
                SdoResponse::UploadSegment { toggle, len, data, last }
            }
            4 => {
                let (index, sub) = mux(d);
                SdoResponse::Abort { index, sub, code: abort_code(d) }
            }
            _ => return None,
        })
    }
}

/// Largest block size (segments per sub-block) CiA 301 allows.
pub const BLOCK_MAX: u8 = 127;

/// The CRC of SDO block transfers (CiA 301 §7.2.4.3.16): CRC-16 CCITT, polynomial 0x1021,
/// initial value 0, no reflection (the "XMODEM" variant), from the `crc` crate.
const BLOCK_CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_XMODEM);

pub fn crc16(data: &[u8]) -> u16 {
    BLOCK_CRC.checksum(data)
}

/// Continue a `crc16` over more data.
pub fn crc16_update(crc: u16, data: &[u8]) -> u16 {
    let mut d = BLOCK_CRC.digest_with_initial(crc);
    d.update(data);
    d.finalize()
}

/// A client → server block transfer frame (not the data segments: `BlockSegment`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockRequest {
    /// Initiate block download; `crc`: the client can compute the CRC.
    InitiateDownload { index: u16, sub: u8, crc: bool, size: Option<u32> },
    /// End block download: `unused` bytes of the last segment carry no data (0…7).
    EndDownload { unused: u8, crc: u16 },
    /// Initiate block upload with the block size the client accepts and the protocol
    /// switch threshold (0 = none; else the server may answer with a normal upload when
    /// the data is at most `pst` bytes).
    InitiateUpload { index: u16, sub: u8, crc: bool, blksize: u8, pst: u8 },
    /// Start the upload (after the server's initiate response).
    StartUpload,
    /// Sub-block received up to `ackseq`; next sub-block of `blksize` segments.
    Ack { ackseq: u8, blksize: u8 },
    /// The client's answer to the server's end-of-upload.
    EndUploadResponse,
}

/// A server → client block transfer frame (not the data segments: `BlockSegment`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockResponse {
    InitiateDownload {
        index: u16,
        sub: u8,
        crc: bool,
        blksize: u8,
    },
    /// Sub-block received up to `ackseq`; next sub-block of `blksize` segments.
    Ack {
        ackseq: u8,
        blksize: u8,
    },
    EndDownloadResponse,
    InitiateUpload {
        index: u16,
        sub: u8,
        crc: bool,
        size: Option<u32>,
    },
    /// End block upload: `unused` bytes of the last segment carry no data.
    EndUpload {
        unused: u8,
        crc: u16,
    },
}

/// One data segment of a sub-block, either direction: sequence number 1…127, 7 data bytes,
/// `last` on the final segment of the whole transfer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockSegment {
    pub seqno: u8,
    pub last: bool,
    pub data: [u8; 7],
}

impl BlockSegment {
    fn bytes(&self) -> [u8; 8] {
        let mut d = [0u8; 8];
        d[0] = ((self.last as u8) << 7) | (self.seqno & 0x7F);
        d[1..8].copy_from_slice(&self.data);
        d
    }
    /// As sent by a client (block download).
    pub fn encode_request(&self, node: u8) -> CanFrame {
        CanFrame::new(cob::SDO_RX + node as u16, &self.bytes())
    }
    /// As sent by a server (block upload).
    pub fn encode_response(&self, node: u8) -> CanFrame {
        CanFrame::new(cob::SDO_TX + node as u16, &self.bytes())
    }
    /// Sequence number 0 does not exist (0x80 with it is an abort).
    pub fn decode(f: &CanFrame) -> Option<Self> {
        if f.len != 8 || f.rtr || f.data[0] & 0x7F == 0 {
            return None;
        }
        let mut data = [0u8; 7];
        data.copy_from_slice(&f.data[1..8]);
        Some(BlockSegment { seqno: f.data[0] & 0x7F, last: f.data[0] & 0x80 != 0, data })
    }
}

impl BlockRequest {
    pub fn encode(&self, node: u8) -> CanFrame {
        let mut d = [0u8; 8];
        match *self {
            BlockRequest::InitiateDownload { index, sub, crc, size } => {
                d[0] = 0xC0 | ((crc as u8) << 2) | ((size.is_some() as u8) << 1);
                put_mux(&mut d, index, sub);
                d[4..8].copy_from_slice(&size.unwrap_or(0).to_le_bytes());
            }
            BlockRequest::EndDownload { unused, crc } => {
                d[0] = 0xC1 | ((unused.min(7)) << 2);
                d[1..3].copy_from_slice(&crc.to_le_bytes());
            }
            BlockRequest::InitiateUpload { index, sub, crc, blksize, pst } => {
                d[0] = 0xA0 | ((crc as u8) << 2);
                put_mux(&mut d, index, sub);
                d[4] = blksize;
                d[5] = pst;
            }
            BlockRequest::StartUpload => d[0] = 0xA3,
            BlockRequest::Ack { ackseq, blksize } => {
                d[0] = 0xA2;
                d[1] = ackseq;
                d[2] = blksize;
            }
            BlockRequest::EndUploadResponse => d[0] = 0xA1,
        }
        CanFrame::new(cob::SDO_RX + node as u16, &d)
    }

    /// Decode a client block frame (command specifier 5 or 6); `None` for anything else.
    pub fn decode(f: &CanFrame) -> Option<Self> {
        if f.len != 8 || f.rtr {
            return None;
        }
        let d = &f.data;
        let cmd = d[0];
        match cmd >> 5 {
            6 if cmd & 0x01 == 0 => {
                let (index, sub) = mux(d);
                let size = (cmd & 0x02 != 0).then(|| u32::from_le_bytes([d[4], d[5], d[6], d[7]]));
                Some(BlockRequest::InitiateDownload { index, sub, crc: cmd & 0x04 != 0, size })
            }
            6 => Some(BlockRequest::EndDownload { unused: (cmd >> 2) & 0x07, crc: u16::from_le_bytes([d[1], d[2]]) }),
            5 => match cmd & 0x03 {
                0 => {
                    let (index, sub) = mux(d);
                    Some(BlockRequest::InitiateUpload { index, sub, crc: cmd & 0x04 != 0, blksize: d[4], pst: d[5] })
                }
                1 => Some(BlockRequest::EndUploadResponse),
                2 => Some(BlockRequest::Ack { ackseq: d[1], blksize: d[2] }),
                _ => Some(BlockRequest::StartUpload),
            },
            _ => None,
        }
    }
}

impl BlockResponse {
    pub fn encode(&self, node: u8) -> CanFrame {
        let mut d = [0u8; 8];
        match *self {
            BlockResponse::InitiateDownload { index, sub, crc, blksize } => {
                d[0] = 0xA0 | ((crc as u8) << 2);
                put_mux(&mut d, index, sub);
                d[4] = blksize;
            }
            BlockResponse::Ack { ackseq, blksize } => {
                d[0] = 0xA2;
                d[1] = ackseq;
                d[2] = blksize;
            }
            BlockResponse::EndDownloadResponse => d[0] = 0xA1,
            BlockResponse::InitiateUpload { index, sub, crc, size } => {
                d[0] = 0xC0 | ((crc as u8) << 2) | ((size.is_some() as u8) << 1);
                put_mux(&mut d, index, sub);
                d[4..8].copy_from_slice(&size.unwrap_or(0).to_le_bytes());
            }
            BlockResponse::EndUpload { unused, crc } => {
                d[0] = 0xC1 | ((unused.min(7)) << 2);
                d[1..3].copy_from_slice(&crc.to_le_bytes());
            }
        }
        CanFrame::new(cob::SDO_TX + node as u16, &d)
    }

    /// Decode a server block frame (command specifier 5 or 6); `None` for anything else.
    pub fn decode(f: &CanFrame) -> Option<Self> {
        if f.len != 8 || f.rtr {
            return None;
        }
        let d = &f.data;
        let cmd = d[0];
        match cmd >> 5 {
            5 => match cmd & 0x03 {
                0 => {
                    let (index, sub) = mux(d);
                    Some(BlockResponse::InitiateDownload { index, sub, crc: cmd & 0x04 != 0, blksize: d[4] })
                }
                1 => Some(BlockResponse::EndDownloadResponse),
                2 => Some(BlockResponse::Ack { ackseq: d[1], blksize: d[2] }),
                _ => None,
            },
            6 if cmd & 0x01 == 0 => {
                let (index, sub) = mux(d);
                let size = (cmd & 0x02 != 0).then(|| u32::from_le_bytes([d[4], d[5], d[6], d[7]]));
                Some(BlockResponse::InitiateUpload { index, sub, crc: cmd & 0x04 != 0, size })
            }
            6 => Some(BlockResponse::EndUpload { unused: (cmd >> 2) & 0x07, crc: u16::from_le_bytes([d[1], d[2]]) }),
            _ => None,
        }
    }
}

/// CiA 301 SDO abort codes (Table 22).
pub mod abort {
    pub const TOGGLE: u32 = 0x0503_0000;
    pub const TIMEOUT: u32 = 0x0504_0000;
    pub const BAD_COMMAND: u32 = 0x0504_0001;
    pub const INVALID_BLOCK_SIZE: u32 = 0x0504_0002;
    pub const INVALID_SEQUENCE: u32 = 0x0504_0003;
    pub const CRC: u32 = 0x0504_0004;
    pub const OUT_OF_MEMORY: u32 = 0x0504_0005;
    pub const UNSUPPORTED_ACCESS: u32 = 0x0601_0000;
    pub const WRITE_ONLY: u32 = 0x0601_0001;
    pub const READ_ONLY: u32 = 0x0601_0002;
    pub const NO_OBJECT: u32 = 0x0602_0000;
    pub const NOT_MAPPABLE: u32 = 0x0604_0041;
    pub const PDO_TOO_LONG: u32 = 0x0604_0042;
    pub const PARAM_INCOMPATIBLE: u32 = 0x0604_0043;
    pub const DEVICE_INCOMPATIBLE: u32 = 0x0604_0047;
    pub const HARDWARE: u32 = 0x0606_0000;
    pub const TYPE_MISMATCH: u32 = 0x0607_0010;
    pub const TOO_LONG: u32 = 0x0607_0012;
    pub const TOO_SHORT: u32 = 0x0607_0013;
    pub const NO_SUBINDEX: u32 = 0x0609_0011;
    pub const INVALID_VALUE: u32 = 0x0609_0030;
    pub const VALUE_TOO_HIGH: u32 = 0x0609_0031;
    pub const VALUE_TOO_LOW: u32 = 0x0609_0032;
    pub const MAX_LESS_THAN_MIN: u32 = 0x0609_0036;
    pub const RESOURCE: u32 = 0x060A_0023;
    pub const GENERAL: u32 = 0x0800_0000;
    pub const STORE: u32 = 0x0800_0020;
    pub const STORE_LOCAL: u32 = 0x0800_0021;
    pub const STORE_STATE: u32 = 0x0800_0022;
    pub const NO_OD: u32 = 0x0800_0023;
    pub const NO_DATA: u32 = 0x0800_0024;
}

/// Every CiA 301 abort code in words.
pub fn abort_text(code: u32) -> &'static str {
    match code {
        0x0503_0000 => "toggle bit not alternated",
        0x0504_0000 => "SDO protocol timed out",
        0x0504_0001 => "client/server command specifier not valid or unknown",
        0x0504_0002 => "invalid block size (block mode only)",
        0x0504_0003 => "invalid sequence number (block mode only)",
        0x0504_0004 => "CRC error (block mode only)",
        0x0504_0005 => "out of memory",
        0x0601_0000 => "unsupported access to an object",
        0x0601_0001 => "attempt to read a write only object",
        0x0601_0002 => "attempt to write a read only object",
        0x0602_0000 => "object does not exist in the object dictionary",
        0x0604_0041 => "object cannot be mapped to the PDO",
        0x0604_0042 => "the number and length of the objects to be mapped would exceed PDO length",
        0x0604_0043 => "general parameter incompatibility reason",
        0x0604_0047 => "general internal incompatibility in the device",
        0x0606_0000 => "access failed due to a hardware error",
        0x0607_0010 => "data type does not match, length of service parameter does not match",
        0x0607_0012 => "data type does not match, length of service parameter too high",
        0x0607_0013 => "data type does not match, length of service parameter too low",
        0x0609_0011 => "sub-index does not exist",
        0x0609_0030 => "invalid value for parameter (download only)",
        0x0609_0031 => "value of parameter written too high (download only)",
        0x0609_0032 => "value of parameter written too low (download only)",
        0x0609_0036 => "maximum value is less than minimum value",
        0x060A_0023 => "resource not available: SDO connection",
        0x0800_0000 => "general error",
        0x0800_0020 => "data cannot be transferred or stored to the application",
        0x0800_0021 => "data cannot be transferred or stored to the application because of local control",
        0x0800_0022 => "data cannot be transferred or stored to the application because of the present device state",
        0x0800_0023 => "object dictionary dynamic generation fails or no object dictionary is present",
        0x0800_0024 => "no data available",
        _ => "unknown abort code",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(f: CanFrame) -> String {
        format!("{f:?}")
    }

    #[test]
    fn expedited_download_is_byte_exact() {
        // Write 0x6060 sub 0 = 8 (INTEGER8) to node 1: 2F 60 60 00 08 00 00 00.
        let r = SdoRequest::InitiateDownload { index: 0x6060, sub: 0, expedited: true, size: Some(1), data: [8, 0, 0, 0] };
        assert_eq!(hex(r.encode(1)), "601#2F60600008000000");
        assert_eq!(SdoRequest::decode(&r.encode(1)), Some(r));
        // 4 bytes: 23, 2 bytes: 2B.
        let r4 = SdoRequest::InitiateDownload { index: 0x1017, sub: 0, expedited: true, size: Some(4), data: [0xE8, 3, 0, 0] };
        assert_eq!(hex(r4.encode(2)), "602#23171000E8030000");
        let r2 = SdoRequest::InitiateDownload { index: 0x1017, sub: 0, expedited: true, size: Some(2), data: [0xE8, 3, 0, 0] };
        assert_eq!(hex(r2.encode(2)), "602#2B171000E8030000");
    }

    #[test]
    fn upload_and_responses_are_byte_exact() {
        assert_eq!(hex(SdoRequest::InitiateUpload { index: 0x1018, sub: 1 }.encode(3)), "603#4018100100000000");
        let resp = SdoResponse::InitiateUpload { index: 0x1000, sub: 0, expedited: true, size: Some(4), data: [0x92, 0x01, 0x02, 0x00] };
        assert_eq!(hex(resp.encode(3)), "583#4300100092010200");
        assert_eq!(SdoResponse::decode(&resp.encode(3)), Some(resp));
        assert_eq!(hex(SdoResponse::InitiateDownload { index: 0x6040, sub: 0 }.encode(1)), "581#6040600000000000");
    }

    #[test]
    fn abort_is_byte_exact_and_in_words() {
        let a = SdoResponse::Abort { index: 0x2345, sub: 0, code: abort::NO_OBJECT };
        assert_eq!(hex(a.encode(1)), "581#8045230000000206");
        assert_eq!(abort_text(abort::NO_OBJECT), "object does not exist in the object dictionary");
    }

    #[test]
    fn segments_round_trip() {
        let s = SdoResponse::UploadSegment { toggle: true, len: 3, data: *b"abc\0\0\0\0", last: true };
        let f = s.encode(4);
        assert_eq!(f.data[0], 0x10 | (4 << 1) | 1);
        assert_eq!(SdoResponse::decode(&f), Some(s));
        let init = SdoResponse::InitiateUpload { index: 0x1008, sub: 0, expedited: false, size: Some(10), data: [10, 0, 0, 0] };
        assert_eq!(hex(init.encode(4)), "584#410810000A000000");
        let d = SdoRequest::DownloadSegment { toggle: false, len: 7, data: *b"1234567", last: false };
        assert_eq!(SdoRequest::decode(&d.encode(4)), Some(d));
    }

    #[test]
    fn crc16_is_ccitt_xmodem() {
        // The standard check value of CRC-16/XMODEM.
        assert_eq!(crc16(b"123456789"), 0x31C3);
        assert_eq!(crc16(b""), 0);
        assert_eq!(crc16_update(crc16(b"1234"), b"56789"), 0x31C3);
    }

    #[test]
    fn block_download_frames_are_byte_exact() {
        // Initiate with CRC and size 1000 to node 5: C6 mux size.
        let r = BlockRequest::InitiateDownload { index: 0x2200, sub: 0, crc: true, size: Some(1000) };
        assert_eq!(hex(r.encode(5)), "605#C6002200E8030000");
        assert_eq!(BlockRequest::decode(&r.encode(5)), Some(r));
        let a = BlockResponse::InitiateDownload { index: 0x2200, sub: 0, crc: true, blksize: 127 };
        assert_eq!(hex(a.encode(5)), "585#A40022007F000000");
        assert_eq!(BlockResponse::decode(&a.encode(5)), Some(a));
        let seg = BlockSegment { seqno: 3, last: true, data: *b"abcdefg" };
        assert_eq!(hex(seg.encode_request(5)), "605#8361626364656667");
        assert_eq!(BlockSegment::decode(&seg.encode_request(5)), Some(seg));
        let ack = BlockResponse::Ack { ackseq: 3, blksize: 127 };
        assert_eq!(hex(ack.encode(5)), "585#A2037F0000000000");
        assert_eq!(BlockResponse::decode(&ack.encode(5)), Some(ack));
        // End: 2 unused bytes, CRC 0x31C3: C1 | 2<<2 = C9, CRC little-endian.
        let end = BlockRequest::EndDownload { unused: 2, crc: 0x31C3 };
        assert_eq!(hex(end.encode(5)), "605#C9C3310000000000");
        assert_eq!(BlockRequest::decode(&end.encode(5)), Some(end));
        assert_eq!(hex(BlockResponse::EndDownloadResponse.encode(5)), "585#A100000000000000");
    }

    #[test]
    fn block_upload_frames_are_byte_exact() {
        let r = BlockRequest::InitiateUpload { index: 0x1008, sub: 0, crc: true, blksize: 127, pst: 0 };
        assert_eq!(hex(r.encode(1)), "601#A40810007F000000");
        assert_eq!(BlockRequest::decode(&r.encode(1)), Some(r));
        let a = BlockResponse::InitiateUpload { index: 0x1008, sub: 0, crc: true, size: Some(9) };
        assert_eq!(hex(a.encode(1)), "581#C608100009000000");
        assert_eq!(BlockResponse::decode(&a.encode(1)), Some(a));
        assert_eq!(hex(BlockRequest::StartUpload.encode(1)), "601#A300000000000000");
        assert_eq!(BlockRequest::decode(&BlockRequest::StartUpload.encode(1)), Some(BlockRequest::StartUpload));
        let ack = BlockRequest::Ack { ackseq: 127, blksize: 64 };
        assert_eq!(hex(ack.encode(1)), "601#A27F400000000000");
        assert_eq!(BlockRequest::decode(&ack.encode(1)), Some(ack));
        let end = BlockResponse::EndUpload { unused: 5, crc: 0xBEEF };
        assert_eq!(hex(end.encode(1)), "581#D5EFBE0000000000");
        assert_eq!(BlockResponse::decode(&end.encode(1)), Some(end));
        assert_eq!(BlockRequest::decode(&BlockRequest::EndUploadResponse.encode(1)), Some(BlockRequest::EndUploadResponse));
        // Segmented and expedited frames are not block frames, and an abort is no segment.
        assert_eq!(BlockRequest::decode(&SdoRequest::InitiateUpload { index: 0x1000, sub: 0 }.encode(1)), None);
        assert_eq!(BlockSegment::decode(&CanFrame::new(0x581, &[0x80, 0, 0x10, 0, 0, 0, 2, 6])), None);
    }

    #[test]
    fn short_frames_are_refused() {
        assert_eq!(SdoRequest::decode(&CanFrame::new(0x601, &[0x40, 0, 0x10])), None);
    }
}
