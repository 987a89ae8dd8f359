//! What each unit of an RTU or ASCII line still owes (an answer for each of its requests
//! that timed out, which it may yet send) and how soon it can answer at all (its fastest
//! reply): plain data, the time passed in (docs/reliability.md "RTU and ASCII", 6 and 7).
//!
//! RTU and ASCII frames carry no id: a device that stalled and then answers what it
//! held sends, for the request on the line, the answers to earlier ones. A device
//! answers in order, so the rule is a count: each request of a unit that timed out is
//! owed, each frame of the unit pays the oldest owed, and a frame of a unit that owes
//! nothing is the only one that may answer the request on the line. A count can be
//! high (a request the device never read, a reply lost to noise): the unit owes
//! until it has paid, or until it has been quiet for its whole response timeout after
//! a frame. That quiet shows it held nothing more then, so what was asked before
//! that frame is forgiven, and the frame itself, if it fitted the request on the line
//! and was held (`receive.rs`), answers that request; what was asked after it (the
//! requests of a stall that began after it) stays owed until paid. A device that
//! sends what it holds no more than its response timeout apart is therefore never one
//! answer behind.

use crate::line::relay::ids::IdMap;
use std::time::Duration;
use tokio::time::Instant;

/// Replies a unit must have had taken before a frame is judged by its fastest: a
/// device's first answers can be slow (a program warming up, a cold cache), and a
/// later one sooner than half of those would be refused though genuine.
pub(super) const SETTLE: u32 = 8;

/// How much sooner than a unit's fastest turn a frame must come to be judged too
/// soon, whatever the halves say: the host's scheduling (a busy machine, tokio's
/// millisecond timer, a USB adapter's latency timer) moves when a reply is read by
/// about that much, so a smaller difference proves nothing about the device.
pub(super) const JITTER: Duration = Duration::from_millis(5);

/// What each unit of one line owes, and its pace: an [`Account`] a unit.
#[derive(Debug, Default)]
pub(super) struct Owed {
    units: IdMap<u8, Account>,
    /// How many units owe anything: none (the usual case) skips the look-up.
    owing: usize,
}

#[derive(Debug)]
struct Account {
    /// Answers owed for requests written before its last frame: forgiven once it has
    /// been quiet for `whole` after that frame.
    before: u32,
    /// Answers owed for requests written after its last frame (those of a stall that
    /// began after it): owed until paid.
    since: u32,
    /// When its last frame (check held) came.
    last: Option<Instant>,
    /// Its whole response timeout: the fixed one, or a learned one's ceiling.
    whole: Duration,
    /// Its fastest and slowest replies taken (from its request's last byte leaving to
    /// the reply's first byte), and how many were taken.
    fastest: Duration,
    slowest: Duration,
    replies: u32,
}

impl Default for Account {
    fn default() -> Self {
        Account {
            before: 0,
            since: 0,
            last: None,
            whole: Duration::ZERO,
            fastest: Duration::MAX,
            slowest: Duration::ZERO,
            replies: 0,
        }
    }
}

impl Account {
    fn owes(&self) -> bool {
        self.before > 0 || self.since > 0
    }

    /// Forgives what was asked before its last frame once it has been quiet for its
    /// whole response timeout after it.
    fn settle(&mut self, now: Instant) {
        if self.before > 0 && self.last.is_some_and(|last| now >= last + self.whole) {
            self.before = 0;
        }
    }
}

impl Owed {
    /// A request to `unit` that left at `left` got no answer in time: the unit may
    /// still send it (`whole`: the unit's whole response timeout).
    pub(super) fn unanswered(&mut self, unit: u8, left: Instant, whole: Duration, now: Instant) {
        if unit == 0 {
            return;
        }
        let u = self.units.entry(unit).or_default();
        let owed = u.owes();
        u.settle(now);
        u.whole = whole;
        if u.last.is_some_and(|last| left < last) {
            u.before = u.before.saturating_add(1);
        } else {
            u.since = u.since.saturating_add(1);
        }
        if !owed {
            self.owing += 1;
        }
    }

