//! What the gateway knows of each line, unit and listener while it runs
//! (docs/watching.md): counters and gauges their owners write with relaxed atomics, read
//! by the metrics listener (`http.rs`), the Prometheus exposition (`expose.rs`),
//! systemd's STATUS= line and `mbgate status`.
//!
//! The relay writes its line's numbers as it goes, a few relaxed atomic stores a
//! request and no lock: nothing here makes the relay wait on a reader. (The status
//! page's last frames come from the capture, `crate::ops::capture`.) A reader sees
//! each number as it was at some instant, the set of them not necessarily at the same
//! one (a scrape in the middle of a reply may count the request and not yet the reply).

pub(crate) mod expose;
pub(crate) mod http;
pub(crate) mod listener;
pub(crate) mod page;
pub(crate) mod status;
pub(crate) mod status_command;
pub(crate) mod web;

use crate::ops::stats::Stats;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::time::Instant;

/// Upper bounds of the reply-time histogram buckets, in seconds, for serial lines: from
/// a fast device on a native UART (1 ms) to a slow device behind a radio link near the
/// longest timeout anyone sets (10 s), 1-2-5 a decade.
pub(crate) const REPLY_BUCKETS: [f64; 13] = [
    0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0,
];

fn load(a: &AtomicU64) -> u64 {
    a.load(Ordering::Relaxed)
}

fn add(a: &AtomicU64, n: u64) {
    a.fetch_add(n, Ordering::Relaxed);
}

/// One unit on a line.
#[derive(Debug, Default)]
pub(crate) struct UnitMetrics {
    /// Requests for this unit the relay took.
    pub(crate) requests: AtomicU64,
    /// Replies from it delivered to masters (exceptions it sent included).
    pub(crate) replies: AtomicU64,
    /// Attempts it did not answer in time (a resent request counts each attempt).
    pub(crate) timeouts: AtomicU64,
    /// 1 while it is backed off (RTU/ASCII, `unit_backoff`), else 0.
    pub(crate) backed_off: AtomicU64,
    /// 1 from its third timeout in a row until it answers again (the log's "not
    /// answering" warning), else 0. What the metrics and `mbgate status` show is
    /// [`LineMetrics::not_answering`]: this, within [`HEALTH_WINDOW`] of a timeout.
    pub(crate) not_answering: AtomicU64,
    /// When its last timeout came, in microseconds after the line's start; 0 for none.
    last_timeout_us: AtomicU64,
    /// Reply times, from the request on the line to its reply.
    reply: Histogram,
    /// Its learned response timeout in microseconds (`response_timeout_ms = "auto"`);
    /// 0 for a fixed one.
    learned_us: AtomicU64,
    /// Why the learned timeout is what it is: its place in `crate::line::relay`'s reasons
    /// ([`LEARNED_WHY`]).
    learned_why: AtomicU64,
}

/// The reasons a learned timeout gives, in the relay's order (docs/reliability.md
/// "Learned timeouts"): the `why` label.
pub(crate) const LEARNED_WHY: [&str; 5] = ["start", "timeout", "learned", "floor", "ceiling"];

/// Durations counted in the buckets of [`REPLY_BUCKETS`]: one count per bucket (not
/// cumulative), the last for those above every bound, and their sum.
#[derive(Debug, Default)]
pub(crate) struct Histogram {
    buckets: [AtomicU64; REPLY_BUCKETS.len() + 1],
    /// Their sum, in microseconds.
    sum_us: AtomicU64,
}

impl Histogram {
    /// One more duration.
    pub(crate) fn observe(&self, took: Duration) {
        let s = took.as_secs_f64();
        let i = REPLY_BUCKETS
            .iter()
            .position(|b| s <= *b)
            .unwrap_or(REPLY_BUCKETS.len());
        add(&self.buckets[i], 1);
        add(&self.sum_us, took.as_micros() as u64);
    }

    /// The upper bound of the bucket that holds the `q` quantile (0 < q ≤ 1), in
    /// seconds; `None` without a count, infinity above 10 s.
    pub(crate) fn quantile_bound(&self, q: f64) -> Option<f64> {
        let (_, count, each) = self.get();
        if count == 0 {
            return None;
        }
        let want = (q * count as f64).ceil() as u64;
        let mut seen = 0;
        each.iter().find_map(|&(bound, n)| {
            seen += n;
            (seen >= want).then_some(bound)
        })
    }

