//! The relay's loop: the one task that owns the line (docs/design.md §1, §5), wiring its
//! parts together and deciding nothing they can decide themselves.
//!
//! Connections talk to it over a channel ([`RelayHandle`], `command.rs`); it owns
//! every part below, so nothing here is locked. Each turn it pets the watchdog
//! (`watchdog.rs`), opens the port when due (`crate::port::lifecycle`), puts requests on the line
//! while it has room (`scheduler.rs` picks, `line/` encodes, `outgoing.rs` buffers,
//! `inflight.rs` times), then waits for one event (`event.rs`): a command, bytes from
//! the port, room to write, the end of a drain, the nearest timer, or shutdown. Bytes
//! read go to the framing (`line/`), whose frames the in-flight table matches to
//! their requests (answered through `pending.rs`) or not (late, or a notification for
//! `masters.rs`); requests past their deadline are resent or answered 0x0B as
//! `inflight.rs` decides.

mod cache;
mod command;
mod event;
mod failures;
mod ids;
mod inflight;
mod learn;
mod line;
mod masters;
mod outgoing;
mod pending;
mod scheduler;
mod telemetry;
mod turnaround;
pub(crate) mod watchdog;

use crate::config::{LineConfig, RelayConfig, SerialConfig};
use crate::frame::Adu;
use crate::metrics::LineMetrics;
use crate::outbox::{Refusal, Ticket};
use crate::port::lifecycle::{Lifecycle, State};
use crate::port::{self, OpenPort};
use crate::stats::Stats;
use crate::woken::Woken;
use cache::Cache;
#[cfg(test)]
pub(crate) use command::channel;
use command::Commands;
pub use command::{Command, ConnId, RelayHandle};
use event::Event;
use inflight::{Failure, InFlight, Paced};
use line::{LineFraming, Seen, Unsolicited};
use masters::Masters;
use outgoing::Outgoing;
use pending::Pending;
use scheduler::{Admitted, Queued, Scheduler};
use std::sync::Arc;
use std::time::Duration;
pub(crate) use telemetry::span;
use telemetry::Telemetry;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::debug;
use watchdog::Watchdog;

/// The task that owns one serial line and everything on it (the module notes): built
/// with [`Relay::new`], driven by [`Relay::run`].
pub struct Relay {
    cfg: RelayConfig,
    rx: Commands,
    masters: Masters,
    /// The requests waiting for the line, and which goes next.
    sched: Scheduler<Pending>,
    /// The requests on the line: deadlines, retries, unit backoff.
    in_flight: InFlight<Pending>,
    line: LineFraming,
    /// What the line made of the bytes read in a turn: kept from turn to turn, so a
    /// reply allocates no list to come in.
    seen: Vec<Seen>,
    /// Replies that may answer identical reads (`cache_ms`; empty when off).
    cache: Cache,
    /// 0x0B answers for backed-off units, at the line's pace.
    paced: Paced<Pending>,
    port: Lifecycle,
    out: Outgoing,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
    draining: bool,
    /// False once every [`RelayHandle`] is gone: `recv` would return at once forever.
    commands_open: bool,
    watchdog: Option<Watchdog>,
    /// The line's numbers, warnings and traffic log.
    telemetry: Telemetry,
    /// The RS-485 transmitter, where the gateway switches it (`serial.direction`).
    turnaround: Option<turnaround::Turnaround>,
}

impl Relay {
    /// A relay for this serial line, and the handle connections use to reach it.
    pub fn new(
        cfg: RelayConfig,
        serial: SerialConfig,
        traffic: bool,
        stats: Arc<Stats>,
        shutdown: CancellationToken,
    ) -> (Self, RelayHandle) {
        let port = Box::new(port::serial::SerialPort::new(serial.clone()));
        Self::build(cfg, serial, port, false, traffic, stats, shutdown)
    }

    /// A relay for a line of docs/design.md §4.1: on its serial port, or on a TCP
    /// connection to its device (`tcp`), where no byte is lost and none takes time on
    /// a wire, so the line keeps no gaps and confirms no frame.
    pub(crate) fn for_line(
        line: &LineConfig,
        traffic: bool,
        stats: Arc<Stats>,
        shutdown: CancellationToken,
    ) -> (Self, RelayHandle) {
        let (cfg, serial) = (line.relay.clone(), line.serial.clone());
        let (relay, handle) = match &line.tcp {
            Some(addr) => {
                let port = port::tcp::TcpPort::new(addr.clone()).with_tls(line.tcp_tls.clone());
                let port = Box::new(port);
                Self::build(cfg, serial, port, true, traffic, stats, shutdown)
            }
            None => Self::new(cfg, serial, traffic, stats, shutdown),
        };
        (relay.with_units(&line.unit_tables), handle)
    }

