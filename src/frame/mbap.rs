//! The MBAP frame (docs/protocol.md §2, "Modbus/TCP (MBAP)") and the strict decoder used on
//! the TCP side (docs/design.md §1 step 1).
//!
//! ```text
//! TID(2) | protocol id(2) = 0000 | length(2) = bytes that follow | unit id(1) | PDU
//! ```

use super::function::{ExceptionCode, FunctionCode};
use super::hex::Hex;
use bytes::{Buf, BufMut, Bytes, BytesMut};
use std::fmt;

/// Bytes before the length field's payload: TID, protocol id, length.
pub(crate) const PREFIX_LEN: usize = 6;
/// The MBAP header including the unit id.
pub(crate) const HEADER_LEN: usize = 7;
/// Smallest valid length field: unit id + function code.
pub(crate) const MIN_LENGTH: u16 = 2;
/// Largest valid length field: unit id + a 253-byte PDU.
pub(crate) const MAX_LENGTH: u16 = 254;
/// Largest whole frame.
pub const MAX_ADU: usize = PREFIX_LEN + MAX_LENGTH as usize;

/// One whole MBAP frame whose length field agrees with its size. Cheap to clone.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct Adu(Bytes);

impl Adu {
    /// Wraps bytes already known to be one length-consistent frame.
    ///
    /// # Panics
    /// If the bytes are shorter than a header or the length field disagrees: callers
    /// only pass frames that a decoder has delimited.
    pub fn from_frame(bytes: Bytes) -> Self {
        assert!(bytes.len() > HEADER_LEN, "frame shorter than a header");
        assert_eq!(
            usize::from(u16::from_be_bytes([bytes[4], bytes[5]])) + PREFIX_LEN,
            bytes.len(),
            "length field disagrees with the frame size"
        );
        Adu(bytes)
    }

    /// Builds a frame from its parts. `pdu` must be 1..=253 bytes.
    ///
    /// Seed 001's example: RTU `11 03 006B 0003` as Modbus/TCP.
    ///
    /// ```
    /// use mbgate::frame::Adu;
    /// let adu = Adu::build(0x0001, 0x11, &[0x03, 0x00, 0x6B, 0x00, 0x03]);
    /// assert_eq!(
    ///     adu.as_bytes(),
    ///     &[0x00, 0x01, 0x00, 0x00, 0x00, 0x06, 0x11, 0x03, 0x00, 0x6B, 0x00, 0x03]
    /// );
    /// assert_eq!(adu.with_tid(0x1234).tid(), 0x1234);
    /// ```
    pub fn build(tid: u16, unit: u8, pdu: &[u8]) -> Self {
        assert!(
            !pdu.is_empty() && pdu.len() < MAX_LENGTH as usize,
            "PDU must be 1..=253 bytes"
        );
        let mut b = BytesMut::with_capacity(HEADER_LEN + pdu.len());
        b.put_u16(tid);
        b.put_u16(0);
        b.put_u16(pdu.len() as u16 + 1);
        b.put_u8(unit);
        b.put_slice(pdu);
        Adu(b.freeze())
    }

    /// [`Adu::build`], in `arena`: a buffer whose room is taken again once every
    /// frame built in it has been dropped, so a decoder that builds one frame at a
    /// time allocates nothing once warm (docs/performance.md "A transaction on a
    /// quiet line").
    pub(crate) fn build_in(arena: &mut BytesMut, tid: u16, unit: u8, pdu: &[u8]) -> Self {
        assert!(
            !pdu.is_empty() && pdu.len() < MAX_LENGTH as usize,
            "PDU must be 1..=253 bytes"
        );
        // Room for the longest frame: the arena is not grown frame by frame.
        arena.reserve(MAX_ADU);
        arena.put_u16(tid);
        arena.put_u16(0);
        arena.put_u16(pdu.len() as u16 + 1);
        arena.put_u8(unit);
        arena.put_slice(pdu);
        Adu(arena.split().freeze())
    }

    /// An exception response (docs/protocol.md §1): function code | 0x80, then the code.
    pub fn exception(
        tid: u16,
        unit: u8,
        function: impl Into<FunctionCode>,
        code: impl Into<ExceptionCode>,
    ) -> Self {
        let function = function.into().exception();
        Self::build(tid, unit, &[function.get(), code.into().get()])
    }

