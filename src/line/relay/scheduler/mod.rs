//! Which request goes on the line next: the per-master queues, round-robin between
//! masters, the queue's depth and each master's share of it, resends ahead of all, and
//! the joining of a read to an identical one still waiting (coalescing), all under one
//! invariant: no request goes on the line behind a later request of any master it
//! answers (docs/design.md §1 "Each master's order").
//! Plain data: no I/O, no clock; the relay's loop asks and acts.
//!
//! How the invariant is kept, whatever moves a request: every waiting request has a
//! number, given when it is queued; each master's queue lists the numbers of the
//! requests it waits for (its own, and those its reads joined) in the order it sent
//! them, which is also ascending, since a read joins only a request numbered after
//! everything its master already waits for. A request goes on the line only from the
//! front of the queue of every master it answers. A master leaving, or a full queue
//! taking one master's part of a shared read, takes that master out of the request
//! and nothing else: the request keeps its number and its place in the other masters'
//! queues. The request with the lowest number is always at the front of all of its
//! masters' queues, so something can always be sent. A resend goes ahead of all, and
//! only if no later request of any of its masters has gone on the line since it went.
//!
//! Priority classes (docs/masters.md "Priority"): each master has a class (its
//! listener's or its role's `priority`, 0 by default); a request's is the highest of
//! the masters it serves. Of the requests ready to go, one of the highest class goes,
//! round-robin among its masters as above; but when a request serving a master of a
//! lower class is ready too, and [`LOWER_EVERY`]` - 1` requests of the higher class
//! have gone in a row past it, the oldest such request goes instead: a lower class
//! gets at least one transaction in [`LOWER_EVERY`] of those taken from the queues,
//! however busy the higher one. Which request is ready is the same rule as without
//! classes (the front of every queue it is in), so each master's order holds.
//!
//! A request that finds nothing waiting (no queue, nothing to resend) goes next
//! whatever comes after it, so it is held alone (`lone`), without the numbers, queues
//! and shares above: on a line with one master polling, every request. It joins the
//! queues, as the first, as soon as anything else is asked of the scheduler (another
//! request, a master leaving, a unit backed off), before that is done (`settle`); so
//! every rule above holds as if it had been queued.
//!
//! The queues, the order and the choice of the next request are here; the classes
//! (`scheduler/classes.rs`), the joining of reads (`scheduler/joins.rs`), each
//! master's share of a full queue (`scheduler/shares.rs`) and what the scheduler asks
//! of a request (`scheduler/queued.rs`) in files of their own.

use super::ids::{IdMap, KeyMap};
use super::ConnId;
use std::collections::VecDeque;
use waiting::Waiting;

mod classes;
mod joins;
mod queued;
mod shares;
mod waiting;

pub(super) use queued::{Queued, ReadKey};

/// How many emptied queues the scheduler keeps for reuse: enough for the masters that
/// take turns on a busy line, few enough to hold no memory worth counting.
const SPARE_QUEUES: usize = 16;

/// When a lower class waits, at least one request in this many taken from the queues
/// serves it (the module notes).
pub(crate) const LOWER_EVERY: u32 = 8;

/// A queued request, and the write epoch of its unit when it was queued: it may be
/// joined only while no request that acts on its unit has been queued since.
#[derive(Debug)]
struct QueuedRequest<R> {
    req: R,
    epoch: (u64, u64),
}

