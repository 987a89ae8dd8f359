//! The pcapng reader: pure, bytes in and records out, no I/O. It reads what the writer
//! beside it (`pcapng.rs`) writes, and what other writers (tshark, dumpcap, mergecap)
//! make of it: either byte order, several sections, any `if_tsresol` and
//! `if_tsoffset`. It never panics: damage stops the reading at the block where it is,
//! and says where and why, with everything before it kept (docs/simulator.md
//! "Replaying a device").
//!
//! [`Blocks`] reads one block at a time, so a caller may hold one block of a file of
//! any size (the replay streams its files); [`read`] reads a file held whole.
//!
//! The block layouts are those of the pcapng specification (IETF draft
//! draft-ietf-opsawg-pcapng, sections 3 and 4); the exported-PDU tags those of
//! Wireshark's `epan/exported_pdu.h`, as in `pcapng.rs`.
//!
//! ```
//! use mbgate::ops::capture::{pcapng, pcapng_read};
//! let mut file = pcapng::section_header("mbgate");
//! file.extend(pcapng::interface("/dev/ttyUSB0", ""));
//! let mut data = pcapng::exported_pdu(&pcapng::Exported { dissector: "mbrtu", ..Default::default() });
//! data.extend([0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87]);
//! file.extend(pcapng::packet(&pcapng::EnhancedPacket { data: &data, at_us: 7, flags: pcapng::OUTBOUND, ..Default::default() }));
//! let read = pcapng_read::read(&file).unwrap();
//! assert_eq!((read.packets.len(), read.damage), (1, None));
//! let p = &read.packets[0];
//! assert_eq!((p.at_us, p.flags, read.interfaces[p.interface].name.as_str()), (7, pcapng::OUTBOUND, "/dev/ttyUSB0"));
//! let e = pcapng_read::exported(p.data).unwrap();
//! assert_eq!((e.dissector.as_str(), e.payload.len()), ("mbrtu", 8));
//! ```

use std::fmt;

const SECTION_HEADER: u32 = 0x0A0D_0D0A;
const INTERFACE_DESCRIPTION: u32 = 1;
const ENHANCED_PACKET: u32 = 6;
const BYTE_ORDER_MAGIC: u32 = 0x1A2B_3C4D;

const OPT_END: u16 = 0;
const OPT_COMMENT: u16 = 1;
const IF_NAME: u16 = 2;
const IF_DESCRIPTION: u16 = 3;
const IF_TSRESOL: u16 = 9;
const IF_TSOFFSET: u16 = 14;
const EPB_FLAGS: u16 = 2;

/// The most interfaces a file may declare, over all its sections. mbgate's capture has
/// one for the TCP side and one a line; every one takes memory to read the file, so a
/// file declaring more is damaged there, not read into memory without end.
pub(crate) const MAX_INTERFACES: usize = 4096;

/// Where reading stopped, and why: the byte offset in the file of the block (or the
/// part of it) that could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("at byte {offset}: {reason}")]
pub struct Damage {
    /// Bytes from the start of the file.
    pub offset: usize,
    /// What was wrong there.
    pub(crate) reason: Unreadable,
}

/// Why a file could not be read (further).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Unreadable {
    /// The file does not start with a pcapng Section Header Block: another format (a
    /// classic pcap file, text), or not a capture at all.
    NotPcapng,
    /// The file ends inside a block (a capture cut short: a full disk, a copy taken
    /// while it was written).
    Truncated,
    /// A block's length is below 12 bytes, not a multiple of 4, or its two copies
    /// disagree.
    BadLength,
    /// A section header whose byte-order magic is neither order of 0x1A2B3C4D, or a
    /// major version other than 1.
    BadSection,
    /// A block's options run past its end.
    BadOptions,
    /// A packet names an interface no description block declared.
    UnknownInterface(u32),
    /// A packet's captured length runs past its block.
    BadPacketLength,
    /// More than [`MAX_INTERFACES`] interface description blocks.
    TooManyInterfaces,
}

