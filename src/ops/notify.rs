//! systemd's notify protocol (sd_notify(3)) for `Type=notify` units: READY=1 once the
//! listener is bound, STOPPING=1 when shutdown begins, WATCHDOG=1 from the relay's loop,
//! STATUS= every few seconds (`crate::ops::metrics::status`).
//!
//! Outside systemd (no `NOTIFY_SOCKET`) every call does nothing. A failure to notify is
//! never fatal: it is logged (a warning the first time, then at debug level) and the
//! gateway carries on; systemd then restarts it if it needed the message.

use sd_notify::NotifyState;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use tracing::{debug, warn};

/// READY=1: the listener is bound and masters can connect. `status` becomes the
/// unit's STATUS= line (`systemctl status`).
pub(crate) fn ready(status: &str) {
    send(&[NotifyState::Ready, NotifyState::Status(status)]);
}

/// STOPPING=1: shutdown has begun. `drain` is the longest the drain may take; systemd
/// is asked to wait at least that long (EXTEND_TIMEOUT_USEC), so a long response
/// timeout never has the gateway killed mid-drain by a shorter `TimeoutStopSec`.
pub(crate) fn stopping(drain: Duration) {
    let usec = u32::try_from(drain.as_micros()).unwrap_or(u32::MAX);
    send(&[
        NotifyState::Stopping,
        NotifyState::Status("draining in-flight requests"),
        NotifyState::ExtendTimeoutUsec(usec),
    ]);
}

/// STATUS=: the line `systemctl status` shows.
pub(crate) fn status(status: &str) {
    send(&[NotifyState::Status(status)]);
}

/// Is the process run by systemd with `Type=notify` (is `NOTIFY_SOCKET` set)?
pub(crate) fn under_systemd() -> bool {
    std::env::var_os("NOTIFY_SOCKET").is_some()
}

/// WATCHDOG=1: the caller's loop is alive.
pub(crate) fn watchdog() {
    send(&[NotifyState::Watchdog]);
}

/// How often to send WATCHDOG=1: half of `WATCHDOG_USEC` (sd_watchdog_enabled(3)), or
/// `None` when systemd asked for no watchdog (or asked another process).
pub(crate) fn watchdog_interval() -> Option<Duration> {
    sd_notify::watchdog_enabled()
        .filter(|d| !d.is_zero())
        .map(|d| d / 2)
}

fn send(states: &[NotifyState<'_>]) {
    static WARNED: AtomicBool = AtomicBool::new(false);
    if let Err(e) = sd_notify::notify(states) {
        if WARNED.swap(true, Ordering::Relaxed) {
            debug!("cannot notify systemd: {e}");
        } else {
            warn!("cannot notify systemd (NOTIFY_SOCKET): {e}; carrying on");
        }
    }
}
