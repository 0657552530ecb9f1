//! SDO client, sans-I/O: frames in, frames out, deadlines checked by `poll`. Expedited,
//! segmented and block upload and download (block with the CRC when the server offers it).
//! One transfer at a time per server, as CiA 301 requires.

use cncgw_bus::canopen::cob;
use cncgw_bus::canopen::sdo::{abort, abort_text, crc16, BlockRequest, BlockResponse, BlockSegment, SdoRequest, SdoResponse, BLOCK_MAX};
use cncgw_bus::CanFrame;

#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SdoError {
    #[error("SDO abort 0x{code:08X} {}", abort_text(*code))]
    Abort { code: u32 },
    #[error("no SDO answer within {timeout_ms} ms (is the node powered, on the bus, with this node id?)")]
    Timeout { timeout_ms: u32 },
    #[error("SDO protocol error: {0}")]
    Protocol(&'static str),
}

#[derive(Debug)]
enum Phase {
    Idle,
    DownloadInit,
    DownloadSeg {
        offset: usize,
        toggle: bool,
        last_sent: bool,
    },
    UploadInit,
    UploadSeg {
        toggle: bool,
    },
    BlockDownInit,
    /// Sub-block sent from `block_start`; `last_seq`: the segment that ends the data, if it
    /// was in this sub-block.
    BlockDownSub {
        block_start: usize,
        last_seq: Option<u8>,
    },
    BlockDownEnd,
    BlockUpInit,
    /// `ackseq`: last in-sequence segment of the sub-block being received.
    BlockUpSub {
        ackseq: u8,
        blksize: u8,
        last_seen: bool,
    },
    BlockUpEnd,
    Done,
}

/// Segments per sub-block the client accepts in a block upload.
const CLIENT_BLKSIZE: u8 = BLOCK_MAX;
/// Largest object the client takes (a guard against a server that never ends).
const MAX_UPLOAD: usize = 1 << 20;

pub struct SdoClient {
    node: u8,
    phase: Phase,
    index: u16,
    sub: u8,
    buf: Vec<u8>,
    deadline_ns: u64,
    timeout_ns: u64,
    result: Option<Result<Vec<u8>, SdoError>>,
    /// Block transfer: both sides compute the CRC; announced upload size.
    crc: bool,
    size: Option<u32>,
    /// `start_upload_small`: an expedited answer is kept here, not in a `Vec` (the cycle
    /// polls with it and must not allocate).
    want_small: bool,
    small: Option<u32>,
    /// The object of a transfer given up in its initiate phase for this one (a background
    /// read the cycle was doing when a fault diagnosis or a blocking transfer took the
    /// channel): its late answer or abort is dropped once, not taken for this transfer's.
    abandoned: Option<(u16, u8)>,
}

impl SdoClient {
    pub fn new(node: u8, timeout_ms: u32) -> Self {
        SdoClient {
            node,
            phase: Phase::Idle,
            index: 0,
            sub: 0,
            buf: Vec::with_capacity(64),
            deadline_ns: 0,
            timeout_ns: timeout_ms as u64 * 1_000_000,
            result: None,
            crc: false,
            size: None,
            want_small: false,
            small: None,
            abandoned: None,
        }
    }

    pub fn busy(&self) -> bool {
        !matches!(self.phase, Phase::Idle | Phase::Done)
    }

    /// Start reading `index:sub`; returns the frame to send.
    pub fn start_upload(&mut self, index: u16, sub: u8, now_ns: u64) -> CanFrame {
        self.begin(index, sub, now_ns);
        self.phase = Phase::UploadInit;
        SdoRequest::InitiateUpload { index, sub }.encode(self.node)
    }

    /// Start writing `data` to `index:sub`; returns the frame to send. Up to 4 bytes go
    /// expedited, longer values segmented.
    pub fn start_download(&mut self, index: u16, sub: u8, data: &[u8], now_ns: u64) -> CanFrame {
        self.begin(index, sub, now_ns);
        self.buf.extend_from_slice(data);
        self.phase = Phase::DownloadInit;
        if data.len() <= 4 && !data.is_empty() {
            let mut d = [0u8; 4];
            d[..data.len()].copy_from_slice(data);
            SdoRequest::InitiateDownload { index, sub, expedited: true, size: Some(data.len() as u32), data: d }.encode(self.node)
        } else {
            SdoRequest::InitiateDownload { index, sub, expedited: false, size: Some(data.len() as u32), data: [0; 4] }.encode(self.node)
        }
    }