impl fmt::Display for Unreadable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Unreadable::NotPcapng => f.write_str("not a pcapng file (no section header block)"),
            Unreadable::Truncated => f.write_str("the file ends inside a block (cut short)"),
            Unreadable::BadLength => f.write_str("a block length that cannot be (corrupt)"),
            Unreadable::BadSection => {
                f.write_str("a section header of unknown byte order or version")
            }
            Unreadable::BadOptions => f.write_str("options that run past their block (corrupt)"),
            Unreadable::UnknownInterface(i) => {
                write!(f, "a packet on interface {i}, never declared")
            }
            Unreadable::BadPacketLength => f.write_str("a packet longer than its block (corrupt)"),
            Unreadable::TooManyInterfaces => {
                write!(
                    f,
                    "more than {MAX_INTERFACES} interfaces (no capture has so many)"
                )
            }
        }
    }
}

/// An interface of the file (its description block).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileInterface {
    /// The link type (252: exported PDUs, as mbgate writes them).
    pub(crate) link_type: u16,
    /// `if_name`, empty if none.
    pub name: String,
    /// `if_description`, empty if none (mbgate's says a line's baud rate:
    /// `line 0: RTU, 19200 baud`).
    pub(crate) description: String,
    /// The section it belongs to, from 0: interfaces are numbered anew in each.
    pub(crate) section: usize,
    /// Ticks a second (`if_tsresol`; 10^6 by default).
    resolution: Resolution,
    /// Seconds added to each timestamp (`if_tsoffset`).
    offset_s: i64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Resolution {
    Decimal(u8),
    Binary(u8),
}

impl FileInterface {
    /// A timestamp of `ticks` on this interface, in microseconds since the epoch
    /// (saturating: a timestamp beyond 2^64 µs is no real one).
    fn micros(&self, ticks: u64) -> u64 {
        let t = u128::from(ticks);
        let us = match self.resolution {
            Resolution::Decimal(n) if n >= 6 => t / 10u128.saturating_pow(u32::from(n) - 6),
            Resolution::Decimal(n) => t.saturating_mul(10u128.pow(6 - u32::from(n))),
            Resolution::Binary(n) if n < 127 => t.saturating_mul(1_000_000) >> n,
            Resolution::Binary(_) => 0,
        };
        let offset = i128::from(self.offset_s) * 1_000_000;
        (us as i128)
            .saturating_add(offset)
            .clamp(0, i128::from(u64::MAX)) as u64
    }
}

/// One packet (an Enhanced Packet Block).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Record<'a> {
    /// Index into [`Read::interfaces`] (over all sections).
    pub interface: usize,
    /// Microseconds since the Unix epoch.
    pub at_us: u64,
    /// The captured bytes.
    pub data: &'a [u8],
    /// `epb_flags` (bit 0 inbound, bit 1 outbound), 0 when absent.
    pub flags: u32,
    /// `opt_comment`, the first if several.
    pub(crate) comment: Option<String>,
}

/// What a file held, up to its end or its damage.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Read<'a> {
    /// The interfaces of every section, in the order of their blocks.
    pub interfaces: Vec<FileInterface>,
    /// The packets, in the order of the file.
    pub packets: Vec<Record<'a>>,
    /// Where reading stopped before the end, if it did.
    pub damage: Option<Damage>,
}

#[derive(Debug, Clone, Copy)]
struct Order {
    big: bool,
}

const LE: Order = Order { big: false };

impl Order {
    fn u16(self, b: &[u8], at: usize) -> Option<u16> {
        let v: [u8; 2] = b.get(at..at + 2)?.try_into().ok()?;
        Some(if self.big {
            u16::from_be_bytes(v)
        } else {
            u16::from_le_bytes(v)
        })
    }
    fn u32(self, b: &[u8], at: usize) -> Option<u32> {
        let v: [u8; 4] = b.get(at..at.checked_add(4)?)?.try_into().ok()?;
        Some(if self.big {
            u32::from_be_bytes(v)
        } else {
            u32::from_le_bytes(v)
        })
    }
    fn u64(self, b: &[u8], at: usize) -> Option<u64> {
        let v: [u8; 8] = b.get(at..at + 8)?.try_into().ok()?;
        Some(if self.big {
            u64::from_be_bytes(v)
        } else {
            u64::from_le_bytes(v)
        })
    }
}

