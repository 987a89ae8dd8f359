//! The in-flight table: the requests on the line with their serial-side ids, deadlines
//! and response timeouts (each unit's own, fixed or learned: `[[line.unit]]`); what a
//! request that got no usable reply becomes (resent, answered 0x0B, or its unit backed
//! off); per-unit backoff; and the pacing of the 0x0B answers for backed-off units.
//! Plain data: no I/O, no clock (the loop passes the time in).

use super::ids::IdMap;
use super::learn::Learned;
use crate::config::unit::{Timeout, UnitPolicy, UnitTables};
use crate::config::RelayConfig;
use crate::frame::Adu;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;

/// What the table needs to know of a request.
pub(super) trait Asked {
    /// The request as the master sent it.
    fn adu(&self) -> &Adu;
    /// How many times it has been resent.
    fn attempts(&self) -> u32;
}

/// A request on the line.
pub(super) struct OnLine<R> {
    /// Its serial-side id (MBAP) or key (RTU/ASCII).
    pub(super) tid: u16,
    pub(super) deadline: Instant,
    /// Its response timeout: `probe_timeout_ms` for a probe of a backed-off unit.
    pub(super) timeout: Duration,
    pub(super) req: R,
}

/// Why a request on the line failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Failure {
    /// No reply in time.
    Timeout,
    /// A reply whose CRC or LRC failed (RTU/ASCII), or that carried its id and unit
    /// (MBAP) or key but did not fit it.
    Corrupt,
}

impl Failure {
    /// What went wrong with one attempt.
    pub(super) fn what(self) -> &'static str {
        match self {
            Failure::Timeout => "no reply",
            Failure::Corrupt => "a bad reply",
        }
    }

    /// What went wrong, when no attempt is left.
    pub(super) fn what_in_the_end(self) -> &'static str {
        match self {
            Failure::Timeout => "no reply in time",
            Failure::Corrupt => "no good reply",
        }
    }
}

/// What becomes of a request that failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Verdict {
    /// Its unit is now backed off for this long: 0x0B, and the unit's waiting requests
    /// with it.
    BackedOff(Duration),
    /// Resent (reads, or any request with `retry_writes`, up to `retries` times).
    Resend,
    /// Answered 0x0B.
    Fail,
}

/// The requests on the line, and the policy for those that fail.
pub(super) struct InFlight<R> {
    entries: Vec<OnLine<R>>,
    probe_timeout: Duration,
    /// Each unit's timeout, retries and pause, by unit id: its `[[line.unit]]`
    /// table's, else the line's.
    policies: Box<[UnitPolicy]>,
    /// The learned timeouts of the units that have one, once they had a request.
    learned: IdMap<u8, Learned>,
    units: UnitHealth,
}

impl<R: Asked> InFlight<R> {
    /// `unit_backoff`: whether units are backed off at all (a bus of units only).
    pub(super) fn new(cfg: &RelayConfig, tables: &UnitTables, unit_backoff: bool) -> Self {
        let mut t = Self {
            entries: Vec::new(),
            probe_timeout: Duration::ZERO,
            policies: Box::default(),
            learned: IdMap::default(),
            units: UnitHealth::new(cfg, unit_backoff),
        };
        t.retune(cfg, tables);
        t
    }

    /// New timeouts and retries (a reload), for the requests sent from now on. A
    /// learned timeout whose bounds changed, or that is learned no more, starts over.
    pub(super) fn retune(&mut self, cfg: &RelayConfig, tables: &UnitTables) {
        self.probe_timeout = Duration::from_millis(cfg.probe_timeout_ms);
        self.policies = (0..=255u8).map(|u| tables.policy(cfg, u)).collect();
        let policies = &self.policies;
        self.learned
            .retain(|&u, l| match policies[usize::from(u)].timeout {
                Timeout::Learned { floor, ceiling } => l.bounds() == (floor, ceiling),
                Timeout::Fixed(_) => false,
            });
    }

