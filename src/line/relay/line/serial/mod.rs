//! The RTU and ASCII line: one request at a time, tied to its reply by time alone
//! (bytes before the request left are not its reply: on a wire, its time at
//! `baud_rate` counts; a reply is taken once the line has been quiet after it), the
//! inter-frame gap, CRC/LRC, the guard after a timeout, broadcasts with their
//! turnaround, local echo. The way in (bytes read to frames seen) is
//! `serial/receive.rs`; what each unit still owes and how soon it answers,
//! `serial/owed.rs`; the line's state, the way out and its timers are here.

use crate::config::{FlowControl, RelayConfig, SerialConfig};
use crate::frame::framer::{Framer, ReplyFor};
use crate::frame::serial::Codec;
use crate::frame::{rtu, Adu};
use crate::line::port::kind::{self, PortInfo};
use crate::ops::capture::dropped::{Dropped, Tape};
use crate::ops::capture::packet::Reason;
use crate::ops::stats::Stats;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;
use tracing::debug;

/// The least quiet that confirms a reply where there is no wire (a pty): a device
/// program that writes one frame too many, a few milliseconds before or after its
/// reply, is caught by it (docs/reliability.md "RTU and ASCII", 7, which gives the
/// measure behind it and its cost).
const PTY_QUIET: Duration = Duration::from_millis(10);

/// A reply to the request on the line, held until the line has been quiet after it.
struct HeldReply {
    /// The reply, with the request's key.
    reply: Adu,
    /// When its last byte came.
    at: Instant,
    /// How long after the request left.
    took: Duration,
    /// The quiet after it that confirms it.
    quiet: Duration,
    /// Its unit owes answers: it is held for the unit's whole response timeout.
    owed: bool,
}

pub(super) struct Serial {
    /// Its settings: the time bytes take on the wire.
    port: SerialConfig,
    /// RTU or ASCII frames: the framer every side of the line uses.
    decoder: Framer,
    /// The silence before each request (`inter_frame_gap_us`; by default 3.5
    /// character times; none over TCP, where the device server keeps the gap on its
    /// own line).
    gap: Duration,
    /// The silence before a request once the last bytes on the line (the device's, or
    /// our own request's) made whole frames: `gap`, but none for ASCII by default (its
    /// frames end with CR LF, and the specification asks for no silence between them).
    gap_after_frame: Duration,
    /// What ends a frame of unknown shape: 3.5 character times, never less than
    /// `silence_floor_ms`.
    silence: Duration,
    /// `frame_gap_ms`: where there is no wire, a partial reply of known length is
    /// discarded after this much silence rather than `silence` (a program on a pty
    /// may pause inside a frame; nothing there is lost or added).
    frame_gap: Duration,
    /// The PDU of the request on the line, for the length of its reply; empty while
    /// nothing is asked (a PDU never is). Kept in its room: no allocation a request.
    asked: Vec<u8>,
    broadcast_delay: Duration,
    /// The line stays quiet this long after a timeout (`timeout_guard_ms`).
    guard: Duration,
    last_rx: Instant,
    /// No request before then: the gap (or the broadcast turnaround) after the last
    /// request left.
    ready_at: Instant,
    next_key: u16,
    /// Bytes sent whose echo is still to be read back (`echo = true`).
    echo: Option<VecDeque<u8>>,
    /// The frame being written is a broadcast.
    broadcast_on_wire: bool,
    /// While a frame is being written: the earliest its last byte can leave.
    tx: Option<Instant>,
    /// Bytes of that frame not yet handed to the port.
    unwritten: usize,
    /// Bytes read while the frame was being written, with when they were read.
    held: Vec<(Instant, Vec<u8>)>,
    /// When the last request's last byte left: bytes read before then answer nothing.
    reply_from: Instant,
    /// Over TCP: bytes take no time on a wire, and there is no gap to keep.
    stream: bool,
    /// A wire at `baud_rate` between the port and the device (not a pty, unless
    /// `port_kind = "wire"`): a request's bytes take their time to leave.
    wire: bool,
    /// The line stays quiet this long after a reply or a timeout (`request_pause_ms`).
    pub(super) request_pause: Duration,
    /// The bytes dropped, for the capture.
    pub(super) tape: Tape,
    /// What a failed check is called: CRC (RTU) or LRC (ASCII).
    check: Reason,
    /// The gaps as configured, kept for where there is a wire: `gap` and
    /// `gap_after_frame` become these again when a reopened port has one.
    wire_gaps: (Duration, Duration),
    /// `inter_frame_gap_us = 0`: the gap is the line's (3.5 character times at
    /// `baud_rate`), so it is kept only where there is a wire.
    auto_gap: bool,
    /// What each unit still owes (an answer for each of its requests that timed
    /// out, which it may yet send: a device that stalled, then answers its backlog)
    /// and its fastest reply (`serial/owed.rs`).
    owed: owed::Owed,
    /// The reply to the request on the line, held until the line has been quiet
    /// after it for `confirm`: a frame that follows sooner refutes it.
    candidate: Option<HeldReply>,
    /// The quiet that confirms a reply: none over TCP, the silence that ends a frame
    /// on a wire, and on a pty that or [`PTY_QUIET`], the longer.
    confirm: Duration,
    /// The request (its key) a reply was held for its unit's whole response timeout:
    /// once a request, so it stays on the line no longer than that past its deadline.
    held_once: Option<u16>,
}

