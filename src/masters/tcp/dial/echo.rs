//! What a dialed server sends back to mbgate's own bytes, told apart from its requests
//! (docs/dialing.md "What the SCADA server must do"): a server may answer the identity
//! and each heartbeat with nothing, with the very same bytes (an echo), or with bytes
//! of its own (an answer: "ACK", "OK"). An owed echo met where a request would begin
//! is taken off at once; while an answer is owed, what comes where a request would
//! begin is held until a pause ([`PAUSE`]) ends it, then judged whole: echoes and
//! requests exactly, or else the server's answer, dropped whole. So no byte of an
//! answer is ever part of a request, and a request never takes bytes from before a
//! pause while an answer is owed. Plain data with time passed in; the connection's
//! reader drives it (`tcp/connection/reader.rs`), telling it when bytes came and when it waited.

use crate::frame::Adu;
use crate::masters::tcp::connection::codec::{FrameError, MasterCodec};
use bytes::BytesMut;
use std::time::Duration;
use tokio::time::Instant;

/// The pause that ends an answer: bytes with no byte after them for this long are
/// judged as they are. The bytes of one write arrive together, or in segments sent back
/// to back (a full segment takes 1.2 ms at 10 Mbit/s, 6 ms at 2 Mbit/s), so a pause of
/// 10 ms within one write is rare even on a slow cellular link; a server answering a
/// heartbeat and then polling on its own timer leaves far more than 10 ms between them.
/// Longer would delay each request that comes while an answer is owed by as much, and
/// lose more requests sent on an answer's heels; shorter would cut the writes of a
/// slow link in two. A pause is only ever seen where no byte came for this long (the
/// reader reads before it waits), so two writes less than 10 ms apart are always one.
pub(in crate::masters::tcp) const PAUSE: Duration = Duration::from_millis(10);

/// The most answers owed at once: a server that acknowledges only some heartbeats
/// does not earn a licence for garbage by the hour.
const ANSWERS_OWED: u8 = 4;

/// The identity and heartbeat sent on one connection, what the server owes back, and
/// what it sent that is held for judging.
#[derive(Debug)]
pub(in crate::masters::tcp) struct Echoes {
    identity: Vec<u8>,
    heartbeat: Vec<u8>,
    /// The identity was sent and its echo not yet met.
    identity_owed: bool,
    /// Heartbeats sent whose echo was not met (at most [`ANSWERS_OWED`]).
    heartbeats_owed: u8,
    /// Answers (echoes or bytes of the server's own) the identity and the heartbeats
    /// sent may still get (at most [`ANSWERS_OWED`]).
    answers_owed: u8,
    /// How long after the last identity or heartbeat its answer may come: bytes
    /// later than that are owed nothing (`connect_timeout_ms`, the dial's bound on
    /// any answer of the server's).
    lapse: Duration,
    /// When the identity or the last heartbeat went out.
    earned: Instant,
    /// The most bytes held for a pause: more are judged at once. No answer and no
    /// burst of requests is longer than the replies a connection can be owed, so a
    /// server that never pauses holds no more memory than that.
    hold: usize,
    /// When the server's last bytes came.
    heard: Option<Instant>,
    /// No byte came for [`PAUSE`] after `heard`.
    quiet: bool,
    /// Bytes at the front judged to be echoes and whole requests (after a pause):
    /// taken as they are.
    judged: usize,
    /// An echo, an answer was dropped on this connection already (the log says the
    /// first of each).
    told: [bool; 2],
}

/// What the front of the bytes read is, for the reader.
#[derive(Debug)]
pub(in crate::masters::tcp) enum Front {
    /// What the codec made of them: a request, more bytes needed, or a violation.
    Decoded(Result<Option<Adu>, FrameError>),
    /// Bytes of the server's that answer mbgate's own, taken off.
    Answered(Answered),
    /// Held: decode nothing until more bytes come, or until this instant (a pause
    /// then ends what is held; tell [`Echoes::paused`]).
    Wait(Option<Instant>),
}

/// What was taken off, and how many bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(in crate::masters::tcp) enum Answered {
    /// The very bytes of the identity or of a heartbeat.
    Echo(usize),
    /// Bytes of the server's own, up to a pause: its answer.
    Answer(usize),
}

/// What an owed echo makes of the front of the bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Strip {
    Took(usize),
    /// The start of an echo: wait for the rest.
    Wait,
    Not,
}

impl Echoes {
    /// The identity (empty: none) goes out now; `heartbeat` will. What is owed lapses
    /// `lapse` after it was earned; at most `hold` bytes are held for a pause.
    pub(in crate::masters::tcp) fn new(
        identity: Vec<u8>,
        heartbeat: Vec<u8>,
        lapse: Duration,
        hold: usize,
        now: Instant,
    ) -> Echoes {
        Echoes {
            identity_owed: !identity.is_empty(),
            answers_owed: u8::from(!identity.is_empty()),
            identity,
            heartbeat,
            heartbeats_owed: 0,
            lapse,
            earned: now,
            hold,
            heard: None,
            quiet: false,
            judged: 0,
            told: [false; 2],
        }
    }

