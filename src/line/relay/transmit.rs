//! The loop's side of the wire going out: what waits is written when the port takes
//! it, each request encoded and put on the line (`send`), the RS-485 transmitter
//! switched as `turnaround.rs` says (docs/rs485.md), and the drain that times the
//! reply from the last byte on the wire.

use super::pending::Pending;
use super::scheduler::Queued;
use super::{turnaround, Relay};
use crate::line::port::lifecycle::State;
use tokio::time::Instant;
use tracing::debug;

impl Relay {
    /// May bytes be written now: always, unless the gateway switches the transmitter
    /// itself and it is not yet on with its delay before passed.
    pub(super) fn may_write(&self, now: Instant) -> bool {
        self.turnaround.as_ref().is_none_or(|t| t.may_write(now))
    }

    /// Writes what waits to go out if the port takes it without waiting (the loop's
    /// wait would find it ready at once): the instant after the write, or `None` when
    /// nothing was written (nothing waits, the transmitter may not start yet, the port
    /// is full or closed, or the write failed and the port was lost). A port that is
    /// full keeps no waker from this try: the loop's wait polls the write again and
    /// registers its own.
    pub(super) fn write_now(&mut self, now: Instant) -> Option<Instant> {
        if self.out.is_empty() || !self.may_write(now) {
            return None;
        }
        let State::Open(open) = &mut self.port.state else {
            return None;
        };
        let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
        match tokio::io::AsyncWrite::poll_write(
            std::pin::Pin::new(&mut open.writer),
            &mut cx,
            self.out.pending(),
        ) {
            std::task::Poll::Pending => None,
            std::task::Poll::Ready(Ok(0)) => None,
            std::task::Poll::Ready(Ok(n)) => {
                let after = Instant::now();
                self.wrote(n, now, after);
                Some(after)
            }
            std::task::Poll::Ready(Err(e)) => {
                self.port_lost(&format!("write failed: {e}"), Instant::now());
                None
            }
        }
    }

    /// `n` bytes of what waited went out, by a write begun at `polled` that returned
    /// at `now`.
    pub(super) fn wrote(&mut self, n: usize, polled: Instant, now: Instant) {
        self.stats.add(&self.stats.serial_bytes_out, n as u64);
        self.line.wrote(n, polled, now);
        self.out.advance(n);
        if self.out.is_empty() && self.line.is_serial() {
            if let Some(t) = &mut self.turnaround {
                // The line times the frame from before the write (`polled`, a lower
                // bound for judging the reply); the transmitter goes off no sooner than
                // the last bytes' time on the wire after the write returned, so a pause
                // of this thread between the two (a busy machine) cannot cut the
                // request's tail where the port cannot say it is empty.
                let left = self.line.leaves_at().unwrap_or(now);
                t.written(self.line.left_after(n, now).map_or(left, |a| a.max(left)));
            }
            // The transmitter switch the gateway drives waits for the drain on any
            // port; without one, only a port that can hold bytes back needs it.
            if self.line.needs_drain() || self.turnaround.is_some() {
                self.start_drain(now);
            } else {
                // No wire, or none that holds bytes back: gone once written, or their
                // time on the wire after it (`LineFraming::needs_drain`).
                self.drained(now);
            }
        }
    }

    /// Bytes are still being written, or have not yet left the port.
    pub(super) fn tx_busy(&self) -> bool {
        !self.out.is_empty() || self.port.drain.is_some()
    }

    /// RTU/ASCII: has the port received bytes the relay has not read yet? Then the
    /// device is talking, and a request now would go over it (on RS-485, collide with
    /// it): the bytes are read first, and the gap counts from them.
    pub(super) fn input_waiting(&self) -> bool {
        self.line.is_serial() && self.port.input_waiting()
    }

    pub(super) fn send(&mut self, req: Pending, now: Instant) {
        let tid = self.line.allocate(now);
        let pause = self.in_flight.policy(req.adu.unit()).pause;
        self.line.pause_after(pause);
        let (line, stats) = (&mut self.line, &self.stats);
        let bytes = self
            .out
            .push_with(tid, |out| line.encode_into(&req.adu, tid, now, stats, out));
        self.telemetry.sent(req.conn(), &req.adu, tid, bytes, now);
        if req.acts() {
            // Reads sent before it may be answered after it was sent: not kept.
            self.cache.acted_on(req.adu.unit());
        }
        if self.line.is_broadcast(&req.adu) {
            self.stats.add(&self.stats.broadcasts, 1);
            req.broadcast_sent(self.cfg.broadcast_reply);
            return;
        }
        // The response time counts from when the request has left: behind whatever is
        // still waiting to be written.
        let queued = self.port.wire_time(self.out.len());
        self.in_flight.start(tid, req, now, queued);
    }

    /// Switches the RS-485 transmitter as the turnaround says (docs/rs485.md): on when
    /// bytes wait to be written (only while no request awaits its reply: `dispatch`
    /// sends one at a time), a look at the port's transmitter when due, off once the
    /// last stop bit has left. A switch that fails loses the port: its requests get
    /// their exception, and it is reopened (the switch taken afresh) with backoff.
    pub(super) fn steer(&mut self, now: Instant) {
        if !self.port.is_open() {
            return;
        }
        // Each pass switches, or looks and moves on (a look that finds the
        // transmitter still busy sets the next one later than now): a few passes are
        // all one turn of the loop can take.
        for _ in 0..6 {
            let waiting = !self.out.is_empty();
            let Some(t) = &mut self.turnaround else {
                return;
            };
            let act = if waiting {
                t.begin(now)
            } else if t.sending() {
                // Its frame was withdrawn before a byte of it was written.
                t.abort()
            } else {
                None
            };
            let Some(a) = act.or_else(|| t.due(now)) else {
                return;
            };
            let late = t.late_by(now);
            match a {
                turnaround::Act::Look => {
                    let empty = self.port.transmitter_empty();
                    t.looked(empty.ok(), now);
                }
                turnaround::Act::On | turnaround::Act::Off => {
                    let on = a == turnaround::Act::On;
                    if let Err(e) = self.port.transmit(on) {
                        let what = if on { "on" } else { "off" };
                        let why = format!("could not switch the RS-485 transmitter {what}: {e}");
                        self.port_lost(&why, now);
                        return;
                    }
                    if on {
                        t.switched_on(Instant::now());
                    }
                    match late {
                        Some(late) if !on => tracing::trace!(
                            us = late.as_micros() as u64,
                            "transmitter off after the last stop bit could have left"
                        ),
                        _ => tracing::trace!(on, "transmitter switched"),
                    }
                }
            }
        }
    }

    /// Switches the transmitter off now if it is on (where the gateway switches it).
    pub(super) fn switch_off(&mut self, now: Instant) {
        let Some(t) = &mut self.turnaround else {
            return;
        };
        if t.abort().is_some() {
            if let Err(e) = self.port.transmit(false) {
                let why = format!("could not switch the RS-485 transmitter off: {e}");
                self.port_lost(&why, now);
            }
        }
    }

    /// Waits for the bytes written to leave the port, off the runtime's thread, so the
    /// reply timer and the inter-frame gap start from the last byte on the wire.
    pub(super) fn start_drain(&mut self, now: Instant) {
        if let Err(e) = self.port.start_drain() {
            debug!("tcdrain unavailable ({e}): timing from the write");
            if let Some(t) = &mut self.turnaround {
                t.drained(now);
            }
            self.drained(now);
        }
    }

    pub(super) fn drained(&mut self, now: Instant) {
        let left = self.line.drained(now, &self.stats);
        self.in_flight.restart(left);
    }
}
