//! Why the gateway could not start, with what a user can do about the failures people
//! meet first (a port held or below 1024).

use std::net::SocketAddr;

/// Why the gateway could not start.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// A listener's address could not be bound.
    ///
    /// The cause is part of the message, with what to do about it, and deliberately
    /// not a `source`: printed as a chain it would appear twice.
    #[error("cannot listen on {addr}: {error}{}", bind_hint(.error, *.addr))]
    Bind {
        /// The listener's address (`tcp.listen` or a `[[listen]]`).
        addr: SocketAddr,
        /// What the system said.
        error: std::io::Error,
    },
    /// A TLS file could not be used (read, parsed, or its key does not fit).
    #[error("{0}")]
    Tls(#[from] crate::tls::TlsError),
    /// A master line could not start (a passive route's address).
    #[error("{0}")]
    MasterLine(#[from] crate::line::bridge::BridgeError),
    /// The metrics listener's web configuration file could not be used.
    #[error("{0}")]
    Web(#[from] crate::ops::metrics::web::WebConfigError),
    /// `metrics.listen` could not be bound.
    #[error("cannot listen for metrics on {addr} (metrics.listen): {error}")]
    MetricsBind {
        /// The metrics address.
        addr: SocketAddr,
        /// What the system said.
        error: std::io::Error,
    },
}

/// What a user can do about a failed bind, for the two failures people meet first.
fn bind_hint(error: &std::io::Error, addr: SocketAddr) -> String {
    match error.kind() {
        std::io::ErrorKind::AddrInUse => {
            let other = SocketAddr::new(addr.ip(), addr.port().wrapping_add(1).max(1024));
            format!(
                " (another process holds port {}: stop it, or choose another port, \
                 e.g. --listen {other})",
                addr.port()
            )
        }
        std::io::ErrorKind::PermissionDenied if addr.port() < 1024 => format!(
            " (ports below 1024 need root or the CAP_NET_BIND_SERVICE capability, which the \
             systemd units grant; or choose a port above 1023, e.g. --listen {})",
            SocketAddr::new(addr.ip(), 5020)
        ),
        _ => String::new(),
    }
}
