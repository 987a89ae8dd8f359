//! The resynchronising MBAP decoder for the serial side (docs/design.md §2).
//!
//! The CIE-M10's serial Modbus/TCP mode puts bare MBAP frames on RS232 with no checksum
//! and no framing gaps, and the line can lose bytes (docs/protocol.md §3). The length field
//! is the only delimiter, so the decoder:
//!
//! - accepts a candidate header only if it is plausible (protocol id 0, length 2..=254,
//!   a function code that can exist) and otherwise drops one byte and looks again;
//! - on a complete candidate that the [`Judge`] rejects (wrong shape, or matching no
//!   request), drops one byte and rescans: the next real frame may start inside it;
//!   unless the judge wants it delivered once confirmed ([`Judge::deliver_refused`]),
//!   when it is held like an accepted frame and rescanned only if refuted;
//! - discards a partial candidate once the line has been quiet for the frame gap (the
//!   caller says so with `quiet`), one byte at a time, so frames inside it are found;
//! - counts every byte it drops;
//! - when the judge asks for it, holds a complete frame until it is confirmed
//!   ([`Judge::confirm`]): a frame that lost a byte completes itself with the first
//!   byte of whatever follows, and its length and byte-count fields still agree, so
//!   only what comes after it can expose it. A held frame is handed on when the bytes
//!   after it form a whole frame the judge accepts, or when the line goes quiet with
//!   nothing after it. When the bytes after it cannot start a frame, or start one
//!   that stops before it is complete, it is refuted and dropped whole: either it
//!   borrowed bytes from what follows, or what follows lost bytes, and a frame found
//!   by rescanning inside it could only be a shifted copy of the next one with
//!   another transaction id (docs/reliability.md). A judge of requests
//!   ([`Judge::resume_inside_refuted`]) has the frame it borrowed from looked for
//!   instead: a frame that starts inside it and runs past its end (one wholly inside
//!   it would be made of its own data).
//!
//! The caller also says when the line has paused ([`Resync::pause`]: quiet for the
//! silence that ends a frame, a few character times, shorter than the frame gap). A
//! device sends each frame's bytes back to back, so:
//!
//! - a held frame with nothing after it is confirmed by a pause (if the judge allows:
//!   [`Judge::pause_confirms`]), not only by the frame gap;
//! - a held frame whose own bytes straddle a pause is suspect: what completed it came
//!   after a silence, so it may have borrowed the start of a later frame. Only a whole
//!   frame after it confirms it; quiet refutes it;
//! - a follower that pauses before it is complete, or straddles a pause, refutes the
//!   held frame: a frame does not stop half way;
//! - a held frame that ends with a whole frame the judge accepts is refuted: a run of
//!   lost bytes as long as that frame would make exactly this (the reply's lost tail
//!   filled by a whole frame that followed it), and it cannot be told apart;
//! - a held frame followed by another with its transaction id but other bytes is
//!   refuted: one of them took its id from somewhere else.
//!
//! A judge that knows nothing can follow a frame ([`Judge::alone`]) has it handed on
//! as soon as it is whole, if nothing is buffered after it (and, if the judge asks,
//! it came back to back).
//!
//! State is kept across [`Resync::push`] calls, so any chunking of the byte stream
//! gives the same frames.
//!
//! ```
//! use mbgate::frame::{ReplyJudge, Resync};
//! let mut d = Resync::new();
//! // Noise, then the CIE-M10's read response (docs/protocol.md §3) in two pieces.
//! d.push(&[0xFF, 0x13, 0x00, 0x00, 0x00, 0x00, 0x00, 0x05]);
//! assert!(d.next_frame(&ReplyJudge, false).is_none());
//! d.push(&[0x01, 0x03, 0x02, 0x00, 0xFF]);
//! let frame = d.next_frame(&ReplyJudge, false).unwrap();
//! assert_eq!(frame.pdu(), &[0x03, 0x02, 0x00, 0xFF]);
//! assert_eq!(d.stats().dropped_bytes, 2);
//! ```

use super::function::FunctionCode;
use super::mbap::{self, Adu, FrameRef, MAX_LENGTH, MIN_LENGTH, PREFIX_LEN};
use super::pdu;
use super::serial::Expect;
use bytes::BytesMut;

/// Decides what a frame on the line may be. The relay's judge knows the outstanding
/// requests; [`ReplyJudge`] knows only what any reply must look like.
pub trait Judge {
    /// Could a frame with this function code be on the line at all?
    fn plausible_function(&self, code: FunctionCode) -> bool;
    /// Is this complete, length-consistent candidate a frame to hand on?
    fn accept(&self, frame: FrameRef<'_>) -> bool;
    /// Must this accepted frame wait for confirmation by what follows it, or by a quiet
    /// line? Judges that know nothing can follow (one request outstanding, no
    /// unsolicited frames) say no and get frames without the wait.
    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        false
    }
    /// For a frame [`confirm`](Judge::confirm) would hold, with nothing buffered after
    /// it: may it be handed on at once? Judges that know nothing can follow it on the
    /// line say yes (the relay with one request in flight and nothing else to come,
    /// docs/reliability.md): a frame that lost bytes then has nothing to complete
    /// itself with. `straddles` says the line paused inside it: on a wire what came
    /// after a pause may be noise completing a frame that lost bytes, and a judge
    /// then says no. Bytes already after it show something did come: it is held as
    /// ever.
    fn alone(&self, _frame: FrameRef<'_>, _straddles: bool) -> bool {
        false
    }
    /// May a pause (`Resync::pause`) confirm this held frame when nothing follows
    /// it, or must the line be quiet for the whole frame gap? Judges that expect
    /// another frame soon (other replies due) say no: a pause inside that next frame,
    /// right after a byte this frame borrowed, must not pass for the end of the talk.
    fn pause_confirms(&self, _frame: FrameRef<'_>) -> bool {
        true
    }
    /// Is this complete candidate, which [`accept`](Judge::accept) refused, still to
    /// be handed on once confirmed like a held frame (the relay: the id and unit of a
    /// request in flight, the shape of no reply to it)? Refuted, or left unconfirmed,
    /// it is rescanned byte by byte as any refused candidate is, so a frame shifted by
    /// lost bytes is still found inside it.
    fn deliver_refused(&self, _frame: FrameRef<'_>) -> bool {
        false
    }
    /// When a held frame this judge accepted is refuted, look inside it for the next
    /// frame (the first plausible start that runs past its end) instead of dropping
    /// it whole? A frame that lost bytes borrowed the first bytes of the one behind
    /// it, which then starts inside it. Requests say yes (a serial master's intact
    /// request right behind a damaged one is recovered); replies no (a reply found
    /// that way could be a shifted copy of the next with another id,
    /// docs/reliability.md).
    fn resume_inside_refuted(&self) -> bool {
        false
    }
    /// On an RTU or ASCII line ([`super::framer::Framer`]), what the frame at the front
    /// must be: the reply to a request (whose shape gives the reply's length), or any
    /// request. Any reply, unless the judge knows the request.
    fn expect(&self) -> Expect<'_> {
        Expect::Reply(&[])
    }
}

