//! The TCP side (docs/design.md §1 steps 1-2, §4 `[tcp]`, §4.1 `[[listen]]`): each
//! listener with its connection limit, and one task per master that reads strictly
//! checked MBAP requests (or RTU-over-TCP ones: the listener's codec, `tcp/codec.rs`,
//! chosen once a connection), hands them to the line
//! serving their unit ([`crate::router`]) and writes back their replies in the order of
//! the requests, with the device's notifications (the path back is [`crate::outbox`]).
//! Who gets in (the allow list, TLS and the master's role) is `tcp/admit.rs`; what a
//! master may do is checked here before a request goes anywhere ([`crate::access`],
//! docs/security.md).

use crate::access;
use crate::capture::packet::{Dir, Ends, Packet, Part, Reason};
use crate::capture::{Hub, Tap};
use crate::config::{Config, ListenConfig, ListenFraming};
use crate::frame::hex::Hex;
use crate::frame::mbap::MAX_ADU;
use crate::frame::pdu;
use crate::frame::Adu;
use crate::metrics::{MasterSeen, Masters};
use crate::outbox::{self, Inbox, Outbox, Refusal, Ticket};
use crate::port::Backoff;
use crate::relay::ConnId;
use crate::router::{Router, Unrouted};
use crate::stats::Stats;
use crate::tls::server::{Acceptor, Grant};
use crate::woken::Woken;
use bytes::BytesMut;
use handshakes::Handshakes;
use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::Poll;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::Semaphore;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

mod admit;
mod codec;
pub(crate) mod dial;
mod echo;
mod handshakes;
mod rtu;
pub(crate) mod tally;
pub(crate) mod udp;

use codec::MasterCodec;

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

/// A listener's socket: TCP, or UDP (`tcp/udp.rs`).
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

/// What every listener's connections share: the configuration, the lines, the
/// counters (each listener its own), connection ids (unique across listeners), the
/// masters connected, shutdown and the task tracker.
#[derive(Clone)]
pub(crate) struct Shared {
    pub(crate) cfg: Arc<Config>,
    /// The configuration as it runs now (a reload changes it): the priority classes.
    pub(crate) running: Arc<std::sync::Mutex<Config>>,
    pub(crate) router: Arc<Router>,
    pub(crate) stats: Arc<Stats>,
    pub(crate) shutdown: CancellationToken,
    pub(crate) tracker: TaskTracker,
    pub(crate) ids: Arc<AtomicU64>,
    pub(crate) masters: Arc<Masters>,
    /// The capture (docs/capture.md): the TCP side is its interface 0.
    pub(crate) capture: Hub,
}

/// One listener as the accept loop runs it: its configuration, its name in the file
/// (`listen[0]`), the address it is bound to, and its TLS acceptor if it has one.
pub(crate) struct Listening {
    pub(crate) listen: ListenConfig,
    pub(crate) name: String,
    pub(crate) local: SocketAddr,
    pub(crate) tls: Option<Arc<Acceptor>>,
}

