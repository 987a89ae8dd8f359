//! The scheduler's tests: its rules one by one, and the property that no path that
//! moves a request puts it on the line behind a later request of a master it answers.

use super::*;
use proptest::prelude::*;
use std::collections::HashMap;

/// A request: each master it serves with a label, its unit, the register it reads
/// (`None`: it acts, like a write), and the turn that last put it on the line.
#[derive(Debug, PartialEq, Eq)]
struct Req {
    askers: Vec<(ConnId, String)>,
    unit: u8,
    reads: Option<u16>,
    turn: u64,
    /// Resends so far (the property test's timeouts).
    attempts: u32,
}

/// A request that acts on `unit` (a write).
#[allow(non_snake_case)]
fn Req(conn: ConnId, unit: u8, label: &str) -> Req {
    Req {
        askers: vec![(conn, label.into())],
        unit,
        reads: None,
        turn: 0,
        attempts: 0,
    }
}

/// A read of register `addr` of `unit`.
fn read(conn: ConnId, unit: u8, addr: u16, label: &str) -> Req {
    Req {
        reads: Some(addr),
        ..Req(conn, unit, label)
    }
}

impl Req {
    /// `askers`, taken out of this request, as a request of their own.
    fn part(&self, askers: Vec<(ConnId, String)>) -> Req {
        Req {
            askers,
            unit: self.unit,
            reads: self.reads,
            turn: self.turn,
            attempts: self.attempts,
        }
    }
}

impl Queued for Req {
    fn conn(&self) -> ConnId {
        self.askers[0].0
    }
    fn unit(&self) -> u8 {
        self.unit
    }
    fn read_key(&self) -> Option<ReadKey> {
        let [hi, lo] = self.reads?.to_be_bytes();
        Some(ReadKey {
            unit: self.unit,
            pdu: [3, hi, lo, 0, 1],
        })
    }
    fn acts(&self) -> bool {
        self.reads.is_none()
    }
    fn masters(&self) -> impl Iterator<Item = ConnId> + '_ {
        self.askers.iter().map(|a| a.0)
    }
    fn join(&mut self, other: Self) {
        self.askers.extend(other.askers);
    }
    fn leave(&mut self, conn: ConnId) -> Option<Self> {
        if self.askers.iter().all(|a| a.0 == conn) {
            return None;
        }
        let (gone, kept) = self.askers.drain(..).partition(|a| a.0 == conn);
        self.askers = kept;
        (!gone.is_empty()).then(|| self.part(gone))
    }
    fn leave_one(&mut self, conn: ConnId) -> Option<Self> {
        let i = self.askers.iter().rposition(|a| a.0 == conn)?;
        if self.askers.len() == 1 {
            return None;
        }
        let one = self.askers.remove(i);
        Some(self.part(vec![one]))
    }
    fn turn(&self) -> u64 {
        self.turn
    }
    fn set_turn(&mut self, turn: u64) {
        self.turn = turn;
    }
}

/// What goes on the line, in order: each request as the labels it answers.
fn sent(s: &mut Scheduler<Req>) -> Vec<String> {
    std::iter::from_fn(|| s.next()).map(|r| label(&r)).collect()
}

fn label(r: &Req) -> String {
    let labels: Vec<&str> = r.askers.iter().map(|a| a.1.as_str()).collect();
    labels.join("+")
}

/// `r` went on the line (as [`Scheduler::next`] hands a request out) and is resent.
fn resend_sent(s: &mut Scheduler<Req>, mut r: Req) {
    s.turns += 1;
    r.turn = s.turns;
    let out = LastOut {
        any: s.turns,
        acting: s.turns,
    };
    for c in r.masters() {
        s.last_out.insert(c, out);
    }
    s.resend(r).unwrap();
}

fn labels(s: &mut Scheduler<Req>) -> Vec<String> {
    sent(s)
}

#[test]
fn round_robin_and_a_newcomer_goes_ahead_of_the_master_just_served() {
    let mut s = Scheduler::new(64, true);
    s.push(Req(1, 1, "a1"));
    assert_eq!(label(&s.next().unwrap()), "a1");
    s.push(Req(1, 1, "a2"));
    s.push(Req(1, 1, "a3"));
    s.push(Req(2, 1, "b1"));
    s.push(Req(3, 1, "c1"));
    assert_eq!(labels(&mut s), ["b1", "c1", "a2", "a3"]);
    assert!(!s.has_waiting());
}

