//! The relay's loop: the one task that owns the line (docs/design.md §1, §5), wiring its
//! parts together and deciding nothing they can decide themselves.
//!
//! Connections talk to it over a channel ([`RelayHandle`], `command.rs`); it owns
//! every part below, so nothing here is locked. Each turn it pets the watchdog
//! (`watchdog.rs`), opens the port when due (`crate::line::port::lifecycle`), puts requests on the line
//! while it has room (`scheduler.rs` picks, `line/` encodes, `outgoing.rs` buffers,
//! `inflight.rs` times), then waits for one event (`event.rs`): a command, bytes from
//! the port, room to write, the end of a drain, the nearest timer, or shutdown. Bytes
//! read go to the framing (`line/`), whose frames the in-flight table matches to
//! their requests (answered through `pending.rs`) or not (late, or a notification for
//! `masters.rs`); requests past their deadline are resent or answered 0x0B as
//! `inflight.rs` decides.
//!
//! This file builds the loop and runs its turn; the loop's other jobs are each in a
//! file of their own: what comes in and goes onto the line (`admit.rs`), the bytes
//! going out and the RS-485 transmitter (`transmit.rs`), the frames coming back
//! (`replies.rs`), failures (`failures.rs`), the port opened or lost and the drain at
//! shutdown (`opening.rs`).

mod admit;
mod cache;
mod command;
mod event;
mod failures;
mod ids;
mod inflight;
mod learn;
mod line;
mod masters;
mod opening;
mod outgoing;
mod pending;
mod replies;
mod scheduler;
mod telemetry;
pub(crate) mod tids;
mod transmit;
mod turnaround;
pub(crate) mod watchdog;

