//! Modbus over UDP (`[[listen]]` with `transport = "udp"`, docs/dialing.md "Modbus
//! over UDP"): each datagram one MBAP request, its reply sent to the datagram's
//! source. Each source is a master of the one connection type (`tcp/connection/mod.rs`:
//! access, per-master order, metrics), its requests handed to the line by the receive
//! loop itself and its replies sent by its writer: a source whose pipelining slots
//! are all in use has its next datagrams dropped, so a flood from one address takes no
//! more of the line than one master's share (`max_pending_per_connection`). A datagram
//! that is not exactly one well-formed MBAP request is dropped and counted, and closes
//! nothing; one that is an answer (an exception, a reply's shape, or the very reply
//! its source was just sent, come back) is never answered (`tcp/connection/unasked.rs`), and a
//! source's exception replies have a budget (`tcp/reflect.rs`), so no loop with
//! another server lasts. At most `max_connections` sources at once, the quietest owed
//! nothing forgotten for a new one (`tcp/udp/sources.rs`); one quiet for `idle_timeout_ms`
//! is forgotten; the lines' notifications reach a source only with `notifications =
//! true`, and only for [`NOTIFIED_FOR`] after its last request. A listener stopped
//! (a reload, shutdown) writes the replies its sources are owed first.

use super::connection::codec::Mbap;
use super::connection::Inbound;
use super::live::Live;
use super::reflect::Guard;
use super::unasked::Unasked;
use super::{accept::admit, Connection, Listening, Shared};
use crate::config::{ListenConfig, NOTIFIED_FOR};
use crate::frame::hex::Hex;
use crate::frame::mbap::{decode_strict, MAX_ADU};
use crate::frame::pdu::{not_a_request, NotRequest};
use crate::frame::Adu;
use crate::line::outbox::{Inbox, Outbox};
use crate::ops::capture::packet::Dir;
use bytes::BytesMut;
use sources::{SourceTable, TableSource};
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
use tokio_util::task::TaskTracker;
use tracing::debug;

mod listeners;
mod sources;

pub(crate) use listeners::Udps;

/// Binds a UDP listener.
pub(crate) fn bind(addr: SocketAddr) -> io::Result<UdpSocket> {
    let socket = std::net::UdpSocket::bind(addr)?;
    socket.set_nonblocking(true)?;
    UdpSocket::from_std(socket)
}

/// Why a datagram is not taken as a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Unfit {
    /// Not exactly one well-formed MBAP frame (`datagrams_dropped`).
    Malformed,
    /// An answer, never answered (`not_requests`).
    Answer(NotRequest),
}

/// `d` as one MBAP request, strictly checked, and no answer (the rule every listener
/// and dial drops answers by, `frame::pdu::not_a_request`).
fn one_request(d: &[u8]) -> Result<Adu, Unfit> {
    let mut buf = BytesMut::from(d);
    match decode_strict(&mut buf) {
        Ok(Some(adu)) if buf.is_empty() => match not_a_request(adu.pdu()) {
            None => Ok(adu),
            Some(what) => Err(Unfit::Answer(what)),
        },
        _ => Err(Unfit::Malformed),
    }
}

/// One source: its connection, the outbox its requests take tickets from (here, in
/// the receive loop: no task between a datagram and the line), the outbox the lines
/// send it notifications through (`notifications = true`), when it last sent, whether
/// its writer has ended, its loop guards, and the configuration as it runs (for its
/// requests' log).
struct Source {
    conn: Arc<Connection>,
    live: Live,
    outbox: Outbox,
    notes: Option<Outbox>,
    last: Instant,
    gone: CancellationToken,
    guard: Arc<Guard>,
}

