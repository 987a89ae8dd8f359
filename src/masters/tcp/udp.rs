//! Modbus over UDP (`[[listen]]` with `transport = "udp"`, docs/dialing.md "Modbus
//! over UDP"): each datagram one MBAP request, its reply sent to the datagram's
//! source. Each source is a master of the one connection type (`tcp/connection.rs`:
//! access, per-master order, metrics), its requests handed to the line by the receive
//! loop itself and its replies sent by its writer: a source whose pipelining slots
//! are all in use has its next datagrams dropped, so a flood from one address takes no
//! more of the line than one master's share (`max_pending_per_connection`). A datagram that is not exactly one well-formed MBAP
//! request is dropped and counted, and closes nothing. At most `max_connections`
//! sources at once; one quiet for `idle_timeout_ms` is forgotten.

use super::codec::Mbap;
use super::tally::SourceTally;
use super::{admit, Connection, Listening, Shared};
use crate::config::{ListenConfig, Transport};
use crate::frame::mbap::{decode_strict, MAX_ADU};
use crate::frame::Adu;
use crate::line::outbox::Outbox;
use bytes::BytesMut;
use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, Waker};
use std::time::Duration;
use tokio::io::AsyncWrite;
use tokio::net::UdpSocket;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::debug;

/// Binds a UDP listener.
pub(crate) fn bind(addr: SocketAddr) -> io::Result<UdpSocket> {
    let socket = std::net::UdpSocket::bind(addr)?;
    socket.set_nonblocking(true)?;
    UdpSocket::from_std(socket)
}

/// `d` as one MBAP request, strictly checked; `None` unless it is exactly one.
fn one_request(d: &[u8]) -> Option<Adu> {
    let mut buf = BytesMut::from(d);
    match decode_strict(&mut buf) {
        Ok(Some(adu)) if buf.is_empty() => Some(adu),
        _ => None,
    }
}

/// One source: its connection, the outbox its requests take tickets from (here, in
/// the receive loop: no task between a datagram and the line), when it last sent,
/// and whether its writer has ended.
struct Source {
    conn: Arc<Connection>,
    outbox: Outbox,
    last: Instant,
    gone: CancellationToken,
}

impl Source {
    /// Its connection begun and its writer running on the tracker; `None`: the
    /// gateway is stopping.
    fn start(conn: Connection, socket: &Arc<UdpSocket>, shared: &Shared) -> Option<Source> {
        let conn = Arc::new(conn);
        let Some((outbox, inbox)) = conn.begin::<Mbap>() else {
            conn.end();
            return None;
        };
        let gone = CancellationToken::new();
        let writer = Replies {
            socket: socket.clone(),
            peer: conn.peer,
        };
        let (c, g, stats) = (conn.clone(), gone.clone(), shared.stats.clone());
        shared.tracker.spawn(async move {
            c.write_loop::<Mbap>(writer, inbox).await;
            g.cancel();
            c.end();
            stats.add(&stats.connections_closed, 1);
        });
        Some(Source {
            conn,
            outbox,
            last: Instant::now(),
            gone,
        })
    }

    /// `adu` (a datagram's one request) taken if the source has a pipelining slot
    /// free at once; `false`: dropped, the source has its share in flight.
    fn take(&mut self, adu: Adu) -> bool {
        let mut ticket = std::pin::pin!(self.outbox.ticket());
        let mut cx = Context::from_waker(Waker::noop());
        let Poll::Ready(ticket) = ticket.as_mut().poll(&mut cx) else {
            return false;
        };
        self.last = Instant::now();
        self.conn.take::<Mbap>(adu, ticket);
        true
    }

    /// Quiet for `idle` with nothing owed at `now`.
    fn idle(&self, idle: Duration, now: Instant) -> bool {
        self.outbox
            .idle_at(self.last, idle)
            .is_some_and(|at| at <= now)
    }

    /// Forgotten: off the lines, so its writer ends once the replies owed are written.
    fn forget(self) {
        self.conn.router.detach(self.conn.id);
    }
}

