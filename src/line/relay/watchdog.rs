//! systemd's watchdog, pinged from a line's own loop (the gateway's first line, a relay
//! or a master line): if the loop wedges, the pings stop and systemd restarts the
//! gateway.

use crate::ops::notify;
use std::time::Duration;
use tokio::time::Instant;

pub(crate) struct Watchdog {
    every: Duration,
    next: Instant,
}

impl Watchdog {
    /// Pings every `every`, the first at `now`.
    pub(crate) fn new(every: Duration, now: Instant) -> Self {
        Self { every, next: now }
    }

    /// When the next ping is due.
    pub(crate) fn next(&self) -> Instant {
        self.next
    }

    /// Sends WATCHDOG=1 if it is due at `now`.
    pub(crate) fn pet(&mut self, now: Instant) {
        if now >= self.next {
            notify::watchdog();
            self.next = now + self.every;
        }
    }
}
