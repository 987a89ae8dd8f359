//! One master's way back: the pipelining slots it may hold, its replies written in the
//! order of its requests, and room for device notifications beside them (README "What
//! it does": masters, replies, notifications).
//!
//! Every invariant of that path lives here, so the connection (src/masters/tcp/mod.rs) and the
//! relay (src/line/relay/mod.rs) need not agree through comments:
//!
//! - A request read from the master gets a [`Ticket`] before it goes anywhere: a
//!   pipelining slot (`max_pending_per_connection` of them), a sequence number in read
//!   order, and a place reserved in the channel to the writer. So its answer can always
//!   be sent, by the relay or by the connection itself, and never waits for room.
//! - Whoever answers consumes the ticket (`Ticket::answer`); a ticket dropped
//!   unanswered (a broadcast with no reply, a request dropped with its master) still
//!   tells the writer, so no later reply waits for it.
//! - The writer ([`Inbox`]) releases replies in sequence: a reply that comes early
//!   (answered by the gateway at once, or by a device that answers out of order) waits
//!   for the ones before it. A master that pipelines with one transaction id, as many
//!   do with 0, pairs every reply with its request.
//! - The slot is free again only once the reply has been written, so a master never
//!   has more than `max_pending_per_connection` requests unanswered, counting replies
//!   waiting for their turn.
//! - A request the gateway answers itself gets the exception code of its
//!   `Refusal` and is counted by it (`Ticket::refuse`), whoever refuses it: the
//!   connection (limits, no relay) or the relay (no port, queue full, timeout, unit
//!   backed off).
//! - A connection is idle only while it owes nothing and is owed nothing
//!   (`Outbox::idle_at`): the clock runs from the master's last byte or its last
//!   reply, whichever is later.
//! - Notifications ([`Notifier`]) take no slot and no sequence number: they are written
//!   as they come, between replies, and never hold one up; they use only the channel's
//!   spare room, so a master that does not read misses them (counted by the relay) and
//!   never loses a reply for them.
//!
//! All of it is one small state under one mutex per master (the channel of
//! `outbox/queue.rs`, the slots beside its queue), shared by the connection,
//! its tickets, the relay's notifier and the writer: each step of a transaction (a
//! ticket, its answer, the writer taking it, the slot freed) is one uncontended lock.
//! (A tokio channel and semaphore did the same in about 1 500 instructions a
//! transaction, a tenth of the gateway's: callgrind, docs/performance.md
//! "Instructions a transaction, counted".)

use crate::frame::{Adu, ExceptionCode};
use crate::line::woken::keep;
use crate::ops::stats::Stats;
use queue::{Beside, Receiver, Sender};
use std::collections::BTreeMap;
use std::fmt;
use std::future::poll_fn;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::task::{Poll, Waker};
use std::time::Duration;
use tokio::time::Instant;

pub(crate) mod queue;

/// Room in each connection's channel for notifications, beyond its replies.
const NOTIFICATION_SLACK: usize = 16;

/// The most frames the gateway holds for one master at once, with
/// `max_pending` requests pipelined: its replies and the notifications beside them.
pub(crate) fn capacity(max_pending: usize) -> usize {
    max_pending + NOTIFICATION_SLACK
}

/// What travels to the writer.
enum Message {
    /// The answer to request `seq`, or `None` when it has none (e.g. a broadcast).
    Reply {
        seq: u64,
        adu: Option<Addressed>,
        slot: Slot,
    },
    Notification(Adu),
}

/// A frame for the master, and the transaction id and unit id it goes out with: the
/// master's own, which a reply from the line carries only once the writer frames it
/// (`Delivery::adu`), so that no frame is made for it in between (docs/performance.md
/// "A transaction on a quiet line").
struct Addressed {
    frame: Adu,
    tid: u16,
    unit: u8,
}

impl Addressed {
    /// `adu` as it is.
    fn of(adu: Adu) -> Addressed {
        Addressed {
            tid: adu.tid(),
            unit: adu.unit(),
            frame: adu,
        }
    }
}

/// A pipelining slot in use. Dropping it frees the slot and restarts the idle clock.
/// Never dropped while the state is locked (it locks it).
struct Slot {
    shared: Arc<queue::SharedQueue<Message, Slots>>,
}