    /// A heartbeat went out at `now`.
    pub(in crate::masters::tcp) fn beat(&mut self, now: Instant) {
        self.heartbeats_owed = (self.heartbeats_owed + 1).min(ANSWERS_OWED);
        self.answers_owed = (self.answers_owed + 1).min(ANSWERS_OWED);
        self.earned = now;
    }

    /// Bytes of the server's came at `now`.
    pub(in crate::masters::tcp) fn came(&mut self, now: Instant) {
        self.heard = Some(now);
        self.quiet = false;
    }

    /// The reader waited until `now` (the instant of [`Front::Wait`]) and no byte came.
    pub(in crate::masters::tcp) fn paused(&mut self, now: Instant) {
        if self.heard.is_some_and(|h| now >= h + PAUSE) {
            self.quiet = true;
        }
    }

    /// The server closed its sending side: no byte will join what is held, which is
    /// judged as at a pause.
    pub(in crate::masters::tcp) fn ended(&mut self) {
        self.quiet = true;
    }

    /// Is this the first of its kind dropped on the connection?
    pub(in crate::masters::tcp) fn first(&mut self, answered: Answered) -> bool {
        let i = usize::from(matches!(answered, Answered::Answer(_)));
        !std::mem::replace(&mut self.told[i], true)
    }

    /// Does the server owe anything back?
    fn owes(&self) -> bool {
        self.answers_owed > 0 || self.identity_owed || self.heartbeats_owed > 0
    }

    /// The next thing at the front of `buf`, where a request would begin: an echo or
    /// an answer taken off, bytes held, or the codec's request.
    pub(in crate::masters::tcp) fn next<C: MasterCodec>(
        &mut self,
        buf: &mut BytesMut,
        codec: &mut C,
    ) -> Front {
        if self.judged > 0 {
            return match self.strip(buf) {
                Strip::Took(n) => {
                    self.judged = self.judged.saturating_sub(n);
                    Front::Answered(Answered::Echo(n))
                }
                _ => Front::Decoded(self.decode_judged(buf, codec)),
            };
        }
        if self.owes() && self.heard.is_some_and(|h| h >= self.earned + self.lapse) {
            // Later than any answer may come: what comes now is owed nothing.
            self.answers_owed = 0;
            self.identity_owed = false;
            self.heartbeats_owed = 0;
        }
        match self.strip(buf) {
            Strip::Took(n) => return Front::Answered(Answered::Echo(n)),
            // The start of an echo waits for the rest, until a pause.
            Strip::Wait if !self.quiet => return Front::Wait(self.heard.map(|h| h + PAUSE)),
            _ => {}
        }
        if self.answers_owed == 0 || buf.is_empty() {
            return Front::Decoded(codec.decode(buf));
        }
        if !self.quiet && buf.len() < self.hold {
            return Front::Wait(self.heard.map(|h| h + PAUSE));
        }
        // A pause (or as much as is ever held) ended what came: echoes and whole
        // requests are taken as they are; anything else, all of it, is the answer.
        if self.whole::<C>(buf) {
            self.judged = buf.len();
            return Front::Decoded(self.decode_judged(buf, codec));
        }
        self.answers_owed -= 1;
        let n = buf.len();
        buf.clear();
        Front::Answered(Answered::Answer(n))
    }

    /// The request at the front of the judged bytes, decoded from them alone (bytes
    /// after the pause never join it), as ended by the pause.
    fn decode_judged<C: MasterCodec>(
        &mut self,
        buf: &mut BytesMut,
        codec: &mut C,
    ) -> Result<Option<Adu>, FrameError> {
        let mut judged = buf.split_to(self.judged.min(buf.len()));
        codec.paused();
        let decoded = codec.decode(&mut judged);
        self.judged = judged.len();
        judged.unsplit(std::mem::take(buf));
        *buf = judged;
        decoded
    }

    /// Is all of `buf` owed echoes and whole requests, in any order?
    fn whole<C: MasterCodec>(&self, buf: &[u8]) -> bool {
        let (mut identity, mut heartbeats) = (self.identity_owed, self.heartbeats_owed);
        let mut rest = buf;
        while !rest.is_empty() {
            if identity && !self.identity.is_empty() && rest.starts_with(&self.identity) {
                identity = false;
                rest = &rest[self.identity.len()..];
            } else if heartbeats > 0
                && !self.heartbeat.is_empty()
                && rest.starts_with(&self.heartbeat)
            {
                heartbeats -= 1;
                rest = &rest[self.heartbeat.len()..];
            } else {
                match first_request::<C>(rest) {
                    Some(n) => rest = &rest[n..],
                    None => return false,
                }
            }
        }
        true
    }

