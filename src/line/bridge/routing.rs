//! The master line's state machine (docs/design.md §4.2): which slave each request goes
//! to, the requests outstanding on each slave's connection with their MBAP ids and
//! deadlines, what waits for room, and the answers the serial master gets. Plain data,
//! time passed in; the loop in `bridge/mod.rs` does the I/O.

use super::requests::Incoming;
use crate::config::master::MasterLine;
use crate::frame::function::{ExceptionCode, FunctionCode};
use crate::frame::pdu;
use crate::frame::Adu;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// What the loop is to do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Action {
    /// Write this frame on route `route`'s connection.
    Send { route: usize, adu: Adu },
    /// Write this reply PDU to the serial master, for `request`.
    Answer { request: Incoming, pdu: Vec<u8> },
}

/// What became of a request, by its unit, for the unit's metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum UnitTally {
    /// Taken off the line.
    Request,
    /// Its slave's reply passed on.
    Reply,
    /// Answered 0x0B: no reply in time, or its connection lost.
    Timeout,
}

/// A slave connection as the routing sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SlaveConnection {
    /// Being made (or, passive, awaited for the first time): requests wait.
    Connecting,
    Up,
    /// Lost or refused, until the next attempt: requests get 0x0A at once.
    Down,
}

/// Running totals.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(crate) struct RoutingCounts {
    /// Requests taken off the serial line.
    pub(crate) requests: u64,
    /// Frames written to slaves.
    pub(crate) forwarded: u64,
    /// Slave replies passed to the serial master.
    pub(crate) replies: u64,
    /// 0x0B answers: no reply in time, or the connection lost with the request sent.
    pub(crate) timeouts: u64,
    /// 0x0A answers: no route, or the slave unreachable.
    pub(crate) unavailable: u64,
    /// Replies that matched nothing outstanding (late, or for a broadcast), dropped.
    pub(crate) late: u64,
    /// Frames with an outstanding request's id and unit that are no answer to it (a
    /// request echoed back, another function, a wrong byte count): dropped, the request
    /// left to its slave's real reply or its timeout.
    pub(crate) bad_replies: u64,
    /// Broadcasts (unit 0 on RTU/ASCII) sent to every route, unanswered.
    pub(crate) broadcasts: u64,
    /// Requests outside the protocol's limits, answered by mbgate.
    pub(crate) refused: u64,
    /// Requests to unit 0 on RTU/ASCII that a broadcast cannot carry (anything but a
    /// write): dropped, as no slave on a bus would answer them.
    pub(crate) broadcasts_refused: u64,
}

#[derive(Debug, Clone)]
struct Held {
    request: Incoming,
    /// Does the serial master still wait for it? (On RTU/ASCII a newer request
    /// means it gave up on this one.)
    answer: bool,
    deadline: Instant,
}

/// One route's live state: its connection to the slave, and the requests sent on it
/// and waiting for it.
#[derive(Debug)]
struct RouteState {
    conn: SlaveConnection,
    timeout: Duration,
    max_in_flight: usize,
    next_tid: u16,
    in_flight: Vec<(u16, Held)>,
    waiting: VecDeque<Held>,
}

/// Every route's state.
#[derive(Debug)]
pub(crate) struct Routing {
    line: MasterLine,
    routes: Vec<RouteState>,
    /// Unit 0 is a broadcast (RTU, ASCII), not on MBAP.
    serial_bus: bool,
    /// Shutting down: new requests get 0x0A, those held are answered or time out.
    closing: bool,
    pub(crate) counts: RoutingCounts,
    /// Each unit's requests, replies and timeouts since the loop last took them
    /// ([`Routing::take_tallies`]).
    tallies: Vec<(u8, UnitTally)>,
}

fn exception_pdu(request: &[u8], code: ExceptionCode) -> Vec<u8> {
    vec![request[0] | 0x80, code.get()]
}

