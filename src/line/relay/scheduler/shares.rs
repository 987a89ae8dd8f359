//! Each master's share of the queue: every waiting request counted once for each
//! master it serves, and the newest request of the master holding the most taken out
//! when the queue is full (0x06).

use super::{Queued, Scheduler};
use crate::line::relay::ConnId;

impl<R: Queued> Scheduler<R> {
    /// `req` waits: it counts for each master it serves.
    pub(super) fn count(&mut self, req: &R) {
        for c in req.masters() {
            *self.held.entry(c).or_default() += 1;
            self.queued += 1;
        }
    }

    /// `req` waits no more.
    pub(super) fn uncount(&mut self, req: &R) {
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

    /// Takes out one request of `conn`, its newest, to be answered 0x06: the last of
    /// its queue. Of a read that also answers others (or `conn`'s own earlier
    /// identical reads) only that one request is taken, and the read stays where it
    /// is for the rest.
    pub(super) fn evict(&mut self, conn: ConnId) -> Option<R> {
        let number = *self.queues.get(&conn)?.back()?;
        let e = self.waiting.get_mut(number)?;
        let gone = match e.req.leave_one(conn) {
            Some(part) => {
                if !e.req.masters().any(|c| c == conn) {
                    self.unlist(conn, number);
                }
                part
            }
            None => {
                let whole = self.remove(number)?;
                self.unlist(conn, number);
                whole
            }
        };
        self.uncount(&gone);
        Some(gone)
    }
}
