//! SDO block transfer server (CiA 301 §7.2.4.3.9–16): block download and block upload with
//! the CRC, the protocol switch threshold and retransmission from the last acknowledged
//! segment. A real drive sends a sub-block back to back; so does this one.

use super::{SdoState, SimDrive};
use cncgw_bus::canopen::sdo::{abort, crc16, BlockRequest, BlockResponse, BlockSegment, SdoRequest, BLOCK_MAX};
use cncgw_bus::CanFrame;

/// Segments per sub-block this server asks for (CiA 301 allows 1…127).
pub(super) const SERVER_BLKSIZE: u8 = BLOCK_MAX;

#[derive(Clone, Debug)]
pub(super) struct Down {
    index: u16,
    sub: u8,
    size: Option<u32>,
    crc: bool,
    buf: Vec<u8>,
    /// Last in-sequence segment of the present sub-block.
    ackseq: u8,
    /// The segment flagged last was received in sequence: the end frame is next.
    done: bool,
    max: usize,
}

#[derive(Clone, Debug)]
pub(super) struct Up {
    index: u16,
    sub: u8,
    data: Vec<u8>,
    crc: bool,
    blksize: u8,
    /// First byte of the sub-block in flight.
    block_start: usize,
    /// Sequence number of the last segment of the transfer if it is in this sub-block.
    last_seq: Option<u8>,
    started: bool,
    ended: bool,
}

impl SimDrive {
    /// Handle an SDO frame while a block transfer is under way, or a block initiate.
    /// Returns false if the frame is not a block transfer frame (the caller decodes it).
    pub(super) fn sdo_block(&mut self, f: &CanFrame, now: u64) -> bool {
        let cmd = f.data[0];
        if let SdoState::BlockDown(d) = &mut self.sdo {
            if !d.done && cmd != 0x80 {
                let Some(seg) = BlockSegment::decode(f) else { return true };
                self.block_segment(seg);
                return true;
            }
        }
        if cmd == 0x80 {
            return false; // abort: the segmented path ends every transfer
        }
        let Some(req) = BlockRequest::decode(f) else {
            let initiate = matches!(SdoRequest::decode(f), Some(SdoRequest::InitiateUpload { .. } | SdoRequest::InitiateDownload { .. }));
            if !initiate && matches!(self.sdo, SdoState::BlockDown(_) | SdoState::BlockUp(_)) {
                let (index, sub) = self.block_mux();
                self.sdo_abort(index, sub, abort::BAD_COMMAND);
                return true;
            }
            return false;
        };
        match req {
            BlockRequest::InitiateDownload { index, sub, crc, size } => self.block_down_init(index, sub, crc, size),
            BlockRequest::EndDownload { unused, crc } => self.block_down_end(unused, crc, now),
            BlockRequest::InitiateUpload { index, sub, crc, blksize, pst } => self.block_up_init(index, sub, crc, blksize, pst, now),
            BlockRequest::StartUpload => match &mut self.sdo {
                SdoState::BlockUp(u) if !u.started => {
                    u.started = true;
                    self.block_up_send();
                }
                _ => self.block_bad_command(),
            },
            BlockRequest::Ack { ackseq, blksize } => self.block_up_ack(ackseq, blksize),
            BlockRequest::EndUploadResponse => match &self.sdo {
                SdoState::BlockUp(u) if u.ended => self.sdo = SdoState::Idle,
                _ => self.block_bad_command(),
            },
        }
        true
    }

    fn block_mux(&self) -> (u16, u8) {
        match &self.sdo {
            SdoState::BlockDown(d) => (d.index, d.sub),
            SdoState::BlockUp(u) => (u.index, u.sub),
            _ => (0, 0),
        }
    }

    fn block_bad_command(&mut self) {
        let (index, sub) = self.block_mux();
        self.sdo_abort(index, sub, abort::BAD_COMMAND);
    }

    fn block_down_init(&mut self, index: u16, sub: u8, crc: bool, size: Option<u32>) {
        self.sdo = SdoState::Idle;
        let e = match self.od.lookup(index, sub) {
            Ok(e) => e,
            Err(code) => return self.sdo_abort(index, sub, code),
        };
        if !e.access.writable() {
            return self.sdo_abort(index, sub, abort::READ_ONLY);
        }
        let max = match e.dtype.size() {
            Some(n) => n,
            None if e.dtype == crate::od::DType::Domain => e.max.max(0) as usize,
            None => 1024,
        };
        if let Some(s) = size {
            match e.dtype.size() {
                Some(n) if (s as usize) < n => return self.sdo_abort(index, sub, abort::TOO_SHORT),
                _ if s as usize > max => return self.sdo_abort(index, sub, abort::TOO_LONG),
                _ => {}
            }
        }
        self.sdo_send_block(BlockResponse::InitiateDownload { index, sub, crc: true, blksize: SERVER_BLKSIZE });
        self.sdo = SdoState::BlockDown(Down { index, sub, size, crc, buf: Vec::new(), ackseq: 0, done: false, max });
    }

