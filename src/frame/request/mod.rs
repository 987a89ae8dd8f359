//! What a master sends and what the answer means, for `mbgate read` and `mbgate write`:
//! builders for the request PDUs of the common function
//! codes and a decoder from a reply PDU to values or an exception (docs/protocol.md §1).
//!
//! Pure: bytes in, values out. Matching a reply to its request (transaction id, unit,
//! shape) uses [`pdu::reply_matches`], the same check the relay applies.
//!
//! ```
//! use mbgate::frame::request::{decode_reply, Reply, Request};
//! // Seed 004: coils 20..38 read as `CD 6B 05`.
//! let req = Request::ReadCoils { addr: 19, qty: 19 };
//! let pdu = req.pdu().unwrap();
//! assert_eq!(pdu, [0x01, 0x00, 0x13, 0x00, 0x13]);
//! let Reply::Bits { addr, values } = decode_reply(&pdu, &[0x01, 0x03, 0xCD, 0x6B, 0x05]).unwrap()
//! else { panic!() };
//! assert_eq!(addr, 19);
//! assert_eq!(values.len(), 19);
//! assert!(values[0] && !values[1] && values[18]);
//! ```

use super::function::{ExceptionCode, FunctionCode as Fc};
use super::hex::Hex;
use super::pdu;

/// One request of the common function codes (docs/protocol.md §1 table). Addresses are
/// PDU addresses (0-based).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Request {
    /// FC 01.
    ReadCoils {
        /// The first coil's address.
        addr: u16,
        /// How many coils, 1..=2000.
        qty: u16,
    },
    /// FC 02.
    ReadDiscreteInputs {
        /// The first input's address.
        addr: u16,
        /// How many inputs, 1..=2000.
        qty: u16,
    },
    /// FC 03.
    ReadHoldingRegisters {
        /// The first register's address.
        addr: u16,
        /// How many registers, 1..=125.
        qty: u16,
    },
    /// FC 04.
    ReadInputRegisters {
        /// The first register's address.
        addr: u16,
        /// How many registers, 1..=125.
        qty: u16,
    },
    /// FC 05: `true` is sent as FF00, `false` as 0000.
    WriteSingleCoil {
        /// The coil's address.
        addr: u16,
        /// On (`true`) or off.
        value: bool,
    },
    /// FC 06.
    WriteSingleRegister {
        /// The register's address.
        addr: u16,
        /// The value written.
        value: u16,
    },
    /// FC 0F.
    WriteMultipleCoils {
        /// The first coil's address.
        addr: u16,
        /// The coils from `addr` on, 1..=1968 of them.
        values: Vec<bool>,
    },
    /// FC 10.
    WriteMultipleRegisters {
        /// The first register's address.
        addr: u16,
        /// The registers from `addr` on, 1..=123 of them.
        values: Vec<u16>,
    },
    /// FC 17: the device writes `values` at `write_addr`, then reads `read_qty`
    /// registers at `read_addr`, in one transaction.
    ReadWriteMultipleRegisters {
        /// The first register read.
        read_addr: u16,
        /// How many registers are read, 1..=125.
        read_qty: u16,
        /// The first register written.
        write_addr: u16,
        /// The registers written from `write_addr` on, 1..=121 of them.
        values: Vec<u16>,
    },
}

/// A request outside the limits of docs/protocol.md §1: it would never be sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RequestError {
    /// Too few or too many items for the function code.
    #[error("{what} must be {min}..={max}, got {got}")]
    Quantity {
        /// What is counted, as the message says it ("coils", "registers").
        what: &'static str,
        /// The fewest allowed (1).
        min: usize,
        /// The most the function code carries (docs/protocol.md §1).
        max: usize,
        /// How many were asked for.
        got: usize,
    },
    /// The block would run past the last address (65535).
    #[error("address {addr} + {qty} {what} runs past address 65535")]
    Range {
        /// What is counted, as the message says it.
        what: &'static str,
        /// The block's first address.
        addr: u16,
        /// How many items it holds.
        qty: usize,
    },
}

/// The limit of the table ([`super::function::TABLE`]) on what `code` reads, or on what
/// it writes.
fn limit(code: Fc, write: bool) -> usize {
    let spec = code.spec().expect("a public function code");
    let q = if write { spec.write } else { spec.read };
    usize::from(q.expect("a quantity field").max)
}

/// Checks `1 <= qty <= max` and that the block `addr..addr+qty` fits the 16-bit
/// address space.
fn block(what: &'static str, addr: u16, qty: usize, max: usize) -> Result<(), RequestError> {
    if !(1..=max).contains(&qty) {
        return Err(RequestError::Quantity {
            what,
            min: 1,
            max,
            got: qty,
        });
    }
    if usize::from(addr) + qty > 0x1_0000 {
        return Err(RequestError::Range { what, addr, qty });
    }
    Ok(())
}