/// Accepts any well-formed reply to a public function code (docs/design.md §2 shape check).
#[derive(Debug, Default, Clone, Copy)]
pub struct ReplyJudge;

impl Judge for ReplyJudge {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.is_reply()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        pdu::reply_well_formed(frame.pdu())
    }
}

/// Accepts any self-consistent request (the simulator's side of the line): a function
/// code without the exception bit and the size it calls for ([`pdu::request_well_formed`]).
/// With `confirm`, requests wait for what follows them or a quiet line, for a device
/// that takes requests back to back.
#[derive(Debug, Default, Clone, Copy)]
pub struct RequestJudge {
    pub(crate) confirm: bool,
}

impl Judge for RequestJudge {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.can_be_request()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        pdu::request_well_formed(frame.pdu())
    }

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        self.confirm
    }

    fn resume_inside_refuted(&self) -> bool {
        true
    }

    fn expect(&self) -> Expect<'_> {
        Expect::Request
    }
}

/// Another judge's decisions, with every frame held for confirmation.
#[derive(Debug, Default, Clone, Copy)]
pub struct Confirmed<J>(pub J);

impl<J: Judge> Judge for Confirmed<J> {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        self.0.plausible_function(code)
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        self.0.accept(frame)
    }

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        true
    }

    fn pause_confirms(&self, frame: FrameRef<'_>) -> bool {
        self.0.pause_confirms(frame)
    }

    fn expect(&self) -> Expect<'_> {
        self.0.expect()
    }
}

/// What the decoder has done so far.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct ResyncStats {
    pub(crate) frames: u64,
    pub dropped_bytes: u64,
    /// Accepted frames that the bytes after them refuted.
    pub(crate) refuted: u64,
}

/// The decoder. Feed it with [`push`](Resync::push), take frames with
/// [`next_frame`](Resync::next_frame).
#[derive(Debug, Default)]
pub struct Resync {
    buf: BytesMut,
    /// Offsets in `buf` at which the line paused (before the byte at that offset), in
    /// order; `buf.len()` last means it is quiet now.
    pauses: Vec<usize>,
    /// Bytes taken from the front so far (yielded or dropped).
    consumed: u64,
    /// Bytes at the front that belong to a refuted frame searched for the next one
    /// ([`Judge::resume_inside_refuted`]): only a frame that runs past them is taken.
    inside: usize,
    stats: ResyncStats,
}

enum Candidate {
    /// The bytes at the front cannot start a frame.
    Implausible,
    /// They may start one; more bytes are needed.
    Incomplete,
    /// A whole candidate frame of this many bytes is at the front.
    Complete(usize),
}

/// What is to become of a held frame.
enum Verdict {
    /// Hand it on.
    Confirmed,
    /// Wait for more bytes, or for the line to go quiet.
    Wait,
    /// Drop it whole.
    Refuted,
}

/// Judges the header at the front of `buf` with whatever bytes of it have arrived, so
/// garbage is dropped as soon as it shows, not when a whole header is in.
fn candidate(buf: &[u8], judge: &impl Judge) -> Candidate {
    let n = buf.len();
    // Protocol id (bytes 2, 3) is 0; the length (bytes 4, 5) is 2..=254, so byte 4 is 0.
    if buf.iter().take(5).skip(2).any(|&b| b != 0) {
        return Candidate::Implausible;
    }
    if n > 5 && !(MIN_LENGTH..=MAX_LENGTH).contains(&u16::from(buf[5])) {
        return Candidate::Implausible;
    }
    if n > 7 && !judge.plausible_function(FunctionCode::new(buf[7])) {
        return Candidate::Implausible;
    }
    if n < PREFIX_LEN {
        return Candidate::Incomplete;
    }
    let total = PREFIX_LEN + usize::from(buf[5]);
    if n < total {
        Candidate::Incomplete
    } else {
        Candidate::Complete(total)
    }
}

impl Resync {
    /// A decoder with nothing buffered.
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends bytes read from the line.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The line has been quiet, since the last byte pushed, for the silence that ends a
    /// frame (a few character times; see the module notes). Bytes pushed after it are
    /// known to have come after a pause.
    pub(crate) fn pause(&mut self) {
        let at = self.buf.len();
        if at > 0 && self.pauses.last() != Some(&at) {
            self.pauses.push(at);
        }
    }

    /// Has the line paused since the last byte pushed?
    pub(crate) fn paused(&self) -> bool {
        !self.buf.is_empty() && self.pauses.last() == Some(&self.buf.len())
    }

