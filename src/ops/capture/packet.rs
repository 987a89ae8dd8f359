//! What one captured packet holds (docs/capture.md "What a packet holds"), and how it
//! is written as a pcapng block: a frame on an interface, in its direction, its bytes
//! for the dissector that reads them, the TCP ends where there are any, and a note for
//! the packet's comment (why bytes were dropped; an ASCII frame as it was on the
//! wire). Pure.

use super::pcapng;
use crate::config::Framing;
use crate::frame::{ascii, rtu, Adu};
use std::net::{IpAddr, SocketAddr};

/// The port Wireshark's Modbus/TCP dissector knows: a packet to it is a query, a
/// packet from it a response (docs/design.md §6).
pub(crate) const MODBUS_PORT: u16 = 502;

/// Which dissector reads the packet's bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Proto {
    /// An MBAP frame (Modbus/TCP).
    Mbtcp,
    /// An RTU frame, CRC included.
    Mbrtu,
    /// Bytes as they are.
    Data,
}

impl Proto {
    fn dissector(self) -> &'static str {
        match self {
            Proto::Mbtcp => "mbtcp",
            Proto::Mbrtu => "mbrtu",
            Proto::Data => "data",
        }
    }
}

/// Which way the packet went, seen from the gateway.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Dir {
    /// To the gateway: from a master, a device, a slave.
    In,
    /// From the gateway.
    Out,
    /// Neither: an event (a timeout).
    Neither,
}

/// The packet's part in its conversation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Part {
    /// A request, to the side that serves.
    Query,
    /// A reply (or a notification), from the side that serves.
    Reply,
    /// Neither: dropped bytes, an event.
    Other,
}

/// Why the gateway dropped bytes it received (docs/capture.md "Dropped bytes").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Reason {
    /// Bytes that start no frame, a frame that lost bytes (MBAP: refuted by what
    /// followed it), a partial frame the line left unfinished.
    LostSync,
    /// Bytes that answer no request now: received before the request went out, after
    /// its timeout, a reply to a request already finished, the port reopened.
    Stale,
    /// The line's echo of the request, or what should have been it and was not.
    Echo,
    /// A reply that began before its request had left.
    TooEarly,
    /// An RTU frame whose CRC failed.
    Crc,
    /// An ASCII frame whose LRC failed.
    Lrc,
    /// Bytes a master sent that broke the protocol (its connection was closed).
    Refused,
}

impl Reason {
    /// The word a packet's comment gives for it: `dropped (WORD): ...`.
    pub(crate) fn word(self) -> &'static str {
        match self {
            Reason::LostSync => "lost sync",
            Reason::Stale => "stale",
            Reason::Echo => "echo",
            Reason::TooEarly => "too early",
            Reason::Crc => "CRC",
            Reason::Lrc => "LRC",
            Reason::Refused => "refused",
        }
    }
}

/// The TCP connection a packet went over: the client's address and port, and the
/// server's address (its port is written as [`MODBUS_PORT`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Ends {
    /// The side that sends queries: a master, or mbgate itself toward a slave.
    pub(crate) client: SocketAddr,
    /// The side that serves: mbgate's listener, or a slave.
    pub(crate) server: SocketAddr,
}

/// One packet for the capture.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Packet {
    /// Microseconds since the Unix epoch, from the capture's one clock.
    pub(crate) at_us: u64,
    /// 0: the TCP side; 1 and up: the lines, in the order of the configuration.
    pub(crate) iface: u16,
    pub(crate) dir: Dir,
    pub(crate) part: Part,
    pub(crate) proto: Proto,
    /// What the dissector reads.
    pub(crate) bytes: Vec<u8>,
    /// The TCP ends (the TCP side only).
    pub(crate) ends: Option<Ends>,
    /// The master's connection the packet belongs to, where one does.
    pub(crate) conn: Option<u64>,
    /// The unit id and function code, where the packet is a frame.
    pub(crate) unit: Option<u8>,
    pub(crate) function: Option<u8>,
    /// The first address and count a request names (for the status page).
    pub(crate) span: Option<(u16, u16)>,
    /// Bytes dropped, and why.
    pub(crate) dropped: Option<Reason>,
    /// The packet's comment.
    pub(crate) note: Option<String>,
    /// What the status page calls it: `gw->serial`, `serial->gw`, `master->gw`,
    /// `gw->master`, `late`, `unsolicited`, `timeout`, `dropped`.
    pub(crate) label: &'static str,
}

