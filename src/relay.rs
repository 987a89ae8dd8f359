//! The one task that owns the serial line (design.md §1, §5).
//!
//! Connections talk to it over a channel ([`RelayHandle`]); it owns the port, the
//! queues, the in-flight table and the decoder, so nothing here is locked. One loop
//! waits on: commands from connections, bytes from the port, room to write to the
//! port, the end of a write (`tcdrain`, RTU/ASCII), the nearest timer (a response
//! deadline, the frame gap or silence, the inter-frame gap, the next reopen, the next
//! systemd watchdog ping), and shutdown.
//!
//! What differs between framings (MBAP, RTU, ASCII) is behind [`line::Line`]; the
//! queues, round-robin, timeouts, retries, unit backoff and exceptions are here, for
//! all of them.

mod line;

use crate::config::{BroadcastReply, Notifications, RelayConfig, SerialConfig};
use crate::frame::hex::Hex;
use crate::frame::pdu::{self, exception};
use crate::frame::Adu;
use crate::notify;
use crate::serial::{self, Backoff};
use crate::stats::Stats;
use bytes::Bytes;
use line::{Line, Seen, Unsolicited};
use std::collections::{HashMap, VecDeque};
use std::os::fd::{AsRawFd, RawFd};
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt, ReadHalf, WriteHalf};
use tokio::sync::{mpsc, OwnedSemaphorePermit};
use tokio::time::Instant;
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

/// Identifies one master's TCP connection.
pub type ConnId = u64;

/// Room kept in each connection's channel for notifications, beyond its replies.
pub const NOTIFICATION_SLACK: usize = 16;

/// A frame on its way to one master. The permit, when present, is the master's
/// pipelining slot (`max_pending_per_connection`): it is freed once the frame is
/// written.
#[derive(Debug)]
pub struct Outbound {
    pub adu: Adu,
    pub permit: Option<OwnedSemaphorePermit>,
}

/// What connections tell the relay.
#[derive(Debug)]
pub enum Command {
    /// A master connected; its frames go to `tx`, whose capacity is
    /// `max_pending_per_connection + NOTIFICATION_SLACK`.
    Attach {
        conn: ConnId,
        tx: mpsc::Sender<Outbound>,
    },
    /// It went away: its queued requests are dropped, its late replies discarded.
    Detach { conn: ConnId },
    /// A request that passed the strict checks, with the master's own transaction id.
    Request {
        conn: ConnId,
        adu: Adu,
        permit: OwnedSemaphorePermit,
    },
}

/// The connections' side of the relay's channel.
#[derive(Debug, Clone)]
pub struct RelayHandle {
    tx: mpsc::UnboundedSender<Command>,
}

impl RelayHandle {
    /// Sends a command; gives it back if the relay has stopped.
    pub fn send(&self, cmd: Command) -> Result<(), Command> {
        self.tx.send(cmd).map_err(|e| e.0)
    }
}

struct Pending {
    conn: ConnId,
    adu: Adu,
    permit: OwnedSemaphorePermit,
    attempts: u32,
}

struct InFlight {
    tid: u16,
    deadline: Instant,
    req: Pending,
}

enum Port {
    Open {
        rd: ReadHalf<SerialStream>,
        wr: WriteHalf<SerialStream>,
        /// The port's descriptor, for `tcdrain` (valid while `rd` and `wr` live).
        fd: RawFd,
    },
    Closed {
        retry_at: Instant,
    },
}

/// Why a request on the line failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Failure {
    /// No reply in time.
    Timeout,
    /// A reply whose CRC or LRC failed, or that did not answer it (RTU/ASCII).
    Corrupt,
}

pub struct Relay {
    cfg: RelayConfig,
    serial: SerialConfig,
    traffic: bool,
    rx: mpsc::UnboundedReceiver<Command>,
    conns: HashMap<ConnId, mpsc::Sender<Outbound>>,
    queues: HashMap<ConnId, VecDeque<Pending>>,
    /// Connections with queued requests, in round-robin order.
    ring: VecDeque<ConnId>,
    /// The connection whose request went on the line last: a connection that starts
    /// waiting goes ahead of it, since it has just had its turn.
    last_served: Option<ConnId>,
    queued: usize,
    /// Requests to resend (reads after a timeout or a bad reply): ahead of the queues.
    retry: VecDeque<Pending>,
    in_flight: Vec<InFlight>,
    line: Line,
    /// `tcdrain` of the last write, running on the blocking pool (RTU/ASCII).
    drain: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
    units: Units,
    port: Port,
    backoff: Backoff,
    port_warned: bool,
    out: Outgoing,
    stats: Arc<Stats>,
    shutdown: CancellationToken,
    draining: bool,
    /// False once every [`RelayHandle`] is gone: `recv` would return at once forever.
    commands_open: bool,
    watchdog: Option<Watchdog>,
}