impl Serial {
    pub(super) fn new(
        relay: &RelayConfig,
        serial: &SerialConfig,
        codec: Codec,
        stream: bool,
        now: Instant,
    ) -> Serial {
        let t35 = if stream {
            // The device server keeps the gap on its own line.
            Duration::ZERO
        } else {
            Duration::from_micros(rtu::t35_us(serial.baud_rate, kind::bits_per_char(serial)))
        };
        let gap = match serial.inter_frame_gap_us {
            _ if stream => Duration::ZERO,
            0 => t35,
            us => Duration::from_micros(us),
        };
        let gap_after_frame = match (serial.inter_frame_gap_us, codec) {
            (0, Codec::Ascii) => Duration::ZERO,
            _ => gap,
        };
        let silence = kind::silence(serial, &PortInfo::unknown());
        Serial {
            port: serial.clone(),
            decoder: Framer::serial(codec),
            gap,
            gap_after_frame,
            silence,
            frame_gap: Duration::from_millis(relay.frame_gap_ms),
            asked: Vec::new(),
            broadcast_delay: Duration::from_millis(relay.broadcast_delay_ms),
            guard: Duration::from_millis(relay.timeout_guard_ms),
            last_rx: now,
            ready_at: now,
            next_key: 0,
            echo: serial.echo.then(VecDeque::new),
            broadcast_on_wire: false,
            tx: None,
            unwritten: 0,
            held: Vec::new(),
            reply_from: now,
            stream,
            wire: !stream,
            request_pause: Duration::from_millis(relay.request_pause_ms),
            tape: Tape::default(),
            check: match codec {
                Codec::Rtu => Reason::Crc,
                Codec::Ascii => Reason::Lrc,
            },
            wire_gaps: (gap, gap_after_frame),
            auto_gap: serial.inter_frame_gap_us == 0,
            owed: owed::Owed::default(),
            candidate: None,
            confirm: if stream { Duration::ZERO } else { silence },
            held_once: None,
        }
    }

    /// How long `bytes` take to leave the port: none over TCP, nor where there is no
    /// wire (a pty passes them at once whatever `baud_rate` says).
    pub(super) fn wire_time(&self, bytes: usize) -> Duration {
        if self.stream || !self.wire {
            Duration::ZERO
        } else {
            kind::wire_time(&self.port, bytes)
        }
    }

