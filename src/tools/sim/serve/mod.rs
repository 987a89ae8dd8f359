//! The simulator's task: it owns the port, decodes requests with the gateway's own
//! resynchronising decoder (docs/design.md §2), answers them through the device profile,
//! and sends replies and notifications through the line model. The console talks to
//! it over a channel.

use super::console::ConsoleCommand;
use super::line::{Chunker, Faults, Pacer};
use super::options::Settings;
use super::packets::PacketDirection;
use super::Device;
use crate::config::SerialConfig;
use crate::frame::framer::{Framed, Framer};
use crate::frame::hex::Hex;
use crate::frame::{Adu, RequestJudge};
use crate::line::port::serial::{self, Lateness, PreciseTimer};
use crate::line::port::Backoff;
use std::collections::VecDeque;
use std::path::Path;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{mpsc, oneshot};
use tokio::time::{sleep_until, Instant};
use tokio_serial::SerialStream;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

mod tcp;

/// A console command and where its answer goes.
#[derive(Debug)]
pub(crate) struct ConsoleRequest {
    pub(crate) command: ConsoleCommand,
    pub(crate) reply: oneshot::Sender<String>,
}

/// Where the simulated device sits.
#[derive(Debug)]
pub(crate) enum SimPort {
    /// A serial port or pty by path, reopened with backoff when it goes away.
    Path(SerialConfig),
    /// An open pty end (`mbgate demo`); losing it ends the simulator.
    Stream(SerialStream),
    /// A device on the network: listens here and serves one connection at a time
    /// (`tcp.rs`).
    Listen(std::net::SocketAddr),
}

/// Why the simulator stopped.
#[derive(Debug, thiserror::Error)]
pub(crate) enum SimError {
    /// Reading or writing the serial port or connection failed.
    #[error("the simulator's port was lost: {0}")]
    Lost(std::io::Error),
}

/// Is this path a pseudo-terminal? A pty has no byte rate of its own, so the simulator
/// paces it; a real UART paces itself.
pub(crate) fn is_pty(path: &Path) -> bool {
    std::fs::canonicalize(path).is_ok_and(|p| p.starts_with("/dev/pts"))
}

/// The pace on a pty: `--baud` paces the bytes as a UART at that speed would; without
/// it the simulator answers at once, as any program on a pty does (the gateway knows
/// a pty has no wire: docs/reliability.md "Knowing the wire").
fn pty_pace(given: Option<u32>) -> Option<u32> {
    given
}

