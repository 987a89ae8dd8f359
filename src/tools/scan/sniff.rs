//! What `mbgate scan --listen` makes of the bytes it heard on a live bus, pure: the
//! whole frames with a good CRC (RTU, of the shapes the public function codes have)
//! or LRC (ASCII) among them, each request paired with the reply that follows it by
//! shape and time (never a repeated request), and per unit the function codes, the
//! counts and the reply times (Modbus Application Protocol V1.1b3 §6 for the shapes;
//! docs/scan.md "Listening to a live bus").

use super::probe::SerialFraming;
use crate::frame::pdu::{reply_matches, reply_well_formed, request_well_formed};
use crate::frame::{ascii, rtu};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

/// A frame seen on the bus, with the times its first and last bytes came.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SniffedFrame {
    /// The unit in it.
    pub(crate) unit: u8,
    /// Its function code (with the exception bit when it is one).
    pub(crate) function: u8,
    /// When its first byte came, from the start of listening.
    pub(crate) start: Duration,
    /// When its last byte came.
    pub(crate) end: Duration,
    /// Its length in bytes.
    pub(crate) len: usize,
    /// Its PDU: the function code and its data.
    pub(crate) pdu: Vec<u8>,
}

/// What one unit did on the bus.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct UnitSeen {
    /// The function codes asked of it, or answered by it where its request was not
    /// heard (without the exception bit).
    pub(crate) functions: BTreeSet<u8>,
    /// Requests to it.
    pub(crate) requests: usize,
    /// Replies from it, exceptions included.
    pub(crate) replies: usize,
    /// Of those, exceptions.
    pub(crate) exceptions: usize,
    /// From each request's last byte to its reply's first.
    pub(crate) times: Vec<Duration>,
}

/// What the bus carried at one setting.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Traffic {
    /// The frames with a good check.
    pub(crate) frames: usize,
    /// Bytes heard in all.
    pub(crate) bytes: usize,
    /// Bytes that were in a frame.
    pub(crate) framed: usize,
    /// By unit.
    pub(crate) units: BTreeMap<u8, UnitSeen>,
}

impl Traffic {
    /// Whether the bus is at this setting: at least `MIN_FRAMES` frames with a good
    /// check, and most of what came in them (at a wrong setting a good check comes
    /// only by chance, now and then).
    pub(crate) fn heard(&self) -> bool {
        self.frames >= MIN_FRAMES && self.framed * 2 > self.bytes
    }

    /// Requests in all.
    pub(crate) fn requests(&self) -> usize {
        self.units.values().map(|u| u.requests).sum()
    }
}

/// Fewer frames than this prove no setting.
pub(crate) const MIN_FRAMES: usize = 3;

/// What came at one setting: every byte, and where each read began and when. One
/// buffer and one entry a read, so an hour of a bus takes its bytes' room and little
/// more.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Listened {
    bytes: Vec<u8>,
    /// (the read's first byte in `bytes`, when it came), in order.
    reads: Vec<(usize, Duration)>,
}

impl Listened {
    /// `bytes` read at `at` (from the start of listening).
    pub(crate) fn push(&mut self, at: Duration, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        self.reads.push((self.bytes.len(), at));
        self.bytes.extend_from_slice(bytes);
    }

    /// Bytes heard in all.
    pub(crate) fn len(&self) -> usize {
        self.bytes.len()
    }

    /// When byte `i` came: the time of the read that brought it.
    fn time_of(&self, i: usize) -> Duration {
        let n = self.reads.partition_point(|&(first, _)| first <= i);
        self.reads[n.saturating_sub(1)].1
    }

    /// The reads of `chunks` (each the bytes of one read and when it came), in order.
    #[cfg(test)]
    pub(crate) fn of(chunks: &[(Duration, Vec<u8>)]) -> Listened {
        let mut h = Listened::default();
        for (at, c) in chunks {
            h.push(*at, c);
        }
        h
    }
}

/// The lengths an RTU frame starting `unit fc b2 .. b6` can have: a request's or a
/// reply's, by the function's shape; the CRC decides which, if any.
fn rtu_lengths(b: &[u8]) -> Vec<usize> {
    let fc = b[1];
    let at = |i: usize| b.get(i).map(|&x| usize::from(x));
    let mut out = Vec::new();
    if fc & 0x80 != 0 {
        out.push(5);
        return out;
    }
    match fc {
        1..=6 => {
            out.push(8);
            if fc <= 4 {
                out.extend(at(2).map(|n| 5 + n));
            }
        }
        15 | 16 => {
            out.push(8);
            out.extend(at(6).map(|n| 9 + n));
        }
        0x11 => {
            out.push(4);
            out.extend(at(2).map(|n| 5 + n));
        }
        _ => {}
    }
    out
}

