//! The RTU and ASCII line's tests: a reply with pauses inside on a pty and on a wire,
//! the gap after a reply (over TCP, to the microsecond, `request_pause_ms`, a unit's own),
//! the drain, and the loop's wakes while a request waits after a timeout.

use super::super::{LineFraming, Seen};
use super::*;
use crate::line::port::kind::Medium;
use crate::line::relay::inflight::OnLine;

const MS: Duration = Duration::from_millis(1);
const US: Duration = Duration::from_micros(1);

/// A wire: a UART that tells when a byte came within a character (FIFO trigger 1).
fn uart() -> Medium {
    Medium::Uart {
        driver: None,
        trigger: Some(1),
    }
}

/// A reply whose bytes come 5 ms apart at 115 200 baud (43 character times): on a
/// pty a partial reply of known length waits for the frame gap, so it is taken
/// whole (once the line has been quiet after it); on a wire 3.5 characters of
/// silence end it, and it fails its CRC.
#[test]
fn an_rtu_reply_with_pauses_inside_is_taken_where_there_is_no_wire() {
    use crate::line::relay::inflight::OnLine;
    let serial = SerialConfig {
        baud_rate: 115_200,
        framing: crate::config::Framing::Rtu,
        ..SerialConfig::default()
    };
    for (kind, taken) in [(Medium::Pty, true), (uart(), false)] {
        let stats = Stats::default();
        let t0 = Instant::now();
        let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
        line.port_opened(&PortInfo::plain(kind.clone()));
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let key = line.allocate(t0);
        line.encode(&read, key, t0, &stats);
        line.wrote(8, t0, t0);
        line.drained(t0 + MS, &stats);
        let f = [OnLine {
            tid: key,
            deadline: t0 + Duration::from_secs(1),
            timeout: Duration::from_secs(1),
            req: (read.clone(), 0u32),
        }];
        let reply = Codec::Rtu.encode(1, &[3, 2, 0, 7]);
        let mut got = Vec::new();
        let mut look = |line: &mut LineFraming, at| {
            got.extend(line.frames(&f, at, &stats).into_iter().map(|s| match s {
                Seen::Frame(frame, _) => Some(frame.pdu().to_vec()),
                Seen::Corrupt(_) => None,
                Seen::Heard(_) => panic!("nothing is owed"),
            }));
        };
        let mut last = t0;
        for (i, b) in reply.iter().enumerate() {
            last = t0 + (5 * i as u32 + 2) * MS;
            line.received(&[*b], last, &stats);
            look(&mut line, last + 4 * MS);
        }
        look(&mut line, last + 10 * MS);
        if taken {
            assert_eq!(got, vec![Some(vec![3, 2, 0, 7])], "{kind:?}");
        } else {
            assert!(got.first() == Some(&None), "{kind:?}: {got:?}");
        }
    }
}

/// RTU at 9600 baud: the next request waits 3.5 characters (4 ms) after a reply on
/// a serial line, none over TCP; `request_pause_ms` stretches the wait on both.
#[test]
fn the_gap_after_a_reply_is_none_over_tcp_and_request_pause_ms_on_both() {
    let serial = SerialConfig {
        baud_rate: 9600,
        framing: crate::config::Framing::Rtu,
        ..SerialConfig::default()
    };
    let stats = Stats::default();
    for (stream, pause, free_after) in
        [(false, 0, 4), (true, 0, 0), (true, 20, 20), (false, 20, 20)]
    {
        let relay = RelayConfig {
            request_pause_ms: pause,
            ..RelayConfig::default()
        };
        let t0 = Instant::now();
        let mut line = LineFraming::new(&relay, &serial, stream, t0);
        line.received(&[1, 3, 2, 0, 7, 0, 0], t0 + MS, &stats);
        let at = t0 + MS;
        let free = at + free_after * MS;
        let before = free.checked_sub(MS).filter(|b| *b >= at);
        if let Some(before) = before {
            assert!(!line.has_room(0, false, before), "{stream} {pause}");
        }
        assert!(line.has_room(0, false, free), "{stream} {pause}");
    }
}

