//! Properties of the resynchronising decoder (docs/design.md §2): any chunking of a valid
//! stream decodes to the same frames; garbage that cannot start a header costs no
//! frame; arbitrary bytes never panic and only ever yield well-formed frames; and on a
//! lossy line (`mbgate::frame::lossy`), a reply that was not sent needs a whole
//! frame's worth of bytes lost around it (docs/reliability.md, "The guarantee").
//!
//! 512 cases each by default; `PROPTEST_CASES=1000000 cargo test --release --test
//! decoder_props` for the long run.

use mbgate::frame::lossy::{self, Run, Talk};
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
/// or the line goes quiet (docs/reliability.md).
const STRICT: Confirmed<ReplyJudge> = Confirmed(ReplyJudge);

/// Register values: anything, or values that look like pieces of MBAP headers (zeros,
/// lengths, unit and function code pairs, byte counts), which make shifted and
/// spelled headers plausible.
fn register_values(
    header_like: bool,
    n: std::ops::RangeInclusive<usize>,
) -> BoxedStrategy<Vec<u16>> {
    if header_like {
        let piece = prop_oneof![
            4 => Just(0x0000u16),
            1 => prop::sample::select(&lossy::HEADER_LIKE[1..]),
            1 => any::<u16>(),
        ];
        prop::collection::vec(piece, n).boxed()
    } else {
        prop::collection::vec(any::<u16>(), n).boxed()
    }
}

/// A reply for the line model: FC 03 with N registers (mostly few, so a run of lost
/// bytes can cover whole frames), an FC 16 echo, an FC 06 echo, or an exception.
fn line_reply(header_like: bool) -> BoxedStrategy<Adu> {
    let unit = prop::sample::select(vec![1u8, 1, 1, 2, 0x11]);
    let regs = (
        unit.clone(),
        prop_oneof![4 => register_values(header_like, 1..=12), 1 => register_values(header_like, 13..=125)],
    )
        .prop_map(|(unit, values)| {
            let mut p = vec![0x03, (values.len() * 2) as u8];
            for v in values {
                p.extend_from_slice(&v.to_be_bytes());
            }
            Adu::build(0, unit, &p)
        });
    let echo = (
        unit.clone(),
        register_values(header_like, 2..=2),
        0x10u8..=0x10,
    )
        .prop_map(|(unit, v, f)| {
            let mut p = vec![f];
            p.extend_from_slice(&v[0].to_be_bytes());
            p.extend_from_slice(&(v[1] % 123 + 1).to_be_bytes());
            Adu::build(0, unit, &p)
        });
    let single = (unit.clone(), register_values(header_like, 2..=2)).prop_map(|(unit, v)| {
        let mut p = vec![0x06];
        p.extend_from_slice(&v[0].to_be_bytes());
        p.extend_from_slice(&v[1].to_be_bytes());
        Adu::build(0, unit, &p)
    });
    let exc = (unit, prop::sample::select(vec![1u8, 3, 6, 0x10]), 1..=4u8)
        .prop_map(|(unit, f, code)| Adu::exception(0, unit, f, code));
    prop_oneof![4 => regs, 2 => echo, 1 => single, 2 => exc].boxed()
}

/// A notification as the CIE-M10 sends it (docs/protocol.md §3): id 0, FC 03, one register.
fn notification(header_like: bool) -> BoxedStrategy<Adu> {
    register_values(header_like, 1..=1)
        .prop_map(|v| Adu::build(0, 1, &[0x03, 0x02, (v[0] >> 8) as u8, v[0] as u8]))
        .boxed()
}

fn talk(header_like: bool) -> impl Strategy<Value = Talk> {
    prop::collection::vec(
        (
            any::<u8>(),
            line_reply(header_like),
            prop::option::weighted(0.25, notification(header_like)),
        ),
        1..10,
    )
    .prop_map(|items| {
        let mut frames = Vec::new();
        for (i, (high, reply, notification)) in items.into_iter().enumerate() {
            frames.push(reply.with_tid(u16::from_be_bytes([high, i as u8 + 1])));
            frames.extend(notification);
        }
        Talk { frames }
    })
}

/// Runs of lost bytes: one byte, a few, or up to 32 (a USB adapter that overruns
/// drops whole chunks); anywhere, or aligned to frame boundaries, or whole frames.
fn run_len() -> impl Strategy<Value = usize> {
    prop_oneof![6 => Just(1usize), 3 => 2..=8usize, 2 => 9..=32usize]
}

fn runs(max: usize) -> impl Strategy<Value = Vec<Run>> {
    let run = prop_oneof![
        3 => (any::<usize>(), run_len()).prop_map(|(at, len)| Run::At { at, len }),
        1 => (any::<usize>(), run_len()).prop_map(|(frame, len)| Run::FromBoundary { frame, len }),
        1 => (any::<usize>(), run_len()).prop_map(|(frame, len)| Run::ToBoundary { frame, len }),
        1 => any::<usize>().prop_map(|frame| Run::Frame { frame }),
    ];
    prop::collection::vec(run, 0..=max)
}

/// Every reply yielded was sent, or a whole frame's worth of bytes was lost around it
/// (`mbgate::frame::lossy`).
fn check_loss(
    talk: &Talk,
    runs: &[Run],
    pauses: &[usize],
    cuts: &[usize],
    pause_confirms: bool,
) -> Result<(), TestCaseError> {
    let found = lossy::unexplained(talk, runs, pauses, cuts, pause_confirms);
    prop_assert!(
        found.is_none(),
        "not sent, too few bytes lost around it: {:?}",
        found
    );
    Ok(())
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

    /// Bytes lost anywhere, at any chunking, never make a frame that was not sent
    /// unless a whole frame's worth (9 bytes, the shortest frame) was lost between
    /// its first byte and the byte after it: runs of 1 to 32 lost bytes, anywhere or
    /// aligned to frame boundaries or one whole frame, notifications among the
    /// replies, the line pausing between frames (a notification after a quiet line),
    /// one request's reply confirmed by a pause.
    #[test]
    fn loss_alone_never_yields_a_frame_that_was_not_sent(
        talk in talk(false),
        runs in runs(4),
        pauses in prop::collection::vec(any::<usize>(), 0..4),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let bounds = talk.bounds();
        let pauses: Vec<usize> = pauses.iter().map(|p| bounds[p % bounds.len()]).collect();
        check_loss(&talk, &runs, &pauses, &cuts, true)?;
    }

    /// The same with pauses inside frames too (a device that stops half way, a USB
    /// adapter slower than `silence_floor_ms`), on a line with other replies due,
    /// where only what follows a frame, or the frame gap, confirms it.
    #[test]
    fn loss_and_pauses_inside_frames_never_yield_a_frame_that_was_not_sent(
        talk in talk(false),
        runs in runs(4),
        pauses in prop::collection::vec(any::<usize>(), 0..6),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let len = talk.bytes().len();
        let pauses: Vec<usize> = pauses.iter().map(|p| p % len).collect();
        check_loss(&talk, &runs, &pauses, &cuts, false)?;
    }

    /// The same with register values that look like pieces of MBAP headers.
    #[test]
    fn loss_with_header_like_values(
        talk in talk(true),
        runs in runs(4),
        pauses in prop::collection::vec(any::<usize>(), 0..4),
        cuts in prop::collection::vec(any::<usize>(), 0..20),
    ) {
        let bounds = talk.bounds();
        let pauses: Vec<usize> = pauses.iter().map(|p| bounds[p % bounds.len()]).collect();
        check_loss(&talk, &runs, &pauses, &cuts, true)?;
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