#[test]
fn resends_go_first() {
    let mut s = Scheduler::new(64, true);
    s.push(Req(1, 1, "a1"));
    resend_sent(&mut s, Req(2, 1, "again"));
    assert_eq!(labels(&mut s), ["again", "a1"]);
}

#[test]
fn a_full_queue_refuses_the_heaviest_masters_newest() {
    let mut s = Scheduler::new(3, true);
    for l in ["a1", "a2", "a3"] {
        assert_eq!(s.push(Req(1, 1, l)), Admitted::Queued);
    }
    assert_eq!(
        s.push(Req(2, 1, "b1")),
        Admitted::Displaced(Req(1, 1, "a3"))
    );
    assert_eq!(s.push(Req(2, 1, "b2")), Admitted::Refused(Req(2, 1, "b2")));
    assert_eq!(s.push(Req(1, 1, "a4")), Admitted::Refused(Req(1, 1, "a4")));
    assert_eq!(s.queued(), 3);
    assert_eq!(labels(&mut s), ["a1", "b1", "a2"]);
}

#[test]
fn detach_unit_sweep_and_drain_take_requests_out() {
    let mut s = Scheduler::new(64, true);
    s.push(Req(1, 1, "a1"));
    s.push(Req(1, 5, "a5"));
    s.push(Req(2, 5, "b5"));
    resend_sent(&mut s, Req(3, 5, "c5"));
    s.push(Req(3, 1, "c1"));
    let swept: Vec<_> = s.take_unit(5).iter().map(label).collect();
    assert_eq!(swept.len(), 3);
    for l in ["c5", "b5", "a5"] {
        assert!(swept.iter().any(|s| s == l), "{swept:?}");
    }
    assert_eq!(s.queued(), 2);
    s.detach(3);
    assert_eq!(s.queued(), 1);
    resend_sent(&mut s, Req(1, 1, "r"));
    let all: Vec<_> = s.drain_all().iter().map(label).collect();
    assert_eq!(all, ["r", "a1"]);
    assert!(!s.has_waiting() && s.next().is_none());
}

/// An identical read joins one still queued, from any master (and the same
/// master's second copy too); a read already sent is joined by nothing; another
/// register, unit or `coalesce = false` never joins.
#[test]
fn identical_queued_reads_join_and_sent_ones_do_not() {
    let mut s = Scheduler::new(64, true);
    assert_eq!(s.push(read(1, 1, 10, "a")), Admitted::Queued);
    assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Joined);
    assert_eq!(s.push(read(3, 1, 10, "c")), Admitted::Joined);
    assert_eq!(s.push(read(3, 1, 11, "c11")), Admitted::Queued);
    assert_eq!(s.push(read(3, 2, 10, "c-unit2")), Admitted::Queued);
    assert_eq!(s.queued(), 5, "a joined read counts for its master");
    assert_eq!(s.joins(), 2);
    assert_eq!(label(&s.next().unwrap()), "a+b+c");
    // On the line now: the next identical read is a transaction of its own.
    assert_eq!(s.push(read(2, 1, 10, "b2")), Admitted::Queued);
    assert_eq!(s.push(read(2, 1, 10, "b3")), Admitted::Joined);
    assert_eq!(sent(&mut s), ["c11", "b2+b3", "c-unit2"]);
    assert_eq!(s.queued(), 0);

    let mut off = Scheduler::new(64, false);
    off.push(read(1, 1, 10, "a"));
    assert_eq!(off.push(read(2, 1, 10, "b")), Admitted::Queued);
    assert_eq!(sent(&mut off), ["a", "b"]);
}

