//! A Modbus/UDP source's loop guards (docs/dialing.md "Modbus over UDP"), and a dialed
//! connection's: the last frame it was sent that reads as a request (a write's reply repeats the write), so that the
//! very same bytes coming back from it at once are known for that frame reflected, not a
//! request; its budget of exception replies; and when it last asked, for its
//! notifications. [`Loops`] is plain data with the time passed in; [`Guard`] holds it
//! for the source's writer and the listener's receive loop, locked only for a frame that
//! reads as a request or is an exception, and only while such a frame is remembered.

use crate::frame::mbap::HEADER_LEN;
use crate::frame::pdu::request_well_formed;
use crate::frame::FunctionCode;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;
use tokio::time::Instant;

/// The least time a frame sent to a source that reads as a request is remembered: a
/// server that answers it (another gateway, pymodbus' `ModbusUdpServer`) does so within
/// a round trip and its own answer's time, far less on a network where a master's
/// retry comes after its timeout (1 s or more for the masters of docs/dialing.md).
pub(crate) const REFLECT_MIN: Duration = Duration::from_secs(1);

/// The exception replies a source may get at once ([`EXCEPTION_EVERY`] gives one back).
pub(crate) const EXCEPTIONS_BURST: u32 = 10;

/// One exception reply more a source may get, this long after the last: 10 a second. A
/// UDP master waits for each answer (pymodbus, a SCADA polling its list); more than
/// that many exceptions a second to one source is a loop through some peer that answers
/// exceptions with requests, or a flood, and each is cheap to provoke (a unit no line
/// serves is answered 0x0A at once, without a device).
pub(crate) const EXCEPTION_EVERY: Duration = Duration::from_millis(100);

/// What a source was last sent that could come back as a request, and its exception
/// budget.
#[derive(Debug)]
pub(crate) struct Loops {
    /// The last frame sent, if it reads as a request, and when.
    echo: Vec<u8>,
    echo_at: Option<Instant>,
    /// Exceptions it may still get now, and when the budget was last topped up.
    tokens: u32,
    refilled: Instant,
}

impl Loops {
    pub(crate) fn new(now: Instant) -> Loops {
        Loops {
            echo: Vec::new(),
            echo_at: None,
            tokens: EXCEPTIONS_BURST,
            refilled: now,
        }
    }

    /// How long a frame sent at `sent`, answering a request that came at `asked`, is
    /// remembered: [`REFLECT_MIN`], or twice the time the gateway took to answer if
    /// longer. Two gateways in a loop each take their own time to answer the other's
    /// frame; for the loop to go on, each must take more than twice the other's time,
    /// which cannot hold both ways: one of them knows its frame come back.
    pub(crate) fn window(sent: Instant, asked: Instant) -> Duration {
        REFLECT_MIN.max(2 * sent.saturating_duration_since(asked))
    }

    /// `frame` (a whole MBAP ADU) is being sent to the source at `now`: remembered if it
    /// reads as a request, else the last one is forgotten (it is no longer the frame
    /// just sent). `false`: it is an exception past the budget, not to be sent.
    pub(crate) fn sent(&mut self, frame: &[u8], now: Instant) -> bool {
        match kind(frame) {
            Kind::Exception => {
                self.echo_at = None;
                self.take_token(now)
            }
            Kind::Answer => {
                self.echo_at = None;
                true
            }
            Kind::Request => {
                self.echo.clear();
                self.echo.extend_from_slice(frame);
                self.echo_at = Some(now);
                true
            }
        }
    }

    /// `frame` (as the peer reads it; `pdu` its PDU) was just written on a dialed
    /// connection at `now`: remembered if it reads as a request (a write's reply), else
    /// the last one forgotten. No budget: a dial's exceptions go to the one server.
    pub(crate) fn remember(&mut self, frame: &[u8], pdu: &[u8], now: Instant) {
        if request_well_formed(pdu) {
            self.echo.clear();
            self.echo.extend_from_slice(frame);
            self.echo_at = Some(now);
        } else {
            self.echo_at = None;
        }
    }

    /// Is `frame`, come on a dialed connection at `now`, the very frame last written
    /// there, within [`REFLECT_MIN`]? (A server that echoes every byte sends a write's
    /// reply straight back, and it reads as the write again.)
    pub(crate) fn came_back(&self, frame: &[u8], now: Instant) -> bool {
        self.echo_at
            .is_some_and(|at| now.saturating_duration_since(at) < REFLECT_MIN)
            && frame == self.echo
    }

    /// Is `datagram`, come at `now` from a source whose last request came at `asked`,
    /// the frame it was last sent, within its window?
    pub(crate) fn reflected(&self, datagram: &[u8], asked: Instant, now: Instant) -> bool {
        self.remembering(asked, now) && datagram == self.echo
    }

