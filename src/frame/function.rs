//! The one table of function codes (Modbus Application Protocol V1.1b3 §6, docs/protocol.md
//! §1): each public code's request shape, reply shape, whether it only reads, and its
//! quantity limits. Every check derives from [`TABLE`]: TCP request validation and reply
//! matching ([`super::pdu`]), RTU frame lengths ([`super::rtu`]), the MBAP decoders'
//! plausible function codes, the simulator and the client. Adding a function code is
//! one entry here.
//!
//! Codes outside the table (user-defined 65..=72 and 100..=110, or anything else a
//! device speaks) stay representable: a gateway passes them through, and nothing is
//! known of their shape.
//!
//! ```
//! use mbgate::frame::function::{FunctionCode, Size};
//! let read = FunctionCode::READ_HOLDING_REGISTERS;
//! assert!(read.is_read());
//! assert_eq!(read.spec().unwrap().read.unwrap().max, 125);
//! // The reply to a read of 3 registers: `03 06` and six data bytes.
//! assert_eq!(read.reply_shape().size(&[0x03, 0x06]), Size::Exactly(8));
//! assert!(FunctionCode::new(0x41).spec().is_none(), "user-defined: passed through");
//! ```

use std::fmt;

/// A function code as it is on the wire: a request's (1..=127), or a reply's, whose high
/// bit marks an exception. Any byte is representable, so unknown and user-defined codes
/// pass through.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FunctionCode(u8);

impl FunctionCode {
    pub const READ_COILS: Self = Self(0x01);
    pub const READ_DISCRETE_INPUTS: Self = Self(0x02);
    pub const READ_HOLDING_REGISTERS: Self = Self(0x03);
    pub const READ_INPUT_REGISTERS: Self = Self(0x04);
    pub const WRITE_SINGLE_COIL: Self = Self(0x05);
    pub const WRITE_SINGLE_REGISTER: Self = Self(0x06);
    pub const READ_EXCEPTION_STATUS: Self = Self(0x07);
    pub const DIAGNOSTICS: Self = Self(0x08);
    pub const GET_COMM_EVENT_COUNTER: Self = Self(0x0B);
    pub const GET_COMM_EVENT_LOG: Self = Self(0x0C);
    pub const WRITE_MULTIPLE_COILS: Self = Self(0x0F);
    pub const WRITE_MULTIPLE_REGISTERS: Self = Self(0x10);
    pub const REPORT_SERVER_ID: Self = Self(0x11);
    pub const READ_FILE_RECORD: Self = Self(0x14);
    pub const WRITE_FILE_RECORD: Self = Self(0x15);
    pub const MASK_WRITE_REGISTER: Self = Self(0x16);
    pub const READ_WRITE_MULTIPLE_REGISTERS: Self = Self(0x17);
    pub const READ_FIFO_QUEUE: Self = Self(0x18);
    pub const ENCAPSULATED_INTERFACE: Self = Self(0x2B);

    /// The code of this wire byte, whatever it is.
    pub const fn new(byte: u8) -> Self {
        Self(byte)
    }

    /// The wire byte.
    pub const fn get(self) -> u8 {
        self.0
    }

    /// The high bit: an exception reply (V1.1b3 §7).
    pub const fn is_exception(self) -> bool {
        self.0 & 0x80 != 0
    }

    /// The request's code this reply code answers (the high bit cleared).
    pub const fn base(self) -> Self {
        Self(self.0 & 0x7F)
    }

    /// The exception reply's code for this request's code.
    pub const fn exception(self) -> Self {
        Self(self.0 | 0x80)
    }

    /// Can a master send it at all? 0 and the exception codes cannot be requests.
    pub const fn can_be_request(self) -> bool {
        self.0 != 0 && !self.is_exception()
    }