    /// Start a block upload of `index:sub` (CRC offered, no protocol switch); returns the
    /// frame to send.
    pub fn start_block_upload(&mut self, index: u16, sub: u8, now_ns: u64) -> CanFrame {
        self.begin(index, sub, now_ns);
        self.phase = Phase::BlockUpInit;
        BlockRequest::InitiateUpload { index, sub, crc: true, blksize: CLIENT_BLKSIZE, pst: 0 }.encode(self.node)
    }

    /// Start a block download of `data` to `index:sub` (size indicated, CRC offered);
    /// returns the frame to send.
    pub fn start_block_download(&mut self, index: u16, sub: u8, data: &[u8], now_ns: u64) -> CanFrame {
        self.begin(index, sub, now_ns);
        self.buf.extend_from_slice(data);
        self.phase = Phase::BlockDownInit;
        BlockRequest::InitiateDownload { index, sub, crc: true, size: Some(data.len() as u32) }.encode(self.node)
    }

    /// `start_upload` for an object of at most 4 bytes whose answer is taken with
    /// `take_expedited`: no allocation for an expedited answer.
    pub fn start_upload_small(&mut self, index: u16, sub: u8, now_ns: u64) -> CanFrame {
        let f = self.start_upload(index, sub, now_ns);
        self.want_small = true;
        f
    }

    fn begin(&mut self, index: u16, sub: u8, now_ns: u64) {
        self.abandoned =
            matches!(self.phase, Phase::UploadInit | Phase::DownloadInit).then_some((self.index, self.sub)).filter(|&o| o != (index, sub));
        self.want_small = false;
        self.small = None;
        self.index = index;
        self.sub = sub;
        self.buf.clear();
        self.result = None;
        self.crc = false;
        self.size = None;
        self.deadline_ns = now_ns + self.timeout_ns;
    }

    fn finish(&mut self, r: Result<Vec<u8>, SdoError>) {
        self.result = Some(r);
        self.phase = Phase::Done;
    }

    fn abort_frame(&self, code: u32) -> CanFrame {
        SdoRequest::Abort { index: self.index, sub: self.sub, code }.encode(self.node)
    }

