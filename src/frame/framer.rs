//! One framer for the serial side's three framings: MBAP (resynchronising,
//! `super::resync`), RTU and ASCII ([`super::serial`]). The relay, the simulator and
//! the client all decode through it: bytes in with [`push`](Framer::push), frames out
//! with [`next_frame`](Framer::next_frame), bytes for the wire with
//! [`encode`](Framer::encode), and one count of the bytes dropped.
//!
//! What a frame must be is the caller's [`Judge`]: on MBAP it decides which candidates
//! are frames (and whether they wait for confirmation); on RTU and ASCII the CRC or
//! LRC decides, and the judge says what is expected ([`Judge::expect`]), so the
//! function code table gives the length that ends a frame.
//!
//! Pure: no clock and no I/O. The caller says when the line paused (MBAP) and when it
//! has been quiet long enough to end a partial frame (`quiet`).
//!
//! ```
//! use mbgate::frame::framer::{Framed, Framer};
//! use mbgate::frame::serial::Codec;
//! use mbgate::frame::{rtu, Adu, ReplyJudge};
//! let mut f = Framer::serial(Codec::Rtu);
//! // Noise, then the reply of docs/protocol.md §2 to a read of three registers.
//! f.push(&[0x00]);
//! assert_eq!(f.next_frame(&ReplyJudge, true), Some(Framed::Corrupt(1)));
//! f.push(&rtu::encode(0x11, &[0x03, 0x06, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64]));
//! let Some(Framed::Frame(adu)) = f.next_frame(&ReplyJudge, false) else { panic!() };
//! assert_eq!((adu.unit(), adu.pdu()[1]), (0x11, 6));
//! assert_eq!(f.dropped(), 1);
//! assert_eq!(f.encode(&Adu::build(0, 0x11, &[3, 0, 0x6B, 0, 3])), rtu::encode(0x11, &[3, 0, 0x6B, 0, 3]));
//! ```

use super::mbap::{FrameRef, HEADER_LEN};
use super::resync::{Judge, Resync};
use super::serial::{Codec, Decoded, Decoder, Expect};
use super::{pdu, Adu, FunctionCode};
use bytes::BytesMut;

/// Any well-formed reply (as [`ReplyJudge`](super::ReplyJudge)), and on an RTU or ASCII
/// line the reply to this request PDU, whose shape gives the reply's length.
#[derive(Debug, Clone, Copy)]
pub struct ReplyFor<'a>(pub &'a [u8]);

impl Judge for ReplyFor<'_> {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.is_reply()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        pdu::reply_well_formed(frame.pdu())
    }

    fn expect(&self) -> Expect<'_> {
        Expect::Reply(self.0)
    }
}

/// One frame off the line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Framed {
    /// A whole frame: on MBAP as received (the judge accepted it); on RTU and ASCII its
    /// check held, and it is given as an ADU of transaction id 0 (they carry none).
    Frame(Adu),
    /// RTU or ASCII: this many bytes made a frame whose CRC or LRC failed, or that was
    /// cut short (counted as dropped).
    Corrupt(usize),
}

/// The decoder of the line's framing: MBAP's resynchronising one, or RTU/ASCII's by
/// CRC or LRC.
#[derive(Debug)]
enum Decoding {
    Mbap(Resync),
    Serial(Decoder),
}

/// The framer for one line; see the module notes.
#[derive(Debug)]
pub struct Framer {
    decoding: Decoding,
    /// RTU/ASCII: where the frames decoded are built as MBAP frames
    /// ([`Adu::build_in`]): no allocation a frame once warm.
    arena: BytesMut,
    /// RTU/ASCII: bytes dropped (noise, failed checks, cleared). MBAP: bytes cleared
    /// are the decoder's own count.
    line_dropped: u64,
    /// RTU/ASCII: bytes taken from the front so far.
    line_consumed: u64,
    /// What [`take_dropped`](Framer::take_dropped) has reported.
    dropped_taken: u64,
    /// What [`take_refuted`](Framer::take_refuted) has reported.
    refuted_taken: u64,
}

impl Framer {
    /// MBAP frames, resynchronising (docs/design.md §2).
    pub fn mbap() -> Self {
        Self::with(Decoding::Mbap(Resync::new()))
    }

    /// RTU or ASCII frames.
    pub fn serial(codec: Codec) -> Self {
        Self::with(Decoding::Serial(Decoder::new(codec)))
    }

    fn with(decoding: Decoding) -> Self {
        Self {
            decoding,
            arena: BytesMut::new(),
            line_dropped: 0,
            line_consumed: 0,
            dropped_taken: 0,
            refuted_taken: 0,
        }
    }