    fn block_segment(&mut self, seg: BlockSegment) {
        let SdoState::BlockDown(d) = &mut self.sdo else { return };
        // Out-of-sequence segments are dropped; the acknowledgement tells the client where
        // to restart (CiA 301: the next sub-block starts after the last acknowledged one).
        if seg.seqno == d.ackseq + 1 {
            d.ackseq = seg.seqno;
            d.buf.extend_from_slice(&seg.data);
            if seg.last {
                d.done = true;
            }
        }
        if d.buf.len() > d.max + 7 {
            let (index, sub) = (d.index, d.sub);
            return self.sdo_abort(index, sub, abort::OUT_OF_MEMORY);
        }
        if seg.seqno >= SERVER_BLKSIZE || seg.last {
            let ackseq = d.ackseq;
            d.ackseq = 0;
            self.sdo_send_block(BlockResponse::Ack { ackseq, blksize: SERVER_BLKSIZE });
        }
    }

    fn block_down_end(&mut self, unused: u8, crc: u16, now: u64) {
        let SdoState::BlockDown(d) = &mut self.sdo else {
            return self.block_bad_command();
        };
        if !d.done {
            let (index, sub) = (d.index, d.sub);
            return self.sdo_abort(index, sub, abort::BAD_COMMAND);
        }
        let (index, sub, size, use_crc) = (d.index, d.sub, d.size, d.crc);
        let mut buf = std::mem::take(&mut d.buf);
        self.sdo = SdoState::Idle;
        let n = buf.len().saturating_sub(unused as usize);
        buf.truncate(n);
        if size.is_some_and(|s| s as usize != buf.len()) {
            return self.sdo_abort(index, sub, abort::TYPE_MISMATCH);
        }
        if use_crc && crc16(&buf) != crc {
            return self.sdo_abort(index, sub, abort::CRC);
        }
        match self.write_object(index, sub, &buf, now) {
            Ok(()) => self.sdo_send_block(BlockResponse::EndDownloadResponse),
            Err(code) => self.sdo_abort(index, sub, code),
        }
    }

    fn block_up_init(&mut self, index: u16, sub: u8, crc: bool, blksize: u8, pst: u8, now: u64) {
        self.sdo = SdoState::Idle;
        if blksize == 0 || blksize > BLOCK_MAX {
            return self.sdo_abort(index, sub, abort::INVALID_BLOCK_SIZE);
        }
        self.refresh_od();
        let data = match self.od.read_bytes(index, sub) {
            Ok(d) => d,
            Err(code) => return self.sdo_abort(index, sub, code),
        };
        if pst > 0 && data.len() <= pst as usize {
            // Protocol switch: small data goes as a normal (expedited or segmented) upload.
            self.sdo_request_plain(SdoRequest::InitiateUpload { index, sub }, now);
            return;
        }
        let size = data.len() as u32;
        self.sdo_send_block(BlockResponse::InitiateUpload { index, sub, crc: true, size: Some(size) });
        self.sdo = SdoState::BlockUp(Up { index, sub, data, crc, blksize, block_start: 0, last_seq: None, started: false, ended: false });
    }

    /// Send the sub-block that starts at `block_start`.
    fn block_up_send(&mut self) {
        let SdoState::BlockUp(u) = &mut self.sdo else { return };
        let node = self.cfg.node;
        let mut pos = u.block_start;
        u.last_seq = None;
        for seqno in 1..=u.blksize {
            let n = (u.data.len() - pos.min(u.data.len())).min(7);
            let mut data = [0u8; 7];
            data[..n].copy_from_slice(&u.data[pos..pos + n]);
            pos += n;
            let last = pos >= u.data.len();
            self.out.push(BlockSegment { seqno, last, data }.encode_response(node));
            if last {
                u.last_seq = Some(seqno);
                break;
            }
        }
    }

    fn block_up_ack(&mut self, ackseq: u8, blksize: u8) {
        let SdoState::BlockUp(u) = &mut self.sdo else {
            return self.block_bad_command();
        };
        if !u.started || u.ended {
            return self.block_bad_command();
        }
        let (index, sub) = (u.index, u.sub);
        if blksize == 0 || blksize > BLOCK_MAX {
            return self.sdo_abort(index, sub, abort::INVALID_BLOCK_SIZE);
        }
        if ackseq > u.last_seq.unwrap_or(u.blksize) {
            return self.sdo_abort(index, sub, abort::INVALID_SEQUENCE);
        }
        if u.last_seq.is_some_and(|l| ackseq >= l) {
            let unused = (u.data.len() as isize - u.block_start as isize - 7 * (ackseq as isize - 1)).clamp(0, 7);
            let unused = 7 - unused as u8;
            let crc = if u.crc { crc16(&u.data) } else { 0 };
            u.ended = true;
            return self.sdo_send_block(BlockResponse::EndUpload { unused, crc });
        }
        u.block_start = (u.block_start + 7 * ackseq as usize).min(u.data.len());
        u.blksize = blksize;
        self.block_up_send();
    }

    fn sdo_send_block(&mut self, r: BlockResponse) {
        self.out.push(r.encode(self.cfg.node));
    }
}
