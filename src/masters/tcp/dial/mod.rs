//! A master mbgate dials (`[[dial]]`, docs/dialing.md): connect out to the server,
//! send the identity, then serve the connection as an accepted one is served (the
//! one connection type of `crate::masters::tcp`: codec, access, per-master order, metrics);
//! when it ends or cannot be made, dial again, for ever, after an exponential backoff
//! with jitter within the dial's bounds. The name is resolved again at each attempt,
//! TCP keepalive finds a peer that vanished, and the log says once what is wrong and
//! once when it is right again ([`Outage`]).

use super::connection::Ended;
use super::tally::SourceTally;
use super::{Connection, Shared};
use crate::config::dial::{DialConfig, TlsDial};
use crate::line::port::Backoff;
use crate::tls::client::Connector;
use crate::tls::server::{grant, Grant, RoleRefused};
use crate::tls::TlsError;
use socket2::{SockRef, TcpKeepalive};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::time::Instant;
use tokio_rustls::client::TlsStream;
use tracing::{debug, info, warn};

mod dialed;
pub(super) mod echo;

pub(super) use dialed::Dialed;

/// Keepalive: the first probe after this much silence, then every `KEEPALIVE_EVERY`,
/// the connection dropped after `KEEPALIVE_PROBES` unanswered (about 25 s in all, as
/// a device's socket, `port/tcp.rs`): a server gone without a word behind a NAT is
/// noticed and dialed again.
const KEEPALIVE_IDLE: Duration = Duration::from_secs(10);
const KEEPALIVE_EVERY: Duration = Duration::from_secs(5);
const KEEPALIVE_PROBES: u32 = 3;

/// A connection that stayed up this long (or `backoff_max_ms`, if shorter) was a good
/// one: the backoff starts over and the log says the dial is back. A server that
/// accepts and closes at once is an outage like one that refuses.
const SETTLE: Duration = Duration::from_secs(5);

