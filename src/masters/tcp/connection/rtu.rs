//! RTU over TCP on the masters' side (docs/design.md §4.1, `framing = "rtu"` on a
//! listener): RTU frames (unit, PDU, CRC-16) on the socket with no MBAP header. A
//! frame ends at the length its function code calls for, or, for a function of
//! unknown shape, at a pause; a bad CRC is a protocol violation that closes only that
//! connection. With no transaction id, one request at a time: the next is read once
//! the reply to the last has been written.

use crate::frame::rtu::{self, Length};
use crate::frame::Adu;
use bytes::BytesMut;
use std::time::Duration;

/// The longest RTU frame: address, 253 bytes of PDU, CRC (Modbus over Serial Line
/// V1.02 §2.5.1.1).
pub(in crate::masters::tcp) const MAX_FRAME: usize = 256;

/// A pause this long ends a request of unknown shape. A master writes its request in
/// one go, so on a socket the pause is far longer than its bytes are ever apart.
pub(in crate::masters::tcp) const SILENCE: Duration = Duration::from_millis(50);

/// Why an RTU master's connection is closed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub(in crate::masters::tcp) enum RtuError {
    #[error("an RTU request whose CRC is wrong ({0} bytes)")]
    BadCrc(usize),
    #[error("more than {MAX_FRAME} bytes without an RTU request")]
    TooLong,
}

/// The request at the front of `buf`, as an ADU with transaction id `tid` (the relay
/// gives it its own id on the line); `None` while more bytes are needed. `quiet`: the
/// master has paused for [`SILENCE`], which ends a request of unknown shape.
pub(in crate::masters::tcp) fn decode(
    buf: &mut BytesMut,
    quiet: bool,
    tid: u16,
) -> Result<Option<Adu>, RtuError> {
    let n = match rtu::request_length(buf) {
        Length::Exactly(n) if buf.len() >= n => n,
        Length::Silence if quiet => buf.len(),
        _ if buf.len() > MAX_FRAME => return Err(RtuError::TooLong),
        _ => return Ok(None),
    };
    if n > MAX_FRAME {
        return Err(RtuError::TooLong);
    }
    let frame = buf.split_to(n);
    match rtu::decode(&frame) {
        Some((unit, pdu)) if !pdu.is_empty() => Ok(Some(Adu::build(tid, unit, pdu))),
        _ => Err(RtuError::BadCrc(n)),
    }
}

/// Does what is buffered wait for a pause to end it (a function of unknown shape)?
pub(in crate::masters::tcp) fn needs_silence(buf: &BytesMut) -> bool {
    !buf.is_empty() && rtu::request_length(buf) == Length::Silence
}

/// The reply as the master reads it: unit, PDU, CRC.
pub(in crate::masters::tcp) fn encode(adu: &Adu) -> Vec<u8> {
    rtu::encode(adu.unit(), adu.pdu())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn buf(bytes: &[u8]) -> BytesMut {
        BytesMut::from(bytes)
    }

    #[test]
    fn a_request_is_whole_at_its_length_and_its_crc_checked() {
        let read = rtu::encode(7, &[3, 0, 1, 0, 2]);
        let mut b = buf(&read[..5]);
        assert_eq!(decode(&mut b, false, 9), Ok(None));
        b.extend_from_slice(&read[5..]);
        b.extend_from_slice(&read[..2]);
        let adu = decode(&mut b, false, 9).unwrap().unwrap();
        assert_eq!(
            (adu.tid(), adu.unit(), adu.pdu()),
            (9, 7, &[3, 0, 1, 0, 2][..])
        );
        assert_eq!(&b[..], &read[..2], "the next request's first bytes stay");

        let mut bad = read.clone();
        bad[3] ^= 1;
        assert_eq!(decode(&mut buf(&bad), false, 1), Err(RtuError::BadCrc(8)));
    }

    #[test]
    fn a_function_of_unknown_shape_ends_at_a_pause() {
        let odd = rtu::encode(1, &[0x41, 1, 2, 3]);
        let mut b = buf(&odd);
        assert!(needs_silence(&b));
        assert_eq!(decode(&mut b, false, 1), Ok(None));
        let adu = decode(&mut b, true, 1).unwrap().unwrap();
        assert_eq!(adu.pdu(), &[0x41, 1, 2, 3]);
        assert!(b.is_empty());
        let mut long = buf(&[1, 0x41]);
        long.extend_from_slice(&[0; MAX_FRAME]);
        assert_eq!(decode(&mut long, false, 1), Err(RtuError::TooLong));
    }
}
