//! The one task that owns the serial line (design.md §1, §5).
//!
//! Connections talk to it over a channel ([`RelayHandle`]); it owns the port, the
//! queues, the in-flight table and the decoder, so nothing here is locked. One loop
//! waits on: commands from connections, bytes from the port, room to write to the
//! port, the nearest timer (a response deadline, the frame gap, the next reopen, the
//! next systemd watchdog ping), and shutdown.

use crate::config::{Notifications, RelayConfig, SerialConfig};
use crate::frame::hex::Hex;
use crate::frame::mbap::FrameRef;
use crate::frame::pdu::{self, exception};
use crate::frame::{Adu, Judge, Resync};
use crate::notify;
use crate::serial::{self, Backoff};
use crate::stats::Stats;
use crate::tids::{self, Tids};
use bytes::Bytes;
use std::collections::{HashMap, VecDeque};
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
    },
    Closed {
        retry_at: Instant,
    },
}

/// The relay's view of which frames on the line it can use (design.md §1 step 4, §2).
struct RelayJudge<'a> {
    in_flight: &'a [InFlight],
    tids: &'a Tids,
    /// Hold frames until what follows them confirms them (issue 4): when another frame
    /// may follow, a reply that lost a byte could complete itself with its first byte.
    strict: bool,
}

