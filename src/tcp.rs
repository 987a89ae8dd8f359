//! The TCP side (design.md §1 steps 1-2, §4 `[tcp]`): the listener with its connection
//! limit, and one task per master that reads strictly checked MBAP requests and writes
//! back whatever the relay sends it.

use crate::config::Config;
use crate::frame::hex::Hex;
use crate::frame::mbap::{decode_strict, MAX_ADU};
use crate::frame::pdu::{self, exception};
use crate::frame::Adu;
use crate::relay::{Command, ConnId, Outbound, RelayHandle, NOTIFICATION_SLACK};
use crate::stats::Stats;
use bytes::BytesMut;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

/// Binds the masters' listener. Every connection it accepts inherits its send buffer,
/// capped here at room for all the replies mbgate can owe one master (the kernel
/// doubles the figure). Left to itself Linux grows a send buffer up to `tcp_wmem`
/// (4 MiB by default): a master that never reads would pin that much kernel memory,
/// and thousands of replies would queue for it before its writer stalled and
/// `idle_timeout_ms` could close it. The serial line, not this buffer, bounds the
/// rate of replies, so a master that reads loses nothing by it.
pub fn listen(addr: SocketAddr, max_pending: usize) -> std::io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    // As `TcpListener::bind` does.
    socket.set_reuseaddr(true)?;
    let room = (max_pending + NOTIFICATION_SLACK) * MAX_ADU;
    socket.set_send_buffer_size(u32::try_from(room).unwrap_or(u32::MAX))?;
    socket.bind(addr)?;
    socket.listen(1024)
}

