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

#[cfg(test)]
mod tests {
    use super::*;

    /// A task's view follows what the gateway publishes, from a receiver made before
    /// it or after; the last value stays once the gateway is gone.
    #[test]
    fn a_task_sees_each_configuration_published_and_keeps_the_last() {
        let running = watch::Sender::new(Arc::new(Config::default()));
        let before = running.subscribe();
        let mut live = Live::new(&before);
        assert!(!live.get().log.traffic);
        running.send_modify(|c| {
            let mut next = Config::clone(c);
            next.log.traffic = true;
            *c = Arc::new(next);
        });
        assert!(live.get().log.traffic, "published after the task began");
        let mut late = Live::new(&before);
        assert!(late.get().log.traffic, "a receiver made before the reload");
        drop(running);
        assert!(live.get().log.traffic, "the last value stays");
    }
}