/// systemd's watchdog, pinged from the relay's own loop: if the loop wedges, the pings
/// stop and systemd restarts the gateway.
struct Watchdog {
    every: Duration,
    next: Instant,
}

impl Relay {
    /// A relay for this line, and the handle connections use to reach it.
    pub fn new(
        cfg: RelayConfig,
        serial: SerialConfig,
        traffic: bool,
        stats: Arc<Stats>,
        shutdown: CancellationToken,
    ) -> (Self, RelayHandle) {
        let (tx, rx) = mpsc::unbounded_channel();
        let now = Instant::now();
        let line = Line::new(&cfg, &serial, now);
        // Only on a bus of units (RTU/ASCII): backing off the CIE-M10, the one unit of
        // an MBAP line, would gain the others nothing.
        let units = Units::new(&cfg, cfg.unit_backoff && line.is_serial());
        let relay = Relay {
            cfg,
            serial,
            traffic,
            rx,
            conns: HashMap::new(),
            queues: HashMap::new(),
            ring: VecDeque::new(),
            last_served: None,
            queued: 0,
            retry: VecDeque::new(),
            in_flight: Vec::new(),
            line,
            drain: None,
            units,
            port: Port::Closed { retry_at: now },
            backoff: Backoff::new(Duration::from_millis(100), Duration::from_secs(2)),
            port_warned: false,
            out: Outgoing::default(),
            stats,
            shutdown,
            draining: false,
            commands_open: true,
            watchdog: None,
        };
        (relay, RelayHandle { tx })
    }

    /// Sends systemd WATCHDOG=1 from the loop every `every` (the first at once);
    /// `None` means no watchdog and no timer for it, so an idle relay sleeps.
    pub fn with_watchdog(mut self, every: Option<Duration>) -> Self {
        self.watchdog = every.map(|every| Watchdog {
            every,
            next: Instant::now(),
        });
        self
    }

    /// Runs until shutdown has been asked for and every request on the line has been
    /// answered or has timed out, or until every handle is gone.
    pub async fn run(mut self) {
        let mut rbuf = vec![0u8; 4096];
        loop {
            let now = Instant::now();
            self.pet_watchdog(now);
            self.open_if_due(now);
            self.dispatch(now);
            if self.draining && self.in_flight.is_empty() {
                break;
            }
            let wake = self.next_wake(now);
            let event = match &mut self.port {
                // Biased, bytes first: a timer that finds bytes waiting must not take
                // the line for quiet (a held reply would be refuted, a frame cut).
                Port::Open { rd, wr, .. } => tokio::select! {
                    biased;
                    r = rd.read(&mut rbuf) => Event::Read(r),
                    cmd = self.rx.recv(), if self.commands_open => Event::Command(cmd),
                    w = wr.write(self.out.pending()), if !self.out.is_empty() => Event::Wrote(w),
                    d = async { self.drain.as_mut().expect("guarded").await }, if self.drain.is_some() => Event::Drained(d),
                    _ = tokio::time::sleep_until(wake) => Event::Timer,
                    _ = self.shutdown.cancelled(), if !self.draining => Event::Shutdown,
                },
                Port::Closed { .. } => tokio::select! {
                    cmd = self.rx.recv(), if self.commands_open => Event::Command(cmd),
                    _ = tokio::time::sleep_until(wake) => Event::Timer,
                    _ = self.shutdown.cancelled(), if !self.draining => Event::Shutdown,
                },
            };
            let now = Instant::now();
            match event {
                Event::Command(Some(cmd)) => self.on_command(cmd),
                Event::Command(None) => {
                    self.commands_open = false;
                    self.start_draining();
                }
                Event::Shutdown => self.start_draining(),
                Event::Read(Ok(0)) => self.port_lost("end of file (the far end went away)", now),
                Event::Read(Ok(n)) => {
                    if self.traffic {
                        debug!(target: "mbgate::traffic", dir = "serial->gw", "{}", Hex(&rbuf[..n]));
                    }
                    self.stats.add(&self.stats.serial_bytes_in, n as u64);
                    self.line.received(&rbuf[..n], now, &self.stats);
                }
                Event::Read(Err(e)) => self.port_lost(&format!("read failed: {e}"), now),
                Event::Wrote(Ok(n)) => {
                    self.stats.add(&self.stats.serial_bytes_out, n as u64);
                    self.out.advance(n);
                    if self.out.is_empty() && self.line.is_serial() {
                        self.start_drain(now);
                    }
                }
                Event::Wrote(Err(e)) => self.port_lost(&format!("write failed: {e}"), now),
                Event::Drained(r) => {
                    self.drain = None;
                    if let Ok(Err(e)) | Err(e) = r.map_err(std::io::Error::other) {
                        debug!("tcdrain: {e}");
                    }
                    self.drained(now);
                }
                Event::Timer => {}
            }
            self.take_frames(now);
            self.expire(now);
        }
        debug!("relay stopped");
    }