impl Source {
    /// Its connection begun and its writer running on the tracker, with notifications
    /// if `notified`; `None`: the gateway is stopping.
    fn start(
        conn: Connection,
        socket: &Arc<UdpSocket>,
        shared: &Shared,
        notified: bool,
    ) -> Option<Source> {
        let conn = Arc::new(conn);
        let Some((outbox, inbox)) = conn.begin::<Mbap>() else {
            conn.end();
            return None;
        };
        let Some((notes, notes_in)) = notes(&conn, notified) else {
            conn.end();
            return None;
        };
        let now = Instant::now();
        let guard = Arc::new(Guard::new(now));
        let gone = CancellationToken::new();
        let writer = Replies {
            socket: socket.clone(),
            conn: conn.clone(),
            guard: guard.clone(),
            deciding: None,
        };
        let writing = write(conn.clone(), writer, inbox, notes_in, gone.clone());
        let stats = shared.stats.clone();
        shared.tracker.spawn(async move {
            writing.await;
            stats.add(&stats.connections_closed, 1);
        });
        Some(Source {
            live: Live::new(&conn.running),
            conn,
            outbox,
            notes,
            last: now,
            gone,
            guard,
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
        if self.notes.is_some() {
            self.guard.asked(self.last);
        }
        self.conn.take::<Mbap>(&mut self.live, adu, ticket);
        true
    }

    /// Quiet for `idle` with nothing owed at `now`.
    fn idle(&self, idle: Duration, now: Instant) -> bool {
        self.outbox
            .idle_at(self.last, idle)
            .is_some_and(|at| at <= now)
            && !self.guard.remembering(self.last, now)
    }

    /// Forgotten: off the lines, so its writer ends once the replies owed are written.
    fn forget(self) {
        self.conn.router.detach(self.conn.id);
    }

    /// Forgotten once the replies it is owed are written (its requests still queued
    /// on the lines among them): the listener stops, or it makes room for a new
    /// source. At shutdown the wait is bounded by the longest answer of the
    /// configuration as it runs then, and a second more (as a connection's own).
    fn finish(self, tracker: &TaskTracker, shutdown: CancellationToken) {
        if !self.outbox.owed() {
            return self.forget();
        }
        tracker.spawn(async move {
            tokio::select! {
                _ = self.outbox.settled() => {}
                _ = async {
                    shutdown.cancelled().await;
                    let bound = self.conn.running.borrow().answer_within();
                    tokio::time::sleep(bound + Duration::from_secs(1)).await;
                } => {}
            }
            self.forget();
        });
    }
}

impl TableSource for Source {
    fn heard(&self) -> Instant {
        self.last
    }

    /// A reply, or the reply it was just sent if that may yet come back (so its
    /// reflection is known); a source whose writer has ended is owed nothing.
    fn owed(&self, now: Instant) -> bool {
        !self.gone.is_cancelled() && (self.outbox.owed() || self.guard.remembering(self.last, now))
    }
}

/// The outbox the lines send a source their notifications through, if `notified`,
/// and the inbox its writer takes them from: no pipelining slot in it, its writer
/// knows them from replies and sends them only to a source that asked lately.
/// `None`: it could not be attached (the gateway is stopping).
fn notes(conn: &Connection, notified: bool) -> Option<(Option<Outbox>, Option<Inbox>)> {
    if !notified {
        return Some((None, None));
    }
    let (notes, notes_in) = Outbox::new(0);
    if !conn.router.attach(conn.id, &notes.notifier()) {
        return None;
    }
    Some((Some(notes), Some(notes_in)))
}

/// A source's writer: its replies written (`writer`), its notifications sent beside
/// them if it has any, until either ends; then `gone`, and its connection ended.
async fn write(
    conn: Arc<Connection>,
    writer: Replies,
    inbox: Inbox,
    notes: Option<Inbox>,
    gone: CancellationToken,
) {
    let (socket, guard) = (writer.socket.clone(), writer.guard.clone());
    let writing = conn.write_loop::<Mbap, _>(&Inbound, writer, inbox);
    match notes {
        None => drop(writing.await),
        Some(notes) => {
            let forwarding = async {
                notify(&conn, &socket, &guard, notes).await;
                std::future::pending::<()>().await
            };
            tokio::select! {
                _ = writing => {}
                _ = forwarding => {}
            }
        }
    }
    gone.cancel();
    conn.end();
}

/// Sends a source the lines' notifications that come within [`NOTIFIED_FOR`] of its
/// last request, as they come, until there are no more; an exception past its budget
/// is not sent. Best effort, as to a TCP master: one the socket cannot take at once is
/// missed.
async fn notify(conn: &Connection, socket: &UdpSocket, guard: &Guard, mut notes: Inbox) {
    let mut live = Live::new(&conn.running);
    while let Some(d) = notes.next().await {
        if !guard.asked_within(Instant::now(), NOTIFIED_FOR) {
            continue;
        }
        let adu = d.adu();
        let frame = adu.as_bytes();
        if !guard.sent(frame) {
            let limited = Unasked::ExceptionLimited;
            conn.unasked
                .note(limited, &conn.stats, conn.peer, conn.local, frame);
            continue;
        }
        if live.get().log.traffic {
            debug!(target: "mbgate::traffic", dir = "gw->master", conn = conn.id, "{}", Hex(frame));
        }
        if conn.tap.on() {
            conn.captured::<Mbap>(&adu, Dir::Out, "gw->master");
        }
        if let Err(e) = socket.try_send_to(frame, conn.peer) {
            debug!(conn = conn.id, "notification not sent: {e}");
        }
    }
}

/// Takes datagrams on `socket` until `stop`. Each is handed to the line from this
/// loop, through its source's outbox (per-source order: the order received); a
/// source with no pipelining slot free has its datagram dropped, so a flood from one
/// address takes no more of the line than one master's share. Sources quiet for
/// `idle_timeout_ms` are forgotten (looked for at most once a second; with 0, never
/// for being quiet, only to make room). When it stops, each source is forgotten once
/// it has been written the replies it is owed.
pub(crate) async fn datagram_loop(
    socket: Arc<UdpSocket>,
    listening: Listening,
    shared: Shared,
    stop: CancellationToken,
) {
    let mut r = Receiving::new(socket, listening, shared);
    // One timer for the loop's life, moved at each sweep for idle sources.
    let sweep = tokio::time::sleep(SWEEP);
    tokio::pin!(sweep);
    // Made once, as the timer is: a cancellation future made again at each pass
    // registers and drops a waiter for each datagram (docs/performance.md "Dialed and
    // UDP masters").
    let stopped = stop.cancelled();
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
                let peer = std::task::ready!(r.socket.poll_recv_from(cx, &mut filled));
                std::task::Poll::Ready(peer.map(|p| (filled.filled().len(), p)))
            }) => r,
            _ = &mut sweep, if !r.idle.is_zero() && !r.sources.is_empty() => {
                let now = Instant::now();
                r.sweep(now);
                sweep.as_mut().reset(now + SWEEP);
                continue;
            }
        };
        match received {
            Ok((n, peer)) => r.datagram(peer, &buf[..n]),
            Err(e) => debug!(local = %r.local, "UDP receive failed: {e}"),
        }
    }
    r.stopped();
}

