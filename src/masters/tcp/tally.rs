//! The counters of the masters' sources a reload adds and removes (dials, UDP
//! listeners): each on the metrics while it runs, taken off them once it is removed,
//! and in the gateway's totals (at the stop and on SIGUSR1) for ever, since what a
//! removed source counted did happen.

use crate::ops::metrics::{Board, ListenerMetrics};
use crate::ops::stats::Stats;
use std::sync::{Arc, Mutex};

/// The sources' counters, shared by the dials and the UDP listeners and read by the
/// totals.
pub(crate) struct SourceTally {
    board: Arc<Board>,
    state: Mutex<SourceCounts>,
}

#[derive(Default)]
struct SourceCounts {
    /// Counters this tally made, of sources running now.
    live: Vec<Arc<Stats>>,
    /// Counters of sources removed whose tasks may still add to them (a connection
    /// writing the replies it owes).
    retired: Vec<Arc<Stats>>,
    /// The sum of the removed sources' counters no task holds any more: the list
    /// of them does not grow with every reload.
    folded: Stats,
}

impl SourceTally {
    pub(crate) fn new(board: Arc<Board>) -> SourceTally {
        SourceTally {
            board,
            state: Mutex::default(),
        }
    }

    /// New counters for a source named `name` on the metrics (`dial HOST:PORT`, a UDP
    /// listener's address), in the totals from now on.
    pub(crate) fn open(&self, name: String) -> Arc<Stats> {
        let stats = Arc::<Stats>::default();
        self.board.add_listener(Arc::new(ListenerMetrics {
            name,
            stats: stats.clone(),
        }));
        self.lock().live.push(stats.clone());
        stats
    }

    /// A source removed: its counters off the metrics; those this tally made stay in
    /// the totals (those of a listener bound at start are in them already).
    pub(crate) fn close(&self, stats: &Arc<Stats>) {
        self.board.remove_listener(stats);
        let mut state = self.lock();
        if let Some(p) = state.live.iter().position(|s| Arc::ptr_eq(s, stats)) {
            let s = state.live.remove(p);
            state.retired.push(s);
        }
        state.compact();
    }

    /// Every source's counters summed, running and removed.
    pub(crate) fn total(&self) -> Stats {
        let mut state = self.lock();
        state.compact();
        let parts = state.live.iter().chain(&state.retired).map(|s| &**s);
        Stats::total(parts.chain([&state.folded]))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, SourceCounts> {
        self.state.lock().expect("not poisoned")
    }
}

impl SourceCounts {
    /// The removed sources' counters that nothing but this list holds (nothing adds
    /// to them any more) folded into one.
    fn compact(&mut self) {
        let SourceCounts {
            retired, folded, ..
        } = self;
        retired.retain(|s| {
            let held = Arc::strong_count(s) > 1;
            if !held {
                *folded = Stats::total([&*folded, &**s]);
            }
            held
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::Ordering;

    /// A source's counts stay in the totals after it is removed (and folded once
    /// nothing holds its counters), and its counters leave the metrics.
    #[test]
    fn a_removed_source_leaves_the_metrics_and_stays_in_the_totals() {
        let board = Arc::new(Board::default());
        let tally = SourceTally::new(board.clone());
        let a = tally.open("dial a:502".into());
        let b = tally.open("dial b:502".into());
        a.add(&a.requests, 3);
        b.add(&b.requests, 4);
        assert_eq!(board.listeners().len(), 2);
        let held = b.clone();
        tally.close(&b);
        drop(b);
        assert_eq!(board.listeners().len(), 1);
        assert_eq!(board.listeners()[0].name, "dial a:502");
        // Still held by its connection: it may still count.
        held.add(&held.requests, 1);
        assert_eq!(tally.total().requests.load(Ordering::Relaxed), 8);
        drop(held);
        tally.close(&a);
        drop(a);
        assert_eq!(tally.total().requests.load(Ordering::Relaxed), 8);
        let state = tally.lock();
        assert!(state.live.is_empty() && state.retired.is_empty(), "folded");
        drop(state);
        assert_eq!(tally.total().requests.load(Ordering::Relaxed), 8);
        assert!(board.listeners().is_empty());
    }
}