    /// An owed echo at the front of `buf` is taken off it.
    fn strip(&mut self, buf: &mut BytesMut) -> Strip {
        if buf.is_empty() {
            return Strip::Not;
        }
        let mut wait = false;
        for which in [Which::Identity, Which::Heartbeat] {
            let (bytes, owed) = match which {
                Which::Identity => (&self.identity, self.identity_owed),
                Which::Heartbeat => (&self.heartbeat, self.heartbeats_owed > 0),
            };
            if !owed || bytes.is_empty() {
                continue;
            }
            if buf.starts_with(bytes) {
                let n = bytes.len();
                let _ = buf.split_to(n);
                match which {
                    Which::Identity => self.identity_owed = false,
                    Which::Heartbeat => self.heartbeats_owed -= 1,
                }
                self.answers_owed = self.answers_owed.saturating_sub(1);
                return Strip::Took(n);
            }
            wait |= bytes.starts_with(buf);
        }
        if wait {
            Strip::Wait
        } else {
            Strip::Not
        }
    }
}

/// The length of the request `bytes` begin with, as ended by a pause; `None`: they
/// begin with none (refused, or cut short).
fn first_request<C: MasterCodec>(bytes: &[u8]) -> Option<usize> {
    let mut codec = C::default();
    codec.paused();
    let mut buf = BytesMut::from(bytes);
    match codec.decode(&mut buf) {
        Ok(Some(_)) => Some(bytes.len() - buf.len()),
        _ => None,
    }
}

#[derive(Clone, Copy)]
enum Which {
    Identity,
    Heartbeat,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::mbap::decode_strict;
    use crate::masters::tcp::connection::codec::{Mbap, Rtu};
    use std::collections::VecDeque;

    const IDENTITY: &[u8] = b"site-17";
    const HEARTBEAT: &[u8] = &[0xff, 0xfe, 0x00, 0x01];
    /// Longer than any script here: nothing lapses unless a test says so.
    const LONG: Duration = Duration::from_secs(3600);
    /// More than any script here sends without a pause.
    const HOLD: usize = 1 << 20;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Where a byte the server sent came from.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Tag {
        /// The `n`th request of the script.
        Request(usize),
        /// The `n`th answer of the script (bytes of the server's own).
        Answer(usize),
        /// An echo of the identity or a heartbeat.
        Echo,
    }

    /// What happens on the connection at an instant: bytes of the server's read, or
    /// mbgate's heartbeat sent.
    #[derive(Debug, Clone)]
    enum Event {
        Bytes(Vec<(u8, Tag)>),
        Beat,
    }

    /// The reader of a dialed MBAP (or RTU) connection, as `tcp/connection/reader.rs` drives the
    /// state: bytes appended as they are read, the turns taken until it waits, a pause
    /// told once its instant passed with no byte read before it (the reader reads
    /// before it waits). What it handed on and what it dropped, each byte with its
    /// origin.
    struct Reader<C: MasterCodec> {
        echoes: Echoes,
        codec: C,
        buf: BytesMut,
        tags: VecDeque<Tag>,
        /// The pause the reader waits for, if any.
        pause: Option<Instant>,
        handed: Vec<(Vec<u8>, Vec<Tag>)>,
        dropped: Vec<(Answered, Vec<Tag>)>,
        /// The codec refused what came: the connection is closed.
        refused: bool,
    }

    impl<C: MasterCodec> Reader<C> {
        fn new(lapse: Duration, t0: Instant) -> Self {
            Reader {
                echoes: Echoes::new(IDENTITY.to_vec(), HEARTBEAT.to_vec(), lapse, HOLD, t0),
                codec: C::default(),
                buf: BytesMut::new(),
                tags: VecDeque::new(),
                pause: None,
                handed: Vec::new(),
                dropped: Vec::new(),
                refused: false,
            }
        }

        /// The events at their instants, in order, then time enough for every pause.
        fn run(mut self, events: &[(Instant, Event)]) -> Self {
            for (at, event) in events {
                self.until(Some(*at));
                if self.refused {
                    return self;
                }
                match event {
                    Event::Beat => self.echoes.beat(*at),
                    Event::Bytes(b) => {
                        self.echoes.came(*at);
                        self.buf.extend(b.iter().map(|(x, _)| *x));
                        self.tags.extend(b.iter().map(|(_, t)| *t));
                        self.turns();
                    }
                }
            }
            self.until(None);
            self
        }

        /// Each pause due before `next` (bytes at the very instant come first).
        fn until(&mut self, next: Option<Instant>) {
            for _ in 0..100 {
                match self.pause {
                    Some(p) if next.is_none_or(|n| p < n) && !self.refused => {
                        self.echoes.paused(p);
                        self.turns();
                    }
                    _ => return,
                }
            }
            panic!("the pauses never end");
        }