/// Accepts masters on `listener` until shutdown. A source not in the allow list is
/// closed at once, before any byte is read. On a plain listener a connection past
/// `max_connections` is closed at once; the others each get a task on the tracker. On a
/// TLS listener the handshake runs in the connection's task within the listener's
/// handshake budget (`tcp/handshakes.rs`), and a connection slot is taken only once
/// the master has authenticated: peers that never do hold no slot. Refusals are
/// logged at most once a minute per source and reason, with counts ([`admit::Refusals`]).
pub(crate) async fn accept_loop(listener: TcpListener, listening: Listening, shared: Shared) {
    let Shared {
        stats,
        shutdown,
        tracker,
        ..
    } = shared.clone();
    let Listening {
        listen,
        name,
        local,
        tls,
    } = listening;
    let limit = Arc::new(Semaphore::new(listen.tcp.max_connections));
    let mut gate = admit::Gate::new(name, listen.access.allow.clone());
    let refusals = Arc::new(admit::Refusals::default());
    let handshakes = Arc::new(Budget::new(listen.tcp.max_connections));
    let listen = Arc::new(listen);
    let mut failing = AcceptFailures::default();
    loop {
        let accepted = tokio::select! {
            _ = shutdown.cancelled() => break,
            r = listener.accept() => r,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                let delay = failing.failed(&e);
                tokio::select! {
                    _ = shutdown.cancelled() => break,
                    _ = tokio::time::sleep(delay) => continue,
                }
            }
        };
        failing.recovered();
        if !gate.admits(peer, &stats) {
            drop(stream);
            continue;
        }
        let slot = if tls.is_some() {
            None
        } else {
            match limit.clone().try_acquire_owned() {
                Ok(slot) => Some(slot),
                Err(_) => {
                    stats.add(&stats.connections_refused, 1);
                    refuse_at_limit(&refusals, peer, listen.tcp.max_connections);
                    drop(stream);
                    continue;
                }
            }
        };
        if let Err(e) = stream.set_nodelay(true) {
            debug!(%peer, "TCP_NODELAY: {e}");
        }
        stats.add(&stats.connections, 1);
        let conn = Connection::new(&shared, listen.clone(), peer, local);
        let closed = stats.clone();
        match (&tls, slot) {
            (Some(acceptor), _) => {
                let turn = handshakes.begin(peer, &refusals, acceptor.name());
                let (acceptor, limit, refusals) =
                    (acceptor.clone(), limit.clone(), refusals.clone());
                tracker.spawn(async move {
                    conn.start_tls(stream, &acceptor, turn, &limit, &refusals)
                        .await;
                    closed.add(&closed.connections_closed, 1);
                });
            }
            (None, slot) => {
                tracker.spawn(async move {
                    let (rd, wr) = stream.into_split();
                    conn.run(rd, wr).await;
                    closed.add(&closed.connections_closed, 1);
                    drop(slot);
                });
            }
        }
    }
    debug!("listener closed");
}

/// A connection turned away at `max_connections`: counted by the caller, logged here
/// once a minute per source with the count between.
fn refuse_at_limit(refusals: &admit::Refusals, peer: SocketAddr, max: usize) {
    let why = format!("max_connections ({max}) reached");
    refusals.refused(peer, &why, "", admit::Loud::Warn);
}

/// A TLS listener's handshakes in progress ([`Handshakes`]) and how to end each: the
/// accept loop begins them, a handshake's [`Turn`] ends it when dropped.
struct Budget {
    state: Mutex<(Handshakes, HashMap<u64, CancellationToken>)>,
}

/// One handshake's place in the budget: `dropped` fires when it must make room for a
/// newer one; dropping the turn gives the place back.
struct Turn {
    id: u64,
    dropped: CancellationToken,
    budget: Arc<Budget>,
}

impl Budget {
    fn new(max_connections: usize) -> Budget {
        Budget {
            state: Mutex::new((Handshakes::for_listener(max_connections), HashMap::new())),
        }
    }

    /// A handshake from `peer` begins; the one it makes room for, if any, is told to
    /// end (and logged, once a minute per source).
    fn begin(self: &Arc<Self>, peer: SocketAddr, refusals: &admit::Refusals, table: &str) -> Turn {
        let dropped = CancellationToken::new();
        let mut state = self.state.lock().expect("not poisoned");
        let (handshakes, tokens) = &mut *state;
        let (id, evicted) = handshakes.begin(peer.ip());
        tokens.insert(id, dropped.clone());
        if let Some(old) = evicted.and_then(|e| tokens.remove(&e)) {
            old.cancel();
            let why = format!(
                "{table}: handshakes in progress at their limit ({} on the listener, {} from one source): the oldest unfinished one gave way",
                handshakes.limit(),
                handshakes.per_source()
            );
            refusals.refused(peer, &why, "", admit::Loud::Info);
        }
        Turn {
            id,
            dropped,
            budget: self.clone(),
        }
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        let mut state = self.budget.state.lock().expect("not poisoned");
        state.0.end(self.id);
        state.1.remove(&self.id);
    }
}

/// accept() failing, mostly for want of file descriptors (EMFILE, ENFILE): the
/// master that could not be taken stays in the listen backlog, so the listener stays
/// ready and an immediate retry fails again (and at the limit accept fails even with
/// no master waiting). Retries back off, 10 ms doubling to 1 s, until one succeeds.
/// The operator is warned at the first failure, then at most once a minute: a gateway
/// that hovers at its limit fails again after each master it takes.
struct AcceptFailures {
    backoff: Backoff,
    /// Failures since the last accept that succeeded.
    count: u64,
    /// Whether this spell of failures was warned about.
    warned: bool,
    last_warning: Option<Instant>,
}