    /// Sum in seconds, count, and the count in each bucket by its upper bound (the
    /// last +Inf), not cumulative: the encoder adds them up.
    pub(crate) fn get(&self) -> (f64, u64, Vec<(f64, u64)>) {
        let mut total = 0;
        let mut each = Vec::with_capacity(self.buckets.len());
        for (i, b) in self.buckets.iter().enumerate() {
            total += load(b);
            let bound = REPLY_BUCKETS.get(i).copied().unwrap_or(f64::INFINITY);
            each.push((bound, load(b)));
        }
        (load(&self.sum_us) as f64 / 1e6, total, each)
    }

    /// How many durations it has counted.
    pub(crate) fn count(&self) -> u64 {
        self.buckets.iter().map(load).sum()
    }
}

impl UnitMetrics {
    /// A reply came `took` after its request went on the line.
    pub(crate) fn observe(&self, took: Duration) {
        self.reply.observe(took);
    }

    /// The unit's learned timeout is now `timeout`, for the reason at `why` in
    /// [`LEARNED_WHY`].
    pub(crate) fn set_learned(&self, timeout: Duration, why: usize) {
        let us = (timeout.as_micros() as u64).max(1);
        self.learned_us.store(us, Ordering::Relaxed);
        self.learned_why.store(why as u64, Ordering::Relaxed);
    }

    /// Its learned timeout and why, if it has one.
    pub(crate) fn learned(&self) -> Option<(Duration, &'static str)> {
        let us = load(&self.learned_us);
        let why = LEARNED_WHY.get(load(&self.learned_why) as usize).copied();
        (us > 0).then(|| (Duration::from_micros(us), why.unwrap_or("start")))
    }

    /// The upper bound of the bucket that holds the `q` quantile of the reply times
    /// (0 < q ≤ 1), in seconds; `None` without replies, infinity above 10 s.
    pub(crate) fn quantile_bound(&self, q: f64) -> Option<f64> {
        self.reply.quantile_bound(q)
    }

    /// The reply-time histogram ([`Histogram::get`]).
    pub(crate) fn histogram(&self) -> (f64, u64, Vec<(f64, u64)>) {
        self.reply.get()
    }
}

/// One line: its counters (the relay's [`Stats`]), its units, its gauges.
#[derive(Debug)]
pub(crate) struct LineMetrics {
    /// The `line` label: the serial port's path, or host:port of a device server.
    pub(crate) name: String,
    pub(crate) stats: Arc<Stats>,
    units: Box<[UnitMetrics]>,
    /// Exception replies the device sent, by exception code.
    device_exceptions: Box<[AtomicU64]>,
    /// Requests waiting for the line.
    pub(crate) queued: AtomicU64,
    /// Requests on the line, awaiting their reply.
    pub(crate) in_flight: AtomicU64,
    /// Masters attached to the line.
    pub(crate) masters: AtomicU64,
    /// Time with a request on the line, in microseconds.
    pub(crate) busy_us: AtomicU64,
    /// When the last reply came, in microseconds after `started`; 0 for none yet.
    pub(crate) last_reply_us: AtomicU64,
    /// Whether the port is open (1) or not (0).
    pub(crate) port_open: AtomicU64,
    /// Outages of the port: lost, or not opened at start; each once, however many
    /// attempts it took to open it again.
    pub(crate) outages: AtomicU64,
    /// The time the port was down, in one word so a scrape never reads half a change:
    /// while it is open, the total of the outages that ended, in microseconds; while
    /// it is down ([`DOWN`] set), when the outage began (microseconds after `started`)
    /// less that total, so the total now is the time since. Written by the line's
    /// task only.
    outage_clock: AtomicU64,
    /// How long requests waited in the queue before they went on the line, by
    /// priority class (docs/masters.md "Priority"): from the relay taking a request
    /// to its first sending.
    pub(crate) queue_wait: [Histogram; QUEUE_CLASSES],
    started: Instant,
    /// Who switches the line's RS-485 transmitter, in words; empty where nobody is
    /// asked to (`crate::config::describe::direction`).
    direction: std::sync::Mutex<String>,
}

/// The top bit of [`LineMetrics`]' outage clock: the port is down.
const DOWN: u64 = 1 << 63;

/// The priority classes a queue wait is counted by: 0 to `priority`'s highest.
pub(crate) const QUEUE_CLASSES: usize = crate::config::access::PRIORITY_MAX as usize + 1;

/// A unit not answering counts as failing (the gateway not healthy) until it answers
/// again, or until this long has passed since its last timeout: a unit nobody asks
/// any more (a mistyped unit id, asked once) is not failing. Longer than the longest
/// default backoff (`unit_backoff_max_ms`, 30 s), so a dead unit that masters keep
/// polling stays failing between its probes.
pub(crate) const HEALTH_WINDOW: Duration = Duration::from_secs(60);