impl Routing {
    /// `serial_bus`: the line is RTU or ASCII (one transaction at a time, unit 0 a
    /// broadcast).
    pub(crate) fn new(line: MasterLine, serial_bus: bool) -> Self {
        let routes = line
            .routes
            .iter()
            .map(|r| RouteState {
                conn: SlaveConnection::Connecting,
                timeout: Duration::from_millis(r.response_timeout_ms),
                max_in_flight: r.max_in_flight,
                next_tid: 1,
                in_flight: Vec::new(),
                waiting: VecDeque::new(),
            })
            .collect();
        Self {
            line,
            routes,
            serial_bus,
            closing: false,
            counts: RoutingCounts::default(),
            tallies: Vec::new(),
        }
    }

    /// The routes' response timeouts as `line` gives them now (a reload; its routes
    /// matched by their place, as the reload checked): requests from now on take
    /// them, those held keep their deadlines.
    pub(crate) fn retune(&mut self, line: &MasterLine) {
        let routes = self.routes.iter_mut().zip(self.line.routes.iter_mut());
        for ((route, cfg), now) in routes.zip(&line.routes) {
            route.timeout = Duration::from_millis(now.response_timeout_ms);
            cfg.response_timeout_ms = now.response_timeout_ms;
        }
    }

    /// Each unit's requests, replies and timeouts since the last call, in order.
    pub(crate) fn take_tallies(&mut self) -> Vec<(u8, UnitTally)> {
        std::mem::take(&mut self.tallies)
    }

    /// Shutting down: requests from now on are answered 0x0A at once; those held
    /// still get their replies, or 0x0B at their deadlines.
    pub(crate) fn close(&mut self) {
        self.closing = true;
    }

    /// Is nothing held (sent, or waiting for its turn)?
    pub(crate) fn idle(&self) -> bool {
        self.routes
            .iter()
            .all(|r| r.in_flight.is_empty() && r.waiting.is_empty())
    }

    fn answer(&mut self, out: &mut Vec<Action>, held: Held, code: ExceptionCode) {
        if code == ExceptionCode::GATEWAY_TARGET_FAILED {
            self.counts.timeouts += 1;
            self.tallies.push((held.request.unit, UnitTally::Timeout));
        } else {
            self.counts.unavailable += 1;
        }
        if held.answer {
            let pdu = exception_pdu(&held.request.pdu, code);
            out.push(Action::Answer {
                request: held.request,
                pdu,
            });
        }
    }

    /// A master on a bus waits for one reply at a time: a new request means it gave up
    /// on any earlier one, whose late reply must not reach it.
    fn given_up(&mut self) {
        for r in &mut self.routes {
            r.in_flight.iter_mut().for_each(|(_, h)| h.answer = false);
            r.waiting.iter_mut().for_each(|h| h.answer = false);
        }
    }

    /// A broadcast: every slave gets it, at once, and nothing is awaited (a reply to it
    /// is dropped as late).
    fn broadcast(&mut self, request: &Incoming, out: &mut Vec<Action>) {
        self.counts.broadcasts += 1;
        for i in 0..self.routes.len() {
            if self.routes[i].conn == SlaveConnection::Up {
                let tid = self.allocate(i);
                let adu = Adu::build(tid, 0, &request.pdu);
                self.counts.forwarded += 1;
                out.push(Action::Send { route: i, adu });
            }
        }
    }