/// The least time between two warnings about failing accepts.
const ACCEPT_WARNING_EVERY: Duration = Duration::from_secs(60);

impl Default for AcceptFailures {
    fn default() -> Self {
        Self {
            backoff: Backoff::new(Duration::from_millis(10), Duration::from_secs(1)),
            count: 0,
            warned: false,
            last_warning: None,
        }
    }
}

impl AcceptFailures {
    /// Logs the failure and returns how long to wait before the next attempt.
    fn failed(&mut self, e: &std::io::Error) -> Duration {
        self.count += 1;
        let delay = self.backoff.next_delay();
        let now = Instant::now();
        let due = self
            .last_warning
            .is_none_or(|t| now.duration_since(t) >= ACCEPT_WARNING_EVERY);
        if self.count == 1 && due {
            let hint = match e.raw_os_error() {
                Some(libc::EMFILE) => {
                    ": mbgate is out of file descriptors (raise its limit, LimitNOFILE= \
                     under systemd, or lower tcp.max_connections)"
                }
                Some(libc::ENFILE) => ": the system is out of file descriptors",
                _ => "",
            };
            warn!("accept failed: {e}{hint}; retrying with backoff up to 1 s (said at most once a minute)");
            self.warned = true;
            self.last_warning = Some(now);
        } else {
            debug!(failures = self.count, "accept failed again: {e}");
        }
        delay
    }

    fn recovered(&mut self) {
        if self.count == 0 {
            return;
        }
        if self.warned {
            info!(
                failures = self.count,
                "accepting connections again after {} failed attempts", self.count
            );
        } else {
            debug!(failures = self.count, "accepting connections again");
        }
        self.count = 0;
        self.warned = false;
        self.backoff.reset();
    }
}

struct Connection {
    id: ConnId,
    peer: SocketAddr,
    cfg: Arc<Config>,
    running: Arc<std::sync::Mutex<Config>>,
    listen: Arc<ListenConfig>,
    router: Arc<Router>,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
    masters: Arc<Masters>,
    /// The listener's own address.
    local: SocketAddr,
    /// A TLS master's role, and what it may do.
    grant: Option<Grant>,
    capture: Hub,
    /// The TCP side's tap.
    tap: Tap,
    /// A dialed connection's own bytes: its heartbeat, and the echoes of them and of
    /// its identity the server may send back (docs/dialing.md).
    dialed: Option<Dialed>,
}

/// What a dialed connection sends of its own, and the echoes it may get back.
struct Dialed {
    /// Sent after `every` without a reply written; empty: never.
    heartbeat: Vec<u8>,
    every: Duration,
    echoes: Mutex<echo::Echoes>,
    /// How long the server may leave a reply unread before the connection is closed
    /// (and dialed again): never for ever, since mbgate has no other way to it.
    stall: Duration,
}

/// Why a connection's reader stopped.
enum End {
    /// The socket failed, the master broke the protocol, or it was idle too long
    /// (said in the words given): close now.
    Closed(String),
    /// No more requests will be read (the master shut down its sending side, or the
    /// gateway is shutting down): write the replies still owed, then close.
    Finish,
}

impl Connection {
    /// A master's connection from any source (accepted, dialed, a UDP source), with
    /// a new id: `listen` says what its requests may do, `local` is our end.
    fn new(
        shared: &Shared,
        listen: Arc<ListenConfig>,
        peer: SocketAddr,
        local: SocketAddr,
    ) -> Connection {
        Connection {
            id: shared.ids.fetch_add(1, Ordering::Relaxed) + 1,
            peer,
            cfg: shared.cfg.clone(),
            running: shared.running.clone(),
            listen,
            router: shared.router.clone(),
            stats: shared.stats.clone(),
            shutdown: shared.shutdown.clone(),
            masters: shared.masters.clone(),
            local,
            grant: None,
            capture: shared.capture.clone(),
            tap: shared.capture.tap(0),
            dialed: None,
        }
    }

