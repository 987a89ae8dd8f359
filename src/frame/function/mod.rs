//! The one table of function codes (Modbus Application Protocol V1.1b3 §6, docs/protocol.md
//! §1): each public code's request shape, reply shape, whether it only reads, and its
//! quantity limits. Every check derives from `TABLE`: TCP request validation and reply
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

mod exception;

pub(crate) use exception::ExceptionCode;
use std::fmt;

/// A function code as it is on the wire: a request's (1..=127), or a reply's, whose high
/// bit marks an exception. Any byte is representable, so unknown and user-defined codes
/// pass through.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FunctionCode(u8);

impl FunctionCode {
    pub(crate) const READ_COILS: Self = Self(0x01);
    pub(crate) const READ_DISCRETE_INPUTS: Self = Self(0x02);
    /// FC 03, read holding registers (V1.1b3 §6.3).
    pub const READ_HOLDING_REGISTERS: Self = Self(0x03);
    pub(crate) const READ_INPUT_REGISTERS: Self = Self(0x04);
    pub(crate) const WRITE_SINGLE_COIL: Self = Self(0x05);
    pub(crate) const WRITE_SINGLE_REGISTER: Self = Self(0x06);
    pub(crate) const READ_EXCEPTION_STATUS: Self = Self(0x07);
    pub(crate) const DIAGNOSTICS: Self = Self(0x08);
    pub(crate) const GET_COMM_EVENT_COUNTER: Self = Self(0x0B);
    pub(crate) const GET_COMM_EVENT_LOG: Self = Self(0x0C);
    pub(crate) const WRITE_MULTIPLE_COILS: Self = Self(0x0F);
    pub(crate) const WRITE_MULTIPLE_REGISTERS: Self = Self(0x10);
    pub(crate) const REPORT_SERVER_ID: Self = Self(0x11);
    pub(crate) const READ_FILE_RECORD: Self = Self(0x14);
    pub(crate) const WRITE_FILE_RECORD: Self = Self(0x15);
    pub(crate) const MASK_WRITE_REGISTER: Self = Self(0x16);
    pub(crate) const READ_WRITE_MULTIPLE_REGISTERS: Self = Self(0x17);
    pub(crate) const READ_FIFO_QUEUE: Self = Self(0x18);
    pub(crate) const ENCAPSULATED_INTERFACE: Self = Self(0x2B);

    /// The code of this wire byte, whatever it is.
    pub const fn new(byte: u8) -> Self {
        Self(byte)
    }

    /// The wire byte.
    pub(crate) const fn get(self) -> u8 {
        self.0
    }

    /// The high bit: an exception reply (V1.1b3 §7).
    pub(crate) const fn is_exception(self) -> bool {
        self.0 & 0x80 != 0
    }

    /// The request's code this reply code answers (the high bit cleared).
    pub(crate) const fn base(self) -> Self {
        Self(self.0 & 0x7F)
    }

    /// The exception reply's code for this request's code.
    pub(crate) const fn exception(self) -> Self {
        Self(self.0 | 0x80)
    }

    /// Can a master send it at all? 0 and the exception codes cannot be requests.
    pub(crate) const fn can_be_request(self) -> bool {
        self.0 != 0 && !self.is_exception()
    }

    /// Its row of `TABLE`, if it is a public code (an exception code has none).
    pub fn spec(self) -> Option<&'static Spec> {
        let row = *INDEX.get(usize::from(self.0))?;
        TABLE.get(usize::from(row))
    }

    /// A public code of the application protocol (in [`TABLE`]).
    pub(crate) fn is_public(self) -> bool {
        self.spec().is_some()
    }

    /// Could a device send a reply with this code: a public one, or its exception form?
    pub(crate) fn is_reply(self) -> bool {
        self.base().is_public()
    }

    /// Does a request with this code only read, so that it may be resent after a
    /// timeout (docs/design.md §4 `retries`)? Anything unknown may act on the device.
    pub fn is_read(self) -> bool {
        self.spec().is_some_and(|s| s.access == Access::Read)
    }

    /// May a request with this code go to unit 0, the broadcast address of a serial
    /// bus? Only the writes of the application protocol: a broadcast is answered by
    /// no device, so it can only be a writing command (Modbus over Serial Line V1.02
    /// §2.1). A read (01-04, 17 too), a diagnostic, a code the specification does
    /// not define, cannot: no device would answer it (docs/protocol.md §2).
    pub(crate) fn may_broadcast(self) -> bool {
        matches!(
            self,
            Self::WRITE_SINGLE_COIL
                | Self::WRITE_SINGLE_REGISTER
                | Self::WRITE_MULTIPLE_COILS
                | Self::WRITE_MULTIPLE_REGISTERS
                | Self::WRITE_FILE_RECORD
                | Self::MASK_WRITE_REGISTER
        )
    }

    /// The shape of a request with this code ([`Shape::Open`] when unknown).
    pub(crate) fn request_shape(self) -> Shape {
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

/// What a request may do to the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Access {
    /// It only reads: resending it is harmless.
    Read,
    /// It may act on the device: resent only with `retry_writes`.
    Write,
}

/// What a quantity counts, and so how many data bytes it takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Item {
    /// Coils or discrete inputs, packed 8 to a byte.
    Bits,
    /// 16-bit registers, 2 bytes each.
    Registers,
}