    /// A port was opened and found to be `info`: whether bytes take their time on a
    /// wire, and the silence that ends a frame of unknown shape. Says how.
    pub(super) fn port_opened(&mut self, info: &PortInfo) -> String {
        if self.stream {
            return "no gap kept: the device server keeps it on its own line".into();
        }
        self.wire = kind::wire(&self.port, info);
        self.silence = kind::silence(&self.port, info);
        // A reply is confirmed by the quiet after it: on a wire the silence that ends
        // a frame; on a pty, where the next request follows a reply at once, long
        // enough for a device program's second write (docs/reliability.md "RTU and
        // ASCII", 7).
        self.confirm = if self.wire {
            self.silence
        } else {
            self.silence.max(PTY_QUIET)
        };
        (self.gap, self.gap_after_frame) = self.wire_gaps;
        if !self.wire && self.auto_gap {
            // Nothing can collide where there is no wire: the device has sent its
            // whole reply before the next request is written, and the two directions
            // of a pty never meet. Once the last frame on the line is whole, the next
            // request goes at once (docs/reliability.md "Knowing the wire"). Bytes
            // still arriving (a late reply, a frame of unknown shape) are waited out
            // as the silence that ends a frame, never less.
            self.gap_after_frame = Duration::ZERO;
            self.gap = self.gap.max(self.silence);
        }
        let wire = if self.wire {
            "a wire at serial.baud_rate: a reply must begin after its request has left"
        } else {
            "no wire: a reply may come however soon after its request, and a request \
             follows a whole reply at once"
        };
        format!(
            "{wire}; {:.2} ms of silence ends a frame of unknown shape, {:.2} ms of quiet \
             after a reply confirms it",
            self.silence.as_secs_f64() * 1000.0,
            self.confirm.as_secs_f64() * 1000.0
        )
    }

    /// A wire at `baud_rate` between the port and the device: its bytes take their
    /// time to leave, and `tcdrain` says when they have.
    pub(super) fn has_wire(&self) -> bool {
        self.wire && !self.stream
    }

    /// Can the port send a request's bytes later than their time on the wire after
    /// the write says? Flow control holds them while the device says stop, and the
    /// kernel's RS-485 mode (`rs485 = true`) keeps the transmitter on for its delays:
    /// there only `tcdrain` knows when the request has left. Elsewhere the line was
    /// silent before the request (the gap), so its last byte leaves its time on the
    /// wire after the write, and asking the drain thread would cost two thread
    /// hand-offs a transaction and tell nothing more (docs/reliability.md "RTU and
    /// ASCII"; docs/performance.md "No drain where it tells nothing").
    pub(super) fn holds_bytes_back(&self) -> bool {
        self.port.flow_control != FlowControl::None || self.port.rs485
    }

    pub(super) fn allocate(&mut self) -> u16 {
        self.next_key = self.next_key.wrapping_add(1);
        self.next_key
    }

    /// `frame` as it is on the wire, CRC or LRC included (for the traffic log).
    pub(super) fn on_wire(&self, frame: &Adu) -> Vec<u8> {
        self.decoder.encode(frame)
    }

    /// Appends `adu` as the line carries it to `out`.
    pub(super) fn encode(&mut self, adu: &Adu, now: Instant, stats: &Stats, out: &mut Vec<u8>) {
        // Nothing received before a request is written can be its reply.
        let held = self.drop_held(now, "received before the request was sent");
        let stale = self.decoder.clear() + held;
        let to = self.decoder.consumed();
        self.tape.dropped_to(
            to,
            Some(now),
            Reason::Stale,
            "received before the request was sent",
        );
        if stale > 0 {
            debug!(bytes = stale, "bytes received before the request discarded");
            stats.add(&stats.dropped_stale, stale as u64);
        }
        self.count_dropped(held, stats);
        self.candidate = None;
        self.held_once = None;
        let start = out.len();
        self.decoder.encode_into(adu, out);
        let bytes = &out[start..];
        if let Some(echo) = &mut self.echo {
            // Any echo still awaited belongs to an earlier request, long done.
            echo.clear();
            echo.extend(bytes);
        }
        self.broadcast_on_wire = adu.unit() == 0;
        // Written from now on: its last byte cannot leave before its time on the wire
        // has passed.
        self.tx = Some(now + self.wire_time(bytes.len()));
        self.unwritten = bytes.len();
    }