    /// `unit`'s settings.
    pub(super) fn policy(&self, unit: u8) -> &UnitPolicy {
        &self.policies[usize::from(unit)]
    }

    /// `unit`'s learned timeout, if it has one (for the metrics).
    pub(super) fn learned(&self, unit: u8) -> Option<&Learned> {
        self.learned.get(&unit)
    }

    /// How long the line stays quiet after `f` timed out, beyond the guard: with a
    /// learned timeout, until its ceiling has passed since `f` left. A reply later
    /// than that would be late with a fixed timeout at the ceiling too, so a learned
    /// timeout lets no late reply through that the ceiling would not
    /// (docs/reliability.md "Learned timeouts").
    pub(super) fn hold_after_timeout(&self, f: &OnLine<R>) -> Duration {
        match self.policy(f.req.adu().unit()).timeout {
            Timeout::Learned { ceiling, .. } => ceiling.saturating_sub(f.timeout),
            Timeout::Fixed(_) => Duration::ZERO,
        }
    }

    /// `unit`'s whole response timeout: the fixed one, or a learned one's ceiling
    /// (the longest its replies may take).
    pub(super) fn whole_timeout(&self, unit: u8) -> Duration {
        match self.policy(unit).timeout {
            Timeout::Fixed(t) => t,
            Timeout::Learned { ceiling, .. } => ceiling,
        }
    }

    /// `unit`'s response timeout now: fixed, or as learned so far.
    fn response_timeout(&mut self, unit: u8) -> Duration {
        match self.policies[usize::from(unit)].timeout {
            Timeout::Fixed(t) => t,
            Timeout::Learned { floor, ceiling } => self
                .learned
                .entry(unit)
                .or_insert_with(|| Learned::new(floor, ceiling))
                .timeout(),
        }
    }

