//! The masters attached to the relay and the fan-out of device notifications to them:
//! dropped or broadcast (`notifications`), a master not reading missing them (counted).

use super::ids::IdMap;
use super::ConnId;
use crate::config::Notifications;
use crate::frame::Adu;
use crate::line::outbox::Notifier;
use crate::ops::stats::Stats;
use tracing::debug;

/// The masters attached to the relay, and what becomes of a notification.
pub(super) struct Masters {
    conns: IdMap<ConnId, Notifier>,
    policy: Notifications,
}

impl Masters {
    pub(super) fn new(policy: Notifications) -> Self {
        Self {
            conns: IdMap::default(),
            policy,
        }
    }

    pub(super) fn attach(&mut self, conn: ConnId, notifier: Notifier) {
        self.conns.insert(conn, notifier);
    }

    pub(super) fn detach(&mut self, conn: ConnId) {
        self.conns.remove(&conn);
    }

    /// How many are attached.
    pub(super) fn len(&self) -> usize {
        self.conns.len()
    }

    /// A frame from the device that answers no request and is no late reply.
    pub(super) fn notification(&self, frame: Adu, stats: &Stats) {
        match self.policy {
            Notifications::Drop => {
                stats.add(&stats.notifications_dropped, 1);
                debug!("unsolicited frame dropped: {:?}", frame);
            }
            Notifications::Broadcast => self.broadcast(frame, stats),
        }
    }

    /// Sends a device notification to every master with room for it; a master whose
    /// spare room is used up (it is not reading) misses it (counted).
    fn broadcast(&self, frame: Adu, stats: &Stats) {
        stats.add(&stats.notifications_broadcast, 1);
        for notifier in self.conns.values() {
            if !notifier.notify(frame.clone()) {
                stats.add(&stats.notifications_missed, 1);
            }
        }
    }
}