    /// Its row of [`TABLE`], if it is a public code (an exception code has none).
    pub fn spec(self) -> Option<&'static Spec> {
        let row = *INDEX.get(usize::from(self.0))?;
        TABLE.get(usize::from(row))
    }

    /// A public code of the application protocol (in [`TABLE`]).
    pub fn is_public(self) -> bool {
        self.spec().is_some()
    }

    /// Could a device send a reply with this code: a public one, or its exception form?
    pub fn is_reply(self) -> bool {
        self.base().is_public()
    }

    /// Does a request with this code only read, so that it may be resent after a
    /// timeout (docs/design.md §4 `retries`)? Anything unknown may act on the device.
    pub fn is_read(self) -> bool {
        self.spec().is_some_and(|s| s.access == Access::Read)
    }

    /// The shape of a request with this code ([`Shape::Open`] when unknown).
    pub fn request_shape(self) -> Shape {
        self.spec().map_or(Shape::Open, |s| s.request)
    }

    /// The shape of a normal reply with this code ([`Shape::Open`] when unknown).
    pub fn reply_shape(self) -> Shape {
        self.spec().map_or(Shape::Open, |s| s.reply)
    }
}

impl From<u8> for FunctionCode {
    fn from(byte: u8) -> Self {
        Self(byte)
    }
}

impl From<FunctionCode> for u8 {
    fn from(code: FunctionCode) -> u8 {
        code.0
    }
}

impl PartialEq<u8> for FunctionCode {
    fn eq(&self, other: &u8) -> bool {
        self.0 == *other
    }
}

impl fmt::Debug for FunctionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "FunctionCode({:#04x})", self.0)
    }
}

impl fmt::Display for FunctionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#04x}", self.0)
    }
}

/// The exception code of an exception reply (V1.1b3 §7). Any byte is representable; a
/// device may only answer with the [known](ExceptionCode::is_known) ones.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ExceptionCode(u8);

impl ExceptionCode {
    pub const ILLEGAL_FUNCTION: Self = Self(0x01);
    pub const ILLEGAL_DATA_ADDRESS: Self = Self(0x02);
    pub const ILLEGAL_DATA_VALUE: Self = Self(0x03);
    pub const SERVER_DEVICE_FAILURE: Self = Self(0x04);
    pub const ACKNOWLEDGE: Self = Self(0x05);
    pub const SERVER_DEVICE_BUSY: Self = Self(0x06);
    pub const MEMORY_PARITY_ERROR: Self = Self(0x08);
    /// The gateway cannot route the request: no serial port, or shutting down.
    pub const GATEWAY_PATH_UNAVAILABLE: Self = Self(0x0A);
    /// The device did not answer in time.
    pub const GATEWAY_TARGET_FAILED: Self = Self(0x0B);

    /// The code of this wire byte, whatever it is.
    pub const fn new(byte: u8) -> Self {
        Self(byte)
    }

    /// The wire byte.
    pub const fn get(self) -> u8 {
        self.0
    }

    /// Is it one of the codes of V1.1b3 §7, the only ones a device may answer with?
    pub fn is_known(self) -> bool {
        self.name().is_some()
    }

    /// Its name in V1.1b3 §7.
    pub fn name(self) -> Option<&'static str> {
        Some(match self {
            Self::ILLEGAL_FUNCTION => "illegal function",
            Self::ILLEGAL_DATA_ADDRESS => "illegal data address",
            Self::ILLEGAL_DATA_VALUE => "illegal data value",
            Self::SERVER_DEVICE_FAILURE => "server device failure",
            Self::ACKNOWLEDGE => "acknowledge",
            Self::SERVER_DEVICE_BUSY => "server device busy",
            Self::MEMORY_PARITY_ERROR => "memory parity error",
            Self::GATEWAY_PATH_UNAVAILABLE => "gateway path unavailable",
            Self::GATEWAY_TARGET_FAILED => "gateway target device failed to respond",
            _ => return None,
        })
    }
}

impl From<u8> for ExceptionCode {
    fn from(byte: u8) -> Self {
        Self(byte)
    }
}

impl From<ExceptionCode> for u8 {
    fn from(code: ExceptionCode) -> u8 {
        code.0
    }
}