/// A request that acts on the unit, from any master, queued between two identical
/// reads keeps them apart; on another unit it does not; to unit 0 (a broadcast) it
/// does for every unit. A master with a write of its own still waiting never joins
/// a read queued after that write, though nothing else stops it.
#[test]
fn a_write_to_the_unit_in_between_ends_the_chance_to_join() {
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 10, "a"));
    s.push(Req(3, 1, "w"));
    assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
    assert_eq!(s.push(read(1, 1, 10, "a2")), Admitted::Joined, "joins b");
    s.push(Req(3, 7, "w-unit7"));
    assert_eq!(s.push(read(4, 1, 10, "d")), Admitted::Joined);
    s.push(Req(3, 0, "broadcast"));
    assert_eq!(s.push(read(4, 1, 10, "d2")), Admitted::Queued);
    assert_eq!(
        sent(&mut s),
        ["a", "w", "b+a2+d", "d2", "w-unit7", "broadcast"]
    );

    // Master 2 writes, then master 1 queues a read, then 2 reads the same: 1's
    // read may go before 2's write, so 2's read waits behind its write.
    let mut s = Scheduler::new(64, true);
    s.push(Req(2, 1, "w2"));
    s.push(read(1, 1, 10, "a"));
    assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
    assert_eq!(s.push(read(3, 1, 10, "c")), Admitted::Joined, "joins b");
    // A resend of 2's write waiting counts the same.
    let mut s = Scheduler::new(64, true);
    resend_sent(&mut s, Req(2, 1, "w2 again"));
    s.push(read(1, 1, 10, "a"));
    assert_eq!(s.push(read(2, 1, 10, "b")), Admitted::Queued);
}

/// A master that goes away leaves the reads it shared queued for the others, and
/// its part of them is no longer counted; a read shared by others is never taken
/// whole by a 0x06: the master holding the most gives up its own part of it.
#[test]
fn a_joined_master_leaving_or_displaced_leaves_the_others_their_read() {
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 10, "a"));
    s.push(read(2, 1, 10, "b"));
    s.push(read(3, 1, 10, "c"));
    s.push(read(2, 1, 20, "b20"));
    s.push(read(1, 1, 20, "a20"));
    resend_sent(&mut s, read(1, 1, 30, "a30 again"));
    s.detach(1);
    assert_eq!(s.queued(), 3);
    assert!(!s.acts_waiting(1, 1));
    // Its read stays where it was for the others: 2 sent it before its read of 20.
    assert_eq!(sent(&mut s), ["b+c", "b20"]);

    // Master 1 holds the most: its newest, a read 2 joined, is taken from it; the
    // read stays queued for 2.
    let mut s = Scheduler::new(4, true);
    s.push(read(1, 1, 10, "a10"));
    s.push(read(1, 1, 11, "a11"));
    s.push(read(1, 1, 12, "a12"));
    assert_eq!(s.push(read(2, 1, 12, "b12")), Admitted::Joined);
    match s.push(read(3, 1, 99, "c")) {
        Admitted::Displaced(r) => assert_eq!(label(&r), "a12"),
        other => panic!("{other:?}"),
    }
    assert_eq!(s.queued(), 4);
    assert_eq!(sent(&mut s), ["a10", "b12", "c", "a11"]);

    // Master 2 holds the most, all of it joined to another's read: its newest
    // request is taken from it.
    let mut s = Scheduler::new(3, true);
    s.push(read(1, 1, 10, "a10"));
    s.push(read(2, 1, 10, "b10"));
    s.push(read(2, 1, 10, "b10'"));
    match s.push(read(3, 1, 99, "c")) {
        Admitted::Displaced(r) => assert_eq!(label(&r), "b10'"),
        other => panic!("{other:?}"),
    }
    assert_eq!(s.queued(), 3);
    assert_eq!(sent(&mut s), ["a10+b10", "c"]);

    // A master whose pipelined identical reads joined each other holds one read on
    // the line but a share of 4: a full queue takes one of them, not all four.
    let mut s = Scheduler::new(5, true);
    for l in ["a1", "a2", "a3", "a4"] {
        s.push(read(1, 1, 10, l));
    }
    s.push(read(2, 1, 20, "b"));
    match s.push(read(3, 1, 30, "c")) {
        Admitted::Displaced(r) => assert_eq!(label(&r), "a4"),
        other => panic!("{other:?}"),
    }
    assert_eq!(s.queued(), 5);
    assert_eq!(sent(&mut s), ["a1+a2+a3", "b", "c"]);
}

