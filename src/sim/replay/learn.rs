//! From a capture's packets to what each device did (pure): every request mbgate put
//! on a line paired with the reply it got, or with the timeout it recorded, and the
//! time between them (docs/capture.md "What a packet holds"; docs/simulator.md
//! "Replaying a device").
//!
//! Only the lines' interfaces are read (every interface but the one named `tcp`):
//! they hold the device's own frames, in the line's framing, timed where they left
//! and arrived. Dropped bytes (their comment starts `dropped (`) and frames that
//! answered no request are not the device's answers and are passed over.

use crate::capture::pcapng;
use crate::capture::pcapng_read::{exported, Read};
use crate::config::Framing;
use crate::frame::rtu;

/// What the device did with one request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Seen {
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
    pub(crate) seen: Seen,
    /// Request out to reply in, for a reply.
    pub(crate) turnaround_us: Option<u64>,
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

/// The requests still waiting for their answer on one line.
#[derive(Debug, Default)]
struct Waiting {
    queries: Vec<(u64, Framing, u16, u8, Vec<u8>)>,
}

/// Every request of every line of `capture` and what came of it, in the order the
/// requests went out on each line (lines one after the other).
pub(crate) fn observations(capture: &Read<'_>) -> Vec<Observation> {
    let mut waiting: Vec<Waiting> = capture
        .interfaces
        .iter()
        .map(|_| Waiting::default())
        .collect();
    let mut out = Vec::new();
    for p in &capture.packets {
        let iface = &capture.interfaces[p.interface];
        if iface.name == "tcp" || iface.link_type != pcapng::LINKTYPE_WIRESHARK_UPPER_PDU {
            continue;
        }
        let comment = p.comment.as_deref().unwrap_or("");
        if comment.starts_with("dropped (") || comment.starts_with("a frame that answers") {
            continue;
        }
        let Some(e) = exported(p.data) else { continue };
        let w = &mut waiting[p.interface];
        if comment.starts_with("timeout: no reply from unit ") {
            // The oldest request still waiting gets the timeout (one at a time on a
            // serial bus; an MBAP line's in order).
            if !w.queries.is_empty() {
                let (at_us, framing, _, unit, request) = w.queries.remove(0);
                out.push(Observation {
                    at_us,
                    unit,
                    request,
                    seen: Seen::Silent,
                    turnaround_us: None,
                    framing,
                });
            }
            continue;
        }
        let ascii = comment.starts_with("ASCII on the wire");
        let Some((framing, tid, unit, pdu)) = frame(&e.dissector, e.payload, ascii) else {
            continue;
        };
        // The direction flag, or (a writer that left it out) the ports: a query goes
        // to 502.
        let outbound = match p.flags & 0b11 {
            0b10 => true,
            0b01 => false,
            _ => e.ports.is_some_and(|(_, dst)| dst == 502),
        };
        if outbound {
            if unit == 0 && framing != Framing::Mbap {
                // A broadcast: no device answers it.
                continue;
            }
            if framing != Framing::Mbap {
                // One request at a time on a bus: a new one ends the wait of any before.
                w.queries.clear();
            }
            w.queries.push((p.at_us, framing, tid, unit, pdu));
            continue;
        }
        let Some(fc) = pdu.first() else { continue };
        let found = w.queries.iter().position(|(_, f, t, u, q)| {
            *u == unit && q.first() == Some(&(fc & 0x7F)) && (*f != Framing::Mbap || *t == tid)
        });
        if let Some(i) = found {
            let (at_us, framing, _, unit, request) = w.queries.remove(i);
            out.push(Observation {
                at_us,
                unit,
                request,
                seen: Seen::Reply(pdu),
                turnaround_us: Some(p.at_us.saturating_sub(at_us)),
                framing,
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::capture::pcapng_read::read;

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
        pcapng::packet(&pcapng::Packet {
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
                (100, 1, Seen::Reply(vec![3, 2, 0, 7]), Some(1500)),
                (2000, 2, Seen::Reply(vec![0x83, 2]), Some(500)),
                (3000, 3, Seen::Silent, None),
            ]
        );
        assert!(got.iter().all(|o| o.framing == Framing::Rtu));
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
                    Seen::Reply(vec![3, 2, 0, 2]),
                    Framing::Mbap
                ),
                (
                    4,
                    vec![0, 0, 1],
                    Seen::Reply(vec![3, 2, 0, 1]),
                    Framing::Mbap
                ),
                (
                    7,
                    vec![0, 0, 1],
                    Seen::Reply(vec![3, 2, 0, 9]),
                    Framing::Ascii
                ),
            ]
        );
    }
}
