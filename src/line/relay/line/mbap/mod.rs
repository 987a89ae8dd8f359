//! The MBAP line (the CIE-M10): serial-side transaction ids, several requests on the
//! line at once, the resynchronising decoder that confirms a frame by what follows it
//! or a pause whenever something can follow it, notifications and late replies told
//! apart, echoes told by timing on a wire (docs/reliability.md). The state the line
//! keeps and its mechanism are here; which frames the relay can use (the decoder's
//! judge, and whether anything can follow a reply) is `mbap/usable.rs`.

mod usable;

use super::{Seen, Unsolicited};
use crate::config::{Notifications, RelayConfig, SerialConfig};
use crate::frame::framer::{Framed, Framer};
use crate::frame::mbap::MAX_ADU;
use crate::frame::pdu;
use crate::frame::Adu;
use crate::line::port::kind::{self, PortInfo};
use crate::line::relay::inflight::{Asked, OnLine};
use crate::line::relay::tids::Tids;
use crate::ops::capture::dropped::Tape;
use crate::ops::capture::packet::Reason;
use crate::ops::stats::Stats;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};
use usable::RelayJudge;

pub(super) struct MbapLine {
    tids: Tids,
    decoder: Framer,
    last_byte: Instant,
    /// The serial settings, for the timing of each port opened.
    serial: SerialConfig,
    /// The silence that ends a frame and confirms a reply with nothing after it: 3.5
    /// character times, never less than `silence_floor_ms` (a USB adapter hands bytes
    /// over in bursts its latency timer apart), never more than the frame gap.
    pause: Duration,
    max_in_flight: usize,
    gap: Duration,
    /// One character on the wire at the configured speed; zero where there is no
    /// wire (a pty, TCP): nothing of a request is then "still on its way".
    char_time: Duration,
    /// A wire at `baud_rate` between the port and the device (`port_kind`).
    wire: bool,
    /// The device sends frames nobody asked for (`device_notifications`, or
    /// `notifications = "broadcast"`: the operator expects them).
    notifies: bool,
    /// The device was heard talking when nothing was asked, though said not to: every
    /// reply is confirmed from then on.
    heard_unasked: bool,
    /// A request ended without its reply: until then (`timeout_guard_ms` after) its
    /// late reply may still come, and follow any other reply.
    late_until: Option<Instant>,
    /// `timeout_guard_ms`.
    guard: Duration,
    /// When every byte handed to the port so far can have left it, written back to
    /// back at the configured speed.
    tx_clear: Instant,
    /// The requests in flight as sent, for telling frames that came too early.
    sent: Vec<Sent>,
    /// Where each chunk read from the port begins in everything received, and when it
    /// was read, back to the first byte the decoder still holds.
    chunks: VecDeque<(u64, Instant)>,
    /// Bytes received so far.
    received: u64,
    /// Over TCP: no byte is lost, so a whole frame needs no confirmation.
    stream: bool,
    /// The line stays quiet this long after the last byte received
    /// (`request_pause_ms`).
    pub(super) request_pause: Duration,
    /// Whether the cost of confirmation by a pause has been said (once a line).
    told_pause: bool,
    /// The bytes dropped, for the capture.
    pub(super) tape: Tape,
}

/// Why a frame with the id of a request in flight does not answer it.
enum Early {
    /// Its first byte was read before the request was sent.
    Stale,
    /// A copy of the request that began before the request could have left the wire.
    Echo,
}

/// A request as it went on the line.
struct Sent {
    tid: u16,
    /// Its bytes, kept here (to know its echo): no allocation a request.
    bytes: SentBytes,
    /// When it was handed to the port: nothing read before then answers it.
    handed: Instant,
    /// The earliest instant its last byte can have left at the configured speed: a
    /// copy of it that began arriving before then is its echo. Counted again from
    /// when the write that carried its last byte returned (`Mbap::wrote`).
    left: Instant,
    /// Its bytes not yet handed to the port by a write that returned.
    unwritten: usize,
}