    pub(super) fn len(&self) -> usize {
        self.entries.len()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub(super) fn entries(&self) -> &[OnLine<R>] {
        &self.entries
    }

    /// Request `req` goes on the line as `tid` at `now`, behind bytes that take
    /// `queued` to leave: its response time counts from when it has left (RTU/ASCII:
    /// restarted when the port has drained). A unit that stopped answering gets a
    /// shorter wait, so a probe holds the line from the healthy units less long.
    pub(super) fn start(&mut self, tid: u16, req: R, now: Instant, queued: Duration) {
        let mut timeout = self.response_timeout(req.adu().unit());
        if self.units.probing(req.adu().unit()) {
            timeout = timeout.min(self.probe_timeout);
        }
        self.entries.push(OnLine {
            tid,
            deadline: now + queued + timeout,
            timeout,
            req,
        });
    }

    /// The nearest deadline, if anything is in flight.
    pub(super) fn next_deadline(&self) -> Option<Instant> {
        self.entries.iter().map(|f| f.deadline).min()
    }

    /// Everything written left the port at `left`: every timer starts from there.
    pub(super) fn restart(&mut self, left: Instant) {
        for f in &mut self.entries {
            f.deadline = left + f.timeout;
        }
    }

    /// Request `tid` got its reply in time, held until `until` (RTU/ASCII: the quiet
    /// after it confirms it): it stays on the line until then. Its response time
    /// stretches with its deadline, so the instant it left (the deadline less the
    /// response time) stays what it was.
    pub(super) fn hold_until(&mut self, tid: u16, until: Instant) {
        if let Some(f) = self.entries.iter_mut().find(|f| f.tid == tid) {
            if until > f.deadline {
                f.timeout += until - f.deadline;
                f.deadline = until;
            }
        }
    }

    /// `unit` was heard (RTU/ASCII: a frame that paid an answer it owed): it is
    /// alive, and no longer counted as not answering.
    pub(super) fn heard(&mut self, unit: u8) {
        self.units.answered(unit);
    }

    /// Takes request `tid` off the line (its reply failed), if it is on it.
    pub(super) fn take(&mut self, tid: u16) -> Option<OnLine<R>> {
        let i = self.entries.iter().position(|f| f.tid == tid)?;
        Some(self.entries.swap_remove(i))
    }

    /// Request `tid` was answered by a reply whose last byte came `at`: taken off the
    /// line, and its unit is healthy again; a learned timeout learns how long it took.
    pub(super) fn answered(&mut self, tid: u16, at: Instant) -> Option<OnLine<R>> {
        let f = self.take(tid)?;
        let unit = f.req.adu().unit();
        self.units.answered(unit);
        if let Some(l) = self.learned.get_mut(&unit) {
            // Its deadline is its timeout after it left.
            let left = f.deadline.checked_sub(f.timeout).unwrap_or(at);
            l.replied(at.saturating_duration_since(left));
        }
        Some(f)
    }

    /// Takes everything off the line (the port was lost).
    pub(super) fn take_all(&mut self) -> Vec<OnLine<R>> {
        std::mem::take(&mut self.entries)
    }

    /// Takes off the line every request whose deadline has passed at `now`.
    pub(super) fn take_expired(&mut self, now: Instant) -> Vec<OnLine<R>> {
        let mut expired = Vec::new();
        let mut i = 0;
        while i < self.entries.len() {
            if self.entries[i].deadline > now {
                i += 1;
            } else {
                expired.push(self.entries.swap_remove(i));
            }
        }
        expired
    }

    /// Is `unit` backed off at `now`? Its requests are answered 0x0B, paced.
    pub(super) fn backed_off(&self, unit: u8, now: Instant) -> bool {
        self.units.backed_off(unit, now)
    }

    /// What becomes of `f`, taken off the line for `why` at `now`. A timeout counts
    /// against its unit (a unit that keeps timing out is backed off); a resend needs
    /// the port open.
    pub(super) fn verdict(
        &mut self,
        f: &OnLine<R>,
        why: Failure,
        now: Instant,
        port_open: bool,
    ) -> Verdict {
        let adu = f.req.adu();
        let unit = adu.unit();
        if why == Failure::Timeout {
            if let Some(l) = self.learned.get_mut(&unit) {
                l.timed_out();
            }
            if let Some(interval) = self.units.timed_out(unit, now) {
                return Verdict::BackedOff(interval);
            }
        }
        let policy = self.policy(unit);
        let may_retry = adu.function_code().is_read() || policy.retry_writes;
        if may_retry && f.req.attempts() < policy.retries && port_open {
            Verdict::Resend
        } else {
            Verdict::Fail
        }
    }
}

/// Per-unit health on an RTU/ASCII bus: a unit that timed out `after` times in a row
/// is backed off for an interval that doubles (from `min` up to `max`) each time a
/// probe fails; a reply forgets it all.
struct UnitHealth {
    enabled: bool,
    after: u32,
    min: Duration,
    max: Duration,
    health: IdMap<u8, Health>,
}

#[derive(Debug, Default)]
struct Health {
    /// Timeouts in a row.
    timeouts: u32,
    /// The current back-off interval, once backed off.
    interval: Option<Duration>,
    until: Option<Instant>,
}

impl UnitHealth {
    fn new(cfg: &RelayConfig, enabled: bool) -> Self {
        let max = Duration::from_millis(cfg.unit_backoff_max_ms);
        Self {
            enabled,
            after: cfg.unit_backoff_after,
            min: Duration::from_millis(cfg.unit_backoff_ms).min(max),
            max,
            health: IdMap::default(),
        }
    }

    fn backed_off(&self, unit: u8, now: Instant) -> bool {
        self.health
            .get(&unit)
            .and_then(|h| h.until)
            .is_some_and(|until| now < until)
    }

    /// A request to `unit` timed out; the interval it is now backed off for, if it is.
    fn timed_out(&mut self, unit: u8, now: Instant) -> Option<Duration> {
        if !self.enabled || unit == 0 {
            return None;
        }
        let h = self.health.entry(unit).or_default();
        h.timeouts += 1;
        if h.timeouts < self.after {
            return None;
        }
        let interval = h.interval.map_or(self.min, |i| (i * 2).min(self.max));
        h.interval = Some(interval);
        h.until = Some(now + interval);
        Some(interval)
    }

