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
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;
    use crate::frame::Adu;

    fn bits(s: &str) -> Vec<bool> {
        s.chars().map(|c| c == '1').collect()
    }

    #[test]
    fn read_coils_20_to_38_as_the_modbus_specification_shows() {
        let req = Request::ReadCoils { addr: 19, qty: 19 }.pdu().unwrap();
        assert_eq!(req, bytes("01 00 13 00 13"));
        let reply = decode_reply(&req, &bytes("01 03 CD 6B 05")).unwrap();
        // CD = 1100 1101: coils 27..20; 6B = 0110 1011: 35..28; 05: 38..36.
        assert_eq!(
            reply,
            Reply::Bits {
                addr: 19,
                values: bits("1011 0011 1101 0110 101".replace(' ', "").as_str()),
            }
        );
        // The padding bits of the last byte are not values.
        assert!(decode_reply(&req, &bytes("01 02 CD 6B")).is_err());
    }

    #[test]
    fn read_discrete_inputs_197_to_218() {
        // The Modbus Application Protocol V1.1b3 example (AC .. 35).
        let req = Request::ReadDiscreteInputs { addr: 196, qty: 22 }
            .pdu()
            .unwrap();
        assert_eq!(req, bytes("02 00 C4 00 16"));
        let Reply::Bits { addr, values } = decode_reply(&req, &bytes("02 03 AC DB 35")).unwrap()
        else {
            panic!("bits expected")
        };
        assert_eq!(addr, 196);
        assert_eq!(values.len(), 22);
        assert_eq!(pack_bits(&values), bytes("AC DB 35"));
    }

    #[test]
    fn read_registers() {
        // Seed 004: registers 108..110 hold 555, 0, 100 (PDU address 107 = 0x6B).
        let req = Request::ReadHoldingRegisters { addr: 107, qty: 3 }
            .pdu()
            .unwrap();
        assert_eq!(req, bytes("03 00 6B 00 03"));
        assert_eq!(
            decode_reply(&req, &bytes("03 06 02 2B 00 00 00 64")).unwrap(),
            Reply::Registers {
                addr: 107,
                values: vec![555, 0, 100]
            }
        );
        // Seed 004: input register 9 holds 10.
        let req = Request::ReadInputRegisters { addr: 8, qty: 1 }
            .pdu()
            .unwrap();
        assert_eq!(req, bytes("04 00 08 00 01"));
        assert_eq!(
            decode_reply(&req, &bytes("04 02 00 0A")).unwrap(),
            Reply::Registers {
                addr: 8,
                values: vec![10]
            }
        );
        // One register short: not an answer.
        assert!(decode_reply(&req, &bytes("04 04 00 0A 00 00")).is_err());
        // An FC 03 reply to an FC 04 request: not an answer.
        assert!(decode_reply(&req, &bytes("03 02 00 0A")).is_err());
    }

    #[test]
    fn cie_m10_frames_byte_exact() {
        // docs/protocol.md §3: read the inputs, 1 word at 0, unit 1, transaction id 0.
        let req = Request::ReadHoldingRegisters { addr: 0, qty: 1 }
            .pdu()
            .unwrap();
        assert_eq!(
            Adu::build(0, 1, &req).as_bytes(),
            &bytes("00 00 00 00 00 06 01 03 00 00 00 01")[..]
        );
        let reply = bytes("00 00 00 00 00 05 01 03 02 00 FF");
        assert_eq!(
            decode_reply(&req, &reply[7..]).unwrap(),
            Reply::Registers {
                addr: 0,
                values: vec![0x00FF]
            }
        );
        // Outputs 0 and 4 ON at address 8.
        let req = Request::WriteMultipleRegisters {
            addr: 8,
            values: vec![0x0011],
        }
        .pdu()
        .unwrap();
        assert_eq!(
            Adu::build(0, 1, &req).as_bytes(),
            &bytes("00 00 00 00 00 09 01 10 00 08 00 01 02 00 11")[..]
        );
        let reply = bytes("00 00 00 00 00 06 01 10 00 08 00 01");
        assert_eq!(
            decode_reply(&req, &reply[7..]).unwrap(),
            Reply::WroteMany {
                addr: 8,
                qty: 1,
                coils: false
            }
        );
        // The exceptions.
        assert_eq!(
            decode_reply(&req, &bytes("90 02")).unwrap(),
            Reply::Exception {
                function: Fc::WRITE_MULTIPLE_REGISTERS,
                code: ExceptionCode::ILLEGAL_DATA_ADDRESS
            }
        );
        let read = Request::ReadHoldingRegisters { addr: 0, qty: 1 }
            .pdu()
            .unwrap();
        assert_eq!(
            decode_reply(&read, &bytes("83 01")).unwrap(),
            Reply::Exception {
                function: Fc::READ_HOLDING_REGISTERS,
                code: ExceptionCode::ILLEGAL_FUNCTION
            }
        );
        // Another function's exception is not an answer.
        assert!(decode_reply(&read, &bytes("90 01")).is_err());
    }

    #[test]
    fn single_writes_echo() {
        let req = Request::WriteSingleCoil {
            addr: 172,
            value: true,
        }
        .pdu()
        .unwrap();
        assert_eq!(req, bytes("05 00 AC FF 00"));
        assert_eq!(
            decode_reply(&req, &req).unwrap(),
            Reply::WroteCoil {
                addr: 172,
                value: true
            }
        );
        let off = Request::WriteSingleCoil {
            addr: 1,
            value: false,
        }
        .pdu()
        .unwrap();
        assert_eq!(off, bytes("05 00 01 00 00"));
        let req = Request::WriteSingleRegister {
            addr: 1,
            value: 0x0003,
        }
        .pdu()
        .unwrap();
        assert_eq!(req, bytes("06 00 01 00 03"));
        assert_eq!(
            decode_reply(&req, &req).unwrap(),
            Reply::WroteRegister { addr: 1, value: 3 }
        );
        // An echo with another value: not an answer.
        assert!(decode_reply(&req, &bytes("06 00 01 00 04")).is_err());
    }

    #[test]
    fn write_ten_coils_at_20_as_the_modbus_specification_shows() {
        // CD 01: coils 27..20 = 1100 1101, 29..28 = 01.
        let values = bits("1011001110");
        let req = Request::WriteMultipleCoils { addr: 19, values }
            .pdu()
            .unwrap();
        assert_eq!(req, bytes("0F 00 13 00 0A 02 CD 01"));
        assert_eq!(
            decode_reply(&req, &bytes("0F 00 13 00 0A")).unwrap(),
            Reply::WroteMany {
                addr: 19,
                qty: 10,
                coils: true
            }
        );
        assert!(decode_reply(&req, &bytes("0F 00 13 00 09")).is_err());
    }

    #[test]
    fn read_write_multiple_registers() {
        // The public spec's FC 17 example: write 3 at 14, read 6 at 3.
        let req = Request::ReadWriteMultipleRegisters {
            read_addr: 3,
            read_qty: 6,
            write_addr: 14,
            values: vec![0xFF; 3],
        }
        .pdu()
        .unwrap();
        assert_eq!(
            req,
            bytes("17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF")
        );
        assert_eq!(
            decode_reply(&req, &bytes("17 0C 00 FE 0A CD 00 01 00 03 00 0D 00 FF")).unwrap(),
            Reply::Registers {
                addr: 3,
                values: vec![0xFE, 0x0ACD, 1, 3, 0x0D, 0xFF]
            }
        );
    }

    #[test]
    fn limits() {
        let q = |qty| Request::ReadHoldingRegisters { addr: 0, qty }.pdu();
        assert!(q(125).is_ok());
        assert_eq!(
            q(126),
            Err(RequestError::Quantity {
                what: "registers",
                min: 1,
                max: 125,
                got: 126
            })
        );
        assert!(q(0).is_err());
        assert!(Request::ReadCoils { addr: 0, qty: 2000 }.pdu().is_ok());
        assert!(Request::ReadCoils { addr: 0, qty: 2001 }.pdu().is_err());
        assert!(Request::ReadCoils {
            addr: 65535,
            qty: 1
        }
        .pdu()
        .is_ok());
        assert_eq!(
            Request::ReadCoils {
                addr: 65535,
                qty: 2
            }
            .pdu(),
            Err(RequestError::Range {
                what: "coils",
                addr: 65535,
                qty: 2
            })
        );
        let coils = |n| Request::WriteMultipleCoils {
            addr: 0,
            values: vec![true; n],
        };
        assert!(coils(1968).pdu().is_ok());
        assert!(coils(1969).pdu().is_err());
        assert!(coils(0).pdu().is_err());
        let regs = |n| Request::WriteMultipleRegisters {
            addr: 0,
            values: vec![1; n],
        };
        assert!(regs(123).pdu().is_ok());
        assert!(regs(124).pdu().is_err());
        let rw = |r, w| Request::ReadWriteMultipleRegisters {
            read_addr: 0,
            read_qty: r,
            write_addr: 0,
            values: vec![0; w],
        };
        assert!(rw(125, 121).pdu().is_ok());
        assert!(rw(126, 1).pdu().is_err());
        assert!(rw(1, 122).pdu().is_err());
    }

    #[test]
    fn bit_packing_round_trips() {
        for n in 1usize..=20 {
            let v: Vec<bool> = (0..n).map(|i| i % 3 == 0).collect();
            let packed = pack_bits(&v);
            assert_eq!(packed.len(), n.div_ceil(8));
            assert_eq!(unpack_bits(&packed, n), v);
            if n % 8 != 0 {
                assert_eq!(packed.last().unwrap() >> (n % 8), 0, "padding is zero");
            }
        }
    }

    #[test]
    fn exception_names() {
        assert_eq!(exception_name(0x02), "illegal data address");
        assert_eq!(
            exception_name(0x0B),
            "gateway target device failed to respond"
        );
        assert_eq!(exception_name(0x7F), "unknown exception");
    }
}