/// A shared read never goes behind a later request of a master it answers: not when
/// the master it was queued for leaves, not when a full queue takes that master's
/// part, and not by joining: a read joins only one queued after everything its master
/// already waits for, and goes on the line only once it is next for all its masters.
#[test]
fn a_shared_read_keeps_its_place_for_every_master_it_answers() {
    // 1 reads 5; 2's read of 5 joins it; 2 writes 5; 1 leaves: 2's read goes first.
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 5, "a"));
    assert_eq!(s.push(read(2, 1, 5, "b")), Admitted::Joined);
    s.push(Req(2, 1, "w"));
    s.detach(1);
    s.audit();
    assert_eq!(sent(&mut s), ["b", "w"]);

    // The same, 1's part taken by a full queue to make room for 3.
    let mut s = Scheduler::new(5, true);
    s.push(read(1, 1, 7, "a7"));
    s.push(read(1, 1, 8, "a8"));
    s.push(read(1, 1, 5, "a5"));
    assert_eq!(s.push(read(2, 1, 5, "b5")), Admitted::Joined);
    s.push(Req(2, 1, "w"));
    match s.push(read(3, 1, 6, "d")) {
        Admitted::Displaced(r) => assert_eq!(label(&r), "a5"),
        other => panic!("{other:?}"),
    }
    s.audit();
    assert_eq!(sent(&mut s), ["a7", "b5", "d", "a8", "w"]);

    // 1 queues two reads; 2 reads 5 (joins 1's second) and then writes: 1's first
    // read goes first, then the shared one, then 2's write, although 2's queue comes
    // up before 1's second turn.
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 4, "a4"));
    s.push(read(1, 1, 5, "a5"));
    assert_eq!(s.push(read(2, 1, 5, "b5")), Admitted::Joined);
    s.push(Req(2, 1, "w"));
    assert_eq!(sent(&mut s), ["a4", "a5+b5", "w"]);

    // Crossed orders: 1 reads 4 then 5, 2 reads 5 then 4. 2's read of 5 joins 1's;
    // its read of 4 cannot join 1's (sent before the read of 5 it waits for).
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 4, "a4"));
    s.push(read(1, 1, 5, "a5"));
    assert_eq!(s.push(read(2, 1, 5, "b5")), Admitted::Joined);
    assert_eq!(s.push(read(2, 1, 4, "b4")), Admitted::Queued);
    s.audit();
    assert_eq!(sent(&mut s), ["a4", "a5+b5", "b4"]);
}

/// A resend goes first, unless a later request of one of its masters that could
/// change its answer went on the line after it (more than one in flight): a later
/// write, or anything later when it writes itself. Then it is given back (to be
/// answered 0x0B). A read may be resent behind its master's later reads.
#[test]
fn a_resend_never_overtakes_a_later_request_that_could_change_its_answer() {
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 4, "a4"));
    s.push(read(1, 1, 5, "a5"));
    s.push(Req(1, 1, "aw"));
    s.push(read(2, 1, 9, "b9"));
    s.push(Req(2, 1, "bw"));
    s.push(read(2, 1, 8, "b8"));
    let out: Vec<Req> = std::iter::from_fn(|| s.next()).collect();
    assert_eq!(
        out.iter().map(label).collect::<Vec<_>>(),
        ["a4", "b9", "a5", "bw", "aw", "b8"]
    );
    let [a4, b9, a5, bw, aw, b8] = out.try_into().unwrap();
    // 1's reads: its write went after them.
    assert_eq!(label(&s.resend(a4).unwrap_err()), "a4");
    assert_eq!(label(&s.resend(a5).unwrap_err()), "a5");
    // 2's read of 8 and 1's write: nothing later of their masters' went on the line.
    s.resend(b8).unwrap();
    s.resend(aw).unwrap();
    // 2's write: its read of 8 went after it (a write resent behind it would change
    // that read's answer); 2's read of 9: its write went after it.
    assert_eq!(label(&s.resend(bw).unwrap_err()), "bw");
    assert_eq!(label(&s.resend(b9).unwrap_err()), "b9");
    assert_eq!(sent(&mut s), ["b8", "aw"]);

    // Two pipelined reads, both unanswered: both resent, the first behind the second.
    let mut s = Scheduler::new(64, true);
    s.push(read(1, 1, 4, "a4"));
    s.push(read(1, 1, 5, "a5"));
    let (a4, a5) = (s.next().unwrap(), s.next().unwrap());
    s.resend(a5).unwrap();
    s.resend(a4).unwrap();
    assert_eq!(sent(&mut s), ["a5", "a4"]);
}

// ---------------------------------------------------------------------------------
// The property: each master's requests go on the line in the order it sent them.