/// The queues of requests waiting for the line.
#[derive(Debug)]
pub(super) struct Scheduler<R> {
    depth: usize,
    /// Whether an identical read may join one waiting (`coalesce`).
    coalesce: bool,
    /// The requests waiting, by number (the order they were queued in).
    waiting: Waiting<QueuedRequest<R>>,
    /// The number the next request queued gets.
    next_number: u64,
    /// Each master's waiting requests, its own and those it joined, as numbers in the
    /// order it sent them (ascending): a request goes on the line only from the front
    /// of the queue of every master it answers.
    queues: IdMap<ConnId, VecDeque<u64>>,
    /// Queues emptied, kept for the next master that starts waiting: a master that
    /// waits for each reply empties its queue every request, and a queue made afresh
    /// each time would be an allocation each time.
    spare: Vec<VecDeque<u64>>,
    /// Connections with queued requests, in round-robin order.
    ring: VecDeque<ConnId>,
    /// The connection whose request went on the line last: a connection that starts
    /// waiting goes ahead of it, since it has just had its turn.
    last_served: Option<ConnId>,
    /// Requests waiting, each counted once for every master it serves.
    queued: usize,
    /// Each master's part of `queued`: its share of the queue.
    held: IdMap<ConnId, usize>,
    /// The newest joinable read of each key, by number (a hint, checked).
    joinable: KeyMap<ReadKey, u64>,
    /// Requests that act, queued so far: per unit, and to unit 0.
    epochs: IdMap<u8, u64>,
    broadcast_epoch: u64,
    /// Requests to resend (reads after a timeout or a bad reply): ahead of the queues.
    retry: VecDeque<R>,
    /// The one request waiting, when it found nothing else waiting (the module notes):
    /// outside `waiting`, the queues, the ring and the shares until `settle`.
    lone: Option<R>,
    /// Requests handed to the line so far (each a turn), and for each master the turns
    /// that last put one of its requests on the line.
    turns: u64,
    last_out: IdMap<ConnId, LastOut>,
    /// Requests that joined another so far.
    joins: u64,
    /// Each master's priority class, if not 0.
    classes: IdMap<ConnId, u8>,
    /// Requests of a higher class taken in a row while one serving a lower class was
    /// ready.
    streak: u32,
}

/// The turns that last put a master's requests on the line: any, and one that acts.
#[derive(Debug, Default, Clone, Copy)]
struct LastOut {
    any: u64,
    acting: u64,
}

/// What became of a request offered to the queue.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Admitted<R> {
    /// Queued.
    Queued,
    /// Joined an identical read waiting for the line: answered with it.
    Joined,
    /// Queued (or joined), in place of this one: the newest request of the master
    /// holding the most of the queue, to be answered 0x06.
    Displaced(R),
    /// The queue is full and the master holds as much of it as any: its own request is
    /// given back, to be answered 0x06.
    Refused(R),
}

impl<R: Queued> Scheduler<R> {
    /// Queues that hold `depth` requests in all; `coalesce`: whether identical reads
    /// join.
    pub(super) fn new(depth: usize, coalesce: bool) -> Self {
        Self {
            depth,
            coalesce,
            waiting: Waiting::default(),
            next_number: 0,
            queues: IdMap::default(),
            spare: Vec::new(),
            ring: VecDeque::new(),
            last_served: None,
            queued: 0,
            held: IdMap::default(),
            joinable: KeyMap::default(),
            epochs: IdMap::default(),
            broadcast_epoch: 0,
            retry: VecDeque::new(),
            lone: None,
            turns: 0,
            last_out: IdMap::default(),
            joins: 0,
            classes: IdMap::default(),
            streak: 0,
        }
    }

    /// Requests queued, each once for every master it serves (resends not counted).
    pub(super) fn queued(&self) -> usize {
        self.queued + self.lone.as_ref().map_or(0, R::served)
    }

    /// Are requests waiting for the line (queued, or to be resent)?
    pub(super) fn has_waiting(&self) -> bool {
        !self.waiting.is_empty() || !self.retry.is_empty() || self.lone.is_some()
    }

    /// The request held alone, if any, joins the queues as `push` would have queued
    /// it (its unit's epoch was moved then): before anything else is asked of them.
    fn settle(&mut self) {
        if let Some(req) = self.lone.take() {
            let conn = req.conn();
            self.count(&req);
            let admitted = self.queue(conn, req);
            debug_assert!(
                matches!(admitted, Admitted::Queued),
                "nothing waited to be joined"
            );
        }
    }