    /// The TLS handshake within its `turn` of the listener's budget, then, with a
    /// connection slot (taken only now: a peer that never authenticates never holds
    /// one), the master served. A handshake that must make room for a newer one ends
    /// at once, counted as failed.
    async fn start_tls(
        mut self,
        stream: TcpStream,
        acceptor: &Acceptor,
        turn: Turn,
        limit: &Arc<Semaphore>,
        refusals: &admit::Refusals,
    ) {
        let handshake =
            admit::handshake(acceptor, stream, self.id, self.peer, &self.stats, refusals);
        let done = tokio::select! {
            done = handshake => done,
            _ = turn.dropped.cancelled() => {
                self.stats.add(&self.stats.tls_failed, 1);
                debug!(conn = self.id, peer = %self.peer, "handshake dropped to make room for a newer one");
                None
            }
            _ = self.shutdown.cancelled() => None,
        };
        drop(turn);
        let Some((stream, grant)) = done else {
            return;
        };
        let Ok(slot) = limit.clone().try_acquire_owned() else {
            self.stats.add(&self.stats.connections_refused, 1);
            refuse_at_limit(refusals, self.peer, self.listen.tcp.max_connections);
            return;
        };
        self.grant = Some(grant);
        let (rd, wr) = tokio::io::split(stream);
        self.run(rd, wr).await;
        drop(slot);
    }

    /// The listener's framing chosen once: the rest is written over its codec. Why
    /// the connection ended, in words.
    async fn run(self, rd: impl AsyncRead + Unpin, wr: impl AsyncWrite + Unpin) -> String {
        match self.listen.framing {
            ListenFraming::Mbap => self.serve::<codec::Mbap>(rd, wr).await,
            ListenFraming::Rtu => self.serve::<codec::Rtu>(rd, wr).await,
        }
    }

    async fn serve<C: MasterCodec>(
        self,
        rd: impl AsyncRead + Unpin,
        wr: impl AsyncWrite + Unpin,
    ) -> String {
        let framing = C::NAME;
        // At debug: a SCADA that connects for each poll would fill the journal at info;
        // the connections are counted (mbgate_listener_connections_total) and the
        // masters connected now listed (mbgate status, the status page).
        match &self.grant {
            None => debug!(conn = self.id, peer = %self.peer, framing, "master connected"),
            Some(g) => debug!(
                conn = self.id,
                peer = %self.peer,
                framing,
                role = %g.role,
                subject = %g.subject,
                "master connected over TLS{}",
                if g.defaulted { " (no role in its certificate: the default role)" } else { "" }
            ),
        }
        self.masters.add(MasterSeen {
            conn: self.id,
            listener: self.local.to_string(),
            source: self.listen.clone(),
            peer: self.peer,
            since: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap_or_default()
                .as_secs_f64(),
            tls: self
                .grant
                .as_ref()
                .map(|g| (g.role.clone(), g.subject.clone())),
        });
        self.capture.connected(self.id, self.peer);
        // A framing with no transaction id (RTU over TCP): one request at a time, and
        // no notifications (nothing would tell them from a reply).
        let pending = if C::IDS {
            self.cfg.max_pending_per_connection()
        } else {
            1
        };
        let (mut outbox, inbox) = Outbox::new(pending);
        let attached = !C::IDS || self.router.attach(self.id, &outbox.notifier());
        // Its role's priority class, else its listener's, as the configuration runs
        // now; told under its lock, so a reload's new classes never arrive before
        // the old one (src/reload.rs `reclassify`).
        {
            let running = self.running.lock().expect("not poisoned");
            let role = self.grant.as_ref().map(|g| g.role.as_str());
            let class = running.priority_of(&self.listen, role);
            self.router.classify(self.id, class);
        }
        let mut why = "notifications have no way to this master".to_owned();
        if attached {
            let writer = self.write_loop::<C>(wr, inbox);
            tokio::pin!(writer);
            let end = tokio::select! {
                end = self.read_loop::<C>(rd, &mut outbox) => end,
                w = &mut writer => End::Closed(w),
            };
            why = match &end {
                End::Closed(w) => w.clone(),
                End::Finish => "the master closed its side (or mbgate is stopping)".to_owned(),
            };
            if let End::Finish = end {
                // The relay answers every request it was given: at once when the
                // gateway shuts down (what is on the line within the response timeout
                // and its retries), else in its turn. Only shutdown bounds the wait
                // here; a master that stops reading meanwhile is closed by the writer.
                let bound = self.cfg.answer_within() + Duration::from_secs(1);
                tokio::select! {
                    _ = outbox.settled() => {}
                    _ = &mut writer => {}
                    _ = async {
                        self.shutdown.cancelled().await;
                        tokio::time::sleep(bound).await;
                    } => {}
                }
            }
        }
        self.router.detach(self.id);
        self.masters.remove(self.id);
        self.capture.forget(self.id);
        debug!(conn = self.id, peer = %self.peer, "master disconnected");
        why
    }

