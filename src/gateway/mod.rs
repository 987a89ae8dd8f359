//! The gateway as a whole: bind the listeners, start a relay for each line, and shut down
//! cleanly (docs/design.md §3: SIGTERM and SIGINT drain in-flight requests, bounded), telling
//! systemd when it is ready and when it stops (see `crate::ops::notify`).

pub(crate) mod control;
mod error;
pub(crate) mod reload;
mod warnings;

pub use error::GatewayError;

use warnings::warn_inapplicable;
pub(crate) use warnings::warnings;

use crate::config::{Config, LineConfig, ListenConfig, Transport};
use crate::line::relay::{Relay, RelayHandle};
use crate::masters::router::Router;
use crate::masters::tcp::{self, Socket};
use crate::ops::metrics::{self, Board, ListenerMetrics, ListenerTransport};
use crate::ops::notify;
use crate::ops::stats::Stats;
use crate::tls::server::Acceptor;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::signal::unix::SignalKind;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

/// Runs the gateway until `shutdown` is cancelled, then drains and returns the totals.
/// Each bound address is logged as `listening on ADDR` (port 0 becomes a real port).
pub async fn run(cfg: Config, shutdown: CancellationToken) -> Result<Arc<Stats>, GatewayError> {
    let listeners = bind(&cfg).await?;
    serve(listeners, cfg, shutdown).await
}

/// [`run`], and on each SIGHUP `load` reads the configuration again and what can
/// change while running is applied ([`crate::gateway::reload`]).
pub(crate) async fn run_reloading(
    cfg: Config,
    load: reload::Loader,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    let listeners = bind(&cfg).await?;
    serve_with(listeners, cfg, Some(load), shutdown).await
}

/// Binds every listener's address, in the order of the configuration (see
/// [`tcp::listen`]).
pub(crate) async fn bind(cfg: &Config) -> Result<Vec<Socket>, GatewayError> {
    if !cfg.listens() {
        // Every line's device is a master: nothing for a Modbus/TCP master to reach;
        // or the file only dials its masters: no port is opened for them.
        return Ok(Vec::new());
    }
    let max_pending = cfg.max_pending_per_connection();
    let bind = |l: &ListenConfig| {
        let addr = l.tcp.listen;
        let bound = match l.transport {
            Transport::Tcp => tcp::listen(addr, max_pending).map(Socket::Tcp),
            Transport::Udp => tcp::udp::bind(addr).map(Socket::Udp),
        };
        bound.map_err(|error| GatewayError::Bind { addr, error })
    };
    cfg.listeners.iter().map(bind).collect()
}

/// [`run`] on listeners already bound (`mbgate demo` prints their addresses first),
/// one for each of `cfg.listeners`.
pub(crate) async fn serve(
    listeners: Vec<Socket>,
    cfg: Config,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    serve_with(listeners, cfg, None, shutdown).await
}

/// The gateway's phases, each its own step: the listeners made ready ([`listening`]),
/// the lines and everything beside them started ([`start`]), the masters served until
/// shutdown ([`accept`]), and the drain ([`drain`]).
async fn serve_with(
    listeners: Vec<Socket>,
    cfg: Config,
    load: Option<reload::Loader>,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    let bound = listening(listeners, &cfg)?;
    warn_inapplicable(&cfg);
    let mut started = start(bound, cfg, load, &shutdown).await?;
    let tracker = accept(&mut started, &shutdown).await;
    Ok(drain(started, tracker).await)
}

/// A listener bound, and what its accept loop is told about it.
type Bound = (Socket, tcp::Listening);

/// Bind, second half: each bound listener with its name in the file, its real address
/// (port 0 is a real port by now) and its TLS acceptor, whose files are read here.
fn listening(listeners: Vec<Socket>, cfg: &Config) -> Result<Vec<Bound>, GatewayError> {
    let mut bound = Vec::new();
    for (i, (listener, listen)) in listeners.into_iter().zip(&cfg.listeners).enumerate() {
        let local = listener.local_addr().map_err(|error| GatewayError::Bind {
            addr: listen.tcp.listen,
            error,
        })?;
        let name = format!("listen[{i}]");
        let tls = match &listen.access.tls {
            Some(t) => Some(Arc::new(Acceptor::new(
                t,
                &format!("{name}.tls"),
                &cfg.roles,
            )?)),
            None => None,
        };
        let listening = tcp::Listening {
            listen: listen.clone(),
            name,
            local,
            tls,
        };
        bound.push((listener, listening));
    }
    Ok(bound)
}