    /// RTU or ASCII; `None` for MBAP.
    pub(crate) fn codec(&self) -> Option<Codec> {
        match &self.decoding {
            Decoding::Mbap(_) => None,
            Decoding::Serial(d) => Some(d.codec()),
        }
    }

    /// `adu` as this line carries it: MBAP as it is; RTU or ASCII from its unit and PDU,
    /// check included.
    pub fn encode(&self, adu: &Adu) -> Vec<u8> {
        match self.codec() {
            None => adu.as_bytes().to_vec(),
            Some(codec) => codec.encode(adu.unit(), adu.pdu()),
        }
    }

    /// [`Framer::encode`], appended to `out`.
    pub(crate) fn encode_into(&self, adu: &Adu, out: &mut Vec<u8>) {
        match self.codec() {
            None => out.extend_from_slice(adu.as_bytes()),
            Some(codec) => codec.encode_into(adu.unit(), adu.pdu(), out),
        }
    }

    /// The length [`encode`](Framer::encode) gives a PDU of `pdu_len` bytes.
    pub fn encoded_len(&self, pdu_len: usize) -> usize {
        match self.codec() {
            None => HEADER_LEN + pdu_len,
            Some(codec) => codec.encoded_len(pdu_len),
        }
    }

    /// Appends bytes read from the line.
    pub fn push(&mut self, bytes: &[u8]) {
        match &mut self.decoding {
            Decoding::Mbap(d) => d.push(bytes),
            Decoding::Serial(d) => d.push(bytes),
        }
    }

    /// The line has been quiet for the silence that ends a frame, since the last byte
    /// pushed (MBAP: see [`Resync::pause`]; RTU and ASCII are told by `quiet`).
    pub(crate) fn pause(&mut self) {
        if let Decoding::Mbap(d) = &mut self.decoding {
            d.pause();
        }
    }

    /// Has the line paused since the last byte pushed (MBAP)?
    pub(crate) fn paused(&self) -> bool {
        match &self.decoding {
            Decoding::Mbap(d) => d.paused(),
            Decoding::Serial(_) => false,
        }
    }

    /// Does a quiet line end a partial frame? MBAP (the frame gap) and RTU (3.5
    /// character times) yes; ASCII only ends at a line feed.
    pub(crate) fn silence_ends_frames(&self) -> bool {
        match &self.decoding {
            Decoding::Mbap(_) => true,
            Decoding::Serial(d) => d.silence_ends_frames(),
        }
    }

    /// The next frame, or `None` when more bytes (or a quiet line) are needed. `quiet`:
    /// the line has been silent long enough that a partial frame will never complete.
    /// Bytes that make no frame (noise before an ASCII colon, MBAP garbage) are
    /// dropped and counted, not returned.
    pub fn next_frame(&mut self, judge: &impl Judge, quiet: bool) -> Option<Framed> {
        self.next_frame_as(judge, quiet, 0)
    }

    /// [`Framer::next_frame`]; an RTU or ASCII frame (which carries no transaction id)
    /// made with `tid`, the key of the request it is judged against.
    pub(crate) fn next_frame_as(
        &mut self,
        judge: &impl Judge,
        quiet: bool,
        tid: u16,
    ) -> Option<Framed> {
        match &mut self.decoding {
            Decoding::Mbap(d) => d.next_frame(judge, quiet).map(Framed::Frame),
            Decoding::Serial(d) => loop {
                match d.next(judge.expect(), quiet)? {
                    // A CRC or LRC frame holds 1..=253 PDU bytes (its size limits).
                    Decoded::Frame { unit, pdu } => {
                        self.line_consumed += d.codec().encoded_len(pdu.len()) as u64;
                        let adu = Adu::build_in(&mut self.arena, tid, unit, &pdu);
                        d.recycle(pdu);
                        return Some(Framed::Frame(adu));
                    }
                    Decoded::Corrupt(n) => {
                        self.line_dropped += n as u64;
                        self.line_consumed += n as u64;
                        return Some(Framed::Corrupt(n));
                    }
                    Decoded::Noise(n) => {
                        self.line_dropped += n as u64;
                        self.line_consumed += n as u64;
                    }
                }
            },
        }
    }

    /// RTU: is the partial frame held one whose length its function code tells (the
    /// reply to the judge's request), or will once more bytes are in? False for MBAP
    /// and ASCII.
    pub(crate) fn length_known(&self, judge: &impl Judge) -> bool {
        match &self.decoding {
            Decoding::Mbap(_) => false,
            Decoding::Serial(d) => d.length_known(judge.expect()),
        }
    }