impl PartialEq<u8> for ExceptionCode {
    fn eq(&self, other: &u8) -> bool {
        self.0 == *other
    }
}

impl fmt::Debug for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ExceptionCode({:#04x})", self.0)
    }
}

impl fmt::Display for ExceptionCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#04x}", self.0)
    }
}

/// What a request may do to the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// It only reads: resending it is harmless.
    Read,
    /// It may act on the device: resent only with `retry_writes`.
    Write,
}

/// What a quantity counts, and so how many data bytes it takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Item {
    /// Coils or discrete inputs, packed 8 to a byte.
    Bits,
    /// 16-bit registers, 2 bytes each.
    Registers,
}

impl Item {
    /// Data bytes for `qty` items.
    pub fn bytes(self, qty: usize) -> usize {
        match self {
            Item::Bits => qty.div_ceil(8),
            Item::Registers => 2 * qty,
        }
    }
}

/// A quantity field of a request: where it is (PDU offset of the 16-bit field) and its
/// limit (V1.1b3 §6). A quantity written is followed by the byte count of the data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Quantity {
    pub at: usize,
    pub max: u16,
    pub item: Item,
}

impl Quantity {
    /// The quantity in `pdu`, if the field is there.
    pub fn of(&self, pdu: &[u8]) -> Option<usize> {
        word(pdu, self.at)
    }

    /// Within 1..=max?
    pub fn allows(&self, qty: usize) -> bool {
        (1..=usize::from(self.max)).contains(&qty)
    }
}

/// How long a PDU with a given code is: the rule that delimits it. Sizes are PDU
/// bytes, function code included.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shape {
    /// Exactly this many bytes.
    Fixed(usize),
    /// A byte count at offset `at` (one byte, or two big-endian when `wide`) covers the
    /// rest; the count is at least `min` and a multiple of `step`.
    Counted {
        at: usize,
        wide: bool,
        min: usize,
        step: usize,
    },
    /// FC 08's reply: at least 5 bytes; as long as a 5-byte request it answers (most
    /// sub-functions echo theirs, V1.1b3 §6.8), otherwise only silence ends it.
    Diagnostic,
    /// Nothing is known: any size; on RTU, silence ends it.
    Open,
}

/// The size [`Shape::size`] finds at the front of a PDU.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Size {
    /// More bytes are needed to tell.
    More,
    /// The PDU is this many bytes.
    Exactly(usize),
    /// Nothing in the bytes tells (on RTU, silence ends it).
    Open,
}

const fn counted(at: usize, min: usize, step: usize) -> Shape {
    Shape::Counted {
        at,
        wide: false,
        min,
        step,
    }
}

impl Shape {
    /// The size of the PDU at the front of `pdu` (function code first), from its count
    /// field where it has one. For [`Shape::Diagnostic`], `request` is the request it
    /// answers.
    pub fn size_for(self, request: &[u8], pdu: &[u8]) -> Size {
        match self {
            Shape::Fixed(n) => Size::Exactly(n),
            Shape::Counted {
                at, wide: false, ..
            } => match pdu.get(at) {
                Some(&c) => Size::Exactly(at + 1 + usize::from(c)),
                None => Size::More,
            },
            Shape::Counted { at, wide: true, .. } => match word(pdu, at) {
                Some(c) => Size::Exactly(at + 2 + c),
                None => Size::More,
            },
            Shape::Diagnostic
                if request.first() == Some(&FunctionCode::DIAGNOSTICS.0) && request.len() == 5 =>
            {
                Size::Exactly(5)
            }
            Shape::Diagnostic | Shape::Open => Size::Open,
        }
    }

    /// [`size_for`](Shape::size_for) without a request.
    pub fn size(self, pdu: &[u8]) -> Size {
        self.size_for(&[], pdu)
    }

