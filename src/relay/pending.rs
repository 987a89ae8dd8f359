//! A master's request as the relay holds it (its master, the ADU, the ticket its answer
//! goes back by, how often it was resent), and the answers the relay gives itself:
//! 0x0A, 0x06, 0x0B, each counted in the relay's stats.

use super::inflight::Asked;
use super::scheduler::Queued;
use super::ConnId;
use crate::config::BroadcastReply;
use crate::frame::pdu;
use crate::frame::Adu;
use crate::outbox::{Refusal, Ticket};
use crate::stats::Stats;

pub(super) struct Pending {
    pub(super) conn: ConnId,
    pub(super) adu: Adu,
    ticket: Ticket,
    pub(super) attempts: u32,
}

impl Queued for Pending {
    fn conn(&self) -> ConnId {
        self.conn
    }
    fn unit(&self) -> u8 {
        self.adu.unit()
    }
}

impl Asked for Pending {
    fn adu(&self) -> &Adu {
        &self.adu
    }
    fn attempts(&self) -> u32 {
        self.attempts
    }
}

impl Pending {
    /// A request just received, never sent.
    pub(super) fn new(conn: ConnId, adu: Adu, ticket: Ticket) -> Self {
        Self {
            conn,
            adu,
            ticket,
            attempts: 0,
        }
    }

    /// The answer to this request, to its master, after its answers to earlier ones.
    pub(super) fn deliver(self, adu: Adu) {
        self.ticket.answer(adu);
    }

    /// Answers with the gateway's own exception for `why`, counted by its kind.
    pub(super) fn answer_exception(self, why: Refusal, stats: &Stats) {
        self.ticket.refuse(&self.adu, why, stats);
    }

    /// 0x0B for a backed-off unit, counted apart from timeouts.
    pub(super) fn answer_backed_off(self, stats: &Stats) {
        self.answer_exception(Refusal::BackedOff, stats);
    }

    /// A broadcast (unit 0, RTU/ASCII) is on its way: no device answers it. The master
    /// gets nothing, or the answer a device would have given (`broadcast_reply`).
    pub(super) fn broadcast_sent(self, reply: BroadcastReply) {
        match reply {
            // The ticket goes unanswered: the master may send another, and its
            // replies behind this one are not held up.
            BroadcastReply::None => drop(self),
            BroadcastReply::Echo => {
                let adu = Adu::build(self.adu.tid(), 0, &pdu::write_echo(self.adu.pdu()));
                self.deliver(adu);
            }
        }
    }
}
