//! A master line made from its configuration: its passive routes bound (a taken
//! address is an error at start), a task for each route's connection, its counts on its
//! metrics; the line's loop is `mod.rs`'s.

use super::requests::Requests;
use super::routing::Routing;
use super::{slave, Bridge, BridgeError, MasterHandle, MasterLineTask, Published, Timing};
use crate::config::master::MasterLine;
use crate::config::Framing;
use crate::frame::Adu;
use crate::line::port::Port;
use crate::line::relay::watchdog::Watchdog;
use crate::ops::capture::Tap;
use crate::ops::metrics::LineMetrics;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::info;

/// What a master line is made of (`start`).
pub(crate) struct MasterLineParts {
    /// The serial port the master is on.
    pub(crate) port: Box<dyn Port>,
    /// Its framing and its timing (`Timing::of_line`).
    pub(crate) framing: Framing,
    pub(crate) timing: Timing,
    /// The routes to the slaves.
    pub(crate) master: MasterLine,
    /// Log every frame as hex (`log.traffic`).
    pub(crate) traffic: bool,
    /// The capture's taps: the serial line's, and the slaves' TCP side's.
    pub(crate) line_tap: Tap,
    pub(crate) tcp_tap: Tap,
    /// Where its counts go.
    pub(crate) metrics: Arc<LineMetrics>,
    /// systemd's interval, when this line pets it (the gateway's first line does; the
    /// gateway says READY=1 and STOPPING=1).
    pub(crate) watchdog: Option<Duration>,
}

/// Makes the master line of `parts`: binds its passive routes (a taken address is an
/// error now, not later), starts a task for each route's connection, and puts its
/// counts on its metrics.
pub(crate) async fn start(
    parts: MasterLineParts,
) -> Result<(MasterLineTask, MasterHandle), BridgeError> {
    let MasterLineParts {
        port,
        framing,
        timing,
        master,
        traffic,
        line_tap,
        tcp_tap,
        metrics,
        watchdog,
    } = parts;
    let (to_slaves, events, slaves_stop, tracker) = spawn_slaves(&master, &tcp_tap).await?;
    let routes: Vec<String> = master
        .routes
        .iter()
        .map(|r| match r.units.as_slice() {
            [] => format!("other units -> {}", r.peer),
            u => format!("units {u:?} -> {}", r.peer),
        })
        .collect();
    info!(
        serial = port.name(),
        "master line on {} ({}): {}",
        port.name(),
        framing.name(),
        routes.join("; ")
    );
    let line = Bridge {
        requests: Requests::new(framing),
        routing: Routing::new(master, framing != Framing::Mbap),
        timing,
        traffic,
        framing,
        tap: line_tap,
        to_slaves,
        watchdog: watchdog.map(|every| Watchdog::new(every, Instant::now())),
        metrics,
        published: Published::default(),
    };
    let (retune, retunes) = mpsc::unbounded_channel();
    let task = MasterLineTask {
        port,
        line,
        events,
        retunes,
        slaves_stop,
        tracker,
    };
    Ok((task, MasterHandle(retune)))
}

/// A task for each route's connection to its slave (a passive route's address bound
/// first): what the line sends each, the events they send back, what stops them once
/// the line has drained, and the tracker they run on.
async fn spawn_slaves(master: &MasterLine, tcp_tap: &Tap) -> Result<Slaves, BridgeError> {
    let (events_tx, events) = mpsc::channel(slave::EVENTS);
    let mut to_slaves = Vec::new();
    // Stopped once the line has drained at shutdown: the replies still due come
    // through these connections.
    let slaves_stop = CancellationToken::new();
    let tracker = tokio_util::task::TaskTracker::new();
    for (i, route) in master.routes.iter().enumerate() {
        let listener = slave::bind(route)
            .await
            .map_err(|error| BridgeError::Bind {
                route: i,
                addr: route.peer.to_string(),
                error,
            })?;
        if let Some(l) = &listener {
            if let Ok(a) = l.local_addr() {
                info!(route = i, "waiting for the slave to connect to {a}");
            }
        }
        let (tx, rx) = mpsc::unbounded_channel();
        to_slaves.push(tx);
        tracker.spawn(slave::run(
            i,
            route.clone(),
            listener,
            rx,
            events_tx.clone(),
            (tcp_tap.clone(), slaves_stop.clone()),
        ));
    }
    drop(events_tx);
    Ok((to_slaves, events, slaves_stop, tracker))
}

/// What [`spawn_slaves`] gives: each route's sender, the events, the stop, the tracker.
type Slaves = (
    Vec<mpsc::UnboundedSender<Adu>>,
    mpsc::Receiver<slave::SlaveEvent>,
    CancellationToken,
    tokio_util::task::TaskTracker,
);