/// The options in `b`: (code, value), until the end option or the end of `b`.
fn options(order: Order, mut b: &[u8]) -> Option<Vec<(u16, &[u8])>> {
    let mut out = Vec::new();
    while b.len() >= 4 {
        let code = order.u16(b, 0)?;
        let len = usize::from(order.u16(b, 2)?);
        if code == OPT_END {
            break;
        }
        let value = b.get(4..4 + len)?;
        out.push((code, value));
        let next = (4 + len + 3) & !3;
        b = b.get(next..).unwrap_or(&[]);
    }
    Some(out)
}

/// The reader between two blocks: where it is in the file, the byte order of the
/// section, and the interfaces declared so far. Feed it each block in turn: the first
/// bytes to [`Blocks::length`], then the whole block to [`Blocks::block`].
#[derive(Debug, Clone)]
pub(crate) struct Blocks {
    /// The interfaces of every section, in the order of their blocks.
    pub interfaces: Vec<FileInterface>,
    /// The interfaces of the current section: their index in `interfaces`.
    section: Vec<usize>,
    sections: usize,
    order: Order,
    /// The offset in the file of the block to come.
    at: usize,
}

impl Default for Blocks {
    fn default() -> Self {
        Blocks {
            interfaces: Vec::new(),
            section: Vec::new(),
            sections: 0,
            order: LE,
            at: 0,
        }
    }
}

/// The bytes [`Blocks::length`] reads of a block: its type and its length (and for a
/// section header, its byte-order magic).
pub(crate) const BLOCK_HEAD: usize = 12;

impl Blocks {
    /// Damage at the block to come.
    pub(crate) fn damage(&self, reason: Unreadable) -> Damage {
        Damage {
            offset: self.at,
            reason,
        }
    }

    /// Is `d` a refusal of the whole file rather than damage after a good start? Only
    /// what its first block says refuses: it is no pcapng file, or of no version read
    /// here; a first block cut short or of an impossible length is damage like any.
    pub(crate) fn refuses(d: &Damage) -> bool {
        d.offset == 0 && !matches!(d.reason, Unreadable::Truncated | Unreadable::BadLength)
    }

    /// The length of the block to come, from its first bytes (`head`: the next
    /// [`BLOCK_HEAD`] of the file, fewer at its end): at least 12 and a multiple of 4.
    /// A section header sets the byte order from here on.
    pub(crate) fn length(&mut self, head: &[u8]) -> Result<usize, Damage> {
        let kind = LE.u32(head, 0);
        if self.at == 0 && kind != Some(SECTION_HEADER) {
            return Err(self.damage(Unreadable::NotPcapng));
        }
        if head.len() < BLOCK_HEAD {
            return Err(self.damage(Unreadable::Truncated));
        }
        if kind == Some(SECTION_HEADER) {
            self.order = match LE.u32(head, 8) {
                Some(BYTE_ORDER_MAGIC) => LE,
                Some(0x4D3C_2B1A) => Order { big: true },
                _ => return Err(self.damage(Unreadable::BadSection)),
            };
        }
        let total = self.order.u32(head, 4).map_or(0, |t| t as usize);
        if total < 12 || !total.is_multiple_of(4) {
            return Err(self.damage(Unreadable::BadLength));
        }
        Ok(total)
    }

