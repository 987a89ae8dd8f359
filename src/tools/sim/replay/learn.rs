//! From a capture's packets to what each device did (pure): every request mbgate put
//! on a line paired with the reply it got, or with the timeout it recorded, and the
//! time between them (docs/capture.md "What a packet holds"; docs/simulator.md
//! "Replaying a device").
//!
//! Only the lines' interfaces are read (every interface but the one named `tcp`):
//! they hold the device's own frames, in the line's framing, timed where they left
//! and arrived. Dropped bytes (their comment starts `dropped (`) and frames that
//! answered no request are not the device's answers and are passed over.
//!
//! [`Learner`] takes the packets one at a time, as the file is read: what it holds
//! between them is the requests still waiting on each line, at most
//! [`MAX_WAITING`] a line.

use crate::config::Framing;
use crate::frame::rtu;
use crate::ops::capture::pcapng;
use crate::ops::capture::pcapng_read::{exported, FileInterface, Record};
use crate::tools::wire::uart::Format;
use std::collections::VecDeque;

/// What the device did with one request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum RecordedReply {
    /// It answered with this PDU (an exception response too).
    Reply(Vec<u8>),
    /// It said nothing before the gateway's timeout.
    Silent,
}

/// One request on a line and what came of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Observation {
    /// When the request went out, microseconds since the epoch.
    pub(crate) at_us: u64,
    pub(crate) unit: u8,
    /// The request PDU.
    pub(crate) request: Vec<u8>,
    pub(crate) seen: RecordedReply,
    /// Request out to reply in, for a reply.
    pub(crate) turnaround_us: Option<u64>,
    /// The time the request's and the reply's bytes take on a wire at the line's
    /// recorded speed (0 where none is recorded): taken out of the turnaround for the
    /// device's own time, unless the line had no wire (`Wires`).
    pub(crate) wire_us: u64,
    /// The line, numbered over every file read (each file's interfaces after the
    /// last file's).
    pub(crate) line: usize,
    /// How the line carried it.
    pub(crate) framing: Framing,
}

/// A frame off a packet: (framing, transaction id for MBAP, unit, PDU).
fn frame(dissector: &str, payload: &[u8], ascii: bool) -> Option<(Framing, u16, u8, Vec<u8>)> {
    match dissector {
        "mbrtu" => {
            let (unit, pdu) = rtu::decode(payload)?;
            let framing = if ascii { Framing::Ascii } else { Framing::Rtu };
            Some((framing, 0, unit, pdu.to_vec()))
        }
        "mbtcp" => {
            if payload.len() < 8 {
                return None;
            }
            let tid = u16::from_be_bytes([payload[0], payload[1]]);
            let len = usize::from(u16::from_be_bytes([payload[4], payload[5]]));
            if payload[2..4] != [0, 0] || len < 2 || payload.len() != 6 + len {
                return None;
            }
            Some((Framing::Mbap, tid, payload[6], payload[7..].to_vec()))
        }
        _ => None,
    }
}

/// The most requests a line may have waiting for their answer: the most a gateway
/// keeps in flight on a line (`max_in_flight`, 1 to 255). A file with more (no
/// capture of mbgate's) forgets the oldest, which would have timed out.
pub(crate) const MAX_WAITING: usize = 256;

/// A request waiting for its answer: (sent at, framing, transaction id, unit, PDU).
type Waiting = (u64, Framing, u16, u8, Vec<u8>);

/// What the capture said so far: each line's speed and the requests still waiting
/// for their answer.
#[derive(Debug, Default)]
pub(crate) struct Learner {
    /// The number of this file's first interface among every file's lines.
    first_line: usize,
    speeds: Vec<Option<Speed>>,
    waiting: Vec<VecDeque<Waiting>>,
}

impl Learner {
    /// A learner for a file whose interfaces are numbered from `first_line` on.
    pub(crate) fn new(first_line: usize) -> Learner {
        Learner {
            first_line,
            ..Learner::default()
        }
    }