    /// Bytes held that are not yet part of a delivered frame.
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Bytes taken from the front so far, yielded or dropped: the offset, in everything
    /// pushed, of the first byte still held. A frame just yielded began at
    /// `consumed() - its length`.
    pub(crate) fn consumed(&self) -> u64 {
        self.consumed
    }

    /// What the decoder has dropped and why, since it was made.
    pub fn stats(&self) -> ResyncStats {
        self.stats
    }

    /// Forgets every buffered byte (the port was closed or reopened); they count as
    /// dropped.
    pub(crate) fn clear(&mut self) {
        self.stats.dropped_bytes += self.buf.len() as u64;
        self.skip(self.buf.len());
    }

    /// Removes `n` bytes from the front, keeping the pauses after them.
    fn take(&mut self, n: usize) -> BytesMut {
        self.forget(n);
        self.buf.split_to(n)
    }

    /// Drops `n` bytes from the front, keeping the pauses after them.
    fn skip(&mut self, n: usize) {
        self.forget(n);
        mbap::skip(&mut self.buf, n);
    }

    fn forget(&mut self, n: usize) {
        self.consumed += n as u64;
        self.inside = self.inside.saturating_sub(n);
        if !self.pauses.is_empty() {
            self.pauses.retain_mut(|p| {
                *p = p.saturating_sub(n);
                *p > 0
            });
        }
    }

    fn drop_one(&mut self) {
        self.skip(1);
        self.stats.dropped_bytes += 1;
    }

    /// Did the line pause strictly between the bytes at `from` and `to`?
    fn pause_within(&self, from: usize, to: usize) -> bool {
        self.pauses.iter().any(|&p| from < p && p < to)
    }

    /// What is to become of the held frame of `total` bytes at the front, given what
    /// follows it. `quiet`: the frame gap has passed.
    fn verdict(&self, total: usize, judge: &impl Judge, quiet: bool) -> Verdict {
        let frame = FrameRef::new(&self.buf[..total]);
        let straddles = self.pause_within(0, total);
        let rest = &self.buf[total..];
        let quiet_now = quiet || self.paused();
        if rest.is_empty() {
            return if !quiet_now {
                Verdict::Wait
            } else if straddles {
                // Completed after a silence by bytes nothing confirms.
                Verdict::Refuted
            } else if !quiet && !judge.pause_confirms(frame) {
                Verdict::Wait
            } else if ends_with_a_frame(&self.buf[..total], judge) {
                Verdict::Refuted
            } else {
                Verdict::Confirmed
            };
        }
        match candidate(rest, judge) {
            Candidate::Implausible => Verdict::Refuted,
            // A frame does not stop half way: one that pauses is the tail of a frame
            // that gained bytes or the start of one that lost some.
            Candidate::Incomplete if quiet_now || self.pause_within(total, self.buf.len()) => {
                Verdict::Refuted
            }
            Candidate::Incomplete => Verdict::Wait,
            Candidate::Complete(n) => {
                let follower = FrameRef::new(&rest[..n]);
                // The same id with other bytes: one of the two is not what it claims
                // (a duplicate reply is the same bytes).
                let contradicts = follower.tid() == frame.tid() && follower != frame;
                if self.pause_within(total, total + n)
                    || contradicts
                    || !judge.accept(follower)
                    || ends_with_a_frame(&self.buf[..total], judge)
                {
                    Verdict::Refuted
                } else {
                    Verdict::Confirmed
                }
            }
        }
    }

    /// The next frame the judge accepts, or `None` when more bytes are needed.
    ///
    /// `quiet` says the line has given no byte for the frame gap: a partial candidate
    /// will never complete, so it is discarded byte by byte and the rest rescanned.
    /// After a call with `quiet` that returns `None`, the buffer is empty.
    pub fn next_frame(&mut self, judge: &impl Judge, quiet: bool) -> Option<Adu> {
        loop {
            match candidate(&self.buf, judge) {
                Candidate::Implausible => self.drop_one(),
                // Made of a refuted frame's own bytes (`resume_inside_refuted`).
                Candidate::Complete(total) if total <= self.inside => self.drop_one(),
                Candidate::Incomplete if quiet && !self.buf.is_empty() => self.drop_one(),
                Candidate::Incomplete => return None,
                Candidate::Complete(total) => {
                    let frame = FrameRef::new(&self.buf[..total]);
                    let accepted = judge.accept(frame);
                    if !accepted && !judge.deliver_refused(frame) {
                        self.drop_one();
                        continue;
                    }
                    let alone = accepted
                        && total == self.buf.len()
                        && judge.alone(frame, self.pause_within(0, total));
                    if !accepted || (judge.confirm(frame) && !alone) {
                        match self.verdict(total, judge, quiet) {
                            Verdict::Confirmed => {}
                            Verdict::Wait => return None,
                            Verdict::Refuted if !accepted => {
                                // Refused in the first place: rescanned as before.
                                self.drop_one();
                                continue;
                            }
                            Verdict::Refuted => {
                                // Skipped whole: a frame found inside it could only be
                                // a shifted copy of what follows. Unless the judge
                                // looks for the frame it borrowed from.
                                self.stats.refuted += 1;
                                if judge.resume_inside_refuted() {
                                    self.inside = total;
                                    self.drop_one();
                                } else {
                                    self.skip(total);
                                    self.stats.dropped_bytes += total as u64;
                                }
                                continue;
                            }
                        }
                    }
                    self.stats.frames += 1;
                    return Some(Adu::from_frame(self.take(total).freeze()));
                }
            }
        }
    }
}