        /// Turns until the reader waits.
        fn turns(&mut self) {
            self.pause = None;
            for _ in 0..10_000 {
                let before = self.buf.len();
                let turn = self.echoes.next(&mut self.buf, &mut self.codec);
                let taken: Vec<Tag> = self.tags.drain(..before - self.buf.len()).collect();
                match turn {
                    Front::Decoded(Ok(Some(adu))) => {
                        self.handed.push((C::frame(&adu).to_vec(), taken));
                    }
                    Front::Answered(d) => self.dropped.push((d, taken)),
                    Front::Decoded(Ok(None)) => {
                        // As the reader: an RTU request of unknown shape ends at the
                        // codec's own pause (no byte comes in these scripts by then).
                        if self.codec.ended_by_pause(&self.buf).is_some() {
                            self.codec.paused();
                            continue;
                        }
                        return;
                    }
                    Front::Decoded(Err(_)) => {
                        self.refused = true;
                        return;
                    }
                    Front::Wait(at) => {
                        assert!(taken.is_empty());
                        self.pause = at;
                        return;
                    }
                }
            }
            panic!("no end of turns");
        }

        /// The bytes handed on as requests, each whole.
        fn requests(&self) -> Vec<Vec<u8>> {
            self.handed.iter().map(|(b, _)| b.clone()).collect()
        }
    }

    /// `bytes` of one origin, each byte tagged.
    fn tagged(bytes: &[u8], tag: Tag) -> Vec<(u8, Tag)> {
        bytes.iter().map(|&b| (b, tag)).collect()
    }

    fn read3(tid: u16) -> Vec<u8> {
        Adu::build(tid, 1, &[3, 0, 3, 0, 1]).as_bytes().to_vec()
    }

    /// The events of a script of the server's writes: each write's bytes at its
    /// instant, in one read.
    fn writes(t0: Instant, script: &[(u64, Event)]) -> Vec<(Instant, Event)> {
        script
            .iter()
            .map(|(at, e)| (t0 + ms(*at), e.clone()))
            .collect()
    }

    /// The case as found: the heartbeat answered `00 00 00 00 00 06` in one write, an
    /// FC 03 read of register 3 50 ms later. The answer is dropped; the read reaches the
    /// line as it was sent, and nothing else does.
    #[test]
    fn an_answer_that_reads_as_a_header_never_joins_the_request_after_it() {
        let t0 = Instant::now();
        let answer = [0, 0, 0, 0, 0, 6];
        let r = Reader::<Mbap>::new(LONG, t0).run(&writes(
            t0,
            &[
                (0, Event::Bytes(tagged(IDENTITY, Tag::Echo))),
                (100, Event::Beat),
                (110, Event::Bytes(tagged(&answer, Tag::Answer(0)))),
                (160, Event::Bytes(tagged(&read3(7), Tag::Request(0)))),
            ],
        ));
        assert_eq!(r.requests(), vec![read3(7)]);
        assert_eq!(r.dropped[1].0, Answered::Answer(6));
        assert!(!r.refused);
    }

    /// A 1- or 2-byte answer ("\x06", "OK"), or `00 00 00 00 00 06`, with a request on
    /// its heels (in the same write, 1 ms or 5 ms after): the request is lost with the
    /// answer, nothing of either reaches the line, and the next request after a pause
    /// is taken as it was sent.
    #[test]
    fn a_request_on_an_answers_heels_is_lost_with_it_and_the_next_is_whole() {
        for answer in [&b"\x06"[..], b"OK", b"OK\r\n", &[0, 0, 0, 0, 0, 6]] {
            for gap in [0, 1, 5] {
                let t0 = Instant::now();
                let mut burst = tagged(answer, Tag::Answer(0));
                let mut script = vec![(0, Event::Beat)];
                if gap == 0 {
                    burst.extend(tagged(&read3(1), Tag::Request(0)));
                    script.push((20, Event::Bytes(burst)));
                } else {
                    script.push((20, Event::Bytes(burst)));
                    script.push((20 + gap, Event::Bytes(tagged(&read3(1), Tag::Request(0)))));
                }
                script.push((200, Event::Bytes(tagged(&read3(2), Tag::Request(1)))));
                let r = Reader::<Mbap>::new(LONG, t0).run(&writes(t0, &script));
                let said = format!("{answer:02x?} then {gap} ms: {:?}", r.dropped);
                assert_eq!(r.requests(), vec![read3(2)], "{said}");
                // The identity's answer and the heartbeat's, each owed once: the
                // burst was one of them.
                assert_eq!(r.dropped.len(), 1, "{said}");
                assert!(!r.refused, "{said}");
            }
        }
    }

    /// The same on an RTU dial: the answer and a request 1 ms after it dropped, the
    /// next request whole.
    #[test]
    fn an_rtu_dial_drops_an_answer_and_what_came_on_its_heels() {
        let t0 = Instant::now();
        let read = crate::frame::rtu::encode(1, &[3, 0, 3, 0, 1]);
        let r = Reader::<Rtu>::new(LONG, t0).run(&writes(
            t0,
            &[
                (0, Event::Bytes(tagged(b"\x06", Tag::Answer(0)))),
                (1, Event::Bytes(tagged(&read, Tag::Request(0)))),
                (100, Event::Bytes(tagged(&read, Tag::Request(1)))),
            ],
        ));
        assert_eq!(r.requests(), vec![read.clone()]);
        assert_eq!(r.dropped[0].0, Answered::Answer(1 + read.len()));
        assert!(!r.refused);
    }