    /// What packet `p` (of a file whose interfaces so far are `interfaces`) shows: a
    /// request's reply or timeout, or nothing yet.
    pub(crate) fn packet(
        &mut self,
        interfaces: &[FileInterface],
        p: &Record<'_>,
    ) -> Option<Observation> {
        let iface = &interfaces[p.interface];
        if iface.name == "tcp" || iface.link_type != pcapng::LINKTYPE_WIRESHARK_UPPER_PDU {
            return None;
        }
        while self.speeds.len() < interfaces.len() {
            self.speeds
                .push(speed(&interfaces[self.speeds.len()].description));
            self.waiting.push(VecDeque::new());
        }
        let comment = p.comment.as_deref().unwrap_or("");
        if comment.starts_with("dropped (") || comment.starts_with("a frame that answers") {
            return None;
        }
        let e = exported(p.data)?;
        let line = self.first_line + p.interface;
        let w = &mut self.waiting[p.interface];
        if comment.starts_with("timeout: no reply from unit ") {
            return timed_out(w, line);
        }
        let ascii = comment.starts_with("ASCII on the wire");
        let (framing, tid, unit, pdu) = frame(&e.dissector, e.payload, ascii)?;
        // The direction flag, or (a writer that left it out) the ports: a query goes
        // to 502.
        let outbound = match p.flags & 0b11 {
            0b10 => true,
            0b01 => false,
            _ => e.ports.is_some_and(|(_, dst)| dst == 502),
        };
        if outbound {
            sent(w, (p.at_us, framing, tid, unit, pdu));
            return None;
        }
        let fc = *pdu.first()?;
        let found = w.iter().position(|(_, f, t, u, q)| {
            *u == unit && q.first() == Some(&(fc & 0x7F)) && (*f != Framing::Mbap || *t == tid)
        })?;
        let (at_us, framing, _, unit, request) = w.remove(found)?;
        let wire = self.speeds[p.interface].map_or(0, |sp| wire_us(sp, framing, &request, &pdu));
        Some(Observation {
            at_us,
            unit,
            request,
            seen: RecordedReply::Reply(pdu),
            turnaround_us: Some(p.at_us.saturating_sub(at_us)),
            wire_us: wire,
            line,
            framing,
        })
    }
}

/// A timeout on `line`: the oldest request still waiting gets it (one at a time on a
/// serial bus; an MBAP line's in order).
fn timed_out(w: &mut VecDeque<Waiting>, line: usize) -> Option<Observation> {
    let (at_us, framing, _, unit, request) = w.pop_front()?;
    Some(Observation {
        at_us,
        unit,
        request,
        seen: RecordedReply::Silent,
        turnaround_us: None,
        wire_us: 0,
        line,
        framing,
    })
}

/// A request on its way to the device, waiting for its reply (a broadcast on a bus
/// waits for none; on a bus a new request ends the wait of any before).
fn sent(w: &mut VecDeque<Waiting>, request: Waiting) {
    let (_, framing, _, unit, _) = &request;
    if *unit == 0 && *framing != Framing::Mbap {
        // A broadcast: no device answers it.
        return;
    }
    if *framing != Framing::Mbap {
        // One request at a time on a bus: a new one ends the wait of any before.
        w.clear();
    }
    if w.len() == MAX_WAITING {
        w.pop_front();
    }
    w.push_back(request);
}

/// Every request of every line of `capture` and what came of it, in the order the
/// answers came.
#[cfg(test)]
pub(crate) fn observations(
    capture: &crate::ops::capture::pcapng_read::Read<'_>,
) -> Vec<Observation> {
    let mut learner = Learner::new(0);
    capture
        .packets
        .iter()
        .filter_map(|p| learner.packet(&capture.interfaces, p))
        .collect()
}

