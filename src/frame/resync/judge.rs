//! What a frame on the line may be, as the MBAP decoder asks it: the [`Judge`] the
//! relay implements with what it knows of the requests in flight, and the stock
//! judges: any reply ([`ReplyJudge`]), any request ([`RequestJudge`]), and another
//! judge with every frame held for confirmation ([`Confirmed`]).

use crate::frame::function::FunctionCode;
use crate::frame::mbap::FrameRef;
use crate::frame::pdu;
use crate::frame::serial::Expect;

/// Decides what a frame on the line may be. The relay's judge knows the outstanding
/// requests; [`ReplyJudge`] knows only what any reply must look like.
pub trait Judge {
    /// Could a frame with this function code be on the line at all?
    fn plausible_function(&self, code: FunctionCode) -> bool;
    /// Is this complete, length-consistent candidate a frame to hand on?
    fn accept(&self, frame: FrameRef<'_>) -> bool;
    /// Must this accepted frame wait for confirmation by what follows it, or by a quiet
    /// line? Judges that know nothing can follow (one request outstanding, no
    /// unsolicited frames) say no and get frames without the wait.
    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        false
    }
    /// For a frame [`confirm`](Judge::confirm) would hold, with nothing buffered after
    /// it: may it be handed on at once? Judges that know nothing can follow it on the
    /// line say yes (the relay with one request in flight and nothing else to come,
    /// docs/reliability.md): a frame that lost bytes then has nothing to complete
    /// itself with. `straddles` says the line paused inside it: on a wire what came
    /// after a pause may be noise completing a frame that lost bytes, and a judge
    /// then says no. Bytes already after it show something did come: it is held as
    /// ever.
    fn alone(&self, _frame: FrameRef<'_>, _straddles: bool) -> bool {
        false
    }
    /// May a pause (`Resync::pause`) confirm this held frame when nothing follows
    /// it, or must the line be quiet for the whole frame gap? Judges that expect
    /// another frame soon (other replies due) say no: a pause inside that next frame,
    /// right after a byte this frame borrowed, must not pass for the end of the talk.
    fn pause_confirms(&self, _frame: FrameRef<'_>) -> bool {
        true
    }
    /// Is this complete candidate, which [`accept`](Judge::accept) refused, still to
    /// be handed on once confirmed like a held frame (the relay: the id and unit of a
    /// request in flight, the shape of no reply to it)? Refuted, or left unconfirmed,
    /// it is rescanned byte by byte as any refused candidate is, so a frame shifted by
    /// lost bytes is still found inside it.
    fn deliver_refused(&self, _frame: FrameRef<'_>) -> bool {
        false
    }
    /// When a held frame this judge accepted is refuted, look inside it for the next
    /// frame (the first plausible start that runs past its end) instead of dropping
    /// it whole? A frame that lost bytes borrowed the first bytes of the one behind
    /// it, which then starts inside it. Requests say yes (a serial master's intact
    /// request right behind a damaged one is recovered); replies no (a reply found
    /// that way could be a shifted copy of the next with another id,
    /// docs/reliability.md).
    fn resume_inside_refuted(&self) -> bool {
        false
    }
    /// On an RTU or ASCII line ([`crate::frame::framer::Framer`]), what the frame at the front
    /// must be: the reply to a request (whose shape gives the reply's length), or any
    /// request. Any reply, unless the judge knows the request.
    fn expect(&self) -> Expect<'_> {
        Expect::Reply(&[])
    }
}

/// Accepts any well-formed reply to a public function code (docs/design.md §2 shape check).
#[derive(Debug, Default, Clone, Copy)]
pub struct ReplyJudge;

impl Judge for ReplyJudge {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.is_reply()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        pdu::reply_well_formed(frame.pdu())
    }
}

/// Accepts any self-consistent request (the simulator's side of the line): a function
/// code without the exception bit and the size it calls for ([`pdu::request_well_formed`]).
/// With `confirm`, requests wait for what follows them or a quiet line, for a device
/// that takes requests back to back.
#[derive(Debug, Default, Clone, Copy)]
pub struct RequestJudge {
    pub(crate) confirm: bool,
}

impl Judge for RequestJudge {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        code.can_be_request()
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        pdu::request_well_formed(frame.pdu())
    }

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        self.confirm
    }

    fn resume_inside_refuted(&self) -> bool {
        true
    }

    fn expect(&self) -> Expect<'_> {
        Expect::Request
    }
}

/// Another judge's decisions, with every frame held for confirmation.
#[derive(Debug, Default, Clone, Copy)]
pub struct Confirmed<J>(pub J);

impl<J: Judge> Judge for Confirmed<J> {
    fn plausible_function(&self, code: FunctionCode) -> bool {
        self.0.plausible_function(code)
    }

    fn accept(&self, frame: FrameRef<'_>) -> bool {
        self.0.accept(frame)
    }

    fn confirm(&self, _frame: FrameRef<'_>) -> bool {
        true
    }

    fn pause_confirms(&self, frame: FrameRef<'_>) -> bool {
        self.0.pause_confirms(frame)
    }

    fn expect(&self) -> Expect<'_> {
        self.0.expect()
    }
}