/// A UDP listener's receive loop: its socket, its configuration, the allow list's
/// gate, and the sources it knows.
struct Receiving {
    socket: Arc<UdpSocket>,
    shared: Shared,
    listen: Arc<ListenConfig>,
    local: SocketAddr,
    gate: admit::Gate,
    sources: SourceTable<Source>,
    /// `idle_timeout_ms`: a source quiet for this long is forgotten.
    idle: Duration,
}

impl Receiving {
    fn new(socket: Arc<UdpSocket>, listening: Listening, shared: Shared) -> Receiving {
        let Listening {
            listen,
            name,
            local,
            ..
        } = listening;
        Receiving {
            socket,
            shared,
            gate: admit::Gate::new(name, listen.access.allow.clone()),
            sources: SourceTable::new(listen.tcp.max_connections),
            idle: Duration::from_millis(listen.tcp.idle_timeout_ms),
            listen: Arc::new(listen),
            local,
        }
    }

    /// A datagram from `peer`: dropped unless its source is allowed and it is one
    /// request (an answer is never answered), then taken by its source, one made for
    /// it if it is new.
    fn datagram(&mut self, peer: SocketAddr, datagram: &[u8]) {
        let stats = &self.shared.stats;
        if !self.gate.admits(peer, stats) {
            return;
        }
        let adu = match one_request(datagram) {
            Ok(adu) => adu,
            Err(Unfit::Malformed) => {
                stats.add(&stats.datagrams_dropped, 1);
                let n = datagram.len();
                debug!(%peer, bytes = n, "a datagram that is not one MBAP request: dropped");
                return;
            }
            Err(Unfit::Answer(what)) => {
                let what = Unasked::Answer(what);
                self.shared
                    .unasked
                    .note(what, stats, peer, self.local, datagram);
                return;
            }
        };
        // A source known and served: one look-up (each hashes the address).
        if let Some(source) = self.sources.get_mut(&peer) {
            if !source.gone.is_cancelled() {
                if source.guard.reflected(datagram, source.last) {
                    let what = Unasked::Reflected;
                    self.shared
                        .unasked
                        .note(what, stats, peer, self.local, datagram);
                } else if !source.take(adu) {
                    stats.add(&stats.datagrams_dropped, 1);
                }
                return;
            }
            // Its writer ended (a send failed): a new connection.
            if let Some(s) = self.sources.remove(&peer) {
                s.forget();
            }
        }
        self.new_source(peer, adu);
    }

