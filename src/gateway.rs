//! The gateway as a whole: bind, start the relay and the listener, and shut down
//! cleanly (docs/design.md §3: SIGTERM and SIGINT drain in-flight requests, bounded), telling
//! systemd when it is ready and when it stops (see [`crate::notify`]).

use crate::config::{Config, Framing, Notifications};
use crate::metrics::{self, Board, ListenerMetrics};
use crate::notify;
use crate::relay::Relay;
use crate::reload;
use crate::stats::Stats;
use crate::tcp;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::signal::unix::SignalKind;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tracing::{debug, info, warn};

#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// The cause is part of the message, with what to do about it, and deliberately
    /// not a `source`: printed as a chain it would appear twice.
    #[error("cannot listen on {addr}: {error}{}", bind_hint(.error, *.addr))]
    Bind {
        addr: SocketAddr,
        error: std::io::Error,
    },
    /// `metrics.listen` could not be bound.
    #[error("cannot listen for metrics on {addr} (metrics.listen): {error}")]
    MetricsBind {
        addr: SocketAddr,
        error: std::io::Error,
    },
}

/// What a user can do about a failed bind, for the two failures people meet first.
fn bind_hint(error: &std::io::Error, addr: SocketAddr) -> String {
    match error.kind() {
        std::io::ErrorKind::AddrInUse => {
            let other = SocketAddr::new(addr.ip(), addr.port().wrapping_add(1).max(1024));
            format!(
                " (another process holds port {}: stop it, or choose another port, \
                 e.g. --listen {other})",
                addr.port()
            )
        }
        std::io::ErrorKind::PermissionDenied if addr.port() < 1024 => format!(
            " (ports below 1024 need root or the CAP_NET_BIND_SERVICE capability, which the \
             systemd units grant; or choose a port above 1023, e.g. --listen {})",
            SocketAddr::new(addr.ip(), 5020)
        ),
        _ => String::new(),
    }
}

/// Runs the gateway until `shutdown` is cancelled, then drains and returns the totals.
/// The bound address is logged as `listening on ADDR` (port 0 becomes a real port).
pub async fn run(cfg: Config, shutdown: CancellationToken) -> Result<Arc<Stats>, GatewayError> {
    let listener = bind(&cfg).await?;
    serve(listener, cfg, shutdown).await
}

/// [`run`], and on each SIGHUP `load` reads the configuration again and what can
/// change while running is applied ([`crate::reload`]).
pub async fn run_reloading(
    cfg: Config,
    load: reload::Loader,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    let listener = bind(&cfg).await?;
    serve_with(listener, cfg, Some(load), shutdown).await
}

/// Binds `tcp.listen` (see [`tcp::listen`]).
pub async fn bind(cfg: &Config) -> Result<TcpListener, GatewayError> {
    let addr = cfg.tcp.listen;
    tcp::listen(addr, cfg.relay.max_pending_per_connection)
        .map_err(|error| GatewayError::Bind { addr, error })
}

/// [`run`] on a listener already bound (`mbgate demo` prints its address first).
pub async fn serve(
    listener: TcpListener,
    cfg: Config,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    serve_with(listener, cfg, None, shutdown).await
}