/// A unit's own pause (`[[line.unit]] request_pause_ms`), set for the request about
/// to be sent, is the quiet time after that transaction, longer or shorter than the
/// line's; after a timeout too.
#[test]
fn a_units_own_pause_is_the_quiet_after_its_transaction() {
    let serial = SerialConfig {
        baud_rate: 9600,
        framing: crate::config::Framing::Rtu,
        ..SerialConfig::default()
    };
    let relay = RelayConfig {
        request_pause_ms: 20,
        timeout_guard_ms: 0,
        ..RelayConfig::default()
    };
    let stats = Stats::default();
    for (pause, free_after) in [(50, 50), (0, 4)] {
        let t0 = Instant::now();
        let mut line = LineFraming::new(&relay, &serial, false, t0);
        line.pause_after(pause * MS);
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let key = line.allocate(t0);
        line.encode(&read, key, t0, &stats);
        line.wrote(8, t0, t0);
        line.drained(t0, &stats);
        line.received(&[1, 3, 2, 0, 7, 0, 0], t0 + 10 * MS, &stats);
        let free = t0 + 10 * MS + free_after * MS;
        assert!(!line.has_room(0, false, free - MS), "pause {pause:?}");
        assert!(line.has_room(0, false, free), "pause {pause:?}");
        // A timeout: quiet for the pause (the guard is 0 here).
        let t1 = free + 100 * MS;
        line.timed_out(t1, Duration::ZERO, &stats);
        assert_eq!(
            line.has_room(0, false, t1 + (pause * MS).saturating_sub(MS)),
            pause == 0
        );
    }
}
/// The gap the line asks its timer for after a whole reply, to the microsecond:
/// 3.5 character times (1750 µs above 19 200 baud, 3646 µs at 9600), or
/// `inter_frame_gap_us`, or for ASCII none; not a microsecond less (the relay's
/// timer is armed for `next_wake`, and `has_room` says when it may write).
#[test]
fn the_gap_after_a_reply_is_asked_to_the_microsecond() {
    let us = Duration::from_micros;
    let stats = Stats::default();
    for (framing, baud, gap_us, gap) in [
        (crate::config::Framing::Rtu, 115_200, 0, us(1750)),
        (crate::config::Framing::Rtu, 9600, 0, us(3646)),
        (crate::config::Framing::Rtu, 115_200, 400, us(400)),
        (crate::config::Framing::Ascii, 115_200, 0, Duration::ZERO),
    ] {
        let serial = SerialConfig {
            baud_rate: baud,
            framing,
            inter_frame_gap_us: gap_us,
            ..SerialConfig::default()
        };
        let relay = RelayConfig::default();
        let t0 = Instant::now();
        let mut line = LineFraming::new(&relay, &serial, false, t0);
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let tid = line.allocate(t0);
        let bytes = line.encode(&read, tid, t0, &stats);
        line.wrote(bytes.len(), t0, t0);
        let left = line.drained(t0 + 50 * MS, &stats);
        let reply = match framing {
            crate::config::Framing::Ascii => crate::frame::ascii::encode(1, &[3, 2, 0, 7]),
            _ => rtu::encode(1, &[3, 2, 0, 7]),
        };
        let at = left + 10 * MS;
        line.received(&reply, at, &stats);
        let asked = OnLine {
            tid,
            deadline: at + Duration::from_secs(1),
            timeout: Duration::from_secs(1),
            req: (read.clone(), 0),
        };
        // Taken once the line has been quiet after it (the silence that ends a frame,
        // on a wire).
        let seen = line.frames(&[asked], at + 50 * MS, &stats);
        assert!(matches!(seen[..], [Seen::Frame(..)]), "the reply is taken");
        let why = format!("{framing:?} at {baud} baud, inter_frame_gap_us {gap_us}");
        if gap.is_zero() {
            assert!(line.has_room(0, false, at), "{why}");
            assert_eq!(line.next_wake(at, true), None, "{why}");
        } else {
            assert_eq!(line.next_wake(at, true), Some(at + gap), "{why}");
            assert!(!line.has_room(0, false, at + gap - us(1)), "{why}");
            assert!(line.has_room(0, false, at + gap), "{why}");
        }
    }
}

/// Where there is no wire (a pty) the next RTU request follows a whole reply at once:
/// nothing can collide there. A wire keeps its 3.5 characters, a set
/// `inter_frame_gap_us` is kept on a pty too, and bytes still arriving (a partial
/// frame) are waited out on both.
#[test]
fn no_gap_after_a_whole_reply_where_there_is_no_wire() {
    let us = Duration::from_micros;
    let stats = Stats::default();
    for (kind, gap_us, gap) in [
        (Medium::Pty, 0, Duration::ZERO),
        (uart(), 0, us(1750)),
        (Medium::Pty, 400, us(400)),
    ] {
        let serial = SerialConfig {
            baud_rate: 115_200,
            framing: crate::config::Framing::Rtu,
            inter_frame_gap_us: gap_us,
            ..SerialConfig::default()
        };
        let t0 = Instant::now();
        let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
        line.port_opened(&PortInfo::plain(kind.clone()));
        let why = format!("{kind:?}, inter_frame_gap_us {gap_us}");
        let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
        let tid = line.allocate(t0);
        let bytes = line.encode(&read, tid, t0, &stats);
        line.wrote(bytes.len(), t0, t0);
        let left = line.drained(t0 + MS, &stats);
        let at = left + MS;
        line.received(&rtu::encode(1, &[3, 2, 0, 7]), at, &stats);
        let asked = OnLine {
            tid,
            deadline: at + Duration::from_secs(1),
            timeout: Duration::from_secs(1),
            req: (read.clone(), 0),
        };
        let seen = line.frames(&[asked], at + 10 * MS, &stats);
        assert!(
            matches!(seen[..], [Seen::Frame(..)]),
            "{why}: the reply is taken"
        );
        if gap.is_zero() {
            assert!(line.has_room(0, false, at), "{why}");
        } else {
            assert!(!line.has_room(0, false, at + gap - us(1)), "{why}");
            assert!(line.has_room(0, false, at + gap), "{why}");
        }
        // Half a frame arriving: waited out as on a wire (3.5 characters of silence,
        // or the gap that is set), on a pty too.
        let later = at + 10 * MS;
        line.received(&[1, 3], later, &stats);
        let partial = if gap_us > 0 { us(gap_us) } else { us(1750) };
        assert!(!line.has_room(0, false, later + partial - us(1)), "{why}");
        assert!(line.has_room(0, false, later + partial), "{why}");
    }
}

/// `tcdrain` is asked for only where the port can send a request later than its time
/// on the wire after the write: on a wire with flow control or in the kernel's RS-485
/// mode. A plain wire and a pty are timed by the write and the wire's arithmetic.
#[test]
fn the_drain_is_asked_for_only_where_the_port_can_hold_bytes_back() {
    use crate::config::FlowControl::{Hardware, None as Free, Software};
    let port = |flow_control, rs485| SerialConfig {
        framing: crate::config::Framing::Rtu,
        flow_control,
        rs485,
        ..SerialConfig::default()
    };
    let cases = [
        (port(Free, false), Medium::Pty, false),
        (port(Free, false), uart(), false),
        (port(Hardware, false), uart(), true),
        (port(Software, false), uart(), true),
        (port(Free, true), uart(), true),
        (port(Hardware, false), Medium::Pty, false),
    ];
    for (serial, medium, drains) in cases {
        let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, Instant::now());
        line.port_opened(&PortInfo::plain(medium.clone()));
        assert_eq!(
            line.needs_drain(),
            drains,
            "flow {:?}, rs485 {}, {medium:?}",
            serial.flow_control,
            serial.rs485
        );
    }
}

