//! The pcapng writer (docs/capture.md "The file"): pure, values in and bytes out, no
//! I/O and no clock. Blocks are written little-endian; each packet is the Wireshark
//! "exported PDU" link type, whose header names the dissector (`mbtcp`, `mbrtu`,
//! `data`) and, where there are any, the addresses and ports (docs/design.md §6).
//!
//! The block layouts are those of the pcapng specification (IETF draft
//! draft-ietf-opsawg-pcapng, sections 4.1 to 4.6); the exported-PDU tags are those of
//! Wireshark's `epan/exported_pdu.h` (tag numbers frozen there: 0 end, 12 dissector
//! name, 20 and 21 IPv4 source and destination, 22 and 23 IPv6, 24 port type, 25 and
//! 26 source and destination port).
//!
//! ```
//! use mbgate::ops::capture::pcapng;
//! let mut file = pcapng::section_header("mbgate");
//! file.extend(pcapng::interface("/dev/ttyUSB0", "line 0"));
//! let mut data = pcapng::exported_pdu(&pcapng::Exported { dissector: "mbrtu", ..Default::default() });
//! data.extend([0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87]);
//! file.extend(pcapng::packet(&pcapng::EnhancedPacket { data: &data, ..Default::default() }));
//! assert_eq!(file.len() % 4, 0);
//! ```

use std::net::IpAddr;

/// `LINKTYPE_WIRESHARK_UPPER_PDU`: each packet starts with exported-PDU tags.
pub(crate) const LINKTYPE_WIRESHARK_UPPER_PDU: u16 = 252;

const SECTION_HEADER: u32 = 0x0A0D_0D0A;
const INTERFACE_DESCRIPTION: u32 = 1;
const INTERFACE_STATISTICS: u32 = 5;
const ENHANCED_PACKET: u32 = 6;
const BYTE_ORDER_MAGIC: u32 = 0x1A2B_3C4D;

const OPT_END: u16 = 0;
const OPT_COMMENT: u16 = 1;
const SHB_USERAPPL: u16 = 4;
const IF_NAME: u16 = 2;
const IF_DESCRIPTION: u16 = 3;
const IF_TSRESOL: u16 = 9;
const EPB_FLAGS: u16 = 2;
const ISB_STARTTIME: u16 = 2;
const ISB_ENDTIME: u16 = 3;
const ISB_IFRECV: u16 = 4;
const ISB_IFDROP: u16 = 5;

/// `epb_flags`: the packet came in to the gateway.
pub const INBOUND: u32 = 0b01;
/// `epb_flags`: the packet went out of the gateway.
pub const OUTBOUND: u32 = 0b10;
/// `epb_flags`: a link-layer CRC error (bit 24; on a serial line, a CRC or LRC that
/// failed).
pub(crate) const CRC_ERROR: u32 = 1 << 24;

const TAG_END: u16 = 0;
const TAG_DISSECTOR_NAME: u16 = 12;
const TAG_IPV4_SRC: u16 = 20;
const TAG_IPV4_DST: u16 = 21;
const TAG_IPV6_SRC: u16 = 22;
const TAG_IPV6_DST: u16 = 23;
const TAG_PORT_TYPE: u16 = 24;
const TAG_SRC_PORT: u16 = 25;
const TAG_DST_PORT: u16 = 26;
/// `EXP_PDU_PT_TCP`.
const PORT_TYPE_TCP: u32 = 2;

fn pad4(n: usize) -> usize {
    (4 - n % 4) % 4
}

/// Appends option `code` with `value`, padded to 32 bits.
fn option(out: &mut Vec<u8>, code: u16, value: &[u8]) {
    // Option values are at most 65535 bytes: longer text is cut (a comment never is
    // that long).
    let value = &value[..value.len().min(usize::from(u16::MAX))];
    out.extend(code.to_le_bytes());
    out.extend((value.len() as u16).to_le_bytes());
    out.extend(value);
    out.extend(std::iter::repeat_n(0, pad4(value.len())));
}

/// A whole block: type, total length, `body` (padded), total length again.
fn block(kind: u32, mut body: Vec<u8>) -> Vec<u8> {
    body.extend(std::iter::repeat_n(0, pad4(body.len())));
    let total = (12 + body.len()) as u32;
    let mut out = Vec::with_capacity(total as usize);
    out.extend(kind.to_le_bytes());
    out.extend(total.to_le_bytes());
    out.extend(body);
    out.extend(total.to_le_bytes());
    out
}

