//! Who gets in (docs/security.md): a listener's allow list, applied before a single
//! byte of the connection is read, with refused sources logged at most once a minute
//! each; and on a TLS listener the handshake and the master's role, in the
//! connection's own task. Each refusal is counted on the listener.

use crate::access::allow::{RefusedLog, Tell};
use crate::access::AllowList;
use crate::stats::Stats;
use crate::tls::server::{Acceptor, Grant, Refused};
use std::net::SocketAddr;
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

/// The TLS handshake and the role of the master on `stream`; a refusal is logged
/// (with the reason rustls or the role check gave) and counted.
pub(crate) async fn handshake(
    acceptor: &Acceptor,
    stream: TcpStream,
    conn: u64,
    peer: SocketAddr,
    stats: &Stats,
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
            match refused {
                Refused::Role(_) => warn!(conn, %peer, "{table}: master refused: {refused}"),
                _ => info!(conn, %peer, "{table}: master refused: {refused}"),
            }
            None
        }
    }
}
