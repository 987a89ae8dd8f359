//! Who gets in (docs/security.md): a listener's allow list, applied before a single
//! byte of the connection is read, with refused sources logged at most once a minute
//! each; and on a TLS listener the handshake and the master's role, in the
//! connection's own task. Each refusal is counted on the listener, and every other
//! kind of refusal (`max_connections`, a failed or dropped handshake, a role refused)
//! is logged as the allow list's are: once a minute per source and reason, with the
//! count of those not said ([`Refusals`]).

use crate::access::allow::{RefusedLog, Tell};
use crate::access::AllowList;
use crate::ops::stats::Stats;
use crate::tls::server::{Acceptor, Grant, Refused};
use std::net::{IpAddr, SocketAddr};
use std::sync::Mutex;
use std::time::Instant;
use tokio::net::TcpStream;
use tokio_rustls::server::TlsStream;
use tracing::{info, warn};

/// A listener's gate: its name in the file (`listen[0]`), its allow list and the log
/// of the sources it refused.
#[derive(Debug)]
pub(crate) struct Gate {
    pub(crate) name: String,
    allow: Option<AllowList>,
    refused: RefusedLog,
}

impl Gate {
    pub(crate) fn new(name: String, allow: Option<AllowList>) -> Gate {
        Gate {
            name,
            allow,
            refused: RefusedLog::default(),
        }
    }

    /// Is `peer` taken? A refused one is counted and, at most once a minute per
    /// source, logged; the caller closes it without reading.
    pub(crate) fn admits(&mut self, peer: SocketAddr, stats: &Stats) -> bool {
        let Some(allow) = &self.allow else {
            return true;
        };
        let ip = peer.ip().to_canonical();
        if allow.allows(ip) {
            return true;
        }
        stats.add(&stats.connections_denied, 1);
        let name = &self.name;
        match self.refused.refused(ip, Instant::now()) {
            Tell::Quiet => {}
            Tell::Source { more: 0 } => warn!(
                %peer,
                "connection refused: {ip} is not in {name}.allow (said once a minute per source)"
            ),
            Tell::Source { more } => warn!(
                %peer,
                "connection refused: {ip} is not in {name}.allow ({more} more from it in the last minute)"
            ),
            Tell::Others { count } => warn!(
                "connections refused from {count} sources not in {name}.allow (too many sources to name each)"
            ),
        }
        false
    }
}

/// The log of a listener's refusals other than its allow list's: each source and
/// reason said at its first refusal, then at most once a minute with the count of
/// those in between; past [`RefusedLog::SOURCES`] pairs, told together. Shared by the
/// accept loop and the connections' tasks.
#[derive(Debug, Default)]
pub(crate) struct Refusals {
    log: Mutex<RefusedLog<(IpAddr, String)>>,
}

/// How loud a refusal is: a warning for what an operator must act on (a master
/// turned away at `max_connections`, a certificate whose role is refused), else info
/// (a peer that failed its handshake: scanners, health checks, attackers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Loud {
    Warn,
    Info,
}

impl Refusals {
    /// `peer` was refused for `why` (the same words each time for one reason; the
    /// details that vary go in `detail`, said when the line is).
    pub(crate) fn refused(&self, peer: SocketAddr, why: &str, detail: &str, loud: Loud) {
        let ip = peer.ip().to_canonical();
        let tell = self
            .log
            .lock()
            .expect("not poisoned")
            .refused((ip, why.to_owned()), Instant::now());
        let line = match tell {
            Tell::Quiet => return,
            Tell::Source { more: 0 } => {
                format!("connection refused: {why}{detail} (said once a minute per source and reason)")
            }
            Tell::Source { more } => format!(
                "connection refused: {why}{detail} ({more} more from {ip} in the last minute)"
            ),
            Tell::Others { count } => format!(
                "connections refused: {why} ({count} from sources too many to name each, in the last minute)"
            ),
        };
        match loud {
            Loud::Warn => warn!(%peer, "{line}"),
            Loud::Info => info!(%peer, "{line}"),
        }
    }
}

/// The TLS handshake and the role of the master on `stream`; a refusal is logged
/// (with the reason rustls or the role check gave, rate-limited by `refusals`) and
/// counted.
pub(crate) async fn handshake(
    acceptor: &Acceptor,
    stream: TcpStream,
    conn: u64,
    peer: SocketAddr,
    stats: &Stats,
    refusals: &Refusals,
) -> Option<(TlsStream<TcpStream>, Grant)> {
    match acceptor.accept(stream).await {
        Ok(admitted) => Some(admitted),
        Err(refused) => {
            let counter = match refused {
                Refused::Role(_) => &stats.tls_refused,
                Refused::TimedOut(_) | Refused::Handshake(_) => &stats.tls_failed,
            };
            stats.add(counter, 1);
            let table = acceptor.name();
            let why = format!("{table}: master refused: {refused}");
            let detail = format!(" (conn {conn})");
            match refused {
                Refused::Role(_) => refusals.refused(peer, &why, &detail, Loud::Warn),
                _ => refusals.refused(peer, &why, &detail, Loud::Info),
            }
            None
        }
    }
}
