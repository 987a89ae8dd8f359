//! Reload (SIGHUP, `systemctl reload`): the configuration file is read again and what
//! can change without dropping a master is applied at once (README "Reload"); what
//! needs a restart is said in the log and left as it runs. A file that does not load
//! is refused with the usual precise error, and the running configuration stays.

use crate::config::{Config, ConfigError, RelayConfig, KEYS};
use crate::metrics::{http, Board};
use crate::relay::{Command, RelayHandle};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

/// Reads the configuration again, as at start (the file, then the flags on top).
pub type Loader = Box<dyn Fn() -> Result<Config, ConfigError> + Send + Sync>;

/// The keys a reload applies while the gateway runs.
pub(crate) const RELOADABLE: [&str; 7] = [
    "relay.response_timeout_ms",
    "relay.retries",
    "relay.retry_writes",
    "relay.probe_timeout_ms",
    "log.level",
    "log.traffic",
    "metrics.listen",
];

/// `running` with the [`RELOADABLE`] keys of `read` (the rest needs a restart); with
/// `[[line]]` tables, each line's `relay` keys too, line by line, while the file keeps
/// the same lines.
pub(crate) fn merged(running: &Config, read: &Config) -> Config {
    let mut c = running.clone();
    retune(&mut c.relay, &read.relay);
    if c.lines.len() == read.lines.len() {
        for (line, new) in c.lines.iter_mut().zip(&read.lines) {
            retune(&mut line.relay, &new.relay);
        }
    }
    c.log = read.log.clone();
    c.metrics = read.metrics.clone();
    c
}

/// The reloadable keys of a line's `relay` table.
fn retune(into: &mut RelayConfig, from: &RelayConfig) {
    into.response_timeout_ms = from.response_timeout_ms;
    into.retries = from.retries;
    into.retry_writes = from.retry_writes;
    into.probe_timeout_ms = from.probe_timeout_ms;
}

/// The keys whose values differ between `a` and `b`, as `section.key = value` of `b`.
fn changed(a: &Config, b: &Config) -> Vec<(String, String)> {
    KEYS.iter()
        .filter(|k| (k.get)(a) != (k.get)(b))
        .map(|k| (format!("{}.{}", k.section, k.name), (k.get)(b)))
        .collect()
}

/// The metrics listener as it runs, moved or stopped by a reload.
pub(crate) struct MetricsListener {
    board: Arc<Board>,
    running: Option<(SocketAddr, CancellationToken)>,
    shutdown: CancellationToken,
}

impl MetricsListener {
    pub(crate) fn new(board: Arc<Board>, shutdown: CancellationToken) -> Self {
        Self {
            board,
            running: None,
            shutdown,
        }
    }

    /// Serves on `listener` (bound at start, so a bad address fails the start).
    pub(crate) fn start(&mut self, addr: SocketAddr, listener: std::net::TcpListener) {
        let stop = self.shutdown.child_token();
        http::spawn(listener, self.board.clone(), stop.clone());
        self.running = Some((addr, stop));
    }

    /// Listens on `want` (none: not at all). A new address that cannot be bound
    /// leaves the old listener running, and says so.
    fn set(&mut self, want: Option<SocketAddr>) -> Result<(), String> {
        if self.running.as_ref().map(|(a, _)| *a) == want {
            return Ok(());
        }
        let bound = match want {
            Some(addr) => match http::bind(addr) {
                Ok(l) => Some((addr, l)),
                Err(e) => return Err(format!("cannot listen for metrics on {addr}: {e}")),
            },
            None => None,
        };
        if let Some((_, stop)) = self.running.take() {
            stop.cancel();
        }
        if let Some((addr, listener)) = bound {
            self.start(addr, listener);
        }
        Ok(())
    }
}

