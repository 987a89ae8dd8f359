//! The opt-in reply cache of a line (`cache_ms`, 0 = off): a read is answered from the
//! last reply to the identical read while that reply is younger than `cache_ms`; a
//! request that acts on a unit (anything but a read) clears the unit's entries when it
//! comes and again when it is sent, and a reply to a read that came before either is
//! not kept. Exception replies are never kept. Plain data: the loop passes the time in.

use super::ids::{IdMap, KeyMap};
use super::scheduler::ReadKey;
use crate::frame::Adu;
use std::time::Duration;
use tokio::time::Instant;

/// The most replies kept: past it, only replies still young are kept, and a new one
/// only if there is room among them.
const MAX_ENTRIES: usize = 4096;

pub(super) struct Cache {
    /// How long a reply may answer identical reads; zero: never (off).
    ttl: Duration,
    entries: KeyMap<ReadKey, (Instant, Adu)>,
    /// Requests that acted on each unit (came or were sent), and on unit 0.
    generations: IdMap<u8, u64>,
    broadcasts: u64,
}

impl Cache {
    pub(super) fn new(ttl: Duration) -> Self {
        Self {
            ttl,
            entries: KeyMap::default(),
            generations: IdMap::default(),
            broadcasts: 0,
        }
    }

    /// The generation of `unit`'s entries now: a reply to a read that came at this
    /// stamp is kept only if it is still the stamp when the reply comes.
    pub(super) fn stamp(&self, unit: u8) -> u64 {
        self.broadcasts + self.generations.get(&unit).copied().unwrap_or(0)
    }

    /// A request that may act on `unit` came, or was sent: its entries are gone, and
    /// replies to reads that came before are not kept. Unit 0 (a broadcast on a bus):
    /// every unit's.
    pub(super) fn acted_on(&mut self, unit: u8) {
        if self.ttl.is_zero() {
            return;
        }
        if unit == 0 {
            self.broadcasts += 1;
            self.entries.clear();
        } else {
            *self.generations.entry(unit).or_default() += 1;
            self.entries.retain(|k, _| k.unit != unit);
        }
    }

    /// The reply to the read `key`, if one younger than the cache's time is kept (its
    /// transaction id is the line's: the caller gives it the master's).
    pub(super) fn get(&self, key: &ReadKey, now: Instant) -> Option<&Adu> {
        let (at, reply) = self.entries.get(key)?;
        (now.saturating_duration_since(*at) < self.ttl).then_some(reply)
    }

    /// `reply` answered the read `key` that came at `stamp`, at `now`: kept, unless
    /// the cache is off, the reply is an exception, or something acted on the unit
    /// since the read came.
    pub(super) fn put(&mut self, key: ReadKey, stamp: u64, reply: &Adu, now: Instant) {
        if self.ttl.is_zero() || reply.function() & 0x80 != 0 || stamp != self.stamp(key.unit) {
            return;
        }
        if self.entries.len() >= MAX_ENTRIES && !self.entries.contains_key(&key) {
            let ttl = self.ttl;
            self.entries
                .retain(|_, (at, _)| now.saturating_duration_since(*at) < ttl);
            if self.entries.len() >= MAX_ENTRIES {
                return;
            }
        }
        self.entries.insert(key, (now, reply.clone()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    fn key(unit: u8, addr: u8) -> ReadKey {
        ReadKey {
            unit,
            pdu: [3, 0, addr, 0, 1],
        }
    }

    fn reply(value: u8) -> Adu {
        Adu::build(9, 1, &[3, 2, 0, value])
    }

    #[test]
    fn a_reply_answers_while_younger_than_the_cache_time() {
        let t0 = Instant::now();
        let mut c = Cache::new(100 * MS);
        c.put(key(1, 10), c.stamp(1), &reply(7), t0);
        assert_eq!(c.get(&key(1, 10), t0 + 99 * MS), Some(&reply(7)));
        assert_eq!(c.get(&key(1, 10), t0 + 100 * MS), None, "not at cache_ms");
        assert_eq!(c.get(&key(1, 11), t0), None, "another register");
        assert_eq!(c.get(&key(2, 10), t0), None, "another unit");
        // Off: nothing is kept.
        let mut off = Cache::new(Duration::ZERO);
        off.put(key(1, 10), 0, &reply(7), t0);
        assert_eq!(off.get(&key(1, 10), t0), None);
    }

    #[test]
    fn exceptions_are_never_kept() {
        let t0 = Instant::now();
        let mut c = Cache::new(100 * MS);
        c.put(key(1, 10), 0, &Adu::exception(9, 1, 3, 2), t0);
        assert_eq!(c.get(&key(1, 10), t0), None);
    }

    /// A write clears its unit's replies (unit 0: every unit's), and a reply to a read
    /// that came before the write is not kept when it arrives after it.
    #[test]
    fn a_request_that_acts_clears_its_unit_and_stale_replies_are_not_kept() {
        let t0 = Instant::now();
        let mut c = Cache::new(100 * MS);
        c.put(key(1, 10), c.stamp(1), &reply(1), t0);
        c.put(key(2, 10), c.stamp(2), &reply(2), t0);
        let before = c.stamp(1);
        c.acted_on(1);
        assert_eq!(c.get(&key(1, 10), t0), None);
        assert!(c.get(&key(2, 10), t0).is_some(), "another unit's stay");
        c.put(key(1, 10), before, &reply(3), t0);
        assert_eq!(c.get(&key(1, 10), t0), None, "read before the write");
        c.put(key(1, 10), c.stamp(1), &reply(4), t0);
        assert_eq!(c.get(&key(1, 10), t0), Some(&reply(4)));
        c.acted_on(0);
        assert_eq!(
            (c.get(&key(1, 10), t0), c.get(&key(2, 10), t0)),
            (None, None)
        );
    }
}