/// A frame, or a piece of one, waiting for the instant its last byte has left the
/// simulated UART.
#[derive(Debug)]
struct InTransit {
    due: Instant,
    bytes: bytes::Bytes,
    /// The whole frame as sent and what it is, on its first piece (for the log).
    frame: Option<(bytes::Bytes, &'static str)>,
}

/// Waits until `due`: on a timerfd ([`PreciseTimer`]) to the microsecond, as
/// the gateway's own line timers are, so a reply leaves the moment its last byte has
/// left the simulated UART whatever the phase of the request against any tick. Tokio's
/// timer counts whole milliseconds and rounds a deadline up: up to 1 ms between that
/// instant and the sending (half a transaction at 115 200 baud), varying with when
/// the request came, which the line-limit benchmark would count against whoever
/// polls. Where there is no timerfd, tokio's timer wakes the simulator a millisecond
/// early and a blocking-pool thread sleeps the rest. A `due` already past returns at
/// once.
pub(crate) async fn until_precisely(timer: Option<&mut PreciseTimer>, due: Instant) {
    if let Some(timer) = timer {
        if timer.until(due).await.is_ok() {
            return;
        }
    }
    const TICK: Duration = Duration::from_millis(1);
    if due > Instant::now() + TICK {
        sleep_until(due - TICK).await;
    }
    let rest = due.saturating_duration_since(Instant::now());
    if !rest.is_zero() {
        let _ = tokio::task::spawn_blocking(move || std::thread::sleep(rest)).await;
    }
}

/// How a session on one open port ended.
enum SessionEnd {
    Shutdown,
    Lost(std::io::Error),
}

struct Sim {
    device: Device,
    delay: Duration,
    /// What the port adds to each reply, taken off a replayed device's time.
    medium: Duration,
    /// How long after their instant replies have been written (the timer's wake, the
    /// write): taken off a replayed device's time too, so the reply leaves on time.
    behind: Lateness,
    pipeline: bool,
    confirm_requests: bool,
    frame_gap: Duration,
    rx_faults: Faults,
    tx_faults: Faults,
    rx_pace: Pacer,
    tx_pace: Pacer,
    chunker: Chunker,
    /// Requests off the line, in the port's framing (the gateway's own framer).
    decoder: Framer,
    out: VecDeque<InTransit>,
    /// Without `--pipeline`, the device is busy until its reply has left.
    busy_until: Option<Instant>,
    last_rx: Instant,
    serving: bool,
}

/// Runs the simulator until `shutdown` (or the console's `quit`).
pub(crate) async fn run(
    settings: Settings,
    port: SimPort,
    mut commands: mpsc::Receiver<ConsoleRequest>,
    shutdown: CancellationToken,
) -> Result<(), SimError> {
    let paced = match &port {
        // Judged each time it opens (below): a pty may not exist yet.
        SimPort::Path(_) => false,
        SimPort::Stream(_) => true,
        // A socket has no byte rate to model.
        SimPort::Listen(_) => false,
    };
    let baud = paced.then(|| pty_pace(settings.baud)).flatten();
    let (seed, given_baud, bits) = (settings.seed, settings.baud, settings.char_bits);
    let toggle = settings.toggle;
    let mut sim = Sim::new(settings, baud);
    sim.say_faults(seed);
    let mut ticks = toggle.map(|period| {
        let mut i = tokio::time::interval_at(Instant::now() + period, period);
        i.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        i
    });

    match port {
        SimPort::Listen(addr) => tcp::listen(&mut sim, addr, &mut commands, ticks, &shutdown).await,
        SimPort::Stream(mut stream) => {
            info!("simulating {} on a pty", sim.describe());
            match sim
                .serve(&mut stream, &mut commands, ticks.as_mut(), &shutdown)
                .await
            {
                SessionEnd::Shutdown => Ok(()),
                SessionEnd::Lost(e) => Err(SimError::Lost(e)),
            }
        }
        SimPort::Path(cfg) => {
            let pace = (given_baud, bits);
            sim.serve_path(&cfg, pace, &mut commands, ticks.as_mut(), &shutdown)
                .await
        }
    }
}

impl Sim {
    /// The simulator of `settings`, its bytes paced at `baud` (none: not paced).
    fn new(settings: Settings, baud: Option<u32>) -> Sim {
        let mut device = settings.device;
        super::replay::announce(&mut device);
        Sim {
            device,
            delay: settings.delay,
            medium: settings.medium,
            behind: Lateness::default(),
            pipeline: settings.pipeline,
            confirm_requests: settings.confirm_requests,
            frame_gap: settings.frame_gap,
            rx_faults: settings.rx_faults,
            tx_faults: settings.tx_faults,
            rx_pace: Pacer::new(baud, settings.char_bits),
            tx_pace: Pacer::new(baud, settings.char_bits),
            chunker: settings.chunker,
            decoder: settings.framing.framer(),
            out: VecDeque::new(),
            busy_until: None,
            last_rx: Instant::now(),
            serving: false,
        }
    }

    /// The line faults, said once when there are any.
    fn say_faults(&self, seed: u64) {
        if self.rx_faults.is_active() || self.tx_faults.is_active() {
            info!(
                "line faults: drop {}, noise {}, to the device {}, from the device {}; --seed {} repeats them",
                self.rx_faults.drop.max(self.tx_faults.drop),
                self.rx_faults.noise.max(self.tx_faults.noise),
                if self.rx_faults.is_active() { "yes" } else { "no" },
                if self.tx_faults.is_active() { "yes" } else { "no" },
                seed
            );
        }
    }

    /// Serves the port at `cfg`, reopened with backoff when it goes away, until
    /// shutdown; a pty paced at the baud rate given (or none), `bits` a character.
    async fn serve_path(
        &mut self,
        cfg: &SerialConfig,
        (given_baud, bits): (Option<u32>, u32),
        commands: &mut mpsc::Receiver<ConsoleRequest>,
        mut ticks: Option<&mut tokio::time::Interval>,
        shutdown: &CancellationToken,
    ) -> Result<(), SimError> {
        let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
        let mut reported = false;
        loop {
            match serial::open(cfg) {
                Ok(mut stream) => {
                    backoff.reset();
                    reported = false;
                    // A pty made after the simulator started (socat in the
                    // background) is only known to be one now.
                    let pty = is_pty(Path::new(&cfg.path));
                    if given_baud.is_some() && !pty {
                        debug!("a real serial port: the UART paces the bytes");
                    }
                    let baud = pty.then(|| pty_pace(given_baud)).flatten();
                    (self.rx_pace, self.tx_pace) = (Pacer::new(baud, bits), Pacer::new(baud, bits));
                    info!(serial = %cfg.path, "simulating {} on {}", self.describe(), cfg.path);
                    match self
                        .serve(&mut stream, commands, ticks.as_deref_mut(), shutdown)
                        .await
                    {
                        SessionEnd::Shutdown => return Ok(()),
                        SessionEnd::Lost(e) => {
                            warn!(serial = %cfg.path, "port lost ({e}); reopening");
                        }
                    }
                }
                Err(e) if !reported => {
                    warn!(serial = %cfg.path, "cannot open the port ({e}); retrying");
                    reported = true;
                }
                Err(e) => debug!(serial = %cfg.path, "cannot open the port: {e}"),
            }
            let until = Instant::now() + backoff.next_delay();
            loop {
                tokio::select! {
                    _ = shutdown.cancelled() => return Ok(()),
                    _ = sleep_until(until) => break,
                    Some(req) = commands.recv() => self.command(req),
                }
            }
        }
    }