    fn next_wake(&self, now: Instant) -> Instant {
        let mut wake = now + Duration::from_secs(3600);
        for f in &self.in_flight {
            wake = wake.min(f.deadline);
        }
        let waiting = !self.ring.is_empty() || !self.retry.is_empty();
        if let Some(w) = self.line.next_wake(now, waiting) {
            wake = wake.min(w);
        }
        if let Port::Closed { retry_at } = self.port {
            wake = wake.min(retry_at);
        }
        if let Some(w) = &self.watchdog {
            wake = wake.min(w.next);
        }
        wake
    }

    fn pet_watchdog(&mut self, now: Instant) {
        if let Some(w) = &mut self.watchdog {
            if now >= w.next {
                notify::watchdog();
                w.next = now + w.every;
            }
        }
    }

    fn is_open(&self) -> bool {
        matches!(self.port, Port::Open { .. })
    }

    fn open_if_due(&mut self, now: Instant) {
        let Port::Closed { retry_at } = self.port else {
            return;
        };
        if now < retry_at || self.draining {
            return;
        }
        match serial::open(&self.serial) {
            Ok(port) => {
                info!(path = %self.serial.path, baud = self.serial.baud_rate, "serial port open");
                let fd = port.as_raw_fd();
                let (rd, wr) = tokio::io::split(port);
                self.port = Port::Open { rd, wr, fd };
                self.backoff.reset();
                self.port_warned = false;
                self.line.clear(&self.stats);
                self.stats.add(&self.stats.serial_opens, 1);
            }
            Err(e) => {
                let delay = self.backoff.next_delay();
                if self.port_warned {
                    debug!(path = %self.serial.path, "serial port still unavailable: {e}");
                } else {
                    warn!(
                        path = %self.serial.path,
                        "serial port unavailable: {e}; retrying with backoff, answering 0x0A meanwhile"
                    );
                    self.port_warned = true;
                }
                self.port = Port::Closed {
                    retry_at: now + delay,
                };
            }
        }
    }

    /// The port failed or its far end went away: answer everything waiting on it, and
    /// reopen with backoff. A request that had begun to go out gets 0x0B, as for a
    /// timeout: it may have reached the device and acted, and no answer came. One whose
    /// bytes never left (held by flow control, or queued) gets 0x0A: there is no path
    /// to the device, and it cannot have acted.
    fn port_lost(&mut self, why: &str, now: Instant) {
        warn!(path = %self.serial.path, "serial port lost: {why}; reopening with backoff");
        self.port = Port::Closed {
            retry_at: now + self.backoff.next_delay(),
        };
        self.port_warned = true;
        self.line.clear(&self.stats);
        if let Some(d) = self.drain.take() {
            d.abort();
        }
        for f in std::mem::take(&mut self.in_flight) {
            self.line.retire(f.tid, now);
            let code = if self.out.withdraw(f.tid) {
                exception::GATEWAY_PATH_UNAVAILABLE
            } else {
                exception::GATEWAY_TARGET_FAILED
            };
            self.answer_exception(f.req, code);
        }
        self.out.clear();
        self.flush_queue(exception::GATEWAY_PATH_UNAVAILABLE);
    }