    /// Does `unit` owe answers at `now`?
    pub(super) fn owes(&mut self, unit: u8, now: Instant) -> bool {
        if self.owing == 0 {
            return false;
        }
        let Some(u) = self.units.get_mut(&unit) else {
            return false;
        };
        if !u.owes() {
            return false;
        }
        u.settle(now);
        if u.owes() {
            return true;
        }
        self.owing -= 1;
        false
    }

    /// `unit`'s whole response timeout, as its last request that timed out had it:
    /// the quiet after a frame that shows it holds nothing more.
    pub(super) fn whole(&self, unit: u8) -> Duration {
        self.units.get(&unit).map_or(Duration::ZERO, |u| u.whole)
    }

    /// A frame of `unit` (its check held) came `at`, and pays nothing: what the unit
    /// owes was all asked before it.
    pub(super) fn heard(&mut self, unit: u8, at: Instant) {
        let u = self.units.entry(unit).or_default();
        u.settle(at);
        u.before = u.before.saturating_add(std::mem::take(&mut u.since));
        u.last = Some(u.last.map_or(at, |last| last.max(at)));
    }

    /// A frame of `unit` came `at` that answers an earlier request, the oldest it
    /// owes: that answer is paid. Returns whether it owed one.
    pub(super) fn pay(&mut self, unit: u8, at: Instant) -> bool {
        let owed = self.owes(unit, at);
        self.heard(unit, at);
        if !owed {
            return false;
        }
        let u = self.units.entry(unit).or_default();
        u.before -= 1;
        if !u.owes() {
            self.owing -= 1;
        }
        true
    }

    /// A reply of `unit` was taken: it came `took` after its request left, its last
    /// byte at `at`. Taken, it was the last frame before a quiet that shows the unit
    /// holds nothing more: it owes nothing.
    pub(super) fn replied(&mut self, unit: u8, at: Instant, took: Duration) {
        let u = self.units.entry(unit).or_default();
        if u.owes() {
            u.before = 0;
            u.since = 0;
            self.owing -= 1;
        }
        u.fastest = u.fastest.min(took);
        u.slowest = u.slowest.max(took);
        u.replies = u.replies.saturating_add(1);
        u.last = Some(u.last.map_or(at, |last| last.max(at)));
    }

    /// Could `unit` have answered with a frame whose first byte came `took` after its
    /// request left and whose bytes took `wire` on the line? Not if its last byte came
    /// sooner than half what the unit's fastest reply would have taken with this
    /// frame's length (its fastest turn plus `wire`), once it has had [`SETTLE`]
    /// taken: such a frame was on its way before the unit could have read the request
    /// (the tail of the last transaction), and answers nothing now. The frame's own
    /// time is on both sides, so a long reply does not make a short one look too soon,
    /// and a unit that turns in a fraction of its reply's time on a wire is not judged
    /// by that fraction's jitter; where there is no wire, `wire` is zero and this is
    /// half the fastest turn. Only a unit whose turns so far stay within a factor of
    /// two is judged so: for one whose own turns spread wider (a device whose answers
    /// take 1 to 4 ms), half its fastest is inside its own range and proves nothing,
    /// and a genuine reply would be refused. Nor is a frame less than [`JITTER`]
    /// sooner than the fastest turn.
    pub(super) fn could_answer(&self, unit: u8, took: Duration, wire: Duration) -> bool {
        self.units.get(&unit).is_none_or(|u| {
            u.replies < SETTLE
                || u.slowest >= u.fastest.saturating_mul(2)
                || (took + wire) * 2 >= u.fastest.saturating_add(wire)
                || took + JITTER >= u.fastest
        })
    }

    /// What `unit` owes now (for the tests).
    #[cfg(test)]
    pub(super) fn owed(&self, unit: u8) -> u32 {
        self.units.get(&unit).map_or(0, |u| u.before + u.since)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);
    const T: Duration = Duration::from_millis(1000);

