//! Properties of the resynchronising decoder (design.md §2): any chunking of a valid
//! stream decodes to the same frames; garbage that cannot start a header costs no
//! frame; arbitrary bytes never panic and only ever yield well-formed frames.

use mbgate::frame::mbap::FrameRef;
use mbgate::frame::pdu;
use mbgate::frame::{Adu, Confirmed, Judge, ReplyJudge, Resync};
use proptest::prelude::*;

/// A well-formed reply: FC 03 with N registers, an FC 16 echo, or an exception.
fn reply() -> impl Strategy<Value = Adu> {
    let regs = (
        any::<u16>(),
        any::<u8>(),
        prop::collection::vec(any::<u16>(), 1..=125),
    )
        .prop_map(|(tid, unit, values)| {
            let mut p = vec![0x03, (values.len() * 2) as u8];
            for v in values {
                p.extend_from_slice(&v.to_be_bytes());
            }
            Adu::build(tid, unit, &p)
        });
    let echo =
        (any::<u16>(), any::<u8>(), any::<u16>(), 1..=123u16).prop_map(|(tid, unit, addr, qty)| {
            let mut p = vec![0x10];
            p.extend_from_slice(&addr.to_be_bytes());
            p.extend_from_slice(&qty.to_be_bytes());
            Adu::build(tid, unit, &p)
        });
    let exc = (
        any::<u16>(),
        any::<u8>(),
        prop::sample::select(vec![1u8, 2, 3, 4, 0x10]),
        1..=4u8,
    )
        .prop_map(|(tid, unit, f, code)| Adu::exception(tid, unit, f, code));
    prop_oneof![regs, echo, exc]
}

/// [`ReplyJudge`]'s shape check, with every frame held until what follows confirms it
/// or the line goes quiet (issue 4).
const STRICT: Confirmed<ReplyJudge> = Confirmed(ReplyJudge);

/// What the relay knows (design.md §1 step 4): the requests on the line, each with its
/// own transaction id, no two sharing a low byte (as the relay allocates them). A
/// frame is a reply only if it answers one of them: same id, unit, function code and
/// shape (here: length). Frames are held for confirmation.
struct Outstanding(Vec<Adu>);

impl Judge for Outstanding {
    fn plausible_function(&self, code: u8) -> bool {
        ReplyJudge.plausible_function(code)
    }
    fn accept(&self, frame: FrameRef<'_>) -> bool {
        self.0.iter().any(|f| {
            f.tid() == frame.tid()
                && f.unit() == frame.unit()
                && f.function() == frame.function()
                && f.as_bytes().len() == frame.as_bytes().len()
        })
    }
    fn confirm(&self, _: FrameRef<'_>) -> bool {
        true
    }
}

/// Replies with transaction ids whose low bytes all differ.
fn replies_to_outstanding() -> impl Strategy<Value = Vec<Adu>> {
    prop::collection::vec(reply(), 1..12).prop_map(|frames| {
        frames
            .into_iter()
            .enumerate()
            .map(|(i, f)| f.with_tid((f.tid() & 0xFF00) | i as u16))
            .collect()
    })
}

fn decode_chunked(stream: &[u8], cuts: &[usize]) -> Vec<Adu> {
    decode_chunked_with(&ReplyJudge, stream, cuts)
}

fn decode_chunked_with(judge: &impl Judge, stream: &[u8], cuts: &[usize]) -> Vec<Adu> {
    let mut cuts: Vec<usize> = cuts.iter().map(|c| c % (stream.len() + 1)).collect();
    cuts.sort_unstable();
    let mut d = Resync::new();
    let mut out = Vec::new();
    let mut at = 0;
    for c in cuts.into_iter().chain([stream.len()]) {
        d.push(&stream[at..c]);
        at = c;
        while let Some(f) = d.next_frame(judge, false) {
            out.push(f);
        }
    }
    while let Some(f) = d.next_frame(judge, true) {
        out.push(f);
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn any_chunking_gives_the_same_frames(
        frames in prop::collection::vec(reply(), 1..12),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let stream: Vec<u8> = frames.iter().flat_map(|f| f.as_bytes().to_vec()).collect();
        prop_assert_eq!(decode_chunked(&stream, &cuts), frames.clone());
        prop_assert_eq!(decode_chunked_with(&STRICT, &stream, &cuts), frames);
    }

    /// Issue 4: bytes lost anywhere, at any chunking, never make a frame that was not
    /// sent, when frames are held for confirmation.
    #[test]
    fn loss_alone_never_yields_a_frame_that_was_not_sent(
        frames in replies_to_outstanding(),
        lost in prop::collection::vec(any::<usize>(), 1..6),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let mut stream: Vec<u8> = frames.iter().flat_map(|f| f.as_bytes().to_vec()).collect();
        let mut lost: Vec<usize> = lost.iter().map(|l| l % stream.len()).collect();
        lost.sort_unstable();
        lost.dedup();
        for l in lost.into_iter().rev() {
            stream.remove(l);
        }
        for f in decode_chunked_with(&Outstanding(frames.clone()), &stream, &cuts) {
            prop_assert!(frames.contains(&f), "not sent: {:?}", f);
        }
    }

    #[test]
    fn garbage_that_cannot_start_a_header_costs_no_frame(
        frames in prop::collection::vec(reply(), 1..8),
        garbage in prop::collection::vec(prop::collection::vec(0x80u8.., 0..40), 8),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        // Bytes >= 0x80 can never be a protocol id or length byte.
        let mut stream = Vec::new();
        for (f, g) in frames.iter().zip(garbage.iter().cycle()) {
            stream.extend(g);
            stream.extend(f.as_bytes());
        }
        stream.extend(&garbage[7]);
        prop_assert_eq!(decode_chunked(&stream, &cuts), frames);
    }

    #[test]
    fn arbitrary_bytes_only_yield_well_formed_frames(
        bytes in prop::collection::vec(any::<u8>(), 0..2000),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        for f in decode_chunked(&bytes, &cuts) {
            prop_assert!(pdu::reply_well_formed(f.pdu()));
            prop_assert_eq!(&f.as_bytes()[2..4], &[0, 0]);
        }
    }
}
