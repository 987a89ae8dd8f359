//! The answers a dialed connection may get to its own bytes (docs/dialing.md "What the
//! server must do"): a server may answer mbgate's identity and heartbeat with nothing,
//! with the very same bytes (an echo), or with bytes of its own (an acknowledgement).
//! An echo met where a request would begin while one is owed is dropped; bytes there
//! that the framing refuses as a request, while an answer is owed, are that answer:
//! dropped and counted, never taken for a request, and the connection stays. Plain
//! data; the connection's loops drive it.

use bytes::BytesMut;

/// The identity and heartbeat sent on one connection, and the echoes still owed.
#[derive(Debug, Default)]
pub(super) struct Echoes {
    identity: Vec<u8>,
    heartbeat: Vec<u8>,
    /// The identity was sent and its echo not yet met.
    identity_owed: bool,
    /// Heartbeats sent whose echo was not met.
    heartbeats_owed: u64,
    /// Answers of the server's own the identity and the heartbeats sent may still
    /// get (at most [`ANSWERS_OWED`]).
    answers_owed: u8,
}

/// The most answers owed at once: a server that acknowledges only some heartbeats
/// does not earn a licence for garbage by the hour.
const ANSWERS_OWED: u8 = 4;

/// What the front of the bytes read is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Strip {
    /// An echo, taken off.
    Took,
    /// The start of an echo: wait for more bytes before deciding.
    Wait,
    /// No echo: a request, or what the framing makes of it.
    Not,
}

impl Echoes {
    /// The identity (empty: none) was just sent; `heartbeat` will be.
    pub(super) fn new(identity: Vec<u8>, heartbeat: Vec<u8>) -> Echoes {
        Echoes {
            identity_owed: !identity.is_empty(),
            answers_owed: u8::from(!identity.is_empty()),
            identity,
            heartbeat,
            heartbeats_owed: 0,
        }
    }

    /// A heartbeat was sent.
    pub(super) fn beat(&mut self) {
        self.heartbeats_owed = self.heartbeats_owed.saturating_add(1);
        self.answers_owed = (self.answers_owed + 1).min(ANSWERS_OWED);
    }

    /// The framing refused `buf` as a request: if an answer is owed, `buf` is it, all
    /// of it taken off (the server writes its answer in one go; a request sent on its
    /// heels is lost with it, and its master asks again). How many bytes were taken;
    /// `None`: no answer owed, `buf` breaks the protocol.
    pub(super) fn answer(&mut self, buf: &mut BytesMut) -> Option<usize> {
        if self.answers_owed == 0 {
            return None;
        }
        self.answers_owed -= 1;
        let n = buf.len();
        buf.clear();
        Some(n)
    }

    /// An owed echo at the front of `buf` is taken off it.
    pub(super) fn strip(&mut self, buf: &mut BytesMut) -> Strip {
        if buf.is_empty() {
            return Strip::Not;
        }
        let mut wait = false;
        for which in [Which::Identity, Which::Heartbeat] {
            let (bytes, owed) = match which {
                Which::Identity => (&self.identity, self.identity_owed),
                Which::Heartbeat => (&self.heartbeat, self.heartbeats_owed > 0),
            };
            if !owed || bytes.is_empty() {
                continue;
            }
            if buf.starts_with(bytes) {
                let n = bytes.len();
                let _ = buf.split_to(n);
                match which {
                    Which::Identity => self.identity_owed = false,
                    Which::Heartbeat => self.heartbeats_owed -= 1,
                }
                self.answers_owed = self.answers_owed.saturating_sub(1);
                return Strip::Took;
            }
            wait |= bytes.starts_with(buf);
        }
        if wait {
            Strip::Wait
        } else {
            Strip::Not
        }
    }
}

#[derive(Clone, Copy)]
enum Which {
    Identity,
    Heartbeat,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_owed_echo_is_dropped_and_a_request_is_not() {
        let mut e = Echoes::new(b"site-17".to_vec(), b"\xff\xfe".to_vec());
        let request: &[u8] = &[0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1];
        // The identity's echo, split across reads, then a request.
        let mut buf = BytesMut::from(&b"site"[..]);
        assert_eq!(e.strip(&mut buf), Strip::Wait);
        buf.extend_from_slice(b"-17");
        buf.extend_from_slice(request);
        assert_eq!(e.strip(&mut buf), Strip::Took);
        assert_eq!(&buf[..], request);
        assert_eq!(e.strip(&mut buf), Strip::Not, "owed no more");
        // A heartbeat echo only once one was sent, and once each.
        let mut hb = BytesMut::from(&b"\xff\xfe\xff\xfe"[..]);
        assert_eq!(e.strip(&mut hb), Strip::Not, "no heartbeat sent yet");
        e.beat();
        assert_eq!(e.strip(&mut hb), Strip::Took);
        assert_eq!(e.strip(&mut hb), Strip::Not, "one echo per heartbeat");
        assert_eq!(&hb[..], b"\xff\xfe");
    }

    /// An answer of the server's own: dropped whole, once per identity or heartbeat
    /// sent (no more than four owed), never when none is owed.
    #[test]
    fn an_answer_is_taken_once_per_byte_sent_and_no_more() {
        let mut e = Echoes::new(b"site-17".to_vec(), b"\xff\xfe".to_vec());
        let mut ack = BytesMut::from(&b"ACK\r\n"[..]);
        assert_eq!(e.answer(&mut ack), Some(5), "the identity's answer");
        assert!(ack.is_empty());
        assert_eq!(e.answer(&mut BytesMut::from(&b"x"[..])), None, "none owed");
        for _ in 0..10 {
            e.beat();
        }
        for _ in 0..ANSWERS_OWED {
            assert_eq!(e.answer(&mut BytesMut::from(&b"OK"[..])), Some(2));
        }
        assert_eq!(
            e.answer(&mut BytesMut::from(&b"OK"[..])),
            None,
            "four at most"
        );
        // An echo is the answer too: none left to take after it.
        e.beat();
        let mut echo = BytesMut::from(&b"\xff\xfe"[..]);
        assert_eq!(e.strip(&mut echo), Strip::Took);
        assert_eq!(e.answer(&mut BytesMut::from(&b"OK"[..])), None);
    }

    #[test]
    fn nothing_to_echo_takes_nothing() {
        let mut e = Echoes::new(Vec::new(), Vec::new());
        e.beat();
        let mut buf = BytesMut::from(&b"\x00\x01"[..]);
        assert_eq!(e.strip(&mut buf), Strip::Not);
        assert_eq!(buf.len(), 2);
    }
}