    /// Queues `req` behind its master's earlier ones, or joins it to an identical read
    /// waiting for the line. When the queue is full the 0x06 falls on the master
    /// holding the most of it: if one holds at least two more waiting requests than
    /// this one's master, its newest makes room; else this master holds as many as
    /// any, and its own request is refused. So a master can always have its share of
    /// the queue waiting (the depth divided by the masters that want it), however fast
    /// the others resend. A joined request counts for its master like any other.
    pub(super) fn push(&mut self, req: R) -> Admitted<R> {
        let conn = req.conn();
        let alone = self.lone.is_none() && self.waiting.is_empty() && self.retry.is_empty();
        if alone && req.served() <= self.depth {
            if req.acts() {
                self.acted_on(req.unit());
            }
            self.lone = Some(req);
            return Admitted::Queued;
        }
        self.settle();
        let mut displaced = None;
        if self.queued + req.served() > self.depth {
            let mine = self.held.get(&conn).copied().unwrap_or(0);
            let heaviest = self.held.iter().max_by_key(|(_, n)| **n);
            match heaviest.map(|(&c, &n)| (c, n)) {
                Some((heavy, n)) if n >= mine + 2 => displaced = self.evict(heavy),
                _ => return Admitted::Refused(req),
            }
        }
        if req.acts() {
            self.acted_on(req.unit());
        }
        self.count(&req);
        let admitted = self.queue(conn, req);
        match displaced {
            Some(d) => Admitted::Displaced(d),
            None => admitted,
        }
    }

    /// `req` of `conn`, counted, joins an identical read or is queued.
    fn queue(&mut self, conn: ConnId, req: R) -> Admitted<R> {
        match self.try_join(req) {
            Ok(()) => Admitted::Joined,
            Err(req) => {
                let number = self.next_number;
                self.next_number += 1;
                if let (true, Some(key)) = (self.coalesce, req.read_key()) {
                    self.joinable.insert(key, number);
                }
                let epoch = self.epoch(req.unit());
                self.waiting.push(number, QueuedRequest { req, epoch });
                self.enlist(conn, number);
                Admitted::Queued
            }
        }
    }

    /// Request `number` goes at the back of `conn`'s queue. Round-robin from its
    /// arrival: a master that starts waiting goes behind every connection still
    /// waiting for a turn, ahead of the one just served.
    fn enlist(&mut self, conn: ConnId, number: u64) {
        let spare = &mut self.spare;
        let q = self
            .queues
            .entry(conn)
            .or_insert_with(|| spare.pop().unwrap_or_default());
        if q.is_empty() {
            match self.ring.back() {
                Some(&back) if Some(back) == self.last_served => {
                    self.ring.insert(self.ring.len() - 1, conn)
                }
                _ => self.ring.push_back(conn),
            }
        }
        q.push_back(number);
    }

    /// Request `number` is no longer in `conn`'s queue.
    fn unlist(&mut self, conn: ConnId, number: u64) {
        if let Some(q) = self.queues.get_mut(&conn) {
            q.retain(|&n| n != number);
            if q.is_empty() {
                self.drop_queue(conn);
                self.ring.retain(|&c| c != conn);
            }
        }
    }

    /// `conn` has no queue any more; its empty one is kept for another (a few of them).
    fn drop_queue(&mut self, conn: ConnId) {
        if let Some(q) = self.queues.remove(&conn) {
            if q.is_empty() && self.spare.len() < SPARE_QUEUES {
                self.spare.push(q);
            }
        }
    }

    /// Takes request `number` out of the waiting ones (not out of the queues).
    fn remove(&mut self, number: u64) -> Option<R> {
        let e = self.waiting.remove(number)?;
        if let Some(key) = e.req.read_key() {
            if self.joinable.get(&key) == Some(&number) {
                self.joinable.remove(&key);
            }
        }
        Some(e.req)
    }

    /// `req`, on the line at turn `req.turn()`, got no usable reply and may be resent:
    /// ahead of every queue, unless that would put it behind a later request of one of
    /// its masters that went on the line since (more than one in flight) and that
    /// could change its answer: a later request that acts, or any later request when
    /// `req` itself acts. A read resent behind its master's later reads gets the
    /// answer it would have got in its place. Given back too when all its masters have
    /// gone (nobody wants it). What is given back is answered as a request that was
    /// not resent.
    pub(super) fn resend(&mut self, req: R) -> Result<(), R> {
        let turn = req.turn();
        let acts = req.acts();
        let overtaken = req.masters().any(|c| {
            self.last_out.get(&c).is_some_and(|out| {
                let later = if acts { out.any } else { out.acting };
                later > turn
            })
        });
        let unwanted = req.masters().all(|c| !self.last_out.contains_key(&c));
        if overtaken || unwanted {
            return Err(req);
        }
        self.retry.push_back(req);
        Ok(())
    }

