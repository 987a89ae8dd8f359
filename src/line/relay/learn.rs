//! The response timeout of one unit learned from its replies (`response_timeout_ms =
//! "auto"`, docs/reliability.md "Learned timeouts"). Plain data: the response times
//! are passed in, nothing here reads a clock.
//!
//! The rules, each held by a property test below:
//! - the timeout is always within `[floor, ceiling]`;
//! - it starts at the ceiling, and stays there until [`SETTLE_AFTER`] replies have
//!   been seen (since the start, or since the last timeout);
//! - once settled it is the 99th percentile of the last [`WINDOW`] response times
//!   times [`MARGIN`], so no more than 1 % of those replies would have been too late;
//! - a timeout gives the unit the ceiling back at once and forgets what was learned:
//!   a unit that went slower is waited for as long as it may take, never timed out
//!   again and again on a timeout learned while it was fast.

use std::collections::VecDeque;
use std::time::Duration;

/// How many of the latest response times the timeout is learned from.
pub(crate) const WINDOW: usize = 100;
/// Replies needed before the timeout leaves the ceiling.
pub(crate) const SETTLE_AFTER: usize = 20;
/// The timeout is the 99th percentile of the response times times this.
pub(crate) const MARGIN: u32 = 2;

/// Why the timeout is what it is (the `why` label of /metrics, the status page,
/// `mbgate status`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum TimeoutReason {
    /// At the ceiling: too few replies yet to learn from.
    Start,
    /// At the ceiling: a request timed out, and learning starts over.
    TimedOut,
    /// The 99th percentile of the last replies times the margin.
    Learned,
    /// That would be below the floor: at the floor.
    Floor,
    /// That would be above the ceiling: at the ceiling.
    Ceiling,
}

impl TimeoutReason {
    /// Every value, in the order of `crate::ops::metrics::LEARNED_WHY`.
    pub(crate) const ALL: [TimeoutReason; 5] = [
        TimeoutReason::Start,
        TimeoutReason::TimedOut,
        TimeoutReason::Learned,
        TimeoutReason::Floor,
        TimeoutReason::Ceiling,
    ];
}

/// One unit's learned timeout.
#[derive(Debug, Clone)]
pub(crate) struct Learned {
    floor: Duration,
    ceiling: Duration,
    /// The latest response times, oldest first; at most [`WINDOW`].
    samples: VecDeque<Duration>,
    current: Duration,
    why: TimeoutReason,
}

impl Learned {
    /// A unit not heard yet: at the ceiling. A floor above the ceiling is the ceiling.
    pub(crate) fn new(floor: Duration, ceiling: Duration) -> Self {
        Self {
            floor: floor.min(ceiling),
            ceiling,
            samples: VecDeque::with_capacity(WINDOW),
            current: ceiling,
            why: TimeoutReason::Start,
        }
    }

    /// The response timeout for the unit's next request.
    pub(crate) fn timeout(&self) -> Duration {
        self.current
    }

    /// Why it is what it is.
    pub(crate) fn why(&self) -> TimeoutReason {
        self.why
    }

    /// The bounds, as configured.
    pub(crate) fn bounds(&self) -> (Duration, Duration) {
        (self.floor, self.ceiling)
    }

    /// The unit replied `took` after its request left.
    pub(crate) fn replied(&mut self, took: Duration) {
        if self.samples.len() == WINDOW {
            self.samples.pop_front();
        }
        self.samples.push_back(took);
        if self.samples.len() < SETTLE_AFTER {
            return;
        }
        let wanted = p99(&self.samples).saturating_mul(MARGIN);
        (self.current, self.why) = if wanted < self.floor {
            (self.floor, TimeoutReason::Floor)
        } else if wanted > self.ceiling {
            (self.ceiling, TimeoutReason::Ceiling)
        } else {
            (wanted, TimeoutReason::Learned)
        };
    }

    /// A request to the unit timed out: the ceiling back, and learning starts over.
    pub(crate) fn timed_out(&mut self) {
        self.samples.clear();
        self.current = self.ceiling;
        self.why = TimeoutReason::TimedOut;
    }
}

/// The 99th percentile (nearest rank) of `samples`, not empty.
fn p99(samples: &VecDeque<Duration>) -> Duration {
    let mut sorted: Vec<Duration> = samples.iter().copied().collect();
    let rank = (sorted.len() * 99).div_ceil(100).max(1);
    let (_, nth, _) = sorted.select_nth_unstable(rank - 1);
    *nth
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn a_fast_unit_settles_low_and_a_timeout_gives_the_ceiling_back() {
        let mut l = Learned::new(10 * MS, 1000 * MS);
        assert_eq!((l.timeout(), l.why()), (1000 * MS, TimeoutReason::Start));
        for _ in 0..SETTLE_AFTER - 1 {
            l.replied(20 * MS);
        }
        assert_eq!(l.timeout(), 1000 * MS, "not settled before enough replies");
        l.replied(20 * MS);
        assert_eq!((l.timeout(), l.why()), (40 * MS, TimeoutReason::Learned));
        l.timed_out();
        assert_eq!((l.timeout(), l.why()), (1000 * MS, TimeoutReason::TimedOut));
        for _ in 0..SETTLE_AFTER {
            l.replied(2 * MS);
        }
        assert_eq!((l.timeout(), l.why()), (10 * MS, TimeoutReason::Floor));
        for _ in 0..WINDOW {
            l.replied(700 * MS);
        }
        assert_eq!((l.timeout(), l.why()), (1000 * MS, TimeoutReason::Ceiling));
    }

    /// What happens to a unit: a reply after this long, or a timeout.
    #[derive(Debug, Clone)]
    enum Event {
        Reply(u64),
        Timeout,
    }

    fn events() -> impl Strategy<Value = Vec<Event>> {
        let one = prop_oneof![
            20 => (0u64..3000).prop_map(Event::Reply),
            1 => Just(Event::Timeout),
        ];
        proptest::collection::vec(one, 0..400)
    }

    proptest! {
        /// Whatever the replies and timeouts: the timeout is within [floor, ceiling];
        /// it starts at the ceiling; after a timeout it is the ceiling until
        /// SETTLE_AFTER replies have come; and when below the ceiling, at most 1 % of
        /// the last WINDOW replies (those since the last timeout) took longer.
        #[test]
        fn within_bounds_starting_high_given_time_back_after_a_timeout(
            floor in 1u64..200,
            ceiling in 1u64..2000,
            events in events(),
        ) {
            let (floor, ceiling) = (Duration::from_millis(floor), Duration::from_millis(ceiling));
            let mut l = Learned::new(floor, ceiling);
            prop_assert_eq!(l.timeout(), ceiling);
            let mut since: Vec<Duration> = Vec::new();
            for e in events {
                match e {
                    Event::Reply(ms) => {
                        let ms = Duration::from_millis(ms);
                        l.replied(ms);
                        since.push(ms);
                    }
                    Event::Timeout => {
                        l.timed_out();
                        since.clear();
                        prop_assert_eq!(l.timeout(), ceiling, "time back at once");
                    }
                }
                let t = l.timeout();
                prop_assert!(t >= floor.min(ceiling) && t <= ceiling, "{t:?} out of bounds");
                if since.len() < SETTLE_AFTER {
                    prop_assert_eq!(t, ceiling, "settled after {} replies", since.len());
                }
                if t < ceiling {
                    let window = &since[since.len().saturating_sub(WINDOW)..];
                    let late = window.iter().filter(|&&s| s > t).count();
                    prop_assert!(late * 100 <= window.len(), "{late} of {} late", window.len());
                }
            }
        }
    }
}
