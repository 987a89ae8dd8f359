//! The masters' side (docs/design.md §1 steps 1-2, §4 `[tcp]`, §4.1 `[[listen]]`):
//! what its parts share. A master comes through one connection type
//! (`tcp/connection/`) from any of three sources, each a folder apart from it:
//! accepted by a listener (`tcp/accept/`), dialed (`tcp/dial/`), or a UDP source
//! (`tcp/udp/`). Its reader (`tcp/connection/reader.rs`) hands strictly checked
//! requests to the line serving their unit ([`crate::masters::router`]), its writer
//! (`tcp/connection/writer.rs`) writes back their replies in the order of the
//! requests (the path back is [`crate::line::outbox`]). Here: the listener's socket,
//! and what every connection shares (the running configuration among it,
//! `tcp/live.rs`).
use crate::config::ListenConfig;
use crate::frame::mbap::MAX_ADU;
use crate::line::outbox;
use crate::masters::router::Router;
use crate::ops::capture::Hub;
use crate::ops::metrics::ConnectedMasters;
use crate::ops::stats::Stats;
use crate::tls::server::Acceptor;
use std::net::SocketAddr;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use tokio::net::{TcpListener, TcpSocket};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

mod accept;
mod connection;
pub(crate) mod dial;
pub(crate) mod live;
mod reflect;
pub(crate) mod tally;
pub(crate) mod udp;

pub(crate) use accept::accept_loop;
use connection::{unasked, Connection};

/// Binds the masters' listener. Every connection it accepts inherits its send buffer,
/// capped here at room for all the replies mbgate can owe one master (the kernel
/// doubles the figure). Left to itself Linux grows a send buffer up to `tcp_wmem`
/// (4 MiB by default): a master that never reads would pin that much kernel memory,
/// and thousands of replies would queue for it before its writer stalled and
/// `idle_timeout_ms` could close it. The serial line, not this buffer, bounds the
/// rate of replies, so a master that reads loses nothing by it.
pub(crate) fn listen(addr: SocketAddr, max_pending: usize) -> std::io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    // As `TcpListener::bind` does.
    socket.set_reuseaddr(true)?;
    socket.set_send_buffer_size(send_buffer(max_pending))?;
    socket.bind(addr)?;
    socket.listen(1024)
}

/// A listener's socket: TCP, or UDP (`tcp/udp/mod.rs`).
pub(crate) enum Socket {
    Tcp(TcpListener),
    Udp(tokio::net::UdpSocket),
}

impl Socket {
    /// The address it is bound to (port 0 is a real port by now).
    pub(crate) fn local_addr(&self) -> std::io::Result<SocketAddr> {
        match self {
            Socket::Tcp(l) => l.local_addr(),
            Socket::Udp(u) => u.local_addr(),
        }
    }
}

/// The send buffer of a master's socket: room for every reply it can be owed
/// ([`listen`] says why no more).
pub(crate) fn send_buffer(max_pending: usize) -> u32 {
    let room = outbox::capacity(max_pending) * MAX_ADU;
    u32::try_from(room).unwrap_or(u32::MAX)
}

/// What every listener's connections share: the configuration as it runs, the lines,
/// the counters (each listener its own), connection ids (unique across listeners),
/// the masters connected, shutdown and the task tracker.
#[derive(Clone)]
pub(crate) struct Shared {
    /// The configuration as it runs now: the gateway's, a reload publishes the new
    /// one through it (`tcp/live.rs`).
    pub(crate) running: live::Running,
    pub(crate) router: Arc<Router>,
    pub(crate) stats: Arc<Stats>,
    pub(crate) shutdown: CancellationToken,
    pub(crate) tracker: TaskTracker,
    pub(crate) ids: Arc<AtomicU64>,
    pub(crate) masters: Arc<ConnectedMasters>,
    /// The capture (docs/capture.md): the TCP side is its interface 0.
    pub(crate) capture: Hub,
    /// Answers masters sent where requests belong, said once a minute per listener.
    pub(crate) unasked: Arc<unasked::UnaskedLog>,
}

/// One listener as the accept loop runs it: its configuration, its name in the file
/// (`listen[0]`), the address it is bound to, and its TLS acceptor if it has one.
pub(crate) struct Listening {
    pub(crate) listen: ListenConfig,
    pub(crate) name: String,
    pub(crate) local: SocketAddr,
    pub(crate) tls: Option<Arc<Acceptor>>,
}