    /// Units with settings of their own (`[[line.unit]]`).
    pub(crate) fn with_units(mut self, units: &crate::config::unit::UnitTables) -> Self {
        self.in_flight.retune(&self.cfg, units);
        self
    }

    fn build(
        cfg: RelayConfig,
        serial: SerialConfig,
        transport: Box<dyn port::Port>,
        stream: bool,
        traffic: bool,
        stats: Arc<Stats>,
        shutdown: CancellationToken,
    ) -> (Self, RelayHandle) {
        let (handle, rx) = command::channel();
        let now = Instant::now();
        let line = LineFraming::new(&cfg, &serial, stream, now);
        // Only on a bus of units (RTU/ASCII): backing off the CIE-M10, the one unit of
        // an MBAP line, would gain the others nothing.
        let units = crate::config::unit::UnitTables::default();
        let in_flight = InFlight::new(&cfg, &units, cfg.unit_backoff && line.is_serial());
        let baud = serial.baud_rate;
        // The line is known by its transport's name (the metrics' `line` label).
        let metrics = Arc::new(LineMetrics::new(transport.name(), stats.clone()));
        let port = Lifecycle::new(transport, baud, now);
        metrics.set_direction(crate::config::describe::direction(&serial));
        // Over TCP the device server has the wire: nothing to switch here.
        let switches = port::serial::direction::gateway_switches(&serial);
        let turnaround = (switches && !stream).then(|| {
            turnaround::Turnaround::new(
                Duration::from_micros(serial.direction_delay_before_us.into()),
                Duration::from_micros(serial.direction_delay_after_us.into()),
                crate::port::kind::wire_time(&serial, 1),
            )
        });
        let relay = Relay {
            sched: Scheduler::new(cfg.queue_depth, cfg.coalesce),
            cache: Cache::new(Duration::from_millis(cfg.cache_ms)),
            masters: Masters::new(cfg.notifications),
            cfg,
            rx,
            in_flight,
            line,
            seen: Vec::new(),
            paced: Paced::new(now),
            port,
            out: Outgoing::default(),
            stats,
            shutdown,
            draining: false,
            commands_open: true,
            watchdog: None,
            telemetry: Telemetry::new(metrics, traffic, serial.framing, baud),
            turnaround,
        };
        (relay, handle)
    }

    /// Runs the line over `transport` instead of the `[serial]` port (a device behind
    /// a TCP socket, an in-memory pipe in tests).
    pub fn with_port(mut self, transport: Box<dyn port::Port>) -> Self {
        // The line is known by its transport's name (the metrics' `line` label).
        let metrics = LineMetrics::new(transport.name(), self.stats.clone());
        metrics.set_direction(self.telemetry.metrics.direction());
        self.telemetry.metrics = Arc::new(metrics);
        self.port.set_transport(transport);
        self
    }

    /// Hands the line's packets to `tap` (the capture and the status page's last
    /// frames, docs/capture.md) while anyone looks.
    pub(crate) fn with_tap(mut self, tap: crate::capture::Tap) -> Self {
        self.telemetry.tap = tap;
        self
    }

    /// The line's numbers as the relay keeps them (`crate::metrics`), for the metrics
    /// listener, systemd's status line and `mbgate status`. Asked after `with_port`,
    /// which names the line afresh.
    pub(crate) fn metrics(&self) -> Arc<LineMetrics> {
        self.telemetry.metrics.clone()
    }

    /// Sends systemd WATCHDOG=1 from the loop every `every` (the first at once);
    /// `None` means no watchdog and no timer for it, so an idle relay sleeps.
    pub(crate) fn with_watchdog(mut self, every: Option<Duration>) -> Self {
        self.watchdog = every.map(|every| Watchdog::new(every, Instant::now()));
        self
    }