/// One step of a random run.
#[derive(Debug, Clone)]
enum Step {
    /// Master `master` sends a read of `addr` (or a write to it) to `unit`.
    Arrive {
        master: usize,
        unit: u8,
        addr: u16,
        write: bool,
    },
    /// The relay puts the next request on the line (if it has room).
    Send,
    /// The reply to the `n`th request on the line comes.
    Reply(usize),
    /// The `n`th request on the line gets no reply: resent if it may be, else 0x0B.
    Timeout(usize),
    /// Master `master` disconnects (and a new one takes its place).
    Leave(usize),
    /// `unit` is backed off: its waiting requests are answered 0x0B.
    BackOff(u8),
    /// The port is lost: everything waiting is answered 0x0A.
    PortLost,
}

fn step() -> impl Strategy<Value = Step> {
    prop_oneof![
        8 => (0..4usize, 1..3u8, 0..3u16, prop::bool::weighted(0.3)).prop_map(
            |(master, unit, addr, write)| Step::Arrive { master, unit, addr, write }
        ),
        6 => Just(Step::Send),
        3 => (0..4usize).prop_map(Step::Reply),
        2 => (0..4usize).prop_map(Step::Timeout),
        1 => (0..4usize).prop_map(Step::Leave),
        1 => (1..3u8).prop_map(Step::BackOff),
        1 => Just(Step::PortLost),
    ]
}

/// A request's masters' tickets: (master, its number for that master).
fn tickets(r: &Req) -> Vec<(ConnId, u64)> {
    r.askers
        .iter()
        .map(|(c, l)| (*c, l.parse().expect("a number")))
        .collect()
}

/// The relay around the scheduler, as plain data: what went on the line for each
/// master, and how each master's request ended.
struct Run {
    s: Scheduler<Req>,
    max_in_flight: usize,
    retries: u32,
    /// Writes are resent too (`retry_writes`).
    retry_writes: bool,
    in_flight: Vec<Req>,
    /// The connection id of each master slot (a new one after a leave).
    conns: [ConnId; 4],
    /// Each slot's priority class (its new connection after a leave keeps it).
    classes: [u8; 4],
    next_conn: ConnId,
    /// Each master's requests sent so far.
    sent_by: HashMap<ConnId, u64>,
    /// What each master saw go on the line: its numbers in each request, and whether
    /// it acts, in order.
    seen: HashMap<ConnId, Vec<(Vec<u64>, bool)>>,
    /// Every ticket's ending (answered, or an exception), at most one each.
    ended: HashMap<(ConnId, u64), &'static str>,
    gone: Vec<ConnId>,
}

impl Run {
    fn new(depth: usize, max_in_flight: usize, retries: u32, flags: (bool, bool)) -> Run {
        let (coalesce, retry_writes) = flags;
        Run {
            s: Scheduler::new(depth, coalesce),
            max_in_flight,
            retries,
            retry_writes,
            in_flight: Vec::new(),
            conns: [1, 2, 3, 4],
            classes: [0; 4],
            next_conn: 5,
            sent_by: HashMap::new(),
            seen: HashMap::new(),
            ended: HashMap::new(),
            gone: Vec::new(),
        }
    }

    fn end(&mut self, r: &Req, how: &'static str) {
        for t in tickets(r) {
            let before = self.ended.insert(t, how);
            assert!(before.is_none(), "{t:?} ended twice: {before:?}, {how}");
        }
    }

    /// `r` goes on the line: for every master it answers, after everything that
    /// master sent before it, and before everything it sent after it; or again (a
    /// resend), behind nothing of that master's that came after it and could change
    /// its answer: no later request that acts, and none at all if it acts itself.
    fn on_line(&mut self, r: &Req) {
        let acts = r.reads.is_none();
        let mut by_master: HashMap<ConnId, Vec<u64>> = HashMap::new();
        for (c, n) in tickets(r) {
            by_master.entry(c).or_default().push(n);
        }
        for (c, numbers) in by_master {
            if self.gone.contains(&c) {
                continue; // it sees nothing any more
            }
            assert!(numbers.is_sorted(), "{c}: {numbers:?} within one request");
            let seen = self.seen.entry(c).or_default();
            let (first, last) = (numbers[0], numbers[numbers.len() - 1]);
            for (earlier, earlier_acts) in seen.iter() {
                let ok = if r.attempts == 0 {
                    earlier.iter().all(|&n| n < first)
                } else {
                    earlier.iter().all(|&n| n <= last) || !(acts || *earlier_acts)
                };
                assert!(
                    ok,
                    "master {c}: {numbers:?} (acts: {acts}, attempt {}) went on the line after {seen:?}",
                    r.attempts
                );
            }
            seen.push((numbers, acts));
        }
    }