    /// Is a frame sent still remembered at `now` (the source may yet send it back)?
    pub(crate) fn remembering(&self, asked: Instant, now: Instant) -> bool {
        self.echo_at
            .is_some_and(|at| now.saturating_duration_since(at) < Self::window(at, asked))
    }

    fn take_token(&mut self, now: Instant) -> bool {
        let gained =
            now.saturating_duration_since(self.refilled).as_nanos() / EXCEPTION_EVERY.as_nanos();
        if gained > 0 {
            let tokens = u128::from(self.tokens) + gained;
            if tokens >= u128::from(EXCEPTIONS_BURST) {
                self.tokens = EXCEPTIONS_BURST;
                self.refilled = now;
            } else {
                // Fewer than the burst: `gained` is small.
                self.tokens = tokens as u32;
                self.refilled += EXCEPTION_EVERY * gained as u32;
            }
        }
        if self.tokens == 0 {
            return false;
        }
        self.tokens -= 1;
        true
    }
}

/// What a frame about to go to a source is, for its guards.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// An exception reply.
    Exception,
    /// A reply without a request's shape (a read's, a long write's): sent back, it is
    /// dropped as a reply, or answered once with an exception, which is dropped in
    /// turn.
    Answer,
    /// A reply with a request's shape too (a write that repeats its request).
    Request,
}

fn kind(frame: &[u8]) -> Kind {
    let pdu = frame.get(HEADER_LEN..).unwrap_or_default();
    if pdu
        .first()
        .is_some_and(|&c| FunctionCode::new(c).is_exception())
    {
        Kind::Exception
    } else if request_well_formed(pdu) {
        Kind::Request
    } else {
        Kind::Answer
    }
}

/// A source's [`Loops`], shared by its writer and the listener's receive loop, and when
/// it last asked.
#[derive(Debug)]
pub(crate) struct Guard {
    /// A frame that reads as a request is remembered: only then is the lock taken for
    /// a datagram from the source.
    remembered: AtomicBool,
    loops: Mutex<Loops>,
    born: Instant,
    /// When the source's last request came, in nanoseconds from `born`.
    asked: AtomicU64,
}

impl Guard {
    pub(crate) fn new(now: Instant) -> Guard {
        Guard {
            remembered: AtomicBool::new(false),
            loops: Mutex::new(Loops::new(now)),
            born: now,
            asked: AtomicU64::new(0),
        }
    }

    /// `frame` is about to be sent to the source (a reply, or a notification):
    /// `false`, it is an exception past the source's budget and is not sent. Nearly
    /// every reply (a read's) neither locks nor reads the clock.
    pub(crate) fn sent(&self, frame: &[u8]) -> bool {
        if kind(frame) == Kind::Answer {
            if self.remembered.load(Ordering::Relaxed) {
                self.remembered.store(false, Ordering::Relaxed);
                self.lock().echo_at = None;
            }
            return true;
        }
        let mut loops = self.lock();
        let send = loops.sent(frame, Instant::now());
        self.remembered
            .store(loops.echo_at.is_some(), Ordering::Relaxed);
        send
    }

    /// Is `datagram`, come now from the source whose last request came at `asked`, the
    /// frame it was just sent?
    pub(crate) fn reflected(&self, datagram: &[u8], asked: Instant) -> bool {
        self.remembered.load(Ordering::Relaxed)
            && self.lock().reflected(datagram, asked, Instant::now())
    }

    /// May the source still send back a frame it was sent, at `now`?
    pub(crate) fn remembering(&self, asked: Instant, now: Instant) -> bool {
        self.remembered.load(Ordering::Relaxed) && self.lock().remembering(asked, now)
    }

    /// The source's request came at `at`.
    pub(crate) fn asked(&self, at: Instant) {
        let ns = at.saturating_duration_since(self.born).as_nanos();
        self.asked
            .store(u64::try_from(ns).unwrap_or(u64::MAX), Ordering::Relaxed);
    }