/// A copy of a request's bytes, in place.
struct SentBytes {
    len: usize,
    buf: [u8; MAX_ADU],
}

impl SentBytes {
    fn of(bytes: &[u8]) -> SentBytes {
        let mut s = SentBytes {
            len: bytes.len(),
            buf: [0; MAX_ADU],
        };
        s.buf[..bytes.len()].copy_from_slice(bytes);
        s
    }
}

impl std::ops::Deref for SentBytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        &self.buf[..self.len]
    }
}

impl MbapLine {
    pub(super) fn new(
        relay: &RelayConfig,
        serial: &SerialConfig,
        stream: bool,
        now: Instant,
    ) -> MbapLine {
        let gap = Duration::from_millis(relay.frame_gap_ms);
        let mut line = MbapLine {
            tids: Tids::new(),
            decoder: Framer::mbap(),
            last_byte: now,
            serial: serial.clone(),
            pause: gap,
            max_in_flight: relay.max_in_flight,
            gap,
            char_time: Duration::ZERO,
            wire: !stream,
            notifies: relay.device_notifications || relay.notifications == Notifications::Broadcast,
            heard_unasked: false,
            late_until: None,
            guard: Duration::from_millis(relay.timeout_guard_ms),
            tx_clear: now,
            sent: Vec::new(),
            chunks: VecDeque::new(),
            received: 0,
            stream,
            request_pause: Duration::from_millis(relay.request_pause_ms),
            told_pause: false,
            tape: Tape::default(),
        };
        // Until a port is open its kind is not known: a wire, the old floor.
        let info = if stream {
            PortInfo::plain(kind::Medium::Tcp)
        } else {
            PortInfo::unknown()
        };
        line.port_opened(&info);
        line
    }

    /// A port was opened and found to be `info`: the echo rule applies only where
    /// there is a wire, and the pause that ends a frame is the port's. Says how.
    pub(super) fn port_opened(&mut self, info: &PortInfo) -> String {
        let wire = !self.stream && kind::wire(&self.serial, info);
        self.wire = wire;
        // A socket or a pty has no line speed: nothing of a request is "still on the
        // wire".
        self.char_time = if wire {
            kind::wire_time(&self.serial, 1000) / 1000
        } else {
            Duration::ZERO
        };
        self.pause = kind::silence(&self.serial, info).min(self.gap);
        let confirm = if self.stream {
            "a whole frame is taken at once".to_owned()
        } else {
            format!(
                "a reply is held for confirmation only when something can follow it, \
                 then a pause of {:.2} ms confirms it",
                self.pause.as_secs_f64() * 1000.0
            )
        };
        let wire = match (self.stream, wire) {
            (true, _) => "",
            (false, true) => {
                "; a wire at serial.baud_rate: echoes and frames begun too early dropped"
            }
            (false, false) => "; no wire: replies taken however soon they come",
        };
        format!("{confirm}{wire}")
    }

    /// Bytes arrived with `in_flight` requests on the line: with none, and no late
    /// reply possible, the device talked unasked.
    pub(super) fn heard(&mut self, n: usize, in_flight: usize, now: Instant, stats: &Stats) {
        if self.stream || in_flight > 0 || self.late_possible(now) {
            return;
        }
        stats.add(&stats.unasked_bytes, n as u64);
        self.unasked("bytes came while nothing was asked");
    }

    /// A whole frame answering nothing on the line came (`late`: a retired id).
    pub(super) fn answered_nothing(&mut self, late: bool, now: Instant) {
        if self.stream || (late && self.late_possible(now)) {
            return;
        }
        self.unasked(if late {
            "a late reply came after relay.timeout_guard_ms"
        } else {
            "a frame came that answers no request"
        });
    }