    fn describe(&self) -> String {
        use super::Profile;
        let profile = match &self.device.profile {
            Profile::CieM10(d) => format!("a CIE-M10 (unit {})", d.unit),
            Profile::Generic(g) => {
                let units: Vec<String> = g.units.keys().map(u8::to_string).collect();
                match units.as_slice() {
                    [one] => format!("a generic device (unit {one})"),
                    many => format!("generic devices (units {})", many.join(", ")),
                }
            }
            Profile::Replay(r) => {
                let units: Vec<String> = r.units().iter().map(u8::to_string).collect();
                format!("a replayed capture (units {})", units.join(", "))
            }
        };
        let pace = if self.tx_pace.char_time().is_zero() {
            String::new()
        } else {
            format!(
                ", {:.1} µs a byte",
                self.tx_pace.char_time().as_secs_f64() * 1e6
            )
        };
        format!("{profile}{pace}")
    }

    async fn serve<P: AsyncReadExt + AsyncWriteExt + Unpin>(
        &mut self,
        port: &mut P,
        commands: &mut mpsc::Receiver<ConsoleRequest>,
        mut ticks: Option<&mut tokio::time::Interval>,
        shutdown: &CancellationToken,
    ) -> SessionEnd {
        self.serving = true;
        let mut buf = vec![0u8; 4096];
        let mut timer = PreciseTimer::new()
            .inspect_err(|e| debug!("no timerfd ({e}): replies timed to the millisecond"))
            .ok();
        let end = loop {
            let due = self.out.front().map(|o| o.due);
            let gap_end = self.last_rx + self.frame_gap;
            let partial = self.decoder.buffered() > 0;
            tokio::select! {
                biased;
                _ = shutdown.cancelled() => break SessionEnd::Shutdown,
                _ = until_precisely(timer.as_mut(), due.unwrap_or_else(Instant::now)), if due.is_some() => {
                    // A port nobody reads fills up and the write waits: a stop still stops.
                    tokio::select! {
                        written = self.send_due(port) => if let Err(e) = written {
                            break SessionEnd::Lost(e);
                        },
                        _ = shutdown.cancelled() => break SessionEnd::Shutdown,
                    }
                }
                r = AsyncReadExt::read(port, &mut buf) => match r {
                    Ok(0) => break SessionEnd::Lost(std::io::ErrorKind::UnexpectedEof.into()),
                    Ok(n) => self.received(&buf[..n], Instant::now()),
                    Err(e) => break SessionEnd::Lost(e),
                },
                _ = sleep_until(gap_end), if partial => self.quiet(),
                Some(req) = commands.recv() => self.command(req),
                _ = async { ticks.as_mut().expect("guarded").tick().await }, if ticks.is_some() => {
                    if let Some(pdu) = self.device.toggle() {
                        self.notify(pdu);
                    }
                }
            }
        };
        // What was received or queued on this port is gone with it.
        self.serving = false;
        self.decoder.clear();
        self.out.clear();
        self.busy_until = None;
        end
    }

    /// With `--confirm-requests`, each request is confirmed by the next or by a quiet
    /// line: a device that takes requests back to back must know where a
    /// damaged one ends.
    fn judge(&self) -> RequestJudge {
        RequestJudge {
            confirm: self.confirm_requests,
        }
    }

    /// Bytes from the line at `now`, through the line model, into the decoder.
    fn received(&mut self, raw: &[u8], now: Instant) {
        let mut bytes = Vec::with_capacity(raw.len());
        self.rx_faults.apply(raw, &mut bytes);
        // On a UART the last of these bytes would arrive this much later.
        let arrived = self.rx_pace.finish(now.into_std(), raw.len()).into();
        self.last_rx = now;
        self.decoder.push(&bytes);
        let judge = self.judge();
        while let Some(framed) = self.decoder.next_frame(&judge, false) {
            self.framed(framed, arrived);
        }
    }

    /// The line went quiet: a partial request will never complete.
    fn quiet(&mut self) {
        let before = self.decoder.dropped();
        let arrived = Instant::now();
        let judge = self.judge();
        while let Some(framed) = self.decoder.next_frame(&judge, true) {
            self.framed(framed, arrived);
        }
        let dropped = self.decoder.dropped() - before;
        if dropped > 0 {
            debug!("discarded {dropped} bytes that made no request");
        }
    }