    /// A request from the serial master at `now`.
    pub(crate) fn request(&mut self, request: Incoming, now: Instant) -> Vec<Action> {
        let mut out = Vec::new();
        self.counts.requests += 1;
        self.tallies.push((request.unit, UnitTally::Request));
        let broadcast = self.serial_bus && request.unit == 0;
        if let Err(code) = pdu::check_request(&request.pdu) {
            self.counts.refused += 1;
            if !broadcast {
                let pdu = exception_pdu(&request.pdu, code);
                out.push(Action::Answer { request, pdu });
            }
            return out;
        }
        if self.serial_bus {
            self.given_up();
        }
        if broadcast && !FunctionCode::new(request.pdu[0]).may_broadcast() {
            // No slave on a bus answers a broadcast, so it can only be a write: a
            // read to unit 0 goes nowhere (docs/protocol.md §2, "Unit 0 on a bus").
            self.counts.broadcasts_refused += 1;
            return out;
        }
        if self.closing {
            let held = Held {
                request,
                answer: !broadcast,
                deadline: now,
            };
            self.answer(&mut out, held, ExceptionCode::GATEWAY_PATH_UNAVAILABLE);
            return out;
        }
        if broadcast {
            self.broadcast(&request, &mut out);
            return out;
        }
        let held = Held {
            request,
            answer: true,
            deadline: now,
        };
        let Some(i) = self.line.route_for(held.request.unit) else {
            self.answer(&mut out, held, ExceptionCode::GATEWAY_PATH_UNAVAILABLE);
            return out;
        };
        let held = Held {
            deadline: now + self.routes[i].timeout,
            ..held
        };
        if self.routes[i].conn == SlaveConnection::Down {
            self.answer(&mut out, held, ExceptionCode::GATEWAY_PATH_UNAVAILABLE);
            return out;
        }
        self.routes[i].waiting.push_back(held);
        self.pump(i, &mut out);
        out
    }

    /// A transaction id not outstanding on route `i` (never 0, so a frame of zeros
    /// matches nothing).
    fn allocate(&mut self, i: usize) -> u16 {
        let r = &mut self.routes[i];
        loop {
            let tid = r.next_tid;
            r.next_tid = r.next_tid.wrapping_add(1).max(1);
            if !r.in_flight.iter().any(|(t, _)| *t == tid) {
                return tid;
            }
        }
    }

    /// Sends what waits on route `i` while its connection is up and has room.
    fn pump(&mut self, i: usize, out: &mut Vec<Action>) {
        while self.routes[i].conn == SlaveConnection::Up
            && self.routes[i].in_flight.len() < self.routes[i].max_in_flight
        {
            let Some(held) = self.routes[i].waiting.pop_front() else {
                break;
            };
            let tid = self.allocate(i);
            let adu = Adu::build(tid, held.request.unit, &held.request.pdu);
            self.routes[i].in_flight.push((tid, held));
            self.counts.forwarded += 1;
            out.push(Action::Send { route: i, adu });
        }
    }

    /// Route `i`'s connection is being made.
    pub(crate) fn connecting(&mut self, i: usize) {
        self.routes[i].conn = SlaveConnection::Connecting;
    }

    /// Route `i`'s connection is up: what waited is sent.
    pub(crate) fn up(&mut self, i: usize) -> Vec<Action> {
        let mut out = Vec::new();
        self.routes[i].conn = SlaveConnection::Up;
        self.pump(i, &mut out);
        out
    }

    /// Route `i`'s connection is lost or could not be made: requests already sent get
    /// 0x0B (the slave may have acted on them), those not sent 0x0A.
    pub(crate) fn down(&mut self, i: usize) -> Vec<Action> {
        let mut out = Vec::new();
        self.routes[i].conn = SlaveConnection::Down;
        for (_, held) in std::mem::take(&mut self.routes[i].in_flight) {
            self.answer(&mut out, held, ExceptionCode::GATEWAY_TARGET_FAILED);
        }
        for held in std::mem::take(&mut self.routes[i].waiting) {
            self.answer(&mut out, held, ExceptionCode::GATEWAY_PATH_UNAVAILABLE);
        }
        out
    }

