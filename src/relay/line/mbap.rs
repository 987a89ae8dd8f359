//! The MBAP line (the CIE-M10): serial-side transaction ids, several requests on the
//! line at once, the resynchronising decoder that confirms a frame by what follows it
//! or a pause whenever something can follow it, notifications and late replies told
//! apart, echoes told by timing on a wire (docs/reliability.md).

use super::{Seen, Unsolicited};
use crate::capture::packet::Reason;
use crate::capture::tape::Tape;
use crate::config::{Notifications, RelayConfig, SerialConfig};
use crate::frame::framer::{Framed, Framer};
use crate::frame::mbap::FrameRef;
use crate::frame::{pdu, FunctionCode};
use crate::frame::{Adu, Judge};
use crate::port::kind::{self, PortInfo};
use crate::relay::inflight::{Asked, InFlight};
use crate::stats::Stats;
use crate::tids::Tids;
use bytes::Bytes;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

pub(super) struct Mbap {
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
    request_pause: Duration,
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
    bytes: Bytes,
    /// When it was handed to the port: nothing read before then answers it.
    handed: Instant,
    /// The earliest instant its last byte can have left at the configured speed: a
    /// copy of it that began arriving before then is its echo.
    left: Instant,
}

/// The relay's view of which frames on the line it can use (docs/design.md §1 step 4,
/// §2).
struct RelayJudge<'a, R> {
    in_flight: &'a [InFlight<R>],
    tids: &'a Tids,
    now: Instant,
    stream: bool,
    /// Nothing but the replies to the requests in flight can come on the line: the
    /// device sends nothing unasked and no late reply is possible.
    only_replies: bool,
    /// There is a wire (and so noise) between the port and the device.
    wire: bool,
}

/// Can anything follow frame `tid` on the line, so that a frame that lost a byte may
/// have completed itself with the first byte of it (docs/reliability.md, "When
/// nothing can follow a reply")? Another request in flight (its reply), a late reply
/// (`late`: a request ended without its reply within the guard time), or a frame the
/// device sends unasked (`unasked`). Otherwise the device sends nothing more until the
/// next request, which the gateway sends only after this one is answered or over.
pub(crate) fn may_follow(
    tid: u16,
    mut in_flight: impl Iterator<Item = u16>,
    late: bool,
    unasked: bool,
) -> bool {
    late || unasked || in_flight.any(|t| t != tid)
}

impl<R: Asked> Judge for RelayJudge<'_, R> {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.is_reply()
            || self
                .in_flight
                .iter()
                .any(|f| f.req.adu().function_code() == code.base())
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        match self.in_flight.iter().find(|f| f.tid == frame.tid()) {
            Some(f) => {
                f.req.adu().unit() == frame.unit()
                    && pdu::reply_matches(f.req.adu().pdu(), frame.pdu())
            }
            // Not an answer to anything on the line: a device notification (id 0), or a
            // late answer (a retired id), to be dropped as such. Any other id is not
            // ours: a reply shifted by a lost byte carries its own low byte after a
            // stranger's high byte (tids.rs), so ids sharing a low byte with one in
            // flight are refused even when retired.
            None => {
                let tid = frame.tid();
                (tid == 0 || self.tids.is_retired(tid))
                    && pdu::reply_well_formed(frame.pdu())
                    && !self.in_flight.iter().any(|f| f.tid & 0xFF == tid & 0xFF)
            }
        }
    }

    /// The id and unit of a request in flight, the shape of no reply to it, and not
    /// a copy of the request (an echo of a read never has a reply's shape): once
    /// confirmed, the device's own answer, unusable. Answered at once (a resend or
    /// 0x0B) rather than left to the response timeout; refuted, it is rescanned as a
    /// refused frame is (docs/reliability.md).
    fn deliver_refused(&self, frame: FrameRef<'_>) -> bool {
        self.in_flight.iter().any(|f| {
            f.tid == frame.tid()
                && f.req.adu().unit() == frame.unit()
                && f.req.adu().pdu() != frame.pdu()
        })
    }

    /// On a serial line: a frame that lost a byte completes itself with the first byte
    /// of whatever follows it. Whether anything can follow decides [`Judge::alone`].
    ///
    /// Not over TCP, where no byte is lost and a whole frame is the frame.
    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        !self.stream
    }

    /// When nothing can follow it ([`may_follow`]), a whole reply with nothing after
    /// it is its device's reply (or register values spelt a header: condition 3), so
    /// it is taken at once, without the pause. On a wire it must have come back to
    /// back: a byte after a pause there may be noise completing a reply that lost one.
    /// Where there is no wire (a pty) there is no noise, and a device that pauses
    /// inside its frames is served.
    fn alone(&self, frame: FrameRef<'_>, straddles: bool) -> bool {
        let tid = frame.tid();
        self.only_replies
            && !(straddles && self.wire)
            && !may_follow(tid, self.in_flight.iter().map(|f| f.tid), false, false)
    }

    /// A pause confirms a frame when no other reply is due (or its own request's time
    /// is up): then nothing is expected after it. While other replies are due, the
    /// frame waits for the next one or for the frame gap: a pause inside that next
    /// reply, right after a byte this one borrowed, must not pass for the end of the
    /// line's talk.
    fn pause_confirms(&self, frame: FrameRef<'_>) -> bool {
        let tid = frame.tid();
        let due = |f: &InFlight<R>| f.deadline > self.now;
        let own_expired = self.in_flight.iter().any(|f| f.tid == tid && !due(f));
        own_expired || !self.in_flight.iter().any(|f| f.tid != tid && due(f))
    }
}

