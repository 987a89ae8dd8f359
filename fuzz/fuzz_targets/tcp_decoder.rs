//! The strict MBAP decoder of the TCP side (docs/design.md §1 step 1) on arbitrary bytes at
//! arbitrary chunking: it never panics, never asks for more than one frame's bytes,
//! yields only frames within the limits, and chunking changes neither the frames nor
//! the error that ends the connection.
#![no_main]

use bytes::BytesMut;
use libfuzzer_sys::fuzz_target;
use mbgate::frame::mbap::{decode_strict, MAX_ADU};
use mbgate::frame::Adu;

/// The frames, and the error if one ended the stream.
fn decode(data: &[u8], cuts: &[u8]) -> (Vec<Adu>, Option<String>) {
    let mut buf = BytesMut::new();
    let mut out = Vec::new();
    let mut at = 0;
    let ends = cuts
        .iter()
        .map(|&c| usize::from(c))
        .chain(std::iter::once(data.len()));
    for step in ends {
        let end = (at + step).min(data.len());
        buf.extend_from_slice(&data[at..end]);
        at = end;
        loop {
            match decode_strict(&mut buf) {
                Ok(Some(f)) => {
                    let b = f.as_bytes();
                    assert!(b.len() <= MAX_ADU);
                    assert_eq!(&b[2..4], &[0, 0]);
                    assert_eq!(usize::from(u16::from_be_bytes([b[4], b[5]])) + 6, b.len());
                    out.push(f);
                }
                Ok(None) => {
                    assert!(buf.len() < MAX_ADU, "never waits for more than a frame");
                    break;
                }
                Err(e) => return (out, Some(e.to_string())),
            }
        }
        if at == data.len() {
            break;
        }
    }
    (out, None)
}

fuzz_target!(|input: (Vec<u8>, Vec<u8>)| {
    let (data, cuts) = input;
    let chunked = decode(&data, &cuts);
    let whole = decode(&data, &[]);
    assert_eq!(chunked, whole, "chunking changes nothing");
});