    /// The next request to put on the line: a resend first, then round-robin across
    /// connections, the first whose next request is next for every master it answers.
    pub(super) fn next(&mut self) -> Option<R> {
        let mut req = match (self.retry.pop_front(), self.lone.take()) {
            (Some(req), lone) => {
                self.lone = lone;
                req
            }
            // Alone, it is the one ready: as `take_queued` would leave things.
            (None, Some(req)) => {
                if !self.classes.is_empty() {
                    self.streak = 0;
                }
                self.last_served = Some(req.conn());
                req
            }
            (None, None) => self.next_queued()?,
        };
        self.turns += 1;
        let turn = self.turns;
        req.set_turn(turn);
        let acts = req.acts();
        for c in req.masters() {
            let out = self.last_out.entry(c).or_default();
            out.any = turn;
            if acts {
                out.acting = turn;
            }
        }
        Some(req)
    }

    fn next_queued(&mut self) -> Option<R> {
        let ready = |s: &Self, number: u64| {
            s.waiting.get(number).is_some_and(|e| {
                e.req
                    .masters()
                    .all(|c| s.queues.get(&c).and_then(|q| q.front()) == Some(&number))
            })
        };
        if self.classes.is_empty() {
            // One class: the first ready in round-robin order.
            let found = self.ring.iter().position(|c| {
                self.queues
                    .get(c)
                    .and_then(|q| q.front())
                    .is_some_and(|&n| ready(self, n))
            });
            return self.take_queued(found);
        }
        // The requests ready to go, in round-robin order, with their classes.
        let candidates: Vec<(usize, u64, (u8, u8))> = self
            .ring
            .iter()
            .enumerate()
            .filter_map(|(i, c)| {
                let &n = self.queues.get(c)?.front()?;
                let e = self.waiting.get(n)?;
                ready(self, n).then(|| (i, n, self.classes_of(&e.req)))
            })
            .collect();
        let top = candidates.iter().map(|(_, _, (_, hi))| *hi).max();
        // The oldest ready request that serves a master below the top class.
        let lower = top.and_then(|top| {
            let below = candidates.iter().filter(|(_, _, (lo, _))| *lo < top);
            below.min_by_key(|(_, n, _)| *n).map(|(i, ..)| *i)
        });
        let found = match (top, lower) {
            (Some(_), Some(i)) if self.streak + 1 >= LOWER_EVERY => {
                self.streak = 0;
                Some(i)
            }
            (Some(top), lower) => {
                self.streak = if lower.is_some() { self.streak + 1 } else { 0 };
                let first = candidates.iter().find(|(_, _, (_, hi))| *hi == top);
                first.map(|(i, ..)| *i)
            }
            (None, _) => None,
        };
        self.take_queued(found)
    }

    /// Takes out the front request of the connection at `found` in the ring (or, if
    /// none is ready, which never happens, the lowest numbered).
    fn take_queued(&mut self, found: Option<usize>) -> Option<R> {
        let (conn, number) = match found {
            Some(i) => {
                let conn = self.ring.remove(i)?;
                (conn, *self.queues.get(&conn)?.front()?)
            }
            // Never: the lowest number is at the front of all its masters' queues.
            None => {
                let (number, e) = self.waiting.first()?;
                let conn = e.req.conn();
                self.ring.retain(|&c| c != conn);
                (conn, number)
            }
        };
        let req = self.remove(number)?;
        for c in req.masters() {
            if let Some(q) = self.queues.get_mut(&c) {
                if q.front() == Some(&number) {
                    q.pop_front();
                }
                if q.is_empty() {
                    self.drop_queue(c);
                    if c != conn {
                        self.ring.retain(|&r| r != c);
                    }
                }
            }
        }
        if self.queues.contains_key(&conn) {
            self.ring.push_back(conn);
        }
        self.uncount(&req);
        self.last_served = Some(conn);
        Some(req)
    }