impl Drop for Slot {
    fn drop(&mut self) {
        let now = Instant::now();
        let waiting = {
            let mut s = self.shared.lock();
            s.more.used -= 1;
            s.more.settled = now;
            s.more.outbox.take()
        };
        if let Some(w) = waiting {
            w.wake();
        }
    }
}

/// What the channel to the writer (`queue.rs`) keeps beside its messages: the
/// pipelining slots and the room promised. Its senders are the outbox, each notifier,
/// each ticket not yet answered: none left and the queue empty, the writer is done.
struct Slots {
    /// Pipelining slots in use: tickets handed out whose reply is not yet written.
    used: usize,
    /// Places in the queue promised to tickets not yet answered: a reply never waits
    /// for room.
    reserved: usize,
    /// The connection, waiting for a slot or room (`ticket`), or for every slot to
    /// be free (`settled`).
    outbox: Option<Waker>,
    /// When a slot was last freed: a reply written, or a request finished without one.
    settled: Instant,
    max_pending: usize,
    /// The most messages sent to the writer and not yet taken, with those promised.
    capacity: usize,
}

impl Beside for Slots {
    /// The writer took a message, or went: room for a connection waiting for it.
    fn room(&mut self) -> Option<Waker> {
        self.outbox.take()
    }
}

/// The connection's side: hands out tickets in read order.
pub struct Outbox {
    sender: Sender<Message, Slots>,
    next_seq: u64,
}

impl Outbox {
    /// An outbox for a master that may pipeline `max_pending` requests, and the inbox
    /// its writer reads.
    pub fn new(max_pending: usize) -> (Outbox, Inbox) {
        let (sender, receiver) = queue::channel(Slots {
            used: 0,
            reserved: 0,
            outbox: None,
            settled: Instant::now(),
            max_pending,
            capacity: capacity(max_pending),
        });
        let outbox = Outbox {
            sender,
            next_seq: 0,
        };
        let inbox = Inbox {
            receiver,
            next: 0,
            held: BTreeMap::new(),
        };
        (outbox, inbox)
    }

    /// A ticket for the next request read, once the master has a pipelining slot free.
    /// Cancel-safe: a ticket not handed out takes no sequence number.
    pub async fn ticket(&mut self) -> Ticket {
        let sender = &self.sender;
        let theirs = poll_fn(|cx| {
            let mut s = sender.lock();
            // Reserved replies never exceed `max_pending` and notifications take only
            // what is free, so the room is short only while the writer is behind on
            // notifications.
            let room = s.len() + s.more.reserved < s.more.capacity;
            if s.more.used < s.more.max_pending && room {
                s.more.used += 1;
                s.more.reserved += 1;
                Poll::Ready(sender.clone_locked(&mut s))
            } else {
                keep(&mut s.more.outbox, cx.waker());
                Poll::Pending
            }
        })
        .await;
        let seq = self.next_seq;
        self.next_seq += 1;
        Ticket {
            seq,
            unit: None,
            sender: Some(theirs),
        }
    }

    /// What the relay uses to send this master notifications.
    pub fn notifier(&self) -> Notifier {
        Notifier {
            sender: self.sender.clone(),
        }
    }

    /// Some request of this master is not yet answered (or its reply not yet written).
    pub(crate) fn owed(&self) -> bool {
        self.sender.lock().more.used > 0
    }

    /// When the master was last answered: its last reply written, or its last request
    /// finished without one. The start of the connection if neither yet.
    #[cfg(test)]
    pub(crate) fn last_settled(&self) -> Instant {
        self.sender.lock().more.settled
    }

    /// When a master whose last byte came at `last_read` is idle for `idle`: that long
    /// after its last byte or its last reply, whichever is later. `None` while it is
    /// owed a reply (or one is waiting to be written): a master waiting for a slow
    /// device is not idle.
    pub(crate) fn idle_at(&self, last_read: Instant, idle: Duration) -> Option<Instant> {
        let s = self.sender.lock();
        (s.more.used == 0).then(|| last_read.max(s.more.settled) + idle)
    }

