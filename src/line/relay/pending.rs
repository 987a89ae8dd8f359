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
use crate::line::outbox::{Refusal, Ticket};
use crate::ops::stats::Stats;
use tokio::time::Instant;

/// One master's request: who asked, under which transaction id, and the way back.
struct Asker {
    conn: ConnId,
    tid: u16,
    ticket: Ticket,
}

/// The masters a request answers, never none: the first held in place, so a request
/// of one master (nearly all of them) allocates nothing for its list.
struct Askers {
    first: Asker,
    /// Those whose identical reads joined it, in the order they asked.
    more: Vec<Asker>,
}

impl Askers {
    fn one(first: Asker) -> Self {
        Askers {
            first,
            more: Vec::new(),
        }
    }

    /// Takes out those `gone` picks, in their order, unless that is none of them or
    /// all of them (a list is never empty): `None` then, and the list as it was.
    fn split_off(&mut self, gone: impl Fn(&Asker) -> bool) -> Option<Askers> {
        if self.iter().all(&gone) || !self.iter().any(&gone) {
            return None;
        }
        let (mut out, mut kept): (Vec<Asker>, Vec<Asker>) =
            std::mem::take(&mut self.more).into_iter().partition(&gone);
        let first = if gone(&self.first) {
            // Someone is kept, and it is not the first: the earliest kept leads now.
            std::mem::replace(&mut self.first, kept.remove(0))
        } else {
            out.remove(0)
        };
        self.more = kept;
        Some(Askers { first, more: out })
    }

    /// Takes out the last asker of `conn`, unless it is the only one left (or there
    /// is none).
    fn remove_last_of(&mut self, conn: ConnId) -> Option<Asker> {
        if self.more.is_empty() {
            return None;
        }
        if let Some(i) = self.more.iter().rposition(|a| a.conn == conn) {
            return Some(self.more.remove(i));
        }
        if self.first.conn != conn {
            return None;
        }
        let lead = self.more.remove(0);
        Some(std::mem::replace(&mut self.first, lead))
    }

    fn len(&self) -> usize {
        1 + self.more.len()
    }

    fn iter(&self) -> impl Iterator<Item = &Asker> {
        std::iter::once(&self.first).chain(&self.more)
    }

    fn extend(&mut self, other: Askers) {
        self.more.push(other.first);
        self.more.extend(other.more);
    }
}

/// Every one, in order.
impl IntoIterator for Askers {
    type Item = Asker;
    type IntoIter = std::iter::Chain<std::iter::Once<Asker>, std::vec::IntoIter<Asker>>;

    fn into_iter(self) -> Self::IntoIter {
        std::iter::once(self.first).chain(self.more)
    }
}

/// A request as the relay holds it, boxed: it moves a dozen times a transaction (in
/// from the connection, into the queue, onto the line, back with its reply), and a
/// pointer moves for nothing where the whole of it went through `memcpy` each time,
/// about 4 % of the gateway's instructions a transaction (callgrind,
/// docs/performance.md "Instructions a transaction, counted"). The box of a request
/// answered by the line is kept for the next one ([`Spare`]): no allocation a
/// transaction for it.
pub(super) struct Pending(Box<Option<Parts>>);

impl std::ops::Deref for Pending {
    type Target = Parts;
    fn deref(&self) -> &Parts {
        // Empty only once delivered, and then it is no `Pending` any more.
        (*self.0)
            .as_ref()
            .expect("a pending request holds its parts")
    }
}

impl std::ops::DerefMut for Pending {
    fn deref_mut(&mut self) -> &mut Parts {
        (*self.0)
            .as_mut()
            .expect("a pending request holds its parts")
    }
}

/// Boxes of requests answered, emptied, for the next requests.
#[derive(Default)]
// The boxes themselves are what is kept: each becomes a `Pending` again as it is.
#[allow(clippy::vec_box)]
pub(super) struct Spare(Vec<Box<Option<Parts>>>);

impl Spare {
    /// Enough for the requests a line turns round between two of its reads.
    const KEPT: usize = 8;

    /// A box for `parts`: a spare one if there is one.
    fn boxed(&mut self, parts: Parts) -> Box<Option<Parts>> {
        match self.0.pop() {
            Some(mut b) => {
                *b = Some(parts);
                b
            }
            None => Box::new(Some(parts)),
        }
    }

    /// Keeps `emptied` (a request's box, answered) for the next request, a few.
    pub(super) fn keep(&mut self, emptied: Emptied) {
        debug_assert!(emptied.0.is_none());
        if self.0.len() < Self::KEPT {
            self.0.push(emptied.0);
        }
    }
}

/// The box of a request answered, empty: for [`Spare::keep`], or dropped.
pub(super) struct Emptied(Box<Option<Parts>>);