    /// A stall: three requests asked after the unit's last frame time out; its
    /// backlog pays them one by one however slowly it comes (within its response
    /// timeout of each other), and only then does it owe nothing.
    #[test]
    fn a_stalls_requests_are_owed_until_paid() {
        let t0 = Instant::now();
        let mut o = Owed::default();
        assert!(!o.pay(1, t0), "owes nothing yet");
        for i in 1..=3 {
            o.unanswered(1, t0 + i * 1100 * MS, T, t0 + (i * 1100 + 1000) * MS);
        }
        assert_eq!(o.owed(1), 3);
        // The stall outlasts any quiet: what was asked after the last frame stays.
        let resume = t0 + 60_000 * MS;
        assert!(o.owes(1, resume));
        for i in 0..3 {
            assert!(o.pay(1, resume + i * 900 * MS), "frame {i} pays");
        }
        assert!(!o.owes(1, resume + 2000 * MS));
        assert!(!o.pay(1, resume + 2000 * MS), "the next is an answer");
    }

    /// A request the device never read: its answer is owed, the next reply pays it
    /// (that request then times out too), and a quiet of the whole response timeout
    /// after that reply forgives both: the unit is not one answer behind for ever.
    #[test]
    fn a_count_too_high_is_forgiven_by_a_whole_timeouts_quiet() {
        let t0 = Instant::now();
        let mut o = Owed::default();
        o.replied(1, t0, 5 * MS);
        o.unanswered(1, t0 + 10 * MS, T, t0 + 1010 * MS);
        // The next request left at 1110 ms, its reply came 5 ms later: it pays.
        let r = t0 + 1115 * MS;
        assert!(o.pay(1, r));
        o.unanswered(1, t0 + 1110 * MS, T, t0 + 2110 * MS);
        assert!(o.owes(1, r + T - MS), "not yet quiet for the whole timeout");
        assert!(!o.owes(1, r + T), "asked before that frame: forgiven");
        assert!(!o.pay(1, r + T + 100 * MS));
    }

    /// What was asked after a frame is not forgiven by the quiet after it: a stall
    /// that began right after a reply keeps its requests owed.
    #[test]
    fn requests_asked_after_the_last_frame_are_not_forgiven() {
        let t0 = Instant::now();
        let mut o = Owed::default();
        o.replied(1, t0, 5 * MS);
        o.unanswered(1, t0 + 10 * MS, T, t0 + 1010 * MS);
        o.unanswered(1, t0 + 1110 * MS, T, t0 + 2110 * MS);
        assert!(o.owes(1, t0 + 10_000 * MS));
        assert_eq!(o.owed(1), 2);
    }

    /// The fastest reply: a frame sooner than half of it is refused once the unit has
    /// had `SETTLE` replies taken, never before; a reply taken sooner (one held for the
    /// unit's whole timeout after its request timed out) is the new fastest.
    #[test]
    fn a_frame_sooner_than_half_the_fastest_reply_could_not_answer() {
        let t0 = Instant::now();
        let mut o = Owed::default();
        assert!(
            o.could_answer(1, Duration::ZERO, Duration::ZERO),
            "nothing known"
        );
        for i in 0..SETTLE {
            assert!(
                o.could_answer(1, MS, Duration::ZERO),
                "reply {i}: not yet settled"
            );
            o.replied(1, t0, (20 + i) * MS);
        }
        assert!(!o.could_answer(1, 9 * MS, Duration::ZERO));
        assert!(o.could_answer(1, 10 * MS, Duration::ZERO));
        // On a wire the frame's own time counts on both sides: a 10 ms frame whose
        // first byte came 5 ms after the request ended 15 ms after it, half the 30 ms
        // the fastest turn would have taken with it.
        assert!(o.could_answer(1, 5 * MS, 10 * MS));
        assert!(!o.could_answer(1, 4 * MS, 10 * MS));
        assert!(
            o.could_answer(2, Duration::ZERO, Duration::ZERO),
            "another unit"
        );
        o.replied(1, t0, 4 * MS);
        assert!(o.could_answer(1, 2 * MS, Duration::ZERO));
        assert!(
            o.could_answer(1, MS, Duration::ZERO),
            "its turns now spread from 4 to 27 ms: half its fastest proves nothing"
        );
        let mut steady = Owed::default();
        for _ in 0..SETTLE {
            steady.replied(1, t0, 20 * MS);
            steady.replied(2, t0, 4 * MS);
        }
        assert!(!steady.could_answer(1, MS, Duration::ZERO));
        assert!(
            steady.could_answer(2, MS, Duration::ZERO),
            "3 ms sooner than its fastest: within the host's jitter"
        );
    }
}