impl Packet {
    /// A packet with nothing in it yet but its bytes for `proto`.
    pub(crate) fn new(dir: Dir, part: Part, proto: Proto, bytes: Vec<u8>) -> Packet {
        Packet {
            at_us: 0,
            iface: 0,
            dir,
            part,
            proto,
            bytes,
            ends: None,
            conn: None,
            unit: None,
            function: None,
            span: None,
            dropped: None,
            note: None,
            label: "",
        }
    }

    /// The frame `adu` as a line of `framing` carries it (`wire`: its bytes on the
    /// line, for ASCII the text). An ASCII frame is given to the RTU dissector as the
    /// same unit and PDU with their CRC, its text in the comment: Wireshark has no
    /// Modbus ASCII dissector (docs/design.md §6).
    pub(crate) fn line_frame(
        framing: Framing,
        adu: &Adu,
        wire: &[u8],
        dir: Dir,
        part: Part,
    ) -> Packet {
        let mut p = Packet::new(dir, part, Proto::Data, Vec::new());
        p.set_line_frame(framing, adu, wire);
        p
    }

    /// Makes this packet (new or [`Packet::clear`]ed: its direction and part set)
    /// the frame `adu` as a line of `framing` carries it, as [`Packet::line_frame`]
    /// does, in the room its bytes already have.
    pub(crate) fn set_line_frame(&mut self, framing: Framing, adu: &Adu, wire: &[u8]) {
        match framing {
            Framing::Mbap => {
                self.proto = Proto::Mbtcp;
                self.bytes.extend_from_slice(wire);
            }
            Framing::Rtu => {
                self.proto = Proto::Mbrtu;
                self.bytes.extend_from_slice(wire);
            }
            Framing::Ascii => {
                self.proto = Proto::Mbrtu;
                self.bytes = rtu::encode(adu.unit(), adu.pdu());
                self.note = Some(format!("ASCII on the wire: {}", ascii_text(wire)));
            }
        }
        self.unit = Some(adu.unit());
        self.function = Some(adu.function());
    }

    /// The packet emptied to what [`Packet::new`] makes, `dir` and `part` set, its
    /// bytes' room kept: the status page's last packets are filled again in place
    /// rather than allocated for each frame (docs/performance.md "What the status page
    /// costs, counted").
    pub(crate) fn clear(&mut self, dir: Dir, part: Part) {
        let mut bytes = std::mem::take(&mut self.bytes);
        bytes.clear();
        *self = Packet::new(dir, part, Proto::Data, bytes);
    }

    /// Bytes dropped for `reason` (`detail` says more): as a frame of `framing` if
    /// they make one (a stale reply, an echo, an RTU frame whose CRC failed), else as
    /// data.
    pub(crate) fn dropped(
        framing: Option<Framing>,
        reason: Reason,
        bytes: Vec<u8>,
        whole: bool,
        detail: &str,
    ) -> Packet {
        let n = bytes.len();
        let (proto, bytes, text) = match framing {
            Some(Framing::Mbap) if whole => (Proto::Mbtcp, bytes, None),
            Some(Framing::Rtu) if whole => (Proto::Mbrtu, bytes, None),
            Some(Framing::Ascii) if whole => match ascii::decode(&bytes) {
                Some((unit, pdu)) => {
                    let text = ascii_text(&bytes);
                    (Proto::Mbrtu, rtu::encode(unit, &pdu), Some(text))
                }
                None => (Proto::Data, bytes, None),
            },
            _ => (Proto::Data, bytes, None),
        };
        let mut p = Packet::new(Dir::In, Part::Other, proto, bytes);
        if proto != Proto::Data && p.bytes.len() >= 2 {
            let head = if proto == Proto::Mbtcp { 6 } else { 0 };
            p.unit = p.bytes.get(head).copied();
            p.function = p.bytes.get(head + 1).copied();
        }
        p.dropped = Some(reason);
        p.label = "dropped";
        let bytes = if n == 1 { "byte" } else { "bytes" };
        let mut note = format!("dropped ({}): {detail} ({n} {bytes})", reason.word());
        if let Some(text) = text {
            note += &format!("; ASCII on the wire: {text}");
        }
        p.note = Some(note);
        p
    }