    fn apply(&mut self, step: Step) {
        match step {
            Step::Arrive {
                master,
                unit,
                addr,
                write,
            } => {
                let conn = self.conns[master];
                let n = self.sent_by.entry(conn).or_default();
                *n += 1;
                let label = n.to_string();
                let r = if write {
                    Req(conn, unit, &label)
                } else {
                    read(conn, unit, addr, &label)
                };
                match self.s.push(r) {
                    Admitted::Queued | Admitted::Joined => {}
                    Admitted::Displaced(r) | Admitted::Refused(r) => self.end(&r, "0x06"),
                }
            }
            Step::Send => {
                if self.in_flight.len() < self.max_in_flight {
                    if let Some(r) = self.s.next() {
                        self.on_line(&r);
                        self.in_flight.push(r);
                    }
                }
            }
            Step::Reply(i) if !self.in_flight.is_empty() => {
                let r = self.in_flight.remove(i % self.in_flight.len());
                self.end(&r, "reply");
            }
            Step::Timeout(i) if !self.in_flight.is_empty() => {
                let mut r = self.in_flight.remove(i % self.in_flight.len());
                if (r.reads.is_some() || self.retry_writes) && r.attempts < self.retries {
                    r.attempts += 1;
                    if let Err(r) = self.s.resend(r) {
                        self.end(&r, "0x0B");
                    }
                } else {
                    self.end(&r, "0x0B");
                }
            }
            Step::Reply(_) | Step::Timeout(_) => {}
            Step::Leave(master) => {
                let conn = self.conns[master];
                self.s.detach(conn);
                self.gone.push(conn);
                self.conns[master] = self.next_conn;
                self.s.set_class(self.next_conn, self.classes[master]);
                self.next_conn += 1;
            }
            Step::BackOff(unit) => {
                for r in self.s.take_unit(unit) {
                    self.end(&r, "0x0B backed off");
                }
            }
            Step::PortLost => {
                for r in std::mem::take(&mut self.in_flight) {
                    self.end(&r, "0x0B port lost");
                }
                for r in self.s.drain_all() {
                    self.end(&r, "0x0A");
                }
            }
        }
        self.s.audit();
    }

    /// The line answers everything left: the scheduler always has a next request
    /// while it says one waits, and every master still connected gets an ending for
    /// every request it sent (one that left gets none for those dropped with it).
    fn finish(&mut self) {
        for r in std::mem::take(&mut self.in_flight) {
            self.end(&r, "reply");
        }
        let mut bound = 10_000;
        while self.s.has_waiting() {
            let r = self.s.next().expect("a request while some wait");
            self.on_line(&r);
            self.end(&r, "reply");
            bound -= 1;
            assert!(bound > 0, "no end");
        }
        assert_eq!(self.s.queued(), 0);
        for (&conn, &n) in &self.sent_by {
            if self.gone.contains(&conn) {
                continue;
            }
            for i in 1..=n {
                assert!(
                    self.ended.contains_key(&(conn, i)),
                    "{conn}:{i} never ended"
                );
            }
        }
    }
}

/// Random interleavings of arrivals (reads and writes, identical reads that join),
/// sends, replies, timeouts and resends, masters leaving, a full queue's evictions, a
/// unit backed off and the port lost: every master sees its requests go on the line
/// in the order it sent them (a resend repeating the last only), every ticket ends
/// once, and nothing is stuck; with the masters in priority classes or not.
/// `MBGATE_LONG=1`: many more runs.
#[test]
fn each_master_sees_its_own_order_through_every_path() {
    let cases = if std::env::var_os("MBGATE_LONG").is_some() {
        50_000
    } else {
        600
    };
    let config = ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    };
    let flags = (prop::bool::weighted(0.85), prop::bool::ANY);
    let params = (3..9usize, 1..4usize, 0..3u32, flags);
    let steps = prop::collection::vec(step(), 1..80);
    let classes = prop_oneof![Just([0u8; 4]), prop::array::uniform4(0..3u8)];
    proptest!(config, |((depth, max_in_flight, retries, flags) in params, steps in steps, classes in classes)| {
        let mut run = Run::new(depth, max_in_flight, retries, flags);
        run.classes = classes;
        for (i, &c) in classes.iter().enumerate() {
            run.s.set_class(run.conns[i], c);
        }
        for s in steps {
            run.apply(s);
        }
        run.finish();
    });
}