    /// Echoes are taken off wherever a request would begin: before a request in its
    /// write, or after one (the heartbeat crossed the request), split across reads.
    #[test]
    fn echoes_are_taken_off_before_and_after_requests() {
        let t0 = Instant::now();
        let mut before = tagged(HEARTBEAT, Tag::Echo);
        before.extend(tagged(&read3(1), Tag::Request(0)));
        let mut after = tagged(&read3(2), Tag::Request(1));
        after.extend(tagged(HEARTBEAT, Tag::Echo));
        let r = Reader::<Mbap>::new(LONG, t0).run(&writes(
            t0,
            &[
                (0, Event::Bytes(tagged(b"site", Tag::Echo))),
                (1, Event::Bytes(tagged(b"-17", Tag::Echo))),
                (50, Event::Beat),
                (60, Event::Bytes(before)),
                (100, Event::Beat),
                (110, Event::Bytes(after)),
            ],
        ));
        assert_eq!(r.requests(), vec![read3(1), read3(2)]);
        let echoes: Vec<Answered> = r.dropped.iter().map(|d| d.0).collect();
        assert_eq!(
            echoes,
            [Answered::Echo(7), Answered::Echo(4), Answered::Echo(4)]
        );
    }

    /// An answer of the server's own is taken once for each identity or heartbeat
    /// sent, no more than four at once; bytes the framing refuses when none is owed
    /// break the protocol.
    #[test]
    fn an_answer_is_taken_once_per_byte_sent_and_no_more() {
        let t0 = Instant::now();
        let mut script = vec![(0, Event::Bytes(tagged(b"ACK\r\n", Tag::Answer(0))))];
        for i in 0..10 {
            script.push((10 + i, Event::Beat));
        }
        for i in 0..5 {
            script.push((
                100 + 50 * i as u64,
                Event::Bytes(tagged(b"OK\r\n", Tag::Answer(1 + i))),
            ));
        }
        let r = Reader::<Mbap>::new(LONG, t0).run(&writes(t0, &script));
        assert_eq!(r.dropped.len(), 1 + 4, "{:?}", r.dropped);
        assert!(r.refused, "the fifth OK is no answer");
        assert!(r.handed.is_empty());
    }

    /// While nothing is owed a request is decoded at once, never held for a pause;
    /// while an answer is owed it waits for one.
    #[test]
    fn a_request_waits_for_a_pause_only_while_an_answer_is_owed() {
        let t0 = Instant::now();
        let mut e = Echoes::new(Vec::new(), HEARTBEAT.to_vec(), LONG, HOLD, t0);
        let mut codec = Mbap;
        let mut buf = BytesMut::from(&read3(1)[..]);
        e.came(t0);
        assert!(matches!(
            e.next(&mut buf, &mut codec),
            Front::Decoded(Ok(Some(_)))
        ));
        e.beat(t0);
        buf.extend_from_slice(&read3(2));
        e.came(t0 + ms(1));
        match e.next(&mut buf, &mut codec) {
            Front::Wait(Some(at)) => assert_eq!(at, t0 + ms(1) + PAUSE),
            other => panic!("{other:?}"),
        }
        e.paused(t0 + ms(5));
        assert!(
            matches!(e.next(&mut buf, &mut codec), Front::Wait(Some(_))),
            "no pause yet"
        );
        e.paused(t0 + ms(1) + PAUSE);
        assert!(matches!(
            e.next(&mut buf, &mut codec),
            Front::Decoded(Ok(Some(_)))
        ));
    }

    /// A request held while an answer is owed, then the server's end of sending (a
    /// request, then `shutdown(SHUT_WR)`): judged then, as at a pause, and taken.
    #[test]
    fn the_end_of_the_bytes_ends_what_is_held() {
        let t0 = Instant::now();
        let mut e = Echoes::new(IDENTITY.to_vec(), Vec::new(), LONG, HOLD, t0);
        let mut buf = BytesMut::from(&read3(1)[..]);
        e.came(t0);
        assert!(matches!(e.next(&mut buf, &mut Mbap), Front::Wait(Some(_))));
        e.ended();
        assert!(matches!(
            e.next(&mut buf, &mut Mbap),
            Front::Decoded(Ok(Some(_)))
        ));
    }

