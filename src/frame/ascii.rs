//! The ASCII frame (docs/protocol.md §2; Modbus over Serial Line V1.02 §2.5.2): `':'`, then the address, the PDU and the
//! LRC as pairs of hex characters, then CR LF. The colon and the line feed delimit
//! frames, so no length or silence is needed; a colon inside a frame starts a new one
//! (Modbus over serial line, §2.5.2.1).
//!
//! ```
//! use mbgate::frame::ascii;
//! assert_eq!(ascii::encode(0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]), b":1103006B00037E\r\n");
//! ```

const HEX: &[u8; 16] = b"0123456789ABCDEF";
/// `:` + address, function code and LRC (6 characters) + CR LF.
pub(crate) const MIN_FRAME: usize = 9;
/// `:` + 2 × (address + 253-byte PDU + LRC) + CR LF.
pub(crate) const MAX_FRAME: usize = 1 + 2 * 255 + 2;

/// The longitudinal redundancy check: the two's complement of the byte sum.
pub(crate) fn lrc(bytes: &[u8]) -> u8 {
    bytes
        .iter()
        .fold(0u8, |a, &b| a.wrapping_add(b))
        .wrapping_neg()
}

/// `:` + hex(unit, pdu, LRC) + CR LF, in upper-case hex.
pub fn encode(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut body = Vec::with_capacity(pdu.len() + 2);
    body.push(unit);
    body.extend_from_slice(pdu);
    body.push(lrc(&body));
    let mut v = Vec::with_capacity(2 * body.len() + 3);
    v.push(b':');
    for b in body {
        v.push(HEX[usize::from(b >> 4)]);
        v.push(HEX[usize::from(b & 0x0F)]);
    }
    v.extend_from_slice(b"\r\n");
    v
}

fn nibble(c: u8) -> Option<u8> {
    (c as char).to_digit(16).map(|d| d as u8)
}

/// The address and PDU of a whole frame (colon to line feed) whose hex and LRC are
/// right; `None` otherwise.
pub fn decode(frame: &[u8]) -> Option<(u8, Vec<u8>)> {
    if !(MIN_FRAME..=MAX_FRAME).contains(&frame.len()) {
        return None;
    }
    let hex = frame.strip_prefix(b":")?.strip_suffix(b"\r\n")?;
    if hex.len() % 2 != 0 {
        return None;
    }
    let body = hex
        .chunks(2)
        .map(|p| Some(nibble(p[0])? << 4 | nibble(p[1])?))
        .collect::<Option<Vec<u8>>>()?;
    let (&check, data) = body.split_last()?;
    (lrc(data) == check).then(|| (data[0], data[1..].to_vec()))
}

/// What the front of a buffer holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Scan {
    /// This many bytes cannot belong to a frame (before a colon, or a frame cut short
    /// by a new colon): drop them.
    Garbage(usize),
    /// A frame from its colon, not yet ended (or nothing at all).
    More,
    /// A whole frame of this many bytes, colon to line feed.
    Frame(usize),
}

/// Finds the frame at the front of `buf`.
pub(crate) fn scan(buf: &[u8]) -> Scan {
    match buf.iter().position(|&b| b == b':') {
        None if buf.is_empty() => Scan::More,
        None => Scan::Garbage(buf.len()),
        Some(0) => match buf[1..].iter().position(|&b| b == b':' || b == b'\n') {
            Some(i) if buf[1 + i] == b':' => Scan::Garbage(1 + i),
            Some(i) => Scan::Frame(i + 2),
            None if buf.len() > MAX_FRAME => Scan::Garbage(buf.len()),
            None => Scan::More,
        },
        Some(i) => Scan::Garbage(i),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lrc_of_the_read_of_protocol_md_section_2() {
        // 11 + 03 + 00 + 6B + 00 + 03 = 0x82; two's complement 0x7E.
        assert_eq!(lrc(&[0x11, 0x03, 0x00, 0x6B, 0x00, 0x03]), 0x7E);
        let f = encode(0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]);
        assert_eq!(decode(&f), Some((0x11, vec![0x03, 0x00, 0x6B, 0x00, 0x03])));
        assert_eq!(decode(b":1103006B00037e\r\n").map(|d| d.0), Some(0x11));
    }

    #[test]
    fn bad_frames_are_refused() {
        assert_eq!(decode(b":1103006B00037F\r\n"), None, "wrong LRC");
        assert_eq!(decode(b":1103006B00037\r\n"), None, "odd length");
        assert_eq!(decode(b":1103006B0X037E\r\n"), None, "not hex");
        assert_eq!(decode(b"1103006B00037E\r\n"), None, "no colon");
    }

    #[test]
    fn scanning() {
        assert_eq!(scan(b""), Scan::More);
        assert_eq!(scan(b"xx:01"), Scan::Garbage(2));
        assert_eq!(scan(b":0103"), Scan::More);
        assert_eq!(scan(b":01:0103"), Scan::Garbage(3));
        assert_eq!(scan(b":010300000001FB\r\n:01"), Scan::Frame(17));
        assert_eq!(scan(b"\r\n"), Scan::Garbage(2));
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        #[test]
        fn encode_decode_round_trip(unit: u8, pdu in proptest::collection::vec(proptest::num::u8::ANY, 1..=253)) {
            let frame = encode(unit, &pdu);
            proptest::prop_assert_eq!(scan(&frame), Scan::Frame(frame.len()));
            proptest::prop_assert_eq!(decode(&frame), Some((unit, pdu)));
        }
    }
}
