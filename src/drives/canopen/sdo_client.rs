//! SDO client, sans-I/O: frames in, frames out, deadlines checked by `poll`. Expedited and
//! segmented upload and download. One transfer at a time per server, as CiA 301 requires.

use cncgw_bus::canopen::cob;
use cncgw_bus::canopen::sdo::{abort, abort_text, SdoRequest, SdoResponse};
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
    DownloadSeg { offset: usize, toggle: bool, last_sent: bool },
    UploadInit,
    UploadSeg { toggle: bool },
    Done,
}

pub struct SdoClient {
    node: u8,
    phase: Phase,
    index: u16,
    sub: u8,
    buf: Vec<u8>,
    deadline_ns: u64,
    timeout_ns: u64,
    result: Option<Result<Vec<u8>, SdoError>>,
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
            SdoRequest::InitiateDownload { index, sub, expedited: true, size: Some(data.len() as u32), data: d }
                .encode(self.node)
        } else {
            SdoRequest::InitiateDownload { index, sub, expedited: false, size: Some(data.len() as u32), data: [0; 4] }
                .encode(self.node)
        }
    }

    fn begin(&mut self, index: u16, sub: u8, now_ns: u64) {
        self.index = index;
        self.sub = sub;
        self.buf.clear();
        self.result = None;
        self.deadline_ns = now_ns + self.timeout_ns;
    }

    fn finish(&mut self, r: Result<Vec<u8>, SdoError>) {
        self.result = Some(r);
        self.phase = Phase::Done;
    }

    fn abort_frame(&self, code: u32) -> CanFrame {
        SdoRequest::Abort { index: self.index, sub: self.sub, code }.encode(self.node)
    }

    /// Feed a received frame. Returns the next frame to send, if any.
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64) -> Option<CanFrame> {
        if f.cob_id() != cob::SDO_TX + self.node as u16 || !self.busy() {
            return None;
        }
        let Some(resp) = SdoResponse::decode(f) else {
            self.finish(Err(SdoError::Protocol("malformed SDO response")));
            return Some(self.abort_frame(abort::BAD_COMMAND));
        };
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
                if expedited {
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
    fn expedited_upload() {
        let mut c = SdoClient::new(3, 100);
        let req = c.start_upload(0x1000, 0, 0);
        assert_eq!(format!("{req:?}"), "603#4000100000000000");
        let resp = CanFrame::new(0x583, &[0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00]);
        assert_eq!(c.on_frame(&resp, 10), None);
        assert_eq!(c.take_result(), Some(Ok(vec![0x92, 0x01, 0x02, 0x00])));
        assert!(!c.busy());
    }

    #[test]
    fn segmented_upload_with_toggles() {
        let mut c = SdoClient::new(1, 100);
        c.start_upload(0x1008, 0, 0);
        let next = c.on_frame(&SdoResponse::InitiateUpload { index: 0x1008, sub: 0, expedited: false, size: Some(10), data: [10, 0, 0, 0] }.encode(1), 1).unwrap();
        assert_eq!(format!("{next:?}"), "601#6000000000000000");
        let next = c.on_frame(&SdoResponse::UploadSegment { toggle: false, len: 7, data: *b"cncgw s", last: false }.encode(1), 2).unwrap();
        assert_eq!(format!("{next:?}"), "601#7000000000000000");
        assert_eq!(c.on_frame(&SdoResponse::UploadSegment { toggle: true, len: 3, data: *b"im\0\0\0\0\0", last: true }.encode(1), 3), None);
        assert_eq!(c.take_result(), Some(Ok(b"cncgw sim\0".to_vec())));
    }

    #[test]
    fn wrong_toggle_aborts() {
        let mut c = SdoClient::new(1, 100);
        c.start_upload(0x1008, 0, 0);
        c.on_frame(&SdoResponse::InitiateUpload { index: 0x1008, sub: 0, expedited: false, size: None, data: [0; 4] }.encode(1), 1);
        let ab = c.on_frame(&SdoResponse::UploadSegment { toggle: true, len: 7, data: [0; 7], last: false }.encode(1), 2).unwrap();
        assert_eq!(format!("{ab:?}"), "601#8008100000000305");
        assert_eq!(c.take_result(), Some(Err(SdoError::Abort { code: abort::TOGGLE })));
    }

    #[test]
    fn expedited_and_segmented_download() {
        let mut c = SdoClient::new(2, 100);
        let f = c.start_download(0x6060, 0, &[8], 0);
        assert_eq!(format!("{f:?}"), "602#2F60600008000000");
        assert_eq!(c.on_frame(&SdoResponse::InitiateDownload { index: 0x6060, sub: 0 }.encode(2), 1), None);
        assert_eq!(c.take_result(), Some(Ok(vec![])));

        let f = c.start_download(0x2000, 1, b"0123456789", 0);
        assert_eq!(format!("{f:?}"), "602#210020010A000000");
        let s1 = c.on_frame(&SdoResponse::InitiateDownload { index: 0x2000, sub: 1 }.encode(2), 1).unwrap();
        assert_eq!(format!("{s1:?}"), "602#0030313233343536");
        let s2 = c.on_frame(&SdoResponse::DownloadSegment { toggle: false }.encode(2), 2).unwrap();
        // toggle 1, 3 bytes (n = 4 unused), last: 0x10 | 4<<1 | 1 = 0x19
        assert_eq!(format!("{s2:?}"), "602#1937383900000000");
        assert_eq!(c.on_frame(&SdoResponse::DownloadSegment { toggle: true }.encode(2), 3), None);
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
}