/// The Section Header Block that starts a file, naming the application.
pub fn section_header(application: &str) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend(BYTE_ORDER_MAGIC.to_le_bytes());
    body.extend(1u16.to_le_bytes());
    body.extend(0u16.to_le_bytes());
    // The section's length is not known: -1.
    body.extend((-1i64).to_le_bytes());
    option(&mut body, SHB_USERAPPL, application.as_bytes());
    option(&mut body, OPT_END, &[]);
    block(SECTION_HEADER, body)
}

/// An Interface Description Block: exported PDUs, no snapshot limit, timestamps in
/// microseconds. Interfaces are numbered in the order their blocks come, from 0.
pub fn interface(name: &str, description: &str) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend(LINKTYPE_WIRESHARK_UPPER_PDU.to_le_bytes());
    body.extend(0u16.to_le_bytes());
    body.extend(0u32.to_le_bytes());
    option(&mut body, IF_NAME, name.as_bytes());
    if !description.is_empty() {
        option(&mut body, IF_DESCRIPTION, description.as_bytes());
    }
    // 10^-6 s.
    option(&mut body, IF_TSRESOL, &[6]);
    option(&mut body, OPT_END, &[]);
    block(INTERFACE_DESCRIPTION, body)
}

/// One packet (an Enhanced Packet Block).
#[derive(Debug, Default, Clone, Copy)]
pub struct EnhancedPacket<'a> {
    /// The interface, by its place among the Interface Description Blocks.
    pub interface: u32,
    /// Microseconds since the Unix epoch.
    pub at_us: u64,
    /// What the interface's link type carries: exported-PDU tags, then the PDU.
    pub data: &'a [u8],
    /// `opt_comment`, if any.
    pub comment: Option<&'a str>,
    /// `epb_flags` ([`INBOUND`], [`OUTBOUND`], [`CRC_ERROR`]); 0 writes none.
    pub flags: u32,
}

/// The Enhanced Packet Block of `p`.
pub fn packet(p: &EnhancedPacket<'_>) -> Vec<u8> {
    let mut body = Vec::with_capacity(20 + p.data.len() + 8);
    body.extend(p.interface.to_le_bytes());
    body.extend(((p.at_us >> 32) as u32).to_le_bytes());
    body.extend((p.at_us as u32).to_le_bytes());
    body.extend((p.data.len() as u32).to_le_bytes());
    body.extend((p.data.len() as u32).to_le_bytes());
    body.extend(p.data);
    body.extend(std::iter::repeat_n(0, pad4(p.data.len())));
    let comment = p.comment.filter(|c| !c.is_empty());
    if comment.is_some() || p.flags != 0 {
        if let Some(c) = comment {
            option(&mut body, OPT_COMMENT, c.as_bytes());
        }
        if p.flags != 0 {
            option(&mut body, EPB_FLAGS, &p.flags.to_le_bytes());
        }
        option(&mut body, OPT_END, &[]);
    }
    block(ENHANCED_PACKET, body)
}

/// What an interface saw over a capture, for its Interface Statistics Block.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct Statistics {
    /// The interface, by its place among the Interface Description Blocks.
    pub(crate) interface: u32,
    /// When the capture started and ended, in microseconds since the Unix epoch.
    pub(crate) start_us: u64,
    /// See `start_us`; also the block's own timestamp.
    pub(crate) end_us: u64,
    /// Packets written for this interface.
    pub(crate) received: u64,
    /// Packets the capture had to drop for this interface (the reader was slow).
    pub(crate) dropped: u64,
}

fn timestamp(us: u64) -> [u8; 8] {
    let mut t = [0u8; 8];
    t[..4].copy_from_slice(&((us >> 32) as u32).to_le_bytes());
    t[4..].copy_from_slice(&(us as u32).to_le_bytes());
    t
}

/// The Interface Statistics Block of `s`.
pub(crate) fn statistics(s: &Statistics) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend(s.interface.to_le_bytes());
    body.extend(timestamp(s.end_us));
    option(&mut body, ISB_STARTTIME, &timestamp(s.start_us));
    option(&mut body, ISB_ENDTIME, &timestamp(s.end_us));
    option(&mut body, ISB_IFRECV, &s.received.to_le_bytes());
    option(&mut body, ISB_IFDROP, &s.dropped.to_le_bytes());
    option(&mut body, OPT_END, &[]);
    block(INTERFACE_STATISTICS, body)
}

