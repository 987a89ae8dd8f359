//! The serial master's requests off a lossy line, and the replies back in its framing
//! (docs/design.md §4.2). Pure: bytes in, requests out, no I/O and no clock.
//!
//! - MBAP: the resynchronising decoder of docs/design.md §2 with the request judge,
//!   every request held until what follows it or a pause confirms it: a request that
//!   lost a byte and took the first byte of the next one is refuted, not forwarded.
//!   Garbage is skipped byte by byte.
//! - RTU / ASCII: the serial decoder; a frame whose CRC or LRC fails is dropped, as a
//!   slave on a bus would drop it.

use crate::config::Framing;
use crate::frame::framer::{Framed, Framer};
use crate::frame::serial::Codec;
use crate::frame::{Adu, RequestJudge};
use crate::ops::capture::dropped::{Dropped, Tape};
use crate::ops::capture::packet::Reason;

/// One request from the serial master.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Incoming {
    /// The master's own transaction id (MBAP), restored on its reply; `None` on RTU
    /// and ASCII, which have none.
    pub(crate) tid: Option<u16>,
    pub(crate) unit: u8,
    pub(crate) pdu: Vec<u8>,
}

/// The line's framer ([`Framer`], shared with the relay, the simulator and the
/// client), judging frames as requests; and the bytes it drops, for the capture.
#[derive(Debug)]
pub(crate) struct Requests(Framer, Tape);

impl Requests {
    pub(crate) fn new(framing: Framing) -> Self {
        Self(framing.framer(), Tape::default())
    }

    /// Keep the bytes dropped, for the capture, or not.
    pub(crate) fn set_tape(&mut self, on: bool) {
        self.1.set(on);
    }

    /// The bytes dropped since the last call, with why (while the tape is on).
    pub(crate) fn take_drops(&mut self) -> Vec<Dropped> {
        self.1.take()
    }

    /// RTU or ASCII (where unit 0 is a broadcast), or `None` for MBAP.
    pub(crate) fn codec(&self) -> Option<Codec> {
        self.0.codec()
    }

    pub(crate) fn push(&mut self, bytes: &[u8]) {
        self.0.push(bytes);
        self.1.push(bytes);
    }

    /// The line has been silent for the pause that ends a frame (MBAP: confirms a
    /// request with nothing after it).
    pub(crate) fn pause(&mut self) {
        self.0.pause();
    }

    pub(crate) fn buffered(&self) -> usize {
        self.0.buffered()
    }

    /// Forgets what is buffered (the port was lost); counted as dropped.
    pub(crate) fn clear(&mut self) {
        self.0.clear();
        let to = self.0.consumed();
        self.1
            .dropped_to(to, None, Reason::Stale, "bytes held when the port was lost");
    }

    /// Bytes dropped so far: garbage, malformed or refuted MBAP frames, RTU/ASCII
    /// frames whose check failed.
    pub(crate) fn dropped(&self) -> u64 {
        self.0.dropped()
    }

    /// The next whole request. `quiet`: the line has been silent for the frame gap
    /// (MBAP) or for 3.5 characters (RTU): a partial frame will not complete.
    pub(crate) fn next(&mut self, quiet: bool) -> Option<Incoming> {
        let mbap = self.0.codec().is_none();
        let check = match self.0.codec() {
            Some(crate::frame::serial::Codec::Ascii) => Reason::Lrc,
            _ => Reason::Crc,
        };
        loop {
            let Some(framed) = self.0.next_frame(&RequestJudge { confirm: true }, quiet) else {
                let to = self.0.consumed();
                let why = "bytes that make no request (garbage, a frame that lost bytes)";
                self.1.dropped_to(to, None, Reason::LostSync, why);
                return None;
            };
            match framed {
                Framed::Frame(adu) => {
                    let len = self.0.encoded_len(adu.pdu().len());
                    self.1.frame(self.0.consumed(), len, None, Reason::LostSync);
                    return Some(Incoming {
                        tid: mbap.then(|| adu.tid()),
                        unit: adu.unit(),
                        pdu: adu.pdu().to_vec(),
                    });
                }
                // Counted by the framer as dropped; a slave on a bus ignores it too.
                Framed::Corrupt(n) => {
                    let why = "a request whose check failed, or cut short";
                    let end = self.0.consumed();
                    self.1
                        .dropped_frame(end, n, None, (Reason::LostSync, check), why);
                }
            }
        }
    }
}