/// The gateway once started: what serving and draining need.
struct Started {
    bound: Vec<Bound>,
    /// The configuration as it runs now: a reload publishes the new one here, and
    /// every master's connection reads it (`masters/tcp/live.rs`).
    running: watch::Sender<Arc<Config>>,
    capture: crate::ops::capture::Capture,
    /// Each listener's counters, in the order of `bound`.
    listener_stats: Vec<Arc<Stats>>,
    /// What every master's connection shares (its tracker the drain waits on).
    shared: tcp::Shared,
    /// The dials running (a reload changes them).
    dials: Arc<Mutex<tcp::dial::Dials>>,
    /// The UDP listeners running (a reload changes them).
    udps: Arc<Mutex<tcp::udp::Udps>>,
    /// Every listener's and line's counters, with `tally`'s: the totals add them up.
    counted: Vec<Arc<Stats>>,
    /// The counters of the dials and the UDP listeners a reload adds and removes.
    tally: Arc<tcp::tally::SourceTally>,
    /// The lines' tasks, running.
    line_tasks: Vec<tokio::task::JoinHandle<()>>,
}

/// Start: the capture and control socket, the lines, the metrics listener, the signal
/// handlers and reload, the log's account of it all, and READY=1. The lines run from
/// here; the listeners accept nothing before [`accept`].
async fn start(
    bound: Vec<Bound>,
    cfg: Config,
    load: Option<reload::Loader>,
    shutdown: &CancellationToken,
) -> Result<Started, GatewayError> {
    // `mbgate reload` asks over the control socket, when there is a file to read again.
    let (reload_handle, asked) = load.as_ref().map(|_| reload::ReloadHandle::new()).unzip();
    // Before the lines: the always-on ring has their first frames.
    let capture = crate::ops::capture::Capture::start(&cfg);
    let board = Arc::new(Board::default());
    crate::gateway::control::start(&cfg, capture.hub(), reload_handle, board.clone(), shutdown);
    let cfg = Arc::new(cfg);
    let running = watch::Sender::new(cfg.clone());
    let _ = board.capture.set(capture.hub().clone());
    board.reloads.started(std::time::SystemTime::now());
    let lines = start_lines(&cfg, &capture, &board, shutdown).await?;
    let listener_stats = listeners_on_board(&bound, &board);
    let mut counted = listener_stats.clone();
    counted.extend(lines.stats);
    let http = start_metrics(&cfg, &board, shutdown)?;
    let router = Arc::new(Router::new(&lines.slaves, lines.relays.clone()));
    let shared = shared(&running, router, &board, &capture, shutdown);
    let tally = Arc::new(tcp::tally::SourceTally::new(board.clone()));
    let udps = Arc::new(Mutex::new(tcp::udp::Udps::new(
        shared.clone(),
        tally.clone(),
    )));
    // The dials start with the listeners ([`accept`]); a reload changes them.
    let dials = Arc::new(Mutex::new(tcp::dial::Dials::new(
        shared.clone(),
        tally.clone(),
    )));
    // Before "listening on", as the other handlers: a reload asked for at once finds
    // its handler, never SIGHUP's default action (the end of the process).
    let hup = load.and_then(hangup);
    // Before "listening on": from then on a signal finds its handler.
    let signals = user_signals();
    announce(&cfg, &bound);
    let line_tasks: Vec<_> = lines.tasks.into_iter().map(tokio::spawn).collect();
    let started = Started {
        bound,
        running,
        capture,
        listener_stats,
        counted,
        tally,
        line_tasks,
        shared,
        dials,
        udps,
    };
    let reload = match (hup, asked) {
        (Some((hup, load)), Some(asked)) => Some((hup, load, asked, lines.handles, http)),
        _ => None,
    };
    watch(&started, &board, reload, signals, shutdown);
    Ok(started)
}