/// The exported-PDU header of a packet: which dissector reads what follows, and
/// where it went from and to.
#[derive(Debug, Default, Clone, Copy)]
pub struct Exported<'a> {
    /// Wireshark's dissector: `mbtcp` (an MBAP frame), `mbrtu` (an RTU frame, CRC
    /// included), `data` (bytes as they are).
    pub dissector: &'a str,
    /// Source and destination addresses (both or neither; of one family, else
    /// neither is written).
    pub addresses: Option<(IpAddr, IpAddr)>,
    /// Source and destination TCP ports. Wireshark's Modbus/TCP dissector tells a
    /// query (to port 502) from a response (from port 502) by them.
    pub ports: Option<(u16, u16)>,
}

fn tag(out: &mut Vec<u8>, tag: u16, value: &[u8]) {
    out.extend(tag.to_be_bytes());
    out.extend((value.len() as u16).to_be_bytes());
    out.extend(value);
}

/// The exported-PDU tags of `e`, in the order of their numbers, ending with the end
/// tag: the start of the packet's data, before the PDU itself. The dissector's name
/// is padded with zeros to 32 bits, the padding counted in its length (as Wireshark
/// writes it).
pub fn exported_pdu(e: &Exported<'_>) -> Vec<u8> {
    let mut out = Vec::with_capacity(64);
    let mut name = e.dissector.as_bytes().to_vec();
    name.extend(std::iter::repeat_n(0, pad4(name.len())));
    tag(&mut out, TAG_DISSECTOR_NAME, &name);
    match e.addresses {
        Some((IpAddr::V4(s), IpAddr::V4(d))) => {
            tag(&mut out, TAG_IPV4_SRC, &s.octets());
            tag(&mut out, TAG_IPV4_DST, &d.octets());
        }
        Some((IpAddr::V6(s), IpAddr::V6(d))) => {
            tag(&mut out, TAG_IPV6_SRC, &s.octets());
            tag(&mut out, TAG_IPV6_DST, &d.octets());
        }
        _ => {}
    }
    if let Some((s, d)) = e.ports {
        tag(&mut out, TAG_PORT_TYPE, &PORT_TYPE_TCP.to_be_bytes());
        tag(&mut out, TAG_SRC_PORT, &u32::from(s).to_be_bytes());
        tag(&mut out, TAG_DST_PORT, &u32::from(d).to_be_bytes());
    }
    tag(&mut out, TAG_END, &[]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blocks of a file: (type, body), checking each one's two lengths agree and
    /// that it is a multiple of 32 bits.
    fn blocks(mut file: &[u8]) -> Vec<(u32, Vec<u8>)> {
        let mut out = Vec::new();
        let word = |b: &[u8], at: usize| u32::from_le_bytes(b[at..at + 4].try_into().unwrap());
        while !file.is_empty() {
            let (kind, total) = (word(file, 0), word(file, 4) as usize);
            assert_eq!(total % 4, 0, "block {kind:#x} of {total} bytes");
            assert_eq!(word(file, total - 4), total as u32, "trailing length");
            out.push((kind, file[8..total - 4].to_vec()));
            file = &file[total..];
        }
        out
    }

    /// Options as (code, value), until the end option.
    fn options(mut b: &[u8]) -> Vec<(u16, Vec<u8>)> {
        let mut out = Vec::new();
        loop {
            let code = u16::from_le_bytes([b[0], b[1]]);
            let len = usize::from(u16::from_le_bytes([b[2], b[3]]));
            if code == OPT_END {
                assert_eq!(len, 0);
                assert_eq!(b.len(), 4, "nothing after the end option");
                return out;
            }
            out.push((code, b[4..4 + len].to_vec()));
            b = &b[4 + len + pad4(len)..];
        }
    }

    #[test]
    fn a_section_header_and_an_interface_as_the_specification_lays_them_out() {
        let shb = section_header("mbgate 0.1.0");
        let b = blocks(&shb);
        assert_eq!(b.len(), 1);
        let (kind, body) = &b[0];
        assert_eq!(*kind, SECTION_HEADER);
        assert_eq!(
            &body[..4],
            &[0x4D, 0x3C, 0x2B, 0x1A],
            "byte-order magic, LE"
        );
        assert_eq!(&body[4..8], &[1, 0, 0, 0], "version 1.0");
        assert_eq!(&body[8..16], &[0xFF; 8], "length unknown");
        assert_eq!(
            options(&body[16..]),
            [(SHB_USERAPPL, b"mbgate 0.1.0".to_vec())]
        );

        let idb = interface("/dev/ttyUSB0", "line 0: rtu");
        let (kind, body) = &blocks(&idb)[0];
        assert_eq!(*kind, INTERFACE_DESCRIPTION);
        assert_eq!(&body[..8], &[252, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(
            options(&body[8..]),
            [
                (IF_NAME, b"/dev/ttyUSB0".to_vec()),
                (IF_DESCRIPTION, b"line 0: rtu".to_vec()),
                (IF_TSRESOL, vec![6]),
            ]
        );
    }

    #[test]
    fn a_packet_carries_its_time_in_microseconds_its_data_padded_and_its_options() {
        let at_us = 1_700_000_000_123_456u64;
        let data = [1u8, 2, 3, 4, 5];
        let epb = packet(&EnhancedPacket {
            interface: 2,
            at_us,
            data: &data,
            comment: Some("dropped (CRC): a reply whose check failed"),
            flags: INBOUND | CRC_ERROR,
        });
        let (kind, body) = &blocks(&epb)[0];
        assert_eq!(*kind, ENHANCED_PACKET);
        let word = |at: usize| u32::from_le_bytes(body[at..at + 4].try_into().unwrap());
        assert_eq!(word(0), 2);
        assert_eq!((u64::from(word(4)) << 32) | u64::from(word(8)), at_us);
        assert_eq!((word(12), word(16)), (5, 5), "captured and original length");
        assert_eq!(&body[20..25], &data);
        assert_eq!(&body[25..28], &[0, 0, 0], "padded to 32 bits");
        assert_eq!(
            options(&body[28..]),
            [
                (
                    OPT_COMMENT,
                    b"dropped (CRC): a reply whose check failed".to_vec()
                ),
                (EPB_FLAGS, (INBOUND | CRC_ERROR).to_le_bytes().to_vec()),
            ]
        );
        // No options at all: the block ends with the data.
        let bare = packet(&EnhancedPacket {
            data: &data[..4],
            ..EnhancedPacket::default()
        });
        assert_eq!(blocks(&bare)[0].1.len(), 24);
    }

    #[test]
    fn interface_statistics_say_what_was_written_and_dropped() {
        let isb = statistics(&Statistics {
            interface: 1,
            start_us: 10,
            end_us: (7 << 32) | 20,
            received: 300,
            dropped: 4,
        });
        let (kind, body) = &blocks(&isb)[0];
        assert_eq!(*kind, INTERFACE_STATISTICS);
        assert_eq!(&body[..12], &[1, 0, 0, 0, 7, 0, 0, 0, 20, 0, 0, 0]);
        let o = options(&body[12..]);
        assert_eq!(o[2], (ISB_IFRECV, 300u64.to_le_bytes().to_vec()));
        assert_eq!(o[3], (ISB_IFDROP, 4u64.to_le_bytes().to_vec()));
    }

    /// The tags Wireshark's exported-PDU dissector reads, big-endian, in the order of
    /// their numbers, the dissector's name zero-padded to 32 bits.
    #[test]
    fn exported_pdu_tags_byte_for_byte() {
        let tcp = exported_pdu(&Exported {
            dissector: "mbtcp",
            addresses: Some(([10, 0, 0, 5].into(), [10, 0, 0, 1].into())),
            ports: Some((40000, 502)),
        });
        let want = crate::frame::hex::parse(
            "00 0C 00 08 6D 62 74 63 70 00 00 00 \
             00 14 00 04 0A 00 00 05  00 15 00 04 0A 00 00 01 \
             00 18 00 04 00 00 00 02  00 19 00 04 00 00 9C 40  00 1A 00 04 00 00 01 F6 \
             00 00 00 00",
        );
        assert_eq!(tcp, want);
        let data = exported_pdu(&Exported {
            dissector: "data",
            ..Exported::default()
        });
        assert_eq!(
            data,
            crate::frame::hex::parse("00 0C 00 04 64 61 74 61 00 00 00 00")
        );
        // Addresses of two families are left out rather than written half.
        let mixed = exported_pdu(&Exported {
            dissector: "mbrtu",
            addresses: Some(([127, 0, 0, 1].into(), std::net::Ipv6Addr::LOCALHOST.into())),
            ports: None,
        });
        assert_eq!(mixed.len(), 4 + 8 + 4);
    }
}