/// Why an attempt to dial failed, or why its connection ended: said once by the
/// outage's warning, then at debug.
#[derive(Debug, thiserror::Error)]
pub(super) enum DialError {
    #[error("cannot resolve {address}: {source}")]
    Resolve {
        address: String,
        source: std::io::Error,
    },
    #[error("cannot resolve {address} within {within:?}")]
    ResolveTimeout { address: String, within: Duration },
    #[error("{0} resolves to no address")]
    NoAddress(String),
    #[error("cannot make a socket: {0}")]
    Socket(std::io::Error),
    #[error("cannot connect to {addr}: {source}")]
    Connect {
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("no connection to {addr} within {within:?}")]
    ConnectTimeout { addr: SocketAddr, within: Duration },
    #[error("TLS: {0}")]
    TlsFiles(#[from] TlsError),
    #[error("TLS handshake failed: {0}")]
    Handshake(std::io::Error),
    #[error("no TLS handshake within {0:?}")]
    HandshakeTimeout(Duration),
    #[error("the server presented no certificate")]
    NoCertificate,
    #[error("the server is refused: {}", refused(.0))]
    Refused(RoleRefused),
    #[error("the identity could not be sent: {0}")]
    Identity(std::io::Error),
    #[error("the identity could not be sent within {0:?}")]
    IdentityTimeout(Duration),
    #[error("the connection to {peer} ended: {why}")]
    Ended { peer: SocketAddr, why: Ended },
}

/// Why a server's certificate is refused, in a dial's words: the role a certificate
/// without one takes is the dial's own `tls.default_role`, not a listener's.
fn refused(why: &RoleRefused) -> String {
    match why {
        RoleRefused::NoRole { subject } => format!(
            "the certificate of {subject:?} carries no Modbus role and the dial has no tls.default_role"
        ),
        other => other.to_string(),
    }
}

/// Dials `dial` (`name`: `dial[0]`) until shutdown; its counters are `shared.stats`.
pub(crate) async fn dial_loop(name: String, dial: DialConfig, shared: Shared) {
    let listen = Arc::new(dial.masters());
    let mut backoff = Backoff::new(
        Duration::from_millis(dial.backoff_min_ms),
        Duration::from_millis(dial.backoff_max_ms),
    );
    let settle = SETTLE.min(Duration::from_millis(dial.backoff_max_ms));
    let mut outage = Outage::new(&name, &dial);
    let shutdown = shared.shutdown.clone();
    loop {
        // As the configuration runs now (a reload does not change it).
        let max_pending = shared.running.borrow().max_pending_per_connection();
        let attempt = tokio::select! {
            _ = shutdown.cancelled() => break,
            a = connect(&dial, max_pending) => a,
        };
        match attempt {
            Err(why) => outage.failed(&why),
            Ok((stream, peer)) => {
                let (mut conn, dialed) = connection(&shared, &listen, &dial, &stream, peer);
                shared.stats.add(&shared.stats.connections, 1);
                let began = Instant::now();
                let why = match &dial.tls {
                    None => serve((conn, dialed), stream, &dial, &mut outage, settle).await,
                    Some(t) => match secure(t, &dial, stream, &shared).await {
                        Ok((tls, grant)) => {
                            conn.grant = Some(grant);
                            serve((conn, dialed), tls, &dial, &mut outage, settle).await
                        }
                        Err(why) => Err(why),
                    },
                };
                shared.stats.add(&shared.stats.connections_closed, 1);
                if began.elapsed() >= settle {
                    backoff.reset();
                }
                if shutdown.is_cancelled() {
                    break;
                }
                outage.failed(&match why {
                    // Why the attempt failed after the connect (TLS, the identity).
                    Err(e) => e,
                    Ok(why) => DialError::Ended { peer, why },
                });
            }
        }
        let delay = jittered(backoff.next_delay());
        debug!(dial = %name, "dialing again in {} ms", delay.as_millis());
        tokio::select! {
            _ = shutdown.cancelled() => break,
            _ = tokio::time::sleep(delay) => {}
        }
    }
    debug!(dial = %name, "dial stopped");
}

/// The wait before the next attempt: between half of `delay` and all of it, so many
/// gateways cut off at once (a server restarted) do not all dial again at once.
fn jittered(delay: Duration) -> Duration {
    let ms = u64::try_from(delay.as_millis()).unwrap_or(u64::MAX);
    Duration::from_millis(fastrand::u64(ms / 2..=ms))
}

/// One attempt: the name resolved now, each of its addresses tried in turn within
/// `connect_timeout_ms` in all, keepalive and Nagle set, the send buffer capped as an
/// accepted master's (`tcp::listen`).
async fn connect(
    dial: &DialConfig,
    max_pending: usize,
) -> Result<(TcpStream, SocketAddr), DialError> {
    let within = Duration::from_millis(dial.connect_timeout_ms);
    let deadline = Instant::now() + within;
    let resolved = tokio::time::timeout_at(deadline, tokio::net::lookup_host(&dial.address));
    let addrs: Vec<SocketAddr> = match resolved.await {
        Ok(Ok(addrs)) => addrs.collect(),
        Ok(Err(source)) => {
            let address = dial.address.clone();
            return Err(DialError::Resolve { address, source });
        }
        Err(_) => {
            let address = dial.address.clone();
            return Err(DialError::ResolveTimeout { address, within });
        }
    };
    let mut last = DialError::NoAddress(dial.address.clone());
    for addr in addrs {
        let socket = match addr {
            SocketAddr::V4(_) => tokio::net::TcpSocket::new_v4(),
            SocketAddr::V6(_) => tokio::net::TcpSocket::new_v6(),
        };
        let socket = socket
            .and_then(|s| {
                s.set_send_buffer_size(super::send_buffer(max_pending))
                    .map(|()| s)
            })
            .map_err(DialError::Socket)?;
        match tokio::time::timeout_at(deadline, socket.connect(addr)).await {
            Ok(Ok(stream)) => {
                let _ = stream.set_nodelay(true);
                let keepalive = TcpKeepalive::new()
                    .with_time(KEEPALIVE_IDLE)
                    .with_interval(KEEPALIVE_EVERY)
                    .with_retries(KEEPALIVE_PROBES);
                if let Err(e) = SockRef::from(&stream).set_tcp_keepalive(&keepalive) {
                    debug!(%addr, "TCP keepalive: {e}");
                }
                return Ok((stream, addr));
            }
            Ok(Err(source)) => last = DialError::Connect { addr, source },
            Err(_) => return Err(DialError::ConnectTimeout { addr, within }),
        }
    }
    Err(last)
}

/// The connection as an accepted one is made, and the dial's own state beside it.
fn connection(
    shared: &Shared,
    listen: &Arc<crate::config::ListenConfig>,
    dial: &DialConfig,
    stream: &TcpStream,
    peer: SocketAddr,
) -> (Connection, Dialed) {
    let local = stream
        .local_addr()
        .unwrap_or(SocketAddr::from(([0, 0, 0, 0], 0)));
    // As the configuration runs now (a reload does not change it).
    let max_pending = shared.running.borrow().max_pending_per_connection();
    let dialed = Dialed::new(dial, super::send_buffer(max_pending) as usize);
    (Connection::new(shared, listen.clone(), peer, local), dialed)
}

/// The TLS handshake with the server within `connect_timeout_ms` (the files read
/// again at each attempt, so a renewed certificate is used from the next one on), and
/// the role its certificate carries (docs/security.md "What a master may do"), as a
/// listener takes a master's; a refusal is counted as a listener's and said as why
/// the attempt failed.
async fn secure(
    t: &TlsDial,
    dial: &DialConfig,
    stream: TcpStream,
    shared: &Shared,
) -> Result<(TlsStream<TcpStream>, Grant), DialError> {
    let stats = &shared.stats;
    let connector = Connector::load(&t.client, &dial.address, "dial.tls")?;
    let within = Duration::from_millis(dial.connect_timeout_ms);
    let tls = match tokio::time::timeout(within, connector.connect(stream)).await {
        Ok(Ok(tls)) => tls,
        Ok(Err(e)) => {
            stats.add(&stats.tls_failed, 1);
            return Err(DialError::Handshake(e));
        }
        Err(_) => {
            stats.add(&stats.tls_failed, 1);
            return Err(DialError::HandshakeTimeout(within));
        }
    };
    let der = tls.get_ref().1.peer_certificates().and_then(|c| c.first());
    let Some(der) = der else {
        stats.add(&stats.tls_refused, 1);
        return Err(DialError::NoCertificate);
    };
    // The roles as the configuration runs now.
    let granted = grant(
        der,
        &shared.running.borrow().roles,
        t.default_role.as_deref(),
    );
    match granted {
        Ok(g) => Ok((tls, g)),
        Err(refused) => {
            stats.add(&stats.tls_refused, 1);
            Err(DialError::Refused(refused))
        }
    }
}

/// The identity sent, then the connection served until it ends; once it has stayed
/// up for `settle`, the outage (if any) is over. Why it ended; `Err`: the identity
/// could not be sent.
async fn serve<S: Halves>(
    (conn, dialed): (Connection, Dialed),
    mut stream: S,
    dial: &DialConfig,
    outage: &mut Outage,
    settle: Duration,
) -> Result<Ended, DialError> {
    let peer = conn.peer;
    if !dial.identity.is_empty() {
        let within = Duration::from_millis(dial.connect_timeout_ms);
        // Flushed: a TLS stream holds what it could not send at once until then.
        let send = async {
            stream.write_all(&dial.identity).await?;
            stream.flush().await
        };
        match tokio::time::timeout(within, send).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(DialError::Identity(e)),
            Err(_) => return Err(DialError::IdentityTimeout(within)),
        }
    }
    outage.connected(peer);
    let (rd, wr) = stream.halves();
    let served = conn.run(dialed, rd, wr);
    tokio::pin!(served);
    tokio::select! {
        why = &mut served => return Ok(why),
        _ = tokio::time::sleep(settle) => outage.settled(peer),
    }
    Ok(served.await)
}

