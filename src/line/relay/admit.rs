//! What comes into the loop and goes onto the line: a connection's command, a
//! master's request admitted (answered at once, from the cache, joined or queued, as
//! the scheduler decides), and the queued requests dispatched while the line has
//! room.

use super::command::{Command, ConnId};
use super::pending::Pending;
use super::scheduler::{Admitted, Queued};
use super::Relay;
use crate::frame::Adu;
use crate::line::outbox::{Refusal, Ticket};
use tokio::time::Instant;
use tracing::debug;

impl Relay {
    /// `cmd`, received at `now`.
    pub(super) fn on_command(&mut self, cmd: Command, now: Instant) {
        match cmd {
            Command::Attach { conn, notifier } => {
                self.masters.attach(conn, notifier);
                self.telemetry.masters(self.masters.len());
            }
            Command::Priority { conn, class } => self.sched.set_class(conn, class),
            Command::Detach { conn } => {
                self.masters.detach(conn);
                self.sched.detach(conn);
                self.telemetry.masters(self.masters.len());
            }
            Command::Retune {
                relay,
                units,
                traffic,
            } => {
                self.in_flight.retune(&relay, &units);
                self.telemetry.set_traffic(traffic);
                self.cfg = *relay;
            }
            Command::Request { conn, adu, ticket } => self.on_request(conn, adu, ticket, now),
        }
    }

    /// A master's request: answered at once (a broadcast that cannot be one, no path,
    /// a backed-off unit, a reply in the cache), joined to an identical read waiting
    /// for the line, or queued.
    pub(super) fn on_request(&mut self, conn: ConnId, adu: Adu, ticket: Ticket, now: Instant) {
        self.stats.add(&self.stats.requests, 1);
        self.telemetry.request(adu.unit());
        let mut req = Pending::new(conn, adu, ticket, now, &mut self.spare);
        let unit = req.adu.unit();
        if self.line.not_broadcast(&req.adu) {
            debug!(
                conn,
                fc = req.adu.function(),
                "a broadcast (unit 0) cannot carry this function: exception 0x01"
            );
            req.answer_exception(Refusal::NotBroadcast, &self.stats);
            return;
        }
        if req.acts() {
            self.cache.acted_on(unit);
        }
        if self.draining || !self.port.is_open() {
            req.answer_exception(Refusal::Unavailable, &self.stats);
            return;
        }
        if let Some(reply) = self.cached(&req, now) {
            self.stats.add(&self.stats.served_from_cache, 1);
            let emptied = req.deliver(&reply);
            self.spare.keep(emptied);
            return;
        }
        if self.in_flight.backed_off(unit, now) {
            self.pace_backed_off(req);
            return;
        }
        req.cache_stamp = self.cache.stamp(unit);
        // A full queue refuses the request of the master holding the most of it (the
        // scheduler's fair share).
        let joins = self.sched.joins();
        let admitted = self.sched.push(req);
        self.stats
            .add(&self.stats.coalesced, self.sched.joins() - joins);
        match admitted {
            Admitted::Queued | Admitted::Joined => {}
            Admitted::Displaced(refused) => {
                debug!(
                    conn = refused.conn(),
                    "queue full: 0x06 to the master holding the most of it, for conn {conn}"
                );
                refused.answer_exception(Refusal::Busy, &self.stats);
            }
            Admitted::Refused(req) => {
                req.answer_exception(Refusal::Busy, &self.stats);
            }
        }
    }

    /// The cached reply that may answer `req`: none while its master has a request
    /// that acts on the unit still waiting for the line (the read must see it).
    pub(super) fn cached(&self, req: &Pending, now: Instant) -> Option<Adu> {
        let key = req.read_key()?;
        let reply = self.cache.get(&key, now)?;
        (!self.sched.acts_waiting(req.conn(), key.unit)).then(|| reply.clone())
    }

    /// Puts queued requests on the line while it has room: fewer than `max_in_flight`
    /// outstanding (MBAP), or none outstanding, the inter-frame gap passed and no byte
    /// waiting to be read (RTU/ASCII). A request for a backed-off unit is answered
    /// 0x0B instead.
    pub(super) fn dispatch(&mut self, now: Instant) {
        while self.port.is_open()
            && self
                .line
                .has_room(self.in_flight.len(), self.tx_busy(), now)
            && self.sched.has_waiting()
            && !self.input_waiting()
        {
            let Some(req) = self.sched.next() else {
                break;
            };
            if req.attempts == 0 {
                let class = self.sched.class_of(&req);
                self.telemetry
                    .waited(class, now.saturating_duration_since(req.came));
            }
            if self.in_flight.backed_off(req.adu.unit(), now) {
                self.pace_backed_off(req);
                continue;
            }
            self.send(req, now);
        }
    }
}
