//! The one connection type every master comes through, whatever its source (accepted
//! by `tcp/accept/mod.rs`, dialed by `tcp/dial/mod.rs`, a UDP source of `tcp/udp/mod.rs`): what it
//! is, its life from the master's arrival to its end (the codec chosen once, the
//! router attached, its priority class, the reader and the writer run together, the
//! replies owed written at the end), why it ended, and how a capture shows its frames.

use super::dial::Dialed;
use super::live::Running;
use super::Shared;
use crate::config::{ListenConfig, ListenFraming, Transport};
use crate::frame::Adu;
use crate::line::outbox::{Inbox, Outbox};
use crate::line::relay::ConnId;
use crate::line::woken::Woken;
use crate::masters::router::Router;
use crate::ops::capture::packet::{Dir, Ends, Part};
use crate::ops::capture::{Hub, Tap};
use crate::ops::metrics::{ConnectedMasters, MasterSeen};
use crate::ops::stats::Stats;
use crate::tls::server::Grant;
use codec::MasterCodec;
use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::debug;

pub(super) mod codec;
mod reader;
mod rtu;
pub(super) mod unasked;
mod writer;

/// A master's connection.
pub(super) struct Connection {
    pub(super) id: ConnId,
    pub(super) peer: SocketAddr,
    /// The configuration as it runs now (a reload changes it); each task reads it
    /// through a [`super::live::Live`] of its own.
    pub(super) running: Running,
    pub(super) listen: Arc<ListenConfig>,
    pub(super) router: Arc<Router>,
    pub(super) stats: Arc<Stats>,
    pub(super) shutdown: CancellationToken,
    pub(super) masters: Arc<ConnectedMasters>,
    /// The listener's own address.
    pub(super) local: SocketAddr,
    /// A TLS master's role, and what it may do.
    pub(super) grant: Option<Grant>,
    pub(super) capture: Hub,
    /// The TCP side's tap.
    pub(super) tap: Tap,
    /// Where answers it sends instead of requests are said.
    pub(super) unasked: Arc<super::unasked::UnaskedLog>,
}

/// What a master's source adds of its own to its connection's reader and writer: a
/// dial its heartbeat and the echoes of what it sent ([`Dialed`]); a master that came
/// to a listener, TCP or UDP, nothing ([`Inbound`]). The reader and writer are made
/// for each, so an accepted connection's carry no test for a dial's bytes.
pub(in crate::masters::tcp) trait Origin: Sync {
    /// A dialed connection's own state; `None` for any other.
    fn dialed(&self) -> Option<&Dialed>;
}

/// A master that came to a listener (accepted, or a UDP source): nothing of its own.
pub(in crate::masters::tcp) struct Inbound;

impl Origin for Inbound {
    #[inline(always)]
    fn dialed(&self) -> Option<&Dialed> {
        None
    }
}

/// Why a connection's reader stopped.
pub(super) enum End {
    /// The socket failed, the master broke the protocol, or it was idle too long:
    /// close now.
    Closed(Ended),
    /// No more requests will be read (the master shut down its sending side, or the
    /// gateway is shutting down): write the replies still owed, then close.
    Finish,
}

/// Why a connection ended (the log and a dial's outage say it).
#[derive(Debug, thiserror::Error)]
pub(super) enum Ended {
    #[error("protocol violation: {0}")]
    Violation(#[from] codec::FrameError),
    #[error("read failed: {0}")]
    Read(std::io::Error),
    #[error("write failed: {0}")]
    Write(std::io::Error),
    #[error("no request for {0} ms (idle_timeout_ms)")]
    Idle(u128),
    #[error("the master stopped reading its replies")]
    Stalled,
    #[error("the connection's replies ended")]
    NoMoreReplies,
    #[error("notifications have no way to this master")]
    Unattached,
    #[error("the master closed its side (or mbgate is stopping)")]
    Finished,
}

impl Connection {
    /// A master's connection from any source (accepted, dialed, a UDP source), with
    /// a new id: `listen` says what its requests may do, `local` is our end.
    pub(super) fn new(
        shared: &Shared,
        listen: Arc<ListenConfig>,
        peer: SocketAddr,
        local: SocketAddr,
    ) -> Connection {
        Connection {
            id: shared.ids.fetch_add(1, Ordering::Relaxed) + 1,
            peer,
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
            unasked: shared.unasked.clone(),
        }
    }

