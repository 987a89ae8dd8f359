//! A master's connection reading its requests: the bytes read decoded by its codec
//! (strictly checked; on a dialed connection, the server's echoes and answers told
//! apart from its requests first, `tcp/dial/echo.rs`), one pipelining slot per request,
//! the idle timeout, and each request checked against the access rules
//! (docs/security.md) before it goes to the line serving its unit
//! ([`crate::masters::router`]).

use super::codec::MasterCodec;
use super::rtu;
use super::{Connection, End, Ended};
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

impl Connection {
    pub(in crate::masters::tcp) async fn read_loop<C: MasterCodec>(
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
        // On a timerfd of its own, not in tokio's timer, which every wait of the
        // runtime would consult (`Deadline`); none when there is no idle timeout.
        // Polled only once it went off (`crate::line::woken`), like the wait for shutdown.
        let mut idle_timer = (!idle.is_zero()).then(|| Woken::new(Deadline::new(last_read + idle)));
        let mut buf = BytesMut::with_capacity(512);
        let mut codec = C::default();
        let mut live = Live::new(&self.running);
        // One wait for shutdown for the connection's life, not one registered with
        // the token and dropped again at every request.
        let mut shutdown = Woken::new(self.shutdown.cancelled());
        // Bytes were read since the clock was last read for them. The idle clock runs
        // from the master's last byte or its last reply, whichever is later, and a
        // request read is always followed by its reply (or by its end without one,
        // which counts as a reply, an answer dropped unanswered too): the time of a
        // read is needed only when it leaves bytes that are no whole request yet. A
        // clock reading less a transaction. (A dialed connection reads it at each
        // read: its echoes get no reply, and its pauses are judged from it.)
        let mut unread_clock = false;
        // A dialed connection: when its server's last bytes came (its idle clock runs
        // from its last request, not from bytes that answer mbgate's own).
        let mut came = last_read;
        // The master closed its sending side once already.
        let mut ended = false;
        loop {
            // `held`: what a dialed server sent is held, until that instant if any.
            let (decoded, held) = match &self.dialed {
                None => (codec.decode(&mut buf), None),
                Some(d) => match self.dialed_front(d, &mut buf, &mut codec) {
                    echo::Front::Answered(_) => continue,
                    echo::Front::Wait(at) => (Ok(None), Some(at.map(Wake::At))),
                    echo::Front::Decoded(decoded) => {
                        if let Ok(Some(adu)) = &decoded {
                            if self.came_back::<C>(d, adu) {
                                continue;
                            }
                            last_read = came;
                        }
                        (decoded, None)
                    }
                },
            };
            match decoded {
                Ok(Some(adu)) => {
                    // One pipelining slot per request: with none free, stop reading
                    // and let TCP push back on the master.
                    let ticket = tokio::select! {
                        t = outbox.ticket() => t,
                        _ = &mut shutdown => return End::Finish,
                    };
                    self.take::<C>(&mut live, adu, ticket);
                    continue;
                }
                Ok(None) => {}
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
                    return End::Closed(Ended::Violation(e));
                }
            }
            if std::mem::take(&mut unread_clock) && !buf.is_empty() {
                last_read = Instant::now();
            }
            let wake = match held {
                Some(held) => held,
                None => codec.ended_by_pause(&buf).map(Wake::After),
            };
            tokio::select! {
                // Bytes first: a pause is only ever one where no byte came.
                biased;
                r = rd.read_buf(&mut buf) => match r {
                    Ok(0) if !ended && self.ended_dialed(&buf) => {
                        // What a dialed server sent last is judged first: no byte
                        // will join it.
                        ended = true;
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
                        return End::Finish;
                    }
                    Ok(_) => match &self.dialed {
                        None => unread_clock = true,
                        Some(d) => {
                            came = Instant::now();
                            d.echoes.lock().expect("not poisoned").came(came);
                        }
                    },
                    Err(e) => {
                        debug!(conn = self.id, "read failed: {e}");
                        return End::Closed(Ended::Read(e));
                    }
                },
                // Made only when polled: a disabled branch's future is still made,
                // and a sleep reads the clock.
                _ = async {
                    match wake {
                        Some(Wake::After(d)) => tokio::time::sleep(d).await,
                        Some(Wake::At(at)) => tokio::time::sleep_until(at).await,
                        None => {}
                    }
                }, if wake.is_some() => match wake {
                    Some(Wake::At(_)) => self.paused_dialed(),
                    _ => codec.paused(),
                },
                _ = async { idle_timer.as_mut().expect("guarded").await }, if idle_timer.is_some() => {
                    // Idle means the master owes nothing and is owed nothing: the clock
                    // runs from its last byte (a dialed server's: its last request;
                    // echoes and answers of heartbeats are none) or its last reply,
                    // whichever is later, and only while no request of its is
                    // unanswered. A partial frame that stopped growing is idle too: a
                    // master gone mid-frame must not hold its connection slot for ever.
                    let now = Instant::now();
                    let wake = match outbox.idle_at(last_read, idle) {
                        None => now + idle,
                        Some(at) if now >= at => {
                            info!(conn = self.id, peer = %self.peer, "idle timeout; closing the connection");
                            return End::Closed(Ended::Idle(idle.as_millis()));
                        }
                        Some(at) => at,
                    };
                    if let Some(t) = &mut idle_timer {
                        t.inner().get_mut().reset(wake);
                    }
                }
                _ = &mut shutdown => return End::Finish,
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

    /// On a dialed connection, what the front of `buf` is (`tcp/dial/echo.rs`): the
    /// server's echo or answer taken off (counted, said once a connection at info,
    /// then at debug), bytes held until a pause, or the codec's request.
    fn dialed_front<C: MasterCodec>(
        &self,
        d: &Dialed,
        buf: &mut BytesMut,
        codec: &mut C,
    ) -> echo::Front {
        let mut echoes = d.echoes.lock().expect("not poisoned");
        let front = echoes.next(buf, codec);
        if let echo::Front::Answered(answered) = front {
            self.stats.add(&self.stats.dial_answers, 1);
            let first = echoes.first(answered);
            drop(echoes);
            let (what, n) = match answered {
                echo::Answered::Echo(n) => ("echoed the identity or a heartbeat", n),
                echo::Answered::Answer(n) => ("answered the identity or a heartbeat", n),
            };
            if first {
                info!(conn = self.id, peer = %self.peer, "the server {what} ({n} bytes): dropped, never relayed (said once a connection; counted in dial_answers)");
            } else {
                debug!(conn = self.id, bytes = n, "the server {what}: dropped");
            }
        }
        front
    }

    /// Is `adu`, from a dialed server, the very reply last written to it come back
    /// (a server that echoes every byte sends a write's reply back, and it reads as
    /// the write)? Counted and said as an answer not answered; its bytes are gone.
    fn came_back<C: MasterCodec>(&self, d: &Dialed, adu: &Adu) -> bool {
        let frame = C::frame(adu);
        let replied = d.replied.lock().expect("not poisoned");
        if !replied.came_back(&frame, Instant::now()) {
            return false;
        }
        drop(replied);
        let what = super::unasked::Unasked::Reflected;
        self.unasked
            .note(what, &self.stats, self.peer, self.local, adu.as_bytes());
        true
    }

    /// A dialed server closed its sending side with bytes held (`buf`): true if they
    /// are to be judged before the reader ends.
    fn ended_dialed(&self, buf: &BytesMut) -> bool {
        match &self.dialed {
            Some(d) if !buf.is_empty() => {
                d.echoes.lock().expect("not poisoned").ended();
                true
            }
            _ => false,
        }
    }

    /// A dialed connection's reader waited for a pause and no byte came.
    fn paused_dialed(&self) {
        if let Some(d) = &self.dialed {
            d.echoes
                .lock()
                .expect("not poisoned")
                .paused(Instant::now());
        }
    }
}