async fn serve_with(
    listener: TcpListener,
    cfg: Config,
    load: Option<reload::Loader>,
    shutdown: CancellationToken,
) -> Result<Arc<Stats>, GatewayError> {
    let addr = cfg.tcp.listen;
    let local = listener
        .local_addr()
        .map_err(|error| GatewayError::Bind { addr, error })?;
    warn_inapplicable(&cfg);
    let running = Arc::new(Mutex::new(cfg.clone()));
    let cfg = Arc::new(cfg);
    let stats = Arc::new(Stats::default());

    let (relay, handle) = Relay::new(
        cfg.relay.clone(),
        cfg.serial.clone(),
        cfg.log.traffic,
        stats.clone(),
        shutdown.clone(),
    );
    let relay = relay.with_watchdog(notify::watchdog_interval());
    let board = Arc::new(Board::default());
    board.add_line(relay.metrics());
    board.add_listener(Arc::new(ListenerMetrics {
        name: local.to_string(),
        stats: stats.clone(),
    }));
    // Off unless asked for: then nothing but the Modbus port listens.
    let mut http = reload::MetricsListener::new(board.clone(), shutdown.clone());
    if let Some(addr) = cfg.metrics.listen {
        let bound =
            metrics::http::bind(addr).map_err(|error| GatewayError::MetricsBind { addr, error })?;
        http.start(addr, bound);
    }
    // Before "listening on", as the other handlers: a reload asked for at once finds
    // its handler, never SIGHUP's default action (the end of the process).
    let hup = match load {
        Some(load) => match tokio::signal::unix::signal(SignalKind::hangup()) {
            Ok(hup) => Some((hup, load)),
            Err(e) => {
                warn!("cannot install the SIGHUP handler: no reload ({e})");
                None
            }
        },
        None => None,
    };
    // Before "listening on": from then on a signal finds its handler.
    let signals = user_signals();
    info!(serial = %cfg.serial.path, "listening on {local}");
    // Before the relay first runs, so READY=1 precedes its first WATCHDOG=1.
    notify::ready(&format!("listening on {local}, serial {}", cfg.serial.path));
    let relay_task = tokio::spawn(relay.run());
    if let Some((hup, load)) = hup {
        let relay = handle.clone();
        let stop = shutdown.clone();
        tokio::spawn(reload::on_sighup(
            hup,
            running.clone(),
            load,
            relay,
            http,
            stop,
        ));
    }
    if notify::under_systemd() {
        tokio::spawn(metrics::status::refresh(board.clone(), shutdown.clone()));
    }
    if let Some(signals) = signals {
        tokio::spawn(report_on_signal(signals, stats.clone(), shutdown.clone()));
    }

    let tracker = TaskTracker::new();
    tcp::accept_loop(
        listener,
        cfg.clone(),
        handle,
        stats.clone(),
        shutdown.clone(),
        tracker.clone(),
    )
    .await;

    // Shutdown: the listener is closed; connections stop reading and the relay answers
    // what is queued (0x0A) and waits for what is on the line.
    // As the configuration runs now: a reload may have changed the timeouts.
    let answer_within = running.lock().expect("not poisoned").relay.answer_within();
    let bound = answer_within + Duration::from_secs(2);
    info!("shutting down: draining in-flight requests");
    // systemd waits for the drain, and a second more for the exit itself.
    notify::stopping(bound + Duration::from_secs(1));
    tracker.close();
    if tokio::time::timeout(bound, async {
        let _ = relay_task.await;
        tracker.wait().await;
    })
    .await
    .is_err()
    {
        warn!("drain did not finish in {bound:?}; exiting anyway");
    }
    info!(%stats, "stopped");
    Ok(stats)
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
    stats: Arc<Stats>,
    shutdown: CancellationToken,
) {
    loop {
        tokio::select! {
            _ = usr1.recv() => info!(%stats, "counters (SIGUSR1)"),
            _ = usr2.recv() => debug!("SIGUSR2 ignored"),
            _ = shutdown.cancelled() => return,
        }
    }
}

/// What the configuration cannot honour on this line ([`warnings`]), said once at start.
fn warn_inapplicable(cfg: &Config) {
    for warning in warnings(cfg) {
        warn!("{warning}");
    }
}

/// Settings an RTU or ASCII line cannot honour: said at start (and by `mbgate
/// check-config`), not refused, so a file written for MBAP keeps working when only the
/// framing changes.
pub fn warnings(cfg: &Config) -> Vec<String> {
    let framing = cfg.serial.framing.name();
    let mut said = Vec::new();
    if cfg.serial.framing == Framing::Mbap {
        return said;
    }
    if cfg.relay.max_in_flight > 1 {
        said.push(format!(
            "framing = {framing} has no transaction id: one request at a time \
             (max_in_flight = {} taken as 1)",
            cfg.relay.max_in_flight
        ));
    }
    if cfg.relay.notifications == Notifications::Broadcast {
        said.push(format!(
            "framing = {framing}: a frame that answers no request is dropped; \
             notifications = broadcast does not apply"
        ));
    }
    said
}
