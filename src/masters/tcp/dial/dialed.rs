//! A dialed connection's own state, apart from the connection every master comes
//! through: the heartbeat it sends, the echoes of it and of the identity the server
//! may send back (`dial/echo.rs`), the reply last written that reads as a request
//! (`tcp/reflect.rs`), how long the server may leave a reply unread; and what the
//! connection's reader and writer do with it (its [`Origin`]).

use super::echo;
use crate::config::dial::DialConfig;
use crate::frame::Adu;
use crate::masters::tcp::connection::codec::MasterCodec;
use crate::masters::tcp::connection::{Connection, Origin};
use crate::masters::tcp::reflect::Loops;
use crate::masters::tcp::unasked::Unasked;
use bytes::BytesMut;
use std::sync::Mutex;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info};

/// What a dialed connection sends of its own, and the echoes it may get back.
pub(in crate::masters::tcp) struct Dialed {
    /// Sent after `every` without a reply written; empty: never.
    pub(in crate::masters::tcp) heartbeat: Vec<u8>,
    pub(in crate::masters::tcp) every: Duration,
    echoes: Mutex<echo::Echoes>,
    /// The last reply written that reads as a request (a write's): its echo is no
    /// request (`tcp/reflect.rs`).
    replied: Mutex<Loops>,
    /// How long the server may leave a reply unread before the connection is closed
    /// (and dialed again): never for ever, since mbgate has no other way to it.
    pub(in crate::masters::tcp) stall: Duration,
}

impl Origin for Dialed {
    #[inline(always)]
    fn dialed(&self) -> Option<&Dialed> {
        Some(self)
    }
}

impl Dialed {
    /// A connection of `dial` begins: `held` is the most of the server's bytes held
    /// for an answer owed.
    pub(super) fn new(dial: &DialConfig, held: usize) -> Dialed {
        Dialed {
            heartbeat: dial.heartbeat.clone(),
            every: Duration::from_millis(dial.heartbeat_ms),
            // An answer to the identity or a heartbeat is owed until the server
            // answered, or for as long as the dial waits for any of its answers; no
            // more bytes are held for it than the replies the connection can be owed.
            echoes: Mutex::new(echo::Echoes::new(
                dial.identity.clone(),
                dial.heartbeat.clone(),
                Duration::from_millis(dial.connect_timeout_ms),
                held,
                Instant::now(),
            )),
            replied: Mutex::new(Loops::new(Instant::now())),
            stall: Duration::from_millis(match dial.idle_timeout_ms {
                0 => dial.connect_timeout_ms,
                idle => idle,
            }),
        }
    }

    /// What the front of `buf` is (`dial/echo.rs`): the server's echo or answer taken
    /// off (counted, said once a connection at info, then at debug), bytes held until
    /// a pause, or the codec's request.
    pub(in crate::masters::tcp) fn front<C: MasterCodec>(
        &self,
        conn: &Connection,
        buf: &mut BytesMut,
        codec: &mut C,
    ) -> echo::Front {
        let mut echoes = self.echoes.lock().expect("not poisoned");
        let front = echoes.next(buf, codec);
        if let echo::Front::Answered(answered) = front {
            conn.stats.add(&conn.stats.dial_answers, 1);
            let first = echoes.first(answered);
            drop(echoes);
            let (what, n) = match answered {
                echo::Answered::Echo(n) => ("echoed the identity or a heartbeat", n),
                echo::Answered::Answer(n) => ("answered the identity or a heartbeat", n),
            };
            if first {
                info!(conn = conn.id, peer = %conn.peer, "the server {what} ({n} bytes): dropped, never relayed (said once a connection; counted in dial_answers)");
            } else {
                debug!(conn = conn.id, bytes = n, "the server {what}: dropped");
            }
        }
        front
    }

    /// Is `adu`, from the server, the very reply last written to it come back (a
    /// server that echoes every byte sends a write's reply back, and it reads as the
    /// write)? Counted and said as an answer not answered; its bytes are gone.
    pub(in crate::masters::tcp) fn came_back<C: MasterCodec>(
        &self,
        conn: &Connection,
        adu: &Adu,
    ) -> bool {
        let frame = C::frame(adu);
        let replied = self.replied.lock().expect("not poisoned");
        if !replied.came_back(&frame, Instant::now()) {
            return false;
        }
        drop(replied);
        let what = Unasked::Reflected;
        conn.unasked
            .note(what, &conn.stats, conn.peer, conn.local, adu.as_bytes());
        true
    }

    /// Bytes of the server's came `at`.
    pub(in crate::masters::tcp) fn came(&self, at: Instant) {
        self.echoes.lock().expect("not poisoned").came(at);
    }

    /// The server closed its sending side with `buf` held: true if its bytes are to
    /// be judged before the reader ends.
    pub(in crate::masters::tcp) fn ended(&self, buf: &BytesMut) -> bool {
        if buf.is_empty() {
            return false;
        }
        self.echoes.lock().expect("not poisoned").ended();
        true
    }

    /// The reader waited for a pause and no byte came, until `now`.
    pub(in crate::masters::tcp) fn paused(&self, now: Instant) {
        self.echoes.lock().expect("not poisoned").paused(now);
    }

    /// A heartbeat is sent `now`.
    pub(in crate::masters::tcp) fn beat(&self, now: Instant) {
        self.echoes.lock().expect("not poisoned").beat(now);
    }

    /// A reply was written to the server, framed as `frame`: remembered if it reads
    /// as a request, so that it coming straight back is not run again.
    pub(in crate::masters::tcp) fn replied(&self, frame: &[u8], pdu: &[u8], now: Instant) {
        let mut replied = self.replied.lock().expect("not poisoned");
        replied.remember(frame, pdu, now);
    }
}