    /// A request off the line; a frame whose CRC or LRC failed is only counted (as
    /// dropped bytes).
    fn framed(&mut self, framed: Framed, arrived: Instant) {
        if let Framed::Frame(frame) = framed {
            self.request(frame, arrived);
        }
    }

    fn request(&mut self, frame: Adu, arrived: Instant) {
        if !self.pipeline && self.busy_until.is_some_and(|b| b > arrived) {
            info!(target: "mbgate::tools::sim::packets", "rx {} (ignored: busy)", Hex(frame.as_bytes()));
            self.device
                .log
                .record(PacketDirection::Rx, frame.as_bytes(), "ignored: busy");
            return;
        }
        if frame.unit() == 0 && self.decoder.codec().is_some() {
            // A broadcast on an RTU/ASCII bus: every device acts, none answers.
            info!(target: "mbgate::tools::sim::packets", "rx {} (broadcast)", Hex(&self.wire(&frame)));
            let wire = self.wire(&frame);
            self.device
                .log
                .record(PacketDirection::Rx, &wire, "broadcast");
            self.device.broadcast(frame.pdu());
            return;
        }
        let answer = self.device.answer(frame.unit(), frame.pdu());
        let note = if answer.reply.is_some() {
            "request"
        } else {
            "no such unit: silent"
        };
        let wire = self.wire(&frame);
        info!(target: "mbgate::tools::sim::packets", "rx {} ({note})", Hex(&wire));
        self.device.log.record(PacketDirection::Rx, &wire, note);
        if let Some(pdu) = answer.reply {
            let reply = Adu::build(frame.tid(), frame.unit(), &pdu);
            // A replayed device's time less what this port adds back (the recorded
            // time held the recording's path already); `--delay-ms` as given.
            let own = answer
                .delay
                .map(|d| d.saturating_sub(self.medium + self.behind.lead()));
            let delay = self.delay + own.unwrap_or_default();
            let done = self.queue(arrived + delay, reply, "reply");
            self.busy_until = Some(done);
        }
        if let Some(pdu) = answer.notification {
            self.notify(pdu);
        }
    }

    /// Queues an input change notification (docs/protocol.md §3): transaction id 0, which
    /// no gateway request carries.
    fn notify(&mut self, pdu: Vec<u8>) {
        let (Some(unit), true) = (self.device.notifying_unit(), self.serving) else {
            return;
        };
        let frame = Adu::build(0, unit, &pdu);
        self.queue(Instant::now(), frame, "notification");
    }

    /// Queues a frame ready at `ready` in its pieces, paced; the instant its last byte
    /// has left.
    fn queue(&mut self, ready: Instant, frame: Adu, note: &'static str) -> Instant {
        let bytes = bytes::Bytes::from(self.wire(&frame));
        let mut first = Some((bytes.clone(), note));
        let (mut at, mut due) = (0, ready);
        for (n, gap) in self.chunker.pieces(bytes.len()) {
            due = self.tx_pace.finish((due + gap).into_std(), n).into();
            self.out.push_back(InTransit {
                due,
                bytes: bytes.slice(at..at + n),
                frame: first.take(),
            });
            at += n;
        }
        due
    }

    /// Writes every frame whose time has come, through the line model, then logs
    /// them: the log's formatting and writing come after the frame's time, not
    /// before it (a replayed device's reply time is the device's, to the tenth of a
    /// millisecond: docs/simulator.md "Replaying a device").
    async fn send_due<P: AsyncWriteExt + Unpin>(&mut self, port: &mut P) -> std::io::Result<()> {
        let now = Instant::now();
        let mut bytes = Vec::new();
        let mut sent = Vec::new();
        while self.out.front().is_some_and(|o| o.due <= now) {
            let o = self.out.pop_front().expect("checked");
            sent.extend(o.frame.map(|(frame, note)| (frame, note, o.due)));
            self.tx_faults.apply(&o.bytes, &mut bytes);
        }
        let written = AsyncWriteExt::write_all(port, &bytes).await;
        let after = Instant::now();
        for (frame, note, due) in sent {
            self.behind.record(after.saturating_duration_since(due));
            info!(target: "mbgate::tools::sim::packets", "tx {} ({note})", Hex(&frame));
            self.device.log.record(PacketDirection::Tx, &frame, note);
        }
        written
    }

    /// A frame as this line carries it: MBAP as is, RTU or ASCII from its unit and PDU.
    fn wire(&self, frame: &Adu) -> Vec<u8> {
        self.decoder.encode(frame)
    }

    fn command(&mut self, req: ConsoleRequest) {
        let outcome = self.device.execute(req.command);
        if let Some(pdu) = outcome.notification {
            self.notify(pdu);
        }
        // On `quit` the console cancels the shutdown token once it has printed this.
        let _ = req.reply.send(outcome.text);
    }
}
