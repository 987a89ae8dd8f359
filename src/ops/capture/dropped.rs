//! The bytes a framer dropped, for the capture (docs/capture.md "Dropped bytes"). A
//! framer only counts what it drops; the [`Tape`] keeps a copy of what was pushed into
//! it, while a capture runs, so that a line can say which bytes were dropped and why.
//! Every byte a framer takes from its front is in a frame it yielded or dropped
//! (`Framer::consumed`), so the bytes taken that were not in a frame are the drops.
//!
//! Pure: offsets in, bytes out. Off (no capture), it keeps nothing and costs a counter.

use super::packet::Reason;
use std::collections::VecDeque;
use tokio::time::Instant;

/// Bytes a line dropped, with why, for the capture.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Dropped {
    /// When the bytes were read, if known; else when they were dropped.
    pub(crate) at: Option<Instant>,
    pub(crate) reason: Reason,
    pub(crate) bytes: Vec<u8>,
    /// They make a whole frame of the line's framing (a stale reply, an echo, an RTU
    /// frame whose CRC failed): shown decoded.
    pub(crate) whole: bool,
    /// What they were, for the packet's comment.
    pub(crate) detail: &'static str,
}

/// A copy of everything pushed into a framer since the capture was turned on, less
/// what has been accounted for.
#[derive(Debug, Default)]
pub(crate) struct Tape {
    on: bool,
    /// Bytes not yet accounted for, from offset `start` of everything pushed.
    bytes: VecDeque<u8>,
    start: u64,
    /// Bytes pushed into the framer so far (on or off).
    pushed: u64,
    /// Drops found, not yet taken.
    found: Vec<Dropped>,
}

impl Tape {
    /// Turns the tape on or off. Turned on, it begins with the next byte pushed:
    /// bytes already in the framer are not on it (a drop among them is cut to what
    /// is).
    pub(crate) fn set(&mut self, on: bool) {
        if on != self.on {
            self.bytes.clear();
            self.start = self.pushed;
            self.on = on;
        }
    }

    /// Bytes pushed into the framer.
    pub(crate) fn push(&mut self, bytes: &[u8]) {
        self.pushed += bytes.len() as u64;
        if self.on {
            self.bytes.extend(bytes);
        } else {
            self.start = self.pushed;
        }
    }