    pub(super) fn has_room(&self, in_flight: usize, busy: bool, now: Instant) -> bool {
        in_flight == 0 && !busy && now >= self.free_at()
    }

    pub(super) fn wrote(&mut self, n: usize, polled: Instant) {
        self.unwritten = self.unwritten.saturating_sub(n);
        let wire = self.wire_time(n);
        if let Some(earliest) = &mut self.tx {
            // Held back by flow control, the last bytes leave later than a frame
            // written in one go would.
            *earliest = (*earliest).max(polled + wire);
        }
    }

    /// While a frame is being written or drained: the earliest its last byte can leave.
    pub(super) fn leaves_at(&self) -> Option<Instant> {
        self.tx
    }

    /// Bytes read before the earliest instant the last byte can have left (its time
    /// on the wire after it was written) are not the reply. `tcdrain` returning is no
    /// such bound: the relay may see it late (its thread and the blocking pool's are
    /// scheduled), and a fast device's reply may be read in between; a USB adapter
    /// may report the bytes gone while its own FIFO still holds them.
    pub(super) fn drained(&mut self, now: Instant, stats: &Stats) -> Instant {
        let earliest = self.tx.take().unwrap_or(now);
        let left = now.max(earliest);
        self.judge_held(earliest, stats);
        let turnaround = if std::mem::take(&mut self.broadcast_on_wire) {
            self.broadcast_delay
        } else {
            self.gap_after_frame
        };
        self.ready_at = self.ready_at.max(left + turnaround);
        left
    }

    /// The silence after which what is buffered ends (a frame of unknown shape) or is
    /// discarded: `silence`, or where there is no wire and the partial frame's length
    /// is known, the frame gap.
    fn quiet_after(&self) -> Duration {
        let known = !self.asked.is_empty() && self.decoder.length_known(&ReplyFor(&self.asked));
        if !self.wire && !self.stream && known {
            self.frame_gap.max(self.silence)
        } else {
            self.silence
        }
    }

    /// The earliest instant the line needs the loop. Each instant counts on its own,
    /// and one that has passed never hides a later one: the turn that reads stray
    /// bytes after a timeout may end past the silence that ends them (a busy machine),
    /// and the end of the guard must still wake the request waiting for it.
    pub(super) fn next_wake(&self, now: Instant, waiting: bool) -> Option<Instant> {
        // The silence that ends what is buffered. Passed already, it wakes the loop at
        // once where looking again ends something (RTU cuts a frame at silence, and
        // bytes nothing asked for are dropped), and not where it would not (an ASCII
        // frame in flight waits for its CR LF): the loop would spin.
        let silence = (self.decoder.buffered() > 0)
            .then(|| self.last_rx + self.quiet_after())
            .filter(|&at| at > now || self.silence_ends_frame());
        // The line free for the next request. Passed, it is dispatch's, which ran this
        // turn and found something else in the way (a request in flight or being
        // written, bytes not yet read), each of which wakes the loop when it changes.
        let free = waiting.then(|| self.free_at()).filter(|&at| at > now);
        // A reply held for confirmation: taken once the line was quiet after it.
        let confirm = self.confirming().map(|(_, at)| at);
        silence.into_iter().chain(free).chain(confirm).min()
    }

    /// The reply held for confirmation: the key of its request, and when the quiet
    /// after it confirms it. Its request stays on the line until then, past its
    /// deadline if need be: the reply came in time.
    pub(super) fn confirming(&self) -> Option<(u16, Instant)> {
        let c = self.candidate.as_ref()?;
        Some((c.reply.tid(), c.at + c.quiet))
    }

