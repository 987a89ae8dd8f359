//! RTU and ASCII on one footing: encode a request or reply, and an incremental decoder
//! that says where the frame at the front of the bytes received ends.
//!
//! The decoder is told whether the line has been quiet (the caller measures silence:
//! 3.5 character times, never shorter than a USB adapter's latency), and what it
//! expects: the reply to a given request, or any request (the simulator's side).
//!
//! - RTU: complete at the length the function code (and byte count) calls for, so a
//!   reply, and an exception at once, is taken when its last byte arrives; a function
//!   code of unknown shape is ended by silence. A frame whose CRC is wrong is
//!   `Decoded::Corrupt`.
//! - ASCII: complete at the line feed; a new colon drops what came before it. Silence
//!   does not cut an ASCII frame (the spec allows a second between characters).

use super::{ascii, rtu};

/// Which serial framing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Codec {
    /// Modbus RTU: binary, CRC-16, frames ended by silence (Modbus over Serial Line
    /// V1.02 §2.5.1).
    Rtu,
    /// Modbus ASCII: `:`, hex digits, LRC, CR LF (Modbus over Serial Line V1.02 §2.5.2).
    Ascii,
}

impl Codec {
    /// The frame for `unit` and `pdu`.
    pub fn encode(self, unit: u8, pdu: &[u8]) -> Vec<u8> {
        match self {
            Codec::Rtu => rtu::encode(unit, pdu),
            Codec::Ascii => ascii::encode(unit, pdu),
        }
    }

    /// [`Codec::encode`], appended to `out`.
    pub(crate) fn encode_into(self, unit: u8, pdu: &[u8], out: &mut Vec<u8>) {
        match self {
            Codec::Rtu => rtu::encode_into(unit, pdu, out),
            Codec::Ascii => out.extend_from_slice(&ascii::encode(unit, pdu)),
        }
    }

    /// The length of that frame for a PDU of `pdu_len` bytes: address and CRC (RTU);
    /// colon, each byte as two hex digits with the LRC, CR LF (ASCII).
    pub(crate) fn encoded_len(self, pdu_len: usize) -> usize {
        match self {
            Codec::Rtu => 1 + pdu_len + 2,
            Codec::Ascii => 1 + 2 * (1 + pdu_len + 1) + 2,
        }
    }
}

/// What the decoder expects at the front of its bytes.
#[derive(Debug, Clone, Copy)]
pub enum Expect<'a> {
    /// The reply to this request PDU.
    Reply(&'a [u8]),
    /// Any request.
    Request,
}

/// One frame off the line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Decoded {
    /// Its check (CRC or LRC) held.
    Frame { unit: u8, pdu: Vec<u8> },
    /// This many bytes made a frame whose check failed, or could not be one.
    Corrupt(usize),
    /// This many bytes came before a frame's start (ASCII: before a colon): noise,
    /// not a damaged frame.
    Noise(usize),
}

/// The incremental decoder: bytes in with [`push`](Decoder::push), frames out with
/// [`next`](Decoder::next); any chunking gives the same frames.
#[derive(Debug)]
pub(crate) struct Decoder {
    codec: Codec,
    buf: Vec<u8>,
    /// The room of the last frame's PDU, given back ([`Decoder::recycle`]) for the
    /// next: an RTU frame is decoded without an allocation.
    spare: Vec<u8>,
}

impl Decoder {
    pub(crate) fn new(codec: Codec) -> Self {
        Self {
            codec,
            buf: Vec::new(),
            spare: Vec::new(),
        }
    }

    /// The PDU of a frame decoded, no longer needed: its room serves the next frame.
    pub(crate) fn recycle(&mut self, pdu: Vec<u8>) {
        self.spare = pdu;
    }

    pub(crate) fn codec(&self) -> Codec {
        self.codec
    }