/// The frames with a good check in what was `heard`, in order.
pub(crate) fn frames(framing: SerialFraming, heard: &Listened) -> Vec<SniffedFrame> {
    let bytes = &heard.bytes;
    let mut out = Vec::new();
    let mut i = 0;
    match framing {
        SerialFraming::Rtu => {
            while i + 4 <= bytes.len() {
                let found = rtu_lengths(&bytes[i..]).into_iter().find_map(|len| {
                    let frame = bytes.get(i..i + len)?;
                    let (unit, pdu) = rtu::decode(frame)?;
                    Some((unit, pdu.to_vec(), len))
                });
                match found {
                    Some((unit, pdu, len)) => {
                        out.push(SniffedFrame {
                            unit,
                            function: pdu[0],
                            start: heard.time_of(i),
                            end: heard.time_of(i + len - 1),
                            len,
                            pdu,
                        });
                        i += len;
                    }
                    None => i += 1,
                }
            }
        }
        SerialFraming::Ascii => {
            while let Some(colon) = bytes[i..].iter().position(|&b| b == b':') {
                let from = i + colon;
                let Some(lf) = bytes[from..].iter().position(|&b| b == b'\n') else {
                    break;
                };
                // A ':' inside starts afresh, as a device's receiver does.
                let to = from + lf;
                let start = bytes[from..to]
                    .iter()
                    .rposition(|&b| b == b':')
                    .map_or(from, |k| from + k);
                if let Some((unit, pdu)) = ascii::decode(&bytes[start..=to]) {
                    if let Some(&function) = pdu.first() {
                        out.push(SniffedFrame {
                            unit,
                            function,
                            start: heard.time_of(start),
                            end: heard.time_of(to),
                            len: to + 1 - start,
                            pdu: pdu.to_vec(),
                        });
                    }
                }
                i = to + 1;
            }
        }
    }
    out
}

/// The shortest time in `seen` from a request to the same bytes again from the master,
/// nothing heard between: its retry (or its next poll) of a request no reply came to.
/// Only a request that cannot be its own reply proves it (an FC 03 read can be told
/// from its reply by its shape; an FC 06 write is answered by its own echo, so two in
/// a row may be a request and its reply). A broadcast (unit 0) gets no reply and is
/// followed sooner, so it proves nothing.
fn retry_gap(seen: &[SniffedFrame]) -> Option<Duration> {
    seen.windows(2)
        .filter(|w| {
            let (a, b) = (&w[0], &w[1]);
            a.unit != 0
                && a.unit == b.unit
                && a.pdu == b.pdu
                && request_well_formed(&a.pdu)
                && !reply_matches(&a.pdu, &a.pdu)
        })
        .map(|w| w[1].start.saturating_sub(w[0].end))
        .min()
}

