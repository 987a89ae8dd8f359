//! How a master's connection frames its requests and replies: one codec for each
//! framing a listener may have (docs/design.md §4.1, `framing` on a `[[listen]]`),
//! chosen once when the connection starts, as tokio-modbus does with its TCP and RTU
//! codecs. The connection's loops are written once over [`MasterCodec`].

use super::rtu;
use crate::frame::mbap::{decode_strict, StrictError};
use crate::frame::Adu;
use crate::ops::capture::packet::Proto;
use bytes::BytesMut;
use std::borrow::Cow;
use std::time::Duration;

/// Why a master's bytes are not a request: the connection is closed.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub(in crate::masters::tcp) enum FrameError {
    #[error(transparent)]
    Mbap(#[from] StrictError),
    #[error(transparent)]
    Rtu(#[from] rtu::RtuError),
}

/// A master's framing on the socket: requests decoded from the bytes read, replies
/// encoded for writing. State of one connection (an RTU master's request count).
pub(in crate::masters::tcp) trait MasterCodec: Default + Send {
    /// As `framing` is written in the configuration.
    const NAME: &'static str;
    /// Do its frames carry a transaction id? Without one a master has one request
    /// outstanding at a time, and gets no notifications (nothing would tell them from
    /// a reply).
    const IDS: bool;
    /// How a capture names its frames.
    const PROTO: Proto;
    /// The request at the front of `buf`, if whole; `Err`: not a request.
    fn decode(&mut self, buf: &mut BytesMut) -> Result<Option<Adu>, FrameError>;
    /// How long a pause of the master's ends what is buffered, if only a pause can.
    fn ended_by_pause(&self, _buf: &BytesMut) -> Option<Duration> {
        None
    }
    /// The master paused as long as `ended_by_pause` said.
    fn paused(&mut self) {}
    /// `adu` as the master sees it on its socket.
    fn frame(adu: &Adu) -> Cow<'_, [u8]>;
    /// `frame` as the master sees it on its socket with transaction id `tid` and unit
    /// id `unit` (its own), appended to `out`: a reply from the line is framed for the
    /// master here, once, not copied for it before.
    fn frame_into(frame: &Adu, tid: u16, unit: u8, out: &mut Vec<u8>);
    /// Is an answer going out as unit `unit` written to the master at all?
    fn answers(_unit: u8) -> bool {
        true
    }
}

/// Modbus/TCP: MBAP header and PDU, strictly checked (docs/protocol.md).
#[derive(Default)]
pub(in crate::masters::tcp) struct Mbap;

impl MasterCodec for Mbap {
    const NAME: &'static str = "mbap";
    const IDS: bool = true;
    const PROTO: Proto = Proto::Mbtcp;

    fn decode(&mut self, buf: &mut BytesMut) -> Result<Option<Adu>, FrameError> {
        // A protocol id byte that is not 0 is refused at once, not once the whole
        // header has come: a dialed server's short acknowledgement ("ACK") is known
        // for what it is without waiting for bytes that may never come.
        if let Some(&b) = buf.get(2).filter(|&&b| b != 0) {
            let low = buf.get(3).copied().unwrap_or(0);
            return Err(StrictError::ProtocolId(u16::from_be_bytes([b, low])).into());
        }
        Ok(decode_strict(buf)?)
    }

    fn frame(adu: &Adu) -> Cow<'_, [u8]> {
        Cow::Borrowed(adu.as_bytes())
    }

    fn frame_into(frame: &Adu, tid: u16, unit: u8, out: &mut Vec<u8>) {
        let b = frame.as_bytes();
        out.extend_from_slice(&tid.to_be_bytes());
        // Protocol id and length, as they are: the PDU is the frame's.
        out.extend_from_slice(&b[2..6]);
        out.push(unit);
        out.extend_from_slice(frame.pdu());
    }
}

/// RTU over TCP (`tcp/connection/rtu.rs`): unit, PDU and CRC, no header.
#[derive(Default)]
pub(in crate::masters::tcp) struct Rtu {
    /// The id the relay sees for the next request (the line gives it its own).
    tid: u16,
    /// The master has paused: that ends a request of unknown shape.
    quiet: bool,
}

