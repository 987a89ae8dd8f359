//! Modbus over UDP (`[[listen]]` with `transport = "udp"`, docs/dialing.md "Modbus
//! over UDP"): each datagram one MBAP request, its reply sent to the datagram's
//! source. Each source is a master of the one connection type of `crate::tcp` (codec,
//! access, per-master order, metrics), fed its datagrams through a small queue: a
//! source whose requests and queue are full has its next datagrams dropped, so a flood
//! from one address takes no more of the line than one master's share
//! (`max_pending_per_connection`). A datagram that is not exactly one well-formed MBAP
//! request is dropped and counted, and closes nothing. At most `max_connections`
//! sources at once; one quiet for `idle_timeout_ms` is forgotten.

use super::tally::Tally;
use super::{admit, Connection, Listening, Shared};
use crate::config::{ListenConfig, Transport};
use crate::frame::mbap::{decode_strict, MAX_ADU};
use bytes::{Bytes, BytesMut};
use std::collections::HashMap;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tracing::debug;

/// Datagrams a source may have waiting beyond the requests its connection holds.
const WAITING: usize = 4;

/// Binds a UDP listener.
pub(crate) fn bind(addr: SocketAddr) -> io::Result<UdpSocket> {
    let socket = std::net::UdpSocket::bind(addr)?;
    socket.set_nonblocking(true)?;
    UdpSocket::from_std(socket)
}

/// Is `d` exactly one MBAP request, strictly checked?
fn one_request(d: &[u8]) -> bool {
    let mut buf = BytesMut::from(d);
    matches!(decode_strict(&mut buf), Ok(Some(_))) && buf.is_empty()
}

/// Takes datagrams on `socket` until shutdown.
pub(crate) async fn datagram_loop(socket: Arc<UdpSocket>, listening: Listening, shared: Shared) {
    let Listening {
        listen,
        name,
        local,
        ..
    } = listening;
    let mut gate = admit::Gate::new(name, listen.access.allow.clone());
    let max_sources = listen.tcp.max_connections;
    let listen = Arc::new(listen);
    let stats = shared.stats.clone();
    let mut sources: HashMap<SocketAddr, mpsc::Sender<Bytes>> = HashMap::new();
    // Room for a datagram one byte too long to be a request: it is seen as such.
    let mut buf = vec![0u8; MAX_ADU + 1];
    loop {
        let received = tokio::select! {
            _ = shared.shutdown.cancelled() => break,
            r = socket.recv_from(&mut buf) => r,
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
        if !one_request(&buf[..n]) {
            stats.add(&stats.datagrams_dropped, 1);
            debug!(%peer, bytes = n, "a datagram that is not one MBAP request: dropped");
            continue;
        }
        let mut datagram = Bytes::copy_from_slice(&buf[..n]);
        if let Some(tx) = sources.get(&peer) {
            match tx.try_send(datagram) {
                Ok(()) => continue,
                Err(mpsc::error::TrySendError::Full(_)) => {
                    stats.add(&stats.datagrams_dropped, 1);
                    continue;
                }
                // Its connection ended (quiet too long): a new one.
                Err(mpsc::error::TrySendError::Closed(d)) => {
                    sources.remove(&peer);
                    datagram = d;
                }
            }
        }
        if sources.len() >= max_sources {
            sources.retain(|_, tx| !tx.is_closed());
            if sources.len() >= max_sources {
                stats.add(&stats.datagrams_dropped, 1);
                stats.add(&stats.connections_refused, 1);
                debug!(%peer, "max_connections ({max_sources}) sources: datagram dropped");
                continue;
            }
        }
        let (tx, rx) = mpsc::channel(WAITING);
        let _ = tx.try_send(datagram);
        sources.insert(peer, tx);
        stats.add(&stats.connections, 1);
        let conn = Connection::new(&shared, listen.clone(), peer, local);
        let reader = Datagrams {
            rx,
            left: Bytes::new(),
        };
        let writer = Replies {
            socket: socket.clone(),
            peer,
        };
        let closed = stats.clone();
        shared.tracker.spawn(async move {
            conn.run(reader, writer).await;
            closed.add(&closed.connections_closed, 1);
        });
    }
    debug!(%local, "UDP listener closed");
}

/// The UDP listeners running, as a reload finds them (docs/dialing.md "Reload"):
/// each its configuration, its socket, the token that stops it and its counters.
pub(crate) struct Udps {
    shared: Shared,
    tally: Arc<Tally>,
    running: Vec<RunningUdp>,
}

struct RunningUdp {
    listen: ListenConfig,
    socket: Arc<UdpSocket>,
    stop: tokio_util::sync::CancellationToken,
    stats: Arc<crate::stats::Stats>,
}

impl Udps {
    pub(crate) fn new(shared: Shared, tally: Arc<Tally>) -> Udps {
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
        stats: Arc<crate::stats::Stats>,
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
        stats: Arc<crate::stats::Stats>,
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

/// A source's datagrams as the byte stream a connection reads: one datagram per read
/// (each a whole request); the end when the listener stops.
struct Datagrams {
    rx: mpsc::Receiver<Bytes>,
    /// What a read had no room for.
    left: Bytes,
}

impl AsyncRead for Datagrams {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        out: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if self.left.is_empty() {
            match self.rx.poll_recv(cx) {
                Poll::Ready(Some(d)) => self.left = d,
                Poll::Ready(None) => return Poll::Ready(Ok(())),
                Poll::Pending => return Poll::Pending,
            }
        }
        let n = self.left.len().min(out.remaining());
        let taken = self.left.split_to(n);
        out.put_slice(&taken);
        Poll::Ready(Ok(()))
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
        assert!(one_request(read));
        assert!(!one_request(&read[..11]), "short");
        let mut two = read.to_vec();
        two.extend_from_slice(read);
        assert!(!one_request(&two), "two requests in one datagram");
        let mut bad = read.to_vec();
        bad[2] = 1;
        assert!(!one_request(&bad), "protocol id");
        assert!(!one_request(b"hello"), "garbage");
    }
}
