//! The accept loop of a TCP listener (docs/design.md §4.1 `[[listen]]`): the allow
//! list before a byte is read (`tcp/accept/admit.rs`), the connection limit, the TLS
//! handshake within the listener's budget (`tcp/accept/handshakes.rs`), each master then
//! served by its connection (`tcp/connection/mod.rs`) on a task of its own; accept()
//! failures backed off and said once a minute.

use super::connection::Inbound;
use super::{Connection, Listening, Shared};
use crate::line::port::Backoff;
use crate::tls::server::Acceptor;
use handshakes::Handshakes;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

pub(super) mod admit;
mod handshakes;

/// Long because it is the listener's loop: each step of a connection's admission
/// (accepted, allowed, a slot, its task) reads the state the listener's connections
/// share (the allow list's gate, the slots, the refusals' log, the handshake budget).
///
/// Accepts masters on `listener` until shutdown. A source not in the allow list is
/// closed at once, before any byte is read. On a plain listener a connection past
/// `max_connections` is closed at once; the others each get a task on the tracker. On a
/// TLS listener the handshake runs in the connection's task within the listener's
/// handshake budget (`tcp/accept/handshakes.rs`), and a connection slot is taken only once
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
                    start_tls(conn, stream, &acceptor, turn, &limit, &refusals).await;
                    closed.add(&closed.connections_closed, 1);
                });
            }
            (None, slot) => {
                tracker.spawn(async move {
                    let (rd, wr) = stream.into_split();
                    conn.run(Inbound, rd, wr).await;
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

/// The TLS handshake within its `turn` of the listener's budget, then, with a
/// connection slot (taken only now: a peer that never authenticates never holds
/// one), the master served. A handshake that must make room for a newer one ends
/// at once, counted as failed.
async fn start_tls(
    mut conn: Connection,
    stream: TcpStream,
    acceptor: &Acceptor,
    turn: Turn,
    limit: &Arc<Semaphore>,
    refusals: &admit::Refusals,
) {
    let handshake = admit::handshake(acceptor, stream, conn.id, conn.peer, &conn.stats, refusals);
    let done = tokio::select! {
        done = handshake => done,
        _ = turn.dropped.cancelled() => {
            conn.stats.add(&conn.stats.tls_failed, 1);
            debug!(conn = conn.id, peer = %conn.peer, "handshake dropped to make room for a newer one");
            None
        }
        _ = conn.shutdown.cancelled() => None,
    };
    drop(turn);
    let Some((stream, grant)) = done else {
        return;
    };
    let Ok(slot) = limit.clone().try_acquire_owned() else {
        conn.stats.add(&conn.stats.connections_refused, 1);
        refuse_at_limit(refusals, conn.peer, conn.listen.tcp.max_connections);
        return;
    };
    conn.grant = Some(grant);
    let (rd, wr) = tokio::io::split(stream);
    conn.run(Inbound, rd, wr).await;
    drop(slot);
}