/// What a [`Pending`] holds.
pub(super) struct Parts {
    /// The request as the first master sent it (its transaction id is that master's).
    pub(super) adu: Adu,
    /// The masters it answers: the one it is queued for first, then those whose
    /// identical read joined it, in the order they asked.
    askers: Askers,
    pub(super) attempts: u32,
    /// The scheduler's turn that last put it on the line (a resend is checked
    /// against it, `scheduler.rs`).
    turn: u64,
    /// The cache's generation for its unit when it came (`cache.rs`): its reply is
    /// kept only if nothing acted on the unit since.
    pub(super) cache_stamp: u64,
    /// When the relay took it: its wait in the queue counts from here.
    pub(super) came: Instant,
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
    fn join(&mut self, mut other: Self) {
        let parts = other.0.take().expect("a pending request holds its parts");
        self.askers.extend(parts.askers);
    }
    fn leave(&mut self, conn: ConnId) -> Option<Self> {
        let gone = self.askers.split_off(|a| a.conn == conn)?;
        Some(self.part(gone))
    }
    fn leave_one(&mut self, conn: ConnId) -> Option<Self> {
        let one = self.askers.remove_last_of(conn)?;
        Some(self.part(Askers::one(one)))
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
    /// A request just received at `came`, never sent, in a box from `spare`.
    pub(super) fn new(
        conn: ConnId,
        adu: Adu,
        ticket: Ticket,
        came: Instant,
        spare: &mut Spare,
    ) -> Self {
        Pending(spare.boxed(Parts {
            askers: Askers::one(Asker {
                conn,
                tid: adu.tid(),
                ticket,
            }),
            adu,
            attempts: 0,
            turn: 0,
            cache_stamp: 0,
            came,
        }))
    }

    /// A request made of `parts`.
    fn of(parts: Parts) -> Self {
        Pending(Box::new(Some(parts)))
    }

    /// `askers`, taken out of this request, as a request of their own.
    fn part(&self, askers: Askers) -> Self {
        Pending::of(Parts {
            adu: self.adu.with_tid(askers.first.tid),
            askers,
            attempts: self.attempts,
            turn: self.turn,
            cache_stamp: self.cache_stamp,
            came: self.came,
        })
    }

    /// The master it is queued for.
    pub(super) fn conn(&self) -> ConnId {
        self.askers.first.conn
    }

    /// How many masters' requests it answers.
    pub(super) fn served(&self) -> u64 {
        self.askers.len() as u64
    }

    /// `reply` (any transaction id) to every master it serves, each with its own
    /// transaction id, after that master's answers to its earlier requests. Its box,
    /// emptied, for the next request.
    pub(super) fn deliver(mut self, reply: &Adu) -> Emptied {
        let parts = self.0.take().expect("a pending request holds its parts");
        for a in parts.askers {
            a.ticket.answer_as(reply, a.tid);
        }
        Emptied(self.0)
    }

    /// Answers every master it serves with the gateway's own exception for `why`,
    /// each with its own transaction id, counted once for each.
    pub(super) fn answer_exception(mut self, why: Refusal, stats: &Stats) {
        let Parts { adu, askers, .. } = self.0.take().expect("a pending request holds its parts");
        for a in askers {
            a.ticket.refuse(&adu.with_tid(a.tid), why, stats);
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
                drop(self.deliver(&adu));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::line::outbox::Outbox;

    /// Askers of connections `conns`, in order, each with transaction id its index.
    async fn askers(outbox: &mut Outbox, conns: &[ConnId]) -> Askers {
        let mut all = Vec::new();
        for (i, &conn) in conns.iter().enumerate() {
            let ticket = outbox.ticket().await;
            all.push(Asker {
                conn,
                tid: i as u16,
                ticket,
            });
        }
        let mut all = all.into_iter();
        let mut a = Askers::one(all.next().unwrap());
        for more in all {
            a.extend(Askers::one(more));
        }
        a
    }

    fn order(a: &Askers) -> Vec<(ConnId, u16)> {
        a.iter().map(|a| (a.conn, a.tid)).collect()
    }

    /// Taking masters out keeps everyone's order, on both sides, and never leaves a
    /// list empty, whether the first is among those taken or not.
    #[tokio::test]
    async fn askers_split_and_keep_their_order() {
        let (mut outbox, _inbox) = Outbox::new(32);
        let mut a = askers(&mut outbox, &[1, 2, 1, 3, 1]).await;
        assert_eq!(a.len(), 5);
        let gone = a.split_off(|x| x.conn == 1).unwrap();
        assert_eq!(order(&gone), [(1, 0), (1, 2), (1, 4)]);
        assert_eq!(order(&a), [(2, 1), (3, 3)]);
        let gone = a.split_off(|x| x.conn == 3).unwrap();
        assert_eq!(order(&gone), [(3, 3)]);
        assert_eq!(order(&a), [(2, 1)]);
        assert!(a.split_off(|x| x.conn == 2).is_none(), "all of them");
        assert!(a.split_off(|x| x.conn == 9).is_none(), "none of them");
        assert_eq!(order(&a), [(2, 1)]);

        let mut a = askers(&mut outbox, &[1, 2, 1, 3]).await;
        assert_eq!(a.remove_last_of(1).map(|x| x.tid), Some(2));
        assert_eq!(order(&a), [(1, 0), (2, 1), (3, 3)]);
        assert_eq!(a.remove_last_of(1).map(|x| x.tid), Some(0), "the first");
        assert_eq!(order(&a), [(2, 1), (3, 3)]);
        assert!(a.remove_last_of(9).is_none());
        assert_eq!(a.remove_last_of(3).map(|x| x.tid), Some(3));
        assert!(a.remove_last_of(2).is_none(), "the only one left");
        assert_eq!(order(&a), [(2, 1)]);
        let served: Vec<u16> = a.into_iter().map(|x| x.tid).collect();
        assert_eq!(served, [1]);
    }
}
