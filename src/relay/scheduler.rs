//! Which request goes on the line next: the per-master queues, round-robin between
//! masters, the queue's depth and each master's share of it, resends ahead of all, and
//! the joining of a read to an identical one still waiting (coalescing).
//! Plain data: no I/O, no clock; the relay's loop asks and acts.

use super::ConnId;
use std::collections::{HashMap, VecDeque};

/// What makes two reads the same read: the unit and the PDU (function code 01-04,
/// address, count). Two requests with the same key get the same reply from the device
/// if nothing acted on it in between.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) struct ReadKey {
    pub(super) unit: u8,
    pub(super) pdu: [u8; 5],
}

/// What the scheduler needs to know of a request.
pub(super) trait Queued: Sized {
    /// The master it is queued for (the first of the masters it serves).
    fn conn(&self) -> ConnId;
    /// The unit it is for.
    fn unit(&self) -> u8;
    /// A read (FC 01-04 of one unit) that an identical read may join; `None` for
    /// anything else.
    fn read_key(&self) -> Option<ReadKey>;
    /// May it act on its unit (anything but a read)? It ends the chance for reads
    /// queued before it to be joined by reads that come after it; to unit 0, for every
    /// unit (a broadcast on a bus).
    fn acts(&self) -> bool;
    /// The masters it serves, once for each of their requests it answers.
    fn masters(&self) -> impl Iterator<Item = ConnId> + '_;
    /// `other`, an identical read, is answered with this one.
    fn join(&mut self, other: Self);
    /// Takes out the requests of `conn` as a request of their own, leaving the others'
    /// (the first of them now the one it is queued for); `None` when it serves no other
    /// master (then the whole request is `conn`'s) or does not serve `conn`.
    fn leave(&mut self, conn: ConnId) -> Option<Self>;
    /// Takes out the newest request of `conn` alone, as [`Queued::leave`] does all of
    /// them; `None` when it is the only request this one answers.
    fn leave_one(&mut self, conn: ConnId) -> Option<Self>;

    /// How many masters' requests it answers.
    fn served(&self) -> usize {
        self.masters().count()
    }
}

/// A queued request, and the write epoch of its unit when it was queued: it may be
/// joined only while no request that acts on its unit has been queued since.
#[derive(Debug)]
struct Entry<R> {
    req: R,
    epoch: (u64, u64),
}