use crate::config::{LineConfig, RelayConfig, SerialConfig};
use crate::line::port;
use crate::line::port::lifecycle::Lifecycle;
use crate::line::woken::Woken;
use crate::ops::metrics::LineMetrics;
use crate::ops::stats::Stats;
use cache::Cache;
#[cfg(test)]
pub(crate) use command::channel;
use command::Commands;
pub use command::{Command, ConnId, RelayHandle};
use event::Event;
use inflight::{InFlight, Paced};
use line::{LineFraming, Seen};
use masters::Masters;
use outgoing::Outgoing;
use pending::{Pending, Spare};
use scheduler::Scheduler;
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
    /// The boxes of requests answered, for the next requests.
    spare: Spare,
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
        let line = LineConfig {
            serial,
            relay: cfg,
            ..LineConfig::default()
        };
        Self::build(&line, port, false, traffic, stats, shutdown)
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
        let port: Box<dyn port::Port> = match &line.tcp {
            Some(addr) => {
                let port = port::tcp::TcpPort::new(addr.clone()).with_tls(line.tcp_tls.clone());
                Box::new(port)
            }
            None => Box::new(port::serial::SerialPort::new(line.serial.clone())),
        };
        let stream = line.tcp.is_some();
        Self::build(line, port, stream, traffic, stats, shutdown)
    }

    /// The relay of `line` (its units with settings of their own resolved once, here).
    fn build(
        config: &LineConfig,
        transport: Box<dyn port::Port>,
        stream: bool,
        traffic: bool,
        stats: Arc<Stats>,
        shutdown: CancellationToken,
    ) -> (Self, RelayHandle) {
        let (handle, rx) = command::channel();
        let now = Instant::now();
        let (cfg, serial, units) = (
            config.relay.clone(),
            config.serial.clone(),
            &config.unit_tables,
        );
        let line = LineFraming::new(&cfg, &serial, stream, now);
        // Only on a bus of units (RTU/ASCII): backing off the CIE-M10, the one unit of
        // an MBAP line, would gain the others nothing.
        let in_flight = InFlight::new(&cfg, units, cfg.unit_backoff && line.is_serial());
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
                crate::line::port::kind::wire_time(&serial, 1),
            )
        });
        let relay = Relay {
            sched: Scheduler::new(cfg.queue_depth, cfg.coalesce),
            cache: Cache::new(Duration::from_millis(cfg.cache_ms)),
            spare: Spare::default(),
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
    pub(crate) fn with_tap(mut self, tap: crate::ops::capture::Tap) -> Self {
        self.telemetry.tap = tap;
        self
    }

    /// The line's numbers as the relay keeps them (`crate::ops::metrics`), for the metrics
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
        let mut timer = crate::line::port::serial::PreciseTimer::new()
            .inspect_err(|e| debug!("no timerfd ({e}): timers to the millisecond"))
            .ok();
        // One wait for shutdown for the relay's life: made afresh each turn of the
        // loop, it would register with the token and unregister again every event;
        // and polled only once the token woke it (`crate::line::woken`).
        let mut shutdown = Woken::new(self.shutdown.clone().cancelled_owned());
        // The clock as the last turn ended. On a line of MBAP frames, which keeps no
        // gap and times nothing before a write to the microsecond, the next turn starts
        // from it (its work since is a few microseconds of ours): a clock read less
        // each turn. RTU and ASCII read it afresh for their gaps, and so does a line
        // whose RS-485 transmitter the gateway switches, for its delays.
        let carry = !self.line.is_serial() && self.turnaround.is_none();
        let mut ended: Option<Instant> = None;
        loop {
            let now = match ended.take() {
                Some(at) if carry => at,
                _ => Instant::now(),
            };
            let now = self.before_wait(now);
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
                now: polled,
                timer: timer.as_mut(),
                shutdown: (!self.draining).then_some(&mut shutdown),
            };
            let event = event::next(&mut self.port, sources, &mut rbuf).await;
            let now = Instant::now();
            self.after_event(event, &rbuf, polled, now);
            ended = Some(now);
        }
        debug!("relay stopped");
    }

    /// A turn's work before its wait, from `now`: the watchdog petted, the port
    /// opened if due, requests dispatched and written while the port takes them at
    /// once. The clock after the last write.
    fn before_wait(&mut self, mut now: Instant) -> Instant {
        if let Some(w) = &mut self.watchdog {
            w.pet(now);
        }
        // The line keeps the bytes it drops only while a capture wants them.
        self.line.set_tape(self.telemetry.capturing());
        self.open_if_due(now);
        self.dispatch(now);
        // What was dispatched is written in this turn when the port takes it at once,
        // not in a turn of its own: one pass of the loop less a transaction.
        let mut wrote = false;
        while let Some(after) = self.write_now(now) {
            (now, wrote) = (after, true);
            self.dispatch(now);
        }
        if wrote {
            // As the turn of a write would have: the gauges, and the line busy from
            // now.
            self.tell(now);
        }
        now
    }

    /// The turn's event handled `now`, then only what it can have changed: frames
    /// only from bytes read or held (a command, a write or a timer adds none to an
    /// MBAP line's empty decoder), deadlines and paced answers only once due (about
    /// 300 instructions a transaction: docs/performance.md "A transaction on a quiet
    /// line").
    fn after_event(&mut self, event: Event, rbuf: &[u8], polled: Instant, now: Instant) {
        let read = matches!(event, Event::Read(Ok(n)) if n > 0);
        self.on_event(event, rbuf, polled, now);
        if read || self.line.may_frame() {
            self.take_frames(now);
        }
        if self.in_flight.next_deadline().is_some_and(|d| d <= now) {
            self.expire(now);
        }
        if self.paced.next_due().is_some_and(|d| d <= now) {
            self.answer_paced(now);
        }
        self.tell(now);
    }

    /// What the turn's wait brought, handled `now`: `rbuf` holds the bytes read, and
    /// `polled` is when a write's wait began.
    fn on_event(&mut self, event: Event, rbuf: &[u8], polled: Instant, now: Instant) {
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
            Event::NodeChanged => self.port.retry_now(now),
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
}