    /// Runs until shutdown has been asked for and every request on the line has been
    /// answered or has timed out, or until every handle is gone.
    pub async fn run(mut self) {
        let mut rbuf = vec![0u8; 4096];
        // Every timer to the microsecond, set only when the next wake moves; without a
        // timerfd, tokio's, to the millisecond.
        let mut timer = crate::port::serial::PreciseTimer::new()
            .inspect_err(|e| debug!("no timerfd ({e}): timers to the millisecond"))
            .ok();
        // One wait for shutdown for the relay's life: made afresh each turn of the
        // loop, it would register with the token and unregister again every event;
        // and polled only once the token woke it (`crate::woken`).
        let mut shutdown = Woken::new(self.shutdown.clone().cancelled_owned());
        // The clock as the last turn ended. On a line of MBAP frames, which keeps no
        // gap and times nothing before a write to the microsecond, the next turn starts
        // from it (its work since is a few microseconds of ours): a clock read less
        // each turn. RTU and ASCII read it afresh for their gaps, and so does a line
        // whose RS-485 transmitter the gateway switches, for its delays.
        let carry = !self.line.is_serial() && self.turnaround.is_none();
        let mut ended: Option<Instant> = None;
        loop {
            let mut now = match ended.take() {
                Some(at) if carry => at,
                _ => Instant::now(),
            };
            if let Some(w) = &mut self.watchdog {
                w.pet(now);
            }
            // The line keeps the bytes it drops only while a capture wants them.
            self.line.set_tape(self.telemetry.capturing());
            self.open_if_due(now);
            self.dispatch(now);
            // What was dispatched is written in this turn when the port takes it at
            // once, not in a turn of its own: one pass of the loop less a transaction.
            let mut wrote = false;
            while let Some(after) = self.write_now(now) {
                (now, wrote) = (after, true);
                self.dispatch(now);
            }
            if wrote {
                // As the turn of a write would have: the gauges, and the line busy
                // from now.
                self.tell(now);
            }
            if self.draining && self.in_flight.is_empty() {
                break;
            }
            self.steer(now);
            let wake = self.next_wake(now);
            // Anything written below is written after this.
            let polled = now;
            let may_write = self.may_write(now);
            let sources = event::Sources {
                commands: self.commands_open.then_some(&mut self.rx),
                out: &self.out,
                may_write,
                wake,
                timer: timer.as_mut(),
                shutdown: (!self.draining).then_some(&mut shutdown),
            };
            let event = event::next(&mut self.port, sources, &mut rbuf).await;
            let now = Instant::now();
            match event {
                Event::Command(Some(cmd)) => self.on_command(cmd, now),
                Event::Command(None) => {
                    self.commands_open = false;
                    self.start_draining();
                }
                Event::Shutdown => self.start_draining(),
                Event::Read(Ok(0)) => self.port_lost("end of file (the far end went away)", now),
                Event::Read(Ok(n)) => {
                    self.stats.add(&self.stats.serial_bytes_in, n as u64);
                    // A capture begun while the loop waited has these bytes too.
                    self.line.set_tape(self.telemetry.capturing());
                    self.line.heard(n, self.in_flight.len(), now, &self.stats);
                    self.line.received(&rbuf[..n], now, &self.stats);
                }
                Event::Read(Err(e)) => self.port_lost(&format!("read failed: {e}"), now),
                Event::Wrote(Ok(n)) => self.wrote(n, polled, now),
                Event::Wrote(Err(e)) => self.port_lost(&format!("write failed: {e}"), now),
                Event::Opened(r) => self.opened(r, now),
                Event::Drained(r) => {
                    self.port.drain = None;
                    let left = match r {
                        // Not later than now: the two clocks are the same one.
                        Ok(at) => Instant::from_std(at).min(now),
                        Err(e) => {
                            debug!("tcdrain: {e}");
                            now
                        }
                    };
                    if let Some(t) = &mut self.turnaround {
                        t.drained(now);
                    }
                    self.drained(left);
                }
                Event::Timer => {}
            }
            self.take_frames(now);
            self.expire(now);
            self.answer_paced(now);
            self.tell(now);
            ended = Some(now);
        }
        debug!("relay stopped");
    }

    /// The end of a turn, for whoever looks: the bytes the line dropped, the gauges,
    /// the line's busy time.
    fn tell(&mut self, now: Instant) {
        for dropped in self.line.take_drops() {
            self.telemetry.dropped(dropped, now);
        }
        let (queued, in_flight) = (self.sched.queued(), self.in_flight.len());
        self.telemetry
            .turn(now, queued, in_flight, self.port.is_open());
    }