/// Takes datagrams on `socket` until shutdown. Each is handed to the line from this
/// loop, through its source's outbox (per-source order: the order received); a
/// source with no pipelining slot free has its datagram dropped, so a flood from one
/// address takes no more of the line than one master's share. Sources quiet for
/// `idle_timeout_ms` are forgotten (looked for at most once a second).
pub(crate) async fn datagram_loop(socket: Arc<UdpSocket>, listening: Listening, shared: Shared) {
    let Listening {
        listen,
        name,
        local,
        ..
    } = listening;
    let mut gate = admit::Gate::new(name, listen.access.allow.clone());
    let max_sources = listen.tcp.max_connections;
    let idle = Duration::from_millis(listen.tcp.idle_timeout_ms);
    let listen = Arc::new(listen);
    let stats = shared.stats.clone();
    let mut sources: HashMap<SocketAddr, Source> = HashMap::new();
    // One timer for the loop's life, moved at each sweep for idle sources.
    let sweep = tokio::time::sleep(SWEEP);
    tokio::pin!(sweep);
    // Made once, as the timer is: a cancellation future made again at each pass
    // registers and drops a waiter for each datagram (docs/performance.md "Dialed and
    // UDP masters").
    let stopped = shared.shutdown.cancelled();
    tokio::pin!(stopped);
    // Room for a datagram one byte too long to be a request: it is seen as such.
    let mut buf = vec![0u8; MAX_ADU + 1];
    loop {
        let received = tokio::select! {
            _ = &mut stopped => break,
            // Polled for readiness as a TCP stream is read, not awaited: `recv_from`
            // would queue and drop a waiter of its own for each datagram.
            r = std::future::poll_fn(|cx| {
                let mut filled = tokio::io::ReadBuf::new(&mut buf);
                let peer = std::task::ready!(socket.poll_recv_from(cx, &mut filled));
                std::task::Poll::Ready(peer.map(|p| (filled.filled().len(), p)))
            }) => r,
            _ = &mut sweep, if !idle.is_zero() && !sources.is_empty() => {
                let now = Instant::now();
                forget_where(&mut sources, |s| s.idle(idle, now));
                sweep.as_mut().reset(now + SWEEP);
                continue;
            }
        };
        let (n, peer) = match received {
            Ok(r) => r,
            Err(e) => {
                debug!(%local, "UDP receive failed: {e}");
                continue;
            }
        };
        if !gate.admits(peer, &stats) {
            continue;
        }
        let Some(adu) = one_request(&buf[..n]) else {
            stats.add(&stats.datagrams_dropped, 1);
            debug!(%peer, bytes = n, "a datagram that is not one MBAP request: dropped");
            continue;
        };
        // A source known and served: one look-up (each hashes the address).
        if let Some(source) = sources.get_mut(&peer) {
            if !source.gone.is_cancelled() {
                if !source.take(adu) {
                    stats.add(&stats.datagrams_dropped, 1);
                }
                continue;
            }
            // Its writer ended (a send failed): a new connection.
            if let Some(s) = sources.remove(&peer) {
                s.forget();
            }
        }
        if sources.len() >= max_sources {
            let now = Instant::now();
            forget_where(&mut sources, |s| {
                s.gone.is_cancelled() || (!idle.is_zero() && s.idle(idle, now))
            });
        }
        if sources.len() >= max_sources {
            stats.add(&stats.datagrams_dropped, 1);
            stats.add(&stats.connections_refused, 1);
            debug!(%peer, "max_connections ({max_sources}) sources: datagram dropped");
            continue;
        }
        stats.add(&stats.connections, 1);
        let conn = Connection::new(&shared, listen.clone(), peer, local);
        let Some(mut source) = Source::start(conn, &socket, &shared) else {
            stats.add(&stats.connections_closed, 1);
            continue;
        };
        if !source.take(adu) {
            stats.add(&stats.datagrams_dropped, 1);
        }
        sources.insert(peer, source);
    }
    for (_, s) in sources.drain() {
        s.forget();
    }
    debug!(%local, "UDP listener closed");
}

/// How often the receive loop looks for sources quiet for `idle_timeout_ms`.
const SWEEP: Duration = Duration::from_secs(1);

/// The sources for which `which` holds forgotten.
fn forget_where(sources: &mut HashMap<SocketAddr, Source>, which: impl Fn(&Source) -> bool) {
    let gone: Vec<SocketAddr> = sources
        .keys()
        .filter(|p| which(&sources[*p]))
        .copied()
        .collect();
    for p in gone {
        if let Some(s) = sources.remove(&p) {
            s.forget();
        }
    }
}

/// The UDP listeners running, as a reload finds them (docs/dialing.md "Reload"):
/// each its configuration, its socket, the token that stops it and its counters.
pub(crate) struct Udps {
    shared: Shared,
    tally: Arc<SourceTally>,
    running: Vec<RunningUdp>,
}