    /// Feed a received frame. Returns the frames to send (a whole sub-block in a block
    /// download; else at most one).
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64) -> Vec<CanFrame> {
        if f.cob_id() != cob::SDO_TX + self.node as u16 || !self.busy() {
            return Vec::new();
        }
        if self.in_block() {
            if f.len != 8 {
                return self.protocol("malformed SDO response", abort::BAD_COMMAND);
            }
            self.deadline_ns = now_ns + self.timeout_ns;
            return self.on_block_frame(f);
        }
        self.on_plain_frame(f, now_ns).into_iter().collect()
    }

    fn in_block(&self) -> bool {
        matches!(
            self.phase,
            Phase::BlockDownInit
                | Phase::BlockDownSub { .. }
                | Phase::BlockDownEnd
                | Phase::BlockUpInit
                | Phase::BlockUpSub { .. }
                | Phase::BlockUpEnd
        )
    }

    fn on_plain_frame(&mut self, f: &CanFrame, now_ns: u64) -> Option<CanFrame> {
        let Some(resp) = SdoResponse::decode(f) else {
            self.finish(Err(SdoError::Protocol("malformed SDO response")));
            return Some(self.abort_frame(abort::BAD_COMMAND));
        };
        let about = match resp {
            SdoResponse::InitiateUpload { index, sub, .. } | SdoResponse::InitiateDownload { index, sub } | SdoResponse::Abort { index, sub, .. } => {
                Some((index, sub))
            }
            _ => None,
        };
        if about.is_some() && about == self.abandoned {
            self.abandoned = None;
            return None;
        }
        self.deadline_ns = now_ns + self.timeout_ns;
        if let SdoResponse::Abort { code, .. } = resp {
            self.finish(Err(SdoError::Abort { code }));
            return None;
        }
        match (&self.phase, resp) {
            (Phase::UploadInit, SdoResponse::InitiateUpload { index, sub, expedited, size, data }) => {
                if index != self.index || sub != self.sub {
                    self.finish(Err(SdoError::Protocol("response for another object")));
                    return Some(self.abort_frame(abort::GENERAL));
                }
                if expedited && self.want_small {
                    let n = size.unwrap_or(4).min(4) as usize;
                    let mut b = [0u8; 4];
                    b[..n].copy_from_slice(&data[..n]);
                    self.small = Some(u32::from_le_bytes(b));
                    self.phase = Phase::Done;
                    None
                } else if expedited {
                    let n = size.unwrap_or(4).min(4) as usize;
                    self.finish(Ok(data[..n].to_vec()));
                    None
                } else {
                    self.phase = Phase::UploadSeg { toggle: false };
                    Some(SdoRequest::UploadSegment { toggle: false }.encode(self.node))
                }
            }
            (Phase::UploadSeg { toggle }, SdoResponse::UploadSegment { toggle: t, len, data, last }) => {
                let toggle = *toggle;
                if t != toggle {
                    self.finish(Err(SdoError::Abort { code: abort::TOGGLE }));
                    return Some(self.abort_frame(abort::TOGGLE));
                }
                self.buf.extend_from_slice(&data[..len as usize]);
                if self.buf.len() > 1 << 20 {
                    self.finish(Err(SdoError::Abort { code: abort::OUT_OF_MEMORY }));
                    return Some(self.abort_frame(abort::OUT_OF_MEMORY));
                }
                if last {
                    let out = std::mem::take(&mut self.buf);
                    self.finish(Ok(out));
                    None
                } else {
                    self.phase = Phase::UploadSeg { toggle: !toggle };
                    Some(SdoRequest::UploadSegment { toggle: !toggle }.encode(self.node))
                }
            }
            (Phase::DownloadInit, SdoResponse::InitiateDownload { index, sub }) => {
                if index != self.index || sub != self.sub {
                    self.finish(Err(SdoError::Protocol("response for another object")));
                    return Some(self.abort_frame(abort::GENERAL));
                }
                if self.buf.len() <= 4 && !self.buf.is_empty() {
                    self.finish(Ok(Vec::new()));
                    None
                } else {
                    self.phase = Phase::DownloadSeg { offset: 0, toggle: false, last_sent: false };
                    Some(self.next_segment())
                }
            }
            (Phase::DownloadSeg { toggle, last_sent, .. }, SdoResponse::DownloadSegment { toggle: t }) => {
                if t != *toggle {
                    self.finish(Err(SdoError::Abort { code: abort::TOGGLE }));
                    return Some(self.abort_frame(abort::TOGGLE));
                }
                if *last_sent {
                    self.finish(Ok(Vec::new()));
                    None
                } else {
                    if let Phase::DownloadSeg { toggle, .. } = &mut self.phase {
                        *toggle = !*toggle;
                    }
                    Some(self.next_segment())
                }
            }
            _ => {
                self.finish(Err(SdoError::Protocol("unexpected SDO response for this transfer")));
                Some(self.abort_frame(abort::BAD_COMMAND))
            }
        }
    }

    fn fail(&mut self, code: u32) -> Vec<CanFrame> {
        self.finish(Err(SdoError::Abort { code }));
        vec![self.abort_frame(code)]
    }

    fn protocol(&mut self, why: &'static str, code: u32) -> Vec<CanFrame> {
        self.finish(Err(SdoError::Protocol(why)));
        vec![self.abort_frame(code)]
    }

    fn on_block_frame(&mut self, f: &CanFrame) -> Vec<CanFrame> {
        if f.data[0] == 0x80 {
            let code = u32::from_le_bytes([f.data[4], f.data[5], f.data[6], f.data[7]]);
            self.finish(Err(SdoError::Abort { code }));
            return Vec::new();
        }
        if let Phase::BlockUpSub { ackseq, blksize, last_seen } = &mut self.phase {
            let Some(seg) = BlockSegment::decode(f) else {
                return self.protocol("malformed block segment", abort::INVALID_SEQUENCE);
            };
            // Out-of-sequence segments are dropped; the acknowledgement at the end of the
            // sub-block tells the server where to restart.
            if seg.seqno == *ackseq + 1 {
                *ackseq = seg.seqno;
                self.buf.extend_from_slice(&seg.data);
                *last_seen = seg.last;
            }
            if self.buf.len() > MAX_UPLOAD {
                return self.fail(abort::OUT_OF_MEMORY);
            }
            if seg.seqno >= *blksize || seg.last {
                let (ack, done) = (*ackseq, *last_seen);
                self.phase = if done { Phase::BlockUpEnd } else { Phase::BlockUpSub { ackseq: 0, blksize: CLIENT_BLKSIZE, last_seen: false } };
                return vec![BlockRequest::Ack { ackseq: ack, blksize: CLIENT_BLKSIZE }.encode(self.node)];
            }
            return Vec::new();
        }
        let Some(resp) = BlockResponse::decode(f) else {
            return self.protocol("unexpected frame in an SDO block transfer", abort::BAD_COMMAND);
        };
        match (&self.phase, resp) {
            (Phase::BlockUpInit, BlockResponse::InitiateUpload { index, sub, crc, size }) => {
                if index != self.index || sub != self.sub {
                    return self.protocol("response for another object", abort::GENERAL);
                }
                self.crc = crc;
                self.size = size;
                self.phase = Phase::BlockUpSub { ackseq: 0, blksize: CLIENT_BLKSIZE, last_seen: false };
                vec![BlockRequest::StartUpload.encode(self.node)]
            }
            (Phase::BlockUpEnd, BlockResponse::EndUpload { unused, crc }) => {
                let n = self.buf.len().saturating_sub(unused as usize);
                self.buf.truncate(n);
                if self.size.is_some_and(|s| s as usize != self.buf.len()) {
                    return self.protocol("block upload length differs from the size announced", abort::GENERAL);
                }
                if self.crc && crc16(&self.buf) != crc {
                    return self.fail(abort::CRC);
                }
                let out = std::mem::take(&mut self.buf);
                self.finish(Ok(out));
                vec![BlockRequest::EndUploadResponse.encode(self.node)]
            }
            (Phase::BlockDownInit, BlockResponse::InitiateDownload { index, sub, crc, blksize }) => {
                if index != self.index || sub != self.sub {
                    return self.protocol("response for another object", abort::GENERAL);
                }
                if blksize == 0 || blksize > BLOCK_MAX {
                    return self.fail(abort::INVALID_BLOCK_SIZE);
                }
                self.crc = crc;
                self.sub_block(0, blksize)
            }
            (&Phase::BlockDownSub { block_start, last_seq }, BlockResponse::Ack { ackseq, blksize }) => {
                if ackseq > last_seq.unwrap_or(BLOCK_MAX) {
                    return self.fail(abort::INVALID_SEQUENCE);
                }
                if last_seq.is_some_and(|l| ackseq >= l) {
                    let in_last = self.buf.len() - (block_start + 7 * (ackseq as usize - 1)).min(self.buf.len());
                    let unused = 7 - in_last.min(7) as u8;
                    let crc = if self.crc { crc16(&self.buf) } else { 0 };
                    self.phase = Phase::BlockDownEnd;
                    return vec![BlockRequest::EndDownload { unused, crc }.encode(self.node)];
                }
                if blksize == 0 || blksize > BLOCK_MAX {
                    return self.fail(abort::INVALID_BLOCK_SIZE);
                }
                // The next sub-block starts after the last acknowledged segment (a
                // retransmission if the server missed some).
                self.sub_block((block_start + 7 * ackseq as usize).min(self.buf.len()), blksize)
            }
            (Phase::BlockDownEnd, BlockResponse::EndDownloadResponse) => {
                self.finish(Ok(Vec::new()));
                Vec::new()
            }
            _ => self.protocol("unexpected SDO block response for this transfer", abort::BAD_COMMAND),
        }
    }

    /// The segments of one sub-block of a block download, from byte `start`.
    fn sub_block(&mut self, start: usize, blksize: u8) -> Vec<CanFrame> {
        let mut out = Vec::with_capacity(blksize as usize);
        let mut pos = start;
        let mut last_seq = None;
        for seqno in 1..=blksize {
            let n = (self.buf.len() - pos).min(7);
            let mut data = [0u8; 7];
            data[..n].copy_from_slice(&self.buf[pos..pos + n]);
            pos += n;
            let last = pos >= self.buf.len();
            out.push(BlockSegment { seqno, last, data }.encode_request(self.node));
            if last {
                last_seq = Some(seqno);
                break;
            }
        }
        self.phase = Phase::BlockDownSub { block_start: start, last_seq };
        out
    }

    fn next_segment(&mut self) -> CanFrame {
        let Phase::DownloadSeg { offset, toggle, last_sent } = &mut self.phase else {
            return self.abort_frame(abort::GENERAL);
        };
        let n = (self.buf.len() - *offset).min(7);
        let mut data = [0u8; 7];
        data[..n].copy_from_slice(&self.buf[*offset..*offset + n]);
        *offset += n;
        let last = *offset >= self.buf.len();
        *last_sent = last;
        SdoRequest::DownloadSegment { toggle: *toggle, len: n as u8, data, last }.encode(self.node)
    }

    /// Check the deadline. On timeout the transfer ends and the abort frame to send is
    /// returned (CiA 301: the client aborts with 0x05040000).
    pub fn poll(&mut self, now_ns: u64) -> Option<CanFrame> {
        if self.busy() && now_ns >= self.deadline_ns {
            self.finish(Err(SdoError::Timeout { timeout_ms: (self.timeout_ns / 1_000_000) as u32 }));
            return Some(self.abort_frame(abort::TIMEOUT));
        }
        None
    }

    /// The finished result of a `start_upload_small` (little-endian, zero-extended), taken
    /// once. Allocation-free for an expedited answer.
    pub fn take_expedited(&mut self) -> Option<Result<u32, SdoError>> {
        if let Some(v) = self.small.take() {
            self.phase = Phase::Idle;
            return Some(Ok(v));
        }
        self.take_result().map(|r| {
            r.map(|d| {
                let mut b = [0u8; 4];
                let n = d.len().min(4);
                b[..n].copy_from_slice(&d[..n]);
                u32::from_le_bytes(b)
            })
        })
    }

    /// The finished transfer's result (taken once).
    pub fn take_result(&mut self) -> Option<Result<Vec<u8>, SdoError>> {
        let r = self.result.take();
        if r.is_some() {
            self.phase = Phase::Idle;
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_expedited_upload_without_a_vec() {
        let mut c = SdoClient::new(3, 100);
        c.start_upload_small(0x6061, 0, 0);
        let resp = CanFrame::new(0x583, &[0x4F, 0x61, 0x60, 0x00, 0x08, 0, 0, 0]);
        assert_eq!(c.on_frame(&resp, 10), vec![]);
        assert_eq!(c.take_expedited(), Some(Ok(8)));
        assert!(!c.busy());
        assert_eq!(c.take_expedited(), None);
        c.start_upload_small(0x6061, 0, 20);
        assert_eq!(c.poll(200_000_000).map(|f| f.data[0]), Some(0x80));
        assert!(matches!(c.take_expedited(), Some(Err(SdoError::Timeout { .. }))));
    }

    #[test]
    fn the_late_answer_of_a_read_given_up_is_not_taken_for_the_next_transfer() {
        // The cycle's torque read (0x6077) is under way when a fault diagnosis reads 0x603F.
        let mut c = SdoClient::new(3, 100);
        c.start_upload_small(0x6077, 0, 0);
        c.start_upload(0x603F, 0, 1);
        let late = SdoResponse::InitiateUpload { index: 0x6077, sub: 0, expedited: true, size: Some(2), data: [5, 0, 0, 0] }.encode(3);
        assert_eq!(c.on_frame(&late, 2), vec![], "dropped, no abort sent");
        assert!(c.busy() && c.take_result().is_none());
        let answer = SdoResponse::InitiateUpload { index: 0x603F, sub: 0, expedited: true, size: Some(2), data: [0x10, 0x23, 0, 0] }.encode(3);
        assert_eq!(c.on_frame(&answer, 3), vec![]);
        assert_eq!(c.take_result(), Some(Ok(vec![0x10, 0x23])));
        // Only once: a second answer for another object is still a protocol error.
        c.start_upload(0x603F, 0, 4);
        assert!(!c.on_frame(&late, 5).is_empty());
        assert!(matches!(c.take_result(), Some(Err(SdoError::Protocol(_)))));
    }

    #[test]
    fn expedited_upload() {
        let mut c = SdoClient::new(3, 100);
        let req = c.start_upload(0x1000, 0, 0);
        assert_eq!(format!("{req:?}"), "603#4000100000000000");
        let resp = CanFrame::new(0x583, &[0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]);
        assert_eq!(c.on_frame(&resp, 10), vec![]);
        assert_eq!(c.take_result(), Some(Ok(vec![0x92, 0x01, 0x02, 0x00])));
        assert!(!c.busy());
    }

    #[test]
    fn segmented_upload_with_toggles() {
        let mut c = SdoClient::new(1, 100);
        c.start_upload(0x1008, 0, 0);
        let next = c
            .on_frame(&SdoResponse::InitiateUpload { index: 0x1008, sub: 0, expedited: false, size: Some(10), data: [10, 0, 0, 0] }.encode(1), 1)
            .pop()
            .unwrap();
        assert_eq!(format!("{next:?}"), "601#6000000000000000");
        let next = c.on_frame(&SdoResponse::UploadSegment { toggle: false, len: 7, data: *b"cncgw s", last: false }.encode(1), 2).pop().unwrap();
        assert_eq!(format!("{next:?}"), "601#7000000000000000");
        assert_eq!(c.on_frame(&SdoResponse::UploadSegment { toggle: true, len: 3, data: *b"im\0\0\0\0\0", last: true }.encode(1), 3), vec![]);
        assert_eq!(c.take_result(), Some(Ok(b"cncgw sim\0".to_vec())));
    }

    #[test]
    fn wrong_toggle_aborts() {
        let mut c = SdoClient::new(1, 100);
        c.start_upload(0x1008, 0, 0);
        c.on_frame(&SdoResponse::InitiateUpload { index: 0x1008, sub: 0, expedited: false, size: None, data: [0; 4] }.encode(1), 1);
        let ab = c.on_frame(&SdoResponse::UploadSegment { toggle: true, len: 7, data: [0; 7], last: false }.encode(1), 2).pop().unwrap();
        assert_eq!(format!("{ab:?}"), "601#8008100000000305");
        assert_eq!(c.take_result(), Some(Err(SdoError::Abort { code: abort::TOGGLE })));
    }

    #[test]
    fn expedited_and_segmented_download() {
        let mut c = SdoClient::new(2, 100);
        let f = c.start_download(0x6060, 0, &[8], 0);
        assert_eq!(format!("{f:?}"), "602#2F60600008000000");
        assert_eq!(c.on_frame(&SdoResponse::InitiateDownload { index: 0x6060, sub: 0 }.encode(2), 1), vec![]);
        assert_eq!(c.take_result(), Some(Ok(vec![])));

        let f = c.start_download(0x2000, 1, b"0123456789", 0);
        assert_eq!(format!("{f:?}"), "602#210020010A000000");
        let s1 = c.on_frame(&SdoResponse::InitiateDownload { index: 0x2000, sub: 1 }.encode(2), 1).pop().unwrap();
        assert_eq!(format!("{s1:?}"), "602#0030313233343536");
        let s2 = c.on_frame(&SdoResponse::DownloadSegment { toggle: false }.encode(2), 2).pop().unwrap();
        // toggle 1, 3 bytes (n = 4 unused), last: 0x10 | 4<<1 | 1 = 0x19
        assert_eq!(format!("{s2:?}"), "602#1937383900000000");
        assert_eq!(c.on_frame(&SdoResponse::DownloadSegment { toggle: true }.encode(2), 3), vec![]);
        assert_eq!(c.take_result(), Some(Ok(vec![])));
    }

    #[test]
    fn abort_and_timeout() {
        let mut c = SdoClient::new(1, 50);
        c.start_upload(0x2345, 0, 0);
        c.on_frame(&SdoResponse::Abort { index: 0x2345, sub: 0, code: abort::NO_OBJECT }.encode(1), 1);
        let e = c.take_result().unwrap().unwrap_err();
        assert_eq!(e.to_string(), "SDO abort 0x06020000 object does not exist in the object dictionary");

        c.start_upload(0x1000, 0, 1_000);
        assert_eq!(c.poll(50_000_999), None);
        let ab = c.poll(50_001_000).unwrap();
        assert_eq!(format!("{ab:?}"), "601#8000100000000405");
        assert_eq!(c.take_result(), Some(Err(SdoError::Timeout { timeout_ms: 50 })));
    }
    fn seg(seqno: u8, last: bool, data: &[u8]) -> CanFrame {
        let mut d = [0u8; 7];
        d[..data.len()].copy_from_slice(data);
        BlockSegment { seqno, last, data: d }.encode_response(1)
    }

    #[test]
    fn block_download_with_retransmission_and_crc() {
        let data: Vec<u8> = (0u8..20).collect();
        let mut c = SdoClient::new(1, 100);
        let f = c.start_block_download(0x2200, 0, &data, 0);
        assert_eq!(format!("{f:?}"), "601#C600220014000000");
        // The server asks for sub-blocks of 2 segments.
        let out = c.on_frame(&BlockResponse::InitiateDownload { index: 0x2200, sub: 0, crc: true, blksize: 2 }.encode(1), 1);
        assert_eq!(out.iter().map(|f| format!("{f:?}")).collect::<Vec<_>>(), ["601#0100010203040506", "601#020708090A0B0C0D"]);
        // Segment 2 was lost: the server acknowledges 1; segment 2 comes again as seqno 1.
        let out = c.on_frame(&BlockResponse::Ack { ackseq: 1, blksize: 2 }.encode(1), 2);
        assert_eq!(format!("{:?}", out[0]), "601#010708090A0B0C0D");
        assert_eq!(out.len(), 2);
        // Bytes 14..20 are the last 6: flagged last, seqno 2.
        assert_eq!(format!("{:?}", out[1]), "601#820E0F1011121300");
        let end = c.on_frame(&BlockResponse::Ack { ackseq: 2, blksize: 2 }.encode(1), 3);
        // 1 unused byte: C1 | 1 << 2 = C5, then the CRC of the 20 bytes.
        let crc = crc16(&data).to_le_bytes();
        assert_eq!(end[0].data[..3], [0xC5, crc[0], crc[1]]);
        assert_eq!(c.on_frame(&BlockResponse::EndDownloadResponse.encode(1), 4), vec![]);
        assert_eq!(c.take_result(), Some(Ok(vec![])));
    }

    #[test]
    fn block_upload_drops_out_of_sequence_segments_and_checks_the_crc() {
        let data: Vec<u8> = (100u8..116).collect(); // 16 bytes: 7 + 7 + 2
        let mut c = SdoClient::new(1, 100);
        let f = c.start_block_upload(0x2200, 0, 0);
        assert_eq!(format!("{f:?}"), "601#A40022007F000000");
        let start = c.on_frame(&BlockResponse::InitiateUpload { index: 0x2200, sub: 0, crc: true, size: Some(16) }.encode(1), 1);
        assert_eq!(format!("{:?}", start[0]), "601#A300000000000000");
        // Segment 2 lost: 1 and 3 (last) arrive; the client acknowledges 1.
        assert_eq!(c.on_frame(&seg(1, false, &data[0..7]), 2), vec![]);
        let ack = c.on_frame(&seg(3, true, &data[14..16]), 3);
        assert_eq!(format!("{:?}", ack[0]), "601#A2017F0000000000");
        // The server restarts after segment 1.
        assert_eq!(c.on_frame(&seg(1, false, &data[7..14]), 4), vec![]);
        let ack = c.on_frame(&seg(2, true, &data[14..16]), 5);
        assert_eq!(format!("{:?}", ack[0]), "601#A2027F0000000000");
        let done = c.on_frame(&BlockResponse::EndUpload { unused: 5, crc: crc16(&data) }.encode(1), 6);
        assert_eq!(format!("{:?}", done[0]), "601#A100000000000000");
        assert_eq!(c.take_result(), Some(Ok(data.clone())));

        // A wrong CRC aborts with 0x05040004.
        c.start_block_upload(0x2200, 0, 10);
        c.on_frame(&BlockResponse::InitiateUpload { index: 0x2200, sub: 0, crc: true, size: Some(2) }.encode(1), 11);
        c.on_frame(&seg(1, true, &data[..2]), 12);
        let ab = c.on_frame(&BlockResponse::EndUpload { unused: 5, crc: crc16(&data[..2]) ^ 1 }.encode(1), 13);
        assert_eq!(format!("{:?}", ab[0]), "601#8000220004000405");
        assert_eq!(c.take_result(), Some(Err(SdoError::Abort { code: abort::CRC })));
    }

    #[test]
    fn block_abort_from_the_server_ends_the_transfer() {
        let mut c = SdoClient::new(1, 100);
        c.start_block_upload(0x1A00, 9, 0);
        assert_eq!(c.on_frame(&SdoResponse::Abort { index: 0x1A00, sub: 9, code: abort::NO_SUBINDEX }.encode(1), 1), vec![]);
        assert_eq!(c.take_result(), Some(Err(SdoError::Abort { code: abort::NO_SUBINDEX })));
    }
}
