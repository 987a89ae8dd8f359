//! The sources a Modbus/UDP listener knows (docs/dialing.md "Modbus over UDP"): at most
//! `max_connections`; a new source that finds none free makes room by the quietest
//! source owed nothing (the least recently heard) being forgotten, or, when every one
//! of the quietest few is owed something, the quietest of all (its replies are still
//! written, by the caller), so sources gone quiet, or forged, never keep a new master
//! out. Plain data with the time passed in: when a source was heard and what it is
//! owed are the caller's to say ([`TableSource`]).

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::net::SocketAddr;
use tokio::time::Instant;

/// What the table asks of a source.
pub(crate) trait TableSource {
    /// When its last datagram was taken.
    fn heard(&self) -> Instant;
    /// Is it owed anything at `now` (a reply, or a frame it may yet send back)? A source
    /// owed something is never forgotten to make room.
    fn owed(&self, now: Instant) -> bool;
}

/// How many of the quietest sources [`SourceTable::room`] looks at for one owed nothing:
/// a burst of datagrams from new sources leaves each source owed its reply until its
/// writer runs, and a table of thousands is not searched whole for each of them.
pub(crate) const LOOK: usize = 16;

/// The sources by address, each with the generation it was added in.
pub(crate) struct SourceTable<V> {
    map: HashMap<SocketAddr, (u64, V)>,
    /// A place for each source by when it was heard, quietest first: each key is no
    /// later than its source's `heard` (moved up when found stale at the top, so the
    /// receive loop pays nothing for it a datagram), and keys of sources gone are
    /// dropped when met; the heap is made again when they outnumber the live.
    by_heard: BinaryHeap<Reverse<(Instant, u64, SocketAddr)>>,
    generation: u64,
    max: usize,
}

impl<V: TableSource> SourceTable<V> {
    pub(crate) fn new(max: usize) -> SourceTable<V> {
        SourceTable {
            map: HashMap::new(),
            by_heard: BinaryHeap::new(),
            generation: 0,
            max,
        }
    }

    pub(crate) fn get_mut(&mut self, peer: &SocketAddr) -> Option<&mut V> {
        self.map.get_mut(peer).map(|(_, v)| v)
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.map.len()
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    /// `peer` forgotten; its source.
    pub(crate) fn remove(&mut self, peer: &SocketAddr) -> Option<V> {
        let v = self.map.remove(peer).map(|(_, v)| v);
        self.tidy();
        v
    }

    /// `v` is the source at `peer`, new (the caller made [`SourceTable::room`] first).
    pub(crate) fn insert(&mut self, peer: SocketAddr, v: V) {
        self.generation += 1;
        self.by_heard
            .push(Reverse((v.heard(), self.generation, peer)));
        self.map.insert(peer, (self.generation, v));
    }

    /// Room for one more source at `now`: `None` when there is, else the source that
    /// makes it, forgotten and returned for the caller to end: the quietest owed
    /// nothing of the [`LOOK`] quietest, or the quietest if each of those is owed
    /// something.
    pub(crate) fn room(&mut self, now: Instant) -> Option<V> {
        if self.map.len() < self.max {
            return None;
        }
        let mut owed = Vec::new();
        let mut made = None;
        while let Some(Reverse((at, generation, peer))) = self.by_heard.pop() {
            let Some((g, v)) = self.map.get(&peer) else {
                continue;
            };
            if *g != generation {
                continue;
            }
            let heard = v.heard();
            if heard > at {
                // Heard since it was placed: placed again, by when.
                self.by_heard.push(Reverse((heard, generation, peer)));
                continue;
            }
            if v.owed(now) {
                owed.push(Reverse((at, generation, peer)));
                if owed.len() == LOOK {
                    break;
                }
                continue;
            }
            made = Some(peer);
            break;
        }
        // Each of the quietest owed something: the quietest of all.
        let made = made.or_else(|| owed.first().map(|Reverse((_, _, p))| *p));
        self.by_heard.extend(
            owed.into_iter()
                .filter(|Reverse((_, _, p))| Some(*p) != made),
        );
        made.and_then(|p| self.map.remove(&p)).map(|(_, v)| v)
    }

    /// The sources for which `which` holds, forgotten and returned.
    pub(crate) fn forget_where(&mut self, mut which: impl FnMut(&V) -> bool) -> Vec<V> {
        let gone: Vec<SocketAddr> = self
            .map
            .iter()
            .filter(|(_, (_, v))| which(v))
            .map(|(p, _)| *p)
            .collect();
        let out = gone
            .iter()
            .filter_map(|p| self.map.remove(p).map(|(_, v)| v))
            .collect();
        self.tidy();
        out
    }

    /// Every source, forgotten and returned.
    pub(crate) fn drain(&mut self) -> Vec<V> {
        self.by_heard.clear();
        self.map.drain().map(|(_, (_, v))| v).collect()
    }

    /// The heap made again from the live sources once places of sources gone
    /// outnumber them, so it never grows past twice the table.
    fn tidy(&mut self) {
        if self.by_heard.len() > 2 * self.map.len() + 16 {
            self.by_heard = self
                .map
                .iter()
                .map(|(p, (g, v))| Reverse((v.heard(), *g, *p)))
                .collect();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::time::Duration;

    #[derive(Debug, Clone)]
    struct Fake {
        heard: Instant,
        owed: bool,
        id: usize,
    }

    impl TableSource for Fake {
        fn heard(&self) -> Instant {
            self.heard
        }
        fn owed(&self, _: Instant) -> bool {
            self.owed
        }
    }

    fn addr(i: usize) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 1000 + i as u16))
    }