    /// Was `unit` backed off, with no reply since? A request to it now is a probe.
    fn probing(&self, unit: u8) -> bool {
        self.health.get(&unit).is_some_and(|h| h.interval.is_some())
    }

    fn answered(&mut self, unit: u8) {
        self.health.remove(&unit);
    }
}

/// 0x0B answers for backed-off units, each due no sooner than the line could have
/// served the request, in order: a master that polls a dead unit in a tight loop gets
/// its answers at the line's pace, not as fast as the gateway can turn them round.
pub(super) struct Paced<R> {
    waiting: VecDeque<(Instant, R)>,
    /// When the next answer may go.
    next: Instant,
}

impl<R> Paced<R> {
    pub(super) fn new(now: Instant) -> Self {
        Self {
            waiting: VecDeque::new(),
            next: now,
        }
    }

    /// `req`, which the line would take `shortest` to serve, is to be answered 0x0B:
    /// given back if that may be done at `now`, else kept until it is due.
    pub(super) fn pace(&mut self, req: R, now: Instant, shortest: Duration) -> Option<R> {
        let due = self.next.max(now);
        self.next = due + shortest;
        if due <= now {
            Some(req)
        } else {
            self.waiting.push_back((due, req));
            None
        }
    }

    /// The answers due at `now`, in order.
    pub(super) fn due(&mut self, now: Instant) -> Vec<R> {
        let mut due = Vec::new();
        while self.waiting.front().is_some_and(|(at, _)| *at <= now) {
            due.push(self.waiting.pop_front().expect("checked").1);
        }
        due
    }

    /// When the next kept answer is due.
    pub(super) fn next_due(&self) -> Option<Instant> {
        self.waiting.front().map(|(at, _)| *at)
    }