    /// The device sends what nobody asked for: from now on every reply is held for
    /// confirmation. Said once.
    fn unasked(&mut self, what: &str) {
        if self.notifies || self.heard_unasked {
            return;
        }
        self.heard_unasked = true;
        warn!(
            "MBAP: {what}, though relay.device_notifications = false says the device \
             sends nothing unasked: every reply is now held until what follows it or a \
             pause confirms it (docs/reliability.md). If the device sends notifications, \
             set relay.device_notifications = true"
        );
    }

    /// May a late reply still come?
    fn late_possible(&self, now: Instant) -> bool {
        self.late_until.is_some_and(|until| now < until)
    }

    /// A request timed out: its reply may still come, for the guard time.
    pub(super) fn timed_out(&mut self, now: Instant) {
        let until = now + self.guard;
        self.late_until = Some(self.late_until.map_or(until, |u| u.max(until)));
    }

    pub(super) fn allocate(&mut self, now: Instant) -> u16 {
        self.tids.allocate(now.into_std())
    }

    pub(super) fn retire(&mut self, tid: u16, now: Instant) {
        self.tids.retire(tid, now.into_std());
        self.sent.retain(|s| s.tid != tid);
    }

    /// Appends `adu` as request `tid` to `out`.
    pub(super) fn encode(&mut self, adu: &Adu, tid: u16, now: Instant, out: &mut Vec<u8>) {
        let start = out.len();
        out.extend_from_slice(&tid.to_be_bytes());
        out.extend_from_slice(&adu.as_bytes()[2..]);
        self.sent(tid, &out[start..], now);
    }

    pub(super) fn has_room(&self, in_flight: usize, now: Instant) -> bool {
        in_flight < self.max_in_flight && self.paused_until().is_none_or(|until| now >= until)
    }

    /// No request before then: `request_pause_ms` after the last byte received (none
    /// without a pause, or before anything was received).
    fn paused_until(&self) -> Option<Instant> {
        let pausing = !self.request_pause.is_zero() && self.received > 0;
        pausing.then(|| self.last_byte + self.request_pause)
    }

    /// Bytes the decoder holds, not yet a frame.
    pub(super) fn buffered(&self) -> usize {
        self.decoder.buffered()
    }

    pub(super) fn received(&mut self, bytes: &[u8], now: Instant) {
        self.chunks.push_back((self.received, now));
        self.received += bytes.len() as u64;
        self.decoder.push(bytes);
        self.tape.push(bytes);
        self.last_byte = now;
    }

    pub(super) fn next_wake(&self, now: Instant, waiting: bool) -> Option<Instant> {
        // First the pause that ends a frame, then the frame gap.
        let quiet_for = if self.decoder.paused() {
            self.gap
        } else {
            self.pause
        };
        let frame = (self.decoder.buffered() > 0).then(|| self.last_byte + quiet_for);
        let pause = self.paused_until().filter(|&until| waiting && until > now);
        frame.into_iter().chain(pause).min()
    }

    pub(super) fn clear(&mut self) {
        self.decoder.clear();
        let to = self.decoder.consumed();
        self.tape.stale_to(to);
        self.chunks.clear();
        self.sent.clear();
    }

    pub(super) fn unsolicited(&self, tid: u16) -> Unsolicited {
        if self.tids.is_retired(tid) {
            Unsolicited::Late
        } else {
            Unsolicited::Notification
        }
    }

    /// Request `tid` goes on the line now as `bytes`, behind whatever is still being
    /// written.
    fn sent(&mut self, tid: u16, bytes: &[u8], now: Instant) {
        let left = self.tx_clear.max(now) + self.char_time * bytes.len() as u32;
        self.tx_clear = left;
        self.sent.push(Sent {
            tid,
            bytes: SentBytes::of(bytes),
            handed: now,
            left,
            unwritten: bytes.len(),
        });
    }