    /// The listener's framing chosen once: the rest is written over its codec, with
    /// what the master's source adds (`origin`). Why the connection ended, in words.
    pub(super) async fn run<O: Origin>(
        self,
        origin: O,
        rd: impl AsyncRead + Unpin,
        wr: impl AsyncWrite + Unpin,
    ) -> Ended {
        match self.listen.framing {
            ListenFraming::Mbap => self.serve::<codec::Mbap, O>(&origin, rd, wr).await,
            ListenFraming::Rtu => self.serve::<codec::Rtu, O>(&origin, rd, wr).await,
        }
    }

    async fn serve<C: MasterCodec, O: Origin>(
        self,
        origin: &O,
        rd: impl AsyncRead + Unpin,
        wr: impl AsyncWrite + Unpin,
    ) -> Ended {
        let mut why = Ended::Unattached;
        if let Some((mut outbox, inbox)) = self.begin::<C>() {
            // Each half polled only when something it waits on woke the task
            // (`crate::line::woken`): a reply wakes the writer alone, a request the
            // reader alone, where the task's every wake polled both (the reader's
            // socket, idle timer and shutdown for each reply: about 400 instructions a
            // transaction, docs/performance.md "A transaction on a quiet line").
            let mut writer = Woken::new(self.write_loop::<C, O>(origin, wr, inbox));
            let mut reader = Woken::new(self.read_loop::<C, O>(origin, rd, &mut outbox));
            let end = tokio::select! {
                end = &mut reader => end,
                w = &mut writer => End::Closed(w),
            };
            drop(reader);
            let finish = matches!(end, End::Finish);
            why = match end {
                End::Closed(w) => w,
                End::Finish => Ended::Finished,
            };
            if finish {
                // The relay answers every request it was given: at once when the
                // gateway shuts down (what is on the line within the response timeout
                // and its retries), else in its turn. Only shutdown bounds the wait
                // here; a master that stops reading meanwhile is closed by the writer.
                tokio::select! {
                    _ = outbox.settled() => {}
                    _ = &mut writer => {}
                    _ = async {
                        self.shutdown.cancelled().await;
                        // The configuration's as it runs at shutdown, as the
                        // gateway's own drain.
                        let bound = self.running.borrow().answer_within();
                        tokio::time::sleep(bound + Duration::from_secs(1)).await;
                    } => {}
                }
            }
        }
        self.end();
        why
    }

    /// The master arrived: said, listed among the masters connected, its outbox made
    /// and attached to the lines (for notifications) with its priority class. The
    /// outbox its reader takes tickets from and the inbox its writer reads; `None`:
    /// it could not be attached (the gateway is stopping), and [`Connection::end`]
    /// is all that is left.
    pub(super) fn begin<C: MasterCodec>(&self) -> Option<(Outbox, Inbox)> {
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
        // no notifications (nothing would tell them from a reply). The outbox's size is
        // fixed at connect (a reload does not change `max_pending_per_connection`).
        let pending = if C::IDS {
            self.running.borrow().max_pending_per_connection()
        } else {
            1
        };
        let (outbox, inbox) = Outbox::new(pending);
        // A UDP source gets them through an outbox of its own, if at all (`tcp/udp/mod.rs`).
        let notified = C::IDS && self.listen.transport != Transport::Udp;
        let attached = !notified || self.router.attach(self.id, &outbox.notifier());
        // Its role's priority class, else its listener's, as the configuration runs
        // now; told while the watch's value is borrowed (its read lock), and a reload
        // publishes the new configuration and reclassifies the masters under its
        // write lock (src/gateway/reload/mod.rs `reclassify`): so a reload's new
        // class never arrives before the old one.
        {
            let running = self.running.borrow();
            let role = self.grant.as_ref().map(|g| g.role.as_str());
            let class = running.priority_of(&self.listen, role);
            self.router.classify(self.id, class);
        }
        attached.then_some((outbox, inbox))
    }

    /// The master gone: off the lines, the masters connected and the capture.
    pub(super) fn end(&self) {
        self.router.detach(self.id);
        self.masters.remove(self.id);
        self.capture.forget(self.id);
        debug!(conn = self.id, peer = %self.peer, "master disconnected");
    }

    pub(super) fn ends(&self) -> Ends {
        Ends {
            client: self.peer,
            server: self.local,
        }
    }

    /// A frame to or from this master, for the capture: as the master framed it
    /// (MBAP with its own transaction id, or RTU with its CRC).
    pub(super) fn captured<C: MasterCodec>(&self, adu: &Adu, dir: Dir, label: &'static str) {
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
            p.span = crate::line::relay::span(adu.pdu());
            p.label = label;
        });
    }
}
