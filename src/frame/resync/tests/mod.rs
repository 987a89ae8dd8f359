//! The decoder's tests: clean streams in any chunking, garbage, lost bytes, the
//! pauses it keeps; and (`confirm.rs`) the confirmation rules, scripted and as
//! properties.

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

/// An FC 03 reply for three registers holding 23413, 23402, 23403.
const A: &str = "00 07 00 00 00 09 01 03 06 5B 75 5B 6A 5B 6B";
/// A change notification (docs/protocol.md §3), transaction id 0.
const NOTIFICATION: &str = "00 00 00 00 00 05 01 03 02 00 0F";
/// A 9-byte exception reply and an FC 16 echo.
const C: &str = "00 0C 00 00 00 03 01 83 02";
const B: &str = "00 0B 00 00 00 06 01 10 00 08 00 01";

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

mod confirm;