/// Packs bits the Modbus way (docs/protocol.md §1): the first bit is the LSB of the first
/// byte; unused high bits of the last byte are zero.
pub(crate) fn pack_bits(bits: &[bool]) -> Vec<u8> {
    let mut out = vec![0u8; bits.len().div_ceil(8)];
    for (i, _) in bits.iter().enumerate().filter(|(_, &b)| b) {
        out[i / 8] |= 1 << (i % 8);
    }
    out
}

/// The first `n` bits of `bytes`, unpacked the Modbus way (docs/protocol.md §1).
pub(crate) fn unpack_bits(bytes: &[u8], n: usize) -> Vec<bool> {
    (0..n.min(bytes.len() * 8))
        .map(|i| bytes[i / 8] & (1 << (i % 8)) != 0)
        .collect()
}

fn put_words(out: &mut Vec<u8>, words: &[u16]) {
    for w in words {
        out.extend_from_slice(&w.to_be_bytes());
    }
}

impl Request {
    /// The function code (docs/protocol.md §1 table).
    pub(crate) fn function(&self) -> Fc {
        match self {
            Request::ReadCoils { .. } => Fc::READ_COILS,
            Request::ReadDiscreteInputs { .. } => Fc::READ_DISCRETE_INPUTS,
            Request::ReadHoldingRegisters { .. } => Fc::READ_HOLDING_REGISTERS,
            Request::ReadInputRegisters { .. } => Fc::READ_INPUT_REGISTERS,
            Request::WriteSingleCoil { .. } => Fc::WRITE_SINGLE_COIL,
            Request::WriteSingleRegister { .. } => Fc::WRITE_SINGLE_REGISTER,
            Request::WriteMultipleCoils { .. } => Fc::WRITE_MULTIPLE_COILS,
            Request::WriteMultipleRegisters { .. } => Fc::WRITE_MULTIPLE_REGISTERS,
            Request::ReadWriteMultipleRegisters { .. } => Fc::READ_WRITE_MULTIPLE_REGISTERS,
        }
    }

    /// Checks the limits of docs/protocol.md §1 (quantities, and blocks that stay inside the
    /// address space).
    pub(crate) fn validate(&self) -> Result<(), RequestError> {
        let read = || limit(self.function(), false);
        let write = || limit(self.function(), true);
        match self {
            Request::ReadCoils { addr, qty } => block("coils", *addr, usize::from(*qty), read()),
            Request::ReadDiscreteInputs { addr, qty } => {
                block("discrete inputs", *addr, usize::from(*qty), read())
            }
            Request::ReadHoldingRegisters { addr, qty }
            | Request::ReadInputRegisters { addr, qty } => {
                block("registers", *addr, usize::from(*qty), read())
            }
            Request::WriteSingleCoil { .. } | Request::WriteSingleRegister { .. } => Ok(()),
            Request::WriteMultipleCoils { addr, values } => {
                block("coils", *addr, values.len(), write())
            }
            Request::WriteMultipleRegisters { addr, values } => {
                block("registers", *addr, values.len(), write())
            }
            Request::ReadWriteMultipleRegisters {
                read_addr,
                read_qty,
                write_addr,
                values,
            } => {
                block("registers read", *read_addr, usize::from(*read_qty), read())?;
                block("registers written", *write_addr, values.len(), write())
            }
        }
    }

    /// The request PDU (function code and data, docs/protocol.md §1 table), after
    /// `Request::validate`.
    pub fn pdu(&self) -> Result<Vec<u8>, RequestError> {
        self.validate()?;
        let mut p = vec![self.function().get()];
        match self {
            Request::ReadCoils { addr, qty }
            | Request::ReadDiscreteInputs { addr, qty }
            | Request::ReadHoldingRegisters { addr, qty }
            | Request::ReadInputRegisters { addr, qty } => put_words(&mut p, &[*addr, *qty]),
            Request::WriteSingleCoil { addr, value } => {
                put_words(&mut p, &[*addr, if *value { 0xFF00 } else { 0x0000 }])
            }
            Request::WriteSingleRegister { addr, value } => put_words(&mut p, &[*addr, *value]),
            Request::WriteMultipleCoils { addr, values } => {
                put_words(&mut p, &[*addr, values.len() as u16]);
                let packed = pack_bits(values);
                p.push(packed.len() as u8);
                p.extend_from_slice(&packed);
            }
            Request::WriteMultipleRegisters { addr, values } => {
                put_words(&mut p, &[*addr, values.len() as u16]);
                p.push((values.len() * 2) as u8);
                put_words(&mut p, values);
            }
            Request::ReadWriteMultipleRegisters {
                read_addr,
                read_qty,
                write_addr,
                values,
            } => {
                put_words(
                    &mut p,
                    &[*read_addr, *read_qty, *write_addr, values.len() as u16],
                );
                p.push((values.len() * 2) as u8);
                put_words(&mut p, values);
            }
        }
        debug_assert_eq!(pdu::check_request(&p), Ok(()), "built {}", Hex(&p));
        Ok(p)
    }
}