/// Does `held` end with a whole frame the judge accepts, starting after its first byte?
/// A frame whose tail was lost, with exactly as many bytes lost as a whole frame that
/// followed it, completes itself with that frame (docs/reliability.md).
fn ends_with_a_frame(held: &[u8], judge: &impl Judge) -> bool {
    let smallest = PREFIX_LEN + usize::from(MIN_LENGTH);
    (1..=held.len().saturating_sub(smallest)).any(|i| {
        matches!(candidate(&held[i..], judge), Candidate::Complete(n) if i + n == held.len())
            && judge.accept(FrameRef::new(&held[i..]))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::{parse as bytes, Hex};
    use proptest::prelude::{prop, Strategy};

    /// Replies of several shapes, the CIE-M10's among them (docs/protocol.md §3).
    fn replies() -> Vec<Vec<u8>> {
        vec![
            bytes("00 01 00 00 00 05 01 03 02 00 FF"),
            bytes("00 02 00 00 00 06 01 10 00 08 00 01"),
            bytes("00 03 00 00 00 03 01 83 02"),
            bytes("00 04 00 00 00 06 11 01 03 CD 6B 05"),
            bytes("00 05 00 00 00 09 01 03 06 00 01 00 02 00 03"),
        ]
    }

    /// Feeds the chunks, then declares the line quiet, collecting every frame.
    fn decode(chunks: &[&[u8]]) -> (Vec<Vec<u8>>, ResyncStats) {
        let mut d = Resync::new();
        let mut out = Vec::new();
        for chunk in chunks {
            d.push(chunk);
            while let Some(f) = d.next_frame(&ReplyJudge, false) {
                out.push(f.as_bytes().to_vec());
            }
        }
        while let Some(f) = d.next_frame(&ReplyJudge, true) {
            out.push(f.as_bytes().to_vec());
        }
        assert_eq!(d.buffered(), 0, "quiet leaves nothing behind");
        (out, d.stats())
    }

    #[test]
    fn clean_stream_at_every_split_offset() {
        let all: Vec<u8> = replies().concat();
        for cut in 0..=all.len() {
            let (frames, stats) = decode(&[&all[..cut], &all[cut..]]);
            assert_eq!(frames, replies(), "split at {cut}");
            assert_eq!(stats.dropped_bytes, 0);
        }
    }

    #[test]
    fn clean_stream_at_every_pair_of_split_offsets() {
        let all: Vec<u8> = replies().concat();
        for a in 0..=all.len() {
            for b in a..=all.len() {
                let (frames, _) = decode(&[&all[..a], &all[a..b], &all[b..]]);
                assert_eq!(frames, replies(), "split at {a} and {b}");
            }
        }
    }

    #[test]
    fn one_byte_at_a_time() {
        let all: Vec<u8> = replies().concat();
        let chunks: Vec<&[u8]> = all.chunks(1).collect();
        assert_eq!(decode(&chunks).0, replies());
    }

    #[test]
    fn garbage_before_and_between_frames() {
        let r = replies();
        let garbage = bytes("FF 13 00 00 7E 00 00 00 00 01 00 00 00 FF");
        let mut all = garbage.clone();
        for f in &r {
            all.extend(f);
            all.extend(&garbage);
        }
        for cut in 0..=all.len() {
            let (frames, stats) = decode(&[&all[..cut], &all[cut..]]);
            assert_eq!(frames, r, "split at {cut}");
            assert_eq!(stats.dropped_bytes, (garbage.len() * (r.len() + 1)) as u64);
        }
    }

    #[test]
    fn garbage_inside_a_header_loses_only_that_frame() {
        let r = replies();
        let mut broken = r[1].clone();
        broken.insert(3, 0x55); // inside the protocol id
        let all = [r[0].clone(), broken.clone(), r[2].clone(), r[3].clone()].concat();
        for cut in 0..=all.len() {
            let (frames, stats) = decode(&[&all[..cut], &all[cut..]]);
            assert_eq!(frames, vec![r[0].clone(), r[2].clone(), r[3].clone()]);
            assert_eq!(stats.dropped_bytes, broken.len() as u64);
        }
    }

    #[test]
    fn garbage_inside_a_reply_that_breaks_its_shape() {
        let r = replies();
        // Noise on the byte count of the FC 03 reply: it no longer fits the length.
        let mut broken = r[4].clone();
        broken[8] = 0x05;
        let all = [r[0].clone(), broken, r[2].clone()].concat();
        let (frames, _) = decode(&[&all]);
        assert_eq!(frames, vec![r[0].clone(), r[2].clone()]);
    }

    #[test]
    fn a_lost_header_byte_loses_only_that_frame() {
        let r = replies();
        for lost in 0..7 {
            let mut broken = r[1].clone();
            broken.remove(lost);
            let all = [r[0].clone(), broken, r[2].clone(), r[3].clone()].concat();
            let (frames, _) = decode(&[&all]);
            assert_eq!(
                frames,
                vec![r[0].clone(), r[2].clone(), r[3].clone()],
                "lost byte {lost}"
            );
        }
    }

    #[test]
    fn a_frame_inside_a_plausible_long_candidate_is_found_after_the_gap() {
        // Garbage that looks like the start of a 254-byte frame, then a real reply.
        let fake = bytes("00 09 00 00 00 FE 01 03");
        let real = replies()[0].clone();
        let mut d = Resync::new();
        d.push(&fake);
        d.push(&real);
        assert_eq!(d.next_frame(&ReplyJudge, false), None, "waits for more");
        let f = d.next_frame(&ReplyJudge, true).expect("found once quiet");
        assert_eq!(f.as_bytes(), &real[..]);
        assert_eq!(d.stats().dropped_bytes, fake.len() as u64);
    }

    #[test]
    fn a_truncated_frame_is_dropped_when_quiet() {
        let r = replies();
        let (frames, stats) = decode(&[&r[0][..8]]);
        assert!(frames.is_empty());
        assert_eq!(stats.dropped_bytes, 8);
    }

    #[test]
    fn clear_counts_what_it_forgets() {
        let mut d = Resync::new();
        d.push(&replies()[0][..5]);
        d.clear();
        assert_eq!(d.buffered(), 0);
        assert_eq!(d.stats().dropped_bytes, 5);
    }

    /// The shape check of [`ReplyJudge`], with every frame held for confirmation.
    const STRICT: Confirmed<ReplyJudge> = Confirmed(ReplyJudge);

    fn decode_with(judge: &impl Judge, chunks: &[&[u8]]) -> Vec<Vec<u8>> {
        let mut d = Resync::new();
        let mut out = Vec::new();
        for chunk in chunks {
            d.push(chunk);
            while let Some(f) = d.next_frame(judge, false) {
                out.push(f.as_bytes().to_vec());
            }
        }
        while let Some(f) = d.next_frame(judge, true) {
            out.push(f.as_bytes().to_vec());
        }
        out
    }

    #[test]
    fn a_reply_that_lost_a_byte_is_refuted_by_what_follows() {
        // The FC 03 reply loses its last data byte and completes itself with the
        // first byte of the next reply: shape and length still agree.
        let r = replies();
        let mut broken = r[4].clone();
        broken.remove(10);
        let all = [broken.clone(), r[0].clone(), r[1].clone()].concat();
        let lenient = decode_with(&ReplyJudge, &[&all]);
        assert_eq!(
            lenient[0],
            [&broken[..], &r[0][..1]].concat(),
            "delivered wrong"
        );
        let strict = decode_with(&STRICT, &[&all]);
        assert!(!strict.contains(&lenient[0]), "never delivered when held");
        assert_eq!(strict.last(), Some(&r[1]));
    }

    #[test]
    fn a_held_frame_waits_for_what_follows_or_for_quiet() {
        let r = replies();
        let mut d = Resync::new();
        d.push(&r[0]);
        assert_eq!(d.next_frame(&STRICT, false), None, "nothing after it yet");
        d.push(&r[1][..7]);
        assert_eq!(d.next_frame(&STRICT, false), None, "only a header after it");
        d.push(&r[1][7..]);
        assert_eq!(d.next_frame(&STRICT, false).unwrap().as_bytes(), &r[0][..]);
        assert_eq!(d.next_frame(&STRICT, false), None, "the last one waits");
        assert_eq!(d.next_frame(&STRICT, true).unwrap().as_bytes(), &r[1][..]);
        // A plausible start that never completes refutes it once the line is quiet:
        // this is how a frame that gained a noise byte ends.
        d.push(&r[2]);
        d.push(&r[3][..4]);
        assert_eq!(d.next_frame(&STRICT, false), None);
        assert_eq!(d.next_frame(&STRICT, true), None);
        assert_eq!(d.buffered(), 0);
        assert_eq!(d.stats().refuted, 1);
        // A noise byte inside a reply: it ends a byte early, and its own last byte
        // is left over.
        let mut noisy = r[4].clone();
        noisy.insert(9, 0x5A);
        d.push(&noisy);
        assert_eq!(d.next_frame(&STRICT, false), None);
        assert_eq!(d.next_frame(&STRICT, true), None);
        assert_eq!(d.stats().refuted, 2);
    }

    /// Every single lost byte of every reply, before every other reply: a held frame
    /// is never one that was not sent.
    #[test]
    fn loss_of_any_one_byte_never_yields_a_frame_that_was_not_sent() {
        let r = replies();
        for (i, victim) in r.iter().enumerate() {
            for lost in 0..victim.len() {
                let mut broken = victim.clone();
                broken.remove(lost);
                let rest: Vec<Vec<u8>> = r
                    .iter()
                    .cycle()
                    .skip(i + 1)
                    .take(r.len())
                    .cloned()
                    .collect();
                let all = [vec![broken], rest.clone()].concat().concat();
                for f in decode_with(&STRICT, &[&all]) {
                    assert!(
                        r.contains(&f),
                        "lost byte {lost} of reply {i}: {:?}",
                        Hex(&f)
                    );
                }
            }
        }
    }

    /// What the line does in a scripted test.
    enum Step<'a> {
        Bytes(&'a [u8]),
        /// Quiet for the silence that ends a frame.
        Pause,
        /// Quiet for the frame gap.
        Gap,
    }

    /// Runs the steps, taking frames after each, as the relay does.
    fn run(judge: &impl Judge, steps: &[Step<'_>]) -> (Vec<Vec<u8>>, Resync) {
        let mut d = Resync::new();
        let mut out = Vec::new();
        for step in steps {
            let quiet = match step {
                Step::Bytes(b) => {
                    d.push(b);
                    false
                }
                Step::Pause => {
                    d.pause();
                    false
                }
                Step::Gap => {
                    d.pause();
                    true
                }
            };
            while let Some(f) = d.next_frame(judge, quiet) {
                out.push(f.as_bytes().to_vec());
            }
        }
        (out, d)
    }

    /// A judge for a line with other replies due: a pause confirms nothing, only the
    /// frame gap does.
    struct RepliesDue;
    impl Judge for RepliesDue {
        fn plausible_function(&self, code: FunctionCode) -> bool {
            code.is_reply()
        }
        fn accept(&self, frame: FrameRef<'_>) -> bool {
            pdu::reply_well_formed(frame.pdu())
        }
        fn confirm(&self, _: FrameRef<'_>) -> bool {
            true
        }
        fn pause_confirms(&self, _: FrameRef<'_>) -> bool {
            false
        }
    }

    /// A relay's view with a read of one register in flight as id 7: a frame with id 7
    /// of another shape is refused, but to be delivered once confirmed.
    struct OneRegisterAsked;
    impl Judge for OneRegisterAsked {
        fn plausible_function(&self, code: FunctionCode) -> bool {
            code.is_reply()
        }
        fn accept(&self, frame: FrameRef<'_>) -> bool {
            let asked = [0x03, 0x00, 0x0A, 0x00, 0x01];
            match frame.tid() {
                7 => pdu::reply_matches(&asked, frame.pdu()),
                _ => pdu::reply_well_formed(frame.pdu()),
            }
        }
        fn confirm(&self, _: FrameRef<'_>) -> bool {
            true
        }
        fn deliver_refused(&self, frame: FrameRef<'_>) -> bool {
            frame.tid() == 7
        }
    }

    /// A refused frame the judge wants is delivered once a pause confirms it; one that
    /// lost its byte count and borrowed the next frame's first byte is refuted by what
    /// follows and rescanned byte by byte, so that next frame is still found (dropping
    /// it whole, as an accepted frame is, would lose it).
    #[test]
    fn a_refused_frame_the_judge_wants_is_delivered_confirmed_and_rescanned_refuted() {
        let two = bytes("00 07 00 00 00 07 01 03 04 00 01 00 02");
        let (got, _) = run(&OneRegisterAsked, &[Step::Bytes(&two), Step::Pause]);
        assert_eq!(got, vec![two.clone()]);
        let (got, _) = run(&OneRegisterAsked, &[Step::Bytes(&two)]);
        assert!(got.is_empty(), "held until confirmed: {got:02X?}");

        let mut lost = bytes("00 07 00 00 00 05 01 03 02 00 2A");
        lost.remove(8);
        let n = bytes(NOTIFICATION);
        let all = [lost, n.clone()].concat();
        for cut in 0..=all.len() {
            let (got, _) = run(
                &OneRegisterAsked,
                &[
                    Step::Bytes(&all[..cut]),
                    Step::Bytes(&all[cut..]),
                    Step::Gap,
                ],
            );
            assert_eq!(got, vec![n.clone()], "cut at {cut}");
        }
    }

    /// An FC 03 reply for three registers holding 23413, 23402, 23403.
    const A: &str = "00 07 00 00 00 09 01 03 06 5B 75 5B 6A 5B 6B";
    /// A change notification (docs/protocol.md §3), transaction id 0.
    const NOTIFICATION: &str = "00 00 00 00 00 05 01 03 02 00 0F";
    /// A 9-byte exception reply and an FC 16 echo.
    const C: &str = "00 0C 00 00 00 03 01 83 02";
    const B: &str = "00 0B 00 00 00 06 01 10 00 08 00 01";

    /// A lost data byte, then a notification at once: the reply completes itself with
    /// the notification's first byte (values 23387, 27227, 27392), and only what comes
    /// after that byte exposes it. Held for confirmation, it is never handed on.
    #[test]
    fn a_notification_at_once_after_a_reply_that_lost_a_byte_refutes_it() {
        let mut a = bytes(A);
        a.remove(10);
        let n = bytes(NOTIFICATION);
        let wrong = [&a[..], &n[..1]].concat();
        let all = [a.clone(), n].concat();
        assert_eq!(decode_with(&ReplyJudge, &[&all])[0], wrong, "taken unheld");
        for cut in 0..=all.len() {
            for quiet in [Step::Pause, Step::Gap] {
                let (got, d) = run(
                    &STRICT,
                    &[Step::Bytes(&all[..cut]), Step::Bytes(&all[cut..]), quiet],
                );
                // The notification goes with it: what is left of it cannot start a frame.
                assert!(got.is_empty(), "split at {cut}: {got:02X?}");
                assert_eq!(d.stats().refuted, 1);
            }
        }
    }

    /// A reply that lost its last byte borrows the next frame's first, and that frame
    /// pauses right after it: the borrowed byte ends the reply before the pause. With
    /// other replies due, a pause does not confirm it, and the rest of the frame,
    /// coming before the frame gap, refutes it.
    #[test]
    fn a_pause_inside_the_next_frame_does_not_confirm_a_reply_while_others_are_due() {
        let a = bytes(A);
        let b = bytes(B);
        let wrong = [&a[..a.len() - 1], &b[..1]].concat();
        let paused = [
            Step::Bytes(&wrong),
            Step::Pause,
            Step::Bytes(&b[1..]),
            Step::Gap,
        ];
        let (got, d) = run(&RepliesDue, &paused);
        assert!(got.is_empty(), "{got:02X?}");
        assert_eq!((d.stats().refuted, d.buffered()), (1, 0));
        // The bounds docs/reliability.md states: with nothing else due a pause
        // confirms it, and with replies due the frame gap does.
        assert_eq!(run(&STRICT, &paused).0, vec![wrong.clone()]);
        let gap = [
            Step::Bytes(&wrong),
            Step::Gap,
            Step::Bytes(&b[1..]),
            Step::Gap,
        ];
        assert_eq!(run(&RepliesDue, &gap).0, vec![wrong]);
        // The reply whole, the next frame after a pause: both delivered.
        let steps = [Step::Bytes(&a), Step::Pause, Step::Bytes(&b), Step::Gap];
        assert_eq!(run(&RepliesDue, &steps).0, vec![a.clone(), b.clone()]);
        let (got, d) = run(&RepliesDue, &[Step::Bytes(&a), Step::Pause]);
        assert!(got.is_empty(), "waits for what follows");
        assert_eq!(d.buffered(), a.len());
    }

    /// A frame completed by bytes that came after a pause may have borrowed the start
    /// of a later frame: only a whole frame after it confirms it, quiet refutes it.
    #[test]
    fn a_frame_that_straddles_a_pause_needs_a_whole_frame_after_it() {
        let mut a = bytes(A);
        a.truncate(a.len() - 2);
        let n = bytes(NOTIFICATION);
        // A lost its last two bytes; the notification came later, after a pause, and
        // lost everything after its second byte.
        let (got, d) = run(
            &STRICT,
            &[
                Step::Bytes(&a),
                Step::Pause,
                Step::Bytes(&n[..2]),
                Step::Pause,
            ],
        );
        assert!(got.is_empty(), "{got:02X?}");
        assert_eq!((d.stats().refuted, d.buffered()), (1, 0));
        // A whole frame right after it does confirm it (a device that paused inside
        // a frame: outside what the pause assumes, but not refused).
        let whole = bytes(A);
        let (got, _) = run(
            &STRICT,
            &[
                Step::Bytes(&whole[..5]),
                Step::Pause,
                Step::Bytes(&whole[5..]),
                Step::Bytes(&n),
                Step::Gap,
            ],
        );
        assert_eq!(got, vec![whole, n]);
    }

    /// A follower that stops half way (a pause inside it, or after its start) refutes
    /// the held frame, and one that straddles a pause does not confirm it.
    #[test]
    fn a_follower_that_pauses_refutes_the_held_frame() {
        let a = bytes(A);
        let b = bytes(B);
        let (got, d) = run(
            &STRICT,
            &[Step::Bytes(&a), Step::Bytes(&b[..4]), Step::Pause],
        );
        assert!(got.is_empty());
        assert_eq!(d.stats().refuted, 1);
        let (got, d) = run(
            &STRICT,
            &[
                Step::Bytes(&a),
                Step::Bytes(&b[..4]),
                Step::Pause,
                Step::Bytes(&b[4..]),
                Step::Gap,
            ],
        );
        assert!(!got.contains(&a), "{got:02X?}");
        assert!(d.stats().refuted >= 1);
    }

    /// A run of lost bytes exactly as long as the frame after the reply, ending where
    /// the reply ended: the reply is completed by that whole frame, and the frame
    /// after confirms it. A held frame that ends with a whole frame is refuted.
    #[test]
    fn a_reply_that_swallowed_a_whole_frame_is_refuted() {
        let a = bytes("00 05 00 00 00 19 01 03 16 00 01 00 02 00 03 00 04 00 05 00 06 00 07 00 08 00 09 00 0A 00 0B");
        let (b, c) = (bytes(B), bytes(C));
        let swallowed = [&a[..a.len() - c.len()], &c[..]].concat();
        let (got, d) = run(
            &STRICT,
            &[Step::Bytes(&swallowed), Step::Bytes(&b), Step::Gap],
        );
        assert_eq!(got, vec![b.clone()]);
        assert_eq!(d.stats().refuted, 1);
        // A 10-register reply that lost 11 bytes holds a whole notification: refuted
        // when quiet follows too.
        let n = bytes(NOTIFICATION);
        let swallowed = [&a[..a.len() - n.len()], &n[..]].concat();
        let (got, _) = run(&STRICT, &[Step::Bytes(&swallowed), Step::Pause]);
        assert!(got.is_empty(), "{got:02X?}");
        // The same frame not at the end of the reply is register data: delivered.
        let data = [&a[..9], &n[..], &a[20..]].concat();
        let (got, _) = run(&STRICT, &[Step::Bytes(&data), Step::Pause]);
        assert_eq!(got, vec![data]);
    }

    /// What remains (docs/reliability.md): the same run of lost bytes, split between
    /// the reply's tail and the swallowed frame's head, leaves the reply completed by
    /// that frame's tail, which nothing on the wire tells from register values.
    #[test]
    fn a_run_as_long_as_a_frame_split_across_its_start_is_not_detected() {
        let a = bytes(A);
        let (b, c) = (bytes(B), bytes(C));
        let wrong = [&a[..a.len() - 4], &c[5..]].concat();
        let (got, _) = run(&STRICT, &[Step::Bytes(&wrong), Step::Bytes(&b), Step::Gap]);
        assert_eq!(got, vec![wrong, b]);
    }

    /// A notification that lost both bytes of its id takes the two bytes before it as
    /// one: register values that equal the id of a request in flight. The real reply
    /// after it carries that id with other bytes: the two contradict each other and the
    /// first is refuted. A duplicate (the same bytes twice) confirms.
    #[test]
    fn a_frame_followed_by_its_own_id_with_other_bytes_is_refuted() {
        let n = bytes(NOTIFICATION);
        let reply = bytes("01 03 00 00 00 05 01 03 02 00 2A");
        // A damaged frame whose last register holds 0x0103, then the notification
        // without its id, then the reply to request 0x0103.
        let taken = [&[0x01u8, 0x03][..], &n[2..]].concat();
        let all = [
            &bytes("00 09 00 00 00 05 01 03")[..],
            &taken[..],
            &reply[..],
        ]
        .concat();
        let (got, d) = run(&STRICT, &[Step::Bytes(&all), Step::Pause]);
        assert_eq!(got, vec![reply.clone()], "{got:02X?}");
        assert!(!got.contains(&taken));
        assert_eq!(d.stats().refuted, 1);
        let twice = [&reply[..], &reply[..]].concat();
        let (got, _) = run(&STRICT, &[Step::Bytes(&twice), Step::Pause]);
        assert_eq!(got, vec![reply.clone(), reply]);
    }

    #[test]
    fn pauses_move_with_the_bytes_taken() {
        let a = bytes(A);
        let mut d = Resync::new();
        d.pause();
        assert!(!d.paused(), "nothing buffered: nothing to mark");
        d.push(&a[..3]);
        d.pause();
        d.pause();
        assert!(d.paused());
        assert_eq!(d.pauses, vec![3]);
        d.push(&a[3..]);
        assert!(!d.paused());
        d.drop_one();
        assert_eq!(d.pauses, vec![2]);
        d.skip(2);
        assert!(
            d.pauses.is_empty(),
            "a pause before the first byte is no pause"
        );
        assert_eq!(d.consumed(), 3);
    }

    struct OnlyTid(u16);
    impl Judge for OnlyTid {
        fn plausible_function(&self, code: FunctionCode) -> bool {
            code.is_reply()
        }
        fn accept(&self, frame: FrameRef<'_>) -> bool {
            frame.tid() == self.0
        }
    }

    #[test]
    fn the_judge_decides() {
        let r = replies();
        let all = r.concat();
        let mut d = Resync::new();
        d.push(&all);
        let f = d.next_frame(&OnlyTid(3), true).unwrap();
        assert_eq!(f.as_bytes(), &r[2][..]);
        assert_eq!(d.next_frame(&OnlyTid(3), true), None);
    }

    /// The relay's view with one read in flight (id 0x1234, unit 1, `qty` registers)
    /// and nothing able to follow it: replies are held (confirm), but a whole one with
    /// nothing after it is taken at once, on a wire only if no pause came inside it.
    struct LoneRead {
        asked: [u8; 5],
        wire: bool,
    }
    impl Judge for LoneRead {
        fn plausible_function(&self, code: FunctionCode) -> bool {
            code.is_reply()
        }
        fn accept(&self, frame: FrameRef<'_>) -> bool {
            frame.tid() == 0x1234
                && frame.unit() == 1
                && pdu::reply_matches(&self.asked, frame.pdu())
        }
        fn confirm(&self, _: FrameRef<'_>) -> bool {
            true
        }
        fn alone(&self, _: FrameRef<'_>, straddles: bool) -> bool {
            !(straddles && self.wire)
        }
    }

    /// Feeds `bytes` cut at `cuts`, the line pausing at `pauses` (offsets), then
    /// paused and quiet: every frame taken.
    fn feed(judge: &impl Judge, bytes: &[u8], cuts: &[usize], pauses: &[usize]) -> Vec<Vec<u8>> {
        let n = bytes.len();
        let mut stops: Vec<(usize, bool)> = cuts.iter().map(|&c| (c % (n + 1), false)).collect();
        stops.extend(pauses.iter().map(|&p| (p % (n + 1), true)));
        stops.sort_unstable();
        let mut d = Resync::new();
        let mut out = Vec::new();
        let mut at = 0;
        for (stop, pause) in stops.into_iter().chain([(n, true)]) {
            d.push(&bytes[at..stop]);
            at = stop;
            if pause {
                d.pause();
            }
            while let Some(f) = d.next_frame(judge, false) {
                out.push(f.as_bytes().to_vec());
            }
        }
        while let Some(f) = d.next_frame(judge, true) {
            out.push(f.as_bytes().to_vec());
        }
        out
    }

    /// An FC 03 reply to [`LoneRead`] whose data bytes are `data`.
    fn lone_reply(data: &[u8]) -> Vec<u8> {
        let mut r = vec![
            0x12,
            0x34,
            0,
            0,
            0,
            3 + data.len() as u8,
            1,
            3,
            data.len() as u8,
        ];
        r.extend_from_slice(data);
        r
    }

    /// Data bytes that cannot spell a header: no zero (a protocol id), no 3 (an
    /// exception's length); condition 3 of docs/reliability.md made concrete.
    fn plain_data() -> impl Strategy<Value = Vec<u8>> {
        (1usize..=20).prop_flat_map(|n| {
            prop::collection::vec((1u8..=255).prop_filter("not 3", |b| *b != 3), 2 * n)
        })
    }

    proptest::proptest! {
        /// docs/reliability.md, "When nothing can follow a reply": a reply that lost
        /// up to 8 bytes anywhere, at any chunking, with pauses anywhere (on a wire or
        /// not), and nothing after it, is taken only whole or not at all; whole,
        /// unpaused (or with no wire), it is taken.
        #[test]
        fn a_lone_reply_is_never_completed_by_its_own_bytes(
            data in plain_data(),
            lost in prop::collection::vec(proptest::prelude::any::<usize>(), 0..=8),
            cuts in prop::collection::vec(proptest::prelude::any::<usize>(), 0..=6),
            pauses in prop::collection::vec(proptest::prelude::any::<usize>(), 0..=3),
            wire in proptest::prelude::any::<bool>(),
        ) {
            let reply = lone_reply(&data);
            let mut gone: Vec<usize> = lost.iter().map(|i| i % reply.len()).collect();
            gone.sort_unstable();
            gone.dedup();
            let received: Vec<u8> = reply
                .iter()
                .enumerate()
                .filter(|(i, _)| gone.binary_search(i).is_err())
                .map(|(_, b)| *b)
                .collect();
            let qty = (data.len() / 2) as u8;
            let judge = LoneRead { asked: [3, 0, 0, 0, qty], wire };
            let got = feed(&judge, &received, &cuts, &pauses);
            for f in &got {
                proptest::prop_assert_eq!(f, &reply, "lost {:?}", gone);
            }
            let paused_inside = pauses.iter().any(|p| {
                let p = p % (received.len() + 1);
                0 < p && p < received.len()
            });
            if gone.is_empty() && !(wire && paused_inside) {
                proptest::prop_assert_eq!(got, vec![reply]);
            }
        }

        /// Noise read with a lone reply that lost bytes, more bytes of it than were
        /// lost: what is after the completed reply refutes it.
        #[test]
        fn noise_read_with_a_damaged_lone_reply_refutes_it(
            data in plain_data(),
            lost in prop::collection::vec(proptest::prelude::any::<usize>(), 1..=4),
            noise in prop::collection::vec(proptest::prelude::any::<u8>(), 5..=8),
        ) {
            let reply = lone_reply(&data);
            let mut gone: Vec<usize> = lost.iter().map(|i| i % reply.len()).collect();
            gone.sort_unstable();
            gone.dedup();
            let mut received: Vec<u8> = reply
                .iter()
                .enumerate()
                .filter(|(i, _)| gone.binary_search(i).is_err())
                .map(|(_, b)| *b)
                .collect();
            received.extend_from_slice(&noise);
            let qty = (data.len() / 2) as u8;
            let judge = LoneRead { asked: [3, 0, 0, 0, qty], wire: true };
            for f in feed(&judge, &received, &[], &[]) {
                proptest::prop_assert_eq!(&f, &reply);
            }
        }
    }
}