    /// Is `pdu` a whole PDU of this shape (the count fields' own limits included)?
    pub fn fits(self, pdu: &[u8]) -> bool {
        match self {
            Shape::Fixed(n) => pdu.len() == n,
            Shape::Counted {
                at,
                wide,
                min,
                step,
            } => {
                let count = if wide {
                    word(pdu, at)
                } else {
                    pdu.get(at).map(|&c| usize::from(c))
                };
                let head = at + if wide { 2 } else { 1 };
                count.is_some_and(|c| c >= min && c % step == 0 && pdu.len() == head + c)
            }
            Shape::Diagnostic => pdu.len() >= 5,
            Shape::Open => true,
        }
    }
}

/// What a normal reply repeats of its request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Echo {
    /// Nothing (it carries data).
    No,
    /// The whole request.
    Whole,
    /// The request's first bytes: code, address and quantity.
    Prefix(usize),
}

/// One public function code: everything the gateway, the simulator and the client know
/// of it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Spec {
    pub code: FunctionCode,
    pub name: &'static str,
    pub access: Access,
    /// The request's size.
    pub request: Shape,
    /// What it reads: the reply's byte count is that many items.
    pub read: Option<Quantity>,
    /// What it writes: the byte count right after the field (at `at + 2`) covers that
    /// many items.
    pub write: Option<Quantity>,
    /// The 16-bit value at offset 3 of request and reply is FF00 or 0000 (FC 05).
    pub coil_value: bool,
    /// The normal reply's size.
    pub reply: Shape,
    pub echo: Echo,
}

const fn row(code: FunctionCode, name: &'static str, access: Access) -> Spec {
    Spec {
        code,
        name,
        access,
        request: Shape::Open,
        read: None,
        write: None,
        coil_value: false,
        reply: Shape::Open,
        echo: Echo::No,
    }
}

const fn qty(at: usize, max: u16, item: Item) -> Option<Quantity> {
    Some(Quantity { at, max, item })
}

use Access::{Read, Write};
use FunctionCode as F;