/// Without the drain, the reply timer starts when the request's last byte leaves by
/// the wire's arithmetic (written at t0, 8 bytes at 9600 baud: 8.33 ms later), and a
/// byte read before then is not the reply.
#[test]
fn without_the_drain_the_request_leaves_its_wire_time_after_the_write() {
    let serial = SerialConfig {
        baud_rate: 9600,
        framing: crate::config::Framing::Rtu,
        flow_control: crate::config::FlowControl::None,
        ..SerialConfig::default()
    };
    let stats = Stats::default();
    let t0 = Instant::now();
    let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
    line.port_opened(&PortInfo::plain(uart()));
    assert!(!line.needs_drain());
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    let key = line.allocate(t0);
    line.encode(&read, key, t0, &stats);
    line.wrote(8, t0, t0);
    // An echo of the first byte, read while the request is still on the wire.
    line.received(&[0x01], t0 + 2 * MS, &stats);
    let left = line.drained(t0, &stats);
    assert_eq!((left - t0).as_micros(), 8 * 10 * 1_000_000 / 9600);
    assert_eq!(
        stats
            .dropped_too_early
            .load(std::sync::atomic::Ordering::Relaxed),
        1
    );
}

/// A line on a port of `kind` whose read, sent at once, timed out 1 s later: the line,
/// and the instant it timed out.
fn timed_out(
    relay: &RelayConfig,
    serial: &SerialConfig,
    kind: Medium,
    stats: &Stats,
) -> (LineFraming, Instant) {
    let t0 = Instant::now();
    let mut line = LineFraming::new(relay, serial, false, t0);
    line.port_opened(&PortInfo::plain(kind));
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    let key = line.allocate(t0);
    let bytes = line.encode(&read, key, t0, stats);
    line.wrote(bytes.len(), t0, t0);
    line.drained(t0, stats);
    let t1 = t0 + 1000 * MS;
    line.timed_out(t1, Duration::ZERO, stats);
    (line, t1)
}

/// A request waits for the guard after a timeout; the late reply comes within the
/// guard, and the turn that read it ends after the silence that ends it (a busy
/// machine). The loop is woken at once to drop it, then at the guard's end: never
/// left asleep with a request waiting (docs/reliability.md "RTU and ASCII").
#[test]
fn a_request_waiting_for_the_guard_is_woken_when_stray_bytes_ended_before_the_turn() {
    use crate::line::relay::inflight::OnLine;
    let guard = 1500 * MS;
    let relay = RelayConfig {
        timeout_guard_ms: 1500,
        ..RelayConfig::default()
    };
    let none: &[OnLine<(Adu, u32)>] = &[];
    for (framing, codec) in [
        (crate::config::Framing::Rtu, Codec::Rtu),
        (crate::config::Framing::Ascii, Codec::Ascii),
    ] {
        let serial = SerialConfig {
            framing,
            ..SerialConfig::default()
        };
        for kind in [Medium::Pty, uart()] {
            let why = format!("{framing:?} on {kind:?}");
            let stats = Stats::default();
            let (mut line, t1) = timed_out(&relay, &serial, kind, &stats);
            let late = t1 + 300 * MS;
            line.received(&codec.encode(1, &[3, 2, 0, 7]), late, &stats);
            // The turn that read it ends well past the silence that ends it (1.82 ms
            // on a pty at 19 200 baud; a UART's floor is a few ms more).
            let now = late + 100 * MS;
            let wake = line.next_wake(now, true);
            assert!(wake.is_some_and(|w| w <= now), "{why}: {wake:?}");
            assert!(line.frames(none, now, &stats).is_empty(), "{why}");
            assert_eq!(line.next_wake(now, true), Some(t1 + guard), "{why}");
            assert!(!line.has_room(0, false, t1 + guard - MS), "{why}");
            assert!(line.has_room(0, false, t1 + guard), "{why}");
        }
    }
}

proptest::proptest! {
    #![proptest_config(proptest::test_runner::Config {
        failure_persistence: None,
        ..Default::default()
    })]

    /// The loop's invariant on a line with nothing in flight and a request waiting:
    /// until the line has room, `next_wake` gives an instant, and waking there (or at
    /// once, for one that has passed) and looking at the line moves it on; within a few
    /// wakes the request may go. Stray bytes of any content in any chunks, at any time
    /// after a timeout, looked at any time later; RTU and ASCII, pty and wire.
    #[test]
    fn a_waiting_request_always_has_a_wake_and_the_line_frees(
        rtu in proptest::bool::ANY,
        wire in proptest::bool::ANY,
        guard_ms in 0u64..3000,
        pause_ms in 0u64..50,
        chunks in proptest::collection::vec(
            (0u64..4000, proptest::collection::vec(proptest::num::u8::ANY, 1..12)),
            0..5,
        ),
        late_us in 0u64..10_000,
    ) {
        use crate::line::relay::inflight::OnLine;
        let none: &[OnLine<(Adu, u32)>] = &[];
        let framing = if rtu {
            crate::config::Framing::Rtu
        } else {
            crate::config::Framing::Ascii
        };
        let relay = RelayConfig {
            timeout_guard_ms: guard_ms,
            request_pause_ms: pause_ms,
            ..RelayConfig::default()
        };
        let serial = SerialConfig { framing, ..SerialConfig::default() };
        let stats = Stats::default();
        let kind = if wire { uart() } else { Medium::Pty };
        let (mut line, t1) = timed_out(&relay, &serial, kind, &stats);
        let mut at = t1;
        for (after_us, bytes) in &chunks {
            at += Duration::from_micros(*after_us);
            line.received(bytes, at, &stats);
        }
        let mut now = at + Duration::from_micros(late_us);
        let mut wakes = 0;
        while !line.has_room(0, false, now) {
            let wake = line.next_wake(now, true);
            proptest::prop_assert!(wake.is_some(), "asleep with a request waiting at {:?}", now - t1);
            wakes += 1;
            proptest::prop_assert!(wakes <= 4, "still no room after {} wakes", wakes);
            now = now.max(wake.unwrap());
            line.frames(none, now, &stats);
        }
    }
}