impl Judge for RelayJudge<'_> {
    fn plausible_function(&self, code: u8) -> bool {
        pdu::is_reply_function(code)
            || self
                .in_flight
                .iter()
                .any(|f| f.req.adu.function() == code & 0x7F)
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        match self.in_flight.iter().find(|f| f.tid == frame.tid()) {
            Some(f) => {
                f.req.adu.unit() == frame.unit() && pdu::reply_matches(f.req.adu.pdu(), frame.pdu())
            }
            // Not an answer to anything on the line: a device notification (id 0), or a
            // late answer (a retired id), to be dropped as such. Any other id is not
            // ours: a reply shifted by a lost byte carries its own low byte after a
            // stranger's high byte (tids.rs), so ids sharing a low byte with one in
            // flight are refused even when retired.
            None => {
                let tid = frame.tid();
                (tid == 0 || self.tids.is_retired(tid))
                    && pdu::reply_well_formed(frame.pdu())
                    && !self.in_flight.iter().any(|f| f.tid & 0xFF == tid & 0xFF)
            }
        }
    }

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        self.strict
    }
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
    in_flight: Vec<InFlight>,
    tids: Tids,
    decoder: Resync,
    last_byte: Instant,
    /// Until then another frame may follow any reply (a late reply, a notification),
    /// so replies are held for confirmation.
    followers_until: Instant,
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
            in_flight: Vec::new(),
            tids: Tids::new(),
            decoder: Resync::new(),
            last_byte: now,
            followers_until: now,
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
                Port::Open { rd, wr } => tokio::select! {
                    biased;
                    r = rd.read(&mut rbuf) => Event::Read(r),
                    cmd = self.rx.recv(), if self.commands_open => Event::Command(cmd),
                    w = wr.write(self.out.pending()), if !self.out.is_empty() => Event::Wrote(w),
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
                    self.decoder.push(&rbuf[..n]);
                    self.last_byte = now;
                }
                Event::Read(Err(e)) => self.port_lost(&format!("read failed: {e}"), now),
                Event::Wrote(Ok(n)) => {
                    self.stats.add(&self.stats.serial_bytes_out, n as u64);
                    self.out.advance(n);
                }
                Event::Wrote(Err(e)) => self.port_lost(&format!("write failed: {e}"), now),
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
        if self.decoder.buffered() > 0 {
            wake = wake.min(self.last_byte + self.gap());
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

    fn gap(&self) -> Duration {
        Duration::from_millis(self.cfg.frame_gap_ms)
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
                let (rd, wr) = tokio::io::split(port);
                self.port = Port::Open { rd, wr };
                self.backoff.reset();
                self.port_warned = false;
                self.decoder.clear();
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
    /// reopen with backoff.
    fn port_lost(&mut self, why: &str, now: Instant) {
        warn!(path = %self.serial.path, "serial port lost: {why}; reopening with backoff");
        self.port = Port::Closed {
            retry_at: now + self.backoff.next_delay(),
        };
        self.port_warned = true;
        self.decoder.clear();
        self.out.clear();
        for f in std::mem::take(&mut self.in_flight) {
            self.tids.retire(f.tid, now.into_std());
            self.answer_exception(f.req, exception::GATEWAY_TARGET_FAILED);
        }
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

    /// Answers every queued request with `code`.
    fn flush_queue(&mut self, code: u8) {
        self.ring.clear();
        self.queued = 0;
        for (_, q) in std::mem::take(&mut self.queues) {
            for req in q {
                self.answer_exception(req, code);
            }
        }
    }

    /// Puts queued requests on the line, round-robin across connections, while fewer
    /// than `max_in_flight` are outstanding.
    fn dispatch(&mut self, now: Instant) {
        while self.in_flight.len() < self.cfg.max_in_flight && self.is_open() {
            let Some(conn) = self.ring.pop_front() else {
                break;
            };
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
            self.send(req, now);
        }
    }

    fn send(&mut self, req: Pending, now: Instant) {
        let tid = self.tids.allocate(now.into_std());
        let frame = req.adu.with_tid(tid);
        if self.traffic {
            debug!(target: "mbgate::traffic", dir = "gw->serial", conn = req.conn, "{}", Hex(frame.as_bytes()));
        }
        self.out.push(tid, frame.into_bytes());
        // The response time counts from when the request has left: behind whatever is
        // still waiting to be written.
        let deadline = now
            + serial::wire_time(&self.serial, self.out.len())
            + Duration::from_millis(self.cfg.response_timeout_ms);
        self.in_flight.push(InFlight { tid, deadline, req });
    }

    /// Can a frame other than the reply to the one request on the line arrive? Then
    /// replies wait for confirmation (issue 4). It can when several requests are on the
    /// line, when the device sends notifications, and for a while after a request timed
    /// out (its reply may still come), an unsolicited frame was seen, or the line
    /// carried garbage (noise that can land inside a reply).
    fn followers_possible(&self, now: Instant) -> bool {
        self.in_flight.len() > 1
            || self.cfg.notifications == Notifications::Broadcast
            || now < self.followers_until
    }

    /// Another frame may follow replies for a while (see [`Self::followers_possible`]).
    fn expect_followers(&mut self, now: Instant) {
        self.followers_until = now + tids::RETIRED_FOR;
    }

    fn take_frames(&mut self, now: Instant) {
        let quiet = now >= self.last_byte + self.gap();
        loop {
            let judge = RelayJudge {
                in_flight: &self.in_flight,
                tids: &self.tids,
                strict: self.followers_possible(now),
            };
            let Some(frame) = self.decoder.next_frame(&judge, quiet) else {
                break;
            };
            self.on_frame(frame, now);
        }
        let decoded = self.decoder.stats();
        if decoded.dropped_bytes > self.stats.get(&self.stats.dropped_bytes) {
            self.expect_followers(now);
        }
        self.stats
            .set(&self.stats.dropped_bytes, decoded.dropped_bytes);
        self.stats.set(&self.stats.refuted_frames, decoded.refuted);
    }

    fn on_frame(&mut self, frame: Adu, now: Instant) {
        let tid = frame.tid();
        if let Some(i) = self.in_flight.iter().position(|f| f.tid == tid) {
            // The judge has checked unit, function code and shape against this request.
            let f = self.in_flight.swap_remove(i);
            // Kept reserved a while: a second answer with this id is recognised as
            // ours and dropped, never broadcast.
            self.tids.retire(tid, now.into_std());
            self.stats.add(&self.stats.replies, 1);
            let reply = frame.with_tid(f.req.adu.tid());
            self.deliver(f.req.conn, reply, Some(f.req.permit));
        } else if self.tids.is_retired(tid) {
            self.expect_followers(now);
            self.stats.add(&self.stats.late_replies, 1);
            debug!(
                tid,
                "late reply dropped (its request timed out or was answered already): {:?}", frame
            );
        } else {
            self.expect_followers(now);
            match self.cfg.notifications {
                Notifications::Drop => {
                    self.stats.add(&self.stats.notifications_dropped, 1);
                    debug!("unsolicited frame dropped: {:?}", frame);
                }
                Notifications::Broadcast => self.broadcast(frame),
            }
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
            self.tids.retire(f.tid, now.into_std());
            self.expect_followers(now);
            if self.out.withdraw(f.tid) {
                // Flow control held it back (CTS low) the whole time: it never left,
                // and must not act on the device after the master was told 0x0B.
                warn!(
                    conn = f.req.conn,
                    "request could not be written in time (is CTS held low?)"
                );
            }
            let function = f.req.adu.function();
            let may_retry = pdu::is_read(function) || self.cfg.retry_writes;
            if may_retry && f.req.attempts < self.cfg.retries && self.is_open() {
                debug!(
                    conn = f.req.conn,
                    attempt = f.req.attempts + 1,
                    "no reply; resending"
                );
                self.stats.add(&self.stats.retries, 1);
                let mut req = f.req;
                req.attempts += 1;
                self.send(req, now);
            } else {
                debug!(
                    conn = f.req.conn,
                    tid = f.req.adu.tid(),
                    "no reply in time: 0x0B"
                );
                self.answer_exception(f.req, exception::GATEWAY_TARGET_FAILED);
            }
        }
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
    Timer,
    Shutdown,
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
    use super::Outgoing;
    use bytes::Bytes;

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
