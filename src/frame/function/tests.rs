//! The function code table held to the frames of the Modbus Application Protocol
//! V1.1b3 §6, and every check held to the table for every code 0..=255.

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

/// What a write writes, from the examples of V1.1b3 §6: the address and count each
/// writing code names (23: its written range, not its read range); nothing for the
/// codes that write no address range; and every read only reads, read device
/// identification included, while every other code of 0..=255 may act on the device.
#[test]
fn written_ranges_and_reads_follow_the_specification_examples() {
    let expect: &[(u8, Option<(u16, u16)>)] = &[
        (0x05, Some((0xAC, 1))),
        (0x06, Some((1, 1))),
        (0x0F, Some((0x13, 10))),
        (0x10, Some((1, 2))),
        (0x16, Some((4, 1))),
        (0x17, Some((0x0E, 3))),
        (0x08, None),
        (0x15, None),
    ];
    for &(code, range) in expect {
        let (req, _) = spec_example(FunctionCode(code));
        let pdu = bytes(req);
        assert_eq!(written(&pdu), range, "FC {code:#04x}");
        assert!(!only_reads(&pdu), "FC {code:#04x} may act on the device");
    }
    for spec in TABLE.iter().filter(|s| s.access == Access::Read) {
        let (req, _) = spec_example(spec.code);
        let pdu = bytes(req);
        assert!(only_reads(&pdu) && written(&pdu).is_none(), "{}", spec.name);
    }
    assert!(
        only_reads(&bytes("2B 0E 01 00")),
        "read device identification"
    );
    assert_eq!(written(&bytes("2B 0E 01 00")), None);
    assert!(!only_reads(&bytes("2B 0D 00")), "CANopen general reference");
    // Read device identification only in its own shape: nothing after the object id
    // to carry to the device, and a read device id code of 01 to 04 (§6.21).
    let trailing = [&bytes("2B 0E 01 00")[..], &[0xAA; 200]].concat();
    for bad in [
        &bytes("2B 0E 01 00 00")[..],
        &trailing,
        &bytes("2B 0E 01"),
        &bytes("2B 0E"),
        &bytes("2B 0E 05 00"),
        &bytes("2B 0E 00 00"),
    ] {
        assert!(!only_reads(bad), "{bad:02X?}");
        assert_eq!(
            crate::frame::pdu::check_request(bad),
            Err(ExceptionCode::ILLEGAL_DATA_VALUE),
            "{bad:02X?}"
        );
    }
    for good in [
        "2B 0E 01 00",
        "2B 0E 04 FF",
        "2B 0D",
        "2B 0D 00 01 02",
        "2B 0F 01",
    ] {
        assert_eq!(
            crate::frame::pdu::check_request(&bytes(good)),
            Ok(()),
            "{good}"
        );
    }
    assert_eq!(
        crate::frame::pdu::check_request(&[0x2B]),
        Err(ExceptionCode::ILLEGAL_DATA_VALUE)
    );
    for code in 0..=255u8 {
        let public_read = FunctionCode(code).is_read();
        assert_eq!(
            only_reads(&[code, 0, 0, 0, 1]),
            public_read,
            "FC {code:#04x}"
        );
    }
    assert_eq!(written(&[]), None);
    assert_eq!(written(&[0x10, 0]), None, "too short to say");
}

/// Of the specification's frames, every request may be one, and every reply is known
/// for an answer but where its request has the same shape (the writes that repeat
/// their request, FC 08, the file records, 0x2B's shapes of its own, and FC 01's
/// example, whose five bytes read as a request for coils too); every exception is one.
#[test]
fn no_request_of_the_specification_is_taken_for_an_answer() {
    for spec in TABLE {
        let code = spec.code;
        let (req, rep) = spec_example(code);
        let (req, rep) = (bytes(req), bytes(rep));
        assert_eq!(pdu::not_a_request(&req), None, "{code} request");
        let answer = pdu::not_a_request(&rep);
        assert_eq!(
            answer.is_some(),
            !spec.request.fits(&rep),
            "{code} reply {answer:?}"
        );
        let exception = [code.exception().get(), 0x02];
        assert_eq!(
            pdu::not_a_request(&exception),
            Some(pdu::NotRequest::Exception),
            "{code}"
        );
    }
    // Every code with its high bit set is an exception; a request within the limits
    // is never taken for an answer.
    for code in 0..=255u8 {
        for tail in [
            &[][..],
            &[0, 1, 0, 1],
            &[2, 0, 0xFF],
            &[0, 1, 0, 1, 2, 0, 7],
        ] {
            let p: Vec<u8> = std::iter::once(code).chain(tail.iter().copied()).collect();
            let kind = pdu::not_a_request(&p);
            if code >= 0x80 {
                assert_eq!(kind, Some(pdu::NotRequest::Exception), "{p:02X?}");
            } else if pdu::check_request(&p).is_ok() {
                assert_eq!(kind, None, "{p:02X?}");
            }
        }
    }
}