    /// Dropped bytes that make a frame are shown as the `part` they would have had
    /// (a stale reply as a reply), so Wireshark decodes their values.
    pub(crate) fn shown_as(mut self, part: Part) -> Packet {
        if self.proto != Proto::Data {
            self.part = part;
        }
        self
    }

    /// The Enhanced Packet Block of this packet, on interface `iface` of the file.
    pub(crate) fn block(&self, iface: u32) -> Vec<u8> {
        let ports = match (self.part, self.ends) {
            (Part::Query, Some(e)) => Some((e.client.port(), MODBUS_PORT)),
            (Part::Reply, Some(e)) => Some((MODBUS_PORT, e.client.port())),
            (Part::Other, Some(e)) => Some((e.client.port(), MODBUS_PORT)),
            // A serial line has no ports: 0 on the side that asks.
            (Part::Query, None) => Some((0, MODBUS_PORT)),
            (Part::Reply, None) => Some((MODBUS_PORT, 0)),
            (Part::Other, None) => None,
        };
        let addresses = self.ends.map(|e| {
            let (c, s) = (plain(e.client.ip()), plain(e.server.ip()));
            match self.part {
                Part::Reply => (s, c),
                _ => (c, s),
            }
        });
        let mut data = pcapng::exported_pdu(&pcapng::Exported {
            dissector: self.proto.dissector(),
            addresses,
            ports,
        });
        data.extend(&self.bytes);
        let mut flags = match self.dir {
            Dir::In => pcapng::INBOUND,
            Dir::Out => pcapng::OUTBOUND,
            Dir::Neither => 0,
        };
        if matches!(self.dropped, Some(Reason::Crc | Reason::Lrc)) {
            flags |= pcapng::CRC_ERROR;
        }
        pcapng::packet(&pcapng::EnhancedPacket {
            interface: iface,
            at_us: self.at_us,
            data: &data,
            comment: self.note.as_deref(),
            flags,
        })
    }
}

/// An IPv4 address written as IPv6 (a dual-stack listener's) is given as IPv4.
fn plain(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(ip, IpAddr::V4),
        v4 => v4,
    }
}