    /// Bytes held that are not yet part of a frame.
    pub fn buffered(&self) -> usize {
        match &self.decoding {
            Decoding::Mbap(d) => d.buffered(),
            Decoding::Serial(d) => d.buffered(),
        }
    }

    /// Forgets every buffered byte (the port was reopened, or nothing before a request
    /// can be its reply); they count as dropped. Returns how many.
    pub(crate) fn clear(&mut self) -> usize {
        match &mut self.decoding {
            Decoding::Mbap(d) => {
                let n = d.buffered();
                d.clear();
                n
            }
            Decoding::Serial(d) => {
                let n = d.clear();
                self.line_dropped += n as u64;
                self.line_consumed += n as u64;
                n
            }
        }
    }

    /// Bytes taken from the front so far, in frames or dropped: a frame just yielded
    /// began at `consumed()` minus its length on the wire.
    pub fn consumed(&self) -> u64 {
        match &self.decoding {
            Decoding::Mbap(d) => d.consumed(),
            Decoding::Serial(_) => self.line_consumed,
        }
    }

    /// Every byte dropped so far: garbage, failed checks, partial frames, cleared.
    pub fn dropped(&self) -> u64 {
        match &self.decoding {
            Decoding::Mbap(d) => d.stats().dropped_bytes,
            Decoding::Serial(_) => self.line_dropped,
        }
    }

    /// Bytes dropped since the last call: what a counter adds.
    pub(crate) fn take_dropped(&mut self) -> u64 {
        let now = self.dropped();
        now - std::mem::replace(&mut self.dropped_taken, now)
    }

    /// MBAP frames that what followed them refuted, so far.
    pub(crate) fn refuted(&self) -> u64 {
        match &self.decoding {
            Decoding::Mbap(d) => d.stats().refuted,
            Decoding::Serial(_) => 0,
        }
    }

    /// Frames refuted since the last call: what a counter adds.
    pub(crate) fn take_refuted(&mut self) -> u64 {
        let now = self.refuted();
        now - std::mem::replace(&mut self.refuted_taken, now)
    }
}

/// For property tests: bytes that mix whole frames of each framing with noise, a
/// piece each (`0` an RTU frame of the PDU, `1` ASCII, `2` MBAP, anything else the
/// bytes themselves, as noise).
#[cfg(test)]
pub(crate) fn mixed_stream(pieces: &[(u8, Vec<u8>)]) -> Vec<u8> {
    use crate::frame::{ascii, rtu};
    let mut data = Vec::new();
    for (how, pdu) in pieces {
        match how {
            0 => data.extend(rtu::encode(1, pdu)),
            1 => data.extend(ascii::encode(1, pdu)),
            2 => data.extend(Adu::build(7, 1, pdu).as_bytes()),
            _ => data.extend(pdu),
        }
    }
    data
}

/// For property tests: the framer of framing `kind % 3` (MBAP, RTU, ASCII).
#[cfg(test)]
pub(crate) fn framer_of(kind: u8) -> Framer {
    match kind % 3 {
        0 => Framer::mbap(),
        1 => Framer::serial(Codec::Rtu),
        _ => Framer::serial(Codec::Ascii),
    }
}

