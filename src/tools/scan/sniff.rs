//! What `mbgate scan --listen` makes of the bytes it heard on a live bus, pure: the
//! whole frames with a good CRC (RTU, of the shapes the public function codes have)
//! or LRC (ASCII) among them, each request paired with the reply that follows it
//! (same unit, same function or its exception), and per unit the function codes, the
//! counts and the reply times (Modbus Application Protocol V1.1b3 §6 for the shapes).

use super::probe::SerialFraming;
use crate::frame::{ascii, rtu};
use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

/// A frame seen on the bus, with the times its first and last bytes came.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SniffedFrame {
    /// The unit in it.
    pub unit: u8,
    /// Its function code (with the exception bit when it is one).
    pub function: u8,
    /// When its first byte came, from the start of listening.
    pub start: Duration,
    /// When its last byte came.
    pub end: Duration,
    /// Its length in bytes.
    pub len: usize,
}

/// What one unit did on the bus.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct UnitSeen {
    /// The function codes asked of it (without the exception bit).
    pub functions: BTreeSet<u8>,
    /// Requests to it.
    pub requests: usize,
    /// Replies from it, exceptions included.
    pub replies: usize,
    /// Of those, exceptions.
    pub exceptions: usize,
    /// From each request's last byte to its reply's first.
    pub times: Vec<Duration>,
}

/// What the bus carried at one setting.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Traffic {
    /// The frames with a good check.
    pub frames: usize,
    /// Bytes heard in all.
    pub bytes: usize,
    /// Bytes that were in a frame.
    pub framed: usize,
    /// By unit.
    pub units: BTreeMap<u8, UnitSeen>,
}

impl Traffic {
    /// Whether the bus is at this setting: at least `MIN_FRAMES` frames with a good
    /// check, and most of what came in them (at a wrong setting a good check comes
    /// only by chance, now and then).
    pub fn heard(&self) -> bool {
        self.frames >= MIN_FRAMES && self.framed * 2 > self.bytes
    }

    /// Requests in all.
    pub fn requests(&self) -> usize {
        self.units.values().map(|u| u.requests).sum()
    }
}

/// Fewer frames than this prove no setting.
pub const MIN_FRAMES: usize = 3;

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

/// The frames with a good check in `chunks` (each the bytes of one read and when it
/// came), in order.
pub fn frames(framing: SerialFraming, chunks: &[(Duration, Vec<u8>)]) -> Vec<SniffedFrame> {
    let mut bytes = Vec::new();
    let mut times = Vec::new();
    for (t, c) in chunks {
        bytes.extend_from_slice(c);
        times.extend(std::iter::repeat_n(*t, c.len()));
    }
    let mut out = Vec::new();
    let mut i = 0;
    match framing {
        SerialFraming::Rtu => {
            while i + 4 <= bytes.len() {
                let found = rtu_lengths(&bytes[i..]).into_iter().find_map(|len| {
                    let frame = bytes.get(i..i + len)?;
                    let (unit, pdu) = rtu::decode(frame)?;
                    Some((unit, pdu[0], len))
                });
                match found {
                    Some((unit, function, len)) => {
                        out.push(SniffedFrame {
                            unit,
                            function,
                            start: times[i],
                            end: times[i + len - 1],
                            len,
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
                            start: times[start],
                            end: times[to],
                            len: to + 1 - start,
                        });
                    }
                }
                i = to + 1;
            }
        }
    }
    out
}

/// The traffic in `chunks`: each frame that follows a request to the same unit with
/// its function (or the exception form), and comes after it, is its reply; any other
/// frame is a request.
pub fn traffic(framing: SerialFraming, chunks: &[(Duration, Vec<u8>)]) -> Traffic {
    let seen = frames(framing, chunks);
    let mut t = Traffic {
        frames: seen.len(),
        bytes: chunks.iter().map(|(_, c)| c.len()).sum(),
        framed: seen.iter().map(|f| f.len).sum(),
        units: BTreeMap::new(),
    };
    let mut pending: Option<&SniffedFrame> = None;
    for f in &seen {
        let unit = t.units.entry(f.unit).or_default();
        match pending {
            Some(req)
                if req.unit == f.unit
                    && f.function & 0x7F == req.function
                    && f.start >= req.end =>
            {
                unit.replies += 1;
                if f.function & 0x80 != 0 {
                    unit.exceptions += 1;
                }
                unit.times.push(f.start - req.end);
                pending = None;
            }
            _ => {
                unit.requests += 1;
                unit.functions.insert(f.function & 0x7F);
                pending = Some(f);
            }
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
        let t = traffic(SerialFraming::Rtu, &chunks);
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
        assert!(!traffic(SerialFraming::Rtu, &chunks).heard());
        assert!(!traffic(SerialFraming::Ascii, &chunks).heard());
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
        let t = traffic(SerialFraming::Ascii, &chunks);
        assert_eq!(t.frames, 4);
        assert_eq!(t.units[&12].replies, 2);
        assert_eq!(t.units[&12].times, vec![ms(20), ms(10)]);
    }
}
