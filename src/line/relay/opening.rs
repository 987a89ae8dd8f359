//! The loop's side of the port's life: opened (the line starts afresh), lost (what
//! waited on it answered 0x0A or 0x0B, reopened with backoff or when its node is
//! back), each outage counted on the metrics board, and the drain at shutdown (the
//! queue answered 0x0A, the requests on the line let finish).

use super::Relay;
use crate::line::outbox::Refusal;
use crate::line::port::OpenPort;
use tokio::time::Instant;
use tracing::debug;

impl Relay {
    pub(super) fn open_if_due(&mut self, now: Instant) {
        if self.draining {
            return;
        }
        if let Some(opened) = self.port.open_if_due(now) {
            self.opened(opened, now);
        }
    }

    /// An open finished: the line starts afresh, or the next attempt is due later.
    pub(super) fn opened(&mut self, opened: std::io::Result<OpenPort>, now: Instant) {
        let Some(info) = self.port.opened(opened, now) else {
            if let Some(since) = self.port.down_since() {
                self.telemetry.metrics.port_down(since);
            }
            return;
        };
        self.telemetry.metrics.port_up(now);
        self.line.clear(&self.stats);
        if let Some(t) = &mut self.turnaround {
            // The switch was taken off with the port.
            t.reset();
        }
        let timing = self.line.port_opened(&info);
        self.port.tell_open(&info, &timing);
        self.stats.add(&self.stats.serial_opens, 1);
    }

    /// The port failed or its far end went away: answer everything waiting on it, and
    /// reopen with backoff. A request that had begun to go out gets 0x0B, as for a
    /// timeout: it may have reached the device and acted, and no answer came. One whose
    /// bytes never left (held by flow control, or queued) gets 0x0A: there is no path
    /// to the device, and it cannot have acted.
    pub(super) fn port_lost(&mut self, why: &str, now: Instant) {
        // Closing the port drops its switch, which leaves the transmitter off.
        if let Some(t) = &mut self.turnaround {
            t.abort();
        }
        self.port.lost(why, now);
        self.telemetry.metrics.port_down(now);
        self.line.clear(&self.stats);
        for f in self.in_flight.take_all() {
            self.line.retire(f.tid, now);
            let why = if self.out.withdraw(f.tid) {
                Refusal::Unavailable
            } else {
                Refusal::TargetFailed
            };
            f.req.answer_exception(why, &self.stats);
        }
        self.out.clear();
        self.flush_queue(Refusal::Unavailable);
    }

    pub(super) fn start_draining(&mut self) {
        if !self.draining {
            debug!(
                in_flight = self.in_flight.len(),
                queued = self.sched.queued(),
                "relay draining"
            );
            self.draining = true;
            self.flush_queue(Refusal::Unavailable);
            for req in self.paced.take_all() {
                req.answer_backed_off(&self.stats);
            }
        }
    }

    /// Answers every queued request (and every one waiting to be resent) with the
    /// exception for `why`.
    pub(super) fn flush_queue(&mut self, why: Refusal) {
        for req in self.sched.drain_all() {
            req.answer_exception(why, &self.stats);
        }
    }
}