    /// May bytes be written now: always, unless the gateway switches the transmitter
    /// itself and it is not yet on with its delay before passed.
    fn may_write(&self, now: Instant) -> bool {
        self.turnaround.as_ref().is_none_or(|t| t.may_write(now))
    }

    /// Writes what waits to go out if the port takes it without waiting (the loop's
    /// wait would find it ready at once): the instant after the write, or `None` when
    /// nothing was written (nothing waits, the transmitter may not start yet, the port
    /// is full or closed, or the write failed and the port was lost). A port that is
    /// full keeps no waker from this try: the loop's wait polls the write again and
    /// registers its own.
    fn write_now(&mut self, now: Instant) -> Option<Instant> {
        if self.out.is_empty() || !self.may_write(now) {
            return None;
        }
        let State::Open(open) = &mut self.port.state else {
            return None;
        };
        let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
        match tokio::io::AsyncWrite::poll_write(
            std::pin::Pin::new(&mut open.writer),
            &mut cx,
            self.out.pending(),
        ) {
            std::task::Poll::Pending => None,
            std::task::Poll::Ready(Ok(0)) => None,
            std::task::Poll::Ready(Ok(n)) => {
                let after = Instant::now();
                self.wrote(n, now, after);
                Some(after)
            }
            std::task::Poll::Ready(Err(e)) => {
                self.port_lost(&format!("write failed: {e}"), Instant::now());
                None
            }
        }
    }

    /// `n` bytes of what waited went out, by a write begun at `polled` that returned
    /// at `now`.
    fn wrote(&mut self, n: usize, polled: Instant, now: Instant) {
        self.stats.add(&self.stats.serial_bytes_out, n as u64);
        self.line.wrote(n, polled, now);
        self.out.advance(n);
        if self.out.is_empty() && self.line.is_serial() {
            if let Some(t) = &mut self.turnaround {
                // The line times the frame from before the write (`polled`, a lower
                // bound for judging the reply); the transmitter goes off no sooner than
                // the last bytes' time on the wire after the write returned, so a pause
                // of this thread between the two (a busy machine) cannot cut the
                // request's tail where the port cannot say it is empty.
                let left = self.line.leaves_at().unwrap_or(now);
                t.written(self.line.left_after(n, now).map_or(left, |a| a.max(left)));
            }
            // The transmitter switch the gateway drives waits for the drain on any
            // port; without one, only a port that can hold bytes back needs it.
            if self.line.needs_drain() || self.turnaround.is_some() {
                self.start_drain(now);
            } else {
                // No wire, or none that holds bytes back: gone once written, or their
                // time on the wire after it (`LineFraming::needs_drain`).
                self.drained(now);
            }
        }
    }

    /// The nearest instant anything needs the loop: a deadline, the line's gaps, a
    /// paced answer, the next open, the watchdog; `None` when nothing does.
    fn next_wake(&self, now: Instant) -> Option<Instant> {
        [
            self.in_flight.next_deadline(),
            self.line.next_wake(now, self.sched.has_waiting()),
            self.turnaround.as_ref().and_then(|t| t.wake(now)),
            self.paced.next_due(),
            self.port.retry_at(),
            self.watchdog.as_ref().map(Watchdog::next),
        ]
        .into_iter()
        .flatten()
        .min()
    }

    fn open_if_due(&mut self, now: Instant) {
        if self.draining {
            return;
        }
        if let Some(opened) = self.port.open_if_due(now) {
            self.opened(opened, now);
        }
    }

    /// An open finished: the line starts afresh, or the next attempt is due later.
    fn opened(&mut self, opened: std::io::Result<OpenPort>, now: Instant) {
        if let Some(info) = self.port.opened(opened, now) {
            self.line.clear(&self.stats);
            if let Some(t) = &mut self.turnaround {
                // The switch was taken off with the port.
                t.reset();
            }
            let timing = self.line.port_opened(&info);
            self.port.tell_open(&info, &timing);
            self.stats.add(&self.stats.serial_opens, 1);
        }
    }