/// One recorded reply's times, for [`Wires`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Recorded {
    /// The capture's interface (the line).
    pub(crate) line: usize,
    /// Request out to reply in, as the capture timed them.
    pub(crate) turnaround_us: u64,
    /// The time the request's and the reply's bytes take on a wire at the line's
    /// recorded speed ([`wire_us`]).
    pub(crate) wire_us: u64,
}

/// Which lines had no wire, from the replies recorded on them: the rule that makes
/// each recorded reply's time the device's own, what a replay waits between the
/// request's last byte in and the reply's first byte out.
///
/// The capture times a request when mbgate hands it to the port, before its first
/// byte leaves, and a reply when its last byte is read (docs/capture.md "What a
/// packet holds"). On a wire the turnaround so holds the request's and the reply's
/// time on it at the line's speed; the replay's own port (a UART, or a pty paced
/// with `--baud`) takes them again, so they are taken out. On a pty there is
/// no wire and nothing is taken out. The capture does not say which the port was;
/// the replies do: no device answers before its request could have crossed the
/// wire and its reply come back, so a line where any reply came sooner than that
/// had no wire (the gateway's own rule: docs/reliability.md "Knowing the wire").
/// Known only once every reply is read: [`Wires::saw`] each, then [`Wires::own`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub(crate) struct Wires {
    none: std::collections::BTreeSet<usize>,
}

impl Wires {
    /// A reply recorded.
    pub(crate) fn saw(&mut self, r: Recorded) {
        if r.turnaround_us < r.wire_us {
            self.none.insert(r.line);
        }
    }

    /// The device's own time in `r`, once every reply was seen.
    pub(crate) fn own(&self, r: Recorded) -> u64 {
        if self.none.contains(&r.line) {
            r.turnaround_us
        } else {
            r.turnaround_us.saturating_sub(r.wire_us)
        }
    }
}

/// The device's own time in each of `recorded` ([`Wires`]).
#[cfg(test)]
pub(crate) fn own_times(recorded: &[Recorded]) -> Vec<u64> {
    let mut wires = Wires::default();
    for r in recorded {
        wires.saw(*r);
    }
    recorded.iter().map(|r| wires.own(*r)).collect()
}

/// A line's speed as its capture says it: bits a second, and bits a character.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Speed {
    pub(crate) baud: u32,
    /// Start, data, parity and stop bits.
    pub(crate) bits: u32,
}

/// The speed an mbgate capture's line description gives (`line 0: rtu, 19200 baud
/// 8E1`), none for a device on the network or another writer's interface. The
/// character's format is in captures made since it was added; without it (an older
/// capture), ten bits a character: start, eight data bits (seven and parity for
/// ASCII), stop.
pub(crate) fn speed(description: &str) -> Option<Speed> {
    let at = description.find(" baud")?;
    let digits = description[..at].rsplit(' ').next()?;
    let baud = digits.parse().ok().filter(|&b| b > 0)?;
    let format = description[at + " baud".len()..]
        .strip_prefix(' ')
        .and_then(|rest| rest.split([',', ' ']).next())
        .and_then(|f| f.parse::<Format>().ok());
    Some(Speed {
        baud,
        bits: format.map_or(10, Format::bits),
    })
}

