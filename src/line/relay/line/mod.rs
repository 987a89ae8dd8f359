//! The framing seam of the relay: what differs between a line of MBAP frames (the
//! CIE-M10) and a line of RTU or ASCII frames, behind one [`LineFraming`] the loop drives.
//! Everything else (queues, round-robin, timeouts, retries, unit backoff, 0x0A/0x0B,
//! the shutdown drain) is the relay's and shared.
//!
//! - [`Mbap`] (`mbap.rs`): serial-side transaction ids, several requests on the line
//!   at once (`max_in_flight`), the resynchronising decoder with confirmation of every
//!   frame something can follow (by what follows it, or by a pause of a few character
//!   times), notifications, echoes told by their timing on a wire.
//! - [`Serial`] (`serial.rs`): RTU or ASCII. No transaction id, so one request at a
//!   time, and only time ties a reply to its request: what was received before a
//!   request was written is discarded, and on a wire a reply must start after the
//!   request has left; frames delimited by
//!   length, silence or line feed and checked by CRC or LRC; the inter-frame gap (3.5
//!   character times) before each request, counted from the last byte seen or sent; a
//!   guard time after a timeout, for the late reply; broadcasts (unit 0) with a
//!   turnaround delay; local-echo suppression.

mod mbap;
mod serial;

use super::inflight::{Asked, OnLine};
use crate::config::{Framing, RelayConfig, SerialConfig};
use crate::frame::serial::Codec;
use crate::frame::{Adu, FunctionCode};
use crate::line::port::kind::PortInfo;
use crate::ops::capture::dropped::Dropped;
use crate::ops::stats::Stats;
use mbap::MbapLine;
use serial::Serial;
use std::time::Duration;
use tokio::time::Instant;

/// What the line made of the bytes it received.
pub(super) enum Seen {
    /// A frame; its transaction id is the serial-side one (for RTU/ASCII, the key of
    /// the request it answers, which it has been checked against); and when its last
    /// byte was read.
    Frame(Adu, Instant),
    /// The answer to the request with this key (RTU/ASCII) or id (MBAP) failed its
    /// CRC or LRC, or did not match the request: the request failed (retried if it may
    /// be). MBAP: a confirmed frame with the request's id and unit whose shape fits no
    /// reply to it. RTU/ASCII: also a reply followed within its quiet by another frame.
    Corrupt(u16),
    /// RTU/ASCII: a frame of this unit paid an answer it owed (a request that timed
    /// out): the unit is alive, though the frame answers nothing on the line now.
    Heard(u8),
}

/// An MBAP frame that answers nothing in flight.
pub(super) enum Unsolicited {
    /// The answer to a request already answered or timed out (a retired id).
    Late,
    /// A device notification (id 0, or an id never used).
    Notification,
}

/// The line's framing, one of two, as the relay's loop drives it.
pub(super) struct LineFraming(FramingState);

/// What one framing keeps: MBAP's ids, decoder and timing, or RTU/ASCII's.
enum FramingState {
    Mbap(MbapLine),
    Serial(Serial),
}

impl LineFraming {
    /// The framing of `serial`; `stream` says the bytes go over TCP, where none is
    /// lost and none takes time on a wire: no inter-frame gap, no echo timing, and an
    /// MBAP frame is taken as soon as it is whole, without waiting for confirmation.
    pub(super) fn new(
        relay: &RelayConfig,
        serial: &SerialConfig,
        stream: bool,
        now: Instant,
    ) -> LineFraming {
        let codec = match serial.framing {
            Framing::Mbap => {
                return LineFraming(FramingState::Mbap(MbapLine::new(
                    relay, serial, stream, now,
                )))
            }
            Framing::Rtu => Codec::Rtu,
            Framing::Ascii => Codec::Ascii,
        };
        LineFraming(FramingState::Serial(Serial::new(
            relay, serial, codec, stream, now,
        )))
    }