    /// The master went away: its waiting requests are dropped (their tickets with them).
    /// A read it shared with others stays for them, where it was.
    pub(super) fn detach(&mut self, conn: ConnId) {
        self.settle();
        self.last_out.remove(&conn);
        self.classes.remove(&conn);
        self.retry.retain_mut(|r| {
            if r.masters().all(|c| c == conn) {
                return false;
            }
            r.leave(conn);
            true
        });
        let Some(q) = self.queues.remove(&conn) else {
            return;
        };
        self.ring.retain(|&c| c != conn);
        for number in q {
            let Some(e) = self.waiting.get_mut(number) else {
                continue;
            };
            let gone = match e.req.leave(conn) {
                Some(part) => part,
                None => match self.remove(number) {
                    Some(whole) => whole,
                    None => continue,
                },
            };
            self.uncount(&gone);
        }
    }

    /// Takes every waiting request out: resends first, then the queues.
    pub(super) fn drain_all(&mut self) -> Vec<R> {
        self.settle();
        self.ring.clear();
        self.queues.clear();
        self.queued = 0;
        self.held.clear();
        self.joinable.clear();
        let mut all: Vec<R> = std::mem::take(&mut self.retry).into();
        all.extend(self.waiting.drain().map(|e| e.req));
        all
    }

    /// Takes out every waiting request for `unit` (it was just backed off).
    pub(super) fn take_unit(&mut self, unit: u8) -> Vec<R> {
        self.settle();
        let numbers: Vec<u64> = self
            .waiting
            .iter()
            .filter(|(_, e)| e.req.unit() == unit)
            .map(|(n, _)| n)
            .collect();
        let mut swept = Vec::new();
        for number in numbers {
            let Some(req) = self.remove(number) else {
                continue;
            };
            let masters: Vec<ConnId> = req.masters().collect();
            for c in masters {
                self.unlist(c, number);
            }
            self.uncount(&req);
            swept.push(req);
        }
        let (gone, kept) = std::mem::take(&mut self.retry)
            .into_iter()
            .partition(|r| r.unit() == unit);
        self.retry = kept;
        swept.extend::<VecDeque<R>>(gone);
        swept
    }

    /// Checks the bookkeeping against the requests (tests): every count, every queue
    /// ascending and listing exactly the requests its master waits for, the ring
    /// holding exactly the masters with a queue.
    #[cfg(test)]
    fn audit(&self) {
        if self.lone.is_some() {
            // Alone: nothing else queued (a resend may wait), and nothing counted in
            // the queues.
            assert!(self.waiting.is_empty(), "alone");
            assert!(self.held.is_empty() && self.queued == 0 && self.ring.is_empty());
            return;
        }
        let mut held: IdMap<ConnId, usize> = IdMap::default();
        let mut listed: IdMap<ConnId, Vec<u64>> = IdMap::default();
        for (n, e) in self.waiting.iter() {
            for c in e.req.masters() {
                *held.entry(c).or_default() += 1;
                let l = listed.entry(c).or_default();
                if l.last() != Some(&n) {
                    l.push(n);
                }
            }
        }
        assert_eq!(held, self.held, "shares");
        assert_eq!(held.values().sum::<usize>(), self.queued, "queued");
        let queues: IdMap<ConnId, Vec<u64>> = self
            .queues
            .iter()
            .map(|(&c, q)| (c, q.iter().copied().collect()))
            .collect();
        assert_eq!(listed, queues, "queues");
        let mut ring: Vec<ConnId> = self.ring.iter().copied().collect();
        ring.sort_unstable();
        let mut with_queue: Vec<ConnId> = self.queues.keys().copied().collect();
        with_queue.sort_unstable();
        assert_eq!(ring, with_queue, "ring");
    }
}

#[cfg(test)]
mod tests;