    async fn read_loop<C: MasterCodec>(
        &self,
        mut rd: impl AsyncRead + Unpin,
        outbox: &mut Outbox,
    ) -> End {
        let idle = Duration::from_millis(self.listen.tcp.idle_timeout_ms);
        let mut last_read = Instant::now();
        // One timer for the connection's life, moved only when it goes off (the idle
        // clock is read then): a timer made afresh each turn of the loop would be
        // registered with tokio's timer once a request, and each registration wakes
        // the reactor (a system call; docs/performance.md "What a transaction costs").
        // Polled only once it went off (`crate::woken`), like the wait for shutdown.
        let mut idle_timer = Woken::new(tokio::time::sleep_until(last_read + idle));
        let mut buf = BytesMut::with_capacity(512);
        let mut codec = C::default();
        // One wait for shutdown for the connection's life, not one registered with
        // the token and dropped again at every request.
        let mut shutdown = Woken::new(self.shutdown.cancelled());
        loop {
            let decoded = match self.echo_in(&mut buf) {
                echo::Strip::Took => continue,
                echo::Strip::Wait => Ok(None),
                echo::Strip::Not => codec.decode(&mut buf),
            };
            match decoded {
                Ok(Some(adu)) => {
                    // One pipelining slot per request: with none free, stop reading
                    // and let TCP push back on the master.
                    let ticket = tokio::select! {
                        t = outbox.ticket() => t,
                        _ = &mut shutdown => return End::Finish,
                    };
                    if self.cfg.log.traffic {
                        debug!(target: "mbgate::traffic", dir = "master->gw", conn = self.id, "{}", Hex(adu.as_bytes()));
                    }
                    if self.tap.on() {
                        self.captured::<C>(&adu, Dir::In, "master->gw");
                    }
                    self.submit(adu, ticket);
                    continue;
                }
                Ok(None) => {}
                Err(e) if self.answer_in(&mut buf, &e) => continue,
                Err(e) => {
                    if self.tap.on() {
                        // What a capture shows of them: a frame's worth, and a few more.
                        let end = buf.len().min(rtu::MAX_FRAME + 8);
                        let mut p =
                            Packet::dropped(None, Reason::Refused, buf[..end].to_vec(), false, "");
                        p.note = Some(format!("dropped (refused): {e}; the connection was closed"));
                        p.ends = Some(self.ends());
                        p.conn = Some(self.id);
                        self.tap.send(p, Instant::now());
                    }
                    self.stats.add(&self.stats.protocol_violations, 1);
                    warn!(conn = self.id, peer = %self.peer, "protocol violation: {e}; closing the connection");
                    return End::Closed(format!("protocol violation: {e}"));
                }
            }
            let pause = codec.ended_by_pause(&buf);
            tokio::select! {
                // Made only when polled: a disabled branch's future is still made,
                // and a sleep reads the clock.
                _ = async { tokio::time::sleep(pause.unwrap_or_default()).await }, if pause.is_some() => codec.paused(),
                r = rd.read_buf(&mut buf) => match r {
                    Ok(0) => {
                        // A shutdown of the master's sending side (`shutdown(SHUT_WR)`,
                        // `nc -N`): no more requests, but it still awaits its replies.
                        debug!(
                            conn = self.id,
                            owed = outbox.owed(),
                            partial = buf.len(),
                            "master closed its sending side; writing the replies owed, then closing"
                        );
                        return End::Finish;
                    }
                    Ok(_) => last_read = Instant::now(),
                    Err(e) => {
                        debug!(conn = self.id, "read failed: {e}");
                        return End::Closed(format!("read failed: {e}"));
                    }
                },
                _ = &mut idle_timer, if !idle.is_zero() => {
                    // Idle means the master owes nothing and is owed nothing: the clock
                    // runs from its last byte or its last reply, whichever is later,
                    // and only while no request of its is unanswered. A partial frame
                    // that stopped growing is idle too: a master gone mid-frame must
                    // not hold its connection slot for ever.
                    let now = Instant::now();
                    let wake = match outbox.idle_at(last_read, idle) {
                        None => now + idle,
                        Some(at) if now >= at => {
                            info!(conn = self.id, peer = %self.peer, "idle timeout; closing the connection");
                            return End::Closed(format!("no request for {} ms (idle_timeout_ms)", idle.as_millis()));
                        }
                        Some(at) => at,
                    };
                    idle_timer.inner().reset(wake);
                }
                _ = &mut shutdown => return End::Finish,
            }
        }
    }

