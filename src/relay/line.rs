//! The framing seam of the relay: what differs between a line of MBAP frames (the
//! CIE-M10) and a line of RTU or ASCII frames. Everything else (queues, round-robin,
//! timeouts, retries, unit backoff, 0x0A/0x0B, the shutdown drain) is the relay's and
//! shared.
//!
//! - [`Mbap`]: serial-side transaction ids, several requests on the line at once
//!   (`max_in_flight`), the resynchronising decoder with confirmation, notifications.
//! - [`Serial`]: RTU or ASCII. No transaction id, so one request at a time, and only
//!   time ties a reply to its request: what was received before a request has left is
//!   discarded, a reply must start after it; frames delimited by length, silence or
//!   line feed and checked by CRC or LRC; the inter-frame gap (3.5 character times)
//!   before each request, counted from the last byte seen or sent; a guard time after
//!   a timeout, for the late reply; broadcasts (unit 0) with a turnaround delay;
//!   local-echo suppression.

use super::InFlight;
use crate::config::{Notifications, RelayConfig, SerialConfig};
use crate::frame::mbap::FrameRef;
use crate::frame::pdu;
use crate::frame::serial::{Codec, Decoded, Decoder, Expect};
use crate::frame::{rtu, Adu, Judge, Resync};
use crate::serial;
use crate::stats::Stats;
use crate::tids::{self, Tids};
use bytes::Bytes;
use std::collections::VecDeque;
use std::time::Duration;
use tokio::time::Instant;
use tracing::debug;

/// What the line made of the bytes it received.
pub(super) enum Seen {
    /// A frame; its transaction id is the serial-side one (for RTU/ASCII, the key of
    /// the request it answers, which it has been checked against).
    Frame(Adu),
    /// The answer to the request with this key failed its CRC or LRC, or did not
    /// match the request: the request failed (retried if it may be).
    Corrupt(u16),
}

pub(super) enum Line {
    Mbap(Mbap),
    Serial(Serial),
}

impl Line {
    pub(super) fn new(relay: &RelayConfig, serial: &SerialConfig, now: Instant) -> Line {
        let codec = match serial.framing {
            crate::config::Framing::Mbap => {
                return Line::Mbap(Mbap {
                    tids: Tids::new(),
                    decoder: Resync::new(),
                    last_byte: now,
                    followers_until: now,
                    max_in_flight: relay.max_in_flight,
                    notifications: relay.notifications,
                    gap: Duration::from_millis(relay.frame_gap_ms),
                })
            }
            crate::config::Framing::Rtu => Codec::Rtu,
            crate::config::Framing::Ascii => Codec::Ascii,
        };
        let t35 =
            Duration::from_micros(rtu::t35_us(serial.baud_rate, serial::bits_per_char(serial)));
        Line::Serial(Serial {
            port: serial.clone(),
            decoder: Decoder::new(codec),
            t35,
            silence: t35.max(Duration::from_millis(serial.silence_floor_ms)),
            broadcast_delay: Duration::from_millis(relay.broadcast_delay_ms),
            guard: Duration::from_millis(relay.timeout_guard_ms),
            last_rx: now,
            ready_at: now,
            next_key: 0,
            echo: serial.echo.then(VecDeque::new),
            broadcast_on_wire: false,
            tx: None,
            held: Vec::new(),
            reply_from: now,
        })
    }

    /// RTU or ASCII: one at a time, broadcasts, unit backoff, drain before timing.
    pub(super) fn is_serial(&self) -> bool {
        matches!(self, Line::Serial(_))
    }

    /// A serial-side id (MBAP) or key (RTU/ASCII) for a request about to be sent.
    pub(super) fn allocate(&mut self, now: Instant) -> u16 {
        match self {
            Line::Mbap(m) => m.tids.allocate(now.into_std()),
            Line::Serial(s) => {
                s.next_key = s.next_key.wrapping_add(1);
                s.next_key
            }
        }
    }

    /// The request is finished (answered, timed out, abandoned).
    pub(super) fn retire(&mut self, tid: u16, now: Instant) {
        if let Line::Mbap(m) = self {
            m.tids.retire(tid, now.into_std());
        }
    }

    /// Is this request a broadcast: sent, no reply awaited?
    pub(super) fn is_broadcast(&self, adu: &Adu) -> bool {
        self.is_serial() && adu.unit() == 0
    }