/// The queues of requests waiting for the line.
#[derive(Debug)]
pub(super) struct Scheduler<R> {
    depth: usize,
    /// Whether an identical read may join one waiting (`coalesce`).
    coalesce: bool,
    queues: HashMap<ConnId, VecDeque<Entry<R>>>,
    /// Connections with queued requests, in round-robin order.
    ring: VecDeque<ConnId>,
    /// The connection whose request went on the line last: a connection that starts
    /// waiting goes ahead of it, since it has just had its turn.
    last_served: Option<ConnId>,
    /// Requests waiting, each counted once for every master it serves.
    queued: usize,
    /// Each master's part of `queued`: its share of the queue.
    held: HashMap<ConnId, usize>,
    /// Where the newest joinable read of each key was queued (a hint, checked).
    joinable: HashMap<ReadKey, ConnId>,
    /// Requests that act, queued so far: per unit, and to unit 0.
    epochs: HashMap<u8, u64>,
    broadcast_epoch: u64,
    /// Requests to resend (reads after a timeout or a bad reply): ahead of the queues.
    retry: VecDeque<R>,
    /// Requests that joined another so far.
    joins: u64,
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
            queues: HashMap::new(),
            ring: VecDeque::new(),
            last_served: None,
            queued: 0,
            held: HashMap::new(),
            joinable: HashMap::new(),
            epochs: HashMap::new(),
            broadcast_epoch: 0,
            retry: VecDeque::new(),
            joins: 0,
        }
    }

    /// Requests that joined an identical read so far (`Joined`, or `Displaced` with
    /// the request joined).
    pub(super) fn joins(&self) -> u64 {
        self.joins
    }

    /// Requests queued, each once for every master it serves (resends not counted).
    pub(super) fn queued(&self) -> usize {
        self.queued
    }

    /// Are requests waiting for the line (queued, or to be resent)?
    pub(super) fn has_waiting(&self) -> bool {
        !self.ring.is_empty() || !self.retry.is_empty()
    }

    /// Has `conn` a request that acts on `unit` still waiting for the line (queued, or
    /// to be resent)? Its own reads behind it must not be answered with what the
    /// device said before it acted: they neither join a read queued by another master
    /// nor take a cached reply.
    pub(super) fn acts_waiting(&self, conn: ConnId, unit: u8) -> bool {
        let acts_on = |r: &R| r.acts() && (r.unit() == unit || r.unit() == 0);
        self.queues
            .get(&conn)
            .is_some_and(|q| q.iter().any(|e| acts_on(&e.req)))
            || self
                .retry
                .iter()
                .any(|r| acts_on(r) && r.masters().any(|c| c == conn))
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
        let admitted = match self.try_join(req) {
            Ok(()) => Admitted::Joined,
            Err(req) => {
                if let (true, Some(key)) = (self.coalesce, req.read_key()) {
                    self.joinable.insert(key, conn);
                }
                let epoch = self.epoch(req.unit());
                self.enqueue(Entry { req, epoch });
                Admitted::Queued
            }
        };
        match displaced {
            Some(d) => Admitted::Displaced(d),
            None => admitted,
        }
    }

    /// The write epoch of `unit`: it moves on with every request queued that acts on it.
    fn epoch(&self, unit: u8) -> (u64, u64) {
        (
            self.broadcast_epoch,
            self.epochs.get(&unit).copied().unwrap_or(0),
        )
    }

    /// A request that acts on `unit` was queued: no read queued before it is joined
    /// by one queued after it.
    fn acted_on(&mut self, unit: u8) {
        if unit == 0 {
            self.broadcast_epoch += 1;
            self.joinable.clear();
        } else {
            *self.epochs.entry(unit).or_default() += 1;
            self.joinable.retain(|k, _| k.unit != unit);
        }
    }

    /// Joins `req` to the newest identical read queued since the last request that
    /// acted on its unit, if there is one and `req`'s master has nothing that acts on
    /// the unit waiting before it; else gives it back.
    fn try_join(&mut self, req: R) -> Result<(), R> {
        let Some(key) = req.read_key().filter(|_| self.coalesce) else {
            return Err(req);
        };
        if self.acts_waiting(req.conn(), key.unit) {
            return Err(req);
        }
        let epoch = self.epoch(key.unit);
        let host = self
            .joinable
            .get(&key)
            .and_then(|host| self.queues.get_mut(host))
            .and_then(|q| {
                q.iter_mut()
                    .rev()
                    .find(|e| e.epoch == epoch && e.req.read_key() == Some(key))
            });
        match host {
            Some(e) => {
                e.req.join(req);
                self.joins += 1;
                Ok(())
            }
            None => Err(req),
        }
    }

    /// At the back of its master's queue. Round-robin from its arrival: a master that
    /// starts waiting goes behind every connection still waiting for a turn, ahead of
    /// the one just served.
    fn enqueue(&mut self, e: Entry<R>) {
        let conn = e.req.conn();
        let q = self.queues.entry(conn).or_default();
        if q.is_empty() {
            match self.ring.back() {
                Some(&back) if Some(back) == self.last_served => {
                    self.ring.insert(self.ring.len() - 1, conn)
                }
                _ => self.ring.push_back(conn),
            }
        }
        q.push_back(e);
    }

    /// `req` waits: it counts for each master it serves.
    fn count(&mut self, req: &R) {
        for c in req.masters() {
            *self.held.entry(c).or_default() += 1;
            self.queued += 1;
        }
    }

    /// `req` waits no more.
    fn uncount(&mut self, req: &R) {
        for c in req.masters() {
            if let Some(n) = self.held.get_mut(&c) {
                *n -= 1;
                if *n == 0 {
                    self.held.remove(&c);
                }
            }
            self.queued -= 1;
        }
    }

    /// Takes out one request of `conn`, its newest, to be answered 0x06: from the
    /// newest read queued for it (a read that also answers others, or its own earlier
    /// identical reads, stays queued for them), else from a read of another's it
    /// joined.
    fn evict(&mut self, conn: ConnId) -> Option<R> {
        let own = self.queues.get_mut(&conn).and_then(|q| {
            let e = q.back_mut()?;
            match e.req.leave_one(conn) {
                // Still answering others; if `conn` was the one it was queued for,
                // it goes on queued for the first of them.
                Some(part) => Some((part, (e.req.conn() != conn).then(|| q.pop_back()))),
                None => q.pop_back().map(|e| (e.req, None)),
            }
        });
        if let Some((gone, moved)) = own {
            self.drop_if_empty(conn);
            if let Some(Some(e)) = moved {
                self.enqueue(e);
            }
            self.uncount(&gone);
            return Some(gone);
        }
        let part = self
            .queues
            .values_mut()
            .find_map(|q| q.iter_mut().rev().find_map(|e| e.req.leave_one(conn)))?;
        self.uncount(&part);
        Some(part)
    }

    fn drop_if_empty(&mut self, conn: ConnId) {
        if self.queues.get(&conn).is_some_and(VecDeque::is_empty) {
            self.queues.remove(&conn);
            self.ring.retain(|&c| c != conn);
        }
    }

    /// `req` is to be resent: ahead of every queue.
    pub(super) fn resend(&mut self, req: R) {
        self.retry.push_back(req);
    }

    /// The next request to put on the line: a resend first, then round-robin across
    /// connections.
    pub(super) fn next(&mut self) -> Option<R> {
        if let Some(req) = self.retry.pop_front() {
            return Some(req);
        }
        loop {
            let conn = self.ring.pop_front()?;
            let Some(q) = self.queues.get_mut(&conn) else {
                continue;
            };
            let Some(e) = q.pop_front() else {
                self.queues.remove(&conn);
                continue;
            };
            // Sent, it can be joined no more.
            if let Some(key) = e.req.read_key() {
                if self.joinable.get(&key) == Some(&conn)
                    && !q.iter().any(|x| x.req.read_key() == Some(key))
                {
                    self.joinable.remove(&key);
                }
            }
            if q.is_empty() {
                self.queues.remove(&conn);
            } else {
                self.ring.push_back(conn);
            }
            self.uncount(&e.req);
            self.last_served = Some(conn);
            return Some(e.req);
        }
    }

    /// The master went away: its waiting requests are dropped (their tickets with them).
    /// A read it shared with others stays for them.
    pub(super) fn detach(&mut self, conn: ConnId) {
        self.retry.retain_mut(|r| {
            if r.masters().all(|c| c == conn) {
                return false;
            }
            r.leave(conn);
            true
        });
        let mut gone = Vec::new();
        let mut rehome = Vec::new();
        if let Some(q) = self.queues.remove(&conn) {
            self.ring.retain(|&c| c != conn);
            for mut e in q {
                match e.req.leave(conn) {
                    Some(part) => {
                        gone.push(part);
                        rehome.push(e);
                    }
                    None => gone.push(e.req),
                }
            }
        }
        for q in self.queues.values_mut() {
            gone.extend(q.iter_mut().filter_map(|e| e.req.leave(conn)));
        }
        for r in &gone {
            self.uncount(r);
        }
        for e in rehome {
            self.enqueue(e);
        }
    }

    /// Takes every waiting request out: resends first, then the queues.
    pub(super) fn drain_all(&mut self) -> Vec<R> {
        self.ring.clear();
        self.queued = 0;
        self.held.clear();
        self.joinable.clear();
        let mut all: Vec<R> = std::mem::take(&mut self.retry).into();
        for (_, q) in std::mem::take(&mut self.queues) {
            all.extend(q.into_iter().map(|e| e.req));
        }
        all
    }

    /// Takes out every waiting request for `unit` (it was just backed off).
    pub(super) fn take_unit(&mut self, unit: u8) -> Vec<R> {
        let mut swept = Vec::new();
        for q in self.queues.values_mut() {
            let (gone, kept): (VecDeque<_>, VecDeque<_>) = std::mem::take(q)
                .into_iter()
                .partition(|e| e.req.unit() == unit);
            *q = kept;
            swept.extend(gone.into_iter().map(|e| e.req));
        }
        for r in &swept {
            self.uncount(r);
        }
        self.queues.retain(|_, q| !q.is_empty());
        let queues = &self.queues;
        self.ring.retain(|c| queues.contains_key(c));
        let (gone, kept) = std::mem::take(&mut self.retry)
            .into_iter()
            .partition(|r| r.unit() == unit);
        self.retry = kept;
        swept.extend::<VecDeque<R>>(gone);
        swept
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A request: each master it serves with a label, its unit, and the register it
    /// reads (`None`: it acts, like a write).
    #[derive(Debug, PartialEq, Eq)]
    struct Req {
        askers: Vec<(ConnId, &'static str)>,
        unit: u8,
        reads: Option<u16>,
    }

    /// A request that acts on `unit` (a write).
    #[allow(non_snake_case)]
    fn Req(conn: ConnId, unit: u8, label: &'static str) -> Req {
        Req {
            askers: vec![(conn, label)],
            unit,
            reads: None,
        }
    }

    /// A read of register `addr` of `unit`.
    fn read(conn: ConnId, unit: u8, addr: u16, label: &'static str) -> Req {
        Req {
            askers: vec![(conn, label)],
            unit,
            reads: Some(addr),
        }
    }

    impl Queued for Req {
        fn conn(&self) -> ConnId {
            self.askers[0].0
        }
        fn unit(&self) -> u8 {
            self.unit
        }
        fn read_key(&self) -> Option<ReadKey> {
            let [hi, lo] = self.reads?.to_be_bytes();
            Some(ReadKey {
                unit: self.unit,
                pdu: [3, hi, lo, 0, 1],
            })
        }
        fn acts(&self) -> bool {
            self.reads.is_none()
        }
        fn masters(&self) -> impl Iterator<Item = ConnId> + '_ {
            self.askers.iter().map(|a| a.0)
        }
        fn join(&mut self, other: Self) {
            self.askers.extend(other.askers);
        }
        fn leave(&mut self, conn: ConnId) -> Option<Self> {
            if self.askers.iter().all(|a| a.0 == conn) {
                return None;
            }
            let (gone, kept) = self.askers.drain(..).partition(|a| a.0 == conn);
            self.askers = kept;
            (!gone.is_empty()).then_some(Req {
                askers: gone,
                unit: self.unit,
                reads: self.reads,
            })
        }
        fn leave_one(&mut self, conn: ConnId) -> Option<Self> {
            let i = self.askers.iter().rposition(|a| a.0 == conn)?;
            (self.askers.len() > 1).then(|| Req {
                askers: vec![self.askers.remove(i)],
                unit: self.unit,
                reads: self.reads,
            })
        }
    }

    /// What goes on the line, in order: each request as the labels it answers.
    fn sent(s: &mut Scheduler<Req>) -> Vec<String> {
        std::iter::from_fn(|| s.next()).map(|r| label(&r)).collect()
    }

    fn label(r: &Req) -> String {
        let labels: Vec<&str> = r.askers.iter().map(|a| a.1).collect();
        labels.join("+")
    }

    fn labels(s: &mut Scheduler<Req>) -> Vec<String> {
        sent(s)
    }

    #[test]
    fn round_robin_and_a_newcomer_goes_ahead_of_the_master_just_served() {
        let mut s = Scheduler::new(64, true);
        s.push(Req(1, 1, "a1"));
        assert_eq!(label(&s.next().unwrap()), "a1");
        s.push(Req(1, 1, "a2"));
        s.push(Req(1, 1, "a3"));
        s.push(Req(2, 1, "b1"));
        s.push(Req(3, 1, "c1"));
        assert_eq!(labels(&mut s), ["b1", "c1", "a2", "a3"]);
        assert!(!s.has_waiting());
    }

    #[test]
    fn resends_go_first() {
        let mut s = Scheduler::new(64, true);
        s.push(Req(1, 1, "a1"));
        s.resend(Req(2, 1, "again"));
        assert_eq!(labels(&mut s), ["again", "a1"]);
    }

    #[test]
    fn a_full_queue_refuses_the_heaviest_masters_newest() {
        let mut s = Scheduler::new(3, true);
        for l in ["a1", "a2", "a3"] {
            assert_eq!(s.push(Req(1, 1, l)), Admitted::Queued);
        }
        assert_eq!(
            s.push(Req(2, 1, "b1")),
            Admitted::Displaced(Req(1, 1, "a3"))
        );
        assert_eq!(s.push(Req(2, 1, "b2")), Admitted::Refused(Req(2, 1, "b2")));
        assert_eq!(s.push(Req(1, 1, "a4")), Admitted::Refused(Req(1, 1, "a4")));
        assert_eq!(s.queued(), 3);
        assert_eq!(labels(&mut s), ["a1", "b1", "a2"]);
    }

    #[test]
    fn detach_unit_sweep_and_drain_take_requests_out() {
        let mut s = Scheduler::new(64, true);
        s.push(Req(1, 1, "a1"));
        s.push(Req(1, 5, "a5"));
        s.push(Req(2, 5, "b5"));
        s.resend(Req(3, 5, "c5"));
        s.push(Req(3, 1, "c1"));
        let swept: Vec<_> = s.take_unit(5).iter().map(label).collect();
        assert_eq!(swept.len(), 3);
        for l in ["c5", "b5", "a5"] {
            assert!(swept.iter().any(|s| s == l), "{swept:?}");
        }
        assert_eq!(s.queued(), 2);
        s.detach(3);
        assert_eq!(s.queued(), 1);
        s.resend(Req(1, 1, "r"));
        let all: Vec<_> = s.drain_all().iter().map(label).collect();
        assert_eq!(all, ["r", "a1"]);
        assert!(!s.has_waiting() && s.next().is_none());
    }

    /// An identical read joins one still queued, from any master (and the same
    /// master's second copy too); a read already sent is joined by nothing; another
    /// register, unit or `coalesce = false` never joins.
    #[test]
    fn identical_queued_reads_join_and_sent_ones_do_not() {
        let mut s = Scheduler::new(64, true);
        assert_eq!(s.push(read(1, 1, 10, "a")), Admitted::Queued);
        assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Joined);
        assert_eq!(s.push(read(3, 1, 10, "c")), Admitted::Joined);
        assert_eq!(s.push(read(3, 1, 11, "c11")), Admitted::Queued);
        assert_eq!(s.push(read(3, 2, 10, "c-unit2")), Admitted::Queued);
        assert_eq!(s.queued(), 5, "a joined read counts for its master");
        assert_eq!(s.joins(), 2);
        assert_eq!(label(&s.next().unwrap()), "a+b+c");
        // On the line now: the next identical read is a transaction of its own.
        assert_eq!(s.push(read(2, 1, 10, "b2")), Admitted::Queued);
        assert_eq!(s.push(read(2, 1, 10, "b3")), Admitted::Joined);
        assert_eq!(sent(&mut s), ["c11", "b2+b3", "c-unit2"]);
        assert_eq!(s.queued(), 0);

        let mut off = Scheduler::new(64, false);
        off.push(read(1, 1, 10, "a"));
        assert_eq!(off.push(read(2, 1, 10, "b")), Admitted::Queued);
        assert_eq!(sent(&mut off), ["a", "b"]);
    }

    /// A request that acts on the unit, from any master, queued between two identical
    /// reads keeps them apart; on another unit it does not; to unit 0 (a broadcast) it
    /// does for every unit. A master with a write of its own still waiting never joins
    /// a read queued after that write, though nothing else stops it.
    #[test]
    fn a_write_to_the_unit_in_between_ends_the_chance_to_join() {
        let mut s = Scheduler::new(64, true);
        s.push(read(1, 1, 10, "a"));
        s.push(Req(3, 1, "w"));
        assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
        assert_eq!(s.push(read(1, 1, 10, "a2")), Admitted::Joined, "joins b");
        s.push(Req(3, 7, "w-unit7"));
        assert_eq!(s.push(read(4, 1, 10, "d")), Admitted::Joined);
        s.push(Req(3, 0, "broadcast"));
        assert_eq!(s.push(read(4, 1, 10, "d2")), Admitted::Queued);
        assert_eq!(
            sent(&mut s),
            ["a", "w", "b+a2+d", "d2", "w-unit7", "broadcast"]
        );

        // Master 2 writes, then master 1 queues a read, then 2 reads the same: 1's
        // read may go before 2's write, so 2's read waits behind its write.
        let mut s = Scheduler::new(64, true);
        s.push(Req(2, 1, "w2"));
        s.push(read(1, 1, 10, "a"));
        assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
        assert_eq!(s.push(read(3, 1, 10, "c")), Admitted::Joined, "joins b");
        // A resend of 2's write waiting counts the same.
        let mut s = Scheduler::new(64, true);
        s.resend(Req(2, 1, "w2 again"));
        s.push(read(1, 1, 10, "a"));
        assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
    }

    /// A master that goes away leaves the reads it shared queued for the others, and
    /// its part of them is no longer counted; a read shared by others is never taken
    /// whole by a 0x06: the master holding the most gives up its own part of it.
    #[test]
    fn a_joined_master_leaving_or_displaced_leaves_the_others_their_read() {
        let mut s = Scheduler::new(64, true);
        s.push(read(1, 1, 10, "a"));
        s.push(read(2, 1, 10, "b"));
        s.push(read(3, 1, 10, "c"));
        s.push(read(2, 1, 20, "b20"));
        s.push(read(1, 1, 20, "a20"));
        s.resend(read(1, 1, 30, "a30 again"));
        s.detach(1);
        assert_eq!(s.queued(), 3);
        assert!(!s.acts_waiting(1, 1));
        // Its read goes on queued for the others, behind what they queued themselves.
        assert_eq!(sent(&mut s), ["b20", "b+c"]);

        // Master 1 holds the most: its newest, a read 2 joined, is taken from it; the
        // read stays queued for 2.
        let mut s = Scheduler::new(4, true);
        s.push(read(1, 1, 10, "a10"));
        s.push(read(1, 1, 11, "a11"));
        s.push(read(1, 1, 12, "a12"));
        assert_eq!(s.push(read(2, 1, 12, "b12")), Admitted::Joined);
        match s.push(read(3, 1, 99, "c")) {
            Admitted::Displaced(r) => assert_eq!(label(&r), "a12"),
            other => panic!("{other:?}"),
        }
        assert_eq!(s.queued(), 4);
        assert_eq!(sent(&mut s), ["a10", "b12", "c", "a11"]);

        // Master 2 holds the most, all of it joined to another's read: its newest
        // request is taken from it.
        let mut s = Scheduler::new(3, true);
        s.push(read(1, 1, 10, "a10"));
        s.push(read(2, 1, 10, "b10"));
        s.push(read(2, 1, 10, "b10'"));
        match s.push(read(3, 1, 99, "c")) {
            Admitted::Displaced(r) => assert_eq!(label(&r), "b10'"),
            other => panic!("{other:?}"),
        }
        assert_eq!(s.queued(), 3);
        assert_eq!(sent(&mut s), ["a10+b10", "c"]);

        // A master whose pipelined identical reads joined each other holds one read on
        // the line but a share of 4: a full queue takes one of them, not all four.
        let mut s = Scheduler::new(5, true);
        for l in ["a1", "a2", "a3", "a4"] {
            s.push(read(1, 1, 10, l));
        }
        s.push(read(2, 1, 20, "b"));
        match s.push(read(3, 1, 30, "c")) {
            Admitted::Displaced(r) => assert_eq!(label(&r), "a4"),
            other => panic!("{other:?}"),
        }
        assert_eq!(s.queued(), 5);
        assert_eq!(sent(&mut s), ["a1+a2+a3", "b", "c"]);
    }
}
