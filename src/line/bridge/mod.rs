//! The line whose device is the master (docs/design.md §4.2): requests that a serial
//! master (a CIE-M10 in master mode, an RTU PLC or HMI) puts on the line go to the
//! Modbus/TCP slave their unit routes to, and the replies come back on the line.
//!
//! - `requests`: the requests off the lossy line, the replies in its framing (pure);
//! - `routing`: routes, ids, what is outstanding, deadlines, answers (plain data, time
//!   passed in);
//! - `slave`: one task per route holding its TCP connection;
//! - `make`: the line made from its configuration, its routes bound;
//! - this file: the loop that owns the serial port and wires them.

mod make;
pub(crate) mod requests;
pub(crate) mod routing;
pub(crate) mod slave;

use crate::config::master::MasterLine;
use crate::config::{Framing, RelayConfig, SerialConfig};
use crate::frame::hex::Hex;
use crate::frame::Adu;
use crate::line::port::lifecycle::{Lifecycle, State};
use crate::line::port::{watch, OpenPort, Port};
use crate::line::relay::watchdog::Watchdog;
use crate::ops::capture::packet::{Dir, Packet, Part};
use crate::ops::capture::Tap;
use crate::ops::metrics::LineMetrics;
pub(crate) use make::{start, MasterLineParts};
use requests::{encode_reply, Requests};
use routing::{Action, Routing, RoutingCounts, UnitTally};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio::time::{sleep_until, Instant};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

/// Why the master line could not start.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    /// A passive route's listening address could not be bound.
    #[error("cannot listen for the slave of route {route} on {addr}: {error}")]
    Bind {
        /// The route's index, in the order of the file.
        route: usize,
        /// The address as configured.
        addr: String,
        /// What the system said.
        error: std::io::Error,
    },
}

/// The line's timing: the pause that ends a frame, and the gap after which a partial
/// one is dropped.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Timing {
    /// Silence that ends a frame: 3.5 characters (at least the adapter's latency).
    pub(crate) pause: Duration,
    /// MBAP: silence after which a partial frame is discarded.
    pub(crate) frame_gap: Duration,
    /// The line's speed, for the log.
    pub(crate) baud: u32,
}

impl Timing {
    /// A line's timing from its `serial` and `relay` tables.
    pub(crate) fn of_line(serial: &SerialConfig, relay: &RelayConfig) -> Self {
        // Taken before the port opens: its kind from the path (its device number).
        let kind = crate::line::port::serial::of_path(&serial.path);
        let port = crate::line::port::kind::PortInfo::plain(kind);
        Self {
            pause: crate::line::port::kind::silence(serial, &port),
            frame_gap: Duration::from_millis(relay.frame_gap_ms),
            baud: serial.baud_rate,
        }
    }
}

/// How a reload reaches a running master line.
#[derive(Debug, Clone)]
pub(crate) struct MasterHandle(mpsc::UnboundedSender<MasterLine>);

impl MasterHandle {
    /// The routes' timeouts as `line` gives them now; `Err` when the line has stopped.
    pub(crate) fn retune(&self, line: MasterLine) -> Result<(), ()> {
        self.0.send(line).map_err(|_| ())
    }
}

/// A master line ready to run: its routes' connections started (a passive route's
/// address bound), its serial port not yet open.
pub(crate) struct MasterLineTask {
    port: Box<dyn Port>,
    line: Bridge,
    events: mpsc::Receiver<slave::SlaveEvent>,
    retunes: mpsc::UnboundedReceiver<MasterLine>,
    slaves_stop: CancellationToken,
    tracker: tokio_util::task::TaskTracker,
}

impl MasterLineTask {
    /// Runs the line until `shutdown`: opens its port, and reopens it with backoff
    /// when it is lost, as every line does (`crate::line::port::lifecycle`); at shutdown
    /// answers what it holds first. The counts at the end.
    pub(crate) async fn run(self, shutdown: CancellationToken) -> RoutingCounts {
        let MasterLineTask {
            port,
            mut line,
            mut events,
            mut retunes,
            slaves_stop,
            tracker,
        } = self;
        let mut port = Lifecycle::new(port, line.timing.baud, Instant::now())
            .meanwhile("the serial master is not heard meanwhile");
        loop {
            let now = Instant::now();
            if let Some(opened) = port.open_if_due(now) {
                line.opened(&mut port, opened, now);
            }
            let State::Open(link) = &mut port.state else {
                match line
                    .wait_for_port(&mut port, (&mut events, &mut retunes), &shutdown)
                    .await
                {
                    Waited::Stop => break,
                    Waited::Opened(opened) => line.opened(&mut port, opened, Instant::now()),
                    Waited::Due => {}
                    Waited::NodeChanged => port.retry_now(Instant::now()),
                }
                continue;
            };
            match line
                .serve(link, (&mut events, &mut retunes), &shutdown)
                .await
            {
                Ok(()) => break,
                Err(e) => {
                    let now = Instant::now();
                    port.lost(&e.to_string(), now);
                    line.closed(now);
                }
            }
        }
        slaves_stop.cancel();
        tracker.close();
        tracker.wait().await;
        line.publish();
        line.said_stopped()
    }
}