    /// The bytes that put `adu` on the line as request `tid`, about to be written.
    pub(super) fn encode(&mut self, adu: &Adu, tid: u16, now: Instant, stats: &Stats) -> Bytes {
        match self {
            Line::Mbap(_) => adu.with_tid(tid).into_bytes(),
            Line::Serial(s) => {
                // Nothing received before a request is written can be its reply.
                let stale =
                    s.decoder.clear() + s.held.drain(..).map(|(_, b)| b.len()).sum::<usize>();
                if stale > 0 {
                    debug!(bytes = stale, "bytes received before the request discarded");
                    stats.add(&stats.dropped_bytes, stale as u64);
                }
                let bytes = s.decoder.codec().encode(adu.unit(), adu.pdu());
                if let Some(echo) = &mut s.echo {
                    // Any echo still awaited belongs to an earlier request, long done.
                    echo.clear();
                    echo.extend(&bytes);
                }
                s.broadcast_on_wire = adu.unit() == 0;
                // Written from now on: its last byte cannot leave before its time on
                // the wire has passed.
                s.tx = Some(now + serial::wire_time(&s.port, bytes.len()));
                Bytes::from(bytes)
            }
        }
    }

    /// May another request go on the line now? `in_flight` are outstanding; `busy`
    /// says bytes are still being written or drained.
    pub(super) fn has_room(&self, in_flight: usize, busy: bool, now: Instant) -> bool {
        match self {
            Line::Mbap(m) => in_flight < m.max_in_flight,
            Line::Serial(s) => in_flight == 0 && !busy && now >= s.free_at(),
        }
    }

    /// `n` bytes were handed to the port, by a write that began after `polled`.
    pub(super) fn wrote(&mut self, n: usize, polled: Instant) {
        if let Line::Serial(s) = self {
            if let Some(earliest) = &mut s.tx {
                // Held back by flow control, the last bytes leave later than a frame
                // written in one go would.
                *earliest = (*earliest).max(polled + serial::wire_time(&s.port, n));
            }
        }
    }

    /// Everything written has left the port (`tcdrain`, RTU/ASCII only). Returns the
    /// instant the last byte left: the reply timer starts there.
    ///
    /// Bytes read before the earliest instant the last byte can have left (its time
    /// on the wire after it was written) are not the reply. `tcdrain` returning is no
    /// such bound: the relay may see it late (its thread and the blocking pool's are
    /// scheduled), and a fast device's reply may be read in between; a USB adapter
    /// may report the bytes gone while its own FIFO still holds them.
    pub(super) fn drained(&mut self, now: Instant, stats: &Stats) -> Instant {
        let Line::Serial(s) = self else {
            return now;
        };
        let earliest = s.tx.take().unwrap_or(now);
        let left = now.max(earliest);
        s.reply_from = earliest;
        for (at, bytes) in std::mem::take(&mut s.held) {
            s.accept(&bytes, at, stats);
        }
        let turnaround = if std::mem::take(&mut s.broadcast_on_wire) {
            s.broadcast_delay
        } else {
            s.t35
        };
        s.ready_at = s.ready_at.max(left + turnaround);
        left
    }

    /// Bytes from the port.
    pub(super) fn received(&mut self, bytes: &[u8], now: Instant, stats: &Stats) {
        match self {
            Line::Mbap(m) => {
                m.decoder.push(bytes);
                m.last_byte = now;
            }
            Line::Serial(s) => {
                s.last_rx = now;
                let rest = s.strip_echo(bytes, stats);
                if rest.is_empty() {
                    return;
                }
                if s.tx.is_some() {
                    // The request is still on its way out: when its last byte left
                    // is not known yet, so these wait for `drained` to judge them.
                    s.held.push((now, rest.to_vec()));
                } else {
                    s.accept(rest, now, stats);
                }
            }
        }
    }

    /// The earliest instant the line needs the relay's attention, if any: the frame gap
    /// or silence that ends a partial frame, the end of the inter-frame gap when
    /// requests are waiting.
    pub(super) fn next_wake(&self, now: Instant, waiting: bool) -> Option<Instant> {
        match self {
            Line::Mbap(m) => (m.decoder.buffered() > 0).then(|| m.last_byte + m.gap),
            Line::Serial(s) => {
                let mut wake: Option<Instant> = None;
                if s.decoder.buffered() > 0 {
                    wake = Some(s.last_rx + s.silence);
                }
                if waiting {
                    let free = s.free_at();
                    wake = Some(wake.map_or(free, |w| w.min(free)));
                }
                wake.filter(|&w| w > now)
            }
        }
    }

    /// Forgets every byte received (the port was opened or lost).
    pub(super) fn clear(&mut self, stats: &Stats) {
        match self {
            Line::Mbap(m) => m.decoder.clear(),
            Line::Serial(s) => {
                stats.add(&stats.dropped_bytes, s.decoder.clear() as u64);
                if let Some(echo) = &mut s.echo {
                    echo.clear();
                }
                s.tx = None;
                s.held.clear();
                s.broadcast_on_wire = false;
            }
        }
    }