/// Reloads on each SIGHUP until shutdown; `running` is the configuration in force.
pub(crate) async fn on_sighup(
    mut hup: tokio::signal::unix::Signal,
    running: Arc<Mutex<Config>>,
    load: Loader,
    relays: Vec<RelayHandle>,
    mut metrics: MetricsListener,
    shutdown: CancellationToken,
) {
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = hup.recv() => {}
        }
        info!("SIGHUP received: reading the configuration again");
        let read = match load() {
            Ok(read) => read,
            Err(e) => {
                error!("reload refused: {e}; the running configuration stays");
                continue;
            }
        };
        let old = running.lock().expect("not poisoned").clone();
        let mut new = merged(&old, &read);
        let mut restart = Vec::new();
        for (key, value) in changed(&old, &read) {
            if !RELOADABLE.contains(&key.as_str()) {
                restart.push(format!("{key} = {value}"));
            }
        }
        // The lines and listeners themselves (their number, units, devices, the keys
        // of each line that a reload does not apply).
        if (&new.lines, &new.listeners) != (&read.lines, &read.listeners) {
            restart.push("the [[line]] or [[listen]] tables".into());
        }
        if let Err(e) = metrics.set(new.metrics.listen) {
            error!("reload: {e}; the metrics listener stays as it was");
            new.metrics = old.metrics.clone();
        }
        crate::logging::reload(&new.log);
        for (relay, line) in relays.iter().zip(new.lines()) {
            let retune = Command::Retune {
                relay: line.relay,
                traffic: new.log.traffic,
            };
            if relay.send(retune).is_err() {
                return; // the relay has stopped: shutting down
            }
        }
        let applied: Vec<String> = changed(&old, &new)
            .into_iter()
            .map(|(k, v)| format!("{k} = {v}"))
            .collect();
        *running.lock().expect("not poisoned") = new;
        if applied.is_empty() {
            info!("reloaded: nothing to change");
        } else {
            info!("reloaded: {}", applied.join(", "));
        }
        if !restart.is_empty() {
            warn!(
                "reload: changed in the file but applied only by a restart (systemctl restart): {}",
                restart.join(", ")
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A configuration with every key changed from the defaults.
    fn all_changed() -> Config {
        let text = "[serial]\npath = \"/dev/x\"\nbaud_rate = 9600\ndata_bits = 7\nparity = \"odd\"\n\
            stop_bits = 2\nflow_control = \"none\"\nframing = \"rtu\"\nsilence_floor_ms = 3\n\
            port_kind = \"wire\"\nlow_latency = false\n\
            rs485 = true\nrs485_delay_before_send_ms = 1\nrs485_delay_after_send_ms = 1\necho = true\n\
            inter_frame_gap_us = 900\n\
            [tcp]\nlisten = \"127.0.0.1:1502\"\nmax_connections = 3\nidle_timeout_ms = 5\n\
            [relay]\nresponse_timeout_ms = 7\nframe_gap_ms = 7\nmax_in_flight = 2\n\
            max_pending_per_connection = 2\nqueue_depth = 9\nretries = 2\nretry_writes = true\n\
            notifications = \"broadcast\"\ndevice_notifications = true\nbroadcast_delay_ms = 1\nbroadcast_reply = \"echo\"\n\
            unit_backoff = false\nunit_backoff_after = 9\nunit_backoff_ms = 9\nunit_backoff_max_ms = 99\n\
            probe_timeout_ms = 9\ntimeout_guard_ms = 9\ncoalesce = false\ncache_ms = 9\n\
            request_pause_ms = 9\n\
            [log]\nlevel = \"debug\"\ntraffic = true\n[metrics]\nlisten = \"127.0.0.1:9502\"\n";
        crate::config::parse(text, "t").unwrap()
    }

    /// With `[[line]]` tables each line takes its own reloadable keys; its units do not
    /// change (they need a restart, and `merged` leaves them as they run).
    #[test]
    fn each_line_takes_its_own_timeout() {
        let file = |t1: u32, t2: u32, units2: &str| {
            let text = format!(
                "[[line]]\nunits = [1]\nserial = {{ path = \"/dev/a\" }}\nrelay = {{ response_timeout_ms = {t1} }}\n\
                 [[line]]\nunits = [{units2}]\nserial = {{ path = \"/dev/b\" }}\nrelay = {{ response_timeout_ms = {t2} }}\n"
            );
            crate::config::parse(&text, "t").unwrap()
        };
        let (old, read) = (file(100, 200, "2"), file(300, 400, "2, 3"));
        let new = merged(&old, &read);
        let timeouts: Vec<u64> = new
            .lines
            .iter()
            .map(|l| l.relay.response_timeout_ms)
            .collect();
        assert_eq!(timeouts, [300, 400]);
        assert_eq!(new.lines[1].units, old.lines[1].units);
        assert_ne!(
            new.lines, read.lines,
            "the units' change waits for a restart"
        );
    }

    #[test]
    fn a_reload_takes_exactly_the_reloadable_keys() {
        let (old, read) = (Config::default(), all_changed());
        assert_eq!(changed(&old, &read).len(), KEYS.len(), "every key differs");
        let new = merged(&old, &read);
        let taken: Vec<String> = changed(&old, &new).into_iter().map(|(k, _)| k).collect();
        assert_eq!(taken, RELOADABLE);
    }
}