/// The time `request` and `reply` (PDUs) take on a wire at `speed` in `framing`, µs.
pub(crate) fn wire_us(speed: Speed, framing: Framing, request: &[u8], reply: &[u8]) -> u64 {
    let bytes = |pdu: &[u8]| match framing {
        // Unit and CRC.
        Framing::Rtu => pdu.len() + 3,
        // Colon, unit, PDU and LRC as two hex digits each, CR LF.
        Framing::Ascii => 1 + 2 * (pdu.len() + 2) + 2,
        // The MBAP header with the unit.
        Framing::Mbap => pdu.len() + 7,
    };
    let chars = (bytes(request) + bytes(reply)) as u64;
    chars * u64::from(speed.bits) * 1_000_000 / u64::from(speed.baud)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::capture::pcapng_read::read;

    fn packet(
        iface: u32,
        at_us: u64,
        dissector: &str,
        bytes: &[u8],
        flags: u32,
        note: &str,
    ) -> Vec<u8> {
        let mut data = pcapng::exported_pdu(&pcapng::Exported {
            dissector,
            ..Default::default()
        });
        data.extend(bytes);
        pcapng::packet(&pcapng::EnhancedPacket {
            interface: iface,
            at_us,
            data: &data,
            comment: Some(note),
            flags,
        })
    }

    #[test]
    fn pairs_requests_with_replies_and_timeouts_on_the_lines_only() {
        let (out, inb) = (pcapng::OUTBOUND, pcapng::INBOUND);
        let mut f = pcapng::section_header("t");
        f.extend(pcapng::interface("tcp", ""));
        f.extend(pcapng::interface("/dev/ttyS0", ""));
        let q = rtu::encode(1, &[3, 0, 0, 0, 1]);
        let r = rtu::encode(1, &[3, 2, 0, 7]);
        let x = rtu::encode(2, &[0x83, 2]);
        // The TCP side: passed over.
        f.extend(packet(0, 5, "mbrtu", &q, out, ""));
        f.extend(packet(1, 100, "mbrtu", &q, out, ""));
        f.extend(packet(
            1,
            90,
            "mbrtu",
            &r,
            inb,
            "dropped (stale): a reply (7 bytes)",
        ));
        f.extend(packet(1, 1600, "mbrtu", &r, inb, ""));
        f.extend(packet(
            1,
            2000,
            "mbrtu",
            &rtu::encode(2, &[3, 0, 9, 0, 1]),
            out,
            "",
        ));
        f.extend(packet(1, 2500, "mbrtu", &x, inb, ""));
        f.extend(packet(
            1,
            3000,
            "mbrtu",
            &rtu::encode(3, &[4, 0, 0, 0, 1]),
            out,
            "",
        ));
        f.extend(packet(
            1,
            9000,
            "data",
            &[],
            0,
            "timeout: no reply from unit 3 to function 4 in time",
        ));
        f.extend(packet(
            1,
            9100,
            "mbrtu",
            &rtu::encode(0, &[6, 0, 0, 0, 1]),
            out,
            "",
        ));
        let capture = read(&f).unwrap();
        let got = observations(&capture);
        let brief: Vec<_> = got
            .iter()
            .map(|o| (o.at_us, o.unit, o.seen.clone(), o.turnaround_us))
            .collect();
        assert_eq!(
            brief,
            [
                (100, 1, RecordedReply::Reply(vec![3, 2, 0, 7]), Some(1500)),
                (2000, 2, RecordedReply::Reply(vec![0x83, 2]), Some(500)),
                (3000, 3, RecordedReply::Silent, None),
            ]
        );
        assert!(got.iter().all(|o| o.framing == Framing::Rtu));
    }

    /// A reply's own time: the wire's time at the line's speed taken out, except on a
    /// line where a reply came sooner than its bytes could have crossed (a pty).
    #[test]
    fn the_device_s_own_time_is_the_turnaround_less_the_wire_where_there_was_one() {
        // 8 request bytes and 7 reply bytes (RTU, FC 03, one register) at 19 200
        // baud: 150 bits, 7812 µs; ASCII: 17 + 15 characters; MBAP: 12 + 11 bytes.
        let (q, r) = ([3, 0, 0, 0, 1], [3, 2, 0, 7]);
        let at = |baud, bits| Speed { baud, bits };
        assert_eq!(wire_us(at(19_200, 10), Framing::Rtu, &q, &r), 7812);
        // 8E1: eleven bits a character.
        assert_eq!(wire_us(at(19_200, 11), Framing::Rtu, &q, &r), 8593);
        assert_eq!(wire_us(at(9_600, 10), Framing::Ascii, &q, &r), 33_333);
        assert_eq!(wire_us(at(4_000_000, 10), Framing::Mbap, &q, &r), 57);
        // Captures made before the format was written: ten bits.
        assert_eq!(speed("line 0: rtu, 19200 baud"), Some(at(19_200, 10)));
        assert_eq!(
            speed("line 1: ascii, 9600 baud, the device is the master"),
            Some(at(9_600, 10))
        );
        assert_eq!(speed("line 0: rtu, 19200 baud 8E1"), Some(at(19_200, 11)));
        assert_eq!(speed("line 0: rtu, 9600 baud 8N2"), Some(at(9_600, 11)));
        assert_eq!(speed("line 0: rtu, 9600 baud 8N1"), Some(at(9_600, 10)));
        assert_eq!(
            speed("line 1: ascii, 9600 baud 7E1, the device is the master"),
            Some(at(9_600, 10))
        );
        assert_eq!(speed("line 0: rtu, 9600 baud 9X3"), Some(at(9_600, 10)));
        assert_eq!(speed("line 2: mbap, device at 10.0.0.5:502"), None);
        assert_eq!(speed("line 0: rtu, 0 baud"), None);
        assert_eq!(speed(""), None);
        let rec = |line, turnaround_us, wire_us| Recorded {
            line,
            turnaround_us,
            wire_us,
        };
        let got = own_times(&[
            // Line 0, a wire: every reply took at least its bytes' time.
            rec(0, 12_812, 7_812),
            rec(0, 7_812, 7_812),
            // Line 1, a pty recorded at 19 200: one reply came in 0.5 ms, so none of
            // its replies crossed a wire and none loses anything.
            rec(1, 9_000, 7_812),
            rec(1, 500, 7_812),
            // Line 2, a device on the network: no wire.
            rec(2, 3_000, 0),
        ]);
        assert_eq!(got, [5_000, 0, 9_000, 500, 3_000]);
    }

    /// The capture's line description gives the speed the wire's time is taken at.
    #[test]
    fn a_line_s_recorded_speed_takes_the_wire_out_of_its_replies() {
        let (out, inb) = (pcapng::OUTBOUND, pcapng::INBOUND);
        let mut f = pcapng::section_header("t");
        f.extend(pcapng::interface("/dev/ttyS0", "line 0: rtu, 9600 baud"));
        f.extend(pcapng::interface("/dev/pts/3", "line 1: rtu, 9600 baud"));
        let q = rtu::encode(1, &[3, 0, 0, 0, 1]);
        let r = rtu::encode(1, &[3, 2, 0, 7]);
        // 15 bytes at 9600 baud: 15 625 µs on a wire; 20 ms recorded on line 0.
        f.extend(packet(0, 1_000, "mbrtu", &q, out, ""));
        f.extend(packet(0, 21_000, "mbrtu", &r, inb, ""));
        // Line 1 answered in 0.4 ms: no wire, its 20 ms reply kept whole.
        f.extend(packet(1, 30_000, "mbrtu", &q, out, ""));
        f.extend(packet(1, 30_400, "mbrtu", &r, inb, ""));
        f.extend(packet(1, 40_000, "mbrtu", &q, out, ""));
        f.extend(packet(1, 60_000, "mbrtu", &r, inb, ""));
        let seen = observations(&read(&f).unwrap());
        let recorded: Vec<Recorded> = seen
            .iter()
            .map(|o| Recorded {
                line: o.line,
                turnaround_us: o.turnaround_us.unwrap(),
                wire_us: o.wire_us,
            })
            .collect();
        let got: Vec<_> = seen.iter().map(|o| o.turnaround_us).collect();
        assert_eq!(got, [Some(20_000), Some(400), Some(20_000)]);
        assert_eq!(own_times(&recorded), [4_375, 400, 20_000]);
    }

    /// A line holds at most [`MAX_WAITING`] requests waiting for their answer (a
    /// gateway keeps 255 in flight at most): a file of requests never answered takes
    /// no more memory, and a reply is looked for among those only.
    #[test]
    fn a_line_keeps_the_last_requests_waiting_and_no_more() {
        let (out, inb) = (pcapng::OUTBOUND, pcapng::INBOUND);
        let mbap = |tid: u16, pdu: &[u8]| crate::frame::Adu::build(tid, 4, pdu).as_bytes().to_vec();
        let mut f = pcapng::section_header("t");
        f.extend(pcapng::interface("192.168.1.20:502", ""));
        for tid in 1..=1000u16 {
            f.extend(packet(
                0,
                10,
                "mbtcp",
                &mbap(tid, &[3, 0, 0, 0, 1]),
                out,
                "",
            ));
        }
        // The first request's reply: forgotten with it. The last one's: found.
        f.extend(packet(0, 20, "mbtcp", &mbap(1, &[3, 2, 0, 1]), inb, ""));
        f.extend(packet(0, 30, "mbtcp", &mbap(1000, &[3, 2, 0, 9]), inb, ""));
        let capture = read(&f).unwrap();
        let mut learner = Learner::new(0);
        let mut seen = Vec::new();
        for p in &capture.packets {
            seen.extend(learner.packet(&capture.interfaces, p));
            assert!(learner.waiting.iter().all(|w| w.len() <= MAX_WAITING));
        }
        assert_eq!(seen.len(), 1);
        assert_eq!(seen[0].seen, RecordedReply::Reply(vec![3, 2, 0, 9]));
        assert_eq!(learner.waiting[0].len(), MAX_WAITING - 1);
    }

    /// An MBAP line's replies are found by their transaction id, an ASCII line's
    /// frames by the text in their comment.
    #[test]
    fn mbap_replies_by_transaction_id_and_ascii_by_its_comment() {
        let (out, inb) = (pcapng::OUTBOUND, pcapng::INBOUND);
        let mbap = |tid: u16, pdu: &[u8]| crate::frame::Adu::build(tid, 4, pdu).as_bytes().to_vec();
        let mut f = pcapng::section_header("t");
        f.extend(pcapng::interface("192.168.1.20:502", ""));
        f.extend(pcapng::interface("/dev/ttyS1", ""));
        f.extend(packet(0, 10, "mbtcp", &mbap(1, &[3, 0, 0, 0, 1]), out, ""));
        f.extend(packet(0, 20, "mbtcp", &mbap(2, &[3, 0, 1, 0, 1]), out, ""));
        f.extend(packet(0, 30, "mbtcp", &mbap(2, &[3, 2, 0, 2]), inb, ""));
        f.extend(packet(0, 40, "mbtcp", &mbap(1, &[3, 2, 0, 1]), inb, ""));
        let ascii = "ASCII on the wire: :070300000001F5\\r\\n";
        f.extend(packet(
            1,
            50,
            "mbrtu",
            &rtu::encode(7, &[3, 0, 0, 0, 1]),
            out,
            ascii,
        ));
        f.extend(packet(
            1,
            60,
            "mbrtu",
            &rtu::encode(7, &[3, 2, 0, 9]),
            inb,
            ascii,
        ));
        let got = observations(&read(&f).unwrap());
        let brief: Vec<_> = got
            .iter()
            .map(|o| (o.unit, o.request[2..].to_vec(), o.seen.clone(), o.framing))
            .collect();
        assert_eq!(
            brief,
            [
                (
                    4,
                    vec![1, 0, 1],
                    RecordedReply::Reply(vec![3, 2, 0, 2]),
                    Framing::Mbap
                ),
                (
                    4,
                    vec![0, 0, 1],
                    RecordedReply::Reply(vec![3, 2, 0, 1]),
                    Framing::Mbap
                ),
                (
                    7,
                    vec![0, 0, 1],
                    RecordedReply::Reply(vec![3, 2, 0, 9]),
                    Framing::Ascii
                ),
            ]
        );
    }
}