struct RunningUdp {
    listen: ListenConfig,
    socket: Arc<UdpSocket>,
    stop: tokio_util::sync::CancellationToken,
    stats: Arc<crate::ops::stats::Stats>,
}

impl Udps {
    pub(crate) fn new(shared: Shared, tally: Arc<SourceTally>) -> Udps {
        Udps {
            shared,
            tally,
            running: Vec::new(),
        }
    }

    /// A UDP listener bound at start, served from now on with its counters `stats`.
    pub(crate) fn adopt(
        &mut self,
        socket: UdpSocket,
        listening: Listening,
        stats: Arc<crate::ops::stats::Stats>,
    ) {
        let listen = listening.listen.clone();
        let socket = Arc::new(socket);
        let stop = self.start(socket.clone(), listening, stats.clone());
        self.running.push(RunningUdp {
            listen,
            socket,
            stop,
            stats,
        });
    }

    fn start(
        &self,
        socket: Arc<UdpSocket>,
        listening: Listening,
        stats: Arc<crate::ops::stats::Stats>,
    ) -> tokio_util::sync::CancellationToken {
        let stop = self.shared.shutdown.child_token();
        let shared = Shared {
            stats,
            shutdown: stop.clone(),
            ..self.shared.clone()
        };
        self.shared
            .tracker
            .spawn(datagram_loop(socket, listening, shared));
        stop
    }

    /// The UDP listeners of `listeners` running, and no other: one unchanged keeps
    /// its sources, one new is bound and started, one gone stops, one changed starts
    /// again with its new settings on the same socket (its sources begin anew). One
    /// gone leaves the metrics, its counts staying in the totals. What it did, in words (a listener that cannot be bound is said and left out).
    pub(crate) fn apply(&mut self, listeners: &[ListenConfig]) -> Vec<String> {
        let mut said = Vec::new();
        let mut old = std::mem::take(&mut self.running);
        let udp = listeners.iter().filter(|l| l.transport == Transport::Udp);
        for (i, l) in udp.enumerate() {
            if let Some(p) = old.iter().position(|r| r.listen == *l) {
                self.running.push(old.remove(p));
                continue;
            }
            let name = format!("udp[{i}]");
            let same_address = old.iter().position(|r| r.listen.tcp.listen == l.tcp.listen);
            let (socket, stats) = match same_address {
                Some(p) => {
                    let r = old.remove(p);
                    r.stop.cancel();
                    (r.socket, r.stats)
                }
                None => match bind(l.tcp.listen) {
                    Ok(s) => (Arc::new(s), self.tally.open(l.tcp.listen.to_string())),
                    Err(e) => {
                        said.push(format!("cannot listen on {} (UDP): {e}", l.tcp.listen));
                        continue;
                    }
                },
            };
            let local = socket.local_addr().unwrap_or(l.tcp.listen);
            tracing::info!("listening on {local} (UDP) for Modbus/UDP masters");
            let listening = Listening {
                listen: l.clone(),
                name,
                local,
                tls: None,
            };
            let stop = self.start(socket.clone(), listening, stats.clone());
            self.running.push(RunningUdp {
                listen: l.clone(),
                socket,
                stop,
                stats,
            });
        }
        for r in old {
            r.stop.cancel();
            self.tally.close(&r.stats);
        }
        said
    }
}

/// A source's replies, each written whole, each one datagram to the source.
struct Replies {
    socket: Arc<UdpSocket>,
    peer: SocketAddr,
}

impl AsyncWrite for Replies {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, b: &[u8]) -> Poll<io::Result<usize>> {
        self.socket.poll_send_to(cx, b, self.peer)
    }
    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
    fn poll_shutdown(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

#[cfg(test)]
mod tests {
    use super::one_request;

    #[test]
    fn a_datagram_is_one_whole_request_or_nothing() {
        let read: &[u8] = &[0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1];
        let adu = one_request(read).expect("one request");
        assert_eq!(adu.as_bytes(), read);
        assert!(one_request(&read[..11]).is_none(), "short");
        let mut two = read.to_vec();
        two.extend_from_slice(read);
        assert!(one_request(&two).is_none(), "two requests in one datagram");
        let mut bad = read.to_vec();
        bad[2] = 1;
        assert!(one_request(&bad).is_none(), "protocol id");
        assert!(one_request(b"hello").is_none(), "garbage");
    }
}