impl Mbap {
    pub(super) fn new(
        relay: &RelayConfig,
        serial: &SerialConfig,
        stream: bool,
        now: Instant,
    ) -> Mbap {
        let gap = Duration::from_millis(relay.frame_gap_ms);
        let mut line = Mbap {
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
            PortInfo::plain(kind::Kind::Tcp)
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

    pub(super) fn encode(&mut self, adu: &Adu, tid: u16, now: Instant) -> Bytes {
        let bytes = adu.with_tid(tid).into_bytes();
        self.sent(tid, &bytes, now);
        bytes
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
        self.tape.dropped_to(
            to,
            None,
            Reason::Stale,
            "bytes held when the port was opened or lost",
        );
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
    fn sent(&mut self, tid: u16, bytes: &Bytes, now: Instant) {
        let left = self.tx_clear.max(now) + self.char_time * bytes.len() as u32;
        self.tx_clear = left;
        self.sent.push(Sent {
            tid,
            bytes: bytes.clone(),
            handed: now,
            left,
        });
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

    pub(super) fn frames<R: Asked>(
        &mut self,
        in_flight: &[InFlight<R>],
        now: Instant,
        stats: &Stats,
    ) -> Vec<Seen> {
        let idle = now.saturating_duration_since(self.last_byte);
        if idle >= self.pause {
            self.decoder.pause();
        }
        let quiet = idle >= self.gap;
        let mut seen = Vec::new();
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
            if let Some(why) = self.too_early(&frame) {
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
                debug!(tid = frame.tid(), "{what}: {:?}", frame);
                stats.add(&stats.dropped_bytes, len as u64);
                stats.add(counter, len as u64);
                self.tape
                    .whole_frame(Some(at), reason, frame.as_bytes(), what);
                continue;
            }
            if let Some(f) = in_flight.iter().find(|f| f.tid == frame.tid()) {
                let asked = f.req.adu();
                if asked.unit() != frame.unit() || !pdu::reply_matches(asked.pdu(), frame.pdu()) {
                    debug!(
                        tid = frame.tid(),
                        "a reply that does not fit its request: {:?}", frame
                    );
                    stats.add(&stats.bad_frames, 1);
                    let why = "a reply with its request's id that does not fit the request";
                    let bytes = frame.as_bytes();
                    self.tape
                        .whole_frame(Some(at), Reason::LostSync, bytes, why);
                    seen.push(Seen::Corrupt(frame.tid()));
                    continue;
                }
            }
            let reply = in_flight.iter().any(|f| f.tid == frame.tid());
            if reply && idle >= self.pause && !self.told_pause {
                self.tell_pause();
            }
            seen.push(Seen::Frame(frame, at));
        }
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
        seen
    }
}

#[cfg(test)]
mod tests {
    use super::super::Line;
    use super::*;
    use crate::frame::hex::parse as bytes;

    const MS: Duration = Duration::from_millis(1);

    fn mbap(baud: u32) -> (Line, Instant) {
        let serial = SerialConfig {
            baud_rate: baud,
            ..SerialConfig::default()
        };
        let now = Instant::now();
        (Line::new(&RelayConfig::default(), &serial, false, now), now)
    }

    /// A request as the table holds it in tests: the ADU, never resent.
    type Req = (Adu, u32);

    /// Request `adu` on the line as `tid` since `now`, due in a second.
    fn in_flight(tid: u16, adu: &Adu, now: Instant) -> InFlight<Req> {
        InFlight {
            tid,
            deadline: now + Duration::from_secs(1),
            timeout: Duration::from_secs(1),
            req: (adu.clone(), 0),
        }
    }

    /// Request `adu` sent now.
    fn send(line: &mut Line, adu: &Adu, now: Instant) -> InFlight<Req> {
        let tid = line.allocate(now);
        line.encode(adu, tid, now, &Stats::default());
        in_flight(tid, adu, now)
    }

    fn frames(line: &mut Line, in_flight: &[InFlight<Req>], now: Instant) -> Vec<Vec<u8>> {
        line.frames(in_flight, now, &Stats::default())
            .into_iter()
            .map(|s| match s {
                Seen::Frame(f, _) => f.as_bytes().to_vec(),
                Seen::Corrupt(_) => panic!("corrupt on an MBAP line"),
            })
            .collect()
    }

    /// An RS-232 loopback sends an FC 06 write straight back, byte for byte its
    /// successful reply, while the write is still going out (12 bytes at 9600 baud
    /// take 12.5 ms). A copy that began before the write had left is its echo; the
    /// device's own reply after it is the answer.
    #[test]
    fn a_copy_of_the_request_that_began_before_it_left_is_its_echo() {
        let (mut line, t0) = mbap(9600);
        let write = Adu::build(9, 1, &[6, 0, 1, 0, 3]);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        line.received(&sent[..4], t0 + MS, &Stats::default());
        line.received(&sent[4..], t0 + 12 * MS, &Stats::default());
        assert!(frames(&mut line, &[f], t0 + 40 * MS).is_empty());
        // Read late, in one piece: its own time on the wire before it was read is
        // still before the write left.
        let (mut line, t0) = mbap(9600);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        line.received(&sent, t0 + 20 * MS, &Stats::default());
        assert!(frames(&mut line, &[f], t0 + 60 * MS).is_empty());
        // The device's reply, begun after the write left.
        let (mut line, t0) = mbap(9600);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        line.received(&sent, t0 + 26 * MS, &Stats::default());
        assert_eq!(frames(&mut line, &[f], t0 + 60 * MS), vec![sent.clone()]);
        // A request queued behind another leaves after it.
        let (mut line, t0) = mbap(9600);
        let first = send(&mut line, &Adu::build(1, 1, &[3, 0, 0, 0, 1]), t0);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        line.received(&sent, t0 + 37 * MS, &Stats::default());
        assert!(frames(&mut line, &[first, f], t0 + 90 * MS).is_empty());
    }

    /// Bytes read before a request was sent cannot begin its reply: a notification
    /// whose header was damaged leaves its last register (here equal to the request's
    /// id) to be scanned, and the next notification, having lost its id, completes a
    /// frame with that id and the shape the request calls for.
    #[test]
    fn a_frame_begun_before_its_request_was_sent_does_not_answer_it() {
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let body = bytes("00 00 00 05 01 03 02 02 F4");
        for stale_before in [true, false] {
            let (mut line, t0) = mbap(19_200);
            let tid = line.allocate(t0);
            let stale = [&bytes("00 00 00 00 05 01 03 02")[..], &tid.to_be_bytes()].concat();
            let sent_at = t0 + 2 * MS;
            let read_at = t0 + if stale_before { MS } else { 3 * MS };
            if stale_before {
                line.received(&stale, read_at, &Stats::default());
            }
            line.encode(&read, tid, sent_at, &Stats::default());
            if !stale_before {
                line.received(&stale, read_at, &Stats::default());
            }
            line.received(&body, t0 + 4 * MS, &Stats::default());
            let f = in_flight(tid, &read, sent_at);
            let got = frames(&mut line, &[f], t0 + 40 * MS);
            if stale_before {
                assert!(got.is_empty(), "{got:02X?}");
            } else {
                // Read after the request left, the same bytes pass: the bound of
                // docs/reliability.md (ids are random, so values equal one by chance).
                assert_eq!(got, vec![[&tid.to_be_bytes()[..], &body[..]].concat()]);
            }
        }
    }

    /// With the device said to send notifications, every reply is held until what
    /// follows confirms it: a reply that lost a data byte, then a notification at once,
    /// is never delivered. A reply alone is confirmed by a pause (the floor of a port
    /// not yet known, 20 ms), not the frame gap; with another reply due it waits for
    /// that one, or for the frame gap.
    #[test]
    fn replies_are_confirmed_by_what_follows_or_a_pause() {
        let relay = RelayConfig {
            device_notifications: true,
            ..RelayConfig::default()
        };
        let serial = SerialConfig::default();
        let t0 = Instant::now();
        let mut line = Line::new(&relay, &serial, false, t0);
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 3]);
        let a = send(&mut line, &read, t0);
        let mut reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
            .as_bytes()
            .to_vec();
        reply.remove(10);
        let notification = bytes("00 00 00 00 00 05 01 03 02 00 0F");
        let at = t0 + 30 * MS;
        line.received(&[reply, notification].concat(), at, &Stats::default());
        for after in [0, 20, 50] {
            assert!(frames(&mut line, std::slice::from_ref(&a), at + after * MS).is_empty());
        }

        let mut line = Line::new(&relay, &serial, false, t0);
        let a = send(&mut line, &read, t0);
        let b = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &[3, 6, 0, 1, 0, 2, 0, 3])
            .as_bytes()
            .to_vec();
        let at = t0 + 30 * MS;
        line.received(&reply, at, &Stats::default());
        let both = [a, b];
        assert!(frames(&mut line, &both, at + 19 * MS).is_empty());
        assert!(
            frames(&mut line, &both, at + 20 * MS).is_empty(),
            "b is due"
        );
        assert_eq!(line.next_wake(at + 20 * MS, false), Some(at + 50 * MS));
        assert_eq!(frames(&mut line, &both, at + 50 * MS), vec![reply]);
        let mut line = Line::new(&relay, &serial, false, t0);
        let a = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &[3, 6, 0, 1, 0, 2, 0, 3])
            .as_bytes()
            .to_vec();
        line.received(&reply, at, &Stats::default());
        assert_eq!(line.next_wake(at, false), Some(at + 20 * MS));
        assert_eq!(frames(&mut line, &[a], at + 20 * MS), vec![reply]);
    }

    /// A reply nothing can follow (one request in flight, no late reply possible, a
    /// device that sends nothing unasked) is taken the moment it is whole; the same
    /// reply that lost a data byte waits for a byte that never comes and is dropped
    /// after the frame gap. With two requests in flight it is held for the other's.
    #[test]
    fn a_lone_reply_is_taken_at_once_and_a_damaged_one_never() {
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 3]);
        let (mut line, t0) = mbap(19_200);
        let a = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
            .as_bytes()
            .to_vec();
        let at = t0 + 10 * MS;
        line.received(&reply, at, &Stats::default());
        assert_eq!(
            line.next_wake(at, false),
            Some(at + 20 * MS),
            "not taken yet"
        );
        assert_eq!(
            frames(&mut line, std::slice::from_ref(&a), at),
            vec![reply.clone()]
        );
        assert_eq!(line.next_wake(at, false), None);

        let (mut line, t0) = mbap(19_200);
        let a = send(&mut line, &read, t0);
        let mut lost = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
            .as_bytes()
            .to_vec();
        lost.remove(10);
        line.received(&lost, at, &Stats::default());
        for after in [0, 20, 50, 60] {
            assert!(frames(&mut line, std::slice::from_ref(&a), at + after * MS).is_empty());
        }

        let (mut line, t0) = mbap(19_200);
        let a = send(&mut line, &read, t0);
        let b = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
            .as_bytes()
            .to_vec();
        line.received(&reply, at, &Stats::default());
        let both = [a, b];
        assert!(
            frames(&mut line, &both, at).is_empty(),
            "b's reply may follow"
        );
        assert_eq!(frames(&mut line, &both, at + 50 * MS), vec![reply]);
    }

    /// What may follow a reply decides whether it is held: a late reply for the guard
    /// time after a timeout (`timeout_guard_ms`, 100 ms), then no longer; anything
    /// heard while nothing was asked, for good (said once, counted); bytes already
    /// after it, or a pause inside it.
    #[test]
    fn what_may_follow_a_reply_holds_it() {
        use std::sync::atomic::Ordering;
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let whole = |tid| Adu::build(tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
        // A timeout: the next reply is held for 100 ms after it.
        let (mut line, t0) = mbap(19_200);
        line.timed_out(t0, &Stats::default());
        let a = send(&mut line, &read, t0);
        line.received(&whole(a.tid), t0 + 5 * MS, &Stats::default());
        assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 5 * MS).is_empty());
        assert_eq!(
            frames(&mut line, std::slice::from_ref(&a), t0 + 25 * MS),
            vec![whole(a.tid)]
        );
        let b = send(&mut line, &read, t0 + 100 * MS);
        line.received(&whole(b.tid), t0 + 105 * MS, &Stats::default());
        assert_eq!(
            frames(&mut line, std::slice::from_ref(&b), t0 + 105 * MS),
            vec![whole(b.tid)]
        );
        // Bytes while nothing is asked: counted, and every reply held from then on.
        let stats = Stats::default();
        let (mut line, t0) = mbap(19_200);
        line.heard(3, 0, t0, &stats);
        line.received(&[0xFF; 3], t0, &stats);
        assert_eq!(stats.unasked_bytes.load(Ordering::Relaxed), 3);
        let a = send(&mut line, &read, t0 + 10 * MS);
        line.heard(11, 1, t0 + 12 * MS, &stats);
        line.received(&whole(a.tid), t0 + 12 * MS, &stats);
        assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 12 * MS).is_empty());
        assert_eq!(
            frames(&mut line, std::slice::from_ref(&a), t0 + 32 * MS),
            vec![whole(a.tid)]
        );
        assert_eq!(
            stats.unasked_bytes.load(Ordering::Relaxed),
            3,
            "only what came unasked"
        );
        // A noise byte right behind a whole reply, read with it: held, then refuted.
        let (mut line, t0) = mbap(19_200);
        let a = send(&mut line, &read, t0);
        line.received(
            &[whole(a.tid), vec![0x5A]].concat(),
            t0 + 5 * MS,
            &Stats::default(),
        );
        for after in [5, 25, 60] {
            assert!(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS).is_empty());
        }
        // A reply that lost its last byte, completed by a noise byte after a pause:
        // it straddles the pause, and is refuted.
        let (mut line, t0) = mbap(19_200);
        let a = send(&mut line, &read, t0);
        let w = whole(a.tid);
        line.received(&w[..w.len() - 1], t0 + 5 * MS, &Stats::default());
        assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 26 * MS).is_empty());
        line.received(&[0x00], t0 + 30 * MS, &Stats::default());
        for after in [30, 55, 90] {
            assert!(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS).is_empty());
        }
    }

    /// On a pty (no wire) a copy of the request read at once is the device's reply:
    /// an FC 06 write answered by a device that answers as soon as the request is in
    /// (pymodbus' serial server).
    #[test]
    fn on_a_pty_a_write_reply_equal_to_the_request_is_taken_at_once() {
        use crate::port::kind::{Kind, PortInfo};
        let (mut line, t0) = mbap(9600);
        let told = line.port_opened(&PortInfo::plain(Kind::Pty));
        assert!(told.contains("no wire"), "{told}");
        let write = Adu::build(9, 1, &[6, 0, 1, 0, 3]);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        line.received(&sent, t0 + MS / 10, &Stats::default());
        assert_eq!(frames(&mut line, &[f], t0 + MS / 10), vec![sent]);
        // Declared a wire, the same is its echo.
        let serial = SerialConfig {
            baud_rate: 9600,
            port_kind: crate::config::PortKind::Wire,
            ..SerialConfig::default()
        };
        let mut line = Line::new(&RelayConfig::default(), &serial, false, t0);
        line.port_opened(&PortInfo::plain(Kind::Pty));
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        let stats = Stats::default();
        line.received(&sent, t0 + MS / 10, &stats);
        assert!(line.frames(&[f], t0 + 60 * MS, &stats).is_empty());
        assert_eq!(
            stats
                .dropped_echo
                .load(std::sync::atomic::Ordering::Relaxed),
            12
        );
    }

    /// A device that pauses inside its reply (libmodbus' test server sends one byte
    /// every 5 ms): with nothing able to follow, on a pty (no wire, no noise) the
    /// whole reply is taken when its last byte comes; on a wire what came after a
    /// pause may be noise completing a damaged reply, and it is refuted.
    #[test]
    fn a_reply_with_pauses_inside_is_taken_where_there_is_no_wire() {
        use crate::port::kind::{Kind, PortInfo};
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        // A UART whose FIFO hands each byte over: the pause is 3.5 characters.
        let uart = Kind::Uart {
            driver: None,
            trigger: Some(1),
        };
        for (kind, taken) in [(Kind::Pty, true), (uart, false)] {
            let serial = SerialConfig {
                baud_rate: 115_200,
                ..SerialConfig::default()
            };
            let t0 = Instant::now();
            let mut line = Line::new(&RelayConfig::default(), &serial, false, t0);
            line.port_opened(&PortInfo::plain(kind.clone()));
            let a = send(&mut line, &read, t0);
            let reply = Adu::build(a.tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
            let mut got = Vec::new();
            for (i, b) in reply.iter().enumerate() {
                let at = t0 + (5 * i as u32 + 1) * MS;
                got.extend(frames(&mut line, std::slice::from_ref(&a), at));
                line.received(&[*b], at, &Stats::default());
                got.extend(frames(&mut line, std::slice::from_ref(&a), at + MS / 2));
            }
            for after in [30, 100] {
                got.extend(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS));
            }
            let want = if taken { vec![reply] } else { Vec::new() };
            assert_eq!(got, want, "{kind:?}");
        }
    }

    /// The dropped-byte counter only grows: two lines counting into one `Stats` (or
    /// the MBAP and RTU code paths) add their own drops, never overwrite each other's
    /// (the decoder's running total used to be stored into it).
    #[test]
    fn dropped_bytes_add_up_across_lines_sharing_the_counters() {
        use std::sync::atomic::Ordering;
        let stats = Stats::default();
        let (mut a, t0) = mbap(19_200);
        let (mut b, _) = mbap(19_200);
        a.received(&[0xFF; 5], t0, &stats);
        b.received(&[0xFF; 3], t0, &stats);
        let later = t0 + Duration::from_secs(1);
        assert!(a.frames::<Req>(&[], later, &stats).is_empty());
        assert!(b.frames::<Req>(&[], later, &stats).is_empty());
        assert!(a.frames::<Req>(&[], later, &stats).is_empty());
        assert_eq!(stats.dropped_bytes.load(Ordering::Relaxed), 8);
    }

    /// Over TCP nothing is lost: a whole reply is taken the moment it is read, with
    /// another reply due (on a serial line it would wait for the frame gap), and
    /// `request_pause_ms` holds the next request back from the last byte read.
    #[test]
    fn over_tcp_a_whole_reply_is_taken_at_once_and_the_pause_kept() {
        let relay = RelayConfig {
            request_pause_ms: 30,
            max_in_flight: 2,
            ..RelayConfig::default()
        };
        let t0 = Instant::now();
        let mut line = Line::new(&relay, &SerialConfig::default(), true, t0);
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let a = send(&mut line, &read, t0);
        let b = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
        let at = t0 + MS;
        line.received(&reply, at, &Stats::default());
        assert_eq!(frames(&mut line, &[a, b], at), vec![reply]);
        assert!(!line.has_room(1, false, at + 29 * MS));
        assert_eq!(line.next_wake(at, true), Some(at + 30 * MS));
        assert!(line.has_room(1, false, at + 30 * MS));
    }
}
