//! The RTU frame (docs/protocol.md §2; Modbus over Serial Line V1.02 §2.5.1): `address | PDU | CRC-16`, the CRC
//! low byte first. RTU has no length field and no transaction id: frames are delimited
//! by their function code's shape where it is known, and by 3.5 character times of
//! silence otherwise (the caller measures the silence, see [`super::serial`]).
//!
//! Seed 001's example:
//!
//! ```
//! use mbgate::frame::rtu;
//! assert_eq!(
//!     rtu::encode(0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]),
//!     [0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87]
//! );
//! ```

use super::function::{FunctionCode, Size};
use crc::{Crc, CRC_16_MODBUS};

const MODBUS: Crc<u16> = Crc::<u16>::new(&CRC_16_MODBUS);

/// Address, function code, and the two CRC bytes: the least a frame holds.
pub(crate) const MIN_FRAME: usize = 4;
/// Address + a 253-byte PDU + CRC.
pub(crate) const MAX_FRAME: usize = 256;

/// The Modbus CRC-16 of `bytes` (sent low byte first).
pub(crate) fn crc16(bytes: &[u8]) -> u16 {
    MODBUS.checksum(bytes)
}

/// `unit | pdu | CRC`.
pub fn encode(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut v = Vec::with_capacity(pdu.len() + 3);
    encode_into(unit, pdu, &mut v);
    v
}

/// [`encode`], appended to `out` (a buffer kept for the next frame: nothing allocated
/// once it has room).
pub(crate) fn encode_into(unit: u8, pdu: &[u8], out: &mut Vec<u8>) {
    let start = out.len();
    out.push(unit);
    out.extend_from_slice(pdu);
    let crc = crc16(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
}

/// The address and PDU of a whole frame whose CRC is right; `None` otherwise (or when
/// it is too short or too long to be a frame).
pub fn decode(frame: &[u8]) -> Option<(u8, &[u8])> {
    if !(MIN_FRAME..=MAX_FRAME).contains(&frame.len()) {
        return None;
    }
    let (body, crc) = frame.split_at(frame.len() - 2);
    (crc16(body).to_le_bytes() == [crc[0], crc[1]]).then(|| (body[0], &body[1..]))
}

/// How long the frame at the front of a buffer is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Length {
    /// More bytes are needed to tell.
    More,
    /// The frame is this many bytes, CRC included.
    Exactly(usize),
    /// Its shape is unknown (FC 08 sub-functions, 2B, vendor codes): silence ends it.
    Silence,
}

/// The frame length for a PDU of this [`Size`]: address and CRC around it.
fn framed(size: Size) -> Length {
    match size {
        Size::More => Length::More,
        Size::Exactly(n) => Length::Exactly(1 + n + 2),
        Size::Open => Length::Silence,
    }
}

/// The length of the reply at the front of `buf` (address first) to the request
/// `request` (a PDU): from the function code's reply shape in the table
/// ([`super::function::TABLE`]), and its byte count where it has one. An exception is
/// known at once (5 bytes), so it never waits for silence.
pub(crate) fn reply_length(request: &[u8], buf: &[u8]) -> Length {
    let Some(&code) = buf.get(1) else {
        return Length::More;
    };
    let code = FunctionCode::new(code);
    if code.is_exception() {
        return Length::Exactly(5);
    }
    framed(code.reply_shape().size_for(request, &buf[1..]))
}

/// The length of the request at the front of `buf` (address first), from its own
/// function code's request shape and byte count (the simulator's side of the line).
pub fn request_length(buf: &[u8]) -> Length {
    let Some(&code) = buf.get(1) else {
        return Length::More;
    };
    let code = FunctionCode::new(code);
    if !code.can_be_request() {
        return Length::Silence;
    }
    framed(code.request_shape().size(&buf[1..]))
}

/// 3.5 character times at `bits_per_second` with `bits_per_char` bits a character, in
/// microseconds: the silence that ends an RTU frame. Above 19 200 baud the spec fixes it
/// at 1750 µs (Modbus over serial line, §2.5.1.1).
pub fn t35_us(bits_per_second: u32, bits_per_char: u32) -> u64 {
    if bits_per_second > 19_200 {
        return 1750;
    }
    (u64::from(bits_per_char) * 35_000_000).div_ceil(10 * u64::from(bits_per_second.max(1)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;

    #[test]
    fn the_read_of_protocol_md_section_2_encodes_with_crc_76_87() {
        let frame = bytes("11 03 00 6B 00 03 76 87");
        assert_eq!(encode(0x11, &bytes("03 00 6B 00 03")), frame);
        assert_eq!(decode(&frame), Some((0x11, &frame[1..6])));
        assert_eq!(crc16(&frame[..6]), 0x8776);
    }

    #[test]
    fn a_wrong_byte_or_crc_is_refused() {
        let frame = bytes("11 03 00 6B 00 03 76 87");
        for i in 0..frame.len() {
            let mut f = frame.clone();
            f[i] ^= 0x01;
            assert_eq!(decode(&f), None, "flip in byte {i}");
        }
        assert_eq!(decode(&frame[..3]), None);
    }

    #[test]
    fn reply_lengths() {
        let read3 = bytes("03 00 6B 00 03");
        assert_eq!(reply_length(&read3, &[]), Length::More);
        assert_eq!(reply_length(&read3, &[0x11]), Length::More);
        assert_eq!(reply_length(&read3, &[0x11, 0x03]), Length::More);
        assert_eq!(reply_length(&read3, &[0x11, 0x03, 6]), Length::Exactly(11));
        assert_eq!(reply_length(&read3, &[0x11, 0x83]), Length::Exactly(5));
        assert_eq!(
            reply_length(&bytes("10 00 01 00 01 02 00 07"), &[1, 0x10]),
            Length::Exactly(8)
        );
        assert_eq!(reply_length(&[0x41], &[1, 0x41]), Length::Silence);
        assert_eq!(
            reply_length(&[0x2B, 0x0E, 1, 0], &[1, 0x2B]),
            Length::Silence
        );
        assert_eq!(
            reply_length(&bytes("08 00 00 12 34"), &[1, 0x08]),
            Length::Exactly(8)
        );
        assert_eq!(
            reply_length(&[0x18, 0, 1], &[1, 0x18, 0, 6]),
            Length::Exactly(12)
        );
    }

    #[test]
    fn request_lengths() {
        assert_eq!(request_length(&bytes("11 03 00 6B")), Length::Exactly(8));
        assert_eq!(
            request_length(&bytes("01 10 00 01 00 02 04")),
            Length::Exactly(13)
        );
        assert_eq!(request_length(&bytes("01 10 00 01 00 02")), Length::More);
        assert_eq!(
            request_length(&[1, 0x17, 0, 0, 0, 1, 0, 0, 0, 1, 2]),
            Length::Exactly(15)
        );
        assert_eq!(request_length(&[1, 0x65]), Length::Silence);
    }

    #[test]
    fn silence_times() {
        // 9600 8N1: 3.5 × 10 bits / 9600 = 3.646 ms.
        assert_eq!(t35_us(9600, 10), 3646);
        assert_eq!(t35_us(19_200, 11), 2006);
        assert_eq!(t35_us(115_200, 10), 1750);
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        #[test]
        fn encode_decode_round_trip(unit: u8, pdu in proptest::collection::vec(proptest::num::u8::ANY, 1..=253)) {
            let frame = encode(unit, &pdu);
            proptest::prop_assert_eq!(decode(&frame), Some((unit, &pdu[..])));
        }
    }
}