/// The traffic in `chunks`. A frame is the reply to the request before it only when
/// its shape answers that request (the same unit, the same function or its exception,
/// the data the request calls for: `frame::pdu::reply_matches`) and it came after the
/// request's last byte. A frame that could also be a request by its shape (an FC 05
/// or 06 write is answered by its own echo, byte for byte, so its repetition looks
/// like its reply) is the reply only when it came within half the time the master
/// was heard to repeat an unanswered request (`retry_gap`): the master sends again
/// only after giving up on a reply, so a reply comes sooner than that, and half of it
/// keeps the timers' jitter from moving a repetition into the window. Where no
/// repetition was heard, nothing tells the two apart, and it is taken as the reply.
/// A frame that answers no request heard (the listening began after its request) is
/// its unit's reply, without a time; one that can be neither is counted only among
/// the frames. Anything else, and everything to unit 0, is a request.
pub(crate) fn traffic(framing: SerialFraming, heard: &Listened) -> Traffic {
    let seen = frames(framing, heard);
    let window = retry_gap(&seen).map(|g| g / 2);
    let mut t = Traffic {
        frames: seen.len(),
        bytes: heard.len(),
        framed: seen.iter().map(|f| f.len).sum(),
        units: BTreeMap::new(),
    };
    let mut pending: Option<&SniffedFrame> = None;
    for f in &seen {
        let may_request = f.unit == 0 || request_well_formed(&f.pdu);
        let answers = pending.filter(|req| {
            f.unit != 0
                && req.unit == f.unit
                && f.start >= req.end
                && reply_matches(&req.pdu, &f.pdu)
                && (!may_request || window.is_none_or(|w| f.start - req.end < w))
        });
        if let Some(req) = answers {
            let unit = t.units.entry(f.unit).or_default();
            unit.replies += 1;
            if f.function & 0x80 != 0 {
                unit.exceptions += 1;
            }
            unit.times.push(f.start - req.end);
            pending = None;
        } else if may_request {
            let unit = t.units.entry(f.unit).or_default();
            unit.requests += 1;
            unit.functions.insert(f.function & 0x7F);
            pending = (f.unit != 0).then_some(f);
        } else if reply_well_formed(&f.pdu) {
            let unit = t.units.entry(f.unit).or_default();
            unit.replies += 1;
            if f.function & 0x80 != 0 {
                unit.exceptions += 1;
            }
            unit.functions.insert(f.function & 0x7F);
        }
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn requests_and_replies_are_paired_with_their_times() {
        let req = rtu::encode(5, &[3, 0, 0, 0, 2]);
        let rep = rtu::encode(5, &[3, 4, 0, 1, 0, 2]);
        let req9 = rtu::encode(9, &[4, 0, 1, 0, 1]);
        let exc9 = rtu::encode(9, &[0x84, 2]);
        let chunks = vec![
            (ms(0), req.clone()),
            (ms(12), rep.clone()),
            (ms(100), req9.clone()),
            (ms(107), exc9),
            (ms(200), vec![0xFF, 0x00, 0x13]),
            (ms(300), req),
            (ms(318), rep),
        ];
        let t = traffic(SerialFraming::Rtu, &Listened::of(&chunks));
        assert_eq!(t.frames, 6);
        assert!(t.heard());
        assert_eq!(t.requests(), 3);
        let u5 = &t.units[&5];
        assert_eq!(u5.functions, BTreeSet::from([3]));
        assert_eq!((u5.requests, u5.replies), (2, 2));
        assert_eq!(u5.times, vec![ms(12), ms(18)]);
        let u9 = &t.units[&9];
        assert_eq!((u9.requests, u9.replies, u9.exceptions), (1, 1, 1));
        assert_eq!(u9.functions, BTreeSet::from([4]));
    }

    #[test]
    fn garbage_proves_no_setting() {
        let mut rng = fastrand::Rng::with_seed(7);
        let chunks: Vec<(Duration, Vec<u8>)> = (0..50)
            .map(|i| (ms(i), (0..20).map(|_| rng.u8(..)).collect()))
            .collect();
        assert!(!traffic(SerialFraming::Rtu, &Listened::of(&chunks)).heard());
        assert!(!traffic(SerialFraming::Ascii, &Listened::of(&chunks)).heard());
    }

    #[test]
    fn ascii_frames_are_found_after_a_stray_colon() {
        let req = ascii::encode(12, &[3, 0, 0, 0, 1]);
        let rep = ascii::encode(12, &[3, 2, 0, 7]);
        let mut first = b":zz".to_vec();
        first.extend(&req);
        let chunks = vec![
            (ms(0), first),
            (ms(20), rep.clone()),
            (ms(40), req),
            (ms(50), rep),
        ];
        let t = traffic(SerialFraming::Ascii, &Listened::of(&chunks));
        assert_eq!(t.frames, 4);
        assert_eq!(t.units[&12].replies, 2);
        assert_eq!(t.units[&12].times, vec![ms(20), ms(10)]);
    }

    /// A poll of units 5 (answering) and 7 (silent), each read sent three times when
    /// unanswered, 500 ms apart: FC 03 in `framing`, the poll 250 ms after each
    /// exchange, the listening begun between unit 5's first request and its reply.
    fn retried_poll(framing: SerialFraming) -> Vec<(Duration, Vec<u8>)> {
        let enc = |unit, pdu: &[u8]| match framing {
            SerialFraming::Rtu => rtu::encode(unit, pdu),
            SerialFraming::Ascii => ascii::encode(unit, pdu),
        };
        let req5 = enc(5, &[3, 0, 0, 0, 2]);
        let rep5 = enc(5, &[3, 4, 0, 1, 0, 2]);
        let req7 = enc(7, &[3, 0, 0, 0, 2]);
        let mut chunks = vec![(ms(8), rep5.clone())];
        let mut t = 258;
        for _ in 0..4 {
            for _ in 0..3 {
                chunks.push((ms(t), req7.clone()));
                t += 500;
            }
            t -= 250;
            chunks.push((ms(t), req5.clone()));
            chunks.push((ms(t + 8), rep5.clone()));
            t += 258;
        }
        chunks
    }

    /// One unit polled every 250 ms, answering in 8 ms, the listening begun between a
    /// request and its reply: the reply heard first does not shift every pair after it.
    #[test]
    fn a_reply_heard_first_is_no_request() {
        for framing in [SerialFraming::Rtu, SerialFraming::Ascii] {
            let enc = |pdu: &[u8]| match framing {
                SerialFraming::Rtu => rtu::encode(5, pdu),
                SerialFraming::Ascii => ascii::encode(5, pdu),
            };
            let (req, rep) = (enc(&[3, 0, 0, 0, 2]), enc(&[3, 4, 0, 1, 0, 2]));
            let mut chunks = vec![(ms(8), rep.clone())];
            for k in 1..=4 {
                chunks.push((ms(k * 258), req.clone()));
                chunks.push((ms(k * 258 + 8), rep.clone()));
            }
            let t = traffic(framing, &Listened::of(&chunks));
            assert_eq!(t.units.keys().collect::<Vec<_>>(), vec![&5]);
            assert_eq!(
                t.units[&5].times,
                vec![ms(8); 4],
                "{framing:?}: not the poll gap"
            );
            assert_eq!((t.units[&5].requests, t.units[&5].replies), (4, 5));
        }
    }

    #[test]
    fn a_retried_request_is_never_its_own_reply() {
        for framing in [SerialFraming::Rtu, SerialFraming::Ascii] {
            let t = traffic(framing, &Listened::of(&retried_poll(framing)));
            let u5 = &t.units[&5];
            // The first reply's request was not heard: a reply without a time.
            assert_eq!(u5.times, vec![ms(8); 4], "{framing:?}: not the poll gap");
            assert_eq!((u5.requests, u5.replies), (4, 5), "{framing:?}");
            let u7 = &t.units[&7];
            assert_eq!((u7.requests, u7.replies), (12, 0), "{framing:?}");
            assert!(u7.times.is_empty());
        }
    }

    #[test]
    fn a_write_echoed_is_its_reply_and_repeated_is_a_retry() {
        let read7 = rtu::encode(7, &[3, 0, 0, 0, 1]);
        let write5 = rtu::encode(5, &[6, 0, 1, 0, 7]);
        let write7 = rtu::encode(7, &[6, 0, 1, 0, 7]);
        let mut chunks = Vec::new();
        // Unit 7 never answers: its read is sent again after 300 ms (the master's
        // retry, proven by the read's shape), and so is its write.
        for k in 0..2u64 {
            chunks.push((ms(k * 300), read7.clone()));
        }
        for k in 0..3u64 {
            chunks.push((ms(1000 + k * 300), write7.clone()));
        }
        // Unit 5 echoes its write after 20 ms (an answer), three times over.
        for k in 0..3u64 {
            chunks.push((ms(2000 + k * 300), write5.clone()));
            chunks.push((ms(2020 + k * 300), write5.clone()));
        }
        let t = traffic(SerialFraming::Rtu, &Listened::of(&chunks));
        assert_eq!((t.units[&7].requests, t.units[&7].replies), (5, 0));
        assert_eq!((t.units[&5].requests, t.units[&5].replies), (3, 3));
        assert_eq!(t.units[&5].times, vec![ms(20); 3]);
        // Without a repetition the shape proves, an echo right after its write is
        // taken as its reply: nothing on the bus tells it from a retry.
        let t = traffic(SerialFraming::Rtu, &Listened::of(&chunks[2..]));
        assert_eq!(t.units[&7].replies, 1);
    }

    #[test]
    fn a_broadcast_is_never_answered() {
        let write0 = rtu::encode(0, &[6, 0, 1, 0, 7]);
        let chunks = vec![(ms(0), write0.clone()), (ms(5), write0.clone())];
        let t = traffic(SerialFraming::Rtu, &Listened::of(&chunks));
        assert_eq!((t.units[&0].requests, t.units[&0].replies), (2, 0));
    }
}
