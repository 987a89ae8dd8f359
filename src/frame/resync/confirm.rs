//! What becomes of a frame the decoder holds for confirmation ([`Judge::confirm`];
//! docs/reliability.md): handed on, waited on, or refuted, given what follows it and
//! where the line paused.
//!
//! A frame that lost a byte completes itself with the first byte of whatever follows,
//! and its length and byte-count fields still agree, so only what comes after it can
//! expose it. A held frame is handed on when the bytes after it form a whole frame the
//! judge accepts, or when the line goes quiet with nothing after it. When the bytes
//! after it cannot start a frame, or start one that stops before it is complete, it is
//! refuted: either it borrowed bytes from what follows, or what follows lost bytes.
//!
//! A device sends each frame's bytes back to back, so, with the pauses the caller
//! reported ([`Resync::pause`]):
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
//!   refuted: one of them took its id from somewhere else (not id 0, which every
//!   device notification carries).
//!

use super::{candidate, Candidate, Judge, Resync};
use crate::frame::mbap::{FrameRef, MIN_LENGTH, PREFIX_LEN};

/// What is to become of a held frame.
pub(super) enum HeldFate {
    /// Hand it on.
    Confirmed,
    /// Wait for more bytes, or for the line to go quiet.
    Wait,
    /// Drop it whole.
    Refuted,
}

impl Resync {
    /// What is to become of the held frame of `total` bytes at the front, given what
    /// follows it. `quiet`: the frame gap has passed.
    pub(super) fn verdict(&self, total: usize, judge: &impl Judge, quiet: bool) -> HeldFate {
        let frame = FrameRef::new(&self.buf[..total]);
        let straddles = self.pause_within(0, total);
        let rest = &self.buf[total..];
        let quiet_now = quiet || self.paused();
        if rest.is_empty() {
            return if !quiet_now {
                HeldFate::Wait
            } else if straddles {
                // Completed after a silence by bytes nothing confirms.
                HeldFate::Refuted
            } else if !quiet && !judge.pause_confirms(frame) {
                HeldFate::Wait
            } else if ends_with_a_frame(&self.buf[..total], judge) {
                HeldFate::Refuted
            } else {
                HeldFate::Confirmed
            };
        }
        match candidate(rest, judge) {
            Candidate::Implausible => HeldFate::Refuted,
            // A frame does not stop half way: one that pauses is the tail of a frame
            // that gained bytes or the start of one that lost some.
            Candidate::Incomplete if quiet_now || self.pause_within(total, self.buf.len()) => {
                HeldFate::Refuted
            }
            Candidate::Incomplete => HeldFate::Wait,
            Candidate::Complete(n) => {
                let follower = FrameRef::new(&rest[..n]);
                // The same id with other bytes: one of the two is not what it claims
                // (a duplicate reply is the same bytes). Not id 0: every notification
                // of the device carries it (docs/protocol.md), and no request's id is
                // 0 or has a low byte of 0, so no reply that lost bytes reads as one.
                let contradicts =
                    follower.tid() == frame.tid() && frame.tid() != 0 && follower != frame;
                if self.pause_within(total, total + n)
                    || contradicts
                    || !judge.accept(follower)
                    || ends_with_a_frame(&self.buf[..total], judge)
                {
                    HeldFate::Refuted
                } else {
                    HeldFate::Confirmed
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