/// Masters in classes 0 to 2 queue reads at random (identical ones joined or not), and
/// the line takes them one by one: of the requests ready to go, one of the highest
/// class goes, except that while one serving a lower class is ready, no more than
/// LOWER_EVERY - 1 of the higher class go in a row; and within each master the order
/// holds.
#[test]
fn a_higher_class_goes_first_and_a_lower_one_gets_one_in_n() {
    let config = ProptestConfig {
        cases: if std::env::var_os("MBGATE_LONG").is_some() {
            20_000
        } else {
            300
        },
        failure_persistence: None,
        ..ProptestConfig::default()
    };
    // Each step: a request of master 1..=6, or a transaction.
    let step = prop_oneof![3 => (1..=6u64).prop_map(Some), 2 => Just(None)];
    let classes = prop::array::uniform6(0..3u8);
    proptest!(config, |(classes in classes, coalesce in prop::bool::ANY, steps in prop::collection::vec(step, 1..300))| {
        let mut s: Scheduler<Req> = Scheduler::new(1000, coalesce);
        let class = |c: ConnId| classes[(c - 1) as usize];
        for c in 1..=6u64 {
            s.set_class(c, class(c));
        }
        let mut sent: HashMap<ConnId, u64> = HashMap::new();
        let mut seen: HashMap<ConnId, u64> = HashMap::new();
        let mut streak = 0;
        for step in steps {
            match step {
                Some(c) => {
                    let n = sent.entry(c).or_default();
                    *n += 1;
                    // Reads of one register, some identical across masters (joined).
                    let _ = s.push(read(c, 1, (*n % 3) as u16, &n.to_string()));
                }
                None => {
                    // The requests ready to go: at the front of the queue of every
                    // master they serve (a joined read waits for each of its masters'
                    // earlier requests), with the lowest and highest class they serve.
                    let span = |n: u64| {
                        let r = &s.waiting.get(n).unwrap().req;
                        r.askers.iter().fold((u8::MAX, 0), |(lo, hi), (c, _)| {
                            (lo.min(class(*c)), hi.max(class(*c)))
                        })
                    };
                    let of = |r: &Req| r.askers.iter().fold((u8::MAX, 0), |(lo, hi), (c, _)| {
                        (lo.min(class(*c)), hi.max(class(*c)))
                    });
                    // Held alone, it is the one ready.
                    let ready: Vec<(u8, u8)> = match &s.lone {
                        Some(r) => vec![of(r)],
                        None => s
                            .queues
                            .values()
                            .filter_map(|q| q.front().copied())
                            .filter(|n| {
                                s.waiting.get(*n).unwrap().req.askers.iter().all(|(c, _)| s.queues[c].front() == Some(n))
                            })
                            .map(span)
                            .collect(),
                    };
                    let mut waiting: Vec<u8> = s.queues.keys().map(|&c| class(c)).collect();
                    waiting.extend(s.lone.iter().map(|r| of(r).1));
                    let Some(r) = s.next() else {
                        prop_assert!(waiting.is_empty());
                        continue;
                    };
                    let (lo, hi) = r.askers.iter().fold((u8::MAX, 0), |(lo, hi), (c, _)| {
                        (lo.min(class(*c)), hi.max(class(*c)))
                    });
                    let top = ready.iter().map(|(_, hi)| *hi).max().unwrap_or(0);
                    let lower_waits = ready.iter().any(|(lo, _)| *lo < top);
                    if lo < top {
                        streak = 0; // a lower class served
                    } else if lower_waits {
                        streak += 1;
                    } else {
                        streak = 0;
                    }
                    prop_assert!(
                        hi == top || lo < top,
                        "class {hi} went while class {top} waited"
                    );
                    prop_assert!(streak < LOWER_EVERY, "a lower class waited {streak} in a row");
                    for (c, label) in &r.askers {
                        let n: u64 = label.parse().unwrap();
                        let last = seen.insert(*c, n).unwrap_or(0);
                        prop_assert!(n > last, "master {c}: {n} after {last}");
                    }
                }
            }
        }
    });
}
