//! The RTU and ASCII line's way in: the bytes read, their local echo stripped, cut
//! into frames by the gap and the CRC/LRC, each tied to the request just sent by time
//! (bytes before it left are not its reply), held until confirmed, or dropped with
//! their reason.

use super::super::Seen;
use super::Serial;
use crate::frame::framer::{Framed, ReplyFor};
use crate::frame::pdu;
use crate::frame::Adu;
use crate::line::relay::inflight::{Asked, OnLine};
use crate::ops::capture::dropped::Dropped;
use crate::ops::capture::packet::Reason;
use crate::ops::stats::Stats;
use tokio::time::Instant;
use tracing::debug;

impl Serial {
    pub(in crate::line::relay::line) fn received(
        &mut self,
        bytes: &[u8],
        now: Instant,
        stats: &Stats,
    ) {
        self.last_rx = now;
        let rest = self.strip_echo(bytes, now, stats);
        if rest.is_empty() {
            return;
        }
        match self.tx {
            // The whole request has been handed to the port and its time on the wire
            // has passed: that bound is all `drained` would judge by, so these are
            // judged now, and a reply is taken without waiting for the drain's answer
            // (the drain thread may be scheduled late; docs/performance.md).
            Some(earliest) if self.unwritten == 0 && now >= earliest => {
                self.judge_held(earliest, stats);
                self.accept(rest, now, stats);
            }
            // The request is still on its way out: when its last byte left is not
            // known yet, so these wait for `drained` to judge them.
            Some(_) => self.held.push((now, rest.to_vec())),
            None => self.accept(rest, now, stats),
        }
    }

    /// The request's last byte left `earliest` or later: bytes held until then are
    /// judged by it.
    pub(super) fn judge_held(&mut self, earliest: Instant, stats: &Stats) {
        self.reply_from = earliest;
        for (at, bytes) in std::mem::take(&mut self.held) {
            self.accept(&bytes, at, stats);
        }
    }

    /// Bytes read at `at`, once the request they follow has left: before its last byte
    /// left they cannot be its reply (an echo, a device that answers too early, a
    /// frame already on its way), and are dropped.
    pub(super) fn accept(&mut self, bytes: &[u8], at: Instant, stats: &Stats) {
        if at < self.reply_from {
            debug!(
                bytes = bytes.len(),
                "bytes received while the request was still being sent discarded"
            );
            stats.add(&stats.dropped_bytes, bytes.len() as u64);
            stats.add(&stats.dropped_too_early, bytes.len() as u64);
            self.tape.dropped_aside(|| Dropped {
                at: Some(at),
                reason: Reason::TooEarly,
                bytes: bytes.to_vec(),
                whole: false,
                detail: "received while the request was still being sent",
            });
        } else {
            self.decoder.push(bytes);
            self.tape.push(bytes);
        }
    }