    fn start_draining(&mut self) {
        if !self.draining {
            debug!(
                in_flight = self.in_flight.len(),
                queued = self.queued,
                "relay draining"
            );
            self.draining = true;
            self.flush_queue(exception::GATEWAY_PATH_UNAVAILABLE);
        }
    }

    fn on_command(&mut self, cmd: Command) {
        match cmd {
            Command::Attach { conn, tx } => {
                self.conns.insert(conn, tx);
            }
            Command::Detach { conn } => {
                self.conns.remove(&conn);
                self.retry.retain(|r| r.conn != conn);
                if let Some(q) = self.queues.remove(&conn) {
                    self.queued -= q.len();
                    self.ring.retain(|&c| c != conn);
                }
            }
            Command::Request { conn, adu, permit } => {
                self.stats.add(&self.stats.requests, 1);
                let req = Pending {
                    conn,
                    adu,
                    permit,
                    attempts: 0,
                };
                if self.draining || !self.is_open() {
                    self.answer_exception(req, exception::GATEWAY_PATH_UNAVAILABLE);
                } else if self.units.backed_off(req.adu.unit(), Instant::now()) {
                    self.answer_backed_off(req);
                } else if self.queued >= self.cfg.queue_depth {
                    self.answer_exception(req, exception::SERVER_DEVICE_BUSY);
                } else {
                    let q = self.queues.entry(conn).or_default();
                    if q.is_empty() {
                        // Round-robin from its arrival: behind every connection still
                        // waiting for a turn, ahead of the one just served.
                        match self.ring.back() {
                            Some(&back) if Some(back) == self.last_served => {
                                self.ring.insert(self.ring.len() - 1, conn)
                            }
                            _ => self.ring.push_back(conn),
                        }
                    }
                    q.push_back(req);
                    self.queued += 1;
                }
            }
        }
    }

    /// Answers every queued request (and every one waiting to be resent) with `code`.
    fn flush_queue(&mut self, code: u8) {
        self.ring.clear();
        self.queued = 0;
        for req in std::mem::take(&mut self.retry) {
            self.answer_exception(req, code);
        }
        for (_, q) in std::mem::take(&mut self.queues) {
            for req in q {
                self.answer_exception(req, code);
            }
        }
    }

    /// The next request to put on the line: a resend first, then round-robin across
    /// connections.
    fn next_request(&mut self) -> Option<Pending> {
        if let Some(req) = self.retry.pop_front() {
            return Some(req);
        }
        loop {
            let conn = self.ring.pop_front()?;
            let Some(q) = self.queues.get_mut(&conn) else {
                continue;
            };
            let Some(req) = q.pop_front() else {
                continue;
            };
            if q.is_empty() {
                self.queues.remove(&conn);
            } else {
                self.ring.push_back(conn);
            }
            self.queued -= 1;
            self.last_served = Some(conn);
            return Some(req);
        }
    }

    /// Puts queued requests on the line while it has room: fewer than `max_in_flight`
    /// outstanding (MBAP), or none outstanding and the inter-frame gap passed
    /// (RTU/ASCII). A request for a backed-off unit is answered at once instead.
    fn dispatch(&mut self, now: Instant) {
        while self.is_open()
            && self
                .line
                .has_room(self.in_flight.len(), self.tx_busy(), now)
        {
            let Some(req) = self.next_request() else {
                break;
            };
            if self.units.backed_off(req.adu.unit(), now) {
                self.answer_backed_off(req);
                continue;
            }
            self.send(req, now);
        }
    }

    /// Bytes are still being written, or have not yet left the port.
    fn tx_busy(&self) -> bool {
        !self.out.is_empty() || self.drain.is_some()
    }

    fn send(&mut self, req: Pending, now: Instant) {
        let tid = self.line.allocate(now);
        let bytes = self.line.encode(&req.adu, tid, now);
        if self.traffic {
            debug!(target: "mbgate::traffic", dir = "gw->serial", conn = req.conn, "{}", Hex(&bytes));
        }
        self.out.push(tid, bytes);
        if self.line.is_broadcast(&req.adu) {
            self.broadcast_sent(req);
            return;
        }
        // The response time counts from when the request has left: behind whatever is
        // still waiting to be written (RTU/ASCII: restarted when the port has drained).
        let deadline = now
            + serial::wire_time(&self.serial, self.out.len())
            + Duration::from_millis(self.cfg.response_timeout_ms);
        self.in_flight.push(InFlight { tid, deadline, req });
    }

