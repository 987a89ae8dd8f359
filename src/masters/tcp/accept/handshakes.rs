//! The TLS handshakes a listener lets run at once (docs/security.md "Handshakes"):
//! a budget of its own, apart from `max_connections`, per listener and per source, so
//! peers that never authenticate cannot take the slots of masters that do. When it is
//! full a new handshake is never refused: the oldest unfinished handshake of the source
//! with the most in progress gives way to it. Plain data; the accept loop drives it.

use std::collections::{BTreeMap, HashMap};
use std::net::IpAddr;

/// Handshakes in progress on one listener, oldest first.
#[derive(Debug)]
pub(crate) struct Handshakes {
    limit: usize,
    per_source: usize,
    next: u64,
    /// Each handshake in progress (by the order it began) and its source.
    open: BTreeMap<u64, IpAddr>,
    /// How many each source has in progress.
    by_source: HashMap<IpAddr, usize>,
}

impl Handshakes {
    /// The budget of a listener that takes `max_connections` masters: four times as
    /// many handshakes (at least 64), an eighth of them from one source.
    pub(crate) fn for_listener(max_connections: usize) -> Handshakes {
        let limit = max_connections.saturating_mul(4).max(64);
        Handshakes::new(limit, limit / 8)
    }

    pub(crate) fn new(limit: usize, per_source: usize) -> Handshakes {
        Handshakes {
            limit: limit.max(1),
            per_source: per_source.clamp(1, limit.max(1)),
            next: 0,
            open: BTreeMap::new(),
            by_source: HashMap::new(),
        }
    }

    /// At most this many at once on the listener.
    pub(crate) fn limit(&self) -> usize {
        self.limit
    }

    /// At most this many at once from one source.
    pub(crate) fn per_source(&self) -> usize {
        self.per_source
    }

    /// The source a budget counts: an IPv4 address (an IPv4-mapped one as the IPv4
    /// address it is), or an IPv6 /64, which one host is commonly given whole.
    pub(crate) fn source(ip: IpAddr) -> IpAddr {
        match ip.to_canonical() {
            IpAddr::V6(v6) => IpAddr::V6((u128::from(v6) & !u128::from(u64::MAX)).into()),
            v4 => v4,
        }
    }

    /// A handshake from `ip` begins: its id, and the one that must end to make room
    /// for it, if the budget was full (the oldest of the same source if that source
    /// is at its share, else the oldest of the source with the most in progress).
    pub(crate) fn begin(&mut self, ip: IpAddr) -> (u64, Option<u64>) {
        let source = Handshakes::source(ip);
        let own = self.by_source.get(&source).copied().unwrap_or(0);
        let evicted = if own >= self.per_source {
            self.oldest_of(source)
        } else if self.open.len() >= self.limit {
            let most = self.by_source.values().copied().max().unwrap_or(0);
            self.open
                .iter()
                .find(|(_, s)| self.by_source.get(s) == Some(&most))
                .map(|(&id, _)| id)
        } else {
            None
        };
        if let Some(id) = evicted {
            self.end(id);
        }
        let id = self.next;
        self.next += 1;
        self.open.insert(id, source);
        *self.by_source.entry(source).or_insert(0) += 1;
        (id, evicted)
    }

    fn oldest_of(&self, source: IpAddr) -> Option<u64> {
        self.open
            .iter()
            .find(|(_, s)| **s == source)
            .map(|(&id, _)| id)
    }