/// A line in `framing` on a port of `kind`, opened at the instant returned.
fn opened(framing: crate::config::Framing, kind: Medium) -> (LineFraming, Instant) {
    let serial = SerialConfig {
        framing,
        ..SerialConfig::default()
    };
    let t0 = Instant::now();
    let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
    line.port_opened(&PortInfo::plain(kind));
    (line, t0)
}

/// `read` put on the line at `at` and gone at once (a pty): the request as the line
/// sees it, with a response timeout of 10 s.
fn ask(line: &mut LineFraming, read: &Adu, at: Instant, stats: &Stats) -> [OnLine<(Adu, u32)>; 1] {
    let key = line.allocate(at);
    let bytes = line.encode(read, key, at, stats);
    line.wrote(bytes.len(), at, at);
    line.drained(at, stats);
    [OnLine {
        tid: key,
        deadline: at + Duration::from_secs(10),
        timeout: Duration::from_secs(10),
        req: (read.clone(), 0),
    }]
}

/// What the line made of its bytes, as text for the assertions: `frame PDU`,
/// `refused`, `heard UNIT`.
fn seen(seen: Vec<Seen>) -> Vec<String> {
    seen.into_iter()
        .map(|s| match s {
            Seen::Frame(f, _) => format!("frame {}", crate::frame::hex::Hex(f.pdu())),
            Seen::Corrupt(_) => "refused".into(),
            Seen::Heard(u) => format!("heard {u}"),
        })
        .collect()
}

const FRAMINGS: [(crate::config::Framing, Codec); 2] = [
    (crate::config::Framing::Rtu, Codec::Rtu),
    (crate::config::Framing::Ascii, Codec::Ascii),
];