    /// A request timed out: its reply may still come (MBAP holds replies for
    /// confirmation a while). RTU/ASCII: a partial reply is discarded, and the line is
    /// left quiet for the guard time, so a reply that comes just too late is dropped
    /// rather than taken for the next request's.
    pub(super) fn timed_out(&mut self, now: Instant, stats: &Stats) {
        match self {
            Line::Mbap(m) => m.expect_followers(now),
            Line::Serial(s) => {
                let held = s.held.drain(..).map(|(_, b)| b.len()).sum::<usize>();
                stats.add(&stats.dropped_bytes, (s.decoder.clear() + held) as u64);
                // Never written in time (CTS held low): nothing of it is on its way.
                s.tx = None;
                s.ready_at = s.ready_at.max(now + s.guard);
            }
        }
    }

    /// The shortest time the line could take to serve `adu`: the request and an
    /// exception reply on the wire, each after its 3.5-character gap. Zero for MBAP.
    pub(super) fn shortest_transaction(&self, adu: &Adu) -> Duration {
        let Line::Serial(s) = self else {
            return Duration::ZERO;
        };
        let codec = s.decoder.codec();
        let bytes = codec.encoded_len(adu.pdu().len()) + codec.encoded_len(2);
        serial::wire_time(&s.port, bytes) + 2 * s.t35
    }

    /// Frames the bytes received so far make, given what is in flight.
    pub(super) fn frames(
        &mut self,
        in_flight: &[InFlight],
        now: Instant,
        stats: &Stats,
    ) -> Vec<Seen> {
        match self {
            Line::Mbap(m) => m.frames(in_flight, now, stats),
            Line::Serial(s) => s.frames(in_flight, now, stats),
        }
    }

    /// An MBAP frame that answers nothing in flight: a late reply or a notification.
    /// Another frame may follow replies for a while.
    pub(super) fn unsolicited(&mut self, tid: u16, now: Instant) -> Unsolicited {
        let Line::Mbap(m) = self else {
            return Unsolicited::Late;
        };
        m.expect_followers(now);
        if m.tids.is_retired(tid) {
            Unsolicited::Late
        } else {
            Unsolicited::Notification
        }
    }
}

pub(super) enum Unsolicited {
    Late,
    Notification,
}

// ---------------------------------------------------------------------------------------
// MBAP

pub(super) struct Mbap {
    tids: Tids,
    decoder: Resync,
    last_byte: Instant,
    /// Until then another frame may follow any reply (a late reply, a notification),
    /// so replies are held for confirmation.
    followers_until: Instant,
    max_in_flight: usize,
    notifications: Notifications,
    gap: Duration,
}

/// The relay's view of which frames on the line it can use (design.md §1 step 4, §2).
struct RelayJudge<'a> {
    in_flight: &'a [InFlight],
    tids: &'a Tids,
    /// Hold frames until what follows them confirms them (issue 4): when another frame
    /// may follow, a reply that lost a byte could complete itself with its first byte.
    strict: bool,
}

