//! The RTU and ASCII line's way in: the bytes read, their local echo stripped, cut
//! into frames by the gap and the CRC/LRC, each tied to the request just sent by time
//! (bytes before it left are not its reply, nor a frame sooner than its unit can
//! answer), paying what its unit owes, held until the line has been quiet after it
//! (for the unit's whole response timeout while it owes), or dropped with their
//! reason (docs/reliability.md "RTU and ASCII", 5 to 7).

use super::super::Seen;
use super::Serial;
use crate::frame::framer::{Framed, ReplyFor};
use crate::frame::pdu;
use crate::frame::Adu;
use crate::line::relay::inflight::{Asked, OnLine};
use crate::ops::capture::dropped::Dropped;
use crate::ops::capture::packet::Reason;
use crate::ops::stats::Stats;
use std::ops::ControlFlow;
use std::time::Duration;
use tokio::time::Instant;
use tracing::debug;

/// A frame read off the line: its last byte's time and its length on the wire.
struct Got {
    frame: Adu,
    at: Instant,
    len: usize,
}

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

    /// The frames the bytes received so far make, given what is in flight (one at a
    /// time on a serial line), pushed onto `seen`.
    pub(in crate::line::relay::line) fn frames_into<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) {
        let asked = in_flight.first().map_or(&[][..], |f| f.req.adu().pdu());
        if self.asked != asked {
            self.asked.clear();
            self.asked.extend_from_slice(asked);
        }
        let Some(f) = in_flight.first() else {
            if let Some(c) = self.candidate.take() {
                self.refuted(&c, stats);
            }
            self.unasked(now, stats, seen);
            return;
        };
        if self
            .candidate
            .as_ref()
            .is_some_and(|c| c.reply.tid() != f.tid)
        {
            // Held for a request no longer on the line.
            if let Some(c) = self.candidate.take() {
                self.refuted(&c, stats);
            }
        }
        self.next_seen(f, now, stats, seen);
    }

    /// The frames for the request `f` on the line: its reply (held until the line has
    /// been quiet after it), frames that pay what their unit owes, or what refutes
    /// the reply or refuses the request.
    fn next_seen<R: Asked>(
        &mut self,
        f: &OnLine<R>,
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) {
        let request = f.req.adu().pdu();
        let quiet = now >= self.last_rx + self.quiet_after();
        loop {
            if self.candidate.as_ref().is_some_and(|c| !c.owed) && self.decoder.buffered() > 0 {
                // Bytes came within the quiet after the reply held: one frame too
                // many, and which of them answers nothing cannot be told. Both go;
                // what follows is dropped as answering nothing (docs/reliability.md
                // "RTU and ASCII", 7).
                return seen.push(self.refute(f.tid, None, now, stats));
            }
            // Made with the request's key: a reply goes to its master as it is.
            let next = self.decoder.next_frame_as(&ReplyFor(request), quiet, f.tid);
            // Noise before a frame (ASCII: before its colon), and a frame whose check
            // failed, the framer has dropped.
            self.count_dropped(0, stats);
            let frame = match next {
                None => {
                    seen.extend(self.confirmed(now));
                    return;
                }
                Some(Framed::Frame(frame)) => frame,
                Some(Framed::Corrupt(n)) => return seen.push(self.corrupt(f.tid, n, now, stats)),
            };
            let at = self.last_rx.min(now);
            let end = self.decoder.consumed();
            let len = self.decoder.encoded_len(frame.pdu().len());
            self.tape.frame(end, len, Some(at), Reason::LostSync);
            let got = Got { frame, at, len };
            if self.after_held(f.tid, &got, now, stats, seen).is_break()
                || self.judge(f, got, now, stats, seen).is_break()
            {
                return;
            }
        }
    }

    /// A frame `got` while a reply is held for the request `tid`: the held one was an
    /// answer its unit owed if the same unit sent more (paid, and `got` is judged
    /// afresh: `Continue`), else `got` refutes it (`Break`).
    fn after_held(
        &mut self,
        tid: u16,
        got: &Got,
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) -> ControlFlow<()> {
        let Some(c) = self.candidate.take() else {
            return ControlFlow::Continue(());
        };
        let unit = got.frame.unit();
        if c.owed && c.reply.unit() == unit {
            // Its unit sent more: the frame held was an answer it owed
            // (docs/reliability.md "RTU and ASCII", 6). This one is judged afresh.
            self.owed.pay(unit, c.at);
            self.drop_backlog(&c.reply, now, stats);
            seen.push(Seen::Heard(unit));
            return ControlFlow::Continue(());
        }
        // Another frame within the quiet after the reply held refutes it (and pays,
        // if its unit owes).
        self.candidate = Some(c);
        if self.owed.pay(unit, got.at) {
            self.drop_backlog(&got.frame, now, stats);
            seen.push(Seen::Heard(unit));
            seen.push(self.refute(tid, None, now, stats));
        } else {
            seen.push(self.refute(tid, Some(&got.frame), now, stats));
        }
        ControlFlow::Break(())
    }

    /// A frame `got` with no reply held, for the request `f` on the line: an answer
    /// its unit owed (dropped), the reply (held, or seen at once), one too soon
    /// (dropped), or a frame that answers something else (the request refused).
    /// `Continue`: read on.
    fn judge<R: Asked>(
        &mut self,
        f: &OnLine<R>,
        got: Got,
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) -> ControlFlow<()> {
        let Got { frame, at, len } = got;
        let unit = frame.unit();
        let asked = unit == f.req.adu().unit();
        let answers = asked && pdu::reply_matches(f.req.adu().pdu(), frame.pdu());
        if self.owed.owes(unit, at) {
            if answers && self.held_once != Some(f.tid) {
                // A unit that owes answers: its frame answers the request on the line
                // only if it is its last for the unit's whole response timeout (it
                // then held nothing more); a frame sooner after it shows it was one
                // owed. Held once for a request, so the request stays on the line at
                // most that long past its deadline.
                self.held_once = Some(f.tid);
                let took = self.answered_in(len, at);
                let quiet = self.owed.whole(unit);
                self.hold(frame, at, took, quiet, true);
                return ControlFlow::Continue(());
            }
            // An answer the unit held to a request that timed out: it answers nothing
            // on the line now.
            self.owed.pay(unit, at);
            self.drop_backlog(&frame, now, stats);
            seen.push(Seen::Heard(unit));
            return ControlFlow::Continue(());
        }
        if answers {
            let took = self.answered_in(len, at);
            if !self.owed.could_answer(unit, took, self.wire_time(len)) {
                // Sooner than the unit can answer: on its way before the unit could
                // have read the request (the tail of the last transaction). Not
                // counted as the unit heard: if it was the reply after all (the device
                // turned faster), the request times out and is owed, and the next
                // reply, held for the unit's whole response timeout, teaches the new
                // pace.
                self.drop_too_soon(&frame, at, stats);
                return ControlFlow::Continue(());
            }
            self.owed.heard(unit, at);
            if self.confirm.is_zero() {
                self.owed.replied(unit, at, took);
                seen.push(Seen::Frame(frame, at));
                return ControlFlow::Break(());
            }
            self.hold(frame, at, took, self.confirm, false);
            return ControlFlow::Continue(());
        }
        self.owed.heard(unit, at);
        seen.push(self.answers_else(f.tid, asked, &frame, at, stats));
        ControlFlow::Break(())
    }

    /// The reply held until the line has been quiet for `quiet` after it.
    fn hold(&mut self, reply: Adu, at: Instant, took: Duration, quiet: Duration, owed: bool) {
        self.candidate = Some(super::HeldReply {
            reply,
            at,
            took,
            quiet,
            owed,
        });
    }

    /// A frame of the request `tid`'s unit that answers another request, or of
    /// another unit: the request refused.
    fn answers_else(
        &mut self,
        tid: u16,
        asked: bool,
        frame: &Adu,
        at: Instant,
        stats: &Stats,
    ) -> Seen {
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
        debug!(unit = frame.unit(), "{detail}");
        self.tape.dropped_aside(|| Dropped {
            at: Some(at),
            reason: Reason::Stale,
            bytes: self.decoder.encode(frame),
            whole: true,
            detail,
        });
        stats.add(&stats.bad_frames, 1);
        Seen::Corrupt(tid)
    }

    /// How soon a unit answered with a frame of `bytes` whose last byte came at
    /// `at`: from its request's last byte leaving to the frame's first byte, so that a
    /// long reply's own time on the wire is no part of the unit's pace (a unit read
    /// 100 registers, then one, answers both as soon; docs/reliability.md "RTU and
    /// ASCII"). Where there is no wire the two are the same.
    fn answered_in(&self, bytes: usize, at: Instant) -> Duration {
        let own = self.wire_time(bytes);
        at.saturating_duration_since(self.reply_from)
            .saturating_sub(own)
    }

    /// Nothing asked: the frames received pay what their units owe (late answers),
    /// or answer nothing; either way dropped. What makes no frame is dropped once the
    /// line is quiet.
    fn unasked(&mut self, now: Instant, stats: &Stats, seen: &mut Vec<Seen>) {
        if self.decoder.buffered() == 0 {
            return;
        }
        let quiet = now >= self.last_rx + self.quiet_after();
        while let Some(next) = self.decoder.next_frame(&ReplyFor(&[]), quiet) {
            let frame = match next {
                Framed::Frame(frame) => frame,
                Framed::Corrupt(n) => {
                    let to = self.decoder.consumed();
                    let why = "bytes that answer no request";
                    self.tape
                        .dropped_to(to, Some(self.last_rx), Reason::Stale, why);
                    stats.add(&stats.dropped_stale, n as u64);
                    continue;
                }
            };
            let at = self.last_rx.min(now);
            let end = self.decoder.consumed();
            let len = self.decoder.encoded_len(frame.pdu().len());
            self.tape.frame(end, len, Some(at), Reason::LostSync);
            let unit = frame.unit();
            if self.owed.pay(unit, at) {
                self.drop_backlog(&frame, now, stats);
                seen.push(Seen::Heard(unit));
            } else {
                debug!(unit, "a frame that answers no request dropped");
                let detail = "a frame that answers no request";
                self.drop_whole(&frame, at, Reason::Stale, detail, stats);
            }
        }
        if quiet && self.decoder.buffered() > 0 {
            // ASCII without its line feed: never a frame.
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
        }
        // Corrupt frames and noise the framer dropped, and what was cleared.
        self.count_dropped(0, stats);
    }

    /// The reply held for confirmation, once the line has been quiet after it for
    /// `confirm` with nothing begun since: the answer.
    pub(super) fn confirmed(&mut self, now: Instant) -> Option<Seen> {
        let c = self.candidate.as_ref()?;
        if self.decoder.buffered() > 0 || now < c.at + c.quiet {
            return None;
        }
        let c = self.candidate.take()?;
        self.owed.replied(c.reply.unit(), c.at, c.took);
        Some(Seen::Frame(c.reply, c.at))
    }

    /// The reply held for the request `tid` was followed within its quiet by bytes
    /// (`frame`, when they made one already): both are dropped, and the request failed.
    fn refute(&mut self, tid: u16, frame: Option<&Adu>, now: Instant, stats: &Stats) -> Seen {
        if let Some(c) = self.candidate.take() {
            self.refuted(&c, stats);
        }
        if let Some(frame) = frame {
            let detail = "a frame within the quiet after a reply: one frame too many";
            let at = self.last_rx.min(now);
            self.drop_whole(frame, at, Reason::Stale, detail, stats);
        }
        debug!("a reply followed by another frame within its quiet: both dropped");
        Seen::Corrupt(tid)
    }

    /// A reply held for confirmation dropped unconfirmed: something followed it
    /// within its quiet, or its request is no longer on the line.
    pub(super) fn refuted(&mut self, c: &super::HeldReply, stats: &Stats) {
        let bytes = self.decoder.encode(&c.reply);
        stats.add(&stats.refuted_frames, 1);
        stats.add(&stats.dropped_bytes, bytes.len() as u64);
        self.tape.dropped_aside(|| Dropped {
            at: Some(c.at),
            reason: Reason::LostSync,
            bytes,
            whole: true,
            detail: "a reply refuted: another frame followed it within its quiet",
        });
    }

    /// A frame that fitted the request on the line, come sooner after it than its
    /// unit can answer: dropped, the request still waits.
    fn drop_too_soon(&mut self, frame: &Adu, at: Instant, stats: &Stats) {
        debug!(
            unit = frame.unit(),
            "a frame sooner than its unit can answer (half its fastest reply) dropped"
        );
        let detail = "sooner after the request than its unit can answer (half its fastest reply)";
        self.drop_whole(frame, at, Reason::TooEarly, detail, stats);
    }

    /// A whole frame dropped, its last byte read at `at`: counted (stale or too early,
    /// and in the bytes dropped) and shown to a capture with why.
    fn drop_whole(
        &mut self,
        frame: &Adu,
        at: Instant,
        reason: Reason,
        detail: &'static str,
        stats: &Stats,
    ) {
        let bytes = self.decoder.encode(frame);
        let counter = match reason {
            Reason::TooEarly => &stats.dropped_too_early,
            _ => &stats.dropped_stale,
        };
        stats.add(counter, bytes.len() as u64);
        stats.add(&stats.dropped_bytes, bytes.len() as u64);
        self.tape.dropped_aside(|| Dropped {
            at: Some(at),
            reason,
            bytes,
            whole: true,
            detail,
        });
    }

    /// A frame from a unit's backlog (the answer to a request that timed out),
    /// dropped and counted as a late reply.
    pub(super) fn drop_backlog(&mut self, frame: &Adu, now: Instant, stats: &Stats) {
        debug!(
            unit = frame.unit(),
            "a frame the device held for a request that timed out, dropped"
        );
        stats.add(&stats.late_replies, 1);
        let detail = "an answer the device held to a request that timed out (its backlog)";
        let at = self.last_rx.min(now);
        self.drop_whole(frame, at, Reason::Stale, detail, stats);
    }

    /// A reply whose check failed (or cut short) for the request `tid`: with a reply
    /// held for confirmation, that one was not followed by quiet, and goes too.
    pub(super) fn corrupt(&mut self, tid: u16, n: usize, now: Instant, stats: &Stats) -> Seen {
        if let Some(c) = self.candidate.take() {
            self.refuted(&c, stats);
        }
        debug!(bytes = n, "a reply whose check failed");
        let end = self.decoder.consumed();
        let at = Some(self.last_rx.min(now));
        let check = (Reason::LostSync, self.check);
        let why = "a reply whose check failed, or cut short";
        self.tape.dropped_frame(end, n, at, check, why);
        stats.add(&stats.bad_frames, 1);
        Seen::Corrupt(tid)
    }
}