impl LineMetrics {
    pub(crate) fn new(name: &str, stats: Arc<Stats>) -> Self {
        Self {
            name: name.to_owned(),
            stats,
            units: (0..256).map(|_| UnitMetrics::default()).collect(),
            device_exceptions: (0..256).map(|_| AtomicU64::new(0)).collect(),
            queued: AtomicU64::new(0),
            in_flight: AtomicU64::new(0),
            masters: AtomicU64::new(0),
            busy_us: AtomicU64::new(0),
            last_reply_us: AtomicU64::new(0),
            port_open: AtomicU64::new(0),
            outages: AtomicU64::new(0),
            outage_clock: AtomicU64::new(0),
            queue_wait: Default::default(),
            started: Instant::now(),
            direction: std::sync::Mutex::new(String::new()),
        }
    }

    /// Says who switches the line's transmitter (`None`: nobody is asked to).
    pub(crate) fn set_direction(&self, said: Option<String>) {
        *self.direction.lock().unwrap_or_else(|e| e.into_inner()) = said.unwrap_or_default();
    }

    /// Who switches the line's transmitter, if anybody is asked to.
    pub(crate) fn direction(&self) -> Option<String> {
        let d = self.direction.lock().unwrap_or_else(|e| e.into_inner());
        (!d.is_empty()).then(|| d.clone())
    }

    pub(crate) fn unit(&self, unit: u8) -> &UnitMetrics {
        &self.units[usize::from(unit)]
    }

    /// The units that have had a request, with their numbers.
    pub(crate) fn units(&self) -> impl Iterator<Item = (u8, &UnitMetrics)> {
        self.units
            .iter()
            .enumerate()
            .filter(|(_, u)| load(&u.requests) > 0)
            .map(|(i, u)| (i as u8, u))
    }

    /// The device answered a request with exception `code`.
    pub(crate) fn device_exception(&self, code: u8) {
        add(&self.device_exceptions[usize::from(code)], 1);
    }

    /// Exception codes the device sent, with how many of each.
    pub(crate) fn device_exceptions(&self) -> Vec<(u8, u64)> {
        let all = self.device_exceptions.iter().enumerate();
        all.map(|(c, n)| (c as u8, load(n)))
            .filter(|(_, n)| *n > 0)
            .collect()
    }

    /// The port went down at `since` (lost, or its first open failed): an outage
    /// begins, unless one is under way.
    pub(crate) fn port_down(&self, since: Instant) {
        let clock = self.outage_clock.load(Ordering::Relaxed);
        if clock & DOWN != 0 {
            return;
        }
        let at = since.saturating_duration_since(self.started).as_micros() as u64;
        add(&self.outages, 1);
        self.outage_clock
            .store(DOWN | at.saturating_sub(clock), Ordering::Relaxed);
    }

    /// The port is open again at `now`: the outage under way, if any, ends.
    pub(crate) fn port_up(&self, now: Instant) {
        let clock = self.outage_clock.load(Ordering::Relaxed);
        if clock & DOWN == 0 {
            return;
        }
        let at = now.saturating_duration_since(self.started).as_micros() as u64;
        self.outage_clock
            .store(at.saturating_sub(clock & !DOWN), Ordering::Relaxed);
    }

    /// The time the port was down up to `now`, the outage under way included.
    pub(crate) fn outage_time(&self, now: Instant) -> Duration {
        let clock = self.outage_clock.load(Ordering::Relaxed);
        let us = if clock & DOWN == 0 {
            clock
        } else {
            let at = now.saturating_duration_since(self.started).as_micros() as u64;
            at.saturating_sub(clock & !DOWN)
        };
        Duration::from_micros(us)
    }

    /// A reply came at `now`.
    pub(crate) fn replied_at(&self, now: Instant) {
        let us = now.saturating_duration_since(self.started).as_micros() as u64;
        self.last_reply_us.store(us.max(1), Ordering::Relaxed);
    }

    /// A request for `unit` timed out at `now`.
    pub(crate) fn timed_out(&self, unit: u8, now: Instant) {
        let u = self.unit(unit);
        add(&u.timeouts, 1);
        let us = self.us_since_start(now).max(1);
        u.last_timeout_us.store(us, Ordering::Relaxed);
    }