    /// What the table does to its sources.
    #[derive(Debug, Clone)]
    enum Op {
        /// A datagram from source `i`, new or known.
        Datagram(usize),
        /// Source `i` is owed (or no longer owed) a reply.
        Owed(usize, bool),
        /// The idle sweep forgets source `i`.
        Forget(usize),
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            4 => (0..60usize).prop_map(Op::Datagram),
            3 => (0..60usize, any::<bool>()).prop_map(|(i, o)| Op::Owed(i, o)),
            1 => (0..60usize).prop_map(Op::Forget),
        ]
    }

    proptest::proptest! {
        /// Against a list of the sources: a new source is never refused; the one
        /// forgotten for it is the least recently heard of those owed nothing when
        /// one is among the `LOOK` quietest, else the quietest; the table never
        /// holds more than its room.
        #[test]
        fn the_quietest_source_owed_nothing_makes_room(max in 1..40usize, ops in proptest::collection::vec(op(), 1..400)) {
            let t0 = Instant::now();
            let mut t = SourceTable::<Fake>::new(max);
            let mut model: Vec<Fake> = Vec::new();
            for (step, o) in ops.into_iter().enumerate() {
                let now = t0 + Duration::from_millis(step as u64);
                match o {
                    Op::Datagram(i) => {
                        if let Some(v) = t.get_mut(&addr(i)) {
                            v.heard = now;
                            model.iter_mut().find(|m| m.id == i).unwrap().heard = now;
                            continue;
                        }
                        let mut by_heard = model.clone();
                        by_heard.sort_by_key(|m| m.heard);
                        let quietest = by_heard
                            .iter()
                            .take(LOOK)
                            .find(|m| !m.owed)
                            .or(by_heard.first())
                            .map(|m| m.id);
                        match t.room(now) {
                            None => prop_assert!(model.len() < max),
                            Some(v) => {
                                prop_assert_eq!(model.len(), max);
                                prop_assert_eq!(Some(v.id), quietest);
                                model.retain(|m| m.id != v.id);
                            }
                        }
                        let f = Fake { heard: now, owed: false, id: i };
                        t.insert(addr(i), f.clone());
                        model.push(f);
                    }
                    Op::Owed(i, owed) => {
                        if let Some(v) = t.get_mut(&addr(i)) {
                            v.owed = owed;
                            model.iter_mut().find(|m| m.id == i).unwrap().owed = owed;
                        }
                    }
                    Op::Forget(i) => {
                        let gone = t.forget_where(|v| v.id == i);
                        prop_assert_eq!(gone.len(), usize::from(model.iter().any(|m| m.id == i)));
                        model.retain(|m| m.id != i);
                    }
                }
                prop_assert_eq!(t.len(), model.len());
                prop_assert!(t.len() <= max);
                prop_assert!(t.by_heard.len() <= 2 * t.len() + 16 + 1);
            }
        }
    }

    /// A client that opens a new socket for each request is answered for ever: each
    /// new source takes the place of the quietest.
    #[test]
    fn a_new_socket_each_request_always_finds_room() {
        let t0 = Instant::now();
        let mut t = SourceTable::<Fake>::new(4);
        for i in 0..1000 {
            let now = t0 + Duration::from_millis(i as u64);
            match t.room(now) {
                None => assert!(i < 4),
                Some(v) => assert_eq!(v.id, i - 4, "the quietest"),
            }
            t.insert(
                addr(i),
                Fake {
                    heard: now,
                    owed: false,
                    id: i,
                },
            );
        }
        assert_eq!(t.len(), 4);
    }
}
