//! A master's connection reading its requests: the bytes read decoded by its codec
//! (strictly checked; a dialed server's echoes and answers taken off first,
//! `tcp/echo.rs`), one pipelining slot per request, the idle timeout, and each
//! request checked against the access rules (docs/security.md) before it goes to the
//! line serving its unit ([`crate::masters::router`]).

use super::codec::{self, MasterCodec};
use super::connection::{Connection, End, Ended};
use super::{echo, rtu};
use crate::frame::hex::Hex;
use crate::frame::pdu;
use crate::frame::Adu;
use crate::line::outbox::{Outbox, Refusal, Ticket};
use crate::line::woken::Woken;
use crate::masters::access;
use crate::masters::router::Unrouted;
use crate::ops::capture::packet::{Dir, Packet, Reason};
use bytes::BytesMut;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::time::Instant;
use tracing::{debug, info, warn};

impl Connection {
    pub(super) async fn read_loop<C: MasterCodec>(
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
        // Polled only once it went off (`crate::line::woken`), like the wait for shutdown.
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
                    self.take::<C>(adu, ticket);
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
                    return End::Closed(Ended::Violation(e));
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
                        return End::Closed(Ended::Read(e));
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
                            return End::Closed(Ended::Idle(idle.as_millis()));
                        }
                        Some(at) => at,
                    };
                    idle_timer.inner().reset(wake);
                }
                _ = &mut shutdown => return End::Finish,
            }
        }
    }

    /// A request read, with its ticket: logged and captured, then submitted.
    pub(super) fn take<C: MasterCodec>(&self, adu: Adu, ticket: Ticket) {
        if self.cfg.log.traffic {
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
}