    /// A broadcast (unit 0, RTU/ASCII) is on its way: no device answers it. The master
    /// gets nothing, or the answer a device would have given (`broadcast_reply`).
    fn broadcast_sent(&mut self, req: Pending) {
        self.stats.add(&self.stats.broadcasts, 1);
        match self.cfg.broadcast_reply {
            // The permit goes with the request: the master may send another.
            BroadcastReply::None => drop(req),
            BroadcastReply::Echo => {
                let adu = Adu::build(req.adu.tid(), 0, &pdu::write_echo(req.adu.pdu()));
                self.deliver(req.conn, adu, Some(req.permit));
            }
        }
    }

    /// Waits for the bytes written to leave the port, off the runtime's thread, so the
    /// reply timer and the inter-frame gap start from the last byte on the wire.
    fn start_drain(&mut self, now: Instant) {
        let Port::Open { fd, .. } = &self.port else {
            return;
        };
        match serial::drain(*fd) {
            Ok(handle) => self.drain = Some(handle),
            Err(e) => {
                debug!("tcdrain unavailable ({e}): timing from the write");
                self.drained(now);
            }
        }
    }

    fn drained(&mut self, now: Instant) {
        let left = self.line.drained(&self.serial, now);
        let timeout = Duration::from_millis(self.cfg.response_timeout_ms);
        for f in &mut self.in_flight {
            f.deadline = left + timeout;
        }
    }

    fn take_frames(&mut self, now: Instant) {
        for seen in self.line.frames(&self.in_flight, now, &self.stats) {
            match seen {
                Seen::Frame(frame) => self.on_frame(frame, now),
                Seen::Corrupt(tid) => {
                    if let Some(i) = self.in_flight.iter().position(|f| f.tid == tid) {
                        let f = self.in_flight.swap_remove(i);
                        self.failed(f, Failure::Corrupt, now);
                    }
                }
            }
        }
    }

    fn on_frame(&mut self, frame: Adu, now: Instant) {
        let tid = frame.tid();
        if let Some(i) = self.in_flight.iter().position(|f| f.tid == tid) {
            // The line has checked unit, function code and shape against this request.
            let f = self.in_flight.swap_remove(i);
            // Kept reserved a while: a second answer with this id is recognised as
            // ours and dropped, never broadcast.
            self.line.retire(tid, now);
            self.units.answered(f.req.adu.unit());
            self.stats.add(&self.stats.replies, 1);
            let reply = frame.with_tid(f.req.adu.tid());
            self.deliver(f.req.conn, reply, Some(f.req.permit));
            return;
        }
        match self.line.unsolicited(tid) {
            Unsolicited::Late => {
                self.stats.add(&self.stats.late_replies, 1);
                debug!(
                    tid,
                    "late reply dropped (its request timed out or was answered already): {:?}",
                    frame
                );
            }
            Unsolicited::Notification => match self.cfg.notifications {
                Notifications::Drop => {
                    self.stats.add(&self.stats.notifications_dropped, 1);
                    debug!("unsolicited frame dropped: {:?}", frame);
                }
                Notifications::Broadcast => self.broadcast(frame),
            },
        }
    }

    /// Sends a device notification to every master with room for it; a master whose
    /// channel holds only room for its own replies misses it (counted).
    fn broadcast(&self, frame: Adu) {
        self.stats.add(&self.stats.notifications_broadcast, 1);
        for tx in self.conns.values() {
            let sent = tx.capacity() > self.cfg.max_pending_per_connection
                && tx
                    .try_send(Outbound {
                        adu: frame.clone(),
                        permit: None,
                    })
                    .is_ok();
            if !sent {
                self.stats.add(&self.stats.notifications_missed, 1);
            }
        }
    }

    fn expire(&mut self, now: Instant) {
        let mut i = 0;
        while i < self.in_flight.len() {
            if self.in_flight[i].deadline > now {
                i += 1;
                continue;
            }
            let f = self.in_flight.swap_remove(i);
            self.line.timed_out(now, &self.stats);
            if self.out.withdraw(f.tid) {
                // Flow control held it back (CTS low) the whole time: it never left,
                // and must not act on the device after the master was told 0x0B.
                warn!(
                    conn = f.req.conn,
                    "request could not be written in time (is CTS held low?)"
                );
            }
            self.failed(f, Failure::Timeout, now);
        }
    }