    /// Whether `u` is failing at `now`: not answering (three timeouts in a row, no
    /// reply since), its last timeout within [`HEALTH_WINDOW`].
    pub(crate) fn not_answering(&self, u: &UnitMetrics, now: Instant) -> bool {
        let last = load(&u.last_timeout_us);
        let recent = last > 0
            && self.us_since_start(now).saturating_sub(last) < HEALTH_WINDOW.as_micros() as u64;
        load(&u.not_answering) == 1 && recent
    }

    /// How long ago the last reply came, if one has.
    pub(crate) fn since_last_reply(&self, now: Instant) -> Option<Duration> {
        let us = load(&self.last_reply_us);
        (us > 0).then(|| now.saturating_duration_since(self.started + Duration::from_micros(us)))
    }

    pub(crate) fn get(&self, a: &AtomicU64) -> u64 {
        load(a)
    }

    fn us_since_start(&self, now: Instant) -> u64 {
        now.saturating_duration_since(self.started).as_micros() as u64
    }
}

/// One Modbus/TCP listener.
#[derive(Debug)]
pub(crate) struct ListenerMetrics {
    /// The `listener` label: the address it is bound to.
    pub(crate) name: String,
    /// Its connection counters (`connections`, `connections_refused`,
    /// `connections_denied`, `tls_failed`, `tls_refused`, `protocol_violations`,
    /// `connections_closed`) and the requests it answered itself (`denied`,
    /// `bad_requests`, `unavailable` for a unit no line serves).
    pub(crate) stats: Arc<Stats>,
}

impl ListenerMetrics {
    /// Masters connected now.
    pub(crate) fn connected(&self) -> u64 {
        let s = &self.stats;
        s.get(&s.connections)
            .saturating_sub(s.get(&s.connections_closed))
    }
}

/// A master connected now, as the status page and `mbgate status` show it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct MasterSeen {
    /// The connection id the logs use (`conn=3`).
    pub(crate) conn: u64,
    /// The listener's address (the `listener` label).
    pub(crate) listener: String,
    /// What it came by, as configured: an accepted connection's or a UDP source's
    /// listener, or a dial (what a reload finds its priority class by).
    pub(crate) source: std::sync::Arc<crate::config::ListenConfig>,
    pub(crate) peer: std::net::SocketAddr,
    /// When it connected, seconds since the Unix epoch.
    pub(crate) since: f64,
    /// A TLS master's role and its certificate's subject (docs/security.md).
    pub(crate) tls: Option<(String, String)>,
}

/// The masters connected now: the connections add and remove themselves (a lock taken
/// once at each end of a connection, never by the relay).
#[derive(Debug, Default)]
pub(crate) struct ConnectedMasters(Mutex<std::collections::BTreeMap<u64, MasterSeen>>);

impl ConnectedMasters {
    pub(crate) fn add(&self, m: MasterSeen) {
        self.0.lock().expect("not poisoned").insert(m.conn, m);
    }

    pub(crate) fn remove(&self, conn: u64) {
        self.0.lock().expect("not poisoned").remove(&conn);
    }

    /// Every master connected, oldest connection first.
    pub(crate) fn list(&self) -> Vec<MasterSeen> {
        self.0
            .lock()
            .expect("not poisoned")
            .values()
            .cloned()
            .collect()
    }
}

/// The configuration's reloads (docs/configuration.md "Reload"): how many took the
/// file and how many refused it, and how the last went, which the alert on a refused
/// reload watches (docs/mbgate-alerts.yml).
#[derive(Debug, Default)]
pub(crate) struct Reloads {
    pub(crate) taken: AtomicU64,
    pub(crate) refused: AtomicU64,
    /// 1 while the last reload refused the file.
    pub(crate) last_refused: AtomicU64,
    /// When the file was last taken, at start or by a reload: Unix time in
    /// microseconds.
    pub(crate) last_taken_us: AtomicU64,
}

impl Reloads {
    /// The file was taken at start, at `now`.
    pub(crate) fn started(&self, now: std::time::SystemTime) {
        self.last_taken_us.store(unix_us(now), Ordering::Relaxed);
    }

    /// A reload at `now` took the file, or refused it.
    pub(crate) fn reloaded(&self, taken: bool, now: std::time::SystemTime) {
        if taken {
            add(&self.taken, 1);
            self.last_taken_us.store(unix_us(now), Ordering::Relaxed);
        } else {
            add(&self.refused, 1);
        }
        self.last_refused
            .store(u64::from(!taken), Ordering::Relaxed);
    }
}

fn unix_us(t: std::time::SystemTime) -> u64 {
    let since = t.duration_since(std::time::SystemTime::UNIX_EPOCH);
    since.unwrap_or_default().as_micros() as u64
}