/// How a wait for the port ended.
enum Waited {
    /// Shutdown.
    Stop,
    /// The open under way finished.
    Opened(std::io::Result<OpenPort>),
    /// The next attempt is due.
    Due,
    /// The port's device node may be back.
    NodeChanged,
}

/// What of the routing's counts is on the metrics board already.
#[derive(Debug, Default)]
struct Published {
    counts: RoutingCounts,
    dropped: u64,
}

struct Bridge {
    requests: Requests,
    routing: Routing,
    timing: Timing,
    traffic: bool,
    framing: Framing,
    /// The line's packets, for the capture.
    tap: Tap,
    to_slaves: Vec<mpsc::UnboundedSender<Adu>>,
    /// systemd's watchdog, when this line pets it.
    watchdog: Option<Watchdog>,
    /// The line's numbers on the metrics board (docs/watching.md), and how far
    /// they are published.
    metrics: Arc<LineMetrics>,
    published: Published,
}

impl Bridge {
    /// The counts at the end, said in the log.
    fn said_stopped(&self) -> RoutingCounts {
        let c = self.routing.counts;
        info!(
            requests = c.requests,
            forwarded = c.forwarded,
            replies = c.replies,
            timeouts = c.timeouts,
            unavailable = c.unavailable,
            late = c.late,
            bad_replies = c.bad_replies,
            broadcasts = c.broadcasts,
            broadcasts_refused = c.broadcasts_refused,
            refused = c.refused,
            dropped_bytes = self.requests.dropped(),
            "master line stopped"
        );
        c
    }

    /// Shutdown: no new request is taken; those held are answered first.
    fn drain(&mut self) {
        self.routing.close();
        if !self.routing.idle() {
            debug!("stopping: answering the requests held first");
        }
    }

    /// Bytes read off the line: counted, taped, and what requests they complete.
    fn heard(&mut self, bytes: &[u8]) -> Vec<Action> {
        if self.traffic {
            debug!("serial rx {}", Hex(bytes));
        }
        let n = bytes.len();
        self.metrics
            .stats
            .add(&self.metrics.stats.serial_bytes_in, n as u64);
        // A capture begun while the loop waited has these bytes too.
        self.requests.set_tape(self.tap.on());
        self.requests.push(bytes);
        self.take(false)
    }

    /// A pause on the line: RTU's 3.5 characters of silence end the frame.
    fn pause(&mut self) -> Vec<Action> {
        self.requests.pause();
        self.take(self.requests.codec().is_some())
    }

    /// The frame gap after a pause: what is buffered is a request or is dropped.
    fn gap(&mut self) -> Vec<Action> {
        let before = self.requests.dropped();
        let actions = self.take(true);
        let n = self.requests.dropped() - before;
        if n > 0 {
            debug!("discarded {n} bytes that made no request");
        }
        actions
    }

