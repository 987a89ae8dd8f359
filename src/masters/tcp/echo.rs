//! The echoes a dialed connection may get back (docs/dialing.md "What the server must
//! do"): a server may answer mbgate's identity and heartbeat bytes with nothing, or
//! with the very same bytes. Such an echo, met where a request would begin while one
//! is owed, is dropped and never taken for a request; anything else is read as the
//! framing says. Plain data; the connection's loops drive it.

/// The identity and heartbeat sent on one connection, and the echoes still owed.
#[derive(Debug, Default)]
pub(super) struct Echoes {
    identity: Vec<u8>,
    heartbeat: Vec<u8>,
    /// The identity was sent and its echo not yet met.
    identity_owed: bool,
    /// Heartbeats sent whose echo was not met.
    heartbeats_owed: u64,
}

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
            identity,
            heartbeat,
            heartbeats_owed: 0,
        }
    }

    /// A heartbeat was sent.
    pub(super) fn beat(&mut self) {
        self.heartbeats_owed = self.heartbeats_owed.saturating_add(1);
    }

    /// An owed echo at the front of `buf` is taken off it.
    pub(super) fn strip(&mut self, buf: &mut bytes::BytesMut) -> Strip {
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
    use bytes::BytesMut;

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

    #[test]
    fn nothing_to_echo_takes_nothing() {
        let mut e = Echoes::new(Vec::new(), Vec::new());
        e.beat();
        let mut buf = BytesMut::from(&b"\x00\x01"[..]);
        assert_eq!(e.strip(&mut buf), Strip::Not);
        assert_eq!(buf.len(), 2);
    }
}