    /// Returns once every ticket handed out has been answered and its reply written.
    pub(crate) async fn settled(&self) {
        poll_fn(|cx| {
            let mut s = self.sender.lock();
            if s.more.used == 0 {
                Poll::Ready(())
            } else {
                keep(&mut s.more.outbox, cx.waker());
                Poll::Pending
            }
        })
        .await
    }
}

/// Why the gateway answers a request itself: the exception code that says so and the
/// counter that counts it, declared together so that no local answer goes uncounted
/// or is counted as another kind (README, "Exceptions mbgate answers itself").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Refusal {
    /// Outside protocol limits: 01 or 03, as the function code table decides
    /// (`bad_requests`).
    BadRequest(ExceptionCode),
    /// No path to the device, 0x0A: no port, or shutting down (`unavailable`).
    Unavailable,
    /// The queue is full, 0x06 (`busy`).
    Busy,
    /// No reply in time, or the port was lost under it, 0x0B (`timeouts`).
    TargetFailed,
    /// Its unit is backed off: 0x0B at once (`backed_off`).
    BackedOff,
    /// The access rules do not permit it (read only, or no write rule matches): 0x01,
    /// as Modbus/TCP Security answers an unauthorized request (`denied`).
    Denied,
    /// To unit 0 on a bus, where it would be a broadcast, but not a write: no device
    /// would answer it, 0x01 (`broadcasts_refused`, docs/protocol.md §2).
    NotBroadcast,
}

impl Refusal {
    /// The exception code the master gets.
    pub(crate) fn code(self) -> ExceptionCode {
        match self {
            Refusal::BadRequest(code) => code,
            Refusal::Unavailable => ExceptionCode::GATEWAY_PATH_UNAVAILABLE,
            Refusal::Busy => ExceptionCode::SERVER_DEVICE_BUSY,
            Refusal::TargetFailed | Refusal::BackedOff => ExceptionCode::GATEWAY_TARGET_FAILED,
            Refusal::Denied => ExceptionCode::ILLEGAL_FUNCTION,
            Refusal::NotBroadcast => ExceptionCode::ILLEGAL_FUNCTION,
        }
    }

    /// The counter it adds to.
    pub(crate) fn counter(self, stats: &Stats) -> &AtomicU64 {
        match self {
            Refusal::BadRequest(_) => &stats.bad_requests,
            Refusal::Unavailable => &stats.unavailable,
            Refusal::Busy => &stats.busy,
            Refusal::TargetFailed => &stats.timeouts,
            Refusal::BackedOff => &stats.backed_off,
            Refusal::Denied => &stats.denied,
            Refusal::NotBroadcast => &stats.broadcasts_refused,
        }
    }
}

/// One request's claim on its master's way back. Answer it once; dropping it
/// unanswered says "no reply" so the requests behind it are not held up.
pub struct Ticket {
    seq: u64,
    /// The master's own unit id, put back into the answer (a remapped unit).
    unit: Option<u8>,
    /// Its slot and its place in the writer's queue, until answered.
    sender: Option<Sender<Message, Slots>>,
}

impl Ticket {
    /// Sends the reply to this request; it is written after the replies to every
    /// earlier request of the same master. Never waits and never fails: the room was
    /// reserved with the ticket (a master already gone simply never sees it).
    pub(crate) fn answer(self, adu: Adu) {
        let tid = adu.tid();
        self.answer_as(&adu, tid);
    }

    /// Sends `reply` (with any transaction id: the line's) as the reply to this
    /// request, written with transaction id `tid` (the master's), as [`Ticket::answer`]
    /// does: the frame is shared, not copied.
    pub(crate) fn answer_as(mut self, reply: &Adu, tid: u16) {
        let unit = self.unit.unwrap_or(reply.unit());
        self.send(Some(Addressed {
            frame: reply.clone(),
            tid,
            unit,
        }));
    }

    /// Answers `request` (the master's own) with the gateway's exception for `why`,
    /// counted.
    pub(crate) fn refuse(self, request: &Adu, why: Refusal, stats: &Stats) {
        stats.add(why.counter(stats), 1);
        let code = why.code();
        self.answer(Adu::exception(
            request.tid(),
            request.unit(),
            request.function_code(),
            code,
        ));
    }

    /// The answer will carry `unit`, whatever unit the line answered as: the master
    /// asked for `unit`, which is another id on the line (docs/design.md §4.1, `remap`).
    pub(crate) fn answering_as(mut self, unit: u8) -> Ticket {
        self.unit = Some(unit);
        self
    }