    /// A server that never pauses while an answer is owed holds no more than `hold`
    /// bytes: they are judged once that many came. Requests streamed are taken in
    /// turn; an answer glued to a stream of requests is dropped with what came with it.
    #[test]
    fn no_more_than_hold_bytes_are_held() {
        let t0 = Instant::now();
        let mut e = Echoes::new(IDENTITY.to_vec(), Vec::new(), LONG, 100, t0);
        let mut buf = BytesMut::new();
        let mut taken = 0;
        for i in 0..20u16 {
            buf.extend_from_slice(&read3(i));
            e.came(t0 + ms(u64::from(i)));
            loop {
                match e.next(&mut buf, &mut Mbap) {
                    Front::Decoded(Ok(Some(_))) => taken += 1,
                    Front::Wait(_) | Front::Decoded(Ok(None)) => break,
                    other => panic!("{other:?}"),
                }
            }
            assert!(buf.len() < 100 + 12, "{} bytes held", buf.len());
        }
        assert!(taken >= 16, "{taken} taken");
        let mut e = Echoes::new(IDENTITY.to_vec(), Vec::new(), LONG, 100, t0);
        let mut buf = BytesMut::from(&b"\x06"[..]);
        for i in 0..20u16 {
            buf.extend_from_slice(&read3(i));
            e.came(t0 + ms(u64::from(i)));
            match e.next(&mut buf, &mut Mbap) {
                Front::Wait(_) => {}
                Front::Answered(Answered::Answer(n)) => {
                    assert!(n >= 100 && buf.is_empty());
                    return;
                }
                other => panic!("{other:?}"),
            }
        }
        panic!("never judged");
    }

    /// What is owed lapses `lapse` after the identity or the last heartbeat: an
    /// answer later than that breaks the protocol as from any master.
    #[test]
    fn an_answer_later_than_the_lapse_is_no_answer() {
        let t0 = Instant::now();
        let late = Reader::<Mbap>::new(ms(1000), t0).run(&writes(
            t0,
            &[(1500, Event::Bytes(tagged(b"ACK", Tag::Answer(0))))],
        ));
        assert!(late.refused);
        let beat = Reader::<Mbap>::new(ms(1000), t0).run(&writes(
            t0,
            &[
                (1200, Event::Beat),
                (1500, Event::Bytes(tagged(b"ACK", Tag::Answer(0)))),
            ],
        ));
        assert!(!beat.refused, "the heartbeat's answer is owed anew");
        // A request after the lapse is not held.
        let mut e = Echoes::new(IDENTITY.to_vec(), Vec::new(), ms(1000), HOLD, t0);
        let mut buf = BytesMut::from(&read3(1)[..]);
        e.came(t0 + ms(1000));
        assert!(matches!(
            e.next(&mut buf, &mut Mbap),
            Front::Decoded(Ok(Some(_)))
        ));
    }

    // The property. A script of the server's: requests, answers and echoes, each a
    // write cut into reads at any byte, and mbgate's heartbeats between.

    /// One step of a script.
    #[derive(Debug, Clone)]
    enum Step {
        /// mbgate sends a heartbeat.
        Beat,
        /// The server writes a request (cut at `cuts`), `gap` ms after the last write.
        Request {
            bytes: Vec<u8>,
            gap: u64,
            cuts: Vec<usize>,
        },
        /// The server answers (if it owes one) with bytes of its own.
        Answer {
            bytes: Vec<u8>,
            gap: u64,
            cuts: Vec<usize>,
        },
        /// The server echoes the heartbeat (if it owes that echo).
        Echo { gap: u64 },
    }

    /// A request of any function code the line takes, any ids and fields.
    fn request() -> impl proptest::strategy::Strategy<Value = Vec<u8>> {
        use proptest::prelude::*;
        (
            any::<u16>(),
            any::<u8>(),
            0u8..3,
            any::<u16>(),
            1u16..126,
            proptest::collection::vec(any::<u16>(), 1..10),
        )
            .prop_map(|(tid, unit, kind, addr, qty, values)| {
                let mut pdu = Vec::new();
                match kind {
                    0 => {
                        pdu.push(3);
                        pdu.extend(addr.to_be_bytes());
                        pdu.extend(qty.to_be_bytes());
                    }
                    1 => {
                        pdu.push(6);
                        pdu.extend(addr.to_be_bytes());
                        pdu.extend(values[0].to_be_bytes());
                    }
                    _ => {
                        pdu.push(16);
                        pdu.extend(addr.to_be_bytes());
                        pdu.extend((values.len() as u16).to_be_bytes());
                        pdu.push((values.len() * 2) as u8);
                        values.iter().for_each(|v| pdu.extend(v.to_be_bytes()));
                    }
                }
                Adu::build(tid, unit, &pdu).as_bytes().to_vec()
            })
    }

    /// Are `bytes` requests and echoes of the identity or heartbeat, whole, one after
    /// another (checked here by the MBAP decoder, not by the state's own judge)?
    fn requests_and_echoes(mut bytes: &[u8]) -> bool {
        while !bytes.is_empty() {
            if let Some(rest) = bytes
                .strip_prefix(IDENTITY)
                .or_else(|| bytes.strip_prefix(HEARTBEAT))
            {
                bytes = rest;
                continue;
            }
            let mut b = BytesMut::from(bytes);
            match decode_strict(&mut b) {
                Ok(Some(adu)) => bytes = &bytes[adu.as_bytes().len()..],
                _ => return false,
            }
        }
        true
    }