/// The public function codes of the Modbus Application Protocol V1.1b3 §6, with their
/// limits. The section of each row is in its name's comment.
pub const TABLE: &[Spec] = &[
    // §6.1, §6.2: quantity 1..=2000, the bits packed in the reply.
    Spec {
        request: Shape::Fixed(5),
        read: qty(3, 2000, Item::Bits),
        reply: counted(1, 1, 1),
        ..row(F::READ_COILS, "read coils", Read)
    },
    Spec {
        request: Shape::Fixed(5),
        read: qty(3, 2000, Item::Bits),
        reply: counted(1, 1, 1),
        ..row(F::READ_DISCRETE_INPUTS, "read discrete inputs", Read)
    },
    // §6.3, §6.4: quantity 1..=125.
    Spec {
        request: Shape::Fixed(5),
        read: qty(3, 125, Item::Registers),
        reply: counted(1, 2, 2),
        ..row(F::READ_HOLDING_REGISTERS, "read holding registers", Read)
    },
    Spec {
        request: Shape::Fixed(5),
        read: qty(3, 125, Item::Registers),
        reply: counted(1, 2, 2),
        ..row(F::READ_INPUT_REGISTERS, "read input registers", Read)
    },
    // §6.5: the value is FF00 (on) or 0000 (off); the reply echoes the request.
    Spec {
        request: Shape::Fixed(5),
        coil_value: true,
        reply: Shape::Fixed(5),
        echo: Echo::Whole,
        ..row(F::WRITE_SINGLE_COIL, "write single coil", Write)
    },
    // §6.6.
    Spec {
        request: Shape::Fixed(5),
        reply: Shape::Fixed(5),
        echo: Echo::Whole,
        ..row(F::WRITE_SINGLE_REGISTER, "write single register", Write)
    },
    // §6.7 (serial line only).
    Spec {
        request: Shape::Fixed(1),
        reply: Shape::Fixed(2),
        ..row(F::READ_EXCEPTION_STATUS, "read exception status", Read)
    },
    // §6.8 (serial line only): sub-functions of many shapes.
    Spec {
        reply: Shape::Diagnostic,
        ..row(F::DIAGNOSTICS, "diagnostics", Write)
    },
    // §6.9, §6.10 (serial line only).
    Spec {
        request: Shape::Fixed(1),
        reply: Shape::Fixed(5),
        ..row(F::GET_COMM_EVENT_COUNTER, "get comm event counter", Read)
    },
    Spec {
        request: Shape::Fixed(1),
        reply: counted(1, 0, 1),
        ..row(F::GET_COMM_EVENT_LOG, "get comm event log", Read)
    },
    // §6.11: quantity 1..=1968 (0x7B0).
    Spec {
        request: counted(5, 0, 1),
        write: qty(3, 1968, Item::Bits),
        reply: Shape::Fixed(5),
        echo: Echo::Prefix(5),
        ..row(F::WRITE_MULTIPLE_COILS, "write multiple coils", Write)
    },
    // §6.12: quantity 1..=123 (0x7B).
    Spec {
        request: counted(5, 0, 1),
        write: qty(3, 123, Item::Registers),
        reply: Shape::Fixed(5),
        echo: Echo::Prefix(5),
        ..row(
            F::WRITE_MULTIPLE_REGISTERS,
            "write multiple registers",
            Write,
        )
    },
    // §6.13 (serial line only).
    Spec {
        request: Shape::Fixed(1),
        reply: counted(1, 0, 1),
        ..row(F::REPORT_SERVER_ID, "report server id", Read)
    },
    // §6.14, §6.15: a byte count after the code covers the sub-requests.
    Spec {
        request: counted(1, 0, 1),
        reply: counted(1, 0, 1),
        ..row(F::READ_FILE_RECORD, "read file record", Read)
    },
    Spec {
        request: counted(1, 0, 1),
        reply: counted(1, 0, 1),
        ..row(F::WRITE_FILE_RECORD, "write file record", Write)
    },
    // §6.16: address, AND mask, OR mask; the reply echoes the request.
    Spec {
        request: Shape::Fixed(7),
        reply: Shape::Fixed(7),
        echo: Echo::Whole,
        ..row(F::MASK_WRITE_REGISTER, "mask write register", Write)
    },
    // §6.17: read 1..=125, write 1..=121 (0x79).
    Spec {
        request: counted(9, 0, 1),
        read: qty(3, 125, Item::Registers),
        write: qty(7, 121, Item::Registers),
        reply: counted(1, 2, 2),
        ..row(
            F::READ_WRITE_MULTIPLE_REGISTERS,
            "read/write multiple registers",
            Write,
        )
    },
    // §6.18: a FIFO pointer address; the reply's byte count is 16-bit.
    Spec {
        request: Shape::Fixed(3),
        reply: Shape::Counted {
            at: 1,
            wide: true,
            min: 2,
            step: 1,
        },
        ..row(F::READ_FIFO_QUEUE, "read fifo queue", Read)
    },
    // §6.19-§6.21: MEI types of their own shapes.
    row(
        F::ENCAPSULATED_INTERFACE,
        "encapsulated interface transport",
        Write,
    ),
];

/// Each request code's row in [`TABLE`] (`u8::MAX`: none), built when compiling, which
/// also refuses a table with a code twice or a code that cannot be a request.
const INDEX: [u8; 128] = {
    let mut index = [u8::MAX; 128];
    let mut row = 0;
    while row < TABLE.len() {
        let code = TABLE[row].code.0 as usize;
        assert!(code != 0 && code < 128, "a request's function code is 1..=127");
        assert!(index[code] == u8::MAX, "a function code in the table twice");
        index[code] = row as u8;
        row += 1;
    }
    index
};