    /// A frame from route `i`'s slave: the reply to the request with its id and unit,
    /// if it is an answer to that request (its function code or its exception, in the
    /// shape the request calls for: `pdu::reply_matches`), else dropped. A frame that
    /// only looks like the answer (the request echoed back by a slave that mirrors what
    /// it gets, a read's reply with the wrong byte count) never reaches the serial
    /// master: the request waits for its real reply, or its timeout (0x0B).
    pub(crate) fn reply(&mut self, i: usize, adu: &Adu) -> Vec<Action> {
        let mut out = Vec::new();
        let r = &mut self.routes[i];
        // The unit asked, or 0 or 255: a Modbus/TCP server addressed by its IP address
        // may ignore the unit id and answer with either (TCP/IP Implementation Guide
        // §4.4.2). The id is mbgate's own on this connection, so nothing else matches.
        let unit_ok = |asked: u8| adu.unit() == asked || adu.unit() == 0 || adu.unit() == 0xFF;
        let found = r
            .in_flight
            .iter()
            .position(|(tid, h)| *tid == adu.tid() && unit_ok(h.request.unit));
        if let Some(at) = found {
            if !pdu::reply_matches(&r.in_flight[at].1.request.pdu, adu.pdu()) {
                self.counts.bad_replies += 1;
                return out;
            }
        }
        match found {
            Some(at) => {
                let (_, held) = r.in_flight.remove(at);
                if held.answer {
                    self.counts.replies += 1;
                    self.tallies.push((held.request.unit, UnitTally::Reply));
                    out.push(Action::Answer {
                        request: held.request,
                        pdu: adu.pdu().to_vec(),
                    });
                } else {
                    self.counts.late += 1;
                }
                self.pump(i, &mut out);
            }
            None => self.counts.late += 1,
        }
        out
    }

    /// Requests whose time is up at `now`: 0x0B if sent (or waiting behind others on a
    /// live connection), 0x0A if the connection never came.
    pub(crate) fn expire(&mut self, now: Instant) -> Vec<Action> {
        let mut out = Vec::new();
        for i in 0..self.routes.len() {
            let r = &mut self.routes[i];
            let (late, kept): (Vec<_>, Vec<_>) = std::mem::take(&mut r.in_flight)
                .into_iter()
                .partition(|(_, h)| h.deadline <= now);
            r.in_flight = kept;
            let (stale, waiting): (VecDeque<_>, VecDeque<_>) = std::mem::take(&mut r.waiting)
                .into_iter()
                .partition(|h| h.deadline <= now);
            r.waiting = waiting;
            let code = if r.conn == SlaveConnection::Up {
                ExceptionCode::GATEWAY_TARGET_FAILED
            } else {
                ExceptionCode::GATEWAY_PATH_UNAVAILABLE
            };
            for (_, held) in late {
                self.answer(&mut out, held, ExceptionCode::GATEWAY_TARGET_FAILED);
            }
            for held in stale {
                self.answer(&mut out, held, code);
            }
            self.pump(i, &mut out);
        }
        out
    }