    /// Did the source's last request come within `within` of `now`?
    pub(crate) fn asked_within(&self, now: Instant, within: Duration) -> bool {
        let at = self.born + Duration::from_nanos(self.asked.load(Ordering::Relaxed));
        now.saturating_duration_since(at) <= within
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Loops> {
        self.loops.lock().expect("not poisoned")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn adu(pdu: &[u8]) -> Vec<u8> {
        crate::frame::Adu::build(7, 1, pdu).as_bytes().to_vec()
    }

    /// A write's reply, which repeats the write, is known come back within its window
    /// and only then; a read's reply or an exception sent after it forgets it.
    #[test]
    fn a_frame_that_reads_as_a_request_is_known_when_it_comes_back() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let write = adu(&[6, 0, 1, 0, 3]);
        let mut l = Loops::new(t0);
        assert!(l.sent(&write, t0 + ms(5)));
        assert!(l.reflected(&write, t0, t0 + ms(10)));
        assert!(l.reflected(&write, t0, t0 + ms(1004)));
        assert!(!l.reflected(&write, t0, t0 + ms(1005)), "past the window");
        assert!(!l.reflected(&adu(&[6, 0, 1, 0, 4]), t0, t0 + ms(10)));
        // Answered after 800 ms: remembered for 1.6 s.
        assert!(l.sent(&write, t0 + ms(800)));
        assert!(l.reflected(&write, t0, t0 + ms(2399)));
        assert!(!l.reflected(&write, t0, t0 + ms(2400)));
        // A read's reply sent since: the write's is not the frame just sent.
        assert!(l.sent(&write, t0 + ms(10)));
        assert!(l.sent(&adu(&[3, 2, 0, 9]), t0 + ms(20)));
        assert!(!l.reflected(&write, t0, t0 + ms(30)));
        assert!(l.sent(&write, t0 + ms(40)));
        assert!(l.sent(&adu(&[0x86, 2]), t0 + ms(50)));
        assert!(!l.reflected(&write, t0, t0 + ms(60)));
        assert!(!l.remembering(t0, t0 + ms(60)));
    }

    /// A dialed server that echoes a write's reply: the echo is known for it within
    /// the window, and only the frame last written.
    #[test]
    fn a_dials_write_reply_echoed_is_known() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let write = adu(&[6, 0, 1, 0, 3]);
        let mut l = Loops::new(t0);
        l.remember(&write, &write[HEADER_LEN..], t0);
        assert!(l.came_back(&write, t0 + ms(5)));
        assert!(!l.came_back(&write, t0 + REFLECT_MIN), "past the window");
        assert!(!l.came_back(&adu(&[6, 0, 1, 0, 4]), t0 + ms(5)));
        // A read's reply written since: the write's is forgotten.
        let read = adu(&[3, 2, 0, 9]);
        l.remember(&read, &read[HEADER_LEN..], t0 + ms(6));
        assert!(!l.came_back(&write, t0 + ms(7)));
        assert!(!l.came_back(&read, t0 + ms(7)));
    }

    /// Two gateways answering each other's frame: the frame comes back to one of them
    /// within its window, whatever their times, unless each took more than twice the
    /// other's (which cannot be).
    #[test]
    fn of_two_peers_in_a_loop_one_knows_its_frame() {
        let ms = Duration::from_millis;
        for (a, b) in [
            (1, 1),
            (5, 900),
            (900, 5),
            (700, 1300),
            (3000, 2000),
            (400, 2500),
        ] {
            let t0 = Instant::now();
            // A answers the forged request after `a`; B answers A's frame after `b`;
            // A answers that after `a` again, and B after `b`.
            let a_sent = t0 + ms(a);
            let b_sent = a_sent + ms(b);
            let a_knows = b_sent.duration_since(a_sent) < Loops::window(a_sent, t0);
            let a_again = b_sent + ms(a);
            let b_knows = a_again.duration_since(b_sent) < Loops::window(b_sent, a_sent);
            assert!(a_knows || b_knows, "{a} ms and {b} ms");
        }
    }

    /// Ten exceptions at once, then one every 100 ms; a quiet source has its ten back.
    #[test]
    fn exceptions_have_a_budget() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let e = adu(&[0x83, 0x0A]);
        let mut l = Loops::new(t0);
        let sent = (0..50).filter(|_| l.sent(&e, t0)).count();
        assert_eq!(sent, EXCEPTIONS_BURST as usize);
        assert!(!l.sent(&e, t0 + ms(99)));
        assert!(l.sent(&e, t0 + ms(100)));
        assert!(!l.sent(&e, t0 + ms(150)));
        assert!(l.sent(&e, t0 + ms(200)));
        // 1 s over a minute: 10 more, then 1 a tenth of a second.
        let mut now = t0 + ms(200);
        let mut total = 0;
        for _ in 0..600 {
            now += ms(100);
            total += (0..5).filter(|_| l.sent(&e, now)).count();
        }
        assert_eq!(total, 600);
        let later = now + Duration::from_secs(60);
        assert_eq!((0..50).filter(|_| l.sent(&e, later)).count(), 10);
        // Replies that are no exception are never held back.
        assert!((0..100).all(|_| l.sent(&adu(&[3, 2, 0, 1]), later)));
    }

    #[test]
    fn the_guard_remembers_only_what_reads_as_a_request() {
        let t0 = Instant::now();
        let g = Guard::new(t0);
        let write = adu(&[6, 0, 1, 0, 3]);
        assert!(g.sent(&adu(&[3, 2, 0, 9])));
        assert!(!g.reflected(&adu(&[3, 2, 0, 9]), t0));
        assert!(g.sent(&write));
        assert!(g.reflected(&write, t0));
        assert!(g.remembering(t0, Instant::now()));
        g.asked(t0 + Duration::from_millis(500));
        assert!(g.asked_within(t0 + Duration::from_millis(1500), Duration::from_secs(1)));
        assert!(!g.asked_within(t0 + Duration::from_millis(1501), Duration::from_secs(1)));
    }
}