/// How a listener's masters reach it: the `transport` label, which keeps a TCP and a
/// UDP listener on one address (docs/dialing.md "Modbus over UDP") two series apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum ListenerTransport {
    /// TCP connections: an accepted master's, or a dial's (`dial HOST:PORT`).
    Tcp,
    /// UDP datagrams.
    Udp,
}

impl ListenerTransport {
    /// The label's value.
    pub(crate) fn label(self) -> &'static str {
        match self {
            ListenerTransport::Tcp => "tcp",
            ListenerTransport::Udp => "udp",
        }
    }
}

/// Everything the gateway shows: its lines and listeners, in the order they started.
#[derive(Debug, Default)]
pub(crate) struct Board {
    pub(crate) lines: Mutex<Vec<Arc<LineMetrics>>>,
    /// Each listener with how its masters reach it.
    listeners: Mutex<Vec<(Arc<ListenerMetrics>, ListenerTransport)>>,
    /// The masters connected now.
    pub(crate) masters: Arc<ConnectedMasters>,
    /// Each line's last minute, a point a second, by line name, while the metrics
    /// listener runs (`page::sample`).
    pub(crate) history: Mutex<std::collections::HashMap<String, page::History>>,
    /// The capture, whose packets the status page lists (each line's last frames).
    pub(crate) capture: std::sync::OnceLock<crate::ops::capture::Hub>,
    /// The configuration's reloads.
    pub(crate) reloads: Arc<Reloads>,
}

impl Board {
    pub(crate) fn add_line(&self, line: Arc<LineMetrics>) {
        self.lines.lock().expect("not poisoned").push(line);
    }

    /// A listener bound at start, reached by `transport`.
    pub(crate) fn add_listener_on(
        &self,
        listener: Arc<ListenerMetrics>,
        transport: ListenerTransport,
    ) {
        let mut listeners = self.listeners.lock().expect("not poisoned");
        listeners.push((listener, transport));
    }

    /// A source the masters' side adds while it runs (`tcp/tally.rs`): a dial, named
    /// `dial HOST:PORT`, over TCP; else a UDP listener, named by its address.
    pub(crate) fn add_listener(&self, listener: Arc<ListenerMetrics>) {
        let transport = if listener.name.starts_with("dial ") {
            ListenerTransport::Tcp
        } else {
            ListenerTransport::Udp
        };
        self.add_listener_on(listener, transport);
    }

    /// The listener (a dial, a UDP listener) counting in `stats` is gone (a reload).
    pub(crate) fn remove_listener(&self, stats: &Arc<crate::ops::stats::Stats>) {
        let mut listeners = self.listeners.lock().expect("not poisoned");
        listeners.retain(|(l, _)| !Arc::ptr_eq(&l.stats, stats));
    }

    pub(crate) fn lines(&self) -> Vec<Arc<LineMetrics>> {
        self.lines.lock().expect("not poisoned").clone()
    }

    pub(crate) fn listeners(&self) -> Vec<Arc<ListenerMetrics>> {
        let listeners = self.listeners.lock().expect("not poisoned");
        listeners.iter().map(|(l, _)| l.clone()).collect()
    }

    /// Each listener with how its masters reach it.
    pub(crate) fn listeners_on(&self) -> Vec<(Arc<ListenerMetrics>, ListenerTransport)> {
        self.listeners.lock().expect("not poisoned").clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each outage counted once, however often it is said; its time counted while it
    /// lasts and kept once it ended, never going back (a counter); and the port open
    /// at start with no outage counts none.
    #[test]
    fn outages_are_counted_once_and_their_time_only_grows() {
        let m = LineMetrics::new("/dev/ttyUSB0", Arc::new(Stats::default()));
        let t0 = m.started;
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        m.port_up(at(5));
        assert_eq!(
            (load(&m.outages), m.outage_time(at(10))),
            (0, Duration::ZERO)
        );
        m.port_down(at(100));
        m.port_down(at(150));
        assert_eq!(load(&m.outages), 1, "one outage, said twice");
        assert_eq!(m.outage_time(at(400)), Duration::from_millis(300));
        m.port_up(at(600));
        assert_eq!(m.outage_time(at(400)), Duration::from_millis(500));
        assert_eq!(m.outage_time(at(5000)), Duration::from_millis(500));
        m.port_up(at(700));
        m.port_down(at(1000));
        assert_eq!(load(&m.outages), 2);
        assert_eq!(m.outage_time(at(1250)), Duration::from_millis(750));
        m.port_up(at(2000));
        assert_eq!(m.outage_time(at(9000)), Duration::from_millis(1500));
    }
}