    /// Reads back the echo of what was sent; bytes that differ from it are line noise
    /// and dropped with it.
    pub(super) fn strip_echo<'a>(
        &mut self,
        bytes: &'a [u8],
        now: Instant,
        stats: &Stats,
    ) -> &'a [u8] {
        let Some(echo) = &mut self.echo else {
            return bytes;
        };
        let n = bytes.len().min(echo.len());
        if echo.iter().take(n).eq(bytes[..n].iter()) {
            echo.drain(..n);
            if n > 0 {
                self.tape.dropped_aside(|| Dropped {
                    at: Some(now),
                    reason: Reason::Echo,
                    bytes: bytes[..n].to_vec(),
                    whole: false,
                    detail: "the line's echo of the request (echo = true)",
                });
            }
            return &bytes[n..];
        }
        debug!(
            expected = echo.len(),
            "the echo of the request differs from what was sent: dropped as noise"
        );
        echo.clear();
        stats.add(&stats.dropped_bytes, bytes.len() as u64);
        self.tape.dropped_aside(|| Dropped {
            at: Some(now),
            reason: Reason::Echo,
            bytes: bytes.to_vec(),
            whole: false,
            detail: "bytes where the echo of the request should be, and different from it",
        });
        &[]
    }

    /// The frame the bytes received so far make, given what is in flight (one at a
    /// time on a serial line), pushed onto `seen`.
    pub(in crate::line::relay::line) fn frames_into<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) {
        seen.extend(self.next_seen(in_flight, now, stats));
    }

    pub(super) fn next_seen<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
    ) -> Option<Seen> {
        let asked = in_flight.first().map(|f| f.req.adu().pdu());
        if self.asked.as_deref() != asked {
            // Kept in the room of the last one: no allocation a request.
            let mut room =
                (self.asked.take()).unwrap_or_else(|| std::mem::take(&mut self.asked_room));
            room.clear();
            match asked {
                Some(asked) => {
                    room.extend_from_slice(asked);
                    self.asked = Some(room);
                }
                None => self.asked_room = room,
            }
        }
        let quiet = now >= self.last_rx + self.quiet_after();
        let Some(f) = in_flight.first() else {
            // Nothing asked: late answers or noise, dropped once the line is quiet.
            if quiet && self.decoder.buffered() > 0 {
                let n = self.decoder.clear();
                let to = self.decoder.consumed();
                self.tape.dropped_to(
                    to,
                    Some(self.last_rx),
                    Reason::Stale,
                    "bytes that answer no request",
                );
                debug!(bytes = n, "bytes that answer no request dropped");
                stats.add(&stats.dropped_stale, n as u64);
                self.count_dropped(0, stats);
            }
            return None;
        };
        let request = f.req.adu().pdu();
        if self
            .unconfirmed
            .as_ref()
            .is_some_and(|(reply, ..)| reply.tid() != f.tid)
        {
            // Held for a request no longer on the line.
            if let Some((reply, ..)) = self.unconfirmed.take() {
                self.drop_backlog(&reply, now, stats);
            }
        }
        loop {
            let next = self.decoder.next_frame_as(&ReplyFor(request), quiet, f.tid);
            // Noise before a frame (ASCII: before its colon), and a frame whose check
            // failed, the framer has dropped.
            self.count_dropped(0, stats);
            let frame = match next {
                None => return self.confirmed(now),
                Some(Framed::Frame(frame)) => frame,
                Some(Framed::Corrupt(n)) => return self.corrupt(f.tid, n, now, stats),
            };
            let at = self.last_rx.min(now);
            let end = self.decoder.consumed();
            let len = self.decoder.encoded_len(frame.pdu().len());
            self.tape.frame(end, len, Some(at), Reason::LostSync);
            let (unit, pdu) = (frame.unit(), frame.pdu());
            // Another frame came before the line was quiet after the one held: that
            // one was an answer the device held to an earlier request.
            if let Some((reply, ..)) = self.unconfirmed.take() {
                self.drop_backlog(&reply, now, stats);
            }
            let asked = unit == f.req.adu().unit();
            let answers = asked && pdu::reply_matches(request, pdu);
            if answers && self.may_owe.contains(unit) {
                // The unit asked may still answer requests of its that timed out: its
                // reply is the answer only if the line stays quiet after it
                // (docs/reliability.md "RTU and ASCII", 6).
                let quiet = self.guard.min(f.timeout / 2);
                self.unconfirmed = Some((frame, at, quiet));
                continue;
            }
            if answers {
                return Some(Seen::Frame(frame, at));
            }
            // The CRC or LRC proves only that these bytes are a frame: one of another
            // unit, of another function than the request's (or its exception), or of
            // another shape answers something else (a stray frame, another request's
            // answer), and the master is told 0x0B at once, as on MBAP
            // (docs/reliability.md "RTU and ASCII", 5).
            let detail = if asked {
                "a frame of the request's unit that does not answer it (another function or shape)"
            } else {
                "a frame from another unit than the request's"
            };
            debug!(unit, "{detail}");
            self.tape.dropped_aside(|| Dropped {
                at: Some(at),
                reason: Reason::Stale,
                bytes: self.decoder.encode(&frame),
                whole: true,
                detail,
            });
            stats.add(&stats.bad_frames, 1);
            return Some(Seen::Corrupt(f.tid));
        }
    }

    /// The reply held for confirmation, once the line has been quiet after it for its
    /// time with nothing begun since: the answer, and its unit owes no more.
    pub(super) fn confirmed(&mut self, now: Instant) -> Option<Seen> {
        let &(_, at, quiet) = self.unconfirmed.as_ref()?;
        if self.decoder.buffered() > 0 || now < self.last_rx.max(at) + quiet {
            return None;
        }
        let (reply, at, _) = self.unconfirmed.take()?;
        self.may_owe.remove(reply.unit());
        Some(Seen::Frame(reply, at))
    }

    /// A frame from a unit's backlog (the answer to a request that timed out),
    /// dropped and counted as a late reply.
    pub(super) fn drop_backlog(&mut self, frame: &Adu, now: Instant, stats: &Stats) {
        debug!(
            unit = frame.unit(),
            "a frame the device held for a request that timed out, dropped"
        );
        let bytes = self.decoder.encode(frame);
        stats.add(&stats.late_replies, 1);
        stats.add(&stats.dropped_stale, bytes.len() as u64);
        stats.add(&stats.dropped_bytes, bytes.len() as u64);
        self.tape.dropped_aside(|| Dropped {
            at: Some(self.last_rx.min(now)),
            reason: Reason::Stale,
            bytes,
            whole: true,
            detail: "an answer the device held to a request that timed out (its backlog)",
        });
    }

    /// A reply whose check failed (or cut short) for the request `tid`: with a reply
    /// held for confirmation, that one was not followed by quiet, and goes too.
    pub(super) fn corrupt(
        &mut self,
        tid: u16,
        n: usize,
        now: Instant,
        stats: &Stats,
    ) -> Option<Seen> {
        if let Some((reply, ..)) = self.unconfirmed.take() {
            self.drop_backlog(&reply, now, stats);
        }
        debug!(bytes = n, "a reply whose check failed");
        let end = self.decoder.consumed();
        let at = Some(self.last_rx.min(now));
        let check = (Reason::LostSync, self.check);
        let why = "a reply whose check failed, or cut short";
        self.tape.dropped_frame(end, n, at, check, why);
        stats.add(&stats.bad_frames, 1);
        Some(Seen::Corrupt(tid))
    }
}