    /// A source not known: room made for it (the quietest forgotten, its replies
    /// still written), its connection begun, and `adu`, its first request, taken.
    fn new_source(&mut self, peer: SocketAddr, adu: Adu) {
        let (shared, stats) = (&self.shared, &self.shared.stats);
        if let Some(quietest) = self.sources.room(Instant::now()) {
            let max = self.listen.tcp.max_connections;
            debug!(%peer, forgotten = %quietest.conn.peer, "max_connections ({max}) sources: the quietest forgotten");
            quietest.finish(&shared.tracker, shared.shutdown.clone());
        }
        stats.add(&stats.connections, 1);
        let conn = Connection::new(shared, self.listen.clone(), peer, self.local);
        let notified = self.listen.notifications;
        let Some(mut source) = Source::start(conn, &self.socket, shared, notified) else {
            stats.add(&stats.connections_closed, 1);
            return;
        };
        if !source.take(adu) {
            stats.add(&stats.datagrams_dropped, 1);
        }
        self.sources.insert(peer, source);
    }

    /// The sources quiet for `idle_timeout_ms` at `now` forgotten.
    fn sweep(&mut self, now: Instant) {
        let idle = self.idle;
        for s in self.sources.forget_where(|s| s.idle(idle, now)) {
            s.forget();
        }
    }

    /// The listener stopped: each source forgotten once it has been written the
    /// replies it is owed.
    fn stopped(mut self) {
        for s in self.sources.drain() {
            s.finish(&self.shared.tracker, self.shared.shutdown.clone());
        }
        debug!(local = %self.local, "UDP listener closed");
    }
}

/// How often the receive loop looks for sources quiet for `idle_timeout_ms`.
const SWEEP: Duration = Duration::from_secs(1);

/// A source's replies, each written whole, each one datagram to the source; an
/// exception past the source's budget is not sent (`tcp/reflect.rs`).
struct Replies {
    socket: Arc<UdpSocket>,
    conn: Arc<Connection>,
    guard: Arc<Guard>,
    /// Whether the frame being written goes out, decided at its first try (a frame
    /// the socket could not take at once is tried again with the same bytes).
    deciding: Option<bool>,
}

impl AsyncWrite for Replies {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, b: &[u8]) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        let guard = &this.guard;
        if !*this.deciding.get_or_insert_with(|| guard.sent(b)) {
            this.deciding = None;
            let c = &this.conn;
            c.unasked
                .note(Unasked::ExceptionLimited, &c.stats, c.peer, c.local, b);
            return Poll::Ready(Ok(b.len()));
        }
        let sent = std::task::ready!(this.socket.poll_send_to(cx, b, this.conn.peer));
        this.deciding = None;
        Poll::Ready(sent)
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
    use super::*;

    #[test]
    fn a_datagram_is_one_whole_request_or_nothing() {
        let read: &[u8] = &[0, 1, 0, 0, 0, 6, 1, 3, 0, 0, 0, 1];
        let adu = one_request(read).expect("one request");
        assert_eq!(adu.as_bytes(), read);
        let malformed = Err(Unfit::Malformed);
        assert_eq!(one_request(&read[..11]).map(|_| ()), malformed, "short");
        let mut two = read.to_vec();
        two.extend_from_slice(read);
        assert_eq!(
            one_request(&two).map(|_| ()),
            malformed,
            "two requests in one"
        );
        let mut bad = read.to_vec();
        bad[2] = 1;
        assert_eq!(one_request(&bad).map(|_| ()), malformed, "protocol id");
        assert_eq!(one_request(b"hello").map(|_| ()), malformed, "garbage");
        // Answers: an exception, a read's reply.
        let exception: &[u8] = &[0, 1, 0, 0, 0, 3, 1, 0x83, 0x0A];
        let answer = |w| Err(Unfit::Answer(w));
        assert_eq!(
            one_request(exception).map(|_| ()),
            answer(NotRequest::Exception)
        );
        let reply: &[u8] = &[0, 1, 0, 0, 0, 5, 1, 3, 2, 0, 0xFF];
        assert_eq!(
            one_request(reply).map(|_| ()),
            answer(NotRequest::ReplyShape)
        );
    }
}