impl MasterCodec for Rtu {
    const NAME: &'static str = "rtu";
    const IDS: bool = false;
    const PROTO: Proto = Proto::Mbrtu;

    fn decode(&mut self, buf: &mut BytesMut) -> Result<Option<Adu>, FrameError> {
        let tid = self.tid.wrapping_add(1);
        let adu = rtu::decode(buf, std::mem::take(&mut self.quiet), tid)?;
        if adu.is_some() {
            self.tid = tid;
        }
        Ok(adu)
    }

    fn ended_by_pause(&self, buf: &BytesMut) -> Option<Duration> {
        rtu::needs_silence(buf).then_some(rtu::SILENCE)
    }

    fn paused(&mut self) {
        self.quiet = true;
    }

    fn frame(adu: &Adu) -> Cow<'_, [u8]> {
        Cow::Owned(rtu::encode(adu))
    }

    fn frame_into(frame: &Adu, _tid: u16, unit: u8, out: &mut Vec<u8>) {
        crate::frame::rtu::encode_into(unit, frame.pdu(), out);
    }

    /// Unit 0 is a broadcast in RTU: its master awaits no answer, and would take one
    /// for the answer to its next request.
    fn answers(unit: u8) -> bool {
        unit != 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::rtu as serial;

    /// The same read as each framing writes it decodes to the same unit and PDU, and
    /// its reply is framed back the same way; only RTU leaves a broadcast unanswered.
    #[test]
    fn each_codec_reads_and_writes_its_own_framing() {
        let pdu = [3, 0, 1, 0, 2];
        let mut mbap = BytesMut::from(&[0, 9, 0, 0, 0, 6, 7, 3, 0, 1, 0, 2][..]);
        let a = Mbap.decode(&mut mbap).unwrap().unwrap();
        assert_eq!((a.tid(), a.unit(), a.pdu()), (9, 7, &pdu[..]));
        assert_eq!(&Mbap::frame(&a)[..], a.as_bytes());

        let mut codec = Rtu::default();
        let wire = serial::encode(7, &pdu);
        let mut rtu = BytesMut::from(&wire[..]);
        let r = codec.decode(&mut rtu).unwrap().unwrap();
        assert_eq!((r.unit(), r.pdu()), (7, &pdu[..]));
        assert_eq!(&Rtu::frame(&r)[..], &wire[..]);
        let mut next = BytesMut::from(&wire[..]);
        let r2 = codec.decode(&mut next).unwrap().unwrap();
        assert_ne!(r.tid(), r2.tid(), "each request its own id on the line");

        assert!(Mbap::answers(0));
        assert!(!Rtu::answers(0), "a broadcast");
        assert!(Rtu::answers(r.unit()));

        // A reply from the line (its id and unit the line's) framed for the master.
        let line = Adu::build(0x4321, 3, &[3, 2, 0, 7]);
        let mut out = Vec::new();
        Mbap::frame_into(&line, 9, 7, &mut out);
        assert_eq!(out, Adu::build(9, 7, &[3, 2, 0, 7]).as_bytes());
        out.clear();
        Rtu::frame_into(&line, 9, 7, &mut out);
        assert_eq!(out, serial::encode(7, &[3, 2, 0, 7]));
    }

    /// A function of unknown shape waits for the master's pause, then ends there.
    #[test]
    fn an_rtu_request_of_unknown_shape_ends_at_the_pause() {
        let mut codec = Rtu::default();
        let odd = serial::encode(1, &[0x41, 1, 2, 3]);
        let mut b = BytesMut::from(&odd[..]);
        assert_eq!(codec.ended_by_pause(&b), Some(rtu::SILENCE));
        assert_eq!(codec.decode(&mut b), Ok(None));
        codec.paused();
        let adu = codec.decode(&mut b).unwrap().unwrap();
        assert_eq!(adu.pdu(), &[0x41, 1, 2, 3]);
        assert_eq!(Mbap.ended_by_pause(&BytesMut::from(&[0u8, 1][..])), None);
    }
}
