//! Reload (SIGHUP, `systemctl reload`, `mbgate reload`): the configuration file is
//! read again and what can change without dropping a master is applied at once
//! (docs/configuration.md "Reload"); what needs a restart is said in the log and left as it runs. The
//! lines are known by their port or address, not their place in the file
//! (`changes.rs`): a file that adds or removes a line, or does not load at all, is
//! refused with the reason, and the running configuration stays. Every change applied
//! is named, line by line and key by key, in the log and in `mbgate reload`'s answer.
//! Every reload also reads the certificates of the TLS listeners again
//! (docs/security.md "Renewing certificates"), and the metrics listener's web
//! configuration file with its certificates and users (docs/watching.md), whatever
//! becomes of the file.

mod changes;

use crate::config::{Config, ConfigError};
use crate::line::relay::{Command, RelayHandle};
use crate::ops::metrics::listener::MetricsListener;
use crate::tls::server::Acceptor;
use std::sync::Arc;
use tokio::sync::{mpsc, oneshot, watch};
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

/// Runs the dials of a configuration (`[[dial]]`), as the masters' side does it.
pub(crate) type RunDials = Box<dyn Fn(&[crate::config::dial::DialConfig]) + Send + Sync>;

/// Runs the UDP listeners of a configuration (`[[listen]]` with `transport = "udp"`).
pub(crate) type RunUdps = Box<dyn Fn(&[crate::config::ListenConfig]) -> Vec<String> + Send + Sync>;

/// Reads the configuration again, as at start (the file, then the flags on top).
pub(crate) type Loader = Box<dyn Fn() -> Result<Config, ConfigError> + Send + Sync>;

/// What a reload did: refused (why), or done (what it applied, and what changed in the
/// file but waits for a restart).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum ReloadOutcome {
    Refused(String),
    Done {
        applied: Vec<String>,
        restart: Vec<String>,
    },
}

impl ReloadOutcome {
    /// What the log says, and `mbgate reload` prints: one line, and a second for what
    /// waits for a restart.
    pub(crate) fn lines(&self) -> Vec<String> {
        match self {
            ReloadOutcome::Refused(why) => {
                vec![format!(
                    "reload refused: {why}; the running configuration stays"
                )]
            }
            ReloadOutcome::Done { applied, restart } => {
                let mut out = vec![match (applied.is_empty(), restart.is_empty()) {
                    (false, _) => format!("reloaded: {}", applied.join(", ")),
                    (true, true) => "reloaded: nothing to change".to_owned(),
                    (true, false) => "reloaded: nothing a reload applies changed".to_owned(),
                }];
                if !restart.is_empty() {
                    out.push(format!(
                        "reload: changed in the file but applied only by a restart (systemctl restart): {}",
                        restart.join(", ")
                    ));
                }
                out
            }
        }
    }

    /// Was the file taken (applied, or with nothing to apply)?
    pub(crate) fn taken(&self) -> bool {
        matches!(self, ReloadOutcome::Done { .. })
    }

    fn log(&self) {
        let lines = self.lines();
        match self {
            ReloadOutcome::Refused(_) => error!("{}", lines[0]),
            ReloadOutcome::Done { .. } => {
                info!("{}", lines[0]);
                if let Some(restart) = lines.get(1) {
                    warn!("{restart}");
                }
            }
        }
    }
}

/// What `mbgate reload` is told: the outcome, then what became of each TLS
/// listener's certificate.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct ReloadReport {
    pub(crate) outcome: ReloadOutcome,
    pub(crate) certificates: Vec<String>,
}

impl ReloadReport {
    /// The lines `mbgate reload` prints, as the log says them.
    pub(crate) fn lines(&self) -> Vec<String> {
        let mut lines = self.outcome.lines();
        lines.extend(self.certificates.iter().cloned());
        lines
    }
}

/// A request for a reload from `mbgate reload` (over the control socket), answered
/// with its outcome.
pub(crate) type ReloadAsked = oneshot::Sender<ReloadReport>;

/// The way to ask the running gateway for a reload.
#[derive(Debug, Clone)]
pub(crate) struct ReloadHandle(mpsc::UnboundedSender<ReloadAsked>);

impl ReloadHandle {
    /// A handle, and what [`on_sighup`] takes the requests from.
    pub(crate) fn new() -> (Self, mpsc::UnboundedReceiver<ReloadAsked>) {
        let (tx, rx) = mpsc::unbounded_channel();
        (Self(tx), rx)
    }

    /// Reloads and says how it went; `None` if the gateway is stopping.
    pub(crate) async fn reload(&self) -> Option<ReloadReport> {
        let (tx, rx) = oneshot::channel();
        self.0.send(tx).ok()?;
        rx.await.ok()
    }
}

/// How a reload reaches a running line, whichever side its device is on.
#[derive(Debug, Clone)]
pub(crate) enum LineHandle {
    /// A relay: the device is a slave.
    Relay(RelayHandle),
    /// A master line: the device is the master.
    Master(crate::line::bridge::MasterHandle),
}

