//! A lossy MBAP line on paper, to hold the resynchronising decoder to the guarantee of
//! docs/reliability.md: frames sent (replies to requests on the line, notifications),
//! runs of lost bytes, pauses, any chunking; what the relay knows of them; and the
//! check. The property tests (tests/inprocess/decoder_props.rs) and the fuzz target
//! (fuzz/fuzz_targets/serial_decoder.rs) drive it.
//!
//! The check: every frame the decoder yields with a nonzero transaction id (a reply)
//! was sent, byte for byte, or at least `SHORTEST_FRAME` bytes were lost around it,
//! from where its first byte was sent to where the header of what confirmed it was,
//! or both bytes of its id were sent as register values (docs/reliability.md, "The
//! guarantee", condition 3). Frames with id 0 are not checked: register values can
//! spell one.

use super::function::{Echo, FunctionCode};
use super::mbap::{FrameRef, HEADER_LEN};
use super::resync::{Judge, ReplyJudge, Resync};
use super::{pdu, Adu};

/// The shortest frame a device sends: an exception reply (6 + 3 bytes). A reply can
/// only be completed by a whole frame when at least this many bytes were lost.
pub(crate) const SHORTEST_FRAME: usize = 9;

/// Register values that look like pieces of MBAP headers: zeros (protocol id, length
/// high byte, transaction ids below 256), lengths, unit and function code pairs, byte
/// counts. They make shifted and spelled headers plausible.
pub const HEADER_LIKE: [u16; 13] = [
    0x0000, 0x0003, 0x0005, 0x0006, 0x0009, 0x0103, 0x0110, 0x0183, 0x0106, 0x0203, 0x0002, 0x0100,
    0x0300,
];

/// What the relay knows (docs/design.md §1 step 4): the requests on the line, each with its
/// own transaction id, no two sharing a low byte and none a low byte of 0 (as the
/// relay allocates them). A frame is a reply only if it answers one of them: same id,
/// unit, function code and shape. A well-formed frame with id 0 is a notification.
/// Every frame is held for confirmation; `pause_confirms` says whether a pause
/// confirms one with nothing after it (no other reply due).
pub struct Outstanding {
    /// The replies due, standing for their requests: a frame is accepted when it has
    /// one's id, unit, function code and length.
    pub replies: Vec<Adu>,
    /// A pause confirms a held frame with nothing after it.
    pub pause_confirms: bool,
}

impl Judge for Outstanding {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        ReplyJudge.plausible_function(code)
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        if frame.tid() == 0 {
            return pdu::reply_well_formed(frame.pdu());
        }
        // As `pdu::reply_matches` checks it against the request: the shape a read of
        // this many registers calls for; a write's echo of its address, quantity or
        // value.
        self.replies.iter().any(|f| {
            f.tid() == frame.tid()
                && f.unit() == frame.unit()
                && f.function() == frame.function()
                && f.as_bytes().len() == frame.as_bytes().len()
                && pdu::reply_well_formed(frame.pdu())
                && echoes(f, frame)
        })
    }

    fn confirm(&self, _: FrameRef<'_>) -> bool {
        true
    }

    fn pause_confirms(&self, _: FrameRef<'_>) -> bool {
        self.pause_confirms
    }
}

/// Does `frame` repeat what the reply `sent` repeats of its request (a write's address,
/// quantity or value; the table's [`Echo`])? Both have the same length.
fn echoes(sent: &Adu, frame: FrameRef<'_>) -> bool {
    match sent.function_code().spec().map(|s| s.echo) {
        Some(Echo::Whole) => sent.pdu() == frame.pdu(),
        Some(Echo::Prefix(n)) => sent.pdu().get(..n) == frame.pdu().get(..n),
        _ => true,
    }
}

/// Frames on the line, in order: replies (ids with distinct low bytes, never 0) and
/// notifications (id 0) among them.
#[derive(Debug, Clone)]
pub struct Talk {
    /// The frames, in the order they are sent.
    pub frames: Vec<Adu>,
}

impl Talk {
    pub(crate) fn replies(&self) -> Vec<Adu> {
        self.frames
            .iter()
            .filter(|f| f.tid() != 0)
            .cloned()
            .collect()
    }

    /// Every frame's bytes, back to back: what is sent.
    pub fn bytes(&self) -> Vec<u8> {
        self.frames
            .iter()
            .flat_map(|f| f.as_bytes().to_vec())
            .collect()
    }

    /// Where each frame starts, and the end.
    pub fn bounds(&self) -> Vec<usize> {
        let mut at = 0;
        let mut out = vec![0];
        for f in &self.frames {
            at += f.as_bytes().len();
            out.push(at);
        }
        out
    }
}

/// A run of lost bytes: anywhere, starting or ending at a frame boundary, or one whole
/// frame. Offsets and frame numbers wrap around what was sent.
#[derive(Debug, Clone)]
pub enum Run {
    /// `len` bytes from offset `at` of what was sent.
    At {
        /// The offset of the first byte lost.
        at: usize,
        /// How many bytes are lost.
        len: usize,
    },
    /// The first `len` bytes of frame `frame` on.
    FromBoundary {
        /// The frame whose start the run begins at.
        frame: usize,
        /// How many bytes are lost.
        len: usize,
    },
    /// The last `len` bytes before the end of frame `frame`.
    ToBoundary {
        /// The frame whose end the run stops at.
        frame: usize,
        /// How many bytes are lost.
        len: usize,
    },
    /// All of frame `frame`.
    Frame {
        /// The frame lost.
        frame: usize,
    },
}