    /// The bytes from what is accounted for up to offset `to`, taken off the tape:
    /// collected where they were dropped, let go where a frame took them.
    fn drain_to(&mut self, to: u64) -> std::collections::vec_deque::Drain<'_, u8> {
        if to <= self.start {
            return self.bytes.drain(..0);
        }
        let n = usize::try_from(to - self.start)
            .unwrap_or(usize::MAX)
            .min(self.bytes.len());
        self.start = to;
        self.bytes.drain(..n)
    }

    /// The framer yielded a frame of `len` bytes, ending at offset `end` (its
    /// `consumed()` now): bytes before it since the last account were dropped for
    /// `reason`.
    pub(crate) fn frame(&mut self, end: u64, len: usize, at: Option<Instant>, reason: Reason) {
        if !self.on {
            return;
        }
        let begin = end.saturating_sub(len as u64);
        self.dropped_to(begin, at, reason, "bytes that start no frame");
        self.drain_to(end);
    }

    /// The framer was cleared (the port opened or lost): everything up to `to` not
    /// yet accounted for was stale.
    pub(crate) fn stale_to(&mut self, to: u64) {
        self.dropped_to(
            to,
            None,
            Reason::Stale,
            "bytes held when the port was opened or lost",
        );
    }

    /// Everything up to offset `to` (the framer's `consumed()` now) not yet accounted
    /// for was dropped for `reason`.
    pub(crate) fn dropped_to(
        &mut self,
        to: u64,
        at: Option<Instant>,
        reason: Reason,
        detail: &'static str,
    ) {
        if !self.on {
            return;
        }
        let bytes: Vec<u8> = self.drain_to(to).collect();
        if !bytes.is_empty() {
            self.found.push(Dropped {
                at,
                reason,
                bytes,
                whole: false,
                detail,
            });
        }
    }

    /// The framer dropped a whole frame of `len` bytes ending at `end` (a frame whose
    /// check failed): bytes before it were dropped for `before`, the frame for
    /// `reason`.
    pub(crate) fn dropped_frame(
        &mut self,
        end: u64,
        len: usize,
        at: Option<Instant>,
        (before, reason): (Reason, Reason),
        detail: &'static str,
    ) {
        if !self.on {
            return;
        }
        self.dropped_to(
            end.saturating_sub(len as u64),
            at,
            before,
            "bytes that start no frame",
        );
        let bytes: Vec<u8> = self.drain_to(end).collect();
        if !bytes.is_empty() {
            self.found.push(Dropped {
                at,
                reason,
                whole: bytes.len() == len,
                bytes,
                detail,
            });
        }
    }

    /// Bytes dropped before they reached the framer (not on the tape): kept when the
    /// tape is on.
    pub(crate) fn dropped_aside(&mut self, d: impl FnOnce() -> Dropped) {
        if self.on {
            self.found.push(d());
        }
    }

    /// A whole frame of the line's framing dropped after the framer yielded it (too
    /// early, an echo, a reply that fits no request): kept when the tape is on.
    pub(crate) fn whole_frame(
        &mut self,
        at: Option<Instant>,
        reason: Reason,
        bytes: &[u8],
        detail: &'static str,
    ) {
        self.dropped_aside(|| Dropped {
            at,
            reason,
            bytes: bytes.to_vec(),
            whole: true,
            detail,
        });
    }

    /// The drops found since the last call.
    pub(crate) fn take(&mut self) -> Vec<Dropped> {
        std::mem::take(&mut self.found)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::framer::{Framed, Framer};
    use crate::frame::serial::Codec;
    use crate::frame::{rtu, Adu, ReplyJudge};

    /// What a framer drops, taken off the tape, is exactly what it counts as dropped,
    /// in the order it came, around the frames it yields.
    #[test]
    fn the_tape_gives_the_bytes_the_framer_counts_as_dropped() {
        let mut f = Framer::mbap();
        let mut t = Tape::default();
        t.set(true);
        let reply = Adu::build(5, 1, &[3, 2, 0, 9]).as_bytes().to_vec();
        let input = [&[0xFF, 0x13][..], &reply, &[0, 6, 0]].concat();
        f.push(&input);
        t.push(&input);
        let Some(Framed::Frame(adu)) = f.next_frame(&ReplyJudge, true) else {
            panic!()
        };
        t.frame(f.consumed(), adu.as_bytes().len(), None, Reason::LostSync);
        assert_eq!(f.next_frame(&ReplyJudge, true), None);
        t.dropped_to(f.consumed(), None, Reason::LostSync, "partial");
        let got = t.take();
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].bytes, [0xFF, 0x13]);
        assert_eq!(got[1].bytes, [0, 6, 0]);
        let total: usize = got.iter().map(|d| d.bytes.len()).sum();
        assert_eq!(total as u64, f.dropped());

        // RTU: noise, then a frame whose CRC failed.
        let mut f = Framer::serial(Codec::Rtu);
        let mut bad = rtu::encode(1, &[3, 2, 0, 9]);
        bad[4] ^= 1;
        f.push(&bad);
        t.push(&bad);
        let Some(Framed::Corrupt(n)) =
            f.next_frame(&crate::frame::framer::ReplyFor(&[3, 0, 0, 0, 1]), false)
        else {
            panic!()
        };
        // A tape turned on fresh for a new framer: its offsets are that framer's.
        let mut t2 = Tape::default();
        t2.set(true);
        t2.push(&bad);
        t2.dropped_frame(
            f.consumed(),
            n,
            None,
            (Reason::LostSync, Reason::Crc),
            "CRC failed",
        );
        let got = t2.take();
        assert_eq!(got.len(), 1);
        assert_eq!(
            (got[0].reason, got[0].whole, &got[0].bytes),
            (Reason::Crc, true, &bad)
        );
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        /// On any bytes in any chunking, for each framing: the drops the tape gives
        /// and the frames the framer yields are every byte it took, in order, none
        /// twice: each dropped byte is in exactly one drop packet.
        #[test]
        fn drops_and_frames_are_every_byte_taken_in_order(
            kind in 0u8..3,
            pieces in proptest::collection::vec(
                (0u8..4, proptest::collection::vec(proptest::num::u8::ANY, 1..12)),
                0..8,
            ),
            cuts in proptest::collection::vec(1u8..40, 0..10),
        ) {
            let data = crate::frame::framer::mixed_stream(&pieces);
            let mut f = crate::frame::framer::framer_of(kind);
            let mut t = Tape::default();
            t.set(true);
            let mut taken = Vec::new();
            let take = |f: &mut Framer, t: &mut Tape, quiet: bool, taken: &mut Vec<u8>| {
                while let Some(framed) = f.next_frame(&ReplyJudge, quiet) {
                    match framed {
                        Framed::Frame(adu) => {
                            let wire = f.encode(&adu);
                            t.frame(f.consumed(), wire.len(), None, Reason::LostSync);
                            for d in t.take() {
                                taken.extend(d.bytes);
                            }
                            taken.extend(wire);
                        }
                        Framed::Corrupt(n) => {
                            t.dropped_frame(f.consumed(), n, None, (Reason::LostSync, Reason::Crc), "x");
                        }
                    }
                }
                t.dropped_to(f.consumed(), None, Reason::LostSync, "x");
                for d in t.take() {
                    taken.extend(d.bytes);
                }
            };
            let mut at = 0;
            for &c in &cuts {
                let end = (at + usize::from(c)).min(data.len());
                f.push(&data[at..end]);
                t.push(&data[at..end]);
                at = end;
                take(&mut f, &mut t, c % 5 == 0, &mut taken);
            }
            f.push(&data[at..]);
            t.push(&data[at..]);
            take(&mut f, &mut t, true, &mut taken);
            f.clear();
            t.dropped_to(f.consumed(), None, Reason::Stale, "x");
            for d in t.take() {
                taken.extend(d.bytes);
            }
            proptest::prop_assert_eq!(taken, data);
        }
    }

    #[test]
    fn off_it_keeps_nothing_and_on_it_starts_with_the_next_byte() {
        let mut t = Tape::default();
        t.push(&[1, 2, 3]);
        t.dropped_to(2, None, Reason::Stale, "x");
        assert!(t.take().is_empty());
        t.set(true);
        t.push(&[4, 5]);
        // Bytes 0..4 were dropped: only what the tape saw (byte 4, offset 3) is given.
        t.dropped_to(4, None, Reason::Stale, "x");
        assert_eq!(t.take()[0].bytes, [4]);
        t.dropped_aside(|| Dropped {
            at: None,
            reason: Reason::Echo,
            bytes: vec![9],
            whole: false,
            detail: "echo",
        });
        assert_eq!(t.take().len(), 1);
        t.set(false);
        t.dropped_aside(|| unreachable!("off: not even built"));
    }
}