    /// Serves the open port until shutdown (`Ok`) or its loss (`Err`). At shutdown
    /// the requests held are answered first (their replies, or 0x0B at their
    /// deadlines; new ones get 0x0A), so the serial master is not cut off mid-request.
    async fn serve(
        &mut self,
        link: &mut OpenPort,
        (events, retunes): (
            &mut mpsc::Receiver<slave::SlaveEvent>,
            &mut mpsc::UnboundedReceiver<MasterLine>,
        ),
        shutdown: &CancellationToken,
    ) -> std::io::Result<()> {
        let mut buf = vec![0u8; 1024];
        let mut last_rx = Instant::now();
        let mut paused = true;
        let mut draining = false;
        loop {
            if draining && self.routing.idle() {
                return Ok(());
            }
            self.requests.set_tape(self.tap.on());
            let partial = self.requests.buffered() > 0;
            let deadline = self.routing.next_deadline().map(Instant::from_std);
            let pet_at = self.watchdog.as_ref().map(Watchdog::next);
            let actions = tokio::select! {
                _ = shutdown.cancelled(), if !draining => {
                    draining = true;
                    self.drain();
                    Vec::new()
                }
                r = link.reader.read(&mut buf) => match r {
                    Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                    Ok(n) => {
                        last_rx = Instant::now();
                        paused = false;
                        self.heard(&buf[..n])
                    }
                    Err(e) => return Err(e),
                },
                _ = sleep_until(last_rx + self.timing.pause), if partial && !paused => {
                    paused = true;
                    self.pause()
                }
                _ = sleep_until(last_rx + self.timing.frame_gap), if partial && paused => {
                    self.gap()
                }
                _ = sleep_until(deadline.unwrap_or_else(Instant::now)), if deadline.is_some() => {
                    self.routing.expire(std::time::Instant::now())
                }
                Some(ev) = events.recv() => self.event(ev),
                Some(routes) = retunes.recv() => {
                    self.routing.retune(&routes);
                    Vec::new()
                }
                _ = sleep_until(pet_at.unwrap_or_else(Instant::now)), if pet_at.is_some() => {
                    self.pet();
                    Vec::new()
                }
            };
            self.act(actions, Some(&mut link.writer)).await?;
            self.publish();
        }
    }

    /// The routing's counts since the last call onto the metrics board, each under the
    /// name a relay's line uses for the same thing (docs/watching.md).
    fn publish(&mut self) {
        let (now, was) = (self.routing.counts, self.published.counts);
        let s = &self.metrics.stats;
        let pairs = [
            (&s.requests, now.requests - was.requests),
            (&s.replies, now.replies - was.replies),
            (&s.timeouts, now.timeouts - was.timeouts),
            (&s.unavailable, now.unavailable - was.unavailable),
            (&s.late_replies, now.late - was.late),
            (&s.bad_frames, now.bad_replies - was.bad_replies),
            (&s.broadcasts, now.broadcasts - was.broadcasts),
            (
                &s.broadcasts_refused,
                now.broadcasts_refused - was.broadcasts_refused,
            ),
            (&s.bad_requests, now.refused - was.refused),
        ];
        for (counter, n) in pairs {
            s.add(counter, n);
        }
        let at = Instant::now();
        if now.replies > was.replies {
            self.metrics.replied_at(at);
        }
        for (unit, tally) in self.routing.take_tallies() {
            let u = self.metrics.unit(unit);
            match tally {
                UnitTally::Request => s.add(&u.requests, 1),
                UnitTally::Reply => s.add(&u.replies, 1),
                UnitTally::Timeout => self.metrics.timed_out(unit, at),
            }
        }
        let dropped = self.requests.dropped();
        s.add(
            &s.dropped_bytes,
            dropped.saturating_sub(self.published.dropped),
        );
        self.published = Published {
            counts: now,
            dropped,
        };
    }

    /// WATCHDOG=1 if it is due.
    fn pet(&mut self) {
        if let Some(w) = &mut self.watchdog {
            w.pet(Instant::now());
        }
    }