    /// Answers the state cannot know from requests: any bytes that are not requests
    /// and echoes, and do not begin with an echo (the server would have echoed, then
    /// sent more).
    fn answer() -> impl proptest::strategy::Strategy<Value = Vec<u8>> {
        use proptest::prelude::*;
        let realistic = prop_oneof![
            Just(b"\x06".to_vec()),
            Just(b"OK".to_vec()),
            Just(b"OK\r\n".to_vec()),
            Just(b"ACK\r\n".to_vec()),
            Just(vec![0, 0, 0, 0, 0, 6]),
            Just(vec![0xff, 0xfe]),
            Just(b"site".to_vec()),
        ];
        prop_oneof![realistic, proptest::collection::vec(any::<u8>(), 1..24)]
            .prop_filter("an answer is no request nor echo", |a| {
                !requests_and_echoes(a) && !a.starts_with(IDENTITY) && !a.starts_with(HEARTBEAT)
            })
    }

    /// A step, the gap before a write drawn from glued (0), a few ms, just past the
    /// pause, and long.
    fn step() -> impl proptest::strategy::Strategy<Value = Step> {
        use proptest::prelude::*;
        let gap = prop_oneof![Just(0u64), 1u64..10, 10u64..30, Just(200u64)];
        let cuts = || proptest::collection::vec(1usize..30, 0..4);
        prop_oneof![
            2 => Just(Step::Beat),
            5 => (request(), gap.clone(), cuts()).prop_map(|(bytes, gap, cuts)| Step::Request { bytes, gap, cuts }),
            3 => (answer(), gap.clone(), cuts()).prop_map(|(bytes, gap, cuts)| Step::Answer { bytes, gap, cuts }),
            1 => gap.prop_map(|gap| Step::Echo { gap }),
        ]
    }

    /// What a script sends: its events, its requests (each with whether it came on
    /// an answer's heels, in the answer's burst), how many answers.
    struct Script {
        events: Vec<(u64, Event)>,
        requests: Vec<Vec<u8>>,
        heels: Vec<bool>,
        answers: usize,
    }

    /// The events of `steps`: each write at its gap after the last (0: in the same
    /// read as the last write's end), cut into reads 1 ms apart (less than the pause);
    /// an answer or echo only when one is owed (the identity's, one a heartbeat, four
    /// at most, as the server would), after a pause. `kept`: the server keeps the
    /// documented rule, a pause after each answer of its own too; else a request may
    /// come on an answer's heels.
    fn script(steps: &[Step], kept: bool) -> Script {
        // Longer than the pause: one exactly as long is no pause (bytes come first).
        let pause = PAUSE.as_millis() as u64 + 1;
        let mut events: Vec<(u64, Event)> = Vec::new();
        let (mut t, mut owed, mut echoes) = (0u64, 1u8, 0u8);
        // The identity and heartbeats sent that no answer of the server's own has met
        // (echoes aside): an echo held with a request behind an owed answer is taken
        // only at the pause, after heartbeats sent meanwhile, so the state meets the
        // cap of answers owed (four) as this count does, not as `owed` does.
        let mut unanswered = 1u8;
        let (mut requests, mut heels, mut answers) = (Vec::new(), Vec::new(), 0);
        // The last write was an answer, or a request on its heels (no pause since the
        // answer); the last write ends at `t`.
        let mut after_answer = false;
        let write = |events: &mut Vec<(u64, Event)>,
                     t: &mut u64,
                     gap: u64,
                     bytes: Vec<(u8, Tag)>,
                     cuts: &[usize]| {
            *t += gap;
            let mut at = *t;
            let mut rest = &bytes[..];
            let mut pieces = Vec::new();
            for c in cuts {
                if *c < rest.len() {
                    pieces.push(rest[..*c].to_vec());
                    rest = &rest[*c..];
                }
            }
            pieces.push(rest.to_vec());
            for (i, p) in pieces.into_iter().enumerate() {
                if i > 0 {
                    at += 1;
                }
                match events.last_mut() {
                    Some((when, Event::Bytes(b))) if *when == at => b.extend(p),
                    _ => events.push((at, Event::Bytes(p))),
                }
            }
            *t = at;
        };
        for s in steps {
            match s {
                // Not past three owed: an answer still held when a heartbeat goes out
                // is taken after it, and four at most (a unit test's) would then count
                // otherwise than here.
                Step::Beat if owed < 3 && unanswered < 3 => {
                    // As the last write ends: the clock of the writes runs on.
                    events.push((t, Event::Beat));
                    owed = (owed + 1).min(ANSWERS_OWED);
                    echoes = (echoes + 1).min(ANSWERS_OWED);
                    unanswered += 1;
                }
                Step::Request { bytes, gap, cuts } => {
                    let gap = if after_answer && kept {
                        (*gap).max(pause)
                    } else {
                        *gap
                    };
                    let n = requests.len();
                    requests.push(bytes.clone());
                    after_answer &= gap < pause;
                    heels.push(after_answer);
                    write(
                        &mut events,
                        &mut t,
                        gap,
                        tagged(bytes, Tag::Request(n)),
                        cuts,
                    );
                }
                Step::Answer { bytes, gap, cuts } if owed > 0 => {
                    let gap = (*gap).max(pause);
                    owed -= 1;
                    write(
                        &mut events,
                        &mut t,
                        gap,
                        tagged(bytes, Tag::Answer(answers)),
                        cuts,
                    );
                    answers += 1;
                    unanswered = unanswered.saturating_sub(1);
                    after_answer = true;
                }
                Step::Echo { gap } if owed > 0 && echoes > 0 => {
                    let gap = if after_answer {
                        (*gap).max(pause)
                    } else {
                        *gap
                    };
                    owed -= 1;
                    echoes -= 1;
                    write(&mut events, &mut t, gap, tagged(HEARTBEAT, Tag::Echo), &[]);
                    after_answer = false;
                }
                _ => {}
            }
        }
        Script {
            events,
            requests,
            heels,
            answers,
        }
    }