    /// The port failed or its far end went away: answer everything waiting on it, and
    /// reopen with backoff. A request that had begun to go out gets 0x0B, as for a
    /// timeout: it may have reached the device and acted, and no answer came. One whose
    /// bytes never left (held by flow control, or queued) gets 0x0A: there is no path
    /// to the device, and it cannot have acted.
    fn port_lost(&mut self, why: &str, now: Instant) {
        // Closing the port drops its switch, which leaves the transmitter off.
        if let Some(t) = &mut self.turnaround {
            t.abort();
        }
        self.port.lost(why, now);
        self.line.clear(&self.stats);
        for f in self.in_flight.take_all() {
            self.line.retire(f.tid, now);
            let why = if self.out.withdraw(f.tid) {
                Refusal::Unavailable
            } else {
                Refusal::TargetFailed
            };
            f.req.answer_exception(why, &self.stats);
        }
        self.out.clear();
        self.flush_queue(Refusal::Unavailable);
    }

    fn start_draining(&mut self) {
        if !self.draining {
            debug!(
                in_flight = self.in_flight.len(),
                queued = self.sched.queued(),
                "relay draining"
            );
            self.draining = true;
            self.flush_queue(Refusal::Unavailable);
            for req in self.paced.take_all() {
                req.answer_backed_off(&self.stats);
            }
        }
    }

    /// `cmd`, received at `now`.
    fn on_command(&mut self, cmd: Command, now: Instant) {
        match cmd {
            Command::Attach { conn, notifier } => {
                self.masters.attach(conn, notifier);
                self.telemetry.masters(self.masters.len());
            }
            Command::Priority { conn, class } => self.sched.set_class(conn, class),
            Command::Detach { conn } => {
                self.masters.detach(conn);
                self.sched.detach(conn);
                self.telemetry.masters(self.masters.len());
            }
            Command::Retune {
                relay,
                units,
                traffic,
            } => {
                self.in_flight.retune(&relay, &units);
                self.telemetry.set_traffic(traffic);
                self.cfg = *relay;
            }
            Command::Request { conn, adu, ticket } => self.on_request(conn, adu, ticket, now),
        }
    }

    /// A master's request: answered at once (a broadcast that cannot be one, no path,
    /// a backed-off unit, a reply in the cache), joined to an identical read waiting
    /// for the line, or queued.
    fn on_request(&mut self, conn: ConnId, adu: Adu, ticket: Ticket, now: Instant) {
        self.stats.add(&self.stats.requests, 1);
        self.telemetry.request(adu.unit());
        let mut req = Pending::new(conn, adu, ticket, now);
        let unit = req.adu.unit();
        if self.line.not_broadcast(&req.adu) {
            debug!(
                conn,
                fc = req.adu.function(),
                "a broadcast (unit 0) cannot carry this function: exception 0x01"
            );
            req.answer_exception(Refusal::NotBroadcast, &self.stats);
            return;
        }
        if req.acts() {
            self.cache.acted_on(unit);
        }
        if self.draining || !self.port.is_open() {
            req.answer_exception(Refusal::Unavailable, &self.stats);
            return;
        }
        if let Some(reply) = self.cached(&req, now) {
            self.stats.add(&self.stats.served_from_cache, 1);
            req.deliver(&reply);
            return;
        }
        if self.in_flight.backed_off(unit, now) {
            self.pace_backed_off(req);
            return;
        }
        req.cache_stamp = self.cache.stamp(unit);
        // A full queue refuses the request of the master holding the most of it (the
        // scheduler's fair share).
        let joins = self.sched.joins();
        let admitted = self.sched.push(req);
        self.stats
            .add(&self.stats.coalesced, self.sched.joins() - joins);
        match admitted {
            Admitted::Queued | Admitted::Joined => {}
            Admitted::Displaced(refused) => {
                debug!(
                    conn = refused.conn(),
                    "queue full: 0x06 to the master holding the most of it, for conn {conn}"
                );
                refused.answer_exception(Refusal::Busy, &self.stats);
            }
            Admitted::Refused(req) => {
                req.answer_exception(Refusal::Busy, &self.stats);
            }
        }
    }

    /// The cached reply that may answer `req`: none while its master has a request
    /// that acts on the unit still waiting for the line (the read must see it).
    fn cached(&self, req: &Pending, now: Instant) -> Option<Adu> {
        let key = req.read_key()?;
        let reply = self.cache.get(&key, now)?;
        (!self.sched.acts_waiting(req.conn(), key.unit)).then(|| reply.clone())
    }

    /// Answers every queued request (and every one waiting to be resent) with the
    /// exception for `why`.
    fn flush_queue(&mut self, why: Refusal) {
        for req in self.sched.drain_all() {
            req.answer_exception(why, &self.stats);
        }
    }

