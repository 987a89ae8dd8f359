//! A master's connection reading its requests: the bytes read decoded by its codec
//! (strictly checked; on a dialed connection, the server's echoes and answers told
//! apart from its requests first, `tcp/dial/echo.rs`), one pipelining slot per request,
//! the idle timeout, and each request checked against the access rules
//! (docs/security.md) before it goes to the line serving its unit
//! ([`crate::masters::router`]).

use super::codec::{FrameError, MasterCodec};
use super::rtu;
use super::{Connection, End, Ended, Origin};
use crate::access;
use crate::frame::hex::Hex;
use crate::frame::pdu;
use crate::frame::Adu;
use crate::line::outbox::{Outbox, Refusal, Ticket};
use crate::line::port::serial::Deadline;
use crate::line::woken::Woken;
use crate::masters::router::Unrouted;
use crate::masters::tcp::dial::{echo, Dialed};
use crate::masters::tcp::live::Live;
use crate::ops::capture::packet::{Dir, Packet, Reason};
use bytes::BytesMut;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// What ends a wait for bytes besides them: the codec's pause (a request of unknown
/// shape), or the instant a dialed server's held bytes are judged.
#[derive(Clone, Copy)]
enum Wake {
    After(Duration),
    At(Instant),
}

impl Wake {
    /// Until it comes.
    async fn sleep(self) {
        match self {
            Wake::After(d) => tokio::time::sleep(d).await,
            Wake::At(at) => tokio::time::sleep_until(at).await,
        }
    }
}

/// What a dialed server's bytes give next.
enum DialedNext {
    /// An echo or answer was taken off, or the very reply last written came back:
    /// there may be more.
    Again,
    /// As a master's bytes would: the codec's request, nothing whole yet, or why they
    /// are no request.
    Decoded(Result<Option<Adu>, FrameError>),
    /// What the server sent is held, and judged at that instant if any.
    Held(Option<Wake>),
}

/// A reader's clocks between two reads. The idle clock runs from the master's last
/// byte or its last reply, whichever is later, and a request read is always followed
/// by its reply (or by its end without one, which counts as a reply, an answer
/// dropped unanswered too): the time of a read is needed only when it leaves bytes
/// that are no whole request yet, a clock reading less a transaction. (A dialed
/// connection reads it at each read: its echoes get no reply, and its pauses are
/// judged from it.)
struct Clocks {
    /// When the master last sent bytes (the idle clock's start).
    last_read: Instant,
    /// Bytes were read since the clock was last read for them.
    unread: bool,
    /// A dialed connection: when its server's last bytes came (its idle clock runs
    /// from its last request, not from bytes that answer mbgate's own).
    came: Instant,
    /// The master closed its sending side once already.
    ended: bool,
}

impl Clocks {
    fn new(now: Instant) -> Clocks {
        Clocks {
            last_read: now,
            unread: false,
            came: now,
            ended: false,
        }
    }
}

/// One idle timer for the connection's life, moved only when it goes off (the idle
/// clock is read then): a timer made afresh each turn of the loop would be registered
/// with tokio's timer once a request, and each registration wakes the reactor (a
/// system call; docs/performance.md "What a transaction costs"). On a timerfd of its
/// own, not in tokio's timer, which every wait of the runtime would consult
/// (`Deadline`); none when there is no idle timeout. Polled only once it went off
/// (`crate::line::woken`), like the wait for shutdown.
fn idle_timer(idle: Duration, now: Instant) -> Option<Woken<Deadline>> {
    (!idle.is_zero()).then(|| Woken::new(Deadline::new(now + idle)))
}