/// A dialed stream cut in its reading and writing halves: a plain socket's own
/// halves (no lock between them, as an accepted connection's), a TLS stream's shared.
trait Halves: AsyncRead + AsyncWrite + Unpin {
    type Rd: AsyncRead + Unpin;
    type Wr: AsyncWrite + Unpin;
    fn halves(self) -> (Self::Rd, Self::Wr);
}

impl Halves for TcpStream {
    type Rd = tokio::net::tcp::OwnedReadHalf;
    type Wr = tokio::net::tcp::OwnedWriteHalf;
    fn halves(self) -> (Self::Rd, Self::Wr) {
        self.into_split()
    }
}

impl Halves for TlsStream<TcpStream> {
    type Rd = tokio::io::ReadHalf<Self>;
    type Wr = tokio::io::WriteHalf<Self>;
    fn halves(self) -> (Self::Rd, Self::Wr) {
        tokio::io::split(self)
    }
}

/// What the log says of one dial: at the first failure what is wrong (a warning), the
/// failures after it at debug, and when a connection has held again, that it is back
/// (with how many attempts failed between), as a serial port's lifecycle does.
struct Outage {
    name: String,
    address: String,
    bounds: String,
    /// Failed attempts since the dial was last up; `None`: up (or never tried).
    failing: Option<(u64, Instant)>,
    /// It was ever up: the first connection says "connected", later ones "back".
    ever: bool,
}