/// An ASCII frame as text: CR and LF written as `\r` and `\n`, other bytes that are
/// not printable in hex.
pub(crate) fn ascii_text(wire: &[u8]) -> String {
    let mut s = String::with_capacity(wire.len() + 4);
    for &b in wire {
        match b {
            b'\r' => s.push_str("\\r"),
            b'\n' => s.push_str("\\n"),
            0x20..=0x7E => s.push(char::from(b)),
            _ => s.push_str(&format!("\\x{b:02X}")),
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tag_ports(block: &[u8]) -> Option<(u32, u32)> {
        let find = |tag: u16| {
            block
                .windows(4)
                .position(|w| w == [(tag >> 8) as u8, tag as u8, 0, 4])
                .map(|i| u32::from_be_bytes(block[i + 4..i + 8].try_into().unwrap()))
        };
        Some((find(25)?, find(26)?))
    }

    #[test]
    fn ascii_frames_go_to_the_rtu_dissector_with_their_text_in_the_comment() {
        let adu = Adu::build(0, 1, &[3, 0, 0, 0, 10]);
        let wire = ascii::encode(1, adu.pdu());
        let p = Packet::line_frame(Framing::Ascii, &adu, &wire, Dir::Out, Part::Query);
        assert_eq!(p.proto, Proto::Mbrtu);
        assert_eq!(p.bytes, rtu::encode(1, &[3, 0, 0, 0, 10]));
        assert_eq!(
            p.note.as_deref(),
            Some("ASCII on the wire: :01030000000AF2\\r\\n")
        );
        assert_eq!((p.unit, p.function), (Some(1), Some(3)));
        // RTU and MBAP go as they were on the wire.
        let rtu_wire = rtu::encode(1, adu.pdu());
        let p = Packet::line_frame(Framing::Rtu, &adu, &rtu_wire, Dir::Out, Part::Query);
        assert_eq!(
            (p.proto, &p.bytes, &p.note),
            (Proto::Mbrtu, &rtu_wire, &None)
        );
    }

    /// A packet filled again in place (the status page's) keeps nothing of the frame
    /// it was but its bytes' room, and filled as a frame equals one made afresh.
    #[test]
    fn a_cleared_packet_is_a_new_one_with_room_and_fills_as_one() {
        let adu = Adu::build(0, 1, &[3, 0, 0, 0, 10]);
        let wire = ascii::encode(1, adu.pdu());
        let mut p = Packet::line_frame(Framing::Ascii, &adu, &wire, Dir::Out, Part::Query);
        let addr: std::net::SocketAddr = "10.0.0.1:40000".parse().unwrap();
        (p.at_us, p.iface, p.conn, p.span) = (7, 2, Some(9), Some((1, 2)));
        p.ends = Some(Ends {
            client: addr,
            server: addr,
        });
        (p.dropped, p.label) = (Some(Reason::Crc), "gw->serial");
        p.bytes.reserve(64);
        let room = p.bytes.capacity();
        p.clear(Dir::In, Part::Reply);
        assert_eq!(
            p,
            Packet::new(Dir::In, Part::Reply, Proto::Data, Vec::new())
        );
        assert_eq!(p.bytes.capacity(), room, "the room is kept");
        for (framing, wire) in [
            (Framing::Mbap, adu.as_bytes().to_vec()),
            (Framing::Rtu, rtu::encode(1, adu.pdu())),
            (Framing::Ascii, wire.clone()),
        ] {
            p.clear(Dir::In, Part::Reply);
            p.set_line_frame(framing, &adu, &wire);
            assert_eq!(
                p,
                Packet::line_frame(framing, &adu, &wire, Dir::In, Part::Reply),
                "{framing:?}"
            );
        }
    }

    /// A query goes to port 502 and a reply comes from it, on the line (no addresses,
    /// port 0 for the side that asks) and on TCP (the client's own port).
    #[test]
    fn queries_go_to_502_and_replies_come_from_it() {
        let q = Packet::new(Dir::Out, Part::Query, Proto::Mbtcp, vec![0; 12]);
        assert_eq!(tag_ports(&q.block(1)), Some((0, 502)));
        let mut r = Packet::new(Dir::In, Part::Reply, Proto::Mbtcp, vec![0; 11]);
        assert_eq!(tag_ports(&r.block(1)), Some((502, 0)));
        r.ends = Some(Ends {
            client: "10.0.0.5:40000".parse().unwrap(),
            server: "[::ffff:10.0.0.1]:5020".parse().unwrap(),
        });
        let b = r.block(0);
        assert_eq!(tag_ports(&b), Some((502, 40000)));
        // Source 10.0.0.1 (the server, as IPv4), destination 10.0.0.5.
        let src = [0, 20, 0, 4, 10, 0, 0, 1];
        let dst = [0, 21, 0, 4, 10, 0, 0, 5];
        assert!(b.windows(8).any(|w| w == src) && b.windows(8).any(|w| w == dst));
        // Dropped bytes on a line carry no ports.
        let d = Packet::dropped(None, Reason::LostSync, vec![0xFF], false, "noise");
        assert_eq!(tag_ports(&d.block(1)), None);
    }

    #[test]
    fn dropped_bytes_say_why_and_keep_the_frame_they_make() {
        let stale = Adu::build(7, 1, &[3, 2, 0, 5]).as_bytes().to_vec();
        let p = Packet::dropped(
            Some(Framing::Mbap),
            Reason::Stale,
            stale.clone(),
            true,
            "a reply to a request already finished",
        );
        assert_eq!((p.proto, &p.bytes), (Proto::Mbtcp, &stale));
        assert_eq!((p.unit, p.function), (Some(1), Some(3)));
        assert_eq!(
            p.note.as_deref(),
            Some("dropped (stale): a reply to a request already finished (11 bytes)")
        );
        let mut bad = rtu::encode(1, &[3, 2, 0, 5]);
        bad[3] ^= 1;
        let p = Packet::dropped(Some(Framing::Rtu), Reason::Crc, bad, true, "CRC failed");
        assert_eq!(p.proto, Proto::Mbrtu);
        let flags = crate::ops::capture::pcapng::CRC_ERROR | crate::ops::capture::pcapng::INBOUND;
        assert!(p.block(1).windows(4).any(|w| w == flags.to_le_bytes()));
        let p = Packet::dropped(
            Some(Framing::Mbap),
            Reason::LostSync,
            vec![0xFF],
            false,
            "x",
        );
        assert_eq!(
            (p.proto, p.note.as_deref()),
            (Proto::Data, Some("dropped (lost sync): x (1 byte)"))
        );
    }
}
