//! The RTU and ASCII line's tests: a reply with pauses inside on a pty and on a wire,
//! the gap after a reply (over TCP, to the microsecond, `request_pause_ms`, a unit's own),
//! the drain, and the loop's wakes while a request waits after a timeout.

use super::super::{LineFraming, Seen};
use super::*;
use crate::line::port::kind::Medium;
use crate::line::relay::inflight::OnLine;

const MS: Duration = Duration::from_millis(1);

/// A wire: a UART that tells when a byte came within a character (FIFO trigger 1).
fn uart() -> Medium {
    Medium::Uart {
        driver: None,
        trigger: Some(1),
    }
}

/// A reply whose bytes come 5 ms apart at 115 200 baud (43 character times): on a
/// pty a partial reply of known length waits for the frame gap, so it is taken
/// whole; on a wire 3.5 characters of silence end it, and it fails its CRC.
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
        for (i, b) in reply.iter().enumerate() {
            let at = t0 + (5 * i as u32 + 2) * MS;
            line.received(&[*b], at, &stats);
            got.extend(
                line.frames(&f, at + 4 * MS, &stats)
                    .into_iter()
                    .map(|s| match s {
                        Seen::Frame(frame, _) => Some(frame.pdu().to_vec()),
                        Seen::Corrupt(_) => None,
                    }),
            );
        }
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
        let seen = line.frames(&[asked], at, &stats);
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
        let seen = line.frames(&[asked], at, &stats);
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

/// A device that stalled answers its backlog when it resumes: after a request to unit
/// 1 timed out, the reads' answers that come back to back for the next read (two of
/// other registers, then the read's own) are the answers the device held; only the
/// last one, followed by the guard's silence, is taken, and the first reply after that
/// is taken at once again. A frame that does not fit the request (an FC 16 echo) is
/// refused at once, as ever (docs/reliability.md "RTU and ASCII", 5 and 6).
#[test]
fn a_stalled_devices_backlog_never_answers_the_request_on_the_line() {
    use crate::line::relay::inflight::OnLine;
    let relay = RelayConfig {
        timeout_guard_ms: 100,
        ..RelayConfig::default()
    };
    for (framing, codec) in [
        (crate::config::Framing::Rtu, Codec::Rtu),
        (crate::config::Framing::Ascii, Codec::Ascii),
    ] {
        let serial = SerialConfig {
            framing,
            ..SerialConfig::default()
        };
        let stats = Stats::default();
        let (mut line, t1) = timed_out(&relay, &serial, Medium::Pty, &stats);
        line.unanswered(1);
        let ask = |line: &mut LineFraming, at: Instant| {
            let read = Adu::build(1, 1, &[3, 0, 5, 0, 1]);
            let key = line.allocate(at);
            let bytes = line.encode(&read, key, at, &stats);
            line.wrote(bytes.len(), at, at);
            line.drained(at, &stats);
            [OnLine {
                tid: key,
                deadline: at + Duration::from_secs(1),
                timeout: Duration::from_secs(1),
                req: (read, 0u32),
            }]
        };
        let t2 = t1 + 200 * MS;
        let f = ask(&mut line, t2);
        let backlog = [
            codec.encode(1, &[3, 2, 0, 8]),
            codec.encode(1, &[3, 2, 0, 9]),
            codec.encode(1, &[3, 2, 0, 5]),
        ];
        for (i, frame) in backlog.iter().enumerate() {
            let at = t2 + (10 + 5 * i as u32) * MS;
            line.received(frame, at, &stats);
            let seen = line.frames(&f, at + MS, &stats);
            assert!(
                seen.is_empty(),
                "{framing:?}: frame {i} taken before the quiet"
            );
        }
        let last = t2 + 20 * MS;
        assert_eq!(line.next_wake(last + MS, false), Some(last + 100 * MS));
        assert!(line.frames(&f, last + 99 * MS, &stats).is_empty());
        match line.frames(&f, last + 100 * MS, &stats).as_slice() {
            [Seen::Frame(frame, at)] => {
                assert_eq!(frame.pdu(), [3, 2, 0, 5], "{framing:?}");
                assert_eq!(*at, last);
            }
            _ => panic!("{framing:?}: the read's own answer not taken"),
        }
        assert_eq!(stats.get(&stats.late_replies), 2, "{framing:?}");
        assert_eq!(stats.get(&stats.bad_frames), 0, "{framing:?}");
        // Confirmed: the unit owes nothing, and its next reply is taken at once.
        let t3 = last + 200 * MS;
        let f = ask(&mut line, t3);
        line.received(&codec.encode(1, &[3, 2, 0, 5]), t3 + MS, &stats);
        assert_eq!(line.frames(&f, t3 + MS, &stats).len(), 1, "{framing:?}");
        // Owing again, a reply held, then a frame that fits no read: both go, the
        // request refused at once.
        line.unanswered(1);
        let t4 = t3 + 200 * MS;
        let f = ask(&mut line, t4);
        line.received(&codec.encode(1, &[3, 2, 0, 8]), t4 + MS, &stats);
        assert!(line.frames(&f, t4 + MS, &stats).is_empty());
        line.received(&codec.encode(1, &[0x10, 0, 9, 0, 1]), t4 + 2 * MS, &stats);
        let seen = line.frames(&f, t4 + 2 * MS, &stats);
        assert!(
            matches!(seen.as_slice(), [Seen::Corrupt(k)] if *k == f[0].tid),
            "{framing:?}"
        );
        assert_eq!(stats.get(&stats.late_replies), 3, "{framing:?}");
    }
}