    proptest::proptest! {
        // No failure file in the tree: a case found is kept by hand as a test.
        #![proptest_config(proptest::test_runner::Config { failure_persistence: None, cases: 512, ..Default::default() })]

        /// The server keeps the rule (a pause before and after each answer of its
        /// own), its writes cut into reads at any byte, heartbeats anywhere: every
        /// request is handed on whole, in order, and nothing else; each answer is
        /// dropped whole, alone; no request handed on holds a byte of an answer.
        #[test]
        fn every_request_is_handed_on_and_no_answer_byte_with_them(
            steps in proptest::collection::vec(step(), 0..24),
        ) {
            let Script { events, requests, answers, .. } = script(&steps, true);
            let t0 = Instant::now();
            let r = Reader::<Mbap>::new(LONG, t0).run(&writes(t0, &events));
            proptest::prop_assert!(!r.refused, "{:?}", r.dropped);
            for (bytes, tags) in &r.handed {
                let Some(Tag::Request(n)) = tags.first() else {
                    proptest::prop_assert!(false, "handed on: {tags:?}");
                    unreachable!()
                };
                proptest::prop_assert!(tags.iter().all(|t| *t == Tag::Request(*n)), "{tags:?}");
                proptest::prop_assert_eq!(bytes, &requests[*n]);
            }
            proptest::prop_assert_eq!(r.requests(), requests);
            let dropped: Vec<usize> = r.dropped.iter().filter_map(|(d, tags)| match d {
                Answered::Answer(_) => match tags.first() { Some(Tag::Answer(n)) if tags.iter().all(|t| t == &Tag::Answer(*n)) => Some(*n), _ => None },
                Answered::Echo(_) => None,
            }).collect();
            proptest::prop_assert_eq!(dropped, (0..answers).collect::<Vec<_>>(), "{:?}", r.dropped);
        }

        /// The server breaks the rule: requests on an answer's heels, in the same
        /// write or a few ms after. Those are lost with the answer; every other
        /// request is handed on whole, in order; whatever is handed on is one of the
        /// server's requests and holds no byte of an answer. (The answers here
        /// cannot begin an MBAP header with the bytes after them: at most 3 bytes, or
        /// a protocol id that is not 0; an answer that begins one,
        /// `00 00 00 00 00 06`, is the first test's.)
        #[test]
        fn requests_on_an_answers_heels_are_lost_never_joined(
            steps in proptest::collection::vec(step(), 0..24),
        ) {
            let headless = |a: &[u8]| a.len() <= 3 || a[2..4] != [0, 0];
            let steps: Vec<Step> = steps
                .into_iter()
                .filter(|s| !matches!(s, Step::Answer { bytes, .. } if !headless(bytes)))
                .collect();
            let s = script(&steps, false);
            let t0 = Instant::now();
            let r = Reader::<Mbap>::new(LONG, t0).run(&writes(t0, &s.events));
            for (bytes, tags) in &r.handed {
                let Some(Tag::Request(n)) = tags.first() else {
                    proptest::prop_assert!(false, "handed on: {tags:?}");
                    unreachable!()
                };
                proptest::prop_assert!(tags.iter().all(|t| *t == Tag::Request(*n)), "{tags:?}");
                proptest::prop_assert_eq!(bytes, &s.requests[*n]);
            }
            proptest::prop_assert!(!r.refused, "{:?}", r.dropped);
            let clear: Vec<Vec<u8>> = s.requests.iter().zip(&s.heels).filter(|(_, h)| !**h).map(|(r, _)| r.clone()).collect();
            proptest::prop_assert_eq!(r.requests(), clear);
            let answers = r.dropped.iter().filter(|(d, _)| matches!(d, Answered::Answer(_))).count();
            proptest::prop_assert_eq!(answers, s.answers);
        }
    }
}