    fn ends(&self) -> Ends {
        Ends {
            client: self.peer,
            server: self.local,
        }
    }

    /// A frame to or from this master, for the capture: as the master framed it
    /// (MBAP with its own transaction id, or RTU with its CRC).
    fn captured<C: MasterCodec>(&self, adu: &Adu, dir: Dir, label: &'static str) {
        let role = if dir == Dir::In {
            Part::Query
        } else {
            Part::Reply
        };
        self.tap.send_with((dir, role), Instant::now(), |p| {
            p.proto = C::PROTO;
            p.bytes.extend_from_slice(&C::frame(adu));
            p.ends = Some(self.ends());
            p.conn = Some(self.id);
            p.unit = Some(adu.unit());
            p.function = Some(adu.function());
            p.span = crate::relay::span(adu.pdu());
            p.label = label;
        });
    }

    /// Hands a request to the relay, or answers it here when it cannot go on the line.
    /// Either way the answer goes through its ticket, so it keeps its place in the
    /// master's order.
    fn submit(&self, adu: Adu, ticket: Ticket) {
        if let Err(code) = pdu::check_request(adu.pdu()) {
            debug!(
                conn = self.id,
                "request outside protocol limits: exception {code}"
            );
            ticket.refuse(&adu, Refusal::BadRequest(code), &self.stats);
            return;
        }
        let role = self.grant.as_ref().map(|g| (g.role.as_str(), &g.policy));
        if let Err(denied) = access::decide(&self.listen.access.policy, role, adu.unit(), adu.pdu())
        {
            debug!(
                conn = self.id,
                peer = %self.peer,
                role = role.map(|r| r.0),
                unit = adu.unit(),
                function = %adu.function_code(),
                written = ?crate::frame::function::written(adu.pdu()),
                "request refused: {denied}; exception 0x01"
            );
            ticket.refuse(&adu, Refusal::Denied, &self.stats);
            return;
        }
        match self.router.submit(self.id, adu, ticket, &self.stats) {
            Ok(()) | Err(Unrouted::Stopped) => {}
            Err(Unrouted::NoLine) => {
                debug!(conn = self.id, "a unit no line serves: exception 0x0a");
            }
        }
    }

    /// A dialed connection's echoes at the front of `buf` (docs/dialing.md).
    fn echo_in(&self, buf: &mut BytesMut) -> echo::Strip {
        let Some(d) = &self.dialed else {
            return echo::Strip::Not;
        };
        let strip = d.echoes.lock().expect("not poisoned").strip(buf);
        if let echo::Strip::Took = strip {
            debug!(
                conn = self.id,
                "the server echoed a heartbeat or the identity: dropped"
            );
        }
        strip
    }

    /// Bytes the framing refused (`e`) that are the server's own answer to the
    /// identity or a heartbeat (docs/dialing.md "What the server must do"): dropped
    /// and counted, the connection kept. `false`: they break the protocol.
    fn answer_in(&self, buf: &mut BytesMut, e: &codec::FrameError) -> bool {
        let Some(d) = &self.dialed else {
            return false;
        };
        let Some(n) = d.echoes.lock().expect("not poisoned").answer(buf) else {
            return false;
        };
        self.stats.add(&self.stats.dial_answers, 1);
        debug!(
            conn = self.id,
            bytes = n,
            "the server answered the identity or a heartbeat ({e}): dropped"
        );
        true
    }