/// Each listener's counters (connections, refusals, requests it answered itself), on
/// the board; each line keeps its own (its metrics are per line), and the totals add
/// them up.
fn listeners_on_board(bound: &[Bound], board: &Board) -> Vec<Arc<Stats>> {
    let listener_stats: Vec<Arc<Stats>> = bound.iter().map(|_| Arc::default()).collect();
    for ((socket, l), stats) in bound.iter().zip(&listener_stats) {
        let transport = match socket {
            Socket::Tcp(_) => ListenerTransport::Tcp,
            Socket::Udp(_) => ListenerTransport::Udp,
        };
        let metrics = Arc::new(ListenerMetrics {
            name: l.local.to_string(),
            stats: stats.clone(),
        });
        board.add_listener_on(metrics, transport);
    }
    listener_stats
}

/// What every master's connection shares, and the tracker the drain waits on.
fn shared(
    running: &watch::Sender<Arc<Config>>,
    router: Arc<Router>,
    board: &Board,
    capture: &crate::ops::capture::Capture,
    shutdown: &CancellationToken,
) -> tcp::Shared {
    tcp::Shared {
        running: running.subscribe(),
        router,
        stats: Arc::default(),
        shutdown: shutdown.clone(),
        tracker: TaskTracker::new(),
        ids: Arc::new(AtomicU64::new(0)),
        masters: board.masters.clone(),
        capture: capture.hub().clone(),
        unasked: Arc::default(),
    }
}

/// What reload needs that the gateway has only at start: SIGHUP's handler and loader,
/// `mbgate reload`'s requests, the lines' handles and the metrics listener.
type ReloadStart = (
    tokio::signal::unix::Signal,
    reload::Loader,
    tokio::sync::mpsc::UnboundedReceiver<reload::ReloadAsked>,
    Vec<reload::LineHandle>,
    crate::ops::metrics::listener::MetricsListener,
);

/// The tasks that watch the running gateway: reload (on SIGHUP and `mbgate reload`),
/// the status systemd shows, and the counters' report on SIGUSR1 and SIGUSR2.
fn watch(
    started: &Started,
    board: &Arc<Board>,
    reload: Option<ReloadStart>,
    signals: Option<UserSignals>,
    shutdown: &CancellationToken,
) {
    if let Some((hup, load, asked, lines, http)) = reload {
        let reloadable = reload::Reloadable {
            running: started.running.clone(),
            masters: board.masters.clone(),
            load,
            lines,
            metrics: http,
            // Their certificates are read again by every reload, whatever becomes of
            // the rest of it.
            acceptors: started
                .bound
                .iter()
                .filter_map(|(_, l)| l.tls.clone())
                .collect(),
            counted: board.reloads.clone(),
            dials: {
                let dials = started.dials.clone();
                Box::new(move |d| dials.lock().expect("not poisoned").apply(d))
            },
            udps: {
                let udps = started.udps.clone();
                Box::new(move |l| udps.lock().expect("not poisoned").apply(l))
            },
        };
        tokio::spawn(reload::on_sighup(hup, asked, reloadable, shutdown.clone()));
    }
    if notify::under_systemd() {
        tokio::spawn(metrics::status::refresh(board.clone(), shutdown.clone()));
    }
    if let Some(signals) = signals {
        let counted = (started.counted.clone(), started.tally.clone());
        tokio::spawn(report_on_signal(signals, counted, shutdown.clone()));
    }
}

/// The lines, made and on the board, not yet running.
struct Lines {
    /// Each line's task, to spawn once the gateway has said it is ready.
    tasks: Vec<std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>>,
    /// How a reload reaches each line.
    handles: Vec<reload::LineHandle>,
    /// The lines whose device is a slave, and their relays: what the router routes
    /// masters' requests to.
    slaves: Vec<LineConfig>,
    relays: Vec<RelayHandle>,
    /// Each line's counters.
    stats: Vec<Arc<Stats>>,
}