    /// A borrowed view of the same frame.
    pub(crate) fn view(&self) -> FrameRef<'_> {
        FrameRef(&self.0)
    }

    /// The transaction id (MBAP header bytes 0-1).
    pub fn tid(&self) -> u16 {
        self.view().tid()
    }

    /// The unit id (MBAP header byte 6): the device behind the gateway.
    pub fn unit(&self) -> u8 {
        self.view().unit()
    }

    /// The function code's wire byte.
    pub fn function(&self) -> u8 {
        self.view().function()
    }

    /// The function code, for looking it up in the table.
    pub(crate) fn function_code(&self) -> FunctionCode {
        self.view().function_code()
    }

    /// Function code followed by its data.
    pub fn pdu(&self) -> &[u8] {
        &self.0[HEADER_LEN..]
    }

    /// The whole frame, header and PDU, as on the wire.
    pub fn as_bytes(&self) -> &[u8] {
        &self.0
    }

    /// The same frame with another transaction id (the relay's id rewriting, docs/design.md
    /// §1 step 3).
    pub fn with_tid(&self, tid: u16) -> Self {
        let src = &self.0[..];
        if src.len() > MAX_ADU {
            // Never from a decoder; a frame built longer still gets its id.
            let mut b = BytesMut::from(src);
            b[..2].copy_from_slice(&tid.to_be_bytes());
            return Adu(b.freeze());
        }
        // Most requests and many replies are short: a small box for them.
        if src.len() <= SHORT {
            Adu(Bytes::from_owner(Owned::<SHORT>::with_tid(src, tid)))
        } else {
            Adu(Bytes::from_owner(Owned::<MAX_ADU>::with_tid(src, tid)))
        }
    }
}

/// Frames up to this long (an FC 03 request, a reply of up to 12 registers) are held
/// in a box of this size.
const SHORT: usize = 32;

/// A frame's bytes in one allocation with the count of their owners: a copy of the
/// frame (the line keeps one of each request it sends, to know its echo) is a count
/// more, where a `Bytes` made from a `Vec` allocates again on its first copy
/// (docs/performance.md "Instructions a transaction, counted").
struct Owned<const N: usize> {
    len: usize,
    buf: [u8; N],
}

impl<const N: usize> Owned<N> {
    /// `src` (at most `N` bytes) with transaction id `tid`.
    fn with_tid(src: &[u8], tid: u16) -> Self {
        let mut frame = Owned {
            len: src.len(),
            buf: [0; N],
        };
        frame.buf[..src.len()].copy_from_slice(src);
        frame.buf[..2].copy_from_slice(&tid.to_be_bytes());
        frame
    }
}

impl<const N: usize> AsRef<[u8]> for Owned<N> {
    fn as_ref(&self) -> &[u8] {
        &self.buf[..self.len]
    }
}

/// A borrowed, length-consistent frame: what a decoder shows a [`crate::frame::Judge`]
/// before it commits to taking the bytes.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct FrameRef<'a>(&'a [u8]);

impl<'a> FrameRef<'a> {
    pub(crate) fn tid(&self) -> u16 {
        u16::from_be_bytes([self.0[0], self.0[1]])
    }

    pub(crate) fn unit(&self) -> u8 {
        self.0[6]
    }

    /// The function code's wire byte.
    pub(crate) fn function(&self) -> u8 {
        self.0[7]
    }

    /// The function code, for looking it up in the table.
    pub(crate) fn function_code(&self) -> FunctionCode {
        FunctionCode::new(self.0[7])
    }

    pub(crate) fn pdu(&self) -> &'a [u8] {
        &self.0[HEADER_LEN..]
    }

    pub(crate) fn as_bytes(&self) -> &'a [u8] {
        self.0
    }

    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        debug_assert!(bytes.len() > HEADER_LEN);
        FrameRef(bytes)
    }
}

impl fmt::Debug for Adu {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Adu[{}]", Hex(&self.0))
    }
}

/// Why the strict decoder rejected a master's frame. Any of these closes the connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum StrictError {
    /// The protocol id is not 0 (Modbus); the value found.
    #[error("protocol id {0:#06x}, expected 0x0000")]
    ProtocolId(u16),
    /// The length field (unit id and PDU) is outside what a PDU can be; the value found.
    #[error("length field {0}, expected {MIN_LENGTH}..={MAX_LENGTH}")]
    Length(u16),
}