    /// A write that returned at `now` handed the next `n` bytes to the port. Each
    /// request whose last byte was among them cannot have left before `now` and the
    /// time on the wire of the bytes of this write up to it: the write may have begun
    /// well after the request was queued (a busy machine runs the loop late), and an
    /// echo counted from the queueing would look like a reply. Counted from the
    /// write's return, a device's own answer is dropped only if it began within a few
    /// microseconds of the request leaving, and only a copy of the request is ever
    /// dropped: the master gets 0x0B, never the echo as "written"
    /// (docs/reliability.md, item 8).
    pub(super) fn wrote(&mut self, n: usize, now: Instant) {
        let (mut rest, mut through) = (n, 0usize);
        for s in self.sent.iter_mut().filter(|s| s.unwritten > 0) {
            if rest == 0 {
                break;
            }
            let take = rest.min(s.unwritten);
            s.unwritten -= take;
            rest -= take;
            through += take;
            if s.unwritten == 0 {
                s.left = s.left.max(now + self.char_time * through as u32);
            }
        }
        self.tx_clear = self.tx_clear.max(now + self.char_time * n as u32);
    }

    /// When the byte at `offset` (in everything received) was read.
    fn read_at(&self, offset: u64) -> Option<Instant> {
        self.chunks
            .iter()
            .rev()
            .find(|&&(start, _)| start <= offset)
            .map(|&(_, at)| at)
    }

    /// Did `frame`, just decoded with the id of a request in flight, begin arriving
    /// too early to be its reply? Then says why.
    ///
    /// - Its first byte was read before the request was handed to the port: it was
    ///   made of bytes already there, a frame that lost its own id and took the two
    ///   bytes before it as one (register values equal to the request's id).
    /// - It is a copy of the request that began arriving before the request could have
    ///   left: its echo. An RS-232 loopback (a cable, an adapter) sends every request
    ///   straight back, and the echo of an FC 05 or 06 write is byte for byte its
    ///   successful reply. It began no later than its first byte was read, nor than its
    ///   own time on the wire before its last byte was read.
    fn too_early(&self, frame: &Adu) -> Option<Early> {
        let sent = self.sent.iter().find(|s| s.tid == frame.tid())?;
        let len = frame.as_bytes().len() as u64;
        let end = self.decoder.consumed();
        let first = self.read_at(end - len)?;
        if first < sent.handed {
            return Some(Early::Stale);
        }
        if frame.as_bytes() != &sent.bytes[..] {
            return None;
        }
        let last = self.read_at(end - 1)?;
        let on_wire = self.char_time * len as u32;
        let began = last.checked_sub(on_wire).map_or(first, |b| b.min(first));
        (began < sent.left).then_some(Early::Echo)
    }

    /// Said the first time a reply waited for the pause that confirms it (nothing
    /// followed it): why replies take longer than the device, and what to do about it
    /// (docs/reliability.md "How", docs/performance.md).
    fn tell_pause(&mut self) {
        self.told_pause = true;
        let why = if self.notifies {
            "the device sends notifications (relay.device_notifications)"
        } else if self.heard_unasked {
            "the device was heard talking unasked"
        } else {
            "another reply, or a late one, could follow it"
        };
        info!(
            "MBAP: a reply waited for the line to be quiet for {:.2} ms after it, to \
             confirm it arrived whole, because {why} (docs/reliability.md); each such \
             reply takes that much longer. The pause comes from the port \
             (serial.silence_floor_ms = \"auto\"); with several requests on the line \
             (relay.max_in_flight) replies confirm each other",
            self.pause.as_secs_f64() * 1000.0
        );
    }

