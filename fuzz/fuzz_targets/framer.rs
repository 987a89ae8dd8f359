//! The one framer (`mbgate::frame::framer`) for MBAP, RTU and ASCII on arbitrary bytes
//! at arbitrary chunking, expecting requests or the reply to a request: it never
//! panics, every byte pushed is in a frame yielded, counted as dropped, or still
//! held, and every frame yielded is encoded back to as many bytes and framed again the
//! same.
#![no_main]

use libfuzzer_sys::fuzz_target;
use mbgate::frame::framer::{frame_in_cuts, Framed, Framer, ReplyFor};
use mbgate::frame::serial::Codec;
use mbgate::frame::RequestJudge;

fn framer(kind: u8) -> Framer {
    match kind % 3 {
        0 => Framer::mbap(),
        1 => Framer::serial(Codec::Rtu),
        _ => Framer::serial(Codec::Ascii),
    }
}

fuzz_target!(|input: (u8, Vec<u8>, Vec<u8>, Vec<u8>)| {
    let (kind, request, data, cuts) = input;
    let mut f = framer(kind);
    let frames = if kind % 2 == 0 {
        frame_in_cuts(&mut f, &RequestJudge::default(), &data, &cuts)
    } else {
        frame_in_cuts(&mut f, &ReplyFor(&request), &data, &cuts)
    };
    let yielded: u64 = frames
        .iter()
        .map(|a| f.encoded_len(a.pdu().len()) as u64)
        .sum();
    assert_eq!(
        yielded + f.dropped(),
        f.consumed(),
        "taken: yielded or dropped"
    );
    assert_eq!(
        f.consumed() + f.buffered() as u64,
        data.len() as u64,
        "every byte taken or held"
    );
    for adu in frames {
        let wire = f.encode(&adu);
        assert_eq!(wire.len(), f.encoded_len(adu.pdu().len()));
        let mut again = framer(kind);
        again.push(&wire);
        let got = if kind % 2 == 0 {
            again.next_frame(&RequestJudge::default(), true)
        } else {
            again.next_frame(&ReplyFor(&request), true)
        };
        assert_eq!(got, Some(Framed::Frame(adu)), "framed again the same");
    }
});
