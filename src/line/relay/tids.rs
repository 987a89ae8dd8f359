//! Serial-side transaction ids (docs/design.md §1 step 3).
//!
//! Every request on the line gets a fresh id that no outstanding request uses, never
//! 0x0000 (the CIE-M10's own change notifications may use it). Ids of finished requests
//! (answered, timed out or abandoned) stay reserved for a while, so a late or duplicate
//! answer is recognised as ours and dropped (docs/design.md §1 steps 5 and 6) instead of
//! being taken for a notification.
//!
//! No two ids in flight share a low byte. A reply that lost its first byte (the id's
//! high byte) and borrowed the byte before it is a copy of that reply with another
//! high byte; with distinct low bytes that copy can never pass for the answer to
//! another request on the line.
//!
//! Ids do not count up: they follow a full-period permutation of the 16-bit space from
//! a random start. A frame that lost both bytes of its id takes the two bytes before it
//! as one, and those are often register values, which are often counters: an id that
//! counted up along with them (a notification carrying a count of changes, polled
//! once per request) would match them far more often than 1 in 65 536
//! (docs/reliability.md).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// How many finished ids are remembered at most.
pub(crate) const RETIRED_MAX: usize = 1024;
/// How long a finished id is remembered.
pub(crate) const RETIRED_FOR: Duration = Duration::from_secs(60);

#[derive(Debug)]
pub(crate) struct Tids {
    next: u16,
    /// One bit per id: in flight or retired.
    reserved: Box<[u64; 1024]>,
    /// Each retired id with the instant it is forgotten (its retirement plus
    /// [`RETIRED_FOR`]): compared with the clock, not subtracted from it.
    retired: VecDeque<(u16, Instant)>,
    /// Ids in flight by low byte.
    live_low: Box<[u8; 256]>,
}

impl Default for Tids {
    fn default() -> Self {
        Self::new()
    }
}

/// The next id after `x`: a linear congruential step modulo 2^16 with a multiplier
/// of 1 mod 4 and an odd increment, which visits every value once per 65 536 steps
/// (Hull-Dobell), so an id is always found.
fn step(x: u16) -> u16 {
    x.wrapping_mul(0x6D25).wrapping_add(0x3C6F)
}

impl Tids {
    pub(crate) fn new() -> Self {
        Self {
            next: fastrand::u16(..),
            reserved: Box::new([0; 1024]),
            retired: VecDeque::new(),
            live_low: Box::new([0; 256]),
        }
    }

    fn is_reserved(&self, tid: u16) -> bool {
        self.reserved[usize::from(tid >> 6)] & (1 << (tid & 63)) != 0
    }

    fn set(&mut self, tid: u16, on: bool) {
        let word = &mut self.reserved[usize::from(tid >> 6)];
        if on {
            *word |= 1 << (tid & 63);
        } else {
            *word &= !(1 << (tid & 63));
        }
    }

    fn expire(&mut self, now: Instant) {
        while let Some(&(tid, until)) = self.retired.front() {
            if self.retired.len() <= RETIRED_MAX && now < until {
                break;
            }
            self.retired.pop_front();
            self.set(tid, false);
        }
    }

    /// A fresh id: not in flight, not retired, no low byte shared with an id in flight,
    /// and never a low byte of 0 (so never 0x0000, the id the CIE-M10's notifications
    /// may carry, nor a shifted copy of one). At most 255 are in flight and
    /// [`RETIRED_MAX`] retired, so one is always found.
    pub(crate) fn allocate(&mut self, now: Instant) -> u16 {
        self.expire(now);
        loop {
            let tid = self.next;
            self.next = step(self.next);
            let low = tid & 0xFF;
            if low != 0 && !self.is_reserved(tid) && self.live_low[usize::from(low)] == 0 {
                self.set(tid, true);
                self.live_low[usize::from(tid & 0xFF)] += 1;
                return tid;
            }
        }
    }

    /// The request is finished (answered, timed out or abandoned): an answer with this
    /// id from now on is late or a duplicate.
    pub(crate) fn retire(&mut self, tid: u16, now: Instant) {
        let live = &mut self.live_low[usize::from(tid & 0xFF)];
        *live = live.saturating_sub(1);
        self.retired.push_back((tid, now + RETIRED_FOR));
        self.expire(now);
    }

    /// Was this id given to a request that is no longer in flight? Only meaningful for
    /// ids the caller has already found not to be in flight.
    pub(crate) fn is_retired(&self, tid: u16) -> bool {
        tid != 0 && self.is_reserved(tid)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_zero_never_reused_while_reserved() {
        let now = Instant::now();
        let mut t = Tids::new();
        let mut held = Vec::new();
        for _ in 0..70_000u32 {
            let tid = t.allocate(now);
            assert_ne!(tid & 0xFF, 0);
            held.push(tid);
            if held.len() > 200 {
                t.retire(held.remove(0), now);
            }
        }
        let mut sorted = held.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), held.len(), "in-flight ids are distinct");
        let mut lows: Vec<u16> = held.iter().map(|t| t & 0xFF).collect();
        lows.sort_unstable();
        lows.dedup();
        assert_eq!(lows.len(), held.len(), "and so are their low bytes");
    }

    #[test]
    fn the_order_visits_every_id_and_does_not_count() {
        let mut seen = vec![false; 65_536];
        let mut x = 7u16;
        for _ in 0..65_536 {
            assert!(!seen[usize::from(x)], "{x} twice in one period");
            seen[usize::from(x)] = true;
            x = step(x);
        }
        let mut t = Tids::new();
        let now = Instant::now();
        let ids: Vec<u16> = (0..100).map(|_| t.allocate(now)).collect();
        let counting = ids
            .windows(2)
            .filter(|w| w[1].wrapping_sub(w[0]) < 16)
            .count();
        assert!(counting < 5, "ids close to the one before: {ids:?}");
    }

    #[test]
    fn retired_ids_are_late_and_skipped() {
        let now = Instant::now();
        let mut t = Tids::new();
        let a = t.allocate(now);
        t.retire(a, now);
        assert!(t.is_retired(a));
        assert!(!t.is_retired(0));
        // Round the whole id space, finishing every request: `a` is skipped while it
        // is among the last RETIRED_MAX finished.
        for _ in 0..RETIRED_MAX - 1 {
            t.next = t.next.wrapping_add(63).max(1);
            let tid = t.allocate(now);
            assert_ne!(tid, a);
            t.retire(tid, now);
        }
        assert!(t.is_retired(a));
        // After RETIRED_FOR it is free again.
        let later = now + RETIRED_FOR + Duration::from_secs(1);
        t.allocate(later);
        assert!(!t.is_retired(a));
    }

    #[test]
    fn retired_set_is_bounded() {
        let now = Instant::now();
        let mut t = Tids::new();
        let first = t.allocate(now);
        t.retire(first, now);
        for _ in 0..RETIRED_MAX {
            let tid = t.allocate(now);
            t.retire(tid, now);
        }
        assert!(!t.is_retired(first), "oldest forgotten past the bound");
        assert!(t.retired.len() <= RETIRED_MAX);
    }
}