    /// Handshake `id` is over (done, failed, or made room for another); an id already
    /// ended is ignored.
    pub(crate) fn end(&mut self, id: u64) {
        let Some(source) = self.open.remove(&id) else {
            return;
        };
        if let Some(n) = self.by_source.get_mut(&source) {
            *n -= 1;
            if *n == 0 {
                self.by_source.remove(&source);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn one_source_makes_room_only_from_its_own() {
        let mut h = Handshakes::new(8, 3);
        let (master, none) = h.begin(ip("10.0.0.1"));
        assert_eq!(none, None);
        let attacker = ip("10.0.0.66");
        let mut mine = Vec::new();
        for _ in 0..3 {
            let (id, e) = h.begin(attacker);
            assert_eq!(e, None);
            mine.push(id);
        }
        for _ in 0..100 {
            let (id, e) = h.begin(attacker);
            assert_eq!(e, Some(mine.remove(0)), "its own oldest");
            mine.push(id);
        }
        assert_eq!(h.open.len(), 4);
        assert!(h.open.contains_key(&master), "the master's handshake kept");
    }

    #[test]
    fn many_sources_give_way_the_one_with_most_first_then_the_oldest() {
        let mut h = Handshakes::new(4, 2);
        let (a1, _) = h.begin(ip("10.0.0.1"));
        let (b1, _) = h.begin(ip("10.0.0.2"));
        let (b2, _) = h.begin(ip("10.0.0.2"));
        let (_c1, _) = h.begin(ip("10.0.0.3"));
        // Full: 10.0.0.2 has the most, its oldest goes.
        assert_eq!(h.begin(ip("10.0.0.4")).1, Some(b1));
        // Now each has one: the oldest of all.
        assert_eq!(h.begin(ip("10.0.0.5")).1, Some(a1));
        assert!(h.open.contains_key(&b2));
        h.end(b2);
        h.end(b2);
        assert_eq!(h.open.len(), 3);
        assert_eq!(h.begin(ip("10.0.0.6")).1, None);
    }

    #[test]
    fn an_ipv6_host_is_its_64_and_a_mapped_address_its_ipv4() {
        assert_eq!(
            Handshakes::source(ip("2001:db8:1:2:aaaa::1")),
            ip("2001:db8:1:2::")
        );
        assert_eq!(Handshakes::source(ip("::ffff:10.0.0.1")), ip("10.0.0.1"));
        let mut h = Handshakes::new(64, 2);
        h.begin(ip("2001:db8::1"));
        h.begin(ip("2001:db8::2"));
        assert!(h.begin(ip("2001:db8::3")).1.is_some());
        assert_eq!(
            Handshakes::for_listener(32).limit(),
            128,
            "four per connection"
        );
        assert_eq!(Handshakes::for_listener(32).per_source(), 16);
        assert_eq!(Handshakes::for_listener(1).limit(), 64);
    }

    #[derive(Debug, Clone)]
    enum Step {
        Begin(u8),
        End(usize),
    }

    proptest! {
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, ..Default::default() })]
        /// Whatever begins and ends: never more than the limit in progress, nor more
        /// than a source's share from one source; a new handshake is always taken;
        /// one made room for is the oldest of its source, from the source with the most
        /// in progress (or the new one's own, at its share); the counts agree.
        #[test]
        fn the_budget_holds_and_a_new_handshake_is_always_taken(
            limit in 1usize..12,
            share in 1usize..12,
            steps in prop::collection::vec(prop_oneof![
                (0u8..6).prop_map(Step::Begin),
                any::<usize>().prop_map(Step::End),
            ], 0..200),
        ) {
            let mut h = Handshakes::new(limit, share);
            let share = h.per_source();
            for s in steps {
                match s {
                    Step::Begin(n) => {
                        let from = IpAddr::from([10, 0, 0, n]);
                        let before = h.open.clone();
                        let counts = h.by_source.clone();
                        let (id, evicted) = h.begin(from);
                        prop_assert!(h.open.contains_key(&id));
                        prop_assert!(before.len() < limit && counts.get(&from).copied().unwrap_or(0) < share
                            || evicted.is_some());
                        if let Some(e) = evicted {
                            let src = before[&e];
                            let oldest = before.iter().find(|(_, s)| **s == src).map(|(&i, _)| i);
                            prop_assert_eq!(Some(e), oldest);
                            let most = counts.values().copied().max().unwrap();
                            prop_assert!(src == from || counts[&src] == most);
                        }
                    }
                    Step::End(i) => {
                        if let Some(&id) = h.open.keys().nth(i % (h.open.len() + 1)) {
                            h.end(id);
                        }
                    }
                }
                prop_assert!(h.open.len() <= limit);
                let mut counted: HashMap<IpAddr, usize> = HashMap::new();
                for s in h.open.values() {
                    *counted.entry(*s).or_insert(0) += 1;
                }
                prop_assert_eq!(&counted, &h.by_source);
                prop_assert!(counted.values().all(|&n| n <= share));
            }
        }
    }
}
