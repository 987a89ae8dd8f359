//! The requests waiting for the line, by number: a deque kept in ascending order.
//!
//! Numbers are given in the order requests are queued, so a new one always goes at the
//! back, and the line nearly always takes the front: both without moving anything else
//! and, once the deque has grown to the queue's depth, without an allocation. (A
//! `BTreeMap` allocated a node for the first request into an empty map and freed it
//! when the last left, which on a line with one master polling was every
//! transaction.) A lookup is a binary search; taking out a request from the middle
//! (a master leaving, a full queue's eviction) moves the ones behind it, at most the
//! queue's depth.

use std::collections::VecDeque;

#[derive(Debug)]
pub(super) struct Waiting<E> {
    entries: VecDeque<(u64, E)>,
}

impl<E> Default for Waiting<E> {
    fn default() -> Self {
        Self {
            entries: VecDeque::new(),
        }
    }
}

impl<E> Waiting<E> {
    pub(super) fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    fn index(&self, number: u64) -> Option<usize> {
        // The front is what the line takes nearly always: looked at before searching.
        match self.entries.front() {
            Some((n, _)) if *n == number => Some(0),
            _ => self.entries.binary_search_by_key(&number, |(n, _)| *n).ok(),
        }
    }

    pub(super) fn get(&self, number: u64) -> Option<&E> {
        self.index(number).map(|i| &self.entries[i].1)
    }

    pub(super) fn get_mut(&mut self, number: u64) -> Option<&mut E> {
        self.index(number).map(|i| &mut self.entries[i].1)
    }

    /// Adds request `number`, which is higher than every number already here.
    pub(super) fn push(&mut self, number: u64, e: E) {
        debug_assert!(self.entries.back().is_none_or(|(n, _)| *n < number));
        self.entries.push_back((number, e));
    }

    pub(super) fn remove(&mut self, number: u64) -> Option<E> {
        let i = self.index(number)?;
        self.entries.remove(i).map(|(_, e)| e)
    }

    /// The lowest-numbered request.
    pub(super) fn first(&self) -> Option<(u64, &E)> {
        self.entries.front().map(|(n, e)| (*n, e))
    }

    /// Every request, lowest number first.
    pub(super) fn iter(&self) -> impl Iterator<Item = (u64, &E)> {
        self.entries.iter().map(|(n, e)| (*n, e))
    }

    /// Takes every request out, lowest number first; the deque keeps its room.
    pub(super) fn drain(&mut self) -> impl Iterator<Item = E> + '_ {
        self.entries.drain(..).map(|(_, e)| e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_and_removes_anywhere_and_keeps_the_order() {
        let mut w = Waiting::default();
        for n in [3u64, 5, 8, 13, 21] {
            w.push(n, n * 10);
        }
        assert_eq!(w.get(8), Some(&80));
        assert_eq!(w.get(4), None);
        assert_eq!(w.remove(8), Some(80));
        assert_eq!(w.remove(8), None);
        assert_eq!(w.remove(3), Some(30));
        *w.get_mut(21).unwrap() += 1;
        assert_eq!(w.first(), Some((5, &50)));
        assert_eq!(w.iter().map(|(n, _)| n).collect::<Vec<_>>(), [5, 13, 21]);
        w.push(34, 340);
        assert_eq!(w.drain().collect::<Vec<_>>(), [50, 130, 211, 340]);
        assert!(w.is_empty());
    }
}