/// Accepts masters until shutdown. A connection past `max_connections` is closed at
/// once and logged; the others each get a task on `tracker`.
pub async fn accept_loop(
    listener: TcpListener,
    cfg: Arc<Config>,
    relay: RelayHandle,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
    tracker: TaskTracker,
) {
    let limit = Arc::new(Semaphore::new(cfg.tcp.max_connections));
    let mut next_id: ConnId = 0;
    loop {
        let accepted = tokio::select! {
            _ = shutdown.cancelled() => break,
            r = listener.accept() => r,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: do not spin.
                warn!("accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Ok(slot) = limit.clone().try_acquire_owned() else {
            stats.add(&stats.connections_refused, 1);
            warn!(%peer, max = cfg.tcp.max_connections, "connection refused: max_connections reached");
            drop(stream);
            continue;
        };
        if let Err(e) = stream.set_nodelay(true) {
            debug!(%peer, "TCP_NODELAY: {e}");
        }
        next_id += 1;
        stats.add(&stats.connections, 1);
        let conn = Connection {
            id: next_id,
            peer,
            cfg: cfg.clone(),
            relay: relay.clone(),
            stats: stats.clone(),
            shutdown: shutdown.clone(),
        };
        tracker.spawn(async move {
            conn.run(stream).await;
            drop(slot);
        });
    }
    debug!("listener closed");
}

struct Connection {
    id: ConnId,
    peer: SocketAddr,
    cfg: Arc<Config>,
    relay: RelayHandle,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
}

/// Why a connection's reader stopped.
enum End {
    /// The master closed, the socket failed, or it was idle too long: close now.
    Closed,
    /// Shutdown: stop reading, but write the replies still owed first.
    Drain,
}

impl Connection {
    async fn run(self, stream: TcpStream) {
        info!(conn = self.id, peer = %self.peer, "master connected");
        let max_pending = self.cfg.relay.max_pending_per_connection;
        let (rd, wr) = stream.into_split();
        let (tx, rx) = mpsc::channel(max_pending + NOTIFICATION_SLACK);
        let permits = Arc::new(Semaphore::new(max_pending));
        let attached = self
            .relay
            .send(Command::Attach {
                conn: self.id,
                tx: tx.clone(),
            })
            .is_ok();
        if attached {
            let writer = self.write_loop(wr, rx);
            tokio::pin!(writer);
            let end = tokio::select! {
                end = self.read_loop(rd, &tx, &permits) => end,
                _ = &mut writer => End::Closed,
            };
            if let End::Drain = end {
                // Every request holds a permit until its answer is written: when all
                // are back, nothing is owed. The relay answers each one within the
                // response timeout (and its retries), so this is bounded; the bound
                // below only guards against a master that never reads.
                let bound = self.cfg.relay.answer_within() + Duration::from_secs(1);
                let all = permits.acquire_many(max_pending as u32);
                tokio::select! {
                    _ = tokio::time::timeout(bound, all) => {}
                    _ = &mut writer => {}
                }
            }
        }
        let _ = self.relay.send(Command::Detach { conn: self.id });
        info!(conn = self.id, peer = %self.peer, "master disconnected");
    }

    async fn read_loop(
        &self,
        mut rd: OwnedReadHalf,
        tx: &mpsc::Sender<Outbound>,
        permits: &Arc<Semaphore>,
    ) -> End {
        let max_pending = self.cfg.relay.max_pending_per_connection;
        let idle = Duration::from_millis(self.cfg.tcp.idle_timeout_ms);
        let mut idle_deadline = Instant::now() + idle;
        let mut buf = BytesMut::with_capacity(512);
        loop {
            // One pipelining slot per request: with none free, stop reading and let
            // TCP push back on the master.
            let permit = tokio::select! {
                p = permits.clone().acquire_owned() => p.expect("semaphore never closed"),
                _ = self.shutdown.cancelled() => return End::Drain,
            };
            let adu = loop {
                match decode_strict(&mut buf) {
                    Ok(Some(adu)) => break adu,
                    Ok(None) => {}
                    Err(e) => {
                        self.stats.add(&self.stats.protocol_violations, 1);
                        warn!(conn = self.id, peer = %self.peer, "protocol violation: {e}; closing the connection");
                        return End::Closed;
                    }
                }
                tokio::select! {
                    r = rd.read_buf(&mut buf) => match r {
                        Ok(0) => return End::Closed,
                        Ok(_) => idle_deadline = Instant::now() + idle,
                        Err(e) => {
                            debug!(conn = self.id, "read failed: {e}");
                            return End::Closed;
                        }
                    },
                    _ = tokio::time::sleep_until(idle_deadline), if !idle.is_zero() => {
                        // Idle means no byte for the period and no reply owed. A partial
                        // frame that stopped growing is idle too: a master gone mid-frame
                        // must not hold its connection slot for ever.
                        if permits.available_permits() + 1 == max_pending {
                            info!(conn = self.id, peer = %self.peer, "idle timeout; closing the connection");
                            return End::Closed;
                        }
                        idle_deadline = Instant::now() + idle;
                    }
                    _ = self.shutdown.cancelled() => return End::Drain,
                }
            };
            if self.cfg.log.traffic {
                debug!(target: "mbgate::traffic", dir = "master->gw", conn = self.id, "{}", Hex(adu.as_bytes()));
            }
            self.submit(adu, permit, tx);
        }
    }

    /// Hands a request to the relay, or answers it here when it cannot go on the line.
    fn submit(&self, adu: Adu, permit: OwnedSemaphorePermit, tx: &mpsc::Sender<Outbound>) {
        let local = |code: u8, permit| {
            let e = Adu::exception(adu.tid(), adu.unit(), adu.function(), code);
            let _ = tx.try_send(Outbound {
                adu: e,
                permit: Some(permit),
            });
        };
        if let Err(code) = pdu::check_request(adu.pdu()) {
            self.stats.add(&self.stats.bad_requests, 1);
            debug!(
                conn = self.id,
                "request outside protocol limits: exception {code:#04x}"
            );
            local(code, permit);
            return;
        }
        let cmd = Command::Request {
            conn: self.id,
            adu: adu.clone(),
            permit,
        };
        if let Err(Command::Request { permit, .. }) = self.relay.send(cmd) {
            self.stats.add(&self.stats.unavailable, 1);
            local(exception::GATEWAY_PATH_UNAVAILABLE, permit);
        }
    }

    /// Writes what the relay sends. A master that stops reading its replies for
    /// `idle_timeout_ms` is closed, so it cannot hold a connection slot for ever.
    async fn write_loop(&self, mut wr: OwnedWriteHalf, mut rx: mpsc::Receiver<Outbound>) {
        let stall = Duration::from_millis(self.cfg.tcp.idle_timeout_ms);
        while let Some(out) = rx.recv().await {
            if self.cfg.log.traffic {
                debug!(target: "mbgate::traffic", dir = "gw->master", conn = self.id, "{}", Hex(out.adu.as_bytes()));
            }
            let write = wr.write_all(out.adu.as_bytes());
            let result = if stall.is_zero() {
                write.await
            } else {
                match tokio::time::timeout(stall, write).await {
                    Ok(r) => r,
                    Err(_) => {
                        info!(conn = self.id, peer = %self.peer, "master stopped reading its replies; closing the connection");
                        return;
                    }
                }
            };
            if let Err(e) = result {
                debug!(conn = self.id, "write failed: {e}");
                return;
            }
            // `out.permit` drops here: the master's slot is free again.
        }
    }
}