    pub(crate) fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Bytes held that are not yet part of a frame.
    pub(crate) fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Does a quiet line end what is buffered (RTU), or does only a line feed (ASCII)?
    pub(crate) fn silence_ends_frames(&self) -> bool {
        self.codec == Codec::Rtu
    }

    /// RTU: is what is buffered the start of a frame whose length its function code
    /// (and byte count) tells, or will once they are in (not one of unknown shape,
    /// which silence ends)?
    pub(crate) fn length_known(&self, expect: Expect<'_>) -> bool {
        let length = match expect {
            Expect::Reply(request) => rtu::reply_length(request, &self.buf),
            Expect::Request => rtu::request_length(&self.buf),
        };
        self.codec == Codec::Rtu && !matches!(length, rtu::Length::Silence)
    }

    /// Forgets every buffered byte (keeping the room); returns how many.
    pub(crate) fn clear(&mut self) -> usize {
        let n = self.buf.len();
        self.buf.clear();
        n
    }

    /// The next frame, if the bytes (and, for RTU, a `quiet` line) delimit one.
    pub(crate) fn next(&mut self, expect: Expect<'_>, quiet: bool) -> Option<Decoded> {
        match self.codec {
            Codec::Rtu => self.next_rtu(expect, quiet),
            Codec::Ascii => self.next_ascii(),
        }
    }

    fn next_rtu(&mut self, expect: Expect<'_>, quiet: bool) -> Option<Decoded> {
        if self.buf.is_empty() {
            return None;
        }
        let length = match expect {
            Expect::Reply(request) => rtu::reply_length(request, &self.buf),
            Expect::Request => rtu::request_length(&self.buf),
        };
        let n = match length {
            rtu::Length::Exactly(n) if self.buf.len() >= n => n,
            _ if quiet => self.buf.len(),
            // Longer than any frame and not ended: no frame, whatever comes next. Cut
            // here, so a device that never pauses holds no more than a frame of memory.
            _ if self.buf.len() > rtu::MAX_FRAME => self.buf.len(),
            _ => return None,
        };
        // Decoded where it lies, its PDU copied into the room of the last one.
        let decoded = match rtu::decode(&self.buf[..n]) {
            Some((unit, pdu)) => {
                let mut room = std::mem::take(&mut self.spare);
                room.clear();
                room.extend_from_slice(pdu);
                Decoded::Frame { unit, pdu: room }
            }
            None => Decoded::Corrupt(n),
        };
        self.buf.drain(..n);
        Some(decoded)
    }

