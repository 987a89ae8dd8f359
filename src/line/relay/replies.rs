//! What the loop does with the frames the line took off the wire: a reply matched to
//! its request (answered, cached, its time learned), a corrupt one failed as the
//! in-flight table says, a late reply or a notification dropped or fanned out.

use super::inflight::Failure;
use super::line::{Seen, Unsolicited};
use super::scheduler::Queued;
use super::{learn, Relay};
use crate::frame::Adu;
use tokio::time::Instant;
use tracing::debug;

impl Relay {
    pub(super) fn take_frames(&mut self, now: Instant) {
        let mut all = std::mem::take(&mut self.seen);
        self.line
            .frames_into(self.in_flight.entries(), now, &self.stats, &mut all);
        for seen in all.drain(..) {
            match seen {
                Seen::Frame(frame, at) => self.on_frame(frame, at, now),
                Seen::Corrupt(tid) => {
                    if let Some(f) = self.in_flight.take(tid) {
                        // What failed its check may be an echo or noise over the start
                        // of the real reply, which can still come: the line keeps the
                        // guard it keeps after a timeout, so that reply never meets
                        // the next request (docs/reliability.md "RTU and ASCII", 3).
                        let hold = self.in_flight.hold_after_timeout(&f);
                        self.line.timed_out(now, hold, &self.stats);
                        self.failed(f, Failure::Corrupt, now);
                    }
                }
                // A late answer: its unit is alive, whatever it answered.
                Seen::Heard(unit) => self.in_flight.heard(unit),
            }
        }
        self.seen = all;
    }

    /// `frame`, taken off the line at `at` (its last byte read), handled `now`.
    pub(super) fn on_frame(&mut self, frame: Adu, at: Instant, now: Instant) {
        let tid = frame.tid();
        // The line has checked unit, function code and shape against this request.
        if let Some(f) = self.in_flight.answered(tid, at) {
            // Kept reserved a while: a second answer with this id is recognised as
            // ours and dropped, never broadcast.
            self.line.retire(tid, now);
            self.stats.add(&self.stats.replies, f.req.served());
            if let Some(key) = f.req.read_key() {
                self.cache.put(key, f.req.cache_stamp, &frame, now);
            }
            // When it left: its deadline is its response timeout after that.
            let left = f.deadline.checked_sub(f.timeout).unwrap_or(now);
            let wire = self
                .telemetry
                .wants_frames()
                .then(|| self.line.on_wire(&frame));
            let (conn, asked) = (f.req.conn(), &f.req.adu);
            if let Some(wire) = &wire {
                self.telemetry.taken(conn, asked, &frame, wire, at);
            }
            self.telemetry
                .replied(conn, asked, &frame, wire.as_deref(), (left, now));
            self.tell_learned(asked.unit());
            let emptied = f.req.deliver(&frame);
            self.spare.keep(emptied);
            return;
        }
        let unsolicited = self.line.unsolicited(tid);
        self.line
            .answered_nothing(matches!(unsolicited, Unsolicited::Late), now);
        match unsolicited {
            Unsolicited::Late => {
                self.stats.add(&self.stats.late_replies, 1);
                self.traffic("late reply, dropped", &frame, at);
                debug!(
                    tid,
                    "late reply dropped (its request timed out or was answered already): {:?}",
                    frame
                );
            }
            Unsolicited::Notification => {
                let what = match self.cfg.notifications {
                    crate::config::Notifications::Drop => "dropped (notifications = drop)",
                    crate::config::Notifications::Broadcast => "broadcast to every master",
                };
                self.traffic(what, &frame, at);
                self.masters.notification(frame, &self.stats)
            }
        }
    }

    /// `unit`'s learned timeout, if it has one, as it is now, for the metrics.
    pub(super) fn tell_learned(&self, unit: u8) {
        if let Some(l) = self.in_flight.learned(unit) {
            let why = learn::TimeoutReason::ALL.iter().position(|w| *w == l.why());
            let u = self.telemetry.metrics.unit(unit);
            u.set_learned(l.timeout(), why.unwrap_or(0));
        }
    }

    /// The traffic log's line, and the capture's packet, for a frame that answers
    /// nothing on the line, taken off it at `at`.
    pub(super) fn traffic(&self, what: &str, frame: &Adu, at: Instant) {
        if self.telemetry.wants_frames() {
            let wire = self.line.on_wire(frame);
            self.telemetry.unsolicited(what, frame, &wire, at);
        }
    }
}