fn word(pdu: &[u8], at: usize) -> Option<usize> {
    let w = pdu.get(at..at + 2)?;
    Some(usize::from(u16::from_be_bytes([w[0], w[1]])))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;
    use crate::frame::resync::{Judge, ReplyJudge, RequestJudge};
    use crate::frame::{pdu, rtu};

    /// A request and its normal reply for each row, as V1.1b3 §6 shows them (FC 11 and
    /// 2B, whose contents are the device's own, in the shape §6.13 and §6.21 give).
    fn spec_example(code: FunctionCode) -> (&'static str, &'static str) {
        match code.get() {
            0x01 => ("01 00 13 00 13", "01 03 CD 6B 05"),
            0x02 => ("02 00 C4 00 16", "02 03 AC DB 35"),
            0x03 => ("03 00 6B 00 03", "03 06 02 2B 00 00 00 64"),
            0x04 => ("04 00 08 00 01", "04 02 00 0A"),
            0x05 => ("05 00 AC FF 00", "05 00 AC FF 00"),
            0x06 => ("06 00 01 00 03", "06 00 01 00 03"),
            0x07 => ("07", "07 6D"),
            0x08 => ("08 00 00 A5 37", "08 00 00 A5 37"),
            0x0B => ("0B", "0B FF FF 01 08"),
            0x0C => ("0C", "0C 08 00 00 01 08 01 21 20 00"),
            0x0F => ("0F 00 13 00 0A 02 CD 01", "0F 00 13 00 0A"),
            0x10 => ("10 00 01 00 02 04 00 0A 01 02", "10 00 01 00 02"),
            0x11 => ("11", "11 03 2A FF 01"),
            0x14 => (
                "14 0E 06 00 04 00 01 00 02 06 00 03 00 09 00 02",
                "14 0C 05 06 0D FE 00 20 05 06 33 CD 00 40",
            ),
            0x15 => (
                "15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D",
                "15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D",
            ),
            0x16 => ("16 00 04 00 F2 00 25", "16 00 04 00 F2 00 25"),
            0x17 => (
                "17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF",
                "17 0C 00 FE 0A CD 00 01 00 03 00 0D 00 FF",
            ),
            0x18 => ("18 04 DE", "18 00 06 00 02 01 B8 12 84"),
            0x2B => ("2B 0E 01 00", "2B 0E 01 01 00 00 01 00 03 41 42 43"),
            _ => panic!("no example from the specification for {code}"),
        }
    }

    /// The RTU frame length its shape gives a whole PDU.
    fn rtu_len(size: Size) -> rtu::Length {
        match size {
            Size::Exactly(n) => rtu::Length::Exactly(n + 3),
            Size::Open => rtu::Length::Silence,
            Size::More => rtu::Length::More,
        }
    }

    #[test]
    fn every_row_fits_the_frames_of_the_specification() {
        for spec in TABLE {
            let code = spec.code;
            let (req, rep) = spec_example(code);
            let (req, rep) = (bytes(req), bytes(rep));
            assert_eq!(req[0], code.get());
            // The request: its shape, its limits, its RTU length.
            assert!(spec.request.fits(&req), "{code} request shape");
            assert_eq!(pdu::check_request(&req), Ok(()), "{code} request limits");
            assert!(pdu::request_well_formed(&req), "{code}");
            let frame = rtu::encode(0x11, &req);
            let want = match spec.request {
                Shape::Open => rtu::Length::Silence,
                _ => rtu::Length::Exactly(frame.len()),
            };
            assert_eq!(rtu::request_length(&frame), want, "{code} RTU request");
            // One byte more or less breaks a known request shape.
            if spec.request != Shape::Open {
                let mut longer = req.clone();
                longer.push(0);
                assert!(!pdu::request_well_formed(&longer), "{code} + 1 byte");
                assert!(
                    !pdu::request_well_formed(&req[..req.len() - 1]),
                    "{code} - 1"
                );
                assert_eq!(
                    pdu::check_request(&longer),
                    Err(ExceptionCode::ILLEGAL_DATA_VALUE)
                );
            }
            // The reply: its shape, its match to the request, its RTU length.
            assert!(spec.reply.fits(&rep), "{code} reply shape");
            assert!(pdu::reply_well_formed(&rep), "{code}");
            assert!(pdu::reply_matches(&req, &rep), "{code} reply matches");
            let frame = rtu::encode(0x11, &rep);
            let want = match spec.reply {
                Shape::Open => rtu::Length::Silence,
                _ => rtu::Length::Exactly(frame.len()),
            };
            assert_eq!(rtu::reply_length(&req, &frame), want, "{code} RTU reply");
            // Its exception is 5 bytes on RTU, and answers it.
            let exc = [code.exception().get(), 0x02];
            assert!(pdu::reply_matches(&req, &exc));
            assert_eq!(
                rtu::reply_length(&req, &rtu::encode(1, &exc)),
                rtu::Length::Exactly(5)
            );
            // Reads are resent; everything else may act on the device.
            assert_eq!(code.is_read(), spec.access == Access::Read);
        }
    }

    #[test]
    fn the_limits_of_section_6() {
        let limit = |code: FunctionCode, write: bool| {
            let s = code.spec().unwrap();
            (if write { s.write } else { s.read }).unwrap().max
        };
        assert_eq!(limit(FunctionCode::READ_COILS, false), 2000);
        assert_eq!(limit(FunctionCode::READ_DISCRETE_INPUTS, false), 2000);
        assert_eq!(limit(FunctionCode::READ_HOLDING_REGISTERS, false), 125);
        assert_eq!(limit(FunctionCode::READ_INPUT_REGISTERS, false), 125);
        assert_eq!(limit(FunctionCode::WRITE_MULTIPLE_COILS, true), 1968);
        assert_eq!(limit(FunctionCode::WRITE_MULTIPLE_REGISTERS, true), 123);
        assert_eq!(
            limit(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS, false),
            125
        );
        assert_eq!(
            limit(FunctionCode::READ_WRITE_MULTIPLE_REGISTERS, true),
            121
        );
        // Each limit, and one past it, through the gateway's request check.
        let read = |code: u8, q: u16| {
            let [h, l] = q.to_be_bytes();
            pdu::check_request(&[code, 0, 0, h, l])
        };
        assert_eq!(read(0x03, 125), Ok(()));
        assert_eq!(read(0x03, 126), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
        assert_eq!(read(0x01, 2000), Ok(()));
        assert_eq!(read(0x01, 2001), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
        let regs = |q: usize| {
            let mut p = vec![0x10, 0, 0, 0, q as u8, (2 * q) as u8];
            p.resize(6 + 2 * q, 0);
            pdu::check_request(&p)
        };
        assert_eq!(regs(123), Ok(()));
        assert_eq!(regs(124), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
        let coils = |q: u16| {
            let n = usize::from(q).div_ceil(8);
            let [h, l] = q.to_be_bytes();
            let mut p = vec![0x0F, 0, 0, h, l, n as u8];
            p.resize(6 + n, 0);
            pdu::check_request(&p)
        };
        assert_eq!(coils(1968), Ok(()));
        assert_eq!(coils(1969), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
        let rw = |r: u8, w: usize| {
            let mut p = vec![0x17, 0, 0, 0, r, 0, 0, 0, w as u8, (2 * w) as u8];
            p.resize(10 + 2 * w, 0);
            pdu::check_request(&p)
        };
        assert_eq!(rw(125, 121), Ok(()));
        assert_eq!(rw(126, 1), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
        assert_eq!(rw(1, 122), Err(ExceptionCode::ILLEGAL_DATA_VALUE));
    }

    /// PDUs of every length up to 20 for a code: zeros, and the byte count fields (at
    /// 1, 5 and 9) set to cover the rest, so counted shapes are met as well as missed.
    fn probes(code: u8) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        for len in 1..=20usize {
            let mut p = vec![0u8; len];
            p[0] = code;
            out.push(p.clone());
            if len >= 5 {
                // A coil's value: on, and neither on nor off.
                for value in [[0xFF, 0x00], [0x12, 0x34]] {
                    let mut v = p.clone();
                    v[3..5].copy_from_slice(&value);
                    out.push(v);
                }
            }
            for at in [1usize, 5, 9] {
                if at < len {
                    let mut q = p.clone();
                    q[at] = (len - at - 1) as u8;
                    if at == 1 && len > 2 {
                        // A 16-bit count at 1 (FC 18's reply).
                        let mut w = p.clone();
                        w[2] = (len - 3) as u8;
                        out.push(w);
                    }
                    // Quantities of 1 (bits) and of half the count (registers).
                    for qty_at in [3usize, 7] {
                        if qty_at + 1 < at {
                            let mut r = q.clone();
                            r[qty_at + 1] = 1;
                            out.push(r);
                            let mut r = q.clone();
                            r[qty_at + 1] = q[at] / 2;
                            out.push(r);
                        }
                    }
                    out.push(q);
                }
            }
        }
        out
    }

    #[test]
    fn every_check_agrees_with_the_table_for_every_code() {
        for byte in 0..=255u8 {
            let code = FunctionCode::new(byte);
            let public = TABLE.iter().any(|s| s.code == code);
            assert_eq!(code.is_public(), public, "{code}");
            // The MBAP decoders' first test of a candidate.
            assert_eq!(
                ReplyJudge.plausible_function(code),
                TABLE.iter().any(|s| s.code == code.base()),
                "{code}"
            );
            assert_eq!(
                RequestJudge::default().plausible_function(code),
                (1..0x80).contains(&byte)
            );
            for p in probes(byte) {
                let request_fits = code.can_be_request() && code.request_shape().fits(&p);
                assert_eq!(pdu::request_well_formed(&p), request_fits, "{p:02X?}");
                match pdu::check_request(&p) {
                    Ok(()) => assert!(request_fits, "{p:02X?} passed"),
                    Err(e) if !code.can_be_request() => {
                        assert_eq!(e, ExceptionCode::ILLEGAL_FUNCTION)
                    }
                    Err(e) => {
                        assert_eq!(e, ExceptionCode::ILLEGAL_DATA_VALUE);
                        assert!(public, "{p:02X?}: unknown codes pass");
                    }
                }
                if !public && code.can_be_request() {
                    assert_eq!(pdu::check_request(&p), Ok(()), "{p:02X?}");
                }
                // RTU lengths: what the table's shapes say, address and CRC around.
                let frame = rtu::encode(1, &p);
                let want = if code.can_be_request() {
                    rtu_len(code.request_shape().size(&frame[1..]))
                } else {
                    rtu::Length::Silence
                };
                assert_eq!(rtu::request_length(&frame), want, "{p:02X?}");
                let want = if code.is_exception() {
                    rtu::Length::Exactly(5)
                } else {
                    rtu_len(code.reply_shape().size_for(&p, &frame[1..]))
                };
                assert_eq!(rtu::reply_length(&p, &frame), want, "{p:02X?}");
                // A request of its own shape is delimited exactly by its RTU length.
                if request_fits && code.request_shape() != Shape::Open {
                    assert_eq!(
                        rtu::request_length(&frame),
                        rtu::Length::Exactly(frame.len())
                    );
                }
                // Replies: the shape, and the coil value of FC 05.
                let reply_fits = if code.is_exception() {
                    code.is_reply() && p.len() == 2 && ExceptionCode::new(p[1]).is_known()
                } else {
                    code.reply_shape().fits(&p)
                        && !code
                            .spec()
                            .is_some_and(|s| s.coil_value && !matches!(p[3..5], [0xFF, 0] | [0, 0]))
                };
                assert_eq!(pdu::reply_well_formed(&p), reply_fits, "{p:02X?}");
            }
        }
    }

    #[test]
    fn unknown_codes_stay_representable() {
        let user = FunctionCode::new(0x41);
        assert_eq!(user.get(), 0x41);
        assert_eq!(user.exception(), FunctionCode::new(0xC1));
        assert_eq!(user.exception().base(), user);
        assert!(user.can_be_request() && !user.is_public() && !user.is_read());
        assert_eq!(user.request_shape(), Shape::Open);
        assert_eq!(ExceptionCode::new(0x7F).name(), None);
        assert_eq!(
            ExceptionCode::GATEWAY_TARGET_FAILED.to_string(),
            "0x0b",
            "as the log has always shown it"
        );
    }
}