    /// The port was opened and found to be `info` (docs/reliability.md "Knowing the
    /// wire"): the line takes its timing from it. Says how, for the log.
    pub(super) fn port_opened(&mut self, info: &PortInfo) -> String {
        match &mut self.0 {
            FramingState::Mbap(m) => m.port_opened(info),
            FramingState::Serial(s) => s.port_opened(info),
        }
    }

    /// `n` bytes were read with `in_flight` requests on the line (MBAP: with none, and
    /// no late reply possible, the device talked unasked).
    pub(super) fn heard(&mut self, n: usize, in_flight: usize, now: Instant, stats: &Stats) {
        if let FramingState::Mbap(m) = &mut self.0 {
            m.heard(n, in_flight, now, stats);
        }
    }

    /// A whole MBAP frame that answers nothing in flight came (`late`: a retired id).
    pub(super) fn answered_nothing(&mut self, late: bool, now: Instant) {
        if let FramingState::Mbap(m) = &mut self.0 {
            m.answered_nothing(late, now);
        }
    }

    /// RTU or ASCII: one at a time, broadcasts, unit backoff, drain before timing.
    pub(super) fn is_serial(&self) -> bool {
        matches!(self.0, FramingState::Serial(_))
    }

    /// A serial-side id (MBAP) or key (RTU/ASCII) for a request about to be sent.
    pub(super) fn allocate(&mut self, now: Instant) -> u16 {
        match &mut self.0 {
            FramingState::Mbap(m) => m.allocate(now),
            FramingState::Serial(s) => s.allocate(),
        }
    }

    /// The request is finished (answered, timed out, abandoned).
    pub(super) fn retire(&mut self, tid: u16, now: Instant) {
        if let FramingState::Mbap(m) = &mut self.0 {
            m.retire(tid, now);
        }
    }

    /// Is this request a broadcast: sent, no reply awaited?
    pub(super) fn is_broadcast(&self, adu: &Adu) -> bool {
        self.is_serial() && adu.unit() == 0
    }

    /// Would this request be a broadcast that cannot be one (a read, anything but a
    /// write: `FunctionCode::may_broadcast`)? No device would answer it, so it never
    /// goes on the line.
    pub(super) fn not_broadcast(&self, adu: &Adu) -> bool {
        self.is_broadcast(adu) && !FunctionCode::new(adu.function()).may_broadcast()
    }