/// What a reply says (docs/protocol.md §1 "normal response data", or an exception).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply {
    /// FC 01, 02: the bits asked for, padding dropped; `addr` is the first one's.
    Bits {
        /// The first bit's address (the request's).
        addr: u16,
        /// As many bits as the request asked for.
        values: Vec<bool>,
    },
    /// FC 03, 04, 17: the registers read; `addr` is the first one's.
    Registers {
        /// The first register's address (the request's).
        addr: u16,
        /// The registers read, in address order.
        values: Vec<u16>,
    },
    /// FC 05: the echo of the coil written.
    WroteCoil {
        /// The coil's address.
        addr: u16,
        /// On (`true`, FF00) or off (0000).
        value: bool,
    },
    /// FC 06: the echo of the register written.
    WroteRegister {
        /// The register's address.
        addr: u16,
        /// The value it now holds.
        value: u16,
    },
    /// FC 0F (`coils`) or 10: where and how many were written.
    WroteMany {
        /// The first address written.
        addr: u16,
        /// How many coils or registers were written.
        qty: u16,
        /// Coils (FC 0F) rather than registers (FC 10).
        coils: bool,
    },
    /// Any other function code (no decoding known): the reply PDU's data.
    Raw {
        /// The reply PDU after its function code.
        data: Vec<u8>,
    },
    /// Exception response: function code | 0x80, then the code (docs/protocol.md §1).
    Exception {
        /// The function code of the request (the high bit cleared).
        function: Fc,
        /// Why the device refused (Modbus Application Protocol V1.1b3 §7).
        code: ExceptionCode,
    },
}

/// A reply PDU that does not answer the request: wrong function code, or a shape the
/// request does not call for (docs/design.md §1 step 4).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("reply PDU {reply} does not answer request PDU {request}")]
pub struct Mismatch {
    pub(crate) request: String,
    pub(crate) reply: String,
}

fn word(p: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([p[at], p[at + 1]])
}

/// Decodes `reply` (a PDU) as the answer to `request` (a PDU that passed
/// [`pdu::check_request`]). The reply must pass [`pdu::reply_matches`] first.
pub fn decode_reply(request: &[u8], reply: &[u8]) -> Result<Reply, Mismatch> {
    if request.is_empty() || !pdu::reply_matches(request, reply) {
        return Err(Mismatch {
            request: Hex(request).to_string(),
            reply: Hex(reply).to_string(),
        });
    }
    let function = Fc::new(reply[0]);
    if function.is_exception() {
        return Ok(Reply::Exception {
            function: function.base(),
            code: ExceptionCode::new(reply[1]),
        });
    }
    Ok(match function {
        Fc::READ_COILS | Fc::READ_DISCRETE_INPUTS => Reply::Bits {
            addr: word(request, 1),
            values: unpack_bits(&reply[2..], usize::from(word(request, 3))),
        },
        Fc::READ_HOLDING_REGISTERS
        | Fc::READ_INPUT_REGISTERS
        | Fc::READ_WRITE_MULTIPLE_REGISTERS => Reply::Registers {
            addr: word(request, 1),
            values: reply[2..].chunks(2).map(|c| word(c, 0)).collect(),
        },
        Fc::WRITE_SINGLE_COIL => Reply::WroteCoil {
            addr: word(reply, 1),
            value: word(reply, 3) == 0xFF00,
        },
        Fc::WRITE_SINGLE_REGISTER => Reply::WroteRegister {
            addr: word(reply, 1),
            value: word(reply, 3),
        },
        Fc::WRITE_MULTIPLE_COILS | Fc::WRITE_MULTIPLE_REGISTERS => Reply::WroteMany {
            addr: word(reply, 1),
            qty: word(reply, 3),
            coils: function == Fc::WRITE_MULTIPLE_COILS,
        },
        _ => Reply::Raw {
            data: reply[1..].to_vec(),
        },
    })
}

/// The name of an exception code (docs/protocol.md §1).
pub(crate) fn exception_name(code: u8) -> &'static str {
    ExceptionCode::new(code)
        .name()
        .unwrap_or("unknown exception")
}

#[cfg(test)]
mod tests;
