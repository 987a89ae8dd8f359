//! Coalescing: an identical read joins one still waiting for the line, only while no
//! request that acts on its unit was queued since (the unit's write epoch) and never
//! ahead of anything its master already waits for (the scheduler's notes).

use super::{Queued, Scheduler};
use crate::line::relay::ConnId;

impl<R: Queued> Scheduler<R> {
    /// Requests that joined an identical read so far (`Joined`, or `Displaced` with
    /// the request joined).
    pub(in crate::line::relay) fn joins(&self) -> u64 {
        self.joins
    }

    /// Has `conn` a request that acts on `unit` still waiting for the line (queued, or
    /// to be resent)? Its own reads behind it must not be answered with what the
    /// device said before it acted: they neither join a read queued by another master
    /// nor take a cached reply.
    pub(in crate::line::relay) fn acts_waiting(&self, conn: ConnId, unit: u8) -> bool {
        let acts_on = |r: &R| r.acts() && (r.unit() == unit || r.unit() == 0);
        let mine = |r: &R| acts_on(r) && r.masters().any(|c| c == conn);
        self.lone.as_ref().is_some_and(mine)
            || self.queues.get(&conn).is_some_and(|q| {
                q.iter()
                    .any(|&n| self.waiting.get(n).is_some_and(|e| acts_on(&e.req)))
            })
            || self.retry.iter().any(mine)
    }

    /// The write epoch of `unit`: it moves on with every request queued that acts on it.
    pub(super) fn epoch(&self, unit: u8) -> (u64, u64) {
        (
            self.broadcast_epoch,
            self.epochs.get(&unit).copied().unwrap_or(0),
        )
    }

    /// A request that acts on `unit` was queued: no read queued before it is joined
    /// by one queued after it.
    pub(super) fn acted_on(&mut self, unit: u8) {
        if unit == 0 {
            self.broadcast_epoch += 1;
            self.joinable.clear();
        } else {
            *self.epochs.entry(unit).or_default() += 1;
            self.joinable.retain(|k, _| k.unit != unit);
        }
    }

    /// Joins `req` to the newest identical read queued since the last request that
    /// acted on its unit, if there is one, `req`'s master has nothing that acts on the
    /// unit waiting before it, and that read is not ahead of anything the master
    /// already waits for (its order); else gives it back.
    pub(super) fn try_join(&mut self, req: R) -> Result<(), R> {
        let Some(key) = req.read_key().filter(|_| self.coalesce) else {
            return Err(req);
        };
        let conn = req.conn();
        if self.acts_waiting(conn, key.unit) {
            return Err(req);
        }
        let Some(&number) = self.joinable.get(&key) else {
            return Err(req);
        };
        let last = self.queues.get(&conn).and_then(|q| q.back().copied());
        if last.is_some_and(|last| last > number) {
            return Err(req);
        }
        let epoch = self.epoch(key.unit);
        match self.waiting.get_mut(number) {
            Some(e) if e.epoch == epoch && e.req.read_key() == Some(key) => {
                e.req.join(req);
                self.joins += 1;
                if last != Some(number) {
                    self.enlist(conn, number);
                }
                Ok(())
            }
            _ => Err(req),
        }
    }
}