    /// The whole frames read so far, each a reply to a request `in_flight`, one
    /// dropped as read before its request left, or one refusing its request as a
    /// misfit; what made no frame counted.
    pub(super) fn frames_into<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) {
        let idle = now.saturating_duration_since(self.last_byte);
        if idle >= self.pause {
            self.decoder.pause();
        }
        let quiet = idle >= self.gap;
        loop {
            let judge = RelayJudge {
                in_flight,
                tids: &self.tids,
                now,
                stream: self.stream,
                only_replies: !self.notifies && !self.heard_unasked && !self.late_possible(now),
                wire: self.wire,
            };
            let frame = match self.decoder.next_frame(&judge, quiet) {
                Some(Framed::Frame(frame)) => frame,
                // No check to fail on MBAP: the judge decides.
                Some(Framed::Corrupt(_)) => continue,
                None => break,
            };
            let end = self.decoder.consumed();
            let len = frame.as_bytes().len();
            let at = self.read_at(end - 1).unwrap_or(now);
            self.tape.frame(end, len, Some(at), Reason::LostSync);
            if self.dropped_early(&frame, at, stats)
                || self.misfit(in_flight, &frame, at, stats, seen)
            {
                continue;
            }
            let reply = in_flight.iter().any(|f| f.tid == frame.tid());
            if reply && idle >= self.pause && !self.told_pause {
                self.tell_pause();
            }
            seen.push(Seen::Frame(frame, at));
        }
        self.settle_turn(now, stats);
    }

    /// A frame read before its request left (stale, or its echo): dropped and
    /// counted. `true`: it was.
    fn dropped_early(&mut self, frame: &Adu, at: Instant, stats: &Stats) -> bool {
        let Some(why) = self.too_early(frame) else {
            return false;
        };
        let (what, counter, reason) = match why {
            Early::Stale => (
                "a frame read before its request was sent, dropped",
                &stats.dropped_stale,
                Reason::Stale,
            ),
            Early::Echo => (
                "a copy of the request that began before it had left: its echo, dropped",
                &stats.dropped_echo,
                Reason::Echo,
            ),
        };
        let len = frame.as_bytes().len() as u64;
        debug!(tid = frame.tid(), "{what}: {:?}", frame);
        stats.add(&stats.dropped_bytes, len);
        stats.add(counter, len);
        self.tape
            .whole_frame(Some(at), reason, frame.as_bytes(), what);
        true
    }

    /// A frame with a request's id that does not fit that request (another unit,
    /// function or shape): the request refused. `true`: it was.
    fn misfit<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        frame: &Adu,
        at: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) -> bool {
        let Some(f) = in_flight.iter().find(|f| f.tid == frame.tid()) else {
            return false;
        };
        let asked = f.req.adu();
        if asked.unit() == frame.unit() && pdu::reply_matches(asked.pdu(), frame.pdu()) {
            return false;
        }
        debug!(
            tid = frame.tid(),
            "a reply that does not fit its request: {:?}", frame
        );
        stats.add(&stats.bad_frames, 1);
        let why = "a reply with its request's id that does not fit the request";
        self.tape
            .whole_frame(Some(at), Reason::LostSync, frame.as_bytes(), why);
        seen.push(Seen::Corrupt(frame.tid()));
        true
    }

    /// The turn's end: the bytes that made no frame said, the chunks read wholly
    /// forgotten, what the framer dropped counted.
    fn settle_turn(&mut self, now: Instant, stats: &Stats) {
        // Bytes the decoder dropped after the last frame: garbage, a refuted frame, a
        // partial frame the frame gap ended.
        let consumed = self.decoder.consumed();
        self.tape.dropped_to(
            consumed,
            Some(now),
            Reason::LostSync,
            "bytes that make no frame (garbage, a frame that lost bytes, a partial frame)",
        );
        // Chunks wholly taken by the decoder are no longer needed.
        let consumed = self.decoder.consumed();
        while self
            .chunks
            .get(1)
            .is_some_and(|&(start, _)| start <= consumed)
        {
            self.chunks.pop_front();
        }
        // What the framer dropped or refuted since the last turn: counters only grow,
        // whatever the framing.
        stats.add(&stats.dropped_bytes, self.decoder.take_dropped());
        stats.add(&stats.refuted_frames, self.decoder.take_refuted());
    }
}

#[cfg(test)]
mod tests;
