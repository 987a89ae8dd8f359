//! A master's request as the relay holds it (the ADU, the ticket its answer goes back
//! by, how often it was resent), with the identical reads of other masters that joined
//! it (coalescing: one transaction, each master answered with its own transaction id
//! through its own ticket), and the answers the relay gives itself: 0x0A, 0x06, 0x0B,
//! each counted in the relay's stats once for every master answered.

use super::inflight::Asked;
use super::scheduler::{Queued, ReadKey};
use super::ConnId;
use crate::config::BroadcastReply;
use crate::frame::Adu;
use crate::frame::{pdu, FunctionCode};
use crate::outbox::{Refusal, Ticket};
use crate::stats::Stats;

/// One master's request: who asked, under which transaction id, and the way back.
struct Asker {
    conn: ConnId,
    tid: u16,
    ticket: Ticket,
}

pub(super) struct Pending {
    /// The request as the first master sent it (its transaction id is that master's).
    pub(super) adu: Adu,
    /// The masters it answers: the one it is queued for first, then those whose
    /// identical read joined it, in the order they asked. Never empty.
    askers: Vec<Asker>,
    pub(super) attempts: u32,
    /// The scheduler's turn that last put it on the line (a resend is checked
    /// against it, `scheduler.rs`).
    turn: u64,
    /// The cache's generation for its unit when it came (`cache.rs`): its reply is
    /// kept only if nothing acted on the unit since.
    pub(super) cache_stamp: u64,
}

impl Queued for Pending {
    fn conn(&self) -> ConnId {
        self.conn()
    }
    fn unit(&self) -> u8 {
        self.adu.unit()
    }
    fn read_key(&self) -> Option<ReadKey> {
        read_key(&self.adu)
    }
    fn acts(&self) -> bool {
        !self.adu.function_code().is_read()
    }
    fn masters(&self) -> impl Iterator<Item = ConnId> + '_ {
        self.askers.iter().map(|a| a.conn)
    }
    fn join(&mut self, other: Self) {
        self.askers.extend(other.askers);
    }
    fn leave(&mut self, conn: ConnId) -> Option<Self> {
        if self.askers.iter().all(|a| a.conn == conn) {
            return None;
        }
        let (gone, kept): (Vec<Asker>, Vec<Asker>) =
            self.askers.drain(..).partition(|a| a.conn == conn);
        self.askers = kept;
        gone.first()?;
        Some(self.part(gone))
    }
    fn leave_one(&mut self, conn: ConnId) -> Option<Self> {
        let i = self.askers.iter().rposition(|a| a.conn == conn)?;
        if self.askers.len() == 1 {
            return None;
        }
        let one = self.askers.remove(i);
        Some(self.part(vec![one]))
    }
    fn turn(&self) -> u64 {
        self.turn
    }
    fn set_turn(&mut self, turn: u64) {
        self.turn = turn;
    }
}

/// The identity of a read that identical reads may join or be answered from the cache
/// for: FC 01-04, of one unit. (Unit 0 too: on an MBAP line it is a unit like any other;
/// on a bus a read to it never gets this far, answered 0x01 as a broadcast that cannot
/// be one.)
pub(super) fn read_key(adu: &Adu) -> Option<ReadKey> {
    let pdu: [u8; 5] = adu.pdu().try_into().ok()?;
    let coalescable = matches!(
        FunctionCode::new(pdu[0]),
        FunctionCode::READ_COILS
            | FunctionCode::READ_DISCRETE_INPUTS
            | FunctionCode::READ_HOLDING_REGISTERS
            | FunctionCode::READ_INPUT_REGISTERS
    );
    coalescable.then_some(ReadKey {
        unit: adu.unit(),
        pdu,
    })
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
            askers: vec![Asker {
                conn,
                tid: adu.tid(),
                ticket,
            }],
            adu,
            attempts: 0,
            turn: 0,
            cache_stamp: 0,
        }
    }

    /// `askers`, taken out of this request, as a request of their own.
    fn part(&self, askers: Vec<Asker>) -> Self {
        Pending {
            adu: self.adu.with_tid(askers[0].tid),
            askers,
            attempts: self.attempts,
            turn: self.turn,
            cache_stamp: self.cache_stamp,
        }
    }

    /// The master it is queued for.
    pub(super) fn conn(&self) -> ConnId {
        self.askers[0].conn
    }

    /// How many masters' requests it answers.
    pub(super) fn served(&self) -> u64 {
        self.askers.len() as u64
    }

    /// `reply` (any transaction id) to every master it serves, each with its own
    /// transaction id, after that master's answers to its earlier requests.
    pub(super) fn deliver(self, reply: &Adu) {
        for a in self.askers {
            a.ticket.answer(reply.with_tid(a.tid));
        }
    }

    /// Answers every master it serves with the gateway's own exception for `why`,
    /// each with its own transaction id, counted once for each.
    pub(super) fn answer_exception(self, why: Refusal, stats: &Stats) {
        for a in self.askers {
            a.ticket.refuse(&self.adu.with_tid(a.tid), why, stats);
        }
    }

    /// 0x0B for a backed-off unit, counted apart from timeouts.
    pub(super) fn answer_backed_off(self, stats: &Stats) {
        self.answer_exception(Refusal::BackedOff, stats);
    }

    /// A broadcast (unit 0, RTU/ASCII; a write: `FunctionCode::may_broadcast`) is on
    /// its way: no device answers it. The master gets nothing, or, with
    /// `broadcast_reply = "echo"`, the acknowledgement a device gives a write, made
    /// from the request itself: it carries nothing read from a device (docs/protocol.md
    /// §2).
    pub(super) fn broadcast_sent(self, reply: BroadcastReply) {
        match reply {
            // The ticket goes unanswered: the master may send another, and its
            // replies behind this one are not held up.
            BroadcastReply::None => drop(self),
            BroadcastReply::Echo => {
                let adu = Adu::build(self.adu.tid(), 0, &pdu::write_echo(self.adu.pdu()));
                self.deliver(&adu);
            }
        }
    }
}