    /// A request on the line got no usable reply: resent if it may be (reads, or any
    /// request with `retry_writes`, up to `retries` times), else answered 0x0B. A
    /// timeout counts against its unit (a unit that keeps timing out is backed off).
    fn failed(&mut self, f: InFlight, why: Failure, now: Instant) {
        self.line.retire(f.tid, now);
        let unit = f.req.adu.unit();
        if why == Failure::Timeout {
            if let Some(interval) = self.units.timed_out(unit, now) {
                warn!(
                    unit,
                    "unit backed off for {interval:?}: its requests get 0x0B at once, then one probes it"
                );
                self.answer_exception(f.req, exception::GATEWAY_TARGET_FAILED);
                self.sweep_backed_off(unit);
                return;
            }
        }
        let function = f.req.adu.function();
        let may_retry = pdu::is_read(function) || self.cfg.retry_writes;
        if may_retry && f.req.attempts < self.cfg.retries && self.is_open() {
            debug!(
                conn = f.req.conn,
                attempt = f.req.attempts + 1,
                "{}; resending",
                match why {
                    Failure::Timeout => "no reply",
                    Failure::Corrupt => "a bad reply",
                }
            );
            self.stats.add(&self.stats.retries, 1);
            let mut req = f.req;
            req.attempts += 1;
            self.retry.push_back(req);
        } else {
            debug!(
                conn = f.req.conn,
                tid = f.req.adu.tid(),
                "{}: 0x0B",
                match why {
                    Failure::Timeout => "no reply in time",
                    Failure::Corrupt => "no good reply",
                }
            );
            self.answer_exception(f.req, exception::GATEWAY_TARGET_FAILED);
        }
    }

    /// A unit was just backed off: its waiting requests are answered now, so they never
    /// take the line from the healthy units.
    fn sweep_backed_off(&mut self, unit: u8) {
        let mut swept = Vec::new();
        for q in self.queues.values_mut() {
            let (gone, kept): (VecDeque<Pending>, VecDeque<Pending>) = std::mem::take(q)
                .into_iter()
                .partition(|r| r.adu.unit() == unit);
            *q = kept;
            swept.extend(gone);
        }
        self.queued -= swept.len();
        self.queues.retain(|_, q| !q.is_empty());
        let queues = &self.queues;
        self.ring.retain(|c| queues.contains_key(c));
        let (gone, kept) = std::mem::take(&mut self.retry)
            .into_iter()
            .partition(|r| r.adu.unit() == unit);
        self.retry = kept;
        swept.extend::<VecDeque<Pending>>(gone);
        for req in swept {
            self.answer_backed_off(req);
        }
    }

    /// 0x0B at once for a backed-off unit, counted apart from timeouts.
    fn answer_backed_off(&self, req: Pending) {
        self.stats.add(&self.stats.backed_off, 1);
        let adu = Adu::exception(
            req.adu.tid(),
            req.adu.unit(),
            req.adu.function(),
            exception::GATEWAY_TARGET_FAILED,
        );
        self.deliver(req.conn, adu, Some(req.permit));
    }

    fn answer_exception(&self, req: Pending, code: u8) {
        let counter = match code {
            exception::GATEWAY_PATH_UNAVAILABLE => &self.stats.unavailable,
            exception::SERVER_DEVICE_BUSY => &self.stats.busy,
            // GATEWAY_TARGET_FAILED: the only other code the relay answers itself.
            _ => &self.stats.timeouts,
        };
        self.stats.add(counter, 1);
        let adu = Adu::exception(req.adu.tid(), req.adu.unit(), req.adu.function(), code);
        self.deliver(req.conn, adu, Some(req.permit));
    }

    fn deliver(&self, conn: ConnId, adu: Adu, permit: Option<OwnedSemaphorePermit>) {
        if let Some(tx) = self.conns.get(&conn) {
            // Capacity covers every permit, so this only fails if the master is gone.
            let _ = tx.try_send(Outbound { adu, permit });
        }
    }
}

enum Event {
    Command(Option<Command>),
    Read(std::io::Result<usize>),
    Wrote(std::io::Result<usize>),
    Drained(Result<std::io::Result<()>, tokio::task::JoinError>),
    Timer,
    Shutdown,
}