    /// Every kept answer, due or not (the relay is shutting down).
    pub(super) fn take_all(&mut self) -> Vec<R> {
        std::mem::take(&mut self.waiting)
            .into_iter()
            .map(|(_, r)| r)
            .collect()
    }
}

/// A request in tests: the ADU and how many times it was resent.
#[cfg(test)]
impl Asked for (Adu, u32) {
    fn adu(&self) -> &Adu {
        &self.0
    }
    fn attempts(&self) -> u32 {
        self.1
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    fn read(unit: u8, attempts: u32) -> (Adu, u32) {
        (Adu::build(7, unit, &[3, 0, 0, 0, 1]), attempts)
    }

    fn write(unit: u8, attempts: u32) -> (Adu, u32) {
        (Adu::build(7, unit, &[6, 0, 1, 0, 3]), attempts)
    }

    #[test]
    fn units_back_off_after_n_timeouts_doubling_up_to_max() {
        let cfg = RelayConfig {
            unit_backoff_after: 2,
            unit_backoff_ms: 100,
            unit_backoff_max_ms: 300,
            ..RelayConfig::default()
        };
        let mut u = UnitHealth::new(&cfg, true);
        let t0 = Instant::now();
        assert_eq!(u.timed_out(5, t0), None);
        assert!(!u.backed_off(5, t0));
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(100)));
        assert!(u.backed_off(5, t0 + Duration::from_millis(99)));
        assert!(
            !u.backed_off(5, t0 + Duration::from_millis(100)),
            "probed after"
        );
        assert!(!u.backed_off(6, t0), "other units are not touched");
        assert!(
            u.probing(5) && !u.probing(6),
            "a request to it now probes it"
        );
        // Failed probes double the interval, up to the max.
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(200)));
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(300)));
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(300)));
        // A reply forgets it all.
        u.answered(5);
        assert!(!u.backed_off(5, t0) && !u.probing(5));
        assert_eq!(u.timed_out(5, t0), None);
        // Broadcasts and a disabled backoff never back off.
        assert_eq!(u.timed_out(0, t0), None);
        let mut off = UnitHealth::new(&cfg, false);
        assert_eq!((off.timed_out(5, t0), off.timed_out(5, t0)), (None, None));
    }

    /// Deadlines count from when the request has left (behind the bytes queued before
    /// it), restart from when the port drained, and expire at the deadline itself.
    #[test]
    fn deadlines_count_from_the_request_leaving_and_restart_on_drain() {
        let cfg = RelayConfig {
            response_timeout_ms: 100,
            ..RelayConfig::default()
        };
        let mut t = InFlight::new(&cfg, &UnitTables::default(), false);
        let t0 = Instant::now();
        t.start(1, read(1, 0), t0, 10 * MS);
        t.start(2, read(2, 0), t0, 30 * MS);
        assert_eq!(t.next_deadline(), Some(t0 + 110 * MS));
        assert!(t.take_expired(t0 + 109 * MS).is_empty());
        let gone: Vec<u16> = t
            .take_expired(t0 + 110 * MS)
            .iter()
            .map(|f| f.tid)
            .collect();
        assert_eq!(gone, [1]);
        t.restart(t0 + 50 * MS);
        assert_eq!(t.next_deadline(), Some(t0 + 150 * MS));
        assert!(t.take(1).is_none(), "already taken");
        assert_eq!(t.take(2).map(|f| f.tid), Some(2));
        assert!(t.is_empty() && t.next_deadline().is_none());
    }

    /// Reads are resent up to `retries` times while the port is open, writes only with
    /// `retry_writes`; a unit that keeps timing out is backed off, its next request
    /// is a probe with the shorter timeout, and a reply makes it healthy again.
    #[test]
    fn verdicts_resend_reads_fail_writes_and_back_off_a_silent_unit() {
        let cfg = RelayConfig {
            retries: 1,
            retry_writes: false,
            response_timeout_ms: 1000,
            probe_timeout_ms: 200,
            unit_backoff_after: 2,
            unit_backoff_ms: 500,
            unit_backoff_max_ms: 4000,
            ..RelayConfig::default()
        };
        let mut t = InFlight::new(&cfg, &UnitTables::default(), true);
        let t0 = Instant::now();
        let verdict = |t: &mut InFlight<(Adu, u32)>, req, why, open| {
            t.start(9, req, t0, Duration::ZERO);
            let f = t.take(9).expect("just started");
            t.verdict(&f, why, t0, open)
        };
        assert_eq!(
            verdict(&mut t, read(1, 0), Failure::Corrupt, true),
            Verdict::Resend
        );
        assert_eq!(
            verdict(&mut t, read(1, 1), Failure::Corrupt, true),
            Verdict::Fail,
            "retries used up"
        );
        assert_eq!(
            verdict(&mut t, read(1, 0), Failure::Corrupt, false),
            Verdict::Fail,
            "the port is closed"
        );
        assert_eq!(
            verdict(&mut t, write(1, 0), Failure::Corrupt, true),
            Verdict::Fail
        );
        let mut writes = InFlight::new(
            &RelayConfig {
                retry_writes: true,
                ..cfg.clone()
            },
            &UnitTables::default(),
            true,
        );
        assert_eq!(
            verdict(&mut writes, write(1, 0), Failure::Corrupt, true),
            Verdict::Resend
        );
        // Two timeouts in a row back unit 3 off; a bad reply does not count.
        assert_eq!(
            verdict(&mut t, read(3, 0), Failure::Timeout, true),
            Verdict::Resend
        );
        assert_eq!(
            verdict(&mut t, read(3, 1), Failure::Timeout, true),
            Verdict::BackedOff(500 * MS)
        );
        assert!(t.backed_off(3, t0 + 499 * MS) && !t.backed_off(3, t0 + 500 * MS));
        assert!(!t.backed_off(1, t0));
        // The probe waits the shorter timeout; its answer clears the unit.
        t.start(4, read(3, 0), t0, Duration::ZERO);
        t.start(5, read(1, 0), t0, Duration::ZERO);
        assert_eq!(t.take(5).map(|f| f.deadline), Some(t0 + 1000 * MS));
        assert_eq!(t.next_deadline(), Some(t0 + 200 * MS));
        assert!(t.answered(4, t0).is_some());
        t.start(6, read(3, 0), t0, Duration::ZERO);
        assert_eq!(t.next_deadline(), Some(t0 + 1000 * MS), "healthy again");
    }

    /// Answers for backed-off units go no faster than the line could serve their
    /// requests: the first at once, the next each `shortest` after the one before.
    #[test]
    fn paced_answers_go_at_the_lines_pace_in_order() {
        let t0 = Instant::now();
        let mut p = Paced::new(t0);
        assert_eq!(p.pace("a", t0, 10 * MS), Some("a"));
        assert_eq!(p.pace("b", t0, 10 * MS), None);
        assert_eq!(p.pace("c", t0 + MS, 10 * MS), None);
        assert_eq!(p.next_due(), Some(t0 + 10 * MS));
        assert!(p.due(t0 + 9 * MS).is_empty());
        assert_eq!(p.due(t0 + 10 * MS), ["b"]);
        assert_eq!(p.next_due(), Some(t0 + 20 * MS));
        assert_eq!(p.take_all(), ["c"]);
        // A line idle since: the next goes at once again.
        assert_eq!(p.pace("d", t0 + 100 * MS, 10 * MS), Some("d"));
        assert!(p.next_due().is_none());
    }

    /// A unit's own table: its retries and retry_writes decide its verdicts, its
    /// pause is the line's pause after it; a learned timeout starts at the ceiling,
    /// learns from the replies, gives the ceiling back after a timeout, and holds the
    /// line quiet until the ceiling after a timeout.
    #[test]
    fn a_units_own_settings_and_learned_timeout() {
        let text = "[[line]]\nserial = { path = \"/dev/x\", framing = \"rtu\" }\n\
                    relay = { response_timeout_ms = 400 }\n\
                    [[line.unit]]\nunits = 5\nretries = 2\nretry_writes = true\nrequest_pause_ms = 30\n\
                    [[line.unit]]\nunits = 6\nresponse_timeout_ms = \"auto\"\nresponse_timeout_max_ms = 800\n";
        let cfg = crate::config::parse(text, "t").unwrap();
        let line = &cfg.lines[0];
        let mut t = InFlight::new(&line.relay, &line.unit_tables, false);
        let t0 = Instant::now();
        assert_eq!(
            (t.policy(5).pause, t.policy(4).pause),
            (30 * MS, Duration::ZERO)
        );
        let verdict = |t: &mut InFlight<(Adu, u32)>, req| {
            t.start(9, req, t0, Duration::ZERO);
            let f = t.take(9).expect("just started");
            t.verdict(&f, Failure::Corrupt, t0, true)
        };
        assert_eq!(
            verdict(&mut t, write(5, 1)),
            Verdict::Resend,
            "its own retries"
        );
        assert_eq!(verdict(&mut t, write(5, 2)), Verdict::Fail);
        assert_eq!(
            verdict(&mut t, read(4, 0)),
            Verdict::Fail,
            "the line's: none"
        );
        // Unit 6: at the ceiling until 20 replies of 20 ms, then the floor (50 ms).
        for _ in 0..20 {
            t.start(1, read(6, 0), t0, Duration::ZERO);
            assert_eq!(t.next_deadline(), Some(t0 + 800 * MS));
            assert!(t.answered(1, t0 + 20 * MS).is_some());
        }
        t.start(1, read(6, 0), t0, Duration::ZERO);
        assert_eq!(
            t.next_deadline(),
            Some(t0 + 50 * MS),
            "learned, at the floor"
        );
        let f = t.take_expired(t0 + 50 * MS).pop().expect("timed out");
        assert_eq!(
            t.hold_after_timeout(&f),
            750 * MS,
            "quiet until the ceiling"
        );
        assert_eq!(t.verdict(&f, Failure::Timeout, t0, true), Verdict::Fail);
        t.start(2, read(6, 0), t0, Duration::ZERO);
        assert_eq!(t.next_deadline(), Some(t0 + 800 * MS), "the ceiling back");
        assert_eq!(
            t.learned(6).map(|l| l.why()),
            Some(crate::line::relay::learn::TimeoutReason::TimedOut)
        );
        let fixed = t.take(2).unwrap();
        t.start(3, read(5, 0), t0, Duration::ZERO);
        let five = t.take(3).unwrap();
        assert_eq!(
            t.hold_after_timeout(&five),
            Duration::ZERO,
            "a fixed timeout: the guard alone"
        );
        drop(fixed);
    }

    proptest::proptest! {
        #![proptest_config(proptest::test_runner::Config {
            failure_persistence: None,
            ..Default::default()
        })]

        /// The invariant of a timeout on an RTU or ASCII line, learned or fixed: the
        /// line stays quiet at least until the ceiling and the guard after it have
        /// passed since the request left (what a fixed timeout at the ceiling keeps),
        /// and frees then (or after `request_pause_ms`, if later). Any floor,
        /// ceiling, guard, pause and learned pace; the in-flight table's hold and the
        /// line's timer together, as the loop drives them.
        #[test]
        fn a_learned_timeout_keeps_the_guard_after_its_ceiling(
            floor_ms in 1u64..200,
            above_ms in 0u64..2000,
            guard_ms in 1u64..500,
            pause_ms in 0u64..300,
            reply_ms in 1u64..1000,
            replies in 0usize..40,
        ) {
            use crate::line::port::kind::{Medium, PortInfo};
            use crate::line::relay::line::LineFraming;
            use crate::ops::stats::Stats;
            let ceiling_ms = floor_ms + above_ms;
            let text = format!(
                "[[line]]\nserial = {{ path = \"/dev/x\", framing = \"rtu\" }}\n\
                 relay = {{ response_timeout_ms = {ceiling_ms}, timeout_guard_ms = {guard_ms}, \
                 request_pause_ms = {pause_ms} }}\n\
                 [[line.unit]]\nunits = 6\nresponse_timeout_ms = \"auto\"\n\
                 response_timeout_min_ms = {floor_ms}\nresponse_timeout_max_ms = {ceiling_ms}\n"
            );
            let cfg = crate::config::parse(&text, "t").unwrap();
            let line_cfg = &cfg.lines[0];
            let stats = Stats::default();
            let t0 = Instant::now();
            let ms = Duration::from_millis;
            let (ceiling, guard) = (ms(ceiling_ms), ms(guard_ms));
            for unit in [6u8, 1] {
                let mut t = InFlight::new(&line_cfg.relay, &line_cfg.unit_tables, false);
                for _ in 0..replies {
                    t.start(1, read(unit, 0), t0, Duration::ZERO);
                    let at = t0 + ms(reply_ms).min(t.next_deadline().unwrap() - t0);
                    t.answered(1, at);
                }
                let mut line =
                    LineFraming::new(&line_cfg.relay, &line_cfg.serial, false, t0);
                line.port_opened(&PortInfo::plain(Medium::Pty));
                let req = read(unit, 0);
                let key = line.allocate(t0);
                let bytes = line.encode(&req.0, key, t0, &stats);
                line.wrote(bytes.len(), t0, t0);
                let left = line.drained(t0, &stats);
                t.start(key, req, left, Duration::ZERO);
                let deadline = t.next_deadline().unwrap();
                proptest::prop_assert!(deadline <= left + ceiling);
                let f = t.take_expired(deadline).pop().unwrap();
                line.timed_out(deadline, t.hold_after_timeout(&f), &stats);
                let guarded = left + ceiling + guard;
                let us = Duration::from_micros(1);
                proptest::prop_assert!(
                    !line.has_room(0, false, guarded - us),
                    "unit {}: free before the ceiling and the guard ({:?} learned)",
                    unit,
                    deadline - left
                );
                let free = guarded.max(deadline + ms(pause_ms));
                proptest::prop_assert!(line.has_room(0, false, free), "unit {}", unit);
            }
        }
    }
}