/// What the line delivers: the bytes not lost, each with where it was sent, and the
/// pauses (before the received byte at each offset).
pub struct Received {
    /// The bytes that arrived, in order.
    pub bytes: Vec<u8>,
    /// For each byte of `bytes`, its offset in what was sent.
    pub sent_at: Vec<usize>,
    /// For each byte sent, whether it was lost.
    pub lost: Vec<bool>,
    /// Offsets in `bytes` before which the line paused, ascending, no repeats.
    pub pauses: Vec<usize>,
}

/// Loses the runs of `talk` and marks its pauses (offsets in what was sent).
pub(crate) fn deliver(talk: &Talk, runs: &[Run], pauses_at: &[usize]) -> Received {
    let sent = talk.bytes();
    let bounds = talk.bounds();
    let frames = talk.frames.len();
    let mut lost = vec![false; sent.len()];
    for r in runs {
        let (from, len) = match *r {
            Run::At { at, len } => (at % sent.len().max(1), len),
            Run::FromBoundary { frame, len } => (bounds[frame % frames], len),
            Run::ToBoundary { frame, len } => {
                let end = bounds[frame % frames + 1];
                (end.saturating_sub(len), len)
            }
            Run::Frame { frame } => {
                let f = frame % frames;
                (bounds[f], bounds[f + 1] - bounds[f])
            }
        };
        for l in lost.iter_mut().skip(from).take(len) {
            *l = true;
        }
    }
    let mut r = Received {
        bytes: Vec::new(),
        sent_at: Vec::new(),
        lost,
        pauses: Vec::new(),
    };
    for (i, &b) in sent.iter().enumerate() {
        if !r.lost[i] {
            r.bytes.push(b);
            r.sent_at.push(i);
        }
    }
    for &p in pauses_at {
        // Before the first byte received that was sent at or after it.
        r.pauses.push(r.sent_at.partition_point(|&s| s < p));
    }
    r.pauses.sort_unstable();
    r.pauses.dedup();
    r
}

/// Feeds what was received in chunks cut at `cuts` (offsets, wrapped), pausing where
/// the line paused, then declares the line quiet for the frame gap; every frame
/// yielded, with where it started. Panics if quiet leaves bytes behind or a byte is
/// neither yielded nor counted dropped.
pub fn decode(judge: &impl Judge, r: &Received, cuts: &[usize]) -> Vec<(usize, Adu)> {
    let n = r.bytes.len();
    let mut stops: Vec<(usize, bool)> = cuts.iter().map(|c| (c % (n + 1), false)).collect();
    stops.extend(r.pauses.iter().map(|&p| (p, true)));
    stops.sort_unstable();
    let mut d = Resync::new();
    let mut out = Vec::new();
    let take = |d: &mut Resync, quiet: bool, out: &mut Vec<(usize, Adu)>| {
        while let Some(f) = d.next_frame(judge, quiet) {
            let start = d.consumed() as usize - f.as_bytes().len();
            out.push((start, f));
        }
    };
    let mut at = 0;
    for (stop, pause) in stops {
        d.push(&r.bytes[at..stop]);
        at = stop;
        if pause {
            d.pause();
        }
        take(&mut d, false, &mut out);
    }
    d.push(&r.bytes[at..]);
    take(&mut d, false, &mut out);
    d.pause();
    take(&mut d, true, &mut out);
    assert_eq!(d.buffered(), 0, "quiet leaves nothing behind");
    let yielded: usize = out.iter().map(|(_, f)| f.as_bytes().len()).sum();
    assert_eq!(
        yielded as u64 + d.stats().dropped_bytes,
        n as u64,
        "every byte is yielded or counted as dropped"
    );
    out
}

/// The bytes lost from where a yielded frame's first byte was sent up to where the
/// header of what confirmed it (the first bytes received after it) was sent, or the
/// end.
pub(crate) fn lost_around(r: &Received, start: usize, len: usize) -> usize {
    let from = r.sent_at[start];
    let to = r
        .sent_at
        .get(start + len + SHORTEST_FRAME - 1)
        .copied()
        .unwrap_or(r.lost.len());
    r.lost[from..to].iter().filter(|&&l| l).count()
}

/// Were both bytes of the id of the frame yielded at `start` (in what was received)
/// sent as values, past some frame's function code? A frame that lost its whole id
/// takes the two bytes before it as one: register values that equal an id in flight
/// then answer its request. That is outside the guarantee (docs/reliability.md, "The
/// guarantee", condition 3: the relay draws its ids so that values match one only by
/// chance), and the line model draws ids and values freely enough to make it happen.
fn id_sent_as_values(bounds: &[usize], r: &Received, start: usize) -> bool {
    r.sent_at[start..start + 2].iter().all(|&at| {
        let frame = bounds.partition_point(|&b| b <= at) - 1;
        at - bounds[frame] > HEADER_LEN
    })
}

/// Runs the line and returns the first reply yielded that was not sent with fewer
/// than `SHORTEST_FRAME` bytes lost around it (nor with its id sent as register
/// values: condition 3), and how many were.
pub fn unexplained(
    talk: &Talk,
    runs: &[Run],
    pauses: &[usize],
    cuts: &[usize],
    pause_confirms: bool,
) -> Option<(Adu, usize)> {
    let r = deliver(talk, runs, pauses);
    let judge = Outstanding {
        replies: talk.replies(),
        pause_confirms,
    };
    let bounds = talk.bounds();
    decode(&judge, &r, cuts)
        .into_iter()
        .filter(|(_, f)| f.tid() != 0 && !talk.frames.contains(f))
        .filter(|&(start, _)| !id_sent_as_values(&bounds, &r, start))
        .map(|(start, f)| {
            let lost = lost_around(&r, start, f.as_bytes().len());
            (f, lost)
        })
        .find(|&(_, lost)| lost < SHORTEST_FRAME)
}