impl Judge for RelayJudge<'_> {
    fn plausible_function(&self, code: u8) -> bool {
        pdu::is_reply_function(code)
            || self
                .in_flight
                .iter()
                .any(|f| f.req.adu.function() == code & 0x7F)
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        match self.in_flight.iter().find(|f| f.tid == frame.tid()) {
            Some(f) => {
                f.req.adu.unit() == frame.unit() && pdu::reply_matches(f.req.adu.pdu(), frame.pdu())
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

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        self.strict
    }
}

impl Mbap {
    /// Can a frame other than the reply to the one request on the line arrive? Then
    /// replies wait for confirmation (issue 4). It can when several requests are on the
    /// line, when the device sends notifications, and for a while after a request timed
    /// out (its reply may still come), an unsolicited frame was seen, or the line
    /// carried garbage (noise that can land inside a reply).
    fn followers_possible(&self, in_flight: usize, now: Instant) -> bool {
        in_flight > 1
            || self.notifications == Notifications::Broadcast
            || now < self.followers_until
    }

    /// Another frame may follow replies for a while (see [`Self::followers_possible`]).
    fn expect_followers(&mut self, now: Instant) {
        self.followers_until = now + tids::RETIRED_FOR;
    }

    fn frames(&mut self, in_flight: &[InFlight], now: Instant, stats: &Stats) -> Vec<Seen> {
        let quiet = now >= self.last_byte + self.gap;
        let mut seen = Vec::new();
        loop {
            let judge = RelayJudge {
                in_flight,
                tids: &self.tids,
                strict: self.followers_possible(in_flight.len(), now),
            };
            let Some(frame) = self.decoder.next_frame(&judge, quiet) else {
                break;
            };
            seen.push(Seen::Frame(frame));
        }
        let decoded = self.decoder.stats();
        if decoded.dropped_bytes > stats.get(&stats.dropped_bytes) {
            self.expect_followers(now);
        }
        stats.set(&stats.dropped_bytes, decoded.dropped_bytes);
        stats.set(&stats.refuted_frames, decoded.refuted);
        seen
    }
}

// ---------------------------------------------------------------------------------------
// RTU and ASCII

pub(super) struct Serial {
    /// Its settings: the time bytes take on the wire.
    port: SerialConfig,
    decoder: Decoder,
    /// 3.5 character times: the gap before each request.
    t35: Duration,
    /// What ends a frame of unknown shape: 3.5 character times, never less than
    /// `silence_floor_ms`.
    silence: Duration,
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
    /// Bytes read while the frame was being written, with when they were read.
    held: Vec<(Instant, Vec<u8>)>,
    /// When the last request's last byte left: bytes read before then answer nothing.
    reply_from: Instant,
}

impl Serial {
    /// The line is free once the turnaround after our last request has passed and the
    /// device has been quiet for 3.5 character times.
    fn free_at(&self) -> Instant {
        self.ready_at.max(self.last_rx + self.t35)
    }

    /// Bytes read at `at`, once the request they follow has left: before its last byte
    /// left they cannot be its reply (an echo, a device that answers too early, a
    /// frame already on its way), and are dropped.
    fn accept(&mut self, bytes: &[u8], at: Instant, stats: &Stats) {
        if at < self.reply_from {
            debug!(
                bytes = bytes.len(),
                "bytes received while the request was still being sent discarded"
            );
            stats.add(&stats.dropped_bytes, bytes.len() as u64);
        } else {
            self.decoder.push(bytes);
        }
    }

    /// Reads back the echo of what was sent; bytes that differ from it are line noise
    /// and dropped with it.
    fn strip_echo<'a>(&mut self, bytes: &'a [u8], stats: &Stats) -> &'a [u8] {
        let Some(echo) = &mut self.echo else {
            return bytes;
        };
        let n = bytes.len().min(echo.len());
        if echo.iter().take(n).eq(bytes[..n].iter()) {
            echo.drain(..n);
            return &bytes[n..];
        }
        debug!(
            expected = echo.len(),
            "the echo of the request differs from what was sent: dropped as noise"
        );
        echo.clear();
        stats.add(&stats.dropped_bytes, bytes.len() as u64);
        &[]
    }

    fn frames(&mut self, in_flight: &[InFlight], now: Instant, stats: &Stats) -> Vec<Seen> {
        let quiet = now >= self.last_rx + self.silence;
        let Some(f) = in_flight.first() else {
            // Nothing asked: late answers or noise, dropped once the line is quiet.
            if quiet && self.decoder.buffered() > 0 {
                let n = self.decoder.clear();
                debug!(bytes = n, "bytes that answer no request dropped");
                stats.add(&stats.dropped_bytes, n as u64);
            }
            return Vec::new();
        };
        let request = f.req.adu.pdu();
        let mut next = self.decoder.next(Expect::Reply(request), quiet);
        while let Some(Decoded::Noise(n)) = next {
            stats.add(&stats.dropped_bytes, n as u64);
            next = self.decoder.next(Expect::Reply(request), quiet);
        }
        match next {
            None | Some(Decoded::Noise(_)) => Vec::new(),
            Some(Decoded::Frame { unit, pdu }) => {
                if unit == f.req.adu.unit() {
                    // The CRC or LRC proves these are the unit's own bytes: a reply of
                    // another shape than the request's goes to the master unchanged, to
                    // judge, as a transparent gateway passes it.
                    if !pdu::reply_matches(request, &pdu) {
                        debug!(
                            unit,
                            "a reply of another shape than its request's, passed on"
                        );
                    }
                    vec![Seen::Frame(Adu::build(f.tid, unit, &pdu))]
                } else {
                    debug!(unit, "a frame that does not answer the request on the line");
                    stats.add(&stats.bad_frames, 1);
                    vec![Seen::Corrupt(f.tid)]
                }
            }
            Some(Decoded::Corrupt(n)) => {
                debug!(bytes = n, "a reply whose check failed");
                stats.add(&stats.bad_frames, 1);
                stats.add(&stats.dropped_bytes, n as u64);
                vec![Seen::Corrupt(f.tid)]
            }
        }
    }
}