    /// Writes the master's replies in the order of its requests, and notifications as
    /// they come; on a dialed connection with a heartbeat, the heartbeat whenever no
    /// reply was written for its interval. A master that stops reading its replies
    /// for `idle_timeout_ms` is closed, so it cannot hold a connection slot for ever.
    /// Why it stopped, in words.
    async fn write_loop<C: MasterCodec>(
        &self,
        mut wr: impl AsyncWrite + Unpin,
        mut inbox: Inbox,
    ) -> String {
        let beat = self.dialed.as_ref().filter(|d| !d.heartbeat.is_empty());
        let Some(beat) = beat else {
            while let Some(out) = inbox.next().await {
                if let Err(why) = self.write_reply::<C>(&mut wr, &out.adu).await {
                    return why;
                }
                // `out` drops here: a reply's pipelining slot is free again, and the
                // idle clock starts from now.
            }
            return "the connection's replies ended".to_owned();
        };
        // One timer for the connection's life, moved at each reply and each beat.
        let timer = tokio::time::sleep(beat.every);
        tokio::pin!(timer);
        loop {
            tokio::select! {
                out = inbox.next() => {
                    let Some(out) = out else {
                        return "the connection's replies ended".to_owned();
                    };
                    if let Err(why) = self.write_reply::<C>(&mut wr, &out.adu).await {
                        return why;
                    }
                }
                _ = &mut timer => {
                    beat.echoes.lock().expect("not poisoned").beat();
                    debug!(conn = self.id, "heartbeat");
                    if let Err(why) = self.write_bytes(&mut wr, &beat.heartbeat).await {
                        return why;
                    }
                }
            }
            timer.as_mut().reset(Instant::now() + beat.every);
        }
    }

    /// One reply or notification written (logged and captured first); `Err`: why the
    /// connection must close.
    async fn write_reply<C: MasterCodec>(
        &self,
        wr: &mut (impl AsyncWrite + Unpin),
        adu: &Adu,
    ) -> Result<(), String> {
        if self.cfg.log.traffic {
            debug!(target: "mbgate::traffic", dir = "gw->master", conn = self.id, "{}", Hex(adu.as_bytes()));
        }
        if self.tap.on() {
            self.captured::<C>(adu, Dir::Out, "gw->master");
        }
        if !C::answers(adu) {
            debug!(
                conn = self.id,
                "answer to a broadcast (unit 0): not written"
            );
            return Ok(());
        }
        self.write_bytes(wr, &C::frame(adu)).await
    }

    /// `frame` written and flushed, within `idle_timeout_ms` if the socket cannot take
    /// it at once.
    async fn write_bytes(
        &self,
        wr: &mut (impl AsyncWrite + Unpin),
        frame: &[u8],
    ) -> Result<(), String> {
        let stall = match &self.dialed {
            Some(d) => d.stall,
            None => Duration::from_millis(self.listen.tcp.idle_timeout_ms),
        };
        // Flushed: a TLS stream holds what it could not send at once until then.
        let write = async {
            wr.write_all(frame).await?;
            wr.flush().await
        };
        let mut write = std::pin::pin!(write);
        // Nearly every reply goes out at once, and needs no timer (each would read
        // the clock): the stall's timer starts only for one the socket cannot take.
        let first = std::future::poll_fn(|cx| Poll::Ready(write.as_mut().poll(cx))).await;
        let result = match first {
            Poll::Ready(r) => r,
            Poll::Pending if stall.is_zero() => write.await,
            Poll::Pending => match tokio::time::timeout(stall, write).await {
                Ok(r) => r,
                Err(_) => {
                    info!(conn = self.id, peer = %self.peer, "master stopped reading its replies; closing the connection");
                    return Err("the master stopped reading its replies".to_owned());
                }
            },
        };
        result.map_err(|e| {
            debug!(conn = self.id, "write failed: {e}");
            format!("write failed: {e}")
        })
    }
}