/// A device that stalled answers its backlog when it resumes: three reads to unit 1
/// timed out (the unit owes three answers), and of the four frames that come for the
/// next read, 900 ms apart (within the unit's response timeout of each other), the
/// first is held for the unit's whole response timeout and shown by the second to be
/// one it owed; the first three pay what it owes and are dropped; the fourth, the
/// read's own, is taken once the line has been quiet after it. Paid up, the unit's
/// next reply is taken as any. Owing again, a frame that fits no read (an FC 16 echo)
/// pays at once, rather than refusing the read; owing nothing, such a frame refuses
/// it at once (docs/reliability.md "RTU and ASCII", 5 and 6).
#[test]
fn a_stalled_devices_backlog_never_answers_the_request_on_the_line() {
    let whole = Duration::from_secs(1);
    for (framing, codec) in FRAMINGS {
        let stats = Stats::default();
        let (mut line, t0) = opened(framing, Medium::Pty);
        let read = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
        let mut at = t0;
        for _ in 0..3 {
            ask(&mut line, &read, at, &stats);
            line.timed_out(at + whole, Duration::ZERO, &stats);
            line.unanswered(1, at, whole, at + whole);
            at += whole + 100 * MS;
        }
        let f = ask(&mut line, &read, at, &stats);
        let paid: [&[&str]; 3] = [&[], &["heard 1", "heard 1"], &["heard 1"]];
        for (i, v) in [8u8, 9, 10].into_iter().enumerate() {
            let came = at + (10 + 900 * i as u32) * MS;
            line.received(&codec.encode(1, &[3, 2, 0, v]), came, &stats);
            assert_eq!(
                seen(line.frames(&f, came + MS, &stats)),
                paid[i],
                "{framing:?} {i}"
            );
            if i == 0 {
                // Held until the unit has been quiet for its whole response timeout.
                assert_eq!(line.confirming(), Some((f[0].tid, came + whole)));
            }
        }
        let own = at + 2710 * MS;
        line.received(&codec.encode(1, &[3, 2, 0, 5]), own, &stats);
        assert!(
            line.frames(&f, own + 4 * MS, &stats).is_empty(),
            "{framing:?}: not yet quiet"
        );
        assert_eq!(line.next_wake(own + 4 * MS, false), Some(own + PTY_QUIET));
        match line.frames(&f, own + PTY_QUIET, &stats).as_slice() {
            [Seen::Frame(frame, came)] => {
                assert_eq!(frame.pdu(), [3, 2, 0, 5], "{framing:?}");
                assert_eq!(*came, own);
            }
            _ => panic!("{framing:?}: the read's own answer not taken"),
        }
        assert_eq!(stats.get(&stats.late_replies), 3, "{framing:?}");
        assert_eq!(stats.get(&stats.bad_frames), 0, "{framing:?}");
        // Paid up: the next reply is taken once quiet.
        let t3 = own + 200 * MS;
        let f = ask(&mut line, &read, t3, &stats);
        line.received(&codec.encode(1, &[3, 2, 0, 5]), t3 + MS, &stats);
        let got = seen(line.frames(&f, t3 + MS + PTY_QUIET, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
        // Owing one again: an FC 16 echo pays it, the read's own reply answers it.
        let t4 = t3 + 200 * MS;
        line.unanswered(1, t4 - 150 * MS, whole, t4 - 50 * MS);
        let f = ask(&mut line, &read, t4, &stats);
        line.received(&codec.encode(1, &[0x10, 0, 9, 0, 1]), t4 + MS, &stats);
        assert_eq!(
            seen(line.frames(&f, t4 + MS, &stats)),
            ["heard 1"],
            "{framing:?}"
        );
        line.received(&codec.encode(1, &[3, 2, 0, 5]), t4 + 2 * MS, &stats);
        let got = seen(line.frames(&f, t4 + 2 * MS + PTY_QUIET, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
        // Owing nothing: the echo refuses the read at once.
        let t5 = t4 + 200 * MS;
        let f = ask(&mut line, &read, t5, &stats);
        line.received(&codec.encode(1, &[0x10, 0, 9, 0, 1]), t5 + MS, &stats);
        assert_eq!(
            seen(line.frames(&f, t5 + MS, &stats)),
            ["refused"],
            "{framing:?}"
        );
        assert_eq!(stats.get(&stats.late_replies), 4, "{framing:?}");
    }
}

/// A unit that owes more than it will ever send (requests it never read: a device
/// that was off): its next reply is held for its whole response timeout, and with
/// nothing after it, it is the answer, and the unit owes nothing more. Never one
/// answer behind for good (docs/reliability.md "RTU and ASCII", 6). If that read
/// times out first (a probe's shorter timeout), the frame held is dropped and the
/// read is owed too: the next reply is held the same way, and taken.
#[test]
fn a_unit_quiet_for_its_whole_response_timeout_owes_nothing_asked_before() {
    let whole = Duration::from_secs(1);
    for (framing, codec) in FRAMINGS {
        let stats = Stats::default();
        let (mut line, t0) = opened(framing, Medium::Pty);
        let read = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
        for i in 0..3 {
            let at = t0 + i * 1100 * MS;
            ask(&mut line, &read, at, &stats);
            line.timed_out(at + whole, Duration::ZERO, &stats);
            line.unanswered(1, at, whole, at + whole);
        }
        let t1 = t0 + 3300 * MS;
        let f = ask(&mut line, &read, t1, &stats);
        let reply = codec.encode(1, &[3, 2, 0, 5]);
        line.received(&reply, t1 + 5 * MS, &stats);
        assert!(
            line.frames(&f, t1 + 5 * MS, &stats).is_empty(),
            "{framing:?}"
        );
        assert!(
            line.frames(&f, t1 + 5 * MS + whole - US, &stats).is_empty(),
            "{framing:?}"
        );
        let got = seen(line.frames(&f, t1 + 5 * MS + whole, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
        let t2 = t1 + 2 * whole;
        let f = ask(&mut line, &read, t2, &stats);
        line.received(&reply, t2 + 5 * MS, &stats);
        let got = seen(line.frames(&f, t2 + 5 * MS + PTY_QUIET, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}: owes nothing");
        // Owing again; the read times out before its reply is confirmed.
        line.unanswered(1, t2 - 100 * MS, whole, t2 - 50 * MS);
        let t3 = t2 + 200 * MS;
        let f = ask(&mut line, &read, t3, &stats);
        line.received(&reply, t3 + 5 * MS, &stats);
        assert!(
            line.frames(&f, t3 + 5 * MS, &stats).is_empty(),
            "{framing:?}"
        );
        line.timed_out(t3 + 250 * MS, Duration::ZERO, &stats);
        line.unanswered(1, t3, whole, t3 + 250 * MS);
        let t4 = t3 + 400 * MS;
        let f = ask(&mut line, &read, t4, &stats);
        line.received(&reply, t4 + 5 * MS, &stats);
        assert!(line.frames(&f, t4 + 5 * MS + PTY_QUIET, &stats).is_empty());
        let got = seen(line.frames(&f, t4 + 5 * MS + whole, &stats));
        assert_eq!(
            got,
            ["frame 03 02 00 05"],
            "{framing:?}: taken after the quiet"
        );
    }
}

/// One frame too many: a reply-shaped frame just before or after the real reply.
/// Whichever comes first is held until the line has been quiet after it; the other
/// within that quiet refutes it, and the request is refused (0x0B): on a pty 2 ms
/// apart (its quiet is `PTY_QUIET`), on a wire 1 ms apart (its quiet is the silence
/// that ends a frame, 1.75 ms at 115 200 baud). A reply with nothing after it is
/// taken once the quiet has passed and not before (docs/reliability.md "RTU and
/// ASCII", 7).
#[test]
fn a_reply_followed_within_its_quiet_by_another_frame_is_refuted_with_it() {
    for (framing, codec) in FRAMINGS {
        for (kind, apart, quiet) in [(Medium::Pty, 2 * MS, PTY_QUIET), (uart(), MS, 1750 * US)] {
            let why = format!("{framing:?} on {kind:?}");
            let stats = Stats::default();
            let serial = SerialConfig {
                framing,
                baud_rate: 115_200,
                ..SerialConfig::default()
            };
            let t0 = Instant::now();
            let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
            line.port_opened(&PortInfo::plain(kind.clone()));
            let read = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
            let (real, extra) = (
                codec.encode(1, &[3, 2, 0, 5]),
                codec.encode(1, &[3, 2, 0, 4]),
            );
            let mut at = t0;
            for (first, second) in [(&extra, &real), (&real, &extra)] {
                let f = ask(&mut line, &read, at, &stats);
                line.received(first, at + 20 * MS, &stats);
                assert!(line.frames(&f, at + 20 * MS, &stats).is_empty(), "{why}");
                let next = at + 20 * MS + apart;
                assert!(line.frames(&f, next - US, &stats).is_empty(), "{why}");
                line.received(second, next, &stats);
                assert_eq!(seen(line.frames(&f, next, &stats)), ["refused"], "{why}");
                line.timed_out(next, Duration::ZERO, &stats);
                // What is left of it answers nothing.
                let none: &[OnLine<(Adu, u32)>] = &[];
                assert!(line.frames(none, at + 40 * MS, &stats).is_empty(), "{why}");
                at += 200 * MS;
            }
            assert_eq!(stats.get(&stats.refuted_frames), 2, "{why}");
            let f = ask(&mut line, &read, at, &stats);
            line.received(&real, at + 20 * MS, &stats);
            assert!(line.frames(&f, at + 20 * MS, &stats).is_empty(), "{why}");
            let (_, until) = line.confirming().expect("held");
            assert_eq!(until, at + 20 * MS + quiet, "{why}");
            assert!(line.frames(&f, until - US, &stats).is_empty(), "{why}");
            assert_eq!(
                seen(line.frames(&f, until, &stats)),
                ["frame 03 02 00 05"],
                "{why}"
            );
        }
    }
}

/// The tail of the last transaction: once the unit has had its replies taken at
/// 20 ms, a frame of the right shape 2 ms after the next request left cannot be its
/// reply (sooner than half the unit's fastest), and is dropped; the real one after
/// it is taken. A unit that turns that much faster has the first such reply refused:
/// its request times out, and the next reply, held for the unit's whole response
/// timeout as any after a timeout, is taken and teaches the new pace.
#[test]
fn a_frame_sooner_than_its_unit_can_answer_is_not_the_reply() {
    for (framing, codec) in FRAMINGS {
        let stats = Stats::default();
        let (mut line, t0) = opened(framing, Medium::Pty);
        let read = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
        let real = codec.encode(1, &[3, 2, 0, 5]);
        let mut at = t0;
        for _ in 0..owed::SETTLE {
            let f = ask(&mut line, &read, at, &stats);
            line.received(&real, at + 20 * MS, &stats);
            assert_eq!(
                line.frames(&f, at + 100 * MS, &stats).len(),
                1,
                "{framing:?}"
            );
            at += 200 * MS;
        }
        let f = ask(&mut line, &read, at, &stats);
        line.received(&codec.encode(1, &[3, 2, 0, 4]), at + 2 * MS, &stats);
        assert!(
            line.frames(&f, at + 10 * MS, &stats).is_empty(),
            "{framing:?}"
        );
        assert_eq!(
            stats.get(&stats.dropped_too_early),
            real.len() as u64,
            "{framing:?}"
        );
        line.received(&real, at + 20 * MS, &stats);
        assert_eq!(
            seen(line.frames(&f, at + 30 * MS, &stats)),
            ["frame 03 02 00 05"]
        );
        // Faster now: the 2 ms reply is refused, and the request times out.
        let whole = Duration::from_secs(1);
        at += 200 * MS;
        let f = ask(&mut line, &read, at, &stats);
        line.received(&real, at + 2 * MS, &stats);
        assert!(
            line.frames(&f, at + 10 * MS, &stats).is_empty(),
            "{framing:?}"
        );
        line.timed_out(at + whole, Duration::ZERO, &stats);
        line.unanswered(1, at, whole, at + whole);
        // The next, held for the whole timeout, is taken, and 2 ms is its pace now.
        at += whole + 100 * MS;
        let f = ask(&mut line, &read, at, &stats);
        line.received(&real, at + 2 * MS, &stats);
        let got = seen(line.frames(&f, at + 2 * MS + whole, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
        at += 200 * MS;
        let f = ask(&mut line, &read, at, &stats);
        line.received(&real, at + 2 * MS, &stats);
        let got = seen(line.frames(&f, at + 2 * MS + PTY_QUIET, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
    }
}

/// On a wire a reply's own time on it is no part of how soon its unit answers: a unit
/// whose first replies were long reads (200 bytes of registers, over 200 ms at 9600
/// baud) answers a one-register read 5 ms after the request too, and that reply, its
/// 7 bytes on the wire after those 5 ms, is taken, not dropped as sooner than the
/// unit can answer (its pace is the time from the request to the reply's first byte).
#[test]
fn a_short_reply_after_long_ones_is_judged_by_its_start_on_a_wire() {
    for (framing, codec) in FRAMINGS {
        let stats = Stats::default();
        let (mut line, t0) = opened(framing, uart());
        let cfg = SerialConfig {
            framing,
            ..SerialConfig::default()
        };
        let turnaround = 5 * MS;
        let long = Adu::build(1, 1, &[3, 0, 0, 0, 100]);
        let mut registers = vec![3, 200];
        registers.extend((0..200).map(|i| i as u8));
        let long_reply = codec.encode(1, &registers);
        let mut at = t0;
        for _ in 0..owed::SETTLE + 2 {
            let f = ask(&mut line, &long, at, &stats);
            let end = at + turnaround + kind::wire_time(&cfg, long_reply.len());
            line.received(&long_reply, end, &stats);
            assert_eq!(
                seen(line.frames(&f, end + 50 * MS, &stats)).len(),
                1,
                "{framing:?}"
            );
            at = end + 100 * MS;
        }
        let short = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
        let short_reply = codec.encode(1, &[3, 2, 0, 5]);
        let f = ask(&mut line, &short, at, &stats);
        let end = at + turnaround + kind::wire_time(&cfg, short_reply.len());
        line.received(&short_reply, end, &stats);
        let got = seen(line.frames(&f, end + 50 * MS, &stats));
        assert_eq!(got, ["frame 03 02 00 05"], "{framing:?}");
        assert_eq!(stats.get(&stats.dropped_too_early), 0, "{framing:?}");
    }
}

/// A device on an RTU line, as the property below draws it: it answers in order, each
/// request it read once (a read of register `a` with `a + 1000`), after its own delay,
/// one every `pace` after a stall, and some answers with one frame too many.
#[derive(Debug, Clone)]
struct Device {
    /// How long it takes to answer each request (µs, by the request's number, cycled):
    /// under the response timeout, or over it (a slow answer); but a request it held
    /// while it sent a frame is answered within the response timeout of that frame.
    delays: Vec<u64>,
    /// From the `n`th request on, the first that finds it idle, it stops reading
    /// for `stop` µs, then answers what waited one every `pace` µs, then what came
    /// meanwhile.
    stall: Option<(usize, u64, u64)>,
    /// Requests it never reads (by number), if they come while it is idle (lost on
    /// the line); one that comes while it is busy it reads after.
    lost: Vec<usize>,
    /// Answers sent with one frame too many (by request number): the frame of the
    /// register before, `gap` µs before (0) or after (1) its real one, within the
    /// quiet; or (2) after the quiet, sooner after the next request than half the
    /// unit's fastest reply taken, once replies are judged by it (and not the answer
    /// itself, which comes no sooner than that).
    extras: Vec<(usize, u8, u64)>,
}

/// Where a frame on the line came from: the answer to request `k`, or a frame too
/// many sent with it.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Origin {
    Answer(usize),
    Extra(usize),
}

/// The device's side as the line sees it: frames with when they arrive.
struct Sim {
    device: Device,
    /// Frames to come: (µs, bytes, origin), in the order they were made.
    out: Vec<(u64, Vec<u8>, Origin)>,
    /// When the device is next free to answer (µs).
    free: u64,
    /// When it sent its last frame (µs).
    sent: u64,
    /// The stall, once begun: when it ends, and how many waited in it.
    stalled: Option<(u64, usize)>,
    /// Whether the unit owes nothing by what the gateway saw: no timeout since its
    /// last reply taken (extra frames only then: the premise below).
    clear: bool,
    /// Replies taken so far, and the quickest and slowest of them (µs from its
    /// request leaving).
    taken: u32,
    fastest: u64,
    slowest: u64,
}

impl Sim {
    /// Request `k` was written at `w` µs.
    fn asked(&mut self, k: usize, w: u64) {
        if self.device.lost.contains(&k) && self.free <= w {
            return;
        }
        let value = |a: usize| {
            let v = (a as u16).wrapping_add(1000).to_be_bytes();
            Codec::Rtu.encode(1, &[3, 2, v[0], v[1]])
        };
        if let Some((n, stop, _)) = self.device.stall {
            if k >= n && self.stalled.is_none() && self.free <= w {
                self.stalled = Some((w + stop, 0));
            }
        }
        let t = match self.stalled {
            Some((end, waited)) if w < end => {
                self.stalled = Some((end, waited + 1));
                let pace = self.device.stall.expect("stalled").2;
                end + pace * (waited as u64 + 1)
            }
            _ => {
                let d = self.device.delays[k % self.device.delays.len()];
                let t = self.free.max(w) + d;
                // Held while the device sent its last frame: within the response
                // timeout of it (the premise).
                if w < self.sent {
                    t.min(self.sent + 199_000)
                } else {
                    t
                }
            }
        };
        self.free = self.free.max(t);
        let extra = self.device.extras.iter().find(|e| e.0 == k);
        let quiet = PTY_QUIET.as_micros() as u64;
        let half = self.fastest / 2;
        // An answer in time, from a unit that owes nothing, and one the gateway can
        // take for a reply (no sooner than half the fastest it took, once it judges
        // by that): only such an answer goes with a frame too many.
        let judged = self.taken >= owed::SETTLE && self.slowest < 2 * self.fastest;
        let reply = !judged || t - w > half;
        let at = match extra {
            Some(&(_, mode, gap))
                if self.clear
                    && reply
                    && t < w + 200_000
                    && self.stalled.is_none_or(|(end, _)| t < end) =>
            {
                match mode {
                    0 => Some(t.saturating_sub(gap).max(w + 1)),
                    1 => Some(t + gap),
                    // Past the quiet, in the next request's window (written as the
                    // reply is taken), sooner than half the fastest reply taken.
                    _ if judged
                        && half > owed::JITTER.as_micros() as u64
                        && t - w >= half + 500 =>
                    {
                        Some(t + quiet + 100 + gap % (half - 500))
                    }
                    _ => None,
                }
            }
            _ => None,
        };
        if let Some(at) = at {
            self.out
                .push((at, value(k.wrapping_sub(1)), Origin::Extra(k)));
            self.sent = self.sent.max(at);
        }
        self.sent = self.sent.max(t);
        self.out.push((t, value(k), Origin::Answer(k)));
        self.out.sort_by_key(|o| o.0);
    }
}

fn device() -> impl proptest::strategy::Strategy<Value = Device> {
    use proptest::prelude::*;
    // The response timeout is 200 ms; a slow answer takes up to 380 ms.
    let delay = prop_oneof![8 => 100u64..60_000, 1 => 210_000u64..380_000];
    (
        prop::collection::vec(delay, 1..8),
        prop::option::of((1usize..20, 250_000u64..1_500_000, 0u64..199_000)),
        prop::collection::vec(0usize..60, 0..3),
        prop::collection::vec((0usize..60, 0u8..3, 0u64..4_900), 0..6),
    )
        .prop_map(|(delays, stall, lost, extras)| Device {
            delays,
            stall,
            lost,
            extras,
        })
}

proptest::proptest! {
    #![proptest_config(proptest::test_runner::Config {
        failure_persistence: None,
        ..Default::default()
    })]

    /// The invariant of an RTU line's replies: no reply handed to a master is another
    /// request's answer or a frame too many: it is never a frame that came sooner after
    /// its request than its unit could answer, nor one followed within the quiet by
    /// another frame of its unit, nor, while its unit owes answers to requests that
    /// timed out, one the unit held for one of those. Over devices that answer in
    /// order, each request they read once (some they never read), after any delay
    /// (some past the response timeout), stall and then answer their backlog at any
    /// pace within the response timeout, and send one frame too many within the quiet
    /// of a reply, or after it but sooner than half their fastest reply taken, with an
    /// answer the gateway can take while they owe nothing. The premise of each:
    /// a request the device held when it sent a frame is answered within the response
    /// timeout of that frame (`Sim::asked`). The relay's loop driven as it drives the
    /// line (its guard any length, none included), on a pty. A device that does none
    /// of this has every request answered.
    #[test]
    fn no_reply_is_another_requests_answer_or_a_frame_too_many(
        device in device(),
        guard_ms in 0u64..150,
    ) {
        drive(device, guard_ms, false)?;
    }
}

/// The relay's loop over the line and the in-flight table, against `device`, for the
/// property above; `trace` prints what happened.
fn drive(
    device: Device,
    guard_ms: u64,
    trace: bool,
) -> Result<(), proptest::test_runner::TestCaseError> {
    let serial = SerialConfig {
        framing: crate::config::Framing::Rtu,
        ..SerialConfig::default()
    };
    let relay = RelayConfig {
        response_timeout_ms: 200,
        timeout_guard_ms: guard_ms,
        unit_backoff: false,
        ..RelayConfig::default()
    };
    let honest = device.stall.is_none()
        && device.lost.is_empty()
        && device.extras.is_empty()
        && device.delays.iter().all(|&d| d < 200_000);
    let tables = crate::config::unit::UnitTables::default();
    let mut in_flight: crate::line::relay::inflight::InFlight<(Adu, u32)> =
        crate::line::relay::inflight::InFlight::new(&relay, &tables, false);
    let stats = Stats::default();
    let t0 = Instant::now();
    let us = |t: u64| t0 + Duration::from_micros(t);
    let mut line = LineFraming::new(&relay, &serial, false, t0);
    line.port_opened(&PortInfo::plain(Medium::Pty));
    let mut sim = Sim {
        device,
        out: Vec::new(),
        free: 0,
        sent: 0,
        stalled: None,
        clear: true,
        taken: 0,
        fastest: u64::MAX,
        slowest: 0,
    };
    let n = 60;
    let (mut next, mut now, mut answered, mut failed) = (0usize, 0u64, 0, 0);
    // Each request's number by its key, and when each frame arrived.
    let mut keys = std::collections::HashMap::new();
    let mut arrived: Vec<(u64, Origin)> = Vec::new();
    let mut turns = 0;
    while answered + failed < n {
        turns += 1;
        proptest::prop_assert!(turns < 100_000, "the line stalled");
        // Dispatch, as the relay does when the line has room.
        if in_flight.is_empty() && next < n && line.has_room(0, false, us(now)) {
            let read = Adu::build(1, 1, &[3, (next >> 8) as u8, next as u8, 0, 1]);
            let key = line.allocate(us(now));
            let bytes = line.encode(&read, key, us(now), &stats);
            line.wrote(bytes.len(), us(now), us(now));
            let left = line.drained(us(now), &stats);
            in_flight.start(key, (read, 0), left, Duration::ZERO);
            keys.insert(key, next);
            sim.asked(next, now);
            next += 1;
        }
        // The next instant anything happens.
        let waiting = in_flight.is_empty() && next < n;
        let wake = [
            sim.out.first().map(|o| us(o.0)),
            in_flight.next_deadline(),
            line.next_wake(us(now), waiting),
        ]
        .into_iter()
        .flatten()
        .min();
        let Some(wake) = wake else {
            proptest::prop_assert!(false, "asleep with {} of {} done", answered + failed, n);
            unreachable!();
        };
        now = now.max((wake - t0).as_micros() as u64);
        while sim.out.first().is_some_and(|o| o.0 <= now) {
            let (at, bytes, origin) = sim.out.remove(0);
            line.received(&bytes, us(at), &stats);
            arrived.push((at, origin));
        }
        for s in line.frames(in_flight.entries(), us(now), &stats) {
            if trace {
                let what = match &s {
                    Seen::Frame(f, _) => format!("frame {}", crate::frame::hex::Hex(f.pdu())),
                    Seen::Corrupt(_) => "refused".into(),
                    Seen::Heard(_) => "heard".into(),
                };
                eprintln!("{now} µs: {what}");
            }
            match s {
                Seen::Frame(frame, at) => {
                    let f = in_flight.answered(frame.tid(), at).expect("on the line");
                    let k = keys[&f.tid];
                    let at_us = (at - t0).as_micros() as u64;
                    let origin = arrived.iter().rev().find(|a| a.0 == at_us).map(|a| a.1);
                    proptest::prop_assert_eq!(
                        frame.pdu(),
                        &[3, 2, ((k + 1000) >> 8) as u8, (k + 1000) as u8][..],
                        "request {} answered with {:?} at {} µs: {:?}",
                        k,
                        origin,
                        at_us,
                        arrived
                    );
                    // Nothing of its unit within the quiet after it.
                    let quiet = PTY_QUIET.as_micros() as u64;
                    let close = arrived
                        .iter()
                        .filter(|a| a.0 > at_us && a.0 < at_us + quiet)
                        .count();
                    proptest::prop_assert_eq!(close, 0);
                    answered += 1;
                    sim.clear = true;
                    sim.taken += 1;
                    let left = f.deadline - f.timeout;
                    let took = (at - left).as_micros() as u64;
                    sim.fastest = sim.fastest.min(took);
                    sim.slowest = sim.slowest.max(took);
                }
                Seen::Corrupt(tid) => {
                    if let Some(f) = in_flight.take(tid) {
                        let hold = in_flight.hold_after_timeout(&f);
                        line.timed_out(us(now), hold, &stats);
                        failed += 1;
                    }
                }
                Seen::Heard(_) => {}
            }
        }
        if let Some((tid, until)) = line.confirming() {
            in_flight.hold_until(tid, until);
        }
        for f in in_flight.take_expired(us(now)) {
            if trace {
                eprintln!("{now} µs: request {} timed out", keys[&f.tid]);
            }
            let hold = in_flight.hold_after_timeout(&f);
            line.timed_out(us(now), hold, &stats);
            let left = f.deadline - f.timeout;
            let whole = in_flight.whole_timeout(1).max(f.timeout);
            line.unanswered(1, left, whole, us(now));
            failed += 1;
            sim.clear = false;
        }
    }
    if honest {
        proptest::prop_assert_eq!(failed, 0, "an honest device got 0x0B");
    }
    Ok(())
}
