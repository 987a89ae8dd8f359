//! Which frames on an MBAP line the relay can use (docs/design.md §1 step 4, §2;
//! docs/reliability.md): the [`Judge`] the resynchronising decoder asks, from the
//! requests in flight, and whether anything can follow a reply ([`may_follow`]). The
//! policy; the line that keeps the state it reads is `mbap.rs`.

use crate::frame::mbap::FrameRef;
use crate::frame::{pdu, FunctionCode, Judge};
use crate::line::relay::inflight::{Asked, OnLine};
use crate::line::relay::tids::Tids;
use tokio::time::Instant;

/// The relay's view of which frames on the line it can use (docs/design.md §1 step 4,
/// §2).
pub(super) struct RelayJudge<'a, R> {
    pub(super) in_flight: &'a [OnLine<R>],
    pub(super) tids: &'a Tids,
    pub(super) now: Instant,
    pub(super) stream: bool,
    /// Nothing but the replies to the requests in flight can come on the line: the
    /// device sends nothing unasked and no late reply is possible.
    pub(super) only_replies: bool,
    /// There is a wire (and so noise) between the port and the device.
    pub(super) wire: bool,
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
        let due = |f: &OnLine<R>| f.deadline > self.now;
        let own_expired = self.in_flight.iter().any(|f| f.tid == tid && !due(f));
        own_expired || !self.in_flight.iter().any(|f| f.tid != tid && due(f))
    }
}
