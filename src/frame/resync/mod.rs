//! The resynchronising MBAP decoder for the serial side (docs/design.md §2): its state
//! machine. What a frame may be is the [`Judge`]'s (`judge.rs`); what becomes of a
//! frame held until what follows it confirms it is `confirm.rs`'s.
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
//!   ([`Judge::confirm`]; the rules in `confirm.rs`), and drops a refuted one whole: a
//!   frame found by rescanning inside it could only be a shifted copy of the next one
//!   with another transaction id (docs/reliability.md). A judge of requests
//!   ([`Judge::resume_inside_refuted`]) has the frame it borrowed from looked for
//!   instead: a frame that starts inside it and runs past its end (one wholly inside
//!   it would be made of its own data).
//!
//! The caller also says when the line has paused ([`Resync::pause`]: quiet for the
//! silence that ends a frame, a few character times, shorter than the frame gap); the
//! decoder keeps where, and the confirmation rules read them.
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

mod confirm;
mod judge;

pub use judge::{Confirmed, Judge, ReplyJudge, RequestJudge};

use super::function::FunctionCode;
use super::mbap::{self, Adu, FrameRef, MAX_LENGTH, MIN_LENGTH, PREFIX_LEN};
use bytes::BytesMut;
use confirm::HeldFate;

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
                            HeldFate::Confirmed => {}
                            HeldFate::Wait => return None,
                            HeldFate::Refuted if !accepted => {
                                // Refused in the first place: rescanned as before.
                                self.drop_one();
                                continue;
                            }
                            HeldFate::Refuted => {
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

#[cfg(test)]
mod tests;
