//! The resynchronising serial decoder (docs/design.md §2, docs/reliability.md) on arbitrary
//! bytes at arbitrary chunking, with and without confirmation, with the line pausing
//! anywhere: it never panics, every frame it yields is length-consistent and accepted
//! by its judge, everything it is fed is either yielded or counted as dropped, quiet
//! empties it, and chunking never changes what it yields. Then on a lossy line built
//! from the input (`mbgate::frame::lossy`: replies and notifications, register values
//! that look like MBAP headers, runs of up to 32 lost bytes anywhere or aligned to
//! frame boundaries, pauses between and inside frames): a reply that was not sent is
//! never yielded unless a whole frame's worth of bytes was lost around it, or its id
//! was register values (docs/reliability.md, "The guarantee", conditions 1 and 3).
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::frame::lossy::{self, Outstanding, Received, Run, Talk};
use mbgate::frame::{pdu, Adu, Confirmed, Judge, ReplyJudge, Resync};

const STRICT: Confirmed<ReplyJudge> = Confirmed(ReplyJudge);

/// Feeds `data` in chunks cut where `cuts` says, then declares the line quiet.
fn decode(judge: &impl Judge, data: &[u8], cuts: &[u8]) -> (Vec<Adu>, u64) {
    let mut d = Resync::new();
    let mut out = Vec::new();
    let mut at = 0;
    for &c in cuts {
        let end = (at + usize::from(c)).min(data.len());
        d.push(&data[at..end]);
        at = end;
        while let Some(f) = d.next_frame(judge, false) {
            out.push(f);
        }
    }
    d.push(&data[at..]);
    while let Some(f) = d.next_frame(judge, false) {
        out.push(f);
    }
    while let Some(f) = d.next_frame(judge, true) {
        out.push(f);
    }
    assert_eq!(d.buffered(), 0, "quiet leaves nothing behind");
    let yielded: usize = out.iter().map(|f| f.as_bytes().len()).sum();
    assert_eq!(
        yielded as u64 + d.stats().dropped_bytes,
        data.len() as u64,
        "every byte is yielded or counted as dropped"
    );
    (out, d.stats().dropped_bytes)
}

/// Bytes of the input read one at a time, zeros once it runs out.
struct Cursor<'a>(std::slice::Iter<'a, u8>);

impl Cursor<'_> {
    fn byte(&mut self) -> u8 {
        self.0.next().copied().unwrap_or(0)
    }
    fn word(&mut self) -> u16 {
        u16::from_be_bytes([self.byte(), self.byte()])
    }
    fn value(&mut self, header_like: bool) -> u16 {
        if header_like && self.byte() % 4 != 0 {
            lossy::HEADER_LIKE[usize::from(self.byte()) % lossy::HEADER_LIKE.len()]
        } else {
            self.word()
        }
    }
}

/// A lossy line from the input: up to ten frames, up to four runs, up to six pauses.
fn line(input: &[u8]) -> (Talk, Vec<Run>, Vec<usize>, bool) {
    let mut c = Cursor(input.iter());
    let header_like = c.byte() % 2 == 1;
    let pause_confirms = c.byte() % 2 == 1;
    let mut frames = Vec::new();
    let mut low = 0u8;
    for _ in 0..1 + c.byte() % 10 {
        let unit = [1, 1, 2, 0x11][usize::from(c.byte() % 4)];
        let pdu = match c.byte() % 5 {
            0 | 1 => {
                let n = 1 + usize::from(c.byte() % 12);
                let mut p = vec![0x03, (2 * n) as u8];
                for _ in 0..n {
                    p.extend(c.value(header_like).to_be_bytes());
                }
                p
            }
            2 => {
                let mut p = vec![[0x06, 0x10][usize::from(c.byte() % 2)]];
                p.extend(c.value(header_like).to_be_bytes());
                p.extend(c.value(header_like).to_be_bytes());
                p
            }
            3 => vec![
                [0x81, 0x83, 0x90][usize::from(c.byte() % 3)],
                1 + c.byte() % 4,
            ],
            _ => {
                let mut p = vec![0x03, 0x02];
                p.extend(c.value(header_like).to_be_bytes());
                frames.push(Adu::build(0, 1, &p));
                continue;
            }
        };
        low += 1;
        frames.push(Adu::build(u16::from_be_bytes([c.byte(), low]), unit, &pdu));
    }
    if frames.is_empty() {
        frames.push(Adu::exception(1, 1, 3, 2));
    }
    let talk = Talk { frames };
    let runs = (0..c.byte() % 5)
        .map(|_| {
            let len = 1 + usize::from(c.byte() % 32);
            let at = usize::from(c.word());
            match c.byte() % 4 {
                0 => Run::At { at, len },
                1 => Run::FromBoundary { frame: at, len },
                2 => Run::ToBoundary { frame: at, len },
                _ => Run::Frame { frame: at },
            }
        })
        .collect();
    let bounds = talk.bounds();
    let pauses = (0..c.byte() % 7)
        .map(|_| {
            let at = usize::from(c.word());
            // A pause confirms a lone reply only between frames (docs/reliability.md).
            if pause_confirms {
                bounds[at % bounds.len()]
            } else {
                at % (bounds[bounds.len() - 1] + 1)
            }
        })
        .collect();
    (talk, runs, pauses, pause_confirms)
}

fuzz_target!(|input: (Vec<u8>, Vec<u8>, Vec<u8>, Vec<u8>)| {
    let (data, cuts, pauses, spec) = input;
    let (lenient, _) = decode(&ReplyJudge, &data, &cuts);
    for f in &lenient {
        let b = f.as_bytes();
        assert_eq!(&b[2..4], &[0, 0]);
        assert_eq!(usize::from(u16::from_be_bytes([b[4], b[5]])) + 6, b.len());
        assert!(pdu::reply_well_formed(f.pdu()));
    }
    assert_eq!(
        lenient,
        decode(&ReplyJudge, &data, &[]).0,
        "chunking changes nothing"
    );
    let (strict, _) = decode(&STRICT, &data, &cuts);
    assert_eq!(
        strict,
        decode(&STRICT, &data, &[]).0,
        "chunking changes nothing"
    );
    for f in &strict {
        assert!(pdu::reply_well_formed(f.pdu()));
    }

    // The same bytes with the line pausing: lossy::decode checks that every byte is
    // yielded or dropped and quiet empties the decoder; chunking still changes nothing.
    let mut received = Received {
        bytes: data.clone(),
        sent_at: (0..data.len()).collect(),
        lost: vec![false; data.len()],
        pauses: pauses
            .iter()
            .map(|&p| usize::from(p) % (data.len() + 1))
            .collect(),
    };
    received.pauses.sort_unstable();
    received.pauses.dedup();
    let cuts: Vec<usize> = cuts.iter().map(|&c| usize::from(c)).collect();
    for pause_confirms in [true, false] {
        let judge = Outstanding {
            replies: Vec::new(),
            pause_confirms,
        };
        assert_eq!(
            lossy::decode(&judge, &received, &cuts),
            lossy::decode(&judge, &received, &[]),
            "chunking changes nothing"
        );
    }
    assert_eq!(
        lossy::decode(&STRICT, &received, &cuts),
        lossy::decode(&STRICT, &received, &[])
    );

    let (talk, runs, pauses, pause_confirms) = line(&spec);
    if let Some((frame, lost)) = lossy::unexplained(&talk, &runs, &pauses, &cuts, pause_confirms) {
        panic!("not sent: {frame:?}, {lost} bytes lost around it; {talk:?} {runs:?} {pauses:?}");
    }
});