    /// Reads the whole block `block` (its length as [`Blocks::length`] gave): a
    /// packet, or `None` for a block that is none (a section, an interface, a block a
    /// replay does not need). Moves on to the next block.
    pub(crate) fn block<'a>(&mut self, block: &'a [u8]) -> Result<Option<Record<'a>>, Damage> {
        let total = block.len();
        let order = self.order;
        if total < 12 || order.u32(block, total - 4).map(|t| t as usize) != Some(total) {
            return Err(self.damage(Unreadable::BadLength));
        }
        let kind = order.u32(block, 0).unwrap_or(0);
        let body = &block[8..total - 4];
        let result = match kind {
            SECTION_HEADER => {
                if order.u16(body, 4) != Some(1) {
                    Err(Unreadable::BadSection)
                } else {
                    self.section.clear();
                    self.sections += 1;
                    Ok(None)
                }
            }
            INTERFACE_DESCRIPTION if self.interfaces.len() >= MAX_INTERFACES => {
                Err(Unreadable::TooManyInterfaces)
            }
            INTERFACE_DESCRIPTION => {
                interface(order, body, self.sections.saturating_sub(1)).map(|i| {
                    self.section.push(self.interfaces.len());
                    self.interfaces.push(i);
                    None
                })
            }
            ENHANCED_PACKET => packet(order, body, &self.section, &self.interfaces).map(Some),
            // Statistics, name resolution, simple packets (no interface, no time),
            // custom blocks: nothing a replay needs.
            _ => Ok(None),
        };
        let record = result.map_err(|reason| self.damage(reason))?;
        self.at += total;
        Ok(record)
    }
}

/// Reads a whole file. `Err` when it is no pcapng file at all (its first block is no
/// section header, [`Blocks::refuses`]); otherwise everything up to the end, or up to
/// the damage, which [`Read::damage`] names.
pub fn read(file: &[u8]) -> Result<Read<'_>, Damage> {
    let mut blocks = Blocks::default();
    let mut packets = Vec::new();
    let mut damage = None;
    while blocks.at < file.len() {
        let rest = &file[blocks.at..];
        let step = blocks
            .length(&rest[..rest.len().min(BLOCK_HEAD)])
            .and_then(|total| match rest.get(..total) {
                Some(block) => blocks.block(block),
                None => Err(blocks.damage(Unreadable::Truncated)),
            });
        match step {
            Ok(p) => packets.extend(p),
            Err(d) if Blocks::refuses(&d) => return Err(d),
            Err(d) => {
                damage = Some(d);
                break;
            }
        }
    }
    Ok(Read {
        interfaces: blocks.interfaces,
        packets,
        damage,
    })
}

fn interface(order: Order, body: &[u8], section: usize) -> Result<FileInterface, Unreadable> {
    let link_type = order.u16(body, 0).ok_or(Unreadable::BadLength)?;
    if body.len() < 8 {
        return Err(Unreadable::BadLength);
    }
    let mut i = FileInterface {
        link_type,
        name: String::new(),
        description: String::new(),
        section,
        resolution: Resolution::Decimal(6),
        offset_s: 0,
    };
    for (code, value) in options(order, &body[8..]).ok_or(Unreadable::BadOptions)? {
        match code {
            IF_NAME => i.name = String::from_utf8_lossy(value).into_owned(),
            IF_DESCRIPTION => i.description = String::from_utf8_lossy(value).into_owned(),
            IF_TSRESOL => {
                if let Some(&r) = value.first() {
                    i.resolution = if r & 0x80 == 0 {
                        Resolution::Decimal(r)
                    } else {
                        Resolution::Binary(r & 0x7F)
                    };
                }
            }
            IF_TSOFFSET => {
                if let Some(v) = order.u64(value, 0) {
                    i.offset_s = v as i64;
                }
            }
            _ => {}
        }
    }
    Ok(i)
}