impl Connection {
    /// Reads the master's requests until it ends (`origin`: what its source adds,
    /// a dial's echoes; nothing for any other): each request decoded takes a
    /// pipelining slot (with none free it stops reading, and TCP pushes back on the
    /// master) and goes on, bytes are read while none is whole, and the wait ends
    /// with a pause that ends a request, the idle timeout or shutdown (one wait for
    /// it for the connection's life, not one registered with the token and dropped
    /// again at every request).
    pub(in crate::masters::tcp) async fn read_loop<C: MasterCodec, O: Origin>(
        &self,
        origin: &O,
        mut rd: impl AsyncRead + Unpin,
        outbox: &mut Outbox,
    ) -> End {
        let mut clocks = Clocks::new(Instant::now());
        let idle = Duration::from_millis(self.listen.tcp.idle_timeout_ms);
        let mut idle_timer = idle_timer(idle, clocks.last_read);
        let mut buf = BytesMut::with_capacity(512);
        let mut codec = C::default();
        let mut live = Live::new(&self.running);
        let mut shutdown = Woken::new(self.shutdown.cancelled());
        loop {
            let (decoded, held) = match origin.dialed() {
                None => (codec.decode(&mut buf), None),
                Some(d) => match self.dialed_next(d, &mut buf, &mut codec, &mut clocks) {
                    DialedNext::Again => continue,
                    DialedNext::Decoded(decoded) => (decoded, None),
                    DialedNext::Held(at) => (Ok(None), Some(at)),
                },
            };
            match decoded {
                Ok(Some(adu)) => {
                    let ticket = tokio::select! {
                        t = outbox.ticket() => t,
                        _ = &mut shutdown => return End::Finish,
                    };
                    self.take::<C>(&mut live, adu, ticket);
                    continue;
                }
                Ok(None) => {}
                Err(e) => return self.violation(&buf, e),
            }
            if std::mem::take(&mut clocks.unread) && !buf.is_empty() {
                clocks.last_read = Instant::now();
            }
            let wake = held.unwrap_or_else(|| codec.ended_by_pause(&buf).map(Wake::After));
            tokio::select! {
                // Bytes first: a pause is only ever one where no byte came.
                biased;
                r = rd.read_buf(&mut buf) => match (r, origin.dialed()) {
                    (Ok(n), None) if n > 0 => clocks.unread = true,
                    (r, d) => if let Some(end) = self.read_other(r, d, &buf, &mut clocks, outbox) { return end },
                },
                // Made only when polled: a disabled branch's future is still made,
                // and a sleep reads the clock.
                _ = async { wake.expect("guarded").sleep().await }, if wake.is_some() => match (wake, origin.dialed()) {
                    (Some(Wake::At(_)), Some(d)) => d.paused(Instant::now()),
                    _ => codec.paused(),
                },
                _ = async { idle_timer.as_mut().expect("guarded").await }, if idle_timer.is_some() => {
                    let timer = idle_timer.as_mut().expect("guarded").inner().get_mut();
                    if let Some(end) = self.idle_gone_off(timer, outbox, clocks.last_read, idle) { return end }
                }
                _ = &mut shutdown => return End::Finish,
            }
        }
    }

    /// A read that is not bytes of an accepted master: a dialed server's bytes (when
    /// they came), the end of the master's sending side, or a failure. `Some`: the
    /// reader ends.
    fn read_other(
        &self,
        read: std::io::Result<usize>,
        dialed: Option<&Dialed>,
        buf: &BytesMut,
        clocks: &mut Clocks,
        outbox: &Outbox,
    ) -> Option<End> {
        match read {
            Ok(0) if !clocks.ended && dialed.is_some_and(|d| d.ended(buf)) => {
                // What a dialed server sent last is judged first: no byte will join
                // it.
                clocks.ended = true;
                None
            }
            Ok(0) => {
                // A shutdown of the master's sending side (`shutdown(SHUT_WR)`,
                // `nc -N`): no more requests, but it still awaits its replies.
                debug!(
                    conn = self.id,
                    owed = outbox.owed(),
                    partial = buf.len(),
                    "master closed its sending side; writing the replies owed, then closing"
                );
                Some(End::Finish)
            }
            Ok(_) => {
                match dialed {
                    None => clocks.unread = true,
                    Some(d) => {
                        clocks.came = Instant::now();
                        d.came(clocks.came);
                    }
                }
                None
            }
            Err(e) => {
                debug!(conn = self.id, "read failed: {e}");
                Some(End::Closed(Ended::Read(e)))
            }
        }
    }