/// The frames `f` yields from `data` fed in chunks of the sizes in `cuts` (the line
/// going quiet after each size that is a multiple of five), then the rest, then a
/// quiet line. Any chunking the property tests and the fuzz target
/// (fuzz/fuzz_targets/framer.rs) draw, fed the one way.
pub fn frame_in_cuts(f: &mut Framer, judge: &impl Judge, data: &[u8], cuts: &[u8]) -> Vec<Adu> {
    let mut out = Vec::new();
    let take = |f: &mut Framer, quiet: bool, out: &mut Vec<Adu>| {
        while let Some(framed) = f.next_frame(judge, quiet) {
            if let Framed::Frame(adu) = framed {
                out.push(adu);
            }
        }
    };
    let mut at = 0;
    for &c in cuts {
        let end = (at + usize::from(c)).min(data.len());
        f.push(&data[at..end]);
        at = end;
        take(f, c % 5 == 0, &mut out);
    }
    f.push(&data[at..]);
    take(f, false, &mut out);
    take(f, true, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{ascii, rtu, ReplyJudge, RequestJudge};

    /// The same request and reply on each framing, in any chunking, give the same
    /// ADU (transaction id 0 where the framing has none), and encode back to the
    /// bytes sent.
    #[test]
    fn one_api_for_the_three_framings() {
        let request = Adu::build(0, 0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]);
        let reply = Adu::build(0, 0x11, &[0x03, 0x06, 0x02, 0x2B, 0x00, 0x00, 0x00, 0x64]);
        let framings = [
            ("mbap", None),
            ("rtu", Some(Codec::Rtu)),
            ("ascii", Some(Codec::Ascii)),
        ];
        for (framing, codec) in framings {
            let new = || codec.map_or_else(Framer::mbap, Framer::serial);
            for (adu, requests) in [(&request, true), (&reply, false)] {
                let wire = new().encode(adu);
                assert_eq!(wire.len(), new().encoded_len(adu.pdu().len()));
                for cut in 0..wire.len() {
                    let mut f = new();
                    let next = |f: &mut Framer| {
                        if requests {
                            f.next_frame(&RequestJudge::default(), false)
                        } else {
                            f.next_frame(&ReplyFor(request.pdu()), false)
                        }
                    };
                    f.push(&wire[..cut]);
                    assert_eq!(next(&mut f), None, "{framing} cut at {cut}");
                    f.push(&wire[cut..]);
                    assert_eq!(next(&mut f), Some(Framed::Frame(adu.clone())), "{framing}");
                    assert_eq!((f.buffered(), f.dropped()), (0, 0));
                    assert_eq!(f.consumed(), wire.len() as u64);
                }
            }
        }
    }

    #[test]
    fn dropped_bytes_are_counted_once_whatever_the_framing() {
        // RTU: a frame whose CRC fails, then one cleared half way.
        let mut f = Framer::serial(Codec::Rtu);
        let mut bad = rtu::encode(1, &[0x06, 0, 1, 0, 3]);
        bad[7] ^= 0xFF;
        f.push(&bad);
        assert_eq!(f.next_frame(&ReplyJudge, false), Some(Framed::Corrupt(8)));
        f.push(&[1, 3]);
        assert_eq!(f.clear(), 2);
        assert_eq!(f.dropped(), 10);
        assert_eq!(f.take_dropped(), 10);
        assert_eq!(f.take_dropped(), 0);
        // ASCII: noise before the colon is dropped, not returned.
        let mut f = Framer::serial(Codec::Ascii);
        f.push(b"zz");
        f.push(&ascii::encode(1, &[0x83, 0x02]));
        let Some(Framed::Frame(adu)) = f.next_frame(&ReplyJudge, false) else {
            panic!("the exception reply")
        };
        assert_eq!(adu.pdu(), [0x83, 0x02]);
        assert_eq!(f.take_dropped(), 2);
        // MBAP: garbage and a cleared partial frame, as the decoder counts them.
        let mut f = Framer::mbap();
        f.push(&[0xFF, 0x13]);
        f.push(Adu::build(5, 1, &[0x83, 0x02]).as_bytes());
        let Some(Framed::Frame(adu)) = f.next_frame(&ReplyJudge, false) else {
            panic!("the exception reply")
        };
        assert_eq!(adu.tid(), 5);
        f.push(&[0, 6, 0]);
        assert_eq!(f.clear(), 3);
        assert_eq!((f.dropped(), f.take_dropped(), f.take_dropped()), (5, 5, 0));
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        /// Every byte pushed is in a frame yielded, counted as dropped, or still held
        /// (ASCII keeps a frame begun at a colon), and every frame yielded encodes
        /// back to as many bytes, on any framing and chunking. The frames come from
        /// bytes that mix whole frames of each framing with noise.
        #[test]
        fn every_byte_is_framed_dropped_or_held(
            kind: u8,
            pieces in proptest::collection::vec(
                (0u8..4, proptest::collection::vec(proptest::num::u8::ANY, 1..12)),
                0..8,
            ),
            cuts in proptest::collection::vec(0u8..40, 0..10),
        ) {
            let data = mixed_stream(&pieces);
            let mut f = framer_of(kind);
            let frames = frame_in_cuts(&mut f, &ReplyJudge, &data, &cuts);
            let yielded: u64 = frames.iter().map(|a| f.encoded_len(a.pdu().len()) as u64).sum();
            proptest::prop_assert_eq!(yielded + f.dropped(), f.consumed());
            proptest::prop_assert_eq!(f.consumed() + f.buffered() as u64, data.len() as u64);
            for adu in frames {
                let mut again = framer_of(kind);
                again.push(&f.encode(&adu));
                proptest::prop_assert_eq!(
                    again.next_frame(&ReplyJudge, true),
                    Some(Framed::Frame(adu))
                );
            }
        }
    }
}
