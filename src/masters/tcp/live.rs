//! The configuration as it runs now, as one task of the masters' side reads it: a
//! receiver of the gateway's watch (a reload publishes the merged configuration
//! through it, src/gateway/reload/mod.rs), with the value last seen kept at hand so
//! a read costs one atomic load of the watch's version, never its lock.

use crate::config::Config;
use std::sync::Arc;
use tokio::sync::watch;

/// The running configuration, published by the gateway: each connection holds a
/// receiver, and reads it where a reload's value must be seen.
pub(crate) type Running = watch::Receiver<Arc<Config>>;

/// One task's view of the running configuration (a connection's reader, its writer,
/// a UDP listener's receive loop): the value last seen, taken again only when the
/// gateway has published a new one.
pub(crate) struct Live {
    running: Running,
    seen: Arc<Config>,
}

impl Live {
    /// The configuration as it runs now, and from now on.
    pub(crate) fn new(running: &Running) -> Live {
        let mut running = running.clone();
        let seen = running.borrow_and_update().clone();
        Live { running, seen }
    }

    /// The configuration as it runs now: the value seen last, unless a reload has
    /// published another since (an acquire load of the watch's version; the watch's
    /// lock only when it moved). With the gateway gone, the last value stays.
    #[inline]
    pub(crate) fn get(&mut self) -> &Config {
        if self.running.has_changed().unwrap_or(false) {
            self.seen = self.running.borrow_and_update().clone();
        }
        &self.seen
    }
}