impl Item {
    /// Data bytes for `qty` items.
    pub(crate) fn bytes(self, qty: usize) -> usize {
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
    pub(crate) at: usize,
    /// The most items one request may carry (125 registers for FC 03, for one).
    pub max: u16,
    pub(crate) item: Item,
}

impl Quantity {
    /// The quantity in `pdu`, if the field is there.
    pub(crate) fn of(&self, pdu: &[u8]) -> Option<usize> {
        word(pdu, self.at)
    }

    /// Within 1..=max?
    pub(crate) fn allows(&self, qty: usize) -> bool {
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
        /// PDU offset of the byte count.
        at: usize,
        /// The count is two bytes, big-endian (FC 18, read FIFO queue).
        wide: bool,
        /// The smallest count a well-formed PDU has.
        min: usize,
        /// The count is a multiple of this (2 for registers).
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
    pub(crate) fn size_for(self, request: &[u8], pdu: &[u8]) -> Size {
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

    /// `Shape::size_for` without a request.
    pub fn size(self, pdu: &[u8]) -> Size {
        self.size_for(&[], pdu)
    }

    /// Is `pdu` a whole PDU of this shape (the count fields' own limits included)?
    pub(crate) fn fits(self, pdu: &[u8]) -> bool {
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
pub(crate) enum Echo {
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
    pub(crate) code: FunctionCode,
    pub(crate) name: &'static str,
    pub(crate) access: Access,
    /// The request's size.
    pub(crate) request: Shape,
    /// What it reads: the reply's byte count is that many items.
    pub read: Option<Quantity>,
    /// What it writes: the byte count right after the field (at `at + 2`) covers that
    /// many items.
    pub(crate) write: Option<Quantity>,
    /// The 16-bit value at offset 3 of request and reply is FF00 or 0000 (FC 05).
    pub(crate) coil_value: bool,
    /// It writes one item, at the address at offset 1 (FC 05, 06, 22).
    pub(crate) writes_one: bool,
    /// The normal reply's size.
    pub(crate) reply: Shape,
    pub(crate) echo: Echo,
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
        writes_one: false,
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
pub(crate) const TABLE: &[Spec] = &[
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
        writes_one: true,
        reply: Shape::Fixed(5),
        echo: Echo::Whole,
        ..row(F::WRITE_SINGLE_COIL, "write single coil", Write)
    },
    // §6.6.
    Spec {
        request: Shape::Fixed(5),
        writes_one: true,
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
        writes_one: true,
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
        assert!(
            code != 0 && code < 128,
            "a request's function code is 1..=127"
        );
        assert!(index[code] == u8::MAX, "a function code in the table twice");
        index[code] = row as u8;
        row += 1;
    }
    index
};

/// MEI type 0x0E of FC 0x2B: read device identification (V1.1b3 §6.21), the one
/// encapsulated interface transport that only reads.
const READ_DEVICE_ID: u8 = 0x0E;

/// MEI type 0x0D of FC 0x2B: CANopen general reference (V1.1b3 §6.20), MEI type
/// specific data of any length after it.
const CANOPEN_REFERENCE: u8 = 0x0D;

/// Does an FC 0x2B request have the shape its MEI type calls for (V1.1b3 §6.19-§6.21,
/// docs/protocol.md §1)? At least the MEI type; MEI 0x0E (read device identification)
/// exactly the read device id code (01 to 04) and the object id, nothing after them;
/// MEI 0x0D its data, any length; other MEI types are reserved and left to the
/// device. `None` for another function code.
pub(crate) fn mei_request_fits(pdu: &[u8]) -> Option<bool> {
    match pdu {
        [0x2B] => Some(false),
        [0x2B, READ_DEVICE_ID, rest @ ..] => Some(matches!(rest, [1..=4, _])),
        [0x2B, CANOPEN_REFERENCE, ..] => Some(true),
        [0x2B, ..] => Some(true),
        _ => None,
    }
}

/// Does this request PDU only read? The table's reads, and FC 0x2B with MEI type 0x0E
/// (read device identification) of exactly its shape: a code and an object id, no
/// bytes after them to carry anything else to the device. Anything else (a write,
/// diagnostics, a code the table does not know) may act on the device: a read-only
/// master may not send it (docs/security.md).
pub fn only_reads(pdu: &[u8]) -> bool {
    match pdu {
        [fc, ..] if FunctionCode(*fc).is_read() => true,
        [0x2B, READ_DEVICE_ID, ..] => mei_request_fits(pdu) == Some(true),
        _ => false,
    }
}

/// The addresses a write request writes: its first address and how many items, coils
/// for FC 05 and 15, holding registers for FC 06, 16, 22 and 23 (only the written range
/// of 23). `None` for a request that writes no address range (FC 08, 21, 0x2B, codes
/// the table does not know) or is too short to say.
pub fn written(pdu: &[u8]) -> Option<(u16, u16)> {
    let spec = FunctionCode(*pdu.first()?).spec()?;
    let (addr, count) = if spec.writes_one {
        (word(pdu, 1)?, 1)
    } else {
        let q = spec.write?;
        (word(pdu, q.at - 2)?, q.of(pdu)?)
    };
    Some((addr as u16, u16::try_from(count).ok()?))
}

fn word(pdu: &[u8], at: usize) -> Option<usize> {
    let w = pdu.get(at..at + 2)?;
    Some(usize::from(u16::from_be_bytes([w[0], w[1]])))
}

#[cfg(test)]
mod tests;