    /// The earliest deadline of anything held.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        self.routes
            .iter()
            .flat_map(|r| {
                let sent = r.in_flight.iter().map(|(_, h)| h.deadline);
                sent.chain(r.waiting.iter().map(|h| h.deadline))
            })
            .min()
    }

    /// The serial port was lost: the master that asked is on the far side of a port
    /// that is gone, and after the reopen it may have moved on to another request
    /// (an RTU master matches a reply by unit and function code only). Nothing held
    /// is answered any more: requests not yet sent are dropped, and the replies to
    /// those sent are taken off their connections as late, never written to the
    /// reopened port.
    pub(crate) fn serial_lost(&mut self) {
        for r in &mut self.routes {
            r.waiting.clear();
            for (_, held) in &mut r.in_flight {
                held.answer = false;
            }
        }
    }

    /// Requests held (sent or waiting) on route `i`.
    #[cfg(test)]
    pub(crate) fn held(&self, i: usize) -> usize {
        self.routes[i].in_flight.len() + self.routes[i].waiting.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::master::{Peer, Route};

    const READ: [u8; 5] = [3, 0, 0, 0, 1];

    fn line(max_in_flight: usize) -> MasterLine {
        let route = |units: &[u8]| Route {
            units: units.to_vec(),
            peer: Peer::Connect("h:1".into()),
            response_timeout_ms: 100,
            max_in_flight,
            allow: None,
        };
        MasterLine {
            routes: vec![route(&[1]), route(&[])],
        }
    }

    fn req(tid: u16, unit: u8) -> Incoming {
        Incoming {
            tid: Some(tid),
            unit,
            pdu: READ.to_vec(),
        }
    }

    fn sent(actions: &[Action]) -> Vec<(usize, u16, u8)> {
        actions
            .iter()
            .filter_map(|a| match a {
                Action::Send { route, adu } => Some((*route, adu.tid(), adu.unit())),
                _ => None,
            })
            .collect()
    }

    fn answers(actions: &[Action]) -> Vec<(Option<u16>, Vec<u8>)> {
        actions
            .iter()
            .filter_map(|a| match a {
                Action::Answer { request, pdu } => Some((request.tid, pdu.clone())),
                _ => None,
            })
            .collect()
    }

    /// A reload's timeouts: the requests after it take them, the one held keeps the
    /// deadline it had.
    #[test]
    fn retune_changes_the_timeout_of_later_requests_only() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(2), false);
        t.up(1);
        assert_eq!(sent(&t.request(req(1, 9), t0)), [(1, 1, 9)]);
        let mut longer = line(2);
        longer.routes[1].response_timeout_ms = 500;
        t.retune(&longer);
        assert_eq!(sent(&t.request(req(2, 9), t0)), [(1, 2, 9)]);
        let timed_out = vec![0x83, 0x0B];
        let at = |ms| t0 + Duration::from_millis(ms);
        assert_eq!(answers(&t.expire(at(200))), [(Some(1), timed_out.clone())]);
        assert_eq!(answers(&t.expire(at(400))), []);
        assert_eq!(answers(&t.expire(at(600))), [(Some(2), timed_out)]);
        assert_eq!(t.counts.timeouts, 2);
        let (r, to) = (UnitTally::Request, UnitTally::Timeout);
        assert_eq!(t.take_tallies(), [(9, r), (9, r), (9, to), (9, to)]);
        assert_eq!(t.take_tallies(), []);
    }

    #[test]
    fn after_the_serial_port_is_lost_nothing_held_is_answered() {
        let now = Instant::now();
        let mut t = Routing::new(line(1), true);
        t.up(0);
        assert_eq!(sent(&t.request(req(7, 1), now)), vec![(0, 1, 1)]);
        assert!(
            sent(&t.request(req(8, 1), now)).is_empty(),
            "waits for room"
        );
        t.serial_lost();
        let reply = Adu::build(1, 1, &[3, 2, 0, 42]);
        let after = t.reply(0, &reply);
        assert!(answers(&after).is_empty(), "{after:?}");
        assert!(sent(&after).is_empty(), "the waiting request was dropped");
        assert_eq!((t.counts.replies, t.counts.late), (0, 1));
        assert_eq!(t.held(0), 0);
        assert!(t.expire(now + Duration::from_secs(1)).is_empty());
    }

    #[test]
    fn routes_by_unit_waits_for_the_connection_and_restores_the_id() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(1), false);
        assert_eq!(t.request(req(7, 1), t0), []);
        assert_eq!(t.request(req(8, 9), t0), []);
        assert_eq!(sent(&t.up(0)), [(0, 1, 1)]);
        assert_eq!(sent(&t.up(1)), [(1, 1, 9)]);
        let a = t.reply(1, &Adu::build(1, 9, &[3, 2, 0, 5]));
        assert_eq!(answers(&a), [(Some(8), vec![3, 2, 0, 5])]);
        // A reply with the id but another unit, or twice: dropped.
        assert_eq!(t.reply(0, &Adu::build(1, 2, &[3, 2, 0, 5])), []);
        let a = t.reply(0, &Adu::build(1, 1, &[0x83, 2]));
        assert_eq!(answers(&a), [(Some(7), vec![0x83, 2])]);
        assert_eq!(t.reply(0, &Adu::build(1, 1, &[0x83, 2])), []);
        assert_eq!(t.counts.late, 2);
    }

    /// A slave that mirrors what it gets (or answers another shape) never has the
    /// mirror taken for the answer: the request waits for the real reply.
    #[test]
    fn a_request_echoed_back_is_no_reply() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(1), false);
        t.up(0);
        assert_eq!(sent(&t.request(req(7, 1), t0)), [(0, 1, 1)]);
        // The read itself, mirrored; a reply of 2 registers to a read of 1; another
        // function; an exception code no server sends.
        for pdu in [&READ[..], &[3, 4, 0, 1, 0, 2], &[4, 2, 0, 5], &[0x83, 0x55]] {
            assert_eq!(t.reply(0, &Adu::build(1, 1, pdu)), [], "{pdu:?}");
        }
        assert_eq!((t.counts.bad_replies, t.counts.replies), (4, 0));
        assert_eq!(t.held(0), 1, "still waiting for its reply");
        let a = t.reply(0, &Adu::build(1, 1, &[3, 2, 0, 5]));
        assert_eq!(answers(&a), [(Some(7), vec![3, 2, 0, 5])]);
        assert_eq!((t.counts.bad_replies, t.counts.replies), (4, 1));
    }

    #[test]
    fn one_at_a_time_unless_pipelining_is_allowed() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(1), false);
        t.up(1);
        assert_eq!(sent(&t.request(req(1, 5), t0)).len(), 1);
        assert_eq!(t.request(req(2, 5), t0), [], "waits for room");
        let a = t.reply(1, &Adu::build(1, 5, &[3, 2, 0, 0]));
        assert_eq!(answers(&a).len(), 1);
        assert_eq!(
            sent(&a),
            [(1, 2, 5)],
            "the next one goes when the first is answered"
        );
        let mut t = Routing::new(line(3), false);
        t.up(1);
        let n: usize = (0..4).map(|i| sent(&t.request(req(i, 5), t0)).len()).sum();
        assert_eq!(n, 3);
        assert_eq!(t.held(1), 4);
    }

    #[test]
    fn timeout_is_0x0b_unreachable_is_0x0a() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(1), false);
        t.up(1);
        t.request(req(1, 5), t0);
        t.request(req(2, 5), t0 + Duration::from_millis(50));
        assert_eq!(t.next_deadline(), Some(t0 + Duration::from_millis(100)));
        assert_eq!(t.expire(t0 + Duration::from_millis(99)), []);
        let a = t.expire(t0 + Duration::from_millis(100));
        assert_eq!(answers(&a), [(Some(1), vec![0x83, 0x0B])]);
        assert_eq!(sent(&a), [(1, 2, 5)]);
        // The connection goes with a request on it: 0x0B for it (it was sent).
        let a = t.down(1);
        assert_eq!(answers(&a), [(Some(2), vec![0x83, 0x0B])]);
        // While down: 0x0A at once, nothing sent.
        let a = t.request(req(3, 5), t0);
        assert_eq!(answers(&a), [(Some(3), vec![0x83, 0x0A])]);
        // Connecting: it waits; the attempt fails: 0x0A.
        t.connecting(1);
        assert_eq!(t.request(req(4, 5), t0), []);
        assert_eq!(answers(&t.down(1)), [(Some(4), vec![0x83, 0x0A])]);
        // A route that never connects within the deadline: 0x0A.
        t.connecting(1);
        t.request(req(5, 5), t0);
        let a = t.expire(t0 + Duration::from_millis(100));
        assert_eq!(answers(&a), [(Some(5), vec![0x83, 0x0A])]);
        assert_eq!((t.counts.timeouts, t.counts.unavailable), (2, 3));
        // Back up: served again.
        t.up(1);
        assert_eq!(sent(&t.request(req(6, 5), t0)).len(), 1);
    }

    #[test]
    fn no_route_is_0x0a_and_bad_requests_are_answered_here() {
        let t0 = Instant::now();
        let mut only = line(1);
        only.routes.pop();
        let mut t = Routing::new(only, false);
        t.up(0);
        assert_eq!(
            answers(&t.request(req(1, 2), t0)),
            [(Some(1), vec![0x83, 0x0A])]
        );
        let zero = Incoming {
            pdu: vec![3, 0, 0, 0, 0],
            ..req(2, 1)
        };
        assert_eq!(answers(&t.request(zero, t0)), [(Some(2), vec![0x83, 0x03])]);
    }

    #[test]
    fn bus_broadcast_goes_everywhere_unanswered_and_a_new_request_supersedes() {
        let t0 = Instant::now();
        let mut t = Routing::new(line(1), true);
        t.up(0);
        t.up(1);
        let bus = |unit| Incoming {
            tid: None,
            unit,
            pdu: vec![6, 0, 1, 0, 7],
        };
        let a = t.request(bus(0), t0);
        assert_eq!(sent(&a), [(0, 1, 0), (1, 1, 0)]);
        assert_eq!(answers(&a), []);
        assert_eq!(t.held(0) + t.held(1), 0, "nothing awaited");
        // The master gave up on unit 1's request and asked another: the late reply
        // is dropped, the new one answered.
        t.request(bus(1), t0);
        let a = t.request(bus(9), t0);
        assert_eq!(sent(&a), [(1, 2, 9)]);
        assert_eq!(t.reply(0, &Adu::build(2, 1, &[6, 0, 1, 0, 7])), []);
        assert_eq!(
            answers(&t.reply(1, &Adu::build(2, 9, &[6, 0, 1, 0, 7]))).len(),
            1
        );
        // A read to unit 0 is no broadcast: sent nowhere, answered nothing, counted.
        let a = t.request(req(0, 0), t0);
        assert_eq!((sent(&a), answers(&a)), (vec![], vec![]));
        assert_eq!(t.counts.broadcasts_refused, 1);
        assert_eq!(t.counts.broadcasts, 1);
    }

    /// A Modbus/TCP slave that ignores the unit id answers with 0 or 255: matched by
    /// mbgate's own transaction id and the function code, answered with the serial
    /// master's unit. Another unit, or another function, is not the reply.
    #[test]
    fn a_slave_answering_as_unit_0_or_255_is_matched() {
        let now = Instant::now();
        let mut t = Routing::new(line(1), false);
        t.up(0);
        for (i, as_unit) in [0u8, 0xFF].into_iter().enumerate() {
            let tid = i as u16 + 1;
            assert_eq!(sent(&t.request(req(7 + tid, 1), now)), [(0, tid, 1)]);
            assert_eq!(t.reply(0, &Adu::build(tid, 2, &[3, 2, 0, 9])), []);
            assert_eq!(t.reply(0, &Adu::build(tid, as_unit, &[4, 2, 0, 9])), []);
            let a = t.reply(0, &Adu::build(tid, as_unit, &[3, 2, 0, 9]));
            assert_eq!(answers(&a), [(Some(7 + tid), vec![3, 2, 0, 9])]);
        }
        // Another unit matches nothing (late); the request's id and unit with another
        // function is no answer to it.
        assert_eq!((t.counts.late, t.counts.bad_replies), (2, 2));
    }

    /// Shutting down: what is held is still answered (its reply, or 0x0B at its
    /// deadline); a new request gets 0x0A at once.
    #[test]
    fn closing_answers_what_is_held_and_refuses_the_rest() {
        let now = Instant::now();
        let mut t = Routing::new(line(1), false);
        t.up(0);
        t.request(req(1, 1), now);
        t.request(req(2, 1), now);
        t.close();
        assert!(!t.idle());
        let a = t.request(req(3, 1), now);
        assert_eq!(answers(&a), [(Some(3), vec![0x83, 0x0A])]);
        let a = t.reply(0, &Adu::build(1, 1, &[3, 2, 0, 5]));
        assert_eq!(answers(&a), [(Some(1), vec![3, 2, 0, 5])]);
        assert_eq!(sent(&a), [(0, 2, 1)], "the one waiting goes too");
        let a = t.expire(now + Duration::from_millis(100));
        assert_eq!(answers(&a), [(Some(2), vec![0x83, 0x0B])]);
        assert!(t.idle());
    }
}