    fn send(&mut self, adu: Option<Addressed>) {
        let Some(sender) = self.sender.take() else {
            return;
        };
        let slot = Slot {
            shared: sender.shared().clone(),
        };
        let message = Message::Reply {
            seq: self.seq,
            adu,
            slot,
        };
        // The writer is gone: the slot is freed here, outside the lock.
        drop(sender.send_and_leave(message, |m| m.reserved -= 1));
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.send(None);
    }
}

impl fmt::Debug for Ticket {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Ticket").field("seq", &self.seq).finish()
    }
}

/// The relay's handle for one master's notifications.
#[derive(Clone)]
pub struct Notifier {
    sender: Sender<Message, Slots>,
}

impl Notifier {
    /// Queues a notification for the master, unless its spare room is used up (it is
    /// not reading) or it is gone: then false, and it misses this one.
    pub(crate) fn notify(&self, adu: Adu) -> bool {
        let message = Message::Notification(adu);
        self.sender
            .send_if(message, |s| s.len() + s.more.reserved < s.more.capacity)
            .is_ok()
    }
}

impl fmt::Debug for Notifier {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Notifier")
    }
}

/// The writer's side: frames in the order they must go out.
pub struct Inbox {
    /// Dropped first: the channel closes, its messages freed outside its lock, then
    /// those held (a slot locks it).
    receiver: Receiver<Message, Slots>,
    /// The sequence number of the next reply to write.
    next: u64,
    /// Replies that came before their turn.
    held: BTreeMap<u64, (Option<Addressed>, Slot)>,
}

/// A frame to deliver to the master. Drop it once written: a reply's pipelining slot is freed then.
pub struct Delivery {
    /// The frame to write to the master (a reply, or a notification), and its ids.
    answer: Addressed,
    _slot: Option<Slot>,
}

impl Delivery {
    /// The frame as the master gets it: with its own transaction id and unit id
    /// (made here when they are not the frame's: for a capture, the log, a test).
    pub fn adu(&self) -> Adu {
        let Addressed { frame, tid, unit } = &self.answer;
        if (frame.tid(), frame.unit()) == (*tid, *unit) {
            frame.clone()
        } else {
            Adu::build(*tid, *unit, frame.pdu())
        }
    }

    /// The frame as it came (a reply: with the line's transaction id and unit id).
    pub(crate) fn frame(&self) -> &Adu {
        &self.answer.frame
    }

    /// The transaction id it goes out with: the master's.
    pub(crate) fn tid(&self) -> u16 {
        self.answer.tid
    }

    /// The unit id it goes out with: the one the master asked.
    pub(crate) fn unit(&self) -> u8 {
        self.answer.unit
    }
}

impl Inbox {
    /// The next frame to write: a notification as soon as it comes, a reply once every
    /// earlier request of this master has been answered. `None` once nothing more can
    /// come. Cancel-safe.
    pub async fn next(&mut self) -> Option<Delivery> {
        loop {
            let (adu, slot) = match self.held.remove(&self.next) {
                Some(held) => held,
                None => match self.recv().await? {
                    Message::Notification(adu) => {
                        return Some(Delivery {
                            answer: Addressed::of(adu),
                            _slot: None,
                        })
                    }
                    // Its turn (nearly always: a master waits for each reply): out at
                    // once, without a stay among those held.
                    Message::Reply { seq, adu, slot } if seq == self.next => (adu, slot),
                    Message::Reply { seq, adu, slot } => {
                        self.held.insert(seq, (adu, slot));
                        continue;
                    }
                },
            };
            self.next += 1;
            match adu {
                Some(answer) => {
                    return Some(Delivery {
                        answer,
                        _slot: Some(slot),
                    })
                }
                // No reply to write: the slot is free now.
                None => continue,
            }
        }
    }

    /// The next message sent, in the order sent; `None` once none is left and nothing
    /// can send any more. Cancel-safe: nothing is taken unless returned.
    fn recv(&mut self) -> impl std::future::Future<Output = Option<Message>> + '_ {
        self.receiver.recv()
    }
}

#[cfg(test)]
mod tests;
