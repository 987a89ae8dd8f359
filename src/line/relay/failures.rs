//! What the loop does with requests that got no usable reply, as the in-flight table
//! decides: resent, answered 0x0B, or their unit backed off, its waiting requests
//! answered at once and its next ones paced at the line's speed.

use super::inflight::{Failure, OnLine, Verdict};
use super::pending::Pending;
use super::Relay;
use crate::line::outbox::Refusal;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

impl Relay {
    /// Requests past their deadline fail; one whose reply came in time and is held
    /// until the line has been quiet after it (RTU/ASCII) waits for that.
    pub(super) fn expire(&mut self, now: Instant) {
        if let Some((tid, until)) = self.line.confirming() {
            self.in_flight.hold_until(tid, until);
        }
        for f in self.in_flight.take_expired(now) {
            // A request timed out with the transmitter still on (its bytes held back,
            // or a UART that never says it is empty): off, so the bus is not held.
            self.switch_off(now);
            let hold = self.in_flight.hold_after_timeout(&f);
            self.line.timed_out(now, hold, &self.stats);
            self.telemetry.timed_out(f.req.conn(), &f.req.adu, now);
            let never_left = self.out.withdraw(f.tid);
            if never_left {
                // Flow control held it back (CTS low) the whole time: it never left,
                // and must not act on the device after the master was told 0x0B.
                warn!(
                    conn = f.req.conn(),
                    "request could not be written in time (is CTS held low?)"
                );
            }
            if self.withdraw_output() == 0 && !never_left {
                // The device may have read it whole, and answer it after any it
                // holds: its unit owes that answer (docs/reliability.md "RTU and
                // ASCII", 6).
                let unit = f.req.adu.unit();
                let left = f.deadline.checked_sub(f.timeout).unwrap_or(now);
                let whole = self.in_flight.whole_timeout(unit).max(f.timeout);
                self.line.unanswered(unit, left, whole, now);
            }
            self.failed(f, Failure::Timeout, now);
        }
    }

    /// RTU/ASCII, after a timeout: what of the request is still in the port's output
    /// queue (flow control held it, or the adapter stopped sending) is withdrawn, so
    /// the device never reads a request its master was told failed, and never answers
    /// it later in place of the next (docs/reliability.md "RTU and ASCII", 6). Not on
    /// MBAP, where a frame cut in two would put the device's parser out of step, and
    /// a late answer is known by its id anyway.
    /// Returns how many bytes were withdrawn: any, and the device never read the
    /// request whole.
    fn withdraw_output(&mut self) -> usize {
        if !self.line.is_serial() {
            return 0;
        }
        match self.port.withdraw_output() {
            Ok(0) => 0,
            Ok(n) => {
                self.stats.add(&self.stats.withdrawn_bytes, n as u64);
                warn!(
                    bytes = n,
                    "a request that timed out had not left the port: withdrawn from its output queue (is CTS held low, or the adapter stalled?)"
                );
                n
            }
            Err(e) => {
                debug!("the port's output queue could not be asked: {e}");
                0
            }
        }
    }

    /// A request on the line got no usable reply: resent if it may be, else answered
    /// 0x0B, or its unit backed off (the in-flight table decides).
    pub(super) fn failed(&mut self, f: OnLine<Pending>, why: Failure, now: Instant) {
        self.line.retire(f.tid, now);
        let open = self.port.is_open();
        let verdict = self.in_flight.verdict(&f, why, now, open);
        self.tell_learned(f.req.adu.unit());
        match verdict {
            Verdict::BackedOff(interval) => {
                let unit = f.req.adu.unit();
                self.telemetry.backed_off(unit);
                // Said once a spell: the warning that the unit is not answering is
                // the telemetry's (telemetry.rs); the longer intervals after failed probes
                // are for debugging.
                if interval <= Duration::from_millis(self.cfg.unit_backoff_ms) {
                    info!(
                        unit,
                        "unit backed off for {interval:?}: its requests get 0x0B at once, then one probes it"
                    );
                } else {
                    debug!(
                        unit,
                        "unit still not answering: backed off for {interval:?}"
                    );
                }
                f.req.answer_exception(Refusal::TargetFailed, &self.stats);
                self.sweep_backed_off(unit);
            }
            Verdict::Resend => {
                let mut req = f.req;
                req.attempts += 1;
                let (conn, attempt) = (req.conn(), req.attempts);
                match self.sched.resend(req) {
                    Ok(()) => {
                        debug!(conn, attempt, "{}; resending", why.what());
                        self.stats.add(&self.stats.retries, 1);
                    }
                    // More than one in flight, and a later request of one of its
                    // masters went on the line after it: resent, it would overtake
                    // that one (docs/design.md §1 "Each master's order").
                    Err(req) => {
                        debug!(
                            conn = req.conn(),
                            "{}; not resent: a later request of its master is on the line: 0x0B",
                            why.what()
                        );
                        req.answer_exception(Refusal::TargetFailed, &self.stats);
                    }
                }
            }
            Verdict::Fail => {
                debug!(
                    conn = f.req.conn(),
                    tid = f.req.adu.tid(),
                    "{}: 0x0B",
                    why.what_in_the_end()
                );
                f.req.answer_exception(Refusal::TargetFailed, &self.stats);
            }
        }
    }

    /// A unit was just backed off: its waiting requests are answered now, so they never
    /// take the line from the healthy units.
    pub(super) fn sweep_backed_off(&mut self, unit: u8) {
        // They have waited their turn on the line already: answered at once.
        for req in self.sched.take_unit(unit) {
            req.answer_backed_off(&self.stats);
        }
    }

    /// 0x0B for a backed-off unit, no sooner than the line could have served the
    /// request: a master that polls a dead unit in a tight loop gets its answers at
    /// the line's pace, not as fast as the gateway can turn them round. Healthy units
    /// are not touched.
    pub(super) fn pace_backed_off(&mut self, req: Pending) {
        let now = Instant::now();
        let shortest = self.line.shortest_transaction(&req.adu);
        if let Some(req) = self.paced.pace(req, now, shortest) {
            req.answer_backed_off(&self.stats);
        }
    }

    /// Sends the paced 0x0B answers whose time has come.
    pub(super) fn answer_paced(&mut self, now: Instant) {
        for req in self.paced.due(now) {
            req.answer_backed_off(&self.stats);
        }
    }
}