    /// The idle timer went off. Idle means the master owes nothing and is owed
    /// nothing: the clock runs from its last byte (a dialed server's: its last
    /// request; echoes and answers of heartbeats are none) or its last reply,
    /// whichever is later, and only while no request of its is unanswered. A partial
    /// frame that stopped growing is idle too: a master gone mid-frame must not hold
    /// its connection slot for ever. `Some`: it is closed; else the timer moved to
    /// when it may be next.
    fn idle_gone_off(
        &self,
        timer: &mut Deadline,
        outbox: &Outbox,
        last_read: Instant,
        idle: Duration,
    ) -> Option<End> {
        let now = Instant::now();
        let wake = match outbox.idle_at(last_read, idle) {
            None => now + idle,
            Some(at) if now >= at => {
                info!(conn = self.id, peer = %self.peer, "idle timeout; closing the connection");
                return Some(End::Closed(Ended::Idle(idle.as_millis())));
            }
            Some(at) => at,
        };
        timer.reset(wake);
        None
    }

    /// The master broke the protocol: counted, said, shown to a capture (a frame's
    /// worth of its bytes, and a few more); the connection closes.
    fn violation(&self, buf: &BytesMut, e: FrameError) -> End {
        if self.tap.on() {
            let end = buf.len().min(rtu::MAX_FRAME + 8);
            let mut p = Packet::dropped(None, Reason::Refused, buf[..end].to_vec(), false, "");
            p.note = Some(format!("dropped (refused): {e}; the connection was closed"));
            p.ends = Some(self.ends());
            p.conn = Some(self.id);
            self.tap.send(p, Instant::now());
        }
        self.stats.add(&self.stats.protocol_violations, 1);
        warn!(conn = self.id, peer = %self.peer, "protocol violation: {e}; closing the connection");
        End::Closed(Ended::Violation(e))
    }

    /// On a dialed connection, what comes next in `buf` (`tcp/dial/echo.rs`).
    fn dialed_next<C: MasterCodec>(
        &self,
        d: &Dialed,
        buf: &mut BytesMut,
        codec: &mut C,
        clocks: &mut Clocks,
    ) -> DialedNext {
        match d.front(self, buf, codec) {
            echo::Front::Answered(_) => DialedNext::Again,
            echo::Front::Wait(at) => DialedNext::Held(at.map(Wake::At)),
            echo::Front::Decoded(decoded) => {
                if let Ok(Some(adu)) = &decoded {
                    if d.came_back::<C>(self, adu) {
                        return DialedNext::Again;
                    }
                    clocks.last_read = clocks.came;
                }
                DialedNext::Decoded(decoded)
            }
        }
    }

    /// A request read, with its ticket: logged (`log.traffic` as the configuration
    /// runs now) and captured, then submitted.
    pub(in crate::masters::tcp) fn take<C: MasterCodec>(
        &self,
        live: &mut Live,
        adu: Adu,
        ticket: Ticket,
    ) {
        if live.get().log.traffic {
            debug!(target: "mbgate::traffic", dir = "master->gw", conn = self.id, "{}", Hex(adu.as_bytes()));
        }
        if self.tap.on() {
            self.captured::<C>(&adu, Dir::In, "master->gw");
        }
        self.submit(adu, ticket);
    }

    /// Hands a request to the relay, or answers it here when it cannot go on the line.
    /// Either way the answer goes through its ticket, so it keeps its place in the
    /// master's order.
    fn submit(&self, adu: Adu, ticket: Ticket) {
        // An answer is never answered: two peers that answer everything would loop
        // (docs/security.md "Threat model"). Its ticket goes unanswered.
        if let Some(what) = pdu::not_a_request(adu.pdu()) {
            self.unasked(what, &adu);
            drop(ticket);
            return;
        }
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
}
