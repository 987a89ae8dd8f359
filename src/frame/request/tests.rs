//! The request builders' and the reply decoder's tests: the examples of the Modbus
//! specification, the CIE-M10's frames byte for byte, the limits, bit packing.

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
    let Reply::Bits { addr, values } = decode_reply(&req, &bytes("02 03 AC DB 35")).unwrap() else {
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