/// Takes one frame off the front of `buf`, checking it strictly (docs/design.md §1 step 1):
/// protocol id 0 and length 2..=254. `Ok(None)` means more bytes are needed. A header
/// is judged as soon as its six bytes are in, so a bad length never makes us wait.
pub fn decode_strict(buf: &mut BytesMut) -> Result<Option<Adu>, StrictError> {
    if buf.len() < PREFIX_LEN {
        return Ok(None);
    }
    let protocol = u16::from_be_bytes([buf[2], buf[3]]);
    if protocol != 0 {
        return Err(StrictError::ProtocolId(protocol));
    }
    let length = u16::from_be_bytes([buf[4], buf[5]]);
    if !(MIN_LENGTH..=MAX_LENGTH).contains(&length) {
        return Err(StrictError::Length(length));
    }
    let total = PREFIX_LEN + usize::from(length);
    if buf.len() < total {
        buf.reserve(total - buf.len());
        return Ok(None);
    }
    let frame = buf.split_to(total).freeze();
    Ok(Some(Adu(frame)))
}

/// Drops the first `n` bytes of `buf` (used by the resynchronising decoder).
pub(crate) fn skip(buf: &mut BytesMut, n: usize) {
    buf.advance(n);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::hex::parse as bytes;

    #[test]
    fn decodes_the_cie_m10_read_request() {
        let mut buf = BytesMut::from(&bytes("00 00 00 00 00 06 01 03 00 00 00 01")[..]);
        let adu = decode_strict(&mut buf).unwrap().unwrap();
        assert_eq!(adu.tid(), 0);
        assert_eq!(adu.unit(), 1);
        assert_eq!(adu.function(), 3);
        assert_eq!(adu.pdu(), &bytes("03 00 00 00 01")[..]);
        assert!(buf.is_empty());
    }

    #[test]
    fn waits_for_a_whole_frame_at_every_split() {
        let frame = bytes("00 00 00 00 00 09 01 10 00 08 00 01 02 00 11");
        for cut in 0..frame.len() {
            let mut buf = BytesMut::from(&frame[..cut]);
            assert_eq!(decode_strict(&mut buf), Ok(None), "cut at {cut}");
            buf.extend_from_slice(&frame[cut..]);
            let adu = decode_strict(&mut buf).unwrap().unwrap();
            assert_eq!(adu.as_bytes(), &frame[..]);
        }
    }

    #[test]
    fn rejects_bad_protocol_id_and_length_at_once() {
        let mut b = BytesMut::from(&bytes("00 01 00 01 00 06")[..]);
        assert_eq!(decode_strict(&mut b), Err(StrictError::ProtocolId(1)));
        let mut b = BytesMut::from(&bytes("00 01 00 00 00 00")[..]);
        assert_eq!(decode_strict(&mut b), Err(StrictError::Length(0)));
        let mut b = BytesMut::from(&bytes("00 01 00 00 00 01")[..]);
        assert_eq!(decode_strict(&mut b), Err(StrictError::Length(1)));
        let mut b = BytesMut::from(&bytes("00 01 00 00 01 2C")[..]);
        assert_eq!(decode_strict(&mut b), Err(StrictError::Length(300)));
        let mut b = BytesMut::from(&bytes("00 01 00 00 00 FF")[..]);
        assert_eq!(decode_strict(&mut b), Err(StrictError::Length(255)));
        let mut b = BytesMut::from(&bytes("00 01 00 00 00 FE")[..]);
        assert_eq!(decode_strict(&mut b), Ok(None));
    }

    #[test]
    fn two_frames_back_to_back() {
        let mut v = bytes("00 07 00 00 00 06 01 03 00 00 00 01");
        v.extend(bytes("00 08 00 00 00 06 01 03 00 08 00 01"));
        let mut buf = BytesMut::from(&v[..]);
        assert_eq!(decode_strict(&mut buf).unwrap().unwrap().tid(), 7);
        assert_eq!(decode_strict(&mut buf).unwrap().unwrap().tid(), 8);
        assert_eq!(decode_strict(&mut buf), Ok(None));
    }

    #[test]
    fn build_and_rewrite() {
        let adu = Adu::build(0x1234, 0x11, &bytes("03 00 6B 00 03"));
        assert_eq!(
            adu.as_bytes(),
            &bytes("12 34 00 00 00 06 11 03 00 6B 00 03")[..]
        );
        assert_eq!(
            adu.with_tid(1).as_bytes(),
            &bytes("00 01 00 00 00 06 11 03 00 6B 00 03")[..]
        );
        assert_eq!(
            Adu::exception(5, 1, 0x03, 0x0B).as_bytes(),
            &bytes("00 05 00 00 00 03 01 83 0B")[..]
        );
    }
}