impl LineHandle {
    /// Gives the line `line`'s reloadable settings; `None` when it has stopped.
    fn retune(&self, line: crate::config::LineConfig, traffic: bool) -> Option<()> {
        match (self, line.master) {
            (LineHandle::Master(m), Some(routes)) => m.retune(routes).ok(),
            (LineHandle::Relay(r), _) => {
                let retune = Command::Retune {
                    relay: Box::new(line.relay),
                    units: line.unit_tables,
                    traffic,
                };
                r.send(retune).ok()
            }
            // Lines are matched by their port and a line's side is fixed: never met.
            (LineHandle::Master(_), None) => Some(()),
        }
    }
}

/// What a reload reloads: the file, the lines it retunes, the metrics listener it
/// moves, and the TLS listeners whose certificates it reads again.
pub(crate) struct Reloadable {
    /// The configuration as it runs: a reload publishes the merged one here, every
    /// master's connection reads it.
    pub(crate) running: watch::Sender<Arc<Config>>,
    /// The masters connected now, whose priority classes a reload may change.
    pub(crate) masters: Arc<crate::ops::metrics::ConnectedMasters>,
    pub(crate) load: Loader,
    pub(crate) lines: Vec<LineHandle>,
    pub(crate) metrics: MetricsListener,
    pub(crate) acceptors: Vec<Arc<Acceptor>>,
    /// Where the metrics count the reloads and say how the last went.
    pub(crate) counted: Arc<crate::ops::metrics::Reloads>,
    /// Runs the dials of the configuration reloaded: adds, removes and changes them
    /// (the masters' side does it; the gateway hands it over).
    pub(crate) dials: RunDials,
    /// Runs the UDP listeners of the configuration reloaded, and says what it could
    /// not bind.
    pub(crate) udps: RunUdps,
}

/// Reloads on each SIGHUP, and on each request of `mbgate reload` (`asked`), until
/// shutdown.
pub(crate) async fn on_sighup(
    mut hup: tokio::signal::unix::Signal,
    mut asked: mpsc::UnboundedReceiver<ReloadAsked>,
    mut it: Reloadable,
    shutdown: CancellationToken,
) {
    loop {
        let answer = tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = hup.recv() => {
                info!("SIGHUP received: reading the configuration again");
                None
            }
            Some(a) = asked.recv() => {
                info!("reload asked for (mbgate reload): reading the configuration again");
                Some(a)
            }
        };
        let mut certificates = reload_certificates(&it.acceptors);
        let Some(outcome) = reload(&mut it) else {
            return; // a relay has stopped: shutting down
        };
        // With the file as it runs now: the new one if taken, else the old.
        let web = it.running.borrow().metrics.web_config.clone();
        certificates.extend(reload_web(&it.metrics, &web));
        outcome.log();
        it.counted
            .reloaded(outcome.taken(), std::time::SystemTime::now());
        if let Some(a) = answer {
            let _ = a.send(ReloadReport {
                outcome,
                certificates,
            });
        }
    }
}

/// The certificate, key and CA of every TLS listener read again (docs/security.md
/// "Renewing certificates"): new connections use them, connected masters keep their
/// session. A file that does not load leaves that listener as it was, and says why.
/// What was said, a line a listener.
fn reload_certificates(acceptors: &[Arc<Acceptor>]) -> Vec<String> {
    let mut said = Vec::new();
    for a in acceptors {
        match a.reload() {
            Ok(subject) => {
                let line = format!(
                    "{}: certificate, key and client CA read again (the gateway is {subject:?}); connected masters keep their session",
                    a.name()
                );
                info!("{line}");
                said.push(line);
            }
            Err(e) => {
                let line = format!(
                    "{}: not reloaded, the certificate in use stays: {e}",
                    a.name()
                );
                warn!("{line}");
                said.push(line);
            }
        }
    }
    said
}

/// The metrics listener's web configuration file read again, its certificates and
/// users with it (docs/watching.md "Behind TLS and a password"): new connections are
/// served with it. A file that does not load leaves the one in use, and says why.
/// What was said, a line (none without a file, before or now).
fn reload_web(metrics: &MetricsListener, path: &str) -> Vec<String> {
    let had = metrics.has_web_file();
    match metrics.reload_web(path) {
        Ok(_) if path.trim().is_empty() && !had => Vec::new(),
        Ok(said) => {
            let line = if path.trim().is_empty() {
                format!("metrics.web_config: none now: {said}")
            } else {
                format!("metrics.web_config: {} read again: {said}", path.trim())
            };
            info!("{line}");
            vec![line]
        }
        Err(e) => {
            let line = format!("metrics.web_config: not reloaded, the one in use stays: {e}");
            warn!("{line}");
            vec![line]
        }
    }
}