    /// Puts queued requests on the line while it has room: fewer than `max_in_flight`
    /// outstanding (MBAP), or none outstanding, the inter-frame gap passed and no byte
    /// waiting to be read (RTU/ASCII). A request for a backed-off unit is answered
    /// 0x0B instead.
    fn dispatch(&mut self, now: Instant) {
        while self.port.is_open()
            && self
                .line
                .has_room(self.in_flight.len(), self.tx_busy(), now)
            && self.sched.has_waiting()
            && !self.input_waiting()
        {
            let Some(req) = self.sched.next() else {
                break;
            };
            if req.attempts == 0 {
                let class = self.sched.class_of(&req);
                self.telemetry
                    .waited(class, now.saturating_duration_since(req.came));
            }
            if self.in_flight.backed_off(req.adu.unit(), now) {
                self.pace_backed_off(req);
                continue;
            }
            self.send(req, now);
        }
    }

    /// Bytes are still being written, or have not yet left the port.
    fn tx_busy(&self) -> bool {
        !self.out.is_empty() || self.port.drain.is_some()
    }

    /// RTU/ASCII: has the port received bytes the relay has not read yet? Then the
    /// device is talking, and a request now would go over it (on RS-485, collide with
    /// it): the bytes are read first, and the gap counts from them.
    fn input_waiting(&self) -> bool {
        self.line.is_serial() && self.port.input_waiting()
    }

    fn send(&mut self, req: Pending, now: Instant) {
        let tid = self.line.allocate(now);
        let pause = self.in_flight.policy(req.adu.unit()).pause;
        self.line.pause_after(pause);
        let bytes = self.line.encode(&req.adu, tid, now, &self.stats);
        self.telemetry.sent(req.conn(), &req.adu, tid, &bytes, now);
        self.out.push(tid, bytes);
        if req.acts() {
            // Reads sent before it may be answered after it was sent: not kept.
            self.cache.acted_on(req.adu.unit());
        }
        if self.line.is_broadcast(&req.adu) {
            self.stats.add(&self.stats.broadcasts, 1);
            req.broadcast_sent(self.cfg.broadcast_reply);
            return;
        }
        // The response time counts from when the request has left: behind whatever is
        // still waiting to be written.
        let queued = self.port.wire_time(self.out.len());
        self.in_flight.start(tid, req, now, queued);
    }

    /// Switches the RS-485 transmitter as the turnaround says (docs/rs485.md): on when
    /// bytes wait to be written (only while no request awaits its reply: `dispatch`
    /// sends one at a time), a look at the port's transmitter when due, off once the
    /// last stop bit has left. A switch that fails loses the port: its requests get
    /// their exception, and it is reopened (the switch taken afresh) with backoff.
    fn steer(&mut self, now: Instant) {
        if !self.port.is_open() {
            return;
        }
        // Each pass switches, or looks and moves on (a look that finds the
        // transmitter still busy sets the next one later than now): a few passes are
        // all one turn of the loop can take.
        for _ in 0..6 {
            let waiting = !self.out.is_empty();
            let Some(t) = &mut self.turnaround else {
                return;
            };
            let act = if waiting {
                t.begin(now)
            } else if t.sending() {
                // Its frame was withdrawn before a byte of it was written.
                t.abort()
            } else {
                None
            };
            let Some(a) = act.or_else(|| t.due(now)) else {
                return;
            };
            let late = t.late_by(now);
            match a {
                turnaround::Act::Look => {
                    let empty = self.port.transmitter_empty();
                    t.looked(empty.ok(), now);
                }
                turnaround::Act::On | turnaround::Act::Off => {
                    let on = a == turnaround::Act::On;
                    if let Err(e) = self.port.transmit(on) {
                        let what = if on { "on" } else { "off" };
                        let why = format!("could not switch the RS-485 transmitter {what}: {e}");
                        self.port_lost(&why, now);
                        return;
                    }
                    if on {
                        t.switched_on(Instant::now());
                    }
                    match late {
                        Some(late) if !on => tracing::trace!(
                            us = late.as_micros() as u64,
                            "transmitter off after the last stop bit could have left"
                        ),
                        _ => tracing::trace!(on, "transmitter switched"),
                    }
                }
            }
        }
    }

    /// Switches the transmitter off now if it is on (where the gateway switches it).
    fn switch_off(&mut self, now: Instant) {
        let Some(t) = &mut self.turnaround else {
            return;
        };
        if t.abort().is_some() {
            if let Err(e) = self.port.transmit(false) {
                let why = format!("could not switch the RS-485 transmitter off: {e}");
                self.port_lost(&why, now);
            }
        }
    }