    /// Does the silence after what is buffered end it, whatever it holds? RTU: the
    /// framer cuts a frame of unknown shape there; with nothing asked, anything is
    /// dropped.
    fn silence_ends_frame(&self) -> bool {
        self.asked.is_empty() || self.decoder.codec() == Some(Codec::Rtu)
    }

    pub(super) fn clear(&mut self, stats: &Stats) {
        self.candidate = None;
        self.decoder.clear();
        let to = self.decoder.consumed();
        self.tape.stale_to(to);
        self.count_dropped(0, stats);
        if let Some(echo) = &mut self.echo {
            echo.clear();
        }
        self.tx = None;
        self.unwritten = 0;
        self.held.clear();
        self.broadcast_on_wire = false;
    }

    /// A request to `unit` that left at `left` got no answer in time: the device may
    /// have read it and answer it later, after any it holds before it; the unit owes
    /// that answer until it pays it, or has been quiet for `whole` (its whole response
    /// timeout) after a frame sent after it was asked (docs/reliability.md "RTU and
    /// ASCII", 6).
    pub(super) fn unanswered(&mut self, unit: u8, left: Instant, whole: Duration, now: Instant) {
        self.owed.unanswered(unit, left, whole, now);
    }

    pub(super) fn timed_out(&mut self, now: Instant, hold: Duration, stats: &Stats) {
        if let Some(c) = self.candidate.take() {
            self.refuted(&c, stats);
        }
        // A partial reply stays buffered: completed, it pays what its unit owes (a
        // late answer), or is dropped as answering nothing.
        let held = self.drop_held(now, "a partial reply when its request timed out");
        self.count_dropped(held, stats);
        // Never written in time (CTS held low): nothing of it is on its way.
        self.tx = None;
        // The guard counts from the end of `hold` (a learned timeout's way to its
        // ceiling): a reply later than the ceiling is dropped for the guard's length,
        // as it would be after a fixed timeout at the ceiling (docs/reliability.md
        // "Learned timeouts").
        let quiet = (hold + self.guard).max(self.request_pause);
        self.ready_at = self.ready_at.max(now + quiet);
    }

    pub(super) fn shortest_transaction(&self, adu: &Adu) -> Duration {
        // The line's pace at `baud_rate`, on a pty too: a backed-off unit's answers
        // come no faster than a wire would serve them.
        let bytes = self.decoder.encoded_len(adu.pdu().len()) + self.decoder.encoded_len(2);
        let on_line = if self.stream {
            Duration::ZERO
        } else {
            kind::wire_time(&self.port, bytes)
        };
        on_line + 2 * self.gap
    }

    /// Drops the bytes held while a request was being written (`why`, for the
    /// capture); returns how many.
    fn drop_held(&mut self, now: Instant, why: &'static str) -> usize {
        let mut n = 0;
        for (at, bytes) in std::mem::take(&mut self.held) {
            n += bytes.len();
            self.tape.dropped_aside(|| Dropped {
                at: Some(at.min(now)),
                reason: Reason::Stale,
                bytes,
                whole: false,
                detail: why,
            });
        }
        n
    }

    /// Counts what the framer dropped since last asked, and `held` bytes dropped
    /// before they reached it.
    fn count_dropped(&mut self, held: usize, stats: &Stats) {
        let n = held as u64 + self.decoder.take_dropped();
        if n > 0 {
            stats.add(&stats.dropped_bytes, n);
        }
    }

    /// The line is free once the turnaround after our last request has passed and the
    /// device has been quiet for the gap, counted from the instant its last byte was
    /// read (docs/performance.md, "RTU at the line's limit"), or `request_pause_ms` if
    /// longer.
    fn free_at(&self) -> Instant {
        let gap = if self.decoder.buffered() == 0 {
            self.gap_after_frame
        } else {
            self.gap
        };
        self.ready_at
            .max(self.last_rx + gap.max(self.request_pause))
    }
}

mod owed;
mod receive;

#[cfg(test)]
mod tests;