impl Outage {
    fn new(name: &str, dial: &DialConfig) -> Outage {
        Outage {
            name: name.to_owned(),
            address: dial.address.clone(),
            bounds: format!("{} ms to {} ms", dial.backoff_min_ms, dial.backoff_max_ms),
            failing: None,
            ever: false,
        }
    }

    fn failed(&mut self, why: &DialError) {
        match &mut self.failing {
            Some((n, _)) => {
                *n += 1;
                debug!(dial = %self.name, failures = *n, "still failing: {why}");
            }
            None => {
                warn!(
                    dial = %self.name,
                    "{} ({}): {why}; dialing again with backoff ({}), said again when it is back",
                    self.name, self.address, self.bounds
                );
                self.failing = Some((1, Instant::now()));
            }
        }
    }

    /// Connected to `peer`: said at once the first time the dial is up.
    fn connected(&mut self, peer: SocketAddr) {
        if self.ever || self.failing.is_some() {
            debug!(dial = %self.name, %peer, "connected");
            return;
        }
        info!(dial = %self.name, "{} ({}): connected to {peer}", self.name, self.address);
        self.ever = true;
    }

    /// A connection to `peer` has held for the settle time.
    fn settled(&mut self, peer: SocketAddr) {
        if let Some((n, since)) = self.failing.take() {
            info!(
                dial = %self.name,
                "{} ({}): connected to {peer} again, after {n} failed attempts over {} s",
                self.name,
                self.address,
                since.elapsed().as_secs()
            );
        }
        self.ever = true;
    }
}

/// The dials running, as a reload finds them: each its configuration, the token that
/// stops it and its counters.
pub(crate) struct Dials {
    shared: Shared,
    tally: Arc<SourceTally>,
    running: Vec<RunningDial>,
}

struct RunningDial {
    dial: DialConfig,
    stop: tokio_util::sync::CancellationToken,
    stats: Arc<crate::ops::stats::Stats>,
}

impl Dials {
    /// None running yet; each dial started by [`Dials::apply`] runs on `shared`'s
    /// tracker, its counters in `tally` (on the metrics as a listener's).
    pub(crate) fn new(shared: Shared, tally: Arc<SourceTally>) -> Dials {
        Dials {
            shared,
            tally,
            running: Vec::new(),
        }
    }

    /// The dials of `dials` running, and no other: one unchanged keeps its
    /// connection, a new one starts, one gone or changed stops (its connection writes
    /// the replies it owes and closes; a changed one dials again at once as new).
    /// A dial to an address already dialed keeps its counters; one gone leaves the
    /// metrics, its counts staying in the totals.
    pub(crate) fn apply(&mut self, dials: &[DialConfig]) {
        let mut old = std::mem::take(&mut self.running);
        let mut kept_stats = Vec::new();
        for (i, d) in dials.iter().enumerate() {
            if let Some(p) = old.iter().position(|r| r.dial == *d) {
                self.running.push(old.remove(p));
                continue;
            }
            let kept = old.iter().find(|r| r.dial.address == d.address);
            let stats = match kept {
                Some(r) => {
                    kept_stats.push(r.stats.clone());
                    r.stats.clone()
                }
                None => self.tally.open(format!("dial {}", d.address)),
            };
            let stop = self.shared.shutdown.child_token();
            let shared = Shared {
                stats: stats.clone(),
                shutdown: stop.clone(),
                ..self.shared.clone()
            };
            self.shared
                .tracker
                .spawn(dial_loop(format!("dial[{i}]"), d.clone(), shared));
            self.running.push(RunningDial {
                dial: d.clone(),
                stop,
                stats,
            });
        }
        for r in old {
            r.stop.cancel();
            if !kept_stats.iter().any(|k| Arc::ptr_eq(k, &r.stats)) {
                self.tally.close(&r.stats);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A server refused for want of a role is told in a dial's words: the dial's
    /// `tls.default_role`, not a listener's.
    #[test]
    fn a_server_without_a_role_is_refused_in_a_dials_words() {
        let no_role = DialError::Refused(RoleRefused::NoRole {
            subject: "CN=scada".into(),
        });
        assert_eq!(
            no_role.to_string(),
            "the server is refused: the certificate of \"CN=scada\" carries no Modbus role \
             and the dial has no tls.default_role"
        );
        let unknown = DialError::Refused(RoleRefused::Unknown {
            subject: "CN=scada".into(),
            role: "boss".into(),
        });
        assert!(unknown.to_string().contains("which no [[role]] names"));
    }
}