/// Start lines: each line its own task (a relay where the device is a slave, a master
/// line where it is the master), with its own queue, timeouts and backoff, so a slow
/// or dead line never holds up another; its capture tap and its metrics on the board.
async fn start_lines(
    cfg: &Config,
    capture: &crate::ops::capture::Capture,
    board: &Board,
    shutdown: &CancellationToken,
) -> Result<Lines, GatewayError> {
    let mut lines = Lines {
        tasks: Vec::new(),
        handles: Vec::new(),
        stats: Vec::new(),
        slaves: Vec::new(),
        relays: Vec::new(),
    };
    for (i, line) in cfg.lines.iter().enumerate() {
        let line_stats = Arc::new(Stats::default());
        lines.stats.push(line_stats.clone());
        // One watchdog for the gateway: every line runs on the one thread, so one
        // loop that turns shows that all of them can.
        let watchdog = if i == 0 {
            notify::watchdog_interval()
        } else {
            None
        };
        let tap = capture.hub().tap(i as u16 + 1);
        if let Some(master) = &line.master {
            let port = crate::line::port::serial::SerialPort::new(line.serial.clone());
            let timing = crate::line::bridge::Timing::of_line(&line.serial, &line.relay);
            let metrics = Arc::new(metrics::LineMetrics::new(line.name(), line_stats));
            board.add_line(metrics.clone());
            let (task, handle) = crate::line::bridge::start(crate::line::bridge::MasterLineParts {
                port: Box::new(port),
                framing: line.serial.framing,
                timing,
                master: master.clone(),
                traffic: cfg.log.traffic,
                line_tap: tap,
                tcp_tap: capture.hub().tap(0),
                metrics,
                watchdog,
            })
            .await?;
            lines.handles.push(reload::LineHandle::Master(handle));
            let shutdown = shutdown.clone();
            lines.tasks.push(Box::pin(async move {
                task.run(shutdown).await;
            }));
            continue;
        }
        let (relay, handle) = Relay::for_line(line, cfg.log.traffic, line_stats, shutdown.clone());
        let relay = relay.with_tap(tap).with_watchdog(watchdog);
        board.add_line(relay.metrics());
        lines
            .handles
            .push(reload::LineHandle::Relay(handle.clone()));
        lines.slaves.push(line.clone());
        lines.relays.push(handle);
        lines.tasks.push(Box::pin(relay.run()));
    }
    Ok(lines)
}

/// The metrics listener: off unless asked for, and then nothing but the Modbus ports
/// listen.
fn start_metrics(
    cfg: &Config,
    board: &Arc<Board>,
    shutdown: &CancellationToken,
) -> Result<crate::ops::metrics::listener::MetricsListener, GatewayError> {
    let access = crate::ops::metrics::web::WebAccess::load(&cfg.metrics.web_config)?;
    let mut http = crate::ops::metrics::listener::MetricsListener::new(
        board.clone(),
        access,
        shutdown.clone(),
    );
    if let Some(addr) = cfg.metrics.listen {
        let listener =
            metrics::http::bind(addr).map_err(|error| GatewayError::MetricsBind { addr, error })?;
        http.start(addr, listener);
    }
    Ok(http)
}

/// SIGHUP's handler, with the loader a reload reads the file by; none (and no reload)
/// when it cannot be installed.
fn hangup(load: reload::Loader) -> Option<(tokio::signal::unix::Signal, reload::Loader)> {
    match tokio::signal::unix::signal(SignalKind::hangup()) {
        Ok(hup) => Some((hup, load)),
        Err(e) => {
            warn!("cannot install the SIGHUP handler: no reload ({e})");
            None
        }
    }
}

/// Each line with its own framing and settings, then each listener with the masters
/// it takes and who may do what (a listener's framing is never printed beside a
/// serial port); then READY=1, before the lines first run, so it precedes the first
/// WATCHDOG=1.
fn announce(cfg: &Config, bound: &[Bound]) {
    let lines = &cfg.lines;
    let devices: Vec<&str> = lines.iter().map(LineConfig::name).collect();
    let devices = devices.join(", ");
    for line in lines {
        info!("line {}", crate::config::describe::line(line));
    }
    for (_, l) in bound {
        let masters = match l.listen.transport {
            Transport::Tcp => crate::config::describe::masters(l.listen.framing),
            Transport::Udp => "Modbus/UDP masters (UDP)",
        };
        info!(serial = %devices, "listening on {} for {masters}", l.local);
        for said in crate::config::effective_access(&l.listen, &cfg.roles) {
            info!("{}: {said}", l.name);
        }
    }
    if cfg.dial_only {
        info!("no listener: the file only dials its masters and opens no port");
    }
    for (i, d) in cfg.dials.iter().enumerate() {
        info!("dial[{i}]: {}", crate::config::describe::dial(d));
    }
    let addrs: Vec<String> = bound.iter().map(|(_, l)| l.local.to_string()).collect();
    notify::ready(&match addrs.is_empty() {
        true => format!("serial {devices}, no Modbus/TCP listener"),
        false => format!("listening on {}, serial {devices}", addrs.join(", ")),
    });
}

