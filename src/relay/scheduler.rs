//! Which request goes on the line next: the per-master queues, round-robin between
//! masters, the queue's depth and each master's share of it, and resends ahead of all.
//! Plain data: no I/O, no clock; the relay's loop asks and acts.

use super::ConnId;
use std::collections::{HashMap, VecDeque};

/// What the scheduler needs to know of a request.
pub(super) trait Queued {
    /// The master that sent it.
    fn conn(&self) -> ConnId;
    /// The unit it is for.
    fn unit(&self) -> u8;
}

/// The queues of requests waiting for the line.
#[derive(Debug)]
pub(super) struct Scheduler<R> {
    depth: usize,
    queues: HashMap<ConnId, VecDeque<R>>,
    /// Connections with queued requests, in round-robin order.
    ring: VecDeque<ConnId>,
    /// The connection whose request went on the line last: a connection that starts
    /// waiting goes ahead of it, since it has just had its turn.
    last_served: Option<ConnId>,
    queued: usize,
    /// Requests to resend (reads after a timeout or a bad reply): ahead of the queues.
    retry: VecDeque<R>,
}

/// What became of a request offered to a full queue.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Admitted<R> {
    /// Queued.
    Queued,
    /// Queued, in place of this one: the newest request of the master holding the most
    /// of the queue, to be answered 0x06.
    Displaced(R),
    /// The queue is full and the master holds as much of it as any: its own request is
    /// given back, to be answered 0x06.
    Refused(R),
}

impl<R: Queued> Scheduler<R> {
    /// Queues that hold `depth` requests in all.
    pub(super) fn new(depth: usize) -> Self {
        Self {
            depth,
            queues: HashMap::new(),
            ring: VecDeque::new(),
            last_served: None,
            queued: 0,
            retry: VecDeque::new(),
        }
    }

    /// Requests queued (resends not counted).
    pub(super) fn queued(&self) -> usize {
        self.queued
    }

    /// Are requests waiting for the line (queued, or to be resent)?
    pub(super) fn has_waiting(&self) -> bool {
        !self.ring.is_empty() || !self.retry.is_empty()
    }

    /// Queues `req` behind its master's earlier ones. When the queue is full the 0x06
    /// falls on the master holding the most of it: if one holds at least two more
    /// waiting requests than this one's master, its newest makes room; else this
    /// master holds as many as any, and its own request is refused. So a master can
    /// always have its share of the queue waiting (the depth divided by the masters
    /// that want it), however fast the others resend.
    pub(super) fn push(&mut self, req: R) -> Admitted<R> {
        let conn = req.conn();
        let mut displaced = None;
        if self.queued >= self.depth {
            let mine = self.queues.get(&conn).map_or(0, VecDeque::len);
            let heaviest = self.queues.iter_mut().max_by_key(|(_, q)| q.len());
            match heaviest {
                Some((_, q)) if q.len() >= mine + 2 => {
                    // Its newest: the one it sent last, and the last it would be served.
                    displaced = q.pop_back();
                    self.queued -= 1;
                }
                _ => return Admitted::Refused(req),
            }
        }
        let q = self.queues.entry(conn).or_default();
        if q.is_empty() {
            // Round-robin from its arrival: behind every connection still waiting for
            // a turn, ahead of the one just served.
            match self.ring.back() {
                Some(&back) if Some(back) == self.last_served => {
                    self.ring.insert(self.ring.len() - 1, conn)
                }
                _ => self.ring.push_back(conn),
            }
        }
        q.push_back(req);
        self.queued += 1;
        match displaced {
            Some(d) => Admitted::Displaced(d),
            None => Admitted::Queued,
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
            let Some(req) = q.pop_front() else {
                continue;
            };
            if q.is_empty() {
                self.queues.remove(&conn);
            } else {
                self.ring.push_back(conn);
            }
            self.queued -= 1;
            self.last_served = Some(conn);
            return Some(req);
        }
    }

    /// The master went away: its waiting requests are dropped (their tickets with them).
    pub(super) fn detach(&mut self, conn: ConnId) {
        self.retry.retain(|r| r.conn() != conn);
        if let Some(q) = self.queues.remove(&conn) {
            self.queued -= q.len();
            self.ring.retain(|&c| c != conn);
        }
    }

    /// Takes every waiting request out: resends first, then the queues.
    pub(super) fn drain_all(&mut self) -> Vec<R> {
        self.ring.clear();
        self.queued = 0;
        let mut all: Vec<R> = std::mem::take(&mut self.retry).into();
        for (_, q) in std::mem::take(&mut self.queues) {
            all.extend(q);
        }
        all
    }

    /// Takes out every waiting request for `unit` (it was just backed off).
    pub(super) fn take_unit(&mut self, unit: u8) -> Vec<R> {
        let mut swept = Vec::new();
        for q in self.queues.values_mut() {
            let (gone, kept): (VecDeque<R>, VecDeque<R>) = std::mem::take(q)
                .into_iter()
                .partition(|r| r.unit() == unit);
            *q = kept;
            swept.extend(gone);
        }
        self.queued -= swept.len();
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

    /// A request: (master, unit, label).
    #[derive(Debug, PartialEq, Eq)]
    struct Req(ConnId, u8, &'static str);

    impl Queued for Req {
        fn conn(&self) -> ConnId {
            self.0
        }
        fn unit(&self) -> u8 {
            self.1
        }
    }

    fn labels(s: &mut Scheduler<Req>) -> Vec<&'static str> {
        std::iter::from_fn(|| s.next()).map(|r| r.2).collect()
    }

    #[test]
    fn round_robin_and_a_newcomer_goes_ahead_of_the_master_just_served() {
        let mut s = Scheduler::new(64);
        s.push(Req(1, 1, "a1"));
        assert_eq!(s.next().unwrap().2, "a1");
        s.push(Req(1, 1, "a2"));
        s.push(Req(1, 1, "a3"));
        s.push(Req(2, 1, "b1"));
        s.push(Req(3, 1, "c1"));
        assert_eq!(labels(&mut s), ["b1", "c1", "a2", "a3"]);
        assert!(!s.has_waiting());
    }

    #[test]
    fn resends_go_first() {
        let mut s = Scheduler::new(64);
        s.push(Req(1, 1, "a1"));
        s.resend(Req(2, 1, "again"));
        assert_eq!(labels(&mut s), ["again", "a1"]);
    }

    #[test]
    fn a_full_queue_refuses_the_heaviest_masters_newest() {
        let mut s = Scheduler::new(3);
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
        let mut s = Scheduler::new(64);
        s.push(Req(1, 1, "a1"));
        s.push(Req(1, 5, "a5"));
        s.push(Req(2, 5, "b5"));
        s.resend(Req(3, 5, "c5"));
        s.push(Req(3, 1, "c1"));
        let swept: Vec<_> = s.take_unit(5).into_iter().map(|r| r.2).collect();
        assert_eq!(swept.len(), 3);
        assert!(swept.contains(&"c5") && swept.contains(&"b5") && swept.contains(&"a5"));
        assert_eq!(s.queued(), 2);
        s.detach(3);
        assert_eq!(s.queued(), 1);
        s.resend(Req(1, 1, "r"));
        let all: Vec<_> = s.drain_all().into_iter().map(|r| r.2).collect();
        assert_eq!(all, ["r", "a1"]);
        assert!(!s.has_waiting() && s.next().is_none());
    }
}