    fn next_ascii(&mut self) -> Option<Decoded> {
        match ascii::scan(&self.buf) {
            ascii::Scan::More => None,
            ascii::Scan::Garbage(n) => {
                let cut_short = self.buf[0] == b':';
                self.buf.drain(..n);
                Some(if cut_short {
                    Decoded::Corrupt(n)
                } else {
                    Decoded::Noise(n)
                })
            }
            ascii::Scan::Frame(n) => {
                let frame: Vec<u8> = self.buf.drain(..n).collect();
                Some(match ascii::decode(&frame) {
                    Some((unit, pdu)) => Decoded::Frame { unit, pdu },
                    None => Decoded::Corrupt(n),
                })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(unit: u8, pdu: &[u8]) -> Option<Decoded> {
        Some(Decoded::Frame {
            unit,
            pdu: pdu.to_vec(),
        })
    }

    #[test]
    fn encoded_len_is_the_frame_length() {
        for pdu in [
            &[0x83, 0x02][..],
            &[0x03, 0, 0, 0, 1],
            &[0x10, 0, 1, 0, 1, 2, 0, 7],
        ] {
            for codec in [Codec::Rtu, Codec::Ascii] {
                assert_eq!(codec.encoded_len(pdu.len()), codec.encode(9, pdu).len());
            }
        }
    }

    #[test]
    fn rtu_reply_complete_at_its_length_in_any_chunking() {
        let request = [0x03, 0x00, 0x6B, 0x00, 0x03];
        let reply = rtu::encode(0x11, &[0x03, 6, 0, 1, 0, 2, 0, 3]);
        for cut in 0..reply.len() {
            let mut d = Decoder::new(Codec::Rtu);
            d.push(&reply[..cut]);
            assert_eq!(d.next(Expect::Reply(&request), false), None, "cut {cut}");
            d.push(&reply[cut..]);
            assert_eq!(
                d.next(Expect::Reply(&request), false),
                frame(0x11, &[0x03, 6, 0, 1, 0, 2, 0, 3])
            );
            assert_eq!(d.buffered(), 0);
        }
    }

    #[test]
    fn rtu_exception_at_once_unknown_code_at_silence() {
        let mut d = Decoder::new(Codec::Rtu);
        d.push(&rtu::encode(1, &[0x83, 0x02]));
        assert_eq!(
            d.next(Expect::Reply(&[3, 0, 0, 0, 1]), false),
            frame(1, &[0x83, 2])
        );
        d.push(&rtu::encode(1, &[0x41, 1, 2, 3]));
        assert_eq!(d.next(Expect::Reply(&[0x41]), false), None);
        assert_eq!(
            d.next(Expect::Reply(&[0x41]), true),
            frame(1, &[0x41, 1, 2, 3])
        );
    }

    /// Bytes of a frame of unknown shape (function 0x41) that never pause: cut and
    /// dropped as soon as they run past the longest RTU frame, never buffered without
    /// end; ASCII drops a colon's bytes past its longest frame likewise.
    #[test]
    fn a_stream_without_a_pause_is_cut_at_the_longest_frame() {
        let mut d = Decoder::new(Codec::Rtu);
        let mut dropped = 0;
        for _ in 0..1000 {
            d.push(&[1, 0x41, 0, 0]);
            while let Some(next) = d.next(Expect::Reply(&[0x41]), false) {
                let Decoded::Corrupt(n) = next else {
                    panic!("{next:?}")
                };
                dropped += n;
            }
            assert!(d.buffered() <= rtu::MAX_FRAME + 4, "{}", d.buffered());
        }
        assert_eq!(dropped + d.buffered(), 4000);
        let mut d = Decoder::new(Codec::Ascii);
        for _ in 0..1000 {
            d.push(b":0141");
            while d.next(Expect::Request, false).is_some() {}
            assert!(d.buffered() <= ascii::MAX_FRAME + 5, "{}", d.buffered());
        }
    }

    #[test]
    fn rtu_bad_crc_and_short_frames_are_corrupt() {
        let mut d = Decoder::new(Codec::Rtu);
        let mut f = rtu::encode(1, &[0x06, 0, 1, 0, 3]);
        f[7] ^= 0xFF;
        d.push(&f);
        assert_eq!(d.next(Expect::Request, false), Some(Decoded::Corrupt(8)));
        d.push(&[1, 3, 0]);
        assert_eq!(d.next(Expect::Request, false), None);
        assert_eq!(d.next(Expect::Request, true), Some(Decoded::Corrupt(3)));
        assert_eq!(d.buffered(), 0);
    }

    #[test]
    fn ascii_frames_by_colon_and_line_feed() {
        let mut d = Decoder::new(Codec::Ascii);
        let f = ascii::encode(1, &[3, 0, 0, 0, 1]);
        d.push(b"zz");
        d.push(&f[..5]);
        assert_eq!(d.next(Expect::Request, false), Some(Decoded::Noise(2)));
        assert_eq!(
            d.next(Expect::Request, true),
            None,
            "silence does not cut ASCII"
        );
        d.push(&f[5..]);
        assert_eq!(d.next(Expect::Request, false), frame(1, &[3, 0, 0, 0, 1]));
        assert_eq!(d.next(Expect::Request, false), None);
        d.push(b":0103:");
        assert_eq!(d.next(Expect::Request, false), Some(Decoded::Corrupt(5)));
    }
}