fn packet<'a>(
    order: Order,
    body: &'a [u8],
    section: &[usize],
    interfaces: &[FileInterface],
) -> Result<Record<'a>, Unreadable> {
    let word = |at| order.u32(body, at).ok_or(Unreadable::BadLength);
    let id = word(0)?;
    let index = *section
        .get(id as usize)
        .ok_or(Unreadable::UnknownInterface(id))?;
    let ticks = (u64::from(word(4)?) << 32) | u64::from(word(8)?);
    let captured = word(12)? as usize;
    let end = 20usize
        .checked_add(captured)
        .filter(|&e| e <= body.len())
        .ok_or(Unreadable::BadPacketLength)?;
    let data = &body[20..end];
    let padded = (end + 3) & !3;
    let mut record = Record {
        interface: index,
        at_us: interfaces[index].micros(ticks),
        data,
        flags: 0,
        comment: None,
    };
    let opts = body.get(padded..).unwrap_or(&[]);
    for (code, value) in options(order, opts).ok_or(Unreadable::BadOptions)? {
        match code {
            OPT_COMMENT if record.comment.is_none() => {
                record.comment = Some(String::from_utf8_lossy(value).into_owned());
            }
            EPB_FLAGS => record.flags = order.u32(value, 0).unwrap_or(0),
            _ => {}
        }
    }
    Ok(record)
}

/// An exported PDU (link type 252): which dissector reads it, the TCP ports if
/// given, and the PDU.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExportedPdu<'a> {
    /// The dissector's name (`mbtcp`, `mbrtu`, `data`), its zero padding removed.
    pub dissector: String,
    /// Source and destination ports, where the tags give them.
    pub(crate) ports: Option<(u32, u32)>,
    /// What follows the tags.
    pub payload: &'a [u8],
}

const TAG_END: u16 = 0;
const TAG_DISSECTOR_NAME: u16 = 12;
const TAG_SRC_PORT: u16 = 25;
const TAG_DST_PORT: u16 = 26;