/// One reload: the file read, its lines matched to the running ones, what a reload
/// applies applied (the relays' timeouts and retries, the log, the metrics listener,
/// the dials and UDP listeners, the masters' priority classes). `None` when a relay
/// has stopped.
fn reload(it: &mut Reloadable) -> Option<ReloadOutcome> {
    let read = match (it.load)() {
        Ok(read) => read,
        Err(e) => return Some(ReloadOutcome::Refused(e.to_string())),
    };
    let old = Arc::clone(&it.running.borrow());
    let matched = match changes::match_lines(&old.lines, &read.lines) {
        Ok(m) => m,
        Err(why) => return Some(ReloadOutcome::Refused(why)),
    };
    let mut new = changes::merged(&old, &read, &matched);
    if let Err(e) = it.metrics.set(new.metrics.listen) {
        error!("reload: {e}; the metrics listener stays as it was");
        new.metrics = old.metrics.clone();
    }
    crate::ops::logging::reload(&new.log);
    for (handle, line) in it.lines.iter().zip(new.lines.clone()) {
        handle.retune(line, new.log.traffic)?;
    }
    (it.dials)(&new.dials);
    for unbound in (it.udps)(&new.listeners) {
        error!("reload: {unbound}");
    }
    let said = |a: &Config, b: &Config, matched: &[usize]| -> Vec<String> {
        let changes = changes::changes(a, b, matched);
        changes.into_iter().map(|c| c.said).collect()
    };
    let same: Vec<usize> = (0..matched.len()).collect();
    let applied = said(&old, &new, &same);
    let restart = said(&new, &read, &matched);
    // Published and the masters reclassified under the watch's write lock: a
    // connection tells its class at connect while it borrows the watch (its read
    // lock), so it tells either its old class before the reclassifying, or its new
    // one after it.
    it.running.send_modify(|running| {
        *running = Arc::new(new);
        reclassify(running, &it.masters, &it.lines);
    });
    Some(ReloadOutcome::Done { applied, restart })
}

/// Tells every line each connected master's priority class under `running`, the
/// configuration as it runs from now on (docs/masters.md "Priority"). Called under
/// the running configuration's write lock (`watch::Sender::send_modify`), whose
/// read lock a connection holds while it tells its class at connect
/// (src/masters/tcp/connection/mod.rs `begin`): a master that connects meanwhile tells
/// either its old class before this, or its new one.
fn reclassify(
    running: &Config,
    masters: &crate::ops::metrics::ConnectedMasters,
    lines: &[LineHandle],
) {
    for m in masters.list() {
        let role = m.tls.as_ref().map(|(role, _)| role.as_str());
        let class = running.priority_of(&m.source, role);
        for line in lines {
            if let LineHandle::Relay(relay) = line {
                let _ = relay.send(Command::Priority {
                    conn: m.conn,
                    class,
                });
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A configuration with every key changed from the defaults but `serial.direction`
    /// (it cannot go with `rs485 = true`).
    pub(super) fn all_changed() -> Config {
        let text = "[serial]\npath = \"/dev/x\"\nbaud_rate = 9600\ndata_bits = 7\nparity = \"odd\"\n\
            stop_bits = 2\nflow_control = \"none\"\nframing = \"rtu\"\nsilence_floor_ms = 3\n\
            port_kind = \"wire\"\nlow_latency = false\n\
            rs485 = true\nrs485_delay_before_send_ms = 1\nrs485_delay_after_send_ms = 1\necho = true\n\
            direction_invert = true\ndirection_gpio_chip = \"gpiochip1\"\ndirection_gpio_line = 4\n\
            direction_delay_before_us = 1\ndirection_delay_after_us = 1\n\
            inter_frame_gap_us = 900\n\
            [tcp]\nlisten = \"127.0.0.1:1502\"\nmax_connections = 3\nidle_timeout_ms = 5\n\
            [relay]\nresponse_timeout_ms = 7\nframe_gap_ms = 7\nmax_in_flight = 2\n\
            max_pending_per_connection = 2\nqueue_depth = 9\nretries = 2\nretry_writes = true\n\
            notifications = \"broadcast\"\ndevice_notifications = true\nbroadcast_delay_ms = 1\nbroadcast_reply = \"echo\"\n\
            unit_backoff = false\nunit_backoff_after = 9\nunit_backoff_ms = 9\nunit_backoff_max_ms = 99\n\
            probe_timeout_ms = 9\ntimeout_guard_ms = 9\ncoalesce = false\ncache_ms = 9\n\
            request_pause_ms = 9\n\
            [log]\nlevel = \"debug\"\ntraffic = true\n[metrics]\nlisten = \"127.0.0.1:9502\"\nweb_config = \"/w.yml\"\n\
            [capture]\nfile = \"/x\"\nfiles = 3\nfile_size_kb = 99\n[control]\nsocket = \"/y\"\n";
        crate::config::parse(text, "t").unwrap()
    }
}