/// Serve: every listener's accept loop (there may be none) until shutdown; the
/// connections they started are on the tracker returned.
async fn accept(started: &mut Started, shutdown: &CancellationToken) -> TaskTracker {
    let shared = started.shared.clone();
    let tracker = shared.tracker.clone();
    let mut accepting = Vec::new();
    let bound = std::mem::take(&mut started.bound);
    for ((listener, listening), stats) in bound.into_iter().zip(&started.listener_stats) {
        let shared = tcp::Shared {
            stats: stats.clone(),
            ..shared.clone()
        };
        match listener {
            Socket::Tcp(l) => accepting.push(tokio::spawn(tcp::accept_loop(l, listening, shared))),
            // On the tracker, each with its own stop: a reload changes them.
            Socket::Udp(u) => {
                let mut udps = started.udps.lock().expect("not poisoned");
                udps.adopt(u, listening, stats.clone());
            }
        }
    }
    // The dials run beside the listeners, on the tracker: the drain waits for the
    // replies their connections owe.
    // Their counters in the totals through the tally, as those a reload adds. As the
    // configuration runs now: a reload may have come since start.
    let running = started.running.borrow().clone();
    started
        .dials
        .lock()
        .expect("not poisoned")
        .apply(&running.dials);
    for accept in accepting {
        let _ = accept.await;
    }
    // The accept loops end at shutdown; with none (every line a master line) serving
    // is waiting for it.
    shutdown.cancelled().await;
    tracker
}

/// Drain: the listeners are closed; connections stop reading and the lines answer
/// what is queued (0x0A) and wait for what is on them, within the longest answer the
/// configuration allows as it runs now (a reload may have changed the timeouts) and
/// two seconds more. Then the capture ends and the totals are logged.
async fn drain(started: Started, tracker: TaskTracker) -> Arc<Stats> {
    let answer_within = started.running.borrow().answer_within();
    let bound = answer_within + Duration::from_secs(2);
    info!("shutting down: draining in-flight requests");
    // systemd waits for the drain, and a second more for the exit itself.
    notify::stopping(bound + Duration::from_secs(1));
    tracker.close();
    if tokio::time::timeout(bound, async {
        for task in started.line_tasks {
            let _ = task.await;
        }
        tracker.wait().await;
    })
    .await
    .is_err()
    {
        warn!("drain did not finish in {bound:?}; exiting anyway");
    }
    // Every capture gets its end, the ring its last packets.
    started.capture.finish().await;
    let totals = Arc::new(totals(&started.counted, &started.tally));
    info!(stats = %totals, "stopped");
    totals
}

/// The gateway's totals: the listeners' and lines' counters, and those of every dial
/// and UDP listener that ran, a reload's among them.
fn totals(counted: &[Arc<Stats>], tally: &tcp::tally::SourceTally) -> Stats {
    let sources = tally.total();
    Stats::total(counted.iter().map(|s| &**s).chain([&sources]))
}

type UserSignals = (tokio::signal::unix::Signal, tokio::signal::unix::Signal);

/// Handlers for SIGUSR1 and SIGUSR2. Left at their defaults both would end the process
/// at once, without the drain: a stray `kill -USR1` must not cost the masters their
/// replies. Once installed they stay for the life of the process.
fn user_signals() -> Option<UserSignals> {
    use tokio::signal::unix::{signal, SignalKind};
    match (
        signal(SignalKind::user_defined1()),
        signal(SignalKind::user_defined2()),
    ) {
        (Ok(usr1), Ok(usr2)) => Some((usr1, usr2)),
        _ => {
            warn!("cannot install the SIGUSR1/SIGUSR2 handlers");
            None
        }
    }
}

/// SIGUSR1 logs the counters now (at info, as on exit) and the gateway carries on;
/// SIGUSR2 is ignored.
async fn report_on_signal(
    (mut usr1, mut usr2): UserSignals,
    (counted, tally): (Vec<Arc<Stats>>, Arc<tcp::tally::SourceTally>),
    shutdown: CancellationToken,
) {
    loop {
        tokio::select! {
            _ = usr1.recv() => {
                let stats = totals(&counted, &tally);
                info!(%stats, "counters (SIGUSR1)");
            }
            _ = usr2.recv() => debug!("SIGUSR2 ignored"),
            _ = shutdown.cancelled() => return,
        }
    }
}