/// Per-unit health on an RTU/ASCII bus: a unit that timed out `after` times in a row
/// is backed off for an interval that doubles (from `min` up to `max`) each time a
/// probe fails; a reply forgets it all.
struct Units {
    enabled: bool,
    after: u32,
    min: Duration,
    max: Duration,
    health: HashMap<u8, Health>,
}

#[derive(Debug, Default)]
struct Health {
    /// Timeouts in a row.
    timeouts: u32,
    /// The current back-off interval, once backed off.
    interval: Option<Duration>,
    until: Option<Instant>,
}

impl Units {
    fn new(cfg: &RelayConfig, enabled: bool) -> Self {
        let max = Duration::from_millis(cfg.unit_backoff_max_ms);
        Self {
            enabled,
            after: cfg.unit_backoff_after,
            min: Duration::from_millis(cfg.unit_backoff_ms).min(max),
            max,
            health: HashMap::new(),
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

    fn answered(&mut self, unit: u8) {
        self.health.remove(&unit);
    }
}

/// Frames waiting to be written to the port, in order. A frame not yet begun can be
/// withdrawn; one partly written is finished, so the device's parser stays in step.
#[derive(Debug, Default)]
struct Outgoing {
    frames: VecDeque<(u16, Bytes)>,
    /// Bytes of the front frame already written.
    written: usize,
    len: usize,
}

impl Outgoing {
    fn push(&mut self, tid: u16, frame: Bytes) {
        self.len += frame.len();
        self.frames.push_back((tid, frame));
    }

    fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Bytes still to write.
    fn len(&self) -> usize {
        self.len
    }

    /// The unwritten rest of the front frame.
    fn pending(&self) -> &[u8] {
        self.frames
            .front()
            .map_or(&[][..], |(_, f)| &f[self.written..])
    }

    fn advance(&mut self, n: usize) {
        self.written += n;
        self.len -= n;
        if let Some((_, f)) = self.frames.front() {
            if self.written >= f.len() {
                self.frames.pop_front();
                self.written = 0;
            }
        }
    }

    /// Removes the frame for `tid` if none of it has been written.
    fn withdraw(&mut self, tid: u16) -> bool {
        let Some(i) = self.frames.iter().position(|(t, _)| *t == tid) else {
            return false;
        };
        if i == 0 && self.written > 0 {
            return false;
        }
        let (_, f) = self.frames.remove(i).expect("index found above");
        self.len -= f.len();
        true
    }

    fn clear(&mut self) {
        self.frames.clear();
        self.written = 0;
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::{Outgoing, Units};
    use crate::config::RelayConfig;
    use bytes::Bytes;
    use std::time::Duration;
    use tokio::time::Instant;

    #[test]
    fn units_back_off_after_n_timeouts_doubling_up_to_max() {
        let cfg = RelayConfig {
            unit_backoff_after: 2,
            unit_backoff_ms: 100,
            unit_backoff_max_ms: 300,
            ..RelayConfig::default()
        };
        let mut u = Units::new(&cfg, true);
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
        // Failed probes double the interval, up to the max.
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(200)));
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(300)));
        assert_eq!(u.timed_out(5, t0), Some(Duration::from_millis(300)));
        // A reply forgets it all.
        u.answered(5);
        assert!(!u.backed_off(5, t0));
        assert_eq!(u.timed_out(5, t0), None);
        // Broadcasts and a disabled backoff never back off.
        assert_eq!(u.timed_out(0, t0), None);
        let mut off = Units::new(&cfg, false);
        assert_eq!((off.timed_out(5, t0), off.timed_out(5, t0)), (None, None));
    }

    #[test]
    fn outgoing_writes_in_order_and_withdraws_only_unstarted_frames() {
        let mut o = Outgoing::default();
        o.push(1, Bytes::from_static(b"abc"));
        o.push(2, Bytes::from_static(b"de"));
        o.push(3, Bytes::from_static(b"f"));
        assert_eq!(o.len(), 6);
        o.advance(2);
        assert_eq!(o.pending(), b"c");
        assert!(!o.withdraw(1), "partly written: finished, not withdrawn");
        assert!(o.withdraw(2));
        assert_eq!(o.len(), 2);
        o.advance(1);
        assert_eq!(o.pending(), b"f");
        o.advance(1);
        assert!(o.is_empty());
        assert_eq!(o.len(), 0);
        assert!(!o.withdraw(3));
    }
}