/// A reply `pdu` to `request` as the line carries it: MBAP with the master's own
/// transaction id, RTU with its CRC, ASCII with its LRC.
pub(crate) fn encode_reply(codec: Option<Codec>, request: &Incoming, pdu: &[u8]) -> Vec<u8> {
    match codec {
        None => Adu::build(request.tid.unwrap_or(0), request.unit, pdu)
            .as_bytes()
            .to_vec(),
        Some(c) => c.encode(request.unit, pdu),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;
    use crate::frame::{ascii, rtu};

    fn all(r: &mut Requests, quiet: bool) -> Vec<Incoming> {
        std::iter::from_fn(|| r.next(quiet)).collect()
    }

    /// The CIE-M10 master's read and write (docs/protocol.md §3), behind garbage.
    #[test]
    fn mbap_requests_behind_garbage_held_until_a_pause() {
        let mut r = Requests::new(Framing::Mbap);
        r.push(&bytes("FF 13 00"));
        r.push(&bytes("00 00 00 00 00 06 01 03 00 00 00 01"));
        assert_eq!(all(&mut r, false), [], "held until confirmed");
        r.pause();
        let read = Incoming {
            tid: Some(0),
            unit: 1,
            pdu: bytes("03 00 00 00 01"),
        };
        assert_eq!(all(&mut r, false), [read]);
        r.push(&bytes("00 01 00 00 00 09 01 10 00 08 00 01 02 00 11"));
        r.pause();
        let write = all(&mut r, false);
        assert_eq!(write[0].tid, Some(1));
        assert_eq!(write[0].pdu, bytes("10 00 08 00 01 02 00 11"));
        assert_eq!(r.dropped(), 3);
    }

    /// A frame that lost a byte, followed at once by a good one: the truncated one
    /// borrows the good one's first byte, and what follows it refutes it. The good
    /// one starts inside it, at the byte it borrowed: found there (the first start
    /// inside that runs past its end) and forwarded. The damaged one never is.
    #[test]
    fn an_intact_request_right_behind_a_damaged_one_is_recovered() {
        let mut r = Requests::new(Framing::Mbap);
        let mut cut = bytes("00 07 00 00 00 06 01 03 00 00 00 01");
        cut.remove(9);
        r.push(&cut);
        r.push(&bytes("00 08 00 00 00 06 01 03 00 00 00 02"));
        r.pause();
        let got = all(&mut r, true);
        assert_eq!(got.len(), 1, "{got:?}");
        assert_eq!(
            (got[0].tid, &got[0].pdu[..]),
            (Some(8), &[3, 0, 0, 0, 2][..])
        );
        assert_eq!(r.dropped(), 11, "the damaged one's own bytes");

        // Back to back with a third, in any chunking: the second and the third.
        let mut stream = cut.clone();
        stream.extend(bytes("00 08 00 00 00 06 01 03 00 00 00 02"));
        stream.extend(bytes("00 09 00 00 00 09 01 10 00 08 00 01 02 00 11"));
        for at in 0..stream.len() {
            let mut r = Requests::new(Framing::Mbap);
            r.push(&stream[..at]);
            let mut got = all(&mut r, false);
            r.push(&stream[at..]);
            got.extend(all(&mut r, false));
            r.pause();
            got.extend(all(&mut r, true));
            let tids: Vec<Option<u16>> = got.iter().map(|g| g.tid).collect();
            assert_eq!(tids, [Some(8), Some(9)], "cut at {at}");
        }
        // A write whose values are a whole request, damaged (a byte of its values
        // lost, so it borrows the next one's first byte and is refuted): its values do
        // not become a request; only a start that runs past its end counts.
        let mut r = Requests::new(Framing::Mbap);
        let inner = bytes("00 05 00 00 00 06 01 06 00 01 00 07");
        let mut write = bytes("00 0A 00 00 00 15 01 10 00 00 00 07 0E AA BB");
        write.extend(&inner);
        write.remove(13);
        r.push(&write);
        r.push(&bytes("00 0B 00 00 00 06 01 03 00 00 00 01"));
        r.pause();
        let got = all(&mut r, true);
        let tids: Vec<Option<u16>> = got.iter().map(|g| g.tid).collect();
        assert_eq!(tids, [Some(11)], "{got:?}");
    }

    #[test]
    fn malformed_mbap_is_not_forwarded() {
        let mut r = Requests::new(Framing::Mbap);
        // FC 16 whose byte count disagrees with its length; then quiet.
        r.push(&bytes("00 02 00 00 00 09 01 10 00 08 00 01 04 00 11"));
        r.pause();
        assert_eq!(all(&mut r, true), []);
        assert_eq!(r.dropped(), 15);
    }

    #[test]
    fn rtu_bad_crc_dropped_good_one_taken() {
        let mut r = Requests::new(Framing::Rtu);
        let mut bad = rtu::encode(1, &bytes("03 00 00 00 01"));
        bad[7] ^= 1;
        r.push(&bad);
        assert_eq!(all(&mut r, false), []);
        r.push(&rtu::encode(2, &bytes("06 00 01 00 07")));
        let got = all(&mut r, false);
        assert_eq!(got.len(), 1);
        assert_eq!((got[0].tid, got[0].unit), (None, 2));
        assert_eq!(r.dropped(), 8);
    }

    #[test]
    fn replies_in_the_line_s_framing() {
        let req = Incoming {
            tid: Some(0x0102),
            unit: 1,
            pdu: bytes("03 00 00 00 01"),
        };
        assert_eq!(
            encode_reply(None, &req, &bytes("03 02 00 FF")),
            bytes("01 02 00 00 00 05 01 03 02 00 FF")
        );
        let rtu_req = Incoming { tid: None, ..req };
        assert_eq!(
            encode_reply(Some(Codec::Rtu), &rtu_req, &[0x83, 0x0B]),
            rtu::encode(1, &[0x83, 0x0B])
        );
        assert_eq!(
            encode_reply(Some(Codec::Ascii), &rtu_req, &[0x83, 0x0A]),
            ascii::encode(1, &[0x83, 0x0A])
        );
    }
}