/// The exported-PDU tags of `data` (big-endian, as Wireshark writes them) and the
/// PDU after them; `None` if the tags run past the data or never end.
pub fn exported(data: &[u8]) -> Option<ExportedPdu<'_>> {
    let be = Order { big: true };
    let mut at = 0usize;
    let mut dissector = String::new();
    let (mut src, mut dst) = (None, None);
    loop {
        let tag = be.u16(data, at)?;
        let len = usize::from(be.u16(data, at + 2)?);
        let value = data.get(at + 4..at + 4 + len)?;
        at += 4 + len;
        match tag {
            TAG_END => break,
            TAG_DISSECTOR_NAME => {
                let name = value.split(|&b| b == 0).next().unwrap_or(&[]);
                dissector = String::from_utf8_lossy(name).into_owned();
            }
            TAG_SRC_PORT => src = be.u32(value, 0),
            TAG_DST_PORT => dst = be.u32(value, 0),
            _ => {}
        }
    }
    Some(ExportedPdu {
        dissector,
        ports: src.zip(dst),
        payload: &data[at..],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ops::capture::pcapng;

    fn file() -> Vec<u8> {
        let mut f = pcapng::section_header("mbgate");
        f.extend(pcapng::interface("tcp", ""));
        f.extend(pcapng::interface("/dev/ttyUSB0", "line 0"));
        for (i, at) in [(1u32, 10u64), (1, 20), (0, 30)] {
            let mut data = pcapng::exported_pdu(&pcapng::Exported {
                dissector: "mbrtu",
                ports: Some((0, 502)),
                ..Default::default()
            });
            data.extend([1, 3, 0, 0, 0, 1, 0x84, 0x0A]);
            f.extend(pcapng::packet(&pcapng::EnhancedPacket {
                interface: i,
                at_us: at,
                data: &data,
                comment: Some("a note"),
                flags: pcapng::OUTBOUND,
            }));
        }
        f.extend(pcapng::statistics(&pcapng::Statistics::default()));
        f
    }

    #[test]
    fn reads_back_what_the_writer_wrote() {
        let f = file();
        let r = read(&f).unwrap();
        assert_eq!(r.damage, None);
        assert_eq!(r.interfaces.len(), 2);
        assert_eq!(r.interfaces[1].name, "/dev/ttyUSB0");
        assert_eq!(r.interfaces[1].link_type, 252);
        let got: Vec<_> = r.packets.iter().map(|p| (p.interface, p.at_us)).collect();
        assert_eq!(got, [(1, 10), (1, 20), (0, 30)]);
        let p = &r.packets[0];
        assert_eq!((p.flags, p.comment.as_deref()), (2, Some("a note")));
        let e = exported(p.data).unwrap();
        assert_eq!(e.dissector, "mbrtu");
        assert_eq!(e.ports, Some((0, 502)));
        assert_eq!(e.payload, [1, 3, 0, 0, 0, 1, 0x84, 0x0A]);
    }

    #[test]
    fn damage_keeps_what_came_before_and_says_where() {
        let f = file();
        // Blocks: section, two interfaces, three packets, statistics.
        let blocks = offsets(&f);
        assert_eq!(blocks.len(), 7);
        // Cut inside the third packet: two packets, and the third's offset.
        let cut = read(&f[..blocks[5] + 10]).unwrap();
        assert_eq!(cut.packets.len(), 2);
        assert_eq!(
            cut.damage,
            Some(Damage {
                offset: blocks[5],
                reason: Unreadable::Truncated
            })
        );
        // A block's length broken: the packets before it.
        let mut bad = f.clone();
        bad[blocks[4] + 4] = 3;
        let r = read(&bad).unwrap();
        assert_eq!(r.packets.len(), 1);
        let d = r.damage.unwrap();
        assert_eq!((d.offset, d.reason), (blocks[4], Unreadable::BadLength));
        assert_eq!(
            d.to_string(),
            format!(
                "at byte {}: a block length that cannot be (corrupt)",
                blocks[4]
            )
        );
        // A packet on an interface never declared.
        let mut bad = f.clone();
        bad[blocks[3] + 8] = 9;
        let d = read(&bad).unwrap().damage.unwrap();
        assert_eq!(
            (d.offset, d.reason),
            (blocks[3], Unreadable::UnknownInterface(9))
        );
        // Not pcapng at all.
        assert_eq!(
            read(b"\xd4\xc3\xb2\xa1 classic pcap").unwrap_err(),
            Damage {
                offset: 0,
                reason: Unreadable::NotPcapng
            }
        );
        assert_eq!(read(b"").unwrap().packets.len(), 0);
    }

    /// The offsets of the blocks of `f`.
    fn offsets(f: &[u8]) -> Vec<usize> {
        let mut out = Vec::new();
        let mut at = 0;
        while at < f.len() {
            out.push(at);
            at += u32::from_le_bytes(f[at + 4..at + 8].try_into().unwrap()) as usize;
        }
        out
    }

    #[test]
    fn big_endian_sections_and_other_resolutions() {
        // A big-endian section (as a big-endian host writes it), nanosecond ticks.
        let mut f = Vec::new();
        let be_block = |kind: u32, body: &[u8]| {
            let total = (12 + body.len()) as u32;
            let mut b = kind.to_be_bytes().to_vec();
            b.extend(total.to_be_bytes());
            b.extend(body);
            b.extend(total.to_be_bytes());
            b
        };
        let mut shb = BYTE_ORDER_MAGIC.to_be_bytes().to_vec();
        shb.extend(1u16.to_be_bytes());
        shb.extend(0u16.to_be_bytes());
        shb.extend((-1i64).to_be_bytes());
        f.extend(be_block(SECTION_HEADER, &shb));
        let mut idb = 252u16.to_be_bytes().to_vec();
        idb.extend([0, 0, 0, 0, 0, 0]);
        idb.extend(IF_TSRESOL.to_be_bytes());
        idb.extend(1u16.to_be_bytes());
        idb.extend([9, 0, 0, 0]);
        f.extend(be_block(INTERFACE_DESCRIPTION, &idb));
        let mut epb = 0u32.to_be_bytes().to_vec();
        let ns = 5_000_123_456u64;
        epb.extend(((ns >> 32) as u32).to_be_bytes());
        epb.extend((ns as u32).to_be_bytes());
        epb.extend(2u32.to_be_bytes());
        epb.extend(2u32.to_be_bytes());
        epb.extend([0xAB, 0xCD, 0, 0]);
        f.extend(be_block(ENHANCED_PACKET, &epb));
        // Then a little-endian section of mbgate's, numbering its interfaces anew.
        f.extend(file());
        let r = read(&f).unwrap();
        assert_eq!(r.damage, None);
        assert_eq!(r.packets[0].at_us, 5_000_123);
        assert_eq!(r.packets[0].data, [0xAB, 0xCD]);
        assert_eq!(
            r.packets[1].interface, 2,
            "the second section's interface 1"
        );
        assert_eq!(r.interfaces[2].section, 1);
    }

    /// What the fuzz target checks, on a few thousand damaged copies of a real file
    /// (every cut, and seeded byte changes): no panic, damage inside the file, every
    /// packet on a declared interface.
    #[test]
    fn any_cut_or_changed_byte_is_damage_never_a_panic() {
        let f = file();
        let check = |bytes: &[u8]| match read(bytes) {
            Err(d) => assert_eq!(d.offset, 0),
            Ok(r) => {
                assert!(r.damage.as_ref().is_none_or(|d| d.offset < bytes.len()));
                for p in &r.packets {
                    assert!(p.interface < r.interfaces.len());
                    let _ = exported(p.data);
                }
            }
        };
        for n in 0..=f.len() {
            check(&f[..n]);
        }
        let mut rng = fastrand::Rng::with_seed(7);
        for _ in 0..3000 {
            let mut g = f.clone();
            for _ in 0..rng.usize(1..4) {
                let i = rng.usize(..g.len());
                g[i] = rng.u8(..);
            }
            check(&g);
        }
    }

    /// Interfaces take memory to read a file: past [`MAX_INTERFACES`] they are damage,
    /// the packets before kept.
    #[test]
    fn more_interfaces_than_any_capture_has_are_damage() {
        let mut f = file();
        let before = read(&f).unwrap().packets.len();
        let at = f.len();
        for _ in 0..MAX_INTERFACES {
            f.extend(pcapng::interface("x", ""));
        }
        let r = read(&f).unwrap();
        assert_eq!(r.interfaces.len(), MAX_INTERFACES);
        assert_eq!(r.packets.len(), before);
        let d = r.damage.unwrap();
        assert_eq!(d.reason, Unreadable::TooManyInterfaces);
        assert_eq!(
            d.offset,
            at + (MAX_INTERFACES - 2) * pcapng::interface("x", "").len()
        );
    }

    /// Read one block at a time, a file gives what it gives read whole, and a block
    /// whose length claims more than the file holds is cut short, not waited for.
    #[test]
    fn blocks_one_at_a_time_read_as_the_whole() {
        let f = file();
        let mut blocks = Blocks::default();
        let mut packets = Vec::new();
        let mut at = 0;
        while at < f.len() {
            let total = blocks
                .length(&f[at..(at + BLOCK_HEAD).min(f.len())])
                .unwrap();
            packets.extend(blocks.block(&f[at..at + total]).unwrap());
            at += total;
        }
        let whole = read(&f).unwrap();
        assert_eq!(
            (packets, blocks.interfaces),
            (whole.packets, whole.interfaces)
        );
        let mut claims = pcapng::section_header("x");
        claims.extend([1, 0, 0, 0, 0xF0, 0xFF, 0xFF, 0xFF, 0, 0, 0, 0]);
        let d = read(&claims).unwrap().damage.unwrap();
        assert_eq!(d.reason, Unreadable::Truncated);
    }

    #[test]
    fn exported_tags_that_run_past_the_data_are_refused() {
        assert_eq!(exported(&[0, 12, 0, 9, b'm']), None);
        assert_eq!(exported(&[0, 12, 0, 0]), None, "no end tag");
        assert_eq!(exported(&[0, 0, 0, 0]).unwrap().payload, b"");
    }
}