    /// Waits for the bytes written to leave the port, off the runtime's thread, so the
    /// reply timer and the inter-frame gap start from the last byte on the wire.
    fn start_drain(&mut self, now: Instant) {
        if let Err(e) = self.port.start_drain() {
            debug!("tcdrain unavailable ({e}): timing from the write");
            if let Some(t) = &mut self.turnaround {
                t.drained(now);
            }
            self.drained(now);
        }
    }

    fn drained(&mut self, now: Instant) {
        let left = self.line.drained(now, &self.stats);
        self.in_flight.restart(left);
    }

    fn take_frames(&mut self, now: Instant) {
        let mut all = std::mem::take(&mut self.seen);
        self.line
            .frames_into(self.in_flight.entries(), now, &self.stats, &mut all);
        for seen in all.drain(..) {
            match seen {
                Seen::Frame(frame, at) => self.on_frame(frame, at, now),
                Seen::Corrupt(tid) => {
                    if let Some(f) = self.in_flight.take(tid) {
                        // What failed its check may be an echo or noise over the start
                        // of the real reply, which can still come: the line keeps the
                        // guard it keeps after a timeout, so that reply never meets
                        // the next request (docs/reliability.md "RTU and ASCII", 3).
                        let hold = self.in_flight.hold_after_timeout(&f);
                        self.line.timed_out(now, hold, &self.stats);
                        self.failed(f, Failure::Corrupt, now);
                    }
                }
            }
        }
        self.seen = all;
    }

    /// `frame`, taken off the line at `at` (its last byte read), handled `now`.
    fn on_frame(&mut self, frame: Adu, at: Instant, now: Instant) {
        let tid = frame.tid();
        // The line has checked unit, function code and shape against this request.
        if let Some(f) = self.in_flight.answered(tid, at) {
            // Kept reserved a while: a second answer with this id is recognised as
            // ours and dropped, never broadcast.
            self.line.retire(tid, now);
            self.stats.add(&self.stats.replies, f.req.served());
            if let Some(key) = f.req.read_key() {
                self.cache.put(key, f.req.cache_stamp, &frame, now);
            }
            // When it left: its deadline is its response timeout after that.
            let left = f.deadline.checked_sub(f.timeout).unwrap_or(now);
            let wire = self
                .telemetry
                .wants_frames()
                .then(|| self.line.on_wire(&frame));
            let (conn, asked) = (f.req.conn(), &f.req.adu);
            if let Some(wire) = &wire {
                self.telemetry.taken(conn, asked, &frame, wire, at);
            }
            self.telemetry
                .replied(conn, asked, &frame, wire.as_deref(), (left, now));
            self.tell_learned(asked.unit());
            f.req.deliver(&frame);
            return;
        }
        let unsolicited = self.line.unsolicited(tid);
        self.line
            .answered_nothing(matches!(unsolicited, Unsolicited::Late), now);
        match unsolicited {
            Unsolicited::Late => {
                self.stats.add(&self.stats.late_replies, 1);
                self.traffic("late reply, dropped", &frame, at);
                debug!(
                    tid,
                    "late reply dropped (its request timed out or was answered already): {:?}",
                    frame
                );
            }
            Unsolicited::Notification => {
                let what = match self.cfg.notifications {
                    crate::config::Notifications::Drop => "dropped (notifications = drop)",
                    crate::config::Notifications::Broadcast => "broadcast to every master",
                };
                self.traffic(what, &frame, at);
                self.masters.notification(frame, &self.stats)
            }
        }
    }

    /// `unit`'s learned timeout, if it has one, as it is now, for the metrics.
    fn tell_learned(&self, unit: u8) {
        if let Some(l) = self.in_flight.learned(unit) {
            let why = learn::Why::ALL.iter().position(|w| *w == l.why());
            let u = self.telemetry.metrics.unit(unit);
            u.set_learned(l.timeout(), why.unwrap_or(0));
        }
    }

    /// The traffic log's line, and the capture's packet, for a frame that answers
    /// nothing on the line, taken off it at `at`.
    fn traffic(&self, what: &str, frame: &Adu, at: Instant) {
        if self.telemetry.wants_frames() {
            let wire = self.line.on_wire(frame);
            self.telemetry.unsolicited(what, frame, &wire, at);
        }
    }
}