    /// The quiet time after the request about to be sent (its unit's
    /// `request_pause_ms`): after its reply or its timeout, before the next request.
    pub(super) fn pause_after(&mut self, pause: Duration) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.request_pause = pause,
            FramingState::Serial(s) => s.request_pause = pause,
        }
    }

    /// Appends to `out` the bytes that put `adu` on the line as request `tid`, about
    /// to be written.
    pub(super) fn encode_into(
        &mut self,
        adu: &Adu,
        tid: u16,
        now: Instant,
        stats: &Stats,
        out: &mut Vec<u8>,
    ) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.encode(adu, tid, now, out),
            FramingState::Serial(s) => s.encode(adu, now, stats, out),
        }
    }

    /// [`LineFraming::encode_into`], the bytes on their own.
    #[cfg(test)]
    pub(super) fn encode(
        &mut self,
        adu: &Adu,
        tid: u16,
        now: Instant,
        stats: &Stats,
    ) -> bytes::Bytes {
        let mut out = Vec::new();
        self.encode_into(adu, tid, now, stats, &mut out);
        bytes::Bytes::from(out)
    }

    /// May another request go on the line now? `in_flight` are outstanding; `busy`
    /// says bytes are still being written or drained.
    pub(super) fn has_room(&self, in_flight: usize, busy: bool, now: Instant) -> bool {
        match &self.0 {
            FramingState::Mbap(m) => m.has_room(in_flight, now),
            FramingState::Serial(s) => s.has_room(in_flight, busy, now),
        }
    }

    /// `n` bytes were handed to the port, by a write that began after `polled` and
    /// returned before `now`. RTU and ASCII count the earliest the bytes can leave
    /// from `polled` (nothing read before then is a reply); MBAP counts when a request
    /// has left from `now`, so that a late-run write never lets its echo pass.
    pub(super) fn wrote(&mut self, n: usize, polled: Instant, now: Instant) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.wrote(n, now),
            FramingState::Serial(s) => s.wrote(n, polled),
        }
    }

    /// RTU/ASCII, while a frame is being written or drained: the earliest its last
    /// stop bit can leave (its time on the wire after it was written).
    pub(super) fn leaves_at(&self) -> Option<Instant> {
        match &self.0 {
            FramingState::Mbap(_) => None,
            FramingState::Serial(s) => s.leaves_at(),
        }
    }

    /// RTU/ASCII: `n` bytes whose write returned at `written` cannot all have left
    /// before their time on the wire after it.
    pub(super) fn left_after(&self, n: usize, written: Instant) -> Option<Instant> {
        match &self.0 {
            FramingState::Mbap(_) => None,
            FramingState::Serial(s) => Some(written + s.wire_time(n)),
        }
    }

    /// Must the relay wait for `tcdrain` before it times the reply (RTU/ASCII on a
    /// wire whose port can hold the request back: `Serial::holds_bytes_back`)? Where
    /// there is no wire (a pty: docs/reliability.md "Knowing the wire") the bytes are
    /// gone once written, and on a plain wire they are gone their time on the wire
    /// after it; asking the drain thread would cost two thread hand-offs a
    /// transaction for nothing.
    pub(super) fn needs_drain(&self) -> bool {
        match &self.0 {
            FramingState::Mbap(_) => false,
            FramingState::Serial(s) => s.has_wire() && s.holds_bytes_back(),
        }
    }

    /// Everything written has left the port (`tcdrain`, RTU/ASCII only). Returns the
    /// instant the last byte left: the reply timer starts there.
    pub(super) fn drained(&mut self, now: Instant, stats: &Stats) -> Instant {
        match &mut self.0 {
            FramingState::Mbap(_) => now,
            FramingState::Serial(s) => s.drained(now, stats),
        }
    }

    /// Bytes from the port.
    pub(super) fn received(&mut self, bytes: &[u8], now: Instant, stats: &Stats) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.received(bytes, now),
            FramingState::Serial(s) => s.received(bytes, now, stats),
        }
    }

    /// The earliest instant the line needs the relay's attention, if any: the frame gap
    /// or silence that ends a partial frame, the end of the inter-frame gap when
    /// requests are waiting.
    pub(super) fn next_wake(&self, now: Instant, waiting: bool) -> Option<Instant> {
        match &self.0 {
            FramingState::Mbap(m) => m.next_wake(now, waiting),
            FramingState::Serial(s) => s.next_wake(now, waiting),
        }
    }

    /// Forgets every byte received (the port was opened or lost).
    pub(super) fn clear(&mut self, stats: &Stats) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.clear(),
            FramingState::Serial(s) => s.clear(stats),
        }
    }

    /// A request timed out: its reply may still come (MBAP recognises it by its id, and
    /// holds replies for confirmation for the guard time, as the late one may follow).
    /// RTU/ASCII: a partial reply is discarded, and the line is left quiet for `hold`
    /// (a learned timeout's way to its ceiling) and the guard time after it, so a
    /// reply that comes just too late is dropped rather than taken for the next
    /// request's.
    pub(super) fn timed_out(&mut self, now: Instant, hold: Duration, stats: &Stats) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.timed_out(now),
            FramingState::Serial(s) => s.timed_out(now, hold, stats),
        }
    }

    /// A request to `unit` that left at `left` got no answer in time: the device may
    /// hold it and answer it later. RTU/ASCII: the unit owes that answer, and none of
    /// its frames answers the request on the line until it has paid what it owes or
    /// been quiet for `whole`, its whole response timeout, after a frame (MBAP knows
    /// a late answer by its id).
    pub(super) fn unanswered(&mut self, unit: u8, left: Instant, whole: Duration, now: Instant) {
        if let FramingState::Serial(s) = &mut self.0 {
            s.unanswered(unit, left, whole, now);
        }
    }

    /// RTU/ASCII: the reply held until the line has been quiet after it, as the key
    /// of its request and the instant that quiet ends. The request stays on the line
    /// until then, past its deadline if need be.
    pub(super) fn confirming(&self) -> Option<(u16, Instant)> {
        match &self.0 {
            FramingState::Mbap(_) => None,
            FramingState::Serial(s) => s.confirming(),
        }
    }

    /// The shortest time the line could take to serve `adu`: the request and an
    /// exception reply on the wire, each after its 3.5-character gap. Zero for MBAP.
    pub(super) fn shortest_transaction(&self, adu: &Adu) -> Duration {
        match &self.0 {
            FramingState::Mbap(_) => Duration::ZERO,
            FramingState::Serial(s) => s.shortest_transaction(adu),
        }
    }

    /// The frames in the bytes received so far, for the tests.
    #[cfg(test)]
    pub(super) fn frames<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
    ) -> Vec<Seen> {
        let mut seen = Vec::new();
        self.frames_into(in_flight, now, stats, &mut seen);
        seen
    }

    /// Frames the bytes received so far make, given what is in flight, pushed onto
    /// `seen`: the relay's own vector, kept from turn to turn, so that a reply costs
    /// no allocation for the list it comes in.
    /// May [`LineFraming::frames_into`] find anything without new bytes? MBAP: only
    /// while its decoder holds bytes (a frame a pause or what follows it confirms, a
    /// partial frame the gap ends); RTU/ASCII always look (a reply held for
    /// confirmation, the request judged against).
    pub(super) fn may_frame(&self) -> bool {
        match &self.0 {
            FramingState::Mbap(m) => m.buffered() > 0,
            FramingState::Serial(_) => true,
        }
    }

    pub(super) fn frames_into<R: Asked>(
        &mut self,
        in_flight: &[OnLine<R>],
        now: Instant,
        stats: &Stats,
        seen: &mut Vec<Seen>,
    ) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.frames_into(in_flight, now, stats, seen),
            FramingState::Serial(s) => s.frames_into(in_flight, now, stats, seen),
        }
    }

    /// `frame` as it was on the wire (its CRC or LRC was checked), for the traffic log.
    pub(super) fn on_wire<'a>(&self, frame: &'a Adu) -> std::borrow::Cow<'a, [u8]> {
        match &self.0 {
            FramingState::Mbap(_) => std::borrow::Cow::Borrowed(frame.as_bytes()),
            FramingState::Serial(s) => std::borrow::Cow::Owned(s.on_wire(frame)),
        }
    }

    /// Keep the bytes the line drops, for the capture (docs/capture.md), or not.
    pub(super) fn set_tape(&mut self, on: bool) {
        match &mut self.0 {
            FramingState::Mbap(m) => m.tape.set(on),
            FramingState::Serial(s) => s.tape.set(on),
        }
    }

    /// The bytes the line dropped since the last call, with why (while the tape is
    /// on).
    pub(super) fn take_drops(&mut self) -> Vec<Dropped> {
        match &mut self.0 {
            FramingState::Mbap(m) => m.tape.take(),
            FramingState::Serial(s) => s.tape.take(),
        }
    }

    /// An MBAP frame that answers nothing in flight: a late reply or a notification.
    pub(super) fn unsolicited(&self, tid: u16) -> Unsolicited {
        match &self.0 {
            FramingState::Mbap(m) => m.unsolicited(tid),
            FramingState::Serial(_) => Unsolicited::Late,
        }
    }
}
