//! What a master sends that is no request but an answer (`frame::pdu::not_a_request`:
//! an exception, a reply's shape; on UDP the gateway's own reply sent back), and the
//! exception replies a UDP source is owed past its budget: never answered or sent,
//! since an answer to an answer is how two peers that answer everything loop for ever
//! (docs/security.md "Threat model"). Each is counted on its listener and logged the
//! first time of each kind on that listener, then at most once a minute with the count
//! in between, as the allow list's refusals are.

use super::Connection;
use crate::access::allow::{RefusedLog, Tell};
use crate::frame::hex::Hex;
use crate::frame::pdu::NotRequest;
use crate::frame::Adu;
use crate::ops::stats::Stats;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use tracing::warn;

/// What was not answered, or not sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(crate) enum Unasked {
    /// A frame that is no request (`not_requests`).
    Answer(NotRequest),
    /// The very reply a peer was just sent, come back: on UDP a reflection or a loop
    /// with another server, on a dial a server that echoes (`not_requests`).
    Reflected,
    /// An exception reply to a UDP source past its budget (`exceptions_limited`).
    ExceptionLimited,
}

impl Unasked {
    fn said(self) -> &'static str {
        match self {
            Unasked::Answer(NotRequest::Exception) => {
                "an exception reply came where a request belongs: dropped, never answered"
            }
            Unasked::Answer(NotRequest::ReplyShape) => {
                "a reply came where a request belongs (a reply's shape): dropped, never answered"
            }
            Unasked::Reflected => {
                "a peer sent back the very reply it was just sent (a UDP source's reflection, a loop with another server, a dialed server that echoes): dropped, never answered"
            }
            Unasked::ExceptionLimited => {
                "a UDP source was owed more exception replies than its budget: those past it not sent"
            }
        }
    }
}

/// The log of every listener's frames not answered, each listener known by its
/// counters (each listener and each dial has its own [`Stats`] for its life, as
/// /metrics shows them), shared by all of them.
#[derive(Debug, Default)]
pub(crate) struct UnaskedLog {
    log: Mutex<RefusedLog<(usize, Unasked)>>,
}

impl UnaskedLog {
    /// `frame`, from or to `peer` on the listener counting in `stats` (at `local`),
    /// was not answered (or not sent) for `what`: counted, and said if due.
    pub(crate) fn note(
        &self,
        what: Unasked,
        stats: &Arc<Stats>,
        peer: SocketAddr,
        local: SocketAddr,
        frame: &[u8],
    ) {
        let counter = match what {
            Unasked::ExceptionLimited => &stats.exceptions_limited,
            _ => &stats.not_requests,
        };
        stats.add(counter, 1);
        let listener = Arc::as_ptr(stats) as usize;
        let tell = self
            .log
            .lock()
            .expect("not poisoned")
            .refused((listener, what), Instant::now());
        let said = what.said();
        let frame = Hex(&frame[..frame.len().min(16)]);
        match tell {
            Tell::Quiet => {}
            Tell::Source { more: 0 } => warn!(
                %peer, %local, %frame,
                "{said} (said once a minute per listener and kind)"
            ),
            Tell::Source { more } => warn!(
                %peer, %local, %frame,
                "{said} ({more} more on this listener in the last minute)"
            ),
            Tell::Others { count } => {
                warn!("{said} ({count} on listeners too many to name each, in the last minute)")
            }
        }
    }
}

impl Connection {
    /// `adu`, read where a request belongs, is an answer: not answered, counted and
    /// said (its ticket, dropped by the caller, holds no later reply up).
    pub(in crate::masters::tcp) fn unasked(&self, what: NotRequest, adu: &Adu) {
        let what = Unasked::Answer(what);
        self.unasked
            .note(what, &self.stats, self.peer, self.local, adu.as_bytes());
    }
}