    /// While the port is closed (until its next attempt) or opening: follows the
    /// slaves (no port to answer on, but the routing still tracks them), the watchdog
    /// and a reload's timeouts, until the open ends, the attempt is due (or the port's
    /// node is back: then it is due now) or shutdown.
    async fn wait_for_port(
        &mut self,
        port: &mut Lifecycle,
        (events, retunes): (
            &mut mpsc::Receiver<slave::SlaveEvent>,
            &mut mpsc::UnboundedReceiver<MasterLine>,
        ),
        shutdown: &CancellationToken,
    ) -> Waited {
        let watch = &mut port.watch;
        let retry_at = match &port.state {
            State::Closed { retry_at } => Some(*retry_at),
            _ => None,
        };
        let mut opening = match &mut port.state {
            State::Opening(o) => Some(o),
            _ => None,
        };
        loop {
            let pet_at = self.watchdog.as_ref().map(Watchdog::next);
            let open = async {
                match opening.as_mut() {
                    Some(o) => o.await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = shutdown.cancelled() => return Waited::Stop,
                r = open => return Waited::Opened(r),
                _ = sleep_until(retry_at.unwrap_or_else(Instant::now)), if retry_at.is_some() => return Waited::Due,
                _ = watch::changed(watch), if retry_at.is_some() && watch.is_some() => return Waited::NodeChanged,
                _ = sleep_until(pet_at.unwrap_or_else(Instant::now)), if pet_at.is_some() => self.pet(),
                Some(ev) = events.recv() => {
                    let actions = self.event(ev);
                    let _ = self.act(actions, None).await;
                    self.publish();
                }
                Some(routes) = retunes.recv() => self.routing.retune(&routes),
            }
        }
    }

    /// An open finished at `now`: open, the line starts afresh and says so; or not,
    /// and the next attempt is due later.
    fn opened(&mut self, port: &mut Lifecycle, opened: std::io::Result<OpenPort>, now: Instant) {
        let m = &self.metrics;
        if let Some(info) = port.opened(opened, now) {
            port.tell_open(&info, "the device is the master");
            m.port_open.store(1, Ordering::Relaxed);
            m.port_up(now);
            m.stats.add(&m.stats.serial_opens, 1);
        } else if let Some(since) = port.down_since() {
            m.port_down(since);
        }
    }

    /// The port was lost: what was read of a request is dropped, and what was held
    /// for the serial master is never answered (it gave up on it).
    fn closed(&mut self, now: Instant) {
        self.metrics.port_open.store(0, Ordering::Relaxed);
        self.metrics.port_down(now);
        self.requests.clear();
        self.routing.serial_lost();
        self.publish();
    }

    /// Every whole request decoded so far, into the routing.
    fn take(&mut self, quiet: bool) -> Vec<Action> {
        let mut out = Vec::new();
        let now = Instant::now();
        while let Some(req) = self.requests.next(quiet) {
            debug!(
                unit = req.unit,
                "request from the serial master: {}",
                Hex(&req.pdu)
            );
            if self.tap.on() {
                self.capture(&req, &req.pdu, Dir::In, now);
            }
            out.extend(self.routing.request(req, std::time::Instant::now()));
        }
        for d in self.requests.take_drops() {
            let p = Packet::dropped(Some(self.framing), d.reason, d.bytes, d.whole, d.detail);
            // What comes off a master's line is a request.
            let p = p.shown_as(Part::Query);
            self.tap.send(p, d.at.unwrap_or(now));
        }
        out
    }

    /// A request from the serial master (`Dir::In`) or the reply to it (`pdu`,
    /// `Dir::Out`) as the line carries it, for the capture.
    fn capture(&self, req: &requests::Incoming, pdu: &[u8], dir: Dir, at: Instant) {
        let wire = encode_reply(self.requests.codec(), req, pdu);
        let adu = Adu::build(req.tid.unwrap_or(0), req.unit, pdu);
        let (role, label) = match dir {
            Dir::In => (Part::Query, "serial->gw"),
            _ => (Part::Reply, "gw->serial"),
        };
        let mut p = Packet::line_frame(self.framing, &adu, &wire, dir, role);
        p.span = crate::line::relay::span(&req.pdu);
        p.label = label;
        self.tap.send(p, at);
    }

    fn event(&mut self, ev: slave::SlaveEvent) -> Vec<Action> {
        match ev {
            slave::SlaveEvent::Connecting(i) => {
                self.routing.connecting(i);
                Vec::new()
            }
            slave::SlaveEvent::Up(i) => self.routing.up(i),
            slave::SlaveEvent::Down(i) => self.routing.down(i),
            slave::SlaveEvent::Frame(i, adu) => {
                if self.traffic {
                    debug!(route = i, "slave rx {}", Hex(adu.as_bytes()));
                }
                self.routing.reply(i, &adu)
            }
        }
    }

    async fn act(
        &mut self,
        actions: Vec<Action>,
        mut writer: Option<&mut crate::line::port::Writer>,
    ) -> std::io::Result<()> {
        for a in actions {
            match a {
                Action::Send { route, adu } => {
                    if self.traffic {
                        debug!(route, "slave tx {}", Hex(adu.as_bytes()));
                    }
                    let _ = self.to_slaves[route].send(adu);
                }
                Action::Answer { request, pdu } => {
                    if self.tap.on() {
                        self.capture(&request, &pdu, Dir::Out, Instant::now());
                    }
                    let bytes = encode_reply(self.requests.codec(), &request, &pdu);
                    if self.traffic {
                        debug!("serial tx {}", Hex(&bytes));
                    }
                    if let Some(w) = writer.as_mut() {
                        w.write_all(&bytes).await?;
                        w.flush().await?;
                        let s = &self.metrics.stats;
                        s.add(&s.serial_bytes_out, bytes.len() as u64);
                    }
                }
            }
        }
        Ok(())
    }
}
