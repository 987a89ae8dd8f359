//! The resynchronising serial decoder (design.md §2, issue 4) on arbitrary bytes at
//! arbitrary chunking, with and without confirmation: it never panics, every frame it
//! yields is length-consistent and accepted by its judge, everything it is fed is
//! either yielded or counted as dropped, quiet empties it, and chunking never changes
//! what it yields.
#![no_main]

use libfuzzer_sys::fuzz_target;
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

fuzz_target!(|input: (Vec<u8>, Vec<u8>)| {
    let (data, cuts) = input;
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
    // Confirmation only ever holds back: it yields a subsequence of what the lenient
    // decoder would, never a frame of its own.
    for f in &strict {
        assert!(pdu::reply_well_formed(f.pdu()));
    }
});
