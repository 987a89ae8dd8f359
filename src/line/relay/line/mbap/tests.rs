//! The MBAP line's tests: echoes and frames begun too early, confirmation only when
//! something can follow a reply, the pause, unasked talk, and the capture's tape.

use super::*;
use crate::frame::hex::parse as bytes;
use crate::line::relay::line::LineFraming;

const MS: Duration = Duration::from_millis(1);

fn mbap(baud: u32) -> (LineFraming, Instant) {
    let serial = SerialConfig {
        baud_rate: baud,
        ..SerialConfig::default()
    };
    let now = Instant::now();
    (
        LineFraming::new(&RelayConfig::default(), &serial, false, now),
        now,
    )
}

/// A request as the table holds it in tests: the ADU, never resent.
type Req = (Adu, u32);

/// Request `adu` on the line as `tid` since `now`, due in a second.
fn in_flight(tid: u16, adu: &Adu, now: Instant) -> OnLine<Req> {
    OnLine {
        tid,
        deadline: now + Duration::from_secs(1),
        timeout: Duration::from_secs(1),
        req: (adu.clone(), 0),
    }
}

/// Request `adu` sent now.
fn send(line: &mut LineFraming, adu: &Adu, now: Instant) -> OnLine<Req> {
    let tid = line.allocate(now);
    line.encode(adu, tid, now, &Stats::default());
    in_flight(tid, adu, now)
}

fn frames(line: &mut LineFraming, in_flight: &[OnLine<Req>], now: Instant) -> Vec<Vec<u8>> {
    line.frames(in_flight, now, &Stats::default())
        .into_iter()
        .map(|s| match s {
            Seen::Frame(f, _) => f.as_bytes().to_vec(),
            Seen::Corrupt(_) | Seen::Heard(_) => panic!("corrupt on an MBAP line"),
        })
        .collect()
}

/// An RS-232 loopback sends an FC 06 write straight back, byte for byte its
/// successful reply, while the write is still going out (12 bytes at 9600 baud
/// take 12.5 ms). A copy that began before the write had left is its echo; the
/// device's own reply after it is the answer.
#[test]
fn a_copy_of_the_request_that_began_before_it_left_is_its_echo() {
    let (mut line, t0) = mbap(9600);
    let write = Adu::build(9, 1, &[6, 0, 1, 0, 3]);
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    line.received(&sent[..4], t0 + MS, &Stats::default());
    line.received(&sent[4..], t0 + 12 * MS, &Stats::default());
    assert!(frames(&mut line, &[f], t0 + 40 * MS).is_empty());
    // Read late, in one piece: its own time on the wire before it was read is
    // still before the write left.
    let (mut line, t0) = mbap(9600);
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    line.received(&sent, t0 + 20 * MS, &Stats::default());
    assert!(frames(&mut line, &[f], t0 + 60 * MS).is_empty());
    // The device's reply, begun after the write left.
    let (mut line, t0) = mbap(9600);
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    line.received(&sent, t0 + 26 * MS, &Stats::default());
    assert_eq!(frames(&mut line, &[f], t0 + 60 * MS), vec![sent.clone()]);
    // A request queued behind another leaves after it.
    let (mut line, t0) = mbap(9600);
    let first = send(&mut line, &Adu::build(1, 1, &[3, 0, 0, 0, 1]), t0);
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    line.received(&sent, t0 + 37 * MS, &Stats::default());
    assert!(frames(&mut line, &[first, f], t0 + 90 * MS).is_empty());
}

/// A busy machine runs the loop late: the write that carries a request returns long
/// after the request was queued. The echo, begun while that write went out, is still
/// its echo; the device's own reply, begun after the request left counted from the
/// write's return, is the answer. Written in two pieces, the request leaves with the
/// second.
#[test]
fn a_request_written_late_leaves_after_its_write() {
    let write = Adu::build(9, 1, &[6, 0, 1, 0, 3]);
    let late = 300 * MS;
    for pieces in [vec![12], vec![5, 7]] {
        let (mut line, t0) = mbap(9600);
        let f = send(&mut line, &write, t0);
        let sent = write.with_tid(f.tid).as_bytes().to_vec();
        for &n in &pieces {
            line.wrote(n, t0, t0 + late);
        }
        // 12.5 ms on the wire from the write's return: an echo read at 4 and 14 ms.
        line.received(&sent[..4], t0 + late + 4 * MS, &Stats::default());
        line.received(&sent[4..], t0 + late + 14 * MS, &Stats::default());
        assert!(
            frames(
                &mut line,
                &[in_flight(f.tid, &write, t0)],
                t0 + late + 60 * MS
            )
            .is_empty(),
            "{pieces:?}"
        );
        // The device's answer, begun after it left.
        line.received(&sent, t0 + late + 40 * MS, &Stats::default());
        assert_eq!(
            frames(&mut line, &[f], t0 + late + 80 * MS),
            vec![sent.clone()],
            "{pieces:?}"
        );
    }
}

/// Bytes read before a request was sent cannot begin its reply: a notification
/// whose header was damaged leaves its last register (here equal to the request's
/// id) to be scanned, and the next notification, having lost its id, completes a
/// frame with that id and the shape the request calls for.
#[test]
fn a_frame_begun_before_its_request_was_sent_does_not_answer_it() {
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    let body = bytes("00 00 00 05 01 03 02 02 F4");
    for stale_before in [true, false] {
        let (mut line, t0) = mbap(19_200);
        let tid = line.allocate(t0);
        let stale = [&bytes("00 00 00 00 05 01 03 02")[..], &tid.to_be_bytes()].concat();
        let sent_at = t0 + 2 * MS;
        let read_at = t0 + if stale_before { MS } else { 3 * MS };
        if stale_before {
            line.received(&stale, read_at, &Stats::default());
        }
        line.encode(&read, tid, sent_at, &Stats::default());
        if !stale_before {
            line.received(&stale, read_at, &Stats::default());
        }
        line.received(&body, t0 + 4 * MS, &Stats::default());
        let f = in_flight(tid, &read, sent_at);
        let got = frames(&mut line, &[f], t0 + 40 * MS);
        if stale_before {
            assert!(got.is_empty(), "{got:02X?}");
        } else {
            // Read after the request left, the same bytes pass: the bound of
            // docs/reliability.md (ids are random, so values equal one by chance).
            assert_eq!(got, vec![[&tid.to_be_bytes()[..], &body[..]].concat()]);
        }
    }
}

/// With the device said to send notifications, every reply is held until what
/// follows confirms it: a reply that lost a data byte, then a notification at once,
/// is never delivered. A reply alone is confirmed by a pause (the floor of a port
/// not yet known, 20 ms), not the frame gap; with another reply due it waits for
/// that one, or for the frame gap.
#[test]
fn replies_are_confirmed_by_what_follows_or_a_pause() {
    let relay = RelayConfig {
        device_notifications: true,
        ..RelayConfig::default()
    };
    let serial = SerialConfig::default();
    let t0 = Instant::now();
    let mut line = LineFraming::new(&relay, &serial, false, t0);
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 3]);
    let a = send(&mut line, &read, t0);
    let mut reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
        .as_bytes()
        .to_vec();
    reply.remove(10);
    let notification = bytes("00 00 00 00 00 05 01 03 02 00 0F");
    let at = t0 + 30 * MS;
    line.received(&[reply, notification].concat(), at, &Stats::default());
    for after in [0, 20, 50] {
        assert!(frames(&mut line, std::slice::from_ref(&a), at + after * MS).is_empty());
    }

    let mut line = LineFraming::new(&relay, &serial, false, t0);
    let a = send(&mut line, &read, t0);
    let b = send(&mut line, &read, t0);
    let reply = Adu::build(a.tid, 1, &[3, 6, 0, 1, 0, 2, 0, 3])
        .as_bytes()
        .to_vec();
    let at = t0 + 30 * MS;
    line.received(&reply, at, &Stats::default());
    let both = [a, b];
    assert!(frames(&mut line, &both, at + 19 * MS).is_empty());
    assert!(
        frames(&mut line, &both, at + 20 * MS).is_empty(),
        "b is due"
    );
    assert_eq!(line.next_wake(at + 20 * MS, false), Some(at + 50 * MS));
    assert_eq!(frames(&mut line, &both, at + 50 * MS), vec![reply]);
    let mut line = LineFraming::new(&relay, &serial, false, t0);
    let a = send(&mut line, &read, t0);
    let reply = Adu::build(a.tid, 1, &[3, 6, 0, 1, 0, 2, 0, 3])
        .as_bytes()
        .to_vec();
    line.received(&reply, at, &Stats::default());
    assert_eq!(line.next_wake(at, false), Some(at + 20 * MS));
    assert_eq!(frames(&mut line, &[a], at + 20 * MS), vec![reply]);
}

/// A reply nothing can follow (one request in flight, no late reply possible, a
/// device that sends nothing unasked) is taken the moment it is whole; the same
/// reply that lost a data byte waits for a byte that never comes and is dropped
/// after the frame gap. With two requests in flight it is held for the other's.
#[test]
fn a_lone_reply_is_taken_at_once_and_a_damaged_one_never() {
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 3]);
    let (mut line, t0) = mbap(19_200);
    let a = send(&mut line, &read, t0);
    let reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
        .as_bytes()
        .to_vec();
    let at = t0 + 10 * MS;
    line.received(&reply, at, &Stats::default());
    assert_eq!(
        line.next_wake(at, false),
        Some(at + 20 * MS),
        "not taken yet"
    );
    assert_eq!(
        frames(&mut line, std::slice::from_ref(&a), at),
        vec![reply.clone()]
    );
    assert_eq!(line.next_wake(at, false), None);

    let (mut line, t0) = mbap(19_200);
    let a = send(&mut line, &read, t0);
    let mut lost = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
        .as_bytes()
        .to_vec();
    lost.remove(10);
    line.received(&lost, at, &Stats::default());
    for after in [0, 20, 50, 60] {
        assert!(frames(&mut line, std::slice::from_ref(&a), at + after * MS).is_empty());
    }

    let (mut line, t0) = mbap(19_200);
    let a = send(&mut line, &read, t0);
    let b = send(&mut line, &read, t0);
    let reply = Adu::build(a.tid, 1, &bytes("03 06 5B 75 5B 6A 5B 6B"))
        .as_bytes()
        .to_vec();
    line.received(&reply, at, &Stats::default());
    let both = [a, b];
    assert!(
        frames(&mut line, &both, at).is_empty(),
        "b's reply may follow"
    );
    assert_eq!(frames(&mut line, &both, at + 50 * MS), vec![reply]);
}

/// What may follow a reply decides whether it is held: a late reply for the guard
/// time after a timeout (`timeout_guard_ms`, 100 ms), then no longer; anything
/// heard while nothing was asked, for good (said once, counted); bytes already
/// after it, or a pause inside it.
#[test]
fn what_may_follow_a_reply_holds_it() {
    use std::sync::atomic::Ordering;
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    let whole = |tid| Adu::build(tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
    // A timeout: the next reply is held for 100 ms after it.
    let (mut line, t0) = mbap(19_200);
    line.timed_out(t0, Duration::ZERO, &Stats::default());
    let a = send(&mut line, &read, t0);
    line.received(&whole(a.tid), t0 + 5 * MS, &Stats::default());
    assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 5 * MS).is_empty());
    assert_eq!(
        frames(&mut line, std::slice::from_ref(&a), t0 + 25 * MS),
        vec![whole(a.tid)]
    );
    let b = send(&mut line, &read, t0 + 100 * MS);
    line.received(&whole(b.tid), t0 + 105 * MS, &Stats::default());
    assert_eq!(
        frames(&mut line, std::slice::from_ref(&b), t0 + 105 * MS),
        vec![whole(b.tid)]
    );
    // Bytes while nothing is asked: counted, and every reply held from then on.
    let stats = Stats::default();
    let (mut line, t0) = mbap(19_200);
    line.heard(3, 0, t0, &stats);
    line.received(&[0xFF; 3], t0, &stats);
    assert_eq!(stats.unasked_bytes.load(Ordering::Relaxed), 3);
    let a = send(&mut line, &read, t0 + 10 * MS);
    line.heard(11, 1, t0 + 12 * MS, &stats);
    line.received(&whole(a.tid), t0 + 12 * MS, &stats);
    assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 12 * MS).is_empty());
    assert_eq!(
        frames(&mut line, std::slice::from_ref(&a), t0 + 32 * MS),
        vec![whole(a.tid)]
    );
    assert_eq!(
        stats.unasked_bytes.load(Ordering::Relaxed),
        3,
        "only what came unasked"
    );
    // A noise byte right behind a whole reply, read with it: held, then refuted.
    let (mut line, t0) = mbap(19_200);
    let a = send(&mut line, &read, t0);
    line.received(
        &[whole(a.tid), vec![0x5A]].concat(),
        t0 + 5 * MS,
        &Stats::default(),
    );
    for after in [5, 25, 60] {
        assert!(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS).is_empty());
    }
    // A reply that lost its last byte, completed by a noise byte after a pause:
    // it straddles the pause, and is refuted.
    let (mut line, t0) = mbap(19_200);
    let a = send(&mut line, &read, t0);
    let w = whole(a.tid);
    line.received(&w[..w.len() - 1], t0 + 5 * MS, &Stats::default());
    assert!(frames(&mut line, std::slice::from_ref(&a), t0 + 26 * MS).is_empty());
    line.received(&[0x00], t0 + 30 * MS, &Stats::default());
    for after in [30, 55, 90] {
        assert!(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS).is_empty());
    }
}

/// On a pty (no wire) a copy of the request read at once is the device's reply:
/// an FC 06 write answered by a device that answers as soon as the request is in
/// (pymodbus' serial server).
#[test]
fn on_a_pty_a_write_reply_equal_to_the_request_is_taken_at_once() {
    use crate::line::port::kind::{Medium, PortInfo};
    let (mut line, t0) = mbap(9600);
    let told = line.port_opened(&PortInfo::plain(Medium::Pty));
    assert!(told.contains("no wire"), "{told}");
    let write = Adu::build(9, 1, &[6, 0, 1, 0, 3]);
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    line.received(&sent, t0 + MS / 10, &Stats::default());
    assert_eq!(frames(&mut line, &[f], t0 + MS / 10), vec![sent]);
    // Declared a wire, the same is its echo.
    let serial = SerialConfig {
        baud_rate: 9600,
        port_kind: crate::config::PortKind::Wire,
        ..SerialConfig::default()
    };
    let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
    line.port_opened(&PortInfo::plain(Medium::Pty));
    let f = send(&mut line, &write, t0);
    let sent = write.with_tid(f.tid).as_bytes().to_vec();
    let stats = Stats::default();
    line.received(&sent, t0 + MS / 10, &stats);
    assert!(line.frames(&[f], t0 + 60 * MS, &stats).is_empty());
    assert_eq!(
        stats
            .dropped_echo
            .load(std::sync::atomic::Ordering::Relaxed),
        12
    );
}

/// A device that pauses inside its reply (libmodbus' test server sends one byte
/// every 5 ms): with nothing able to follow, on a pty (no wire, no noise) the
/// whole reply is taken when its last byte comes; on a wire what came after a
/// pause may be noise completing a damaged reply, and it is refuted.
#[test]
fn a_reply_with_pauses_inside_is_taken_where_there_is_no_wire() {
    use crate::line::port::kind::{Medium, PortInfo};
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    // A UART whose FIFO hands each byte over: the pause is 3.5 characters.
    let uart = Medium::Uart {
        driver: None,
        trigger: Some(1),
    };
    for (kind, taken) in [(Medium::Pty, true), (uart, false)] {
        let serial = SerialConfig {
            baud_rate: 115_200,
            ..SerialConfig::default()
        };
        let t0 = Instant::now();
        let mut line = LineFraming::new(&RelayConfig::default(), &serial, false, t0);
        line.port_opened(&PortInfo::plain(kind.clone()));
        let a = send(&mut line, &read, t0);
        let reply = Adu::build(a.tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
        let mut got = Vec::new();
        for (i, b) in reply.iter().enumerate() {
            let at = t0 + (5 * i as u32 + 1) * MS;
            got.extend(frames(&mut line, std::slice::from_ref(&a), at));
            line.received(&[*b], at, &Stats::default());
            got.extend(frames(&mut line, std::slice::from_ref(&a), at + MS / 2));
        }
        for after in [30, 100] {
            got.extend(frames(&mut line, std::slice::from_ref(&a), t0 + after * MS));
        }
        let want = if taken { vec![reply] } else { Vec::new() };
        assert_eq!(got, want, "{kind:?}");
    }
}

/// The dropped-byte counter only grows: two lines counting into one `Stats` (or
/// the MBAP and RTU code paths) add their own drops, never overwrite each other's
/// (the decoder's running total used to be stored into it).
#[test]
fn dropped_bytes_add_up_across_lines_sharing_the_counters() {
    use std::sync::atomic::Ordering;
    let stats = Stats::default();
    let (mut a, t0) = mbap(19_200);
    let (mut b, _) = mbap(19_200);
    a.received(&[0xFF; 5], t0, &stats);
    b.received(&[0xFF; 3], t0, &stats);
    let later = t0 + Duration::from_secs(1);
    assert!(a.frames::<Req>(&[], later, &stats).is_empty());
    assert!(b.frames::<Req>(&[], later, &stats).is_empty());
    assert!(a.frames::<Req>(&[], later, &stats).is_empty());
    assert_eq!(stats.dropped_bytes.load(Ordering::Relaxed), 8);
}

/// Over TCP nothing is lost: a whole reply is taken the moment it is read, with
/// another reply due (on a serial line it would wait for the frame gap), and
/// `request_pause_ms` holds the next request back from the last byte read.
#[test]
fn over_tcp_a_whole_reply_is_taken_at_once_and_the_pause_kept() {
    let relay = RelayConfig {
        request_pause_ms: 30,
        max_in_flight: 2,
        ..RelayConfig::default()
    };
    let t0 = Instant::now();
    let mut line = LineFraming::new(&relay, &SerialConfig::default(), true, t0);
    let read = Adu::build(1, 1, &[3, 0, 0, 0, 1]);
    let a = send(&mut line, &read, t0);
    let b = send(&mut line, &read, t0);
    let reply = Adu::build(a.tid, 1, &[3, 2, 0, 7]).as_bytes().to_vec();
    let at = t0 + MS;
    line.received(&reply, at, &Stats::default());
    assert_eq!(frames(&mut line, &[a, b], at), vec![reply]);
    assert!(!line.has_room(1, false, at + 29 * MS));
    assert_eq!(line.next_wake(at, true), Some(at + 30 * MS));
    assert!(line.has_room(1, false, at + 30 * MS));
}

/// Two device notifications (id 0) back to back, with nothing in flight: both are
/// frames of the line, neither lost.
#[test]
fn two_notifications_back_to_back_are_both_seen() {
    let relay = RelayConfig {
        device_notifications: true,
        ..RelayConfig::default()
    };
    let t0 = Instant::now();
    let mut line = LineFraming::new(&relay, &SerialConfig::default(), false, t0);
    let one = bytes("00 00 00 00 00 05 01 03 02 00 0F");
    let two = bytes("00 00 00 00 00 05 01 03 02 00 10");
    let at = t0 + 30 * MS;
    line.received(&[one.clone(), two.clone()].concat(), at, &Stats::default());
    let mut got = Vec::new();
    for after in [0, 20, 50, 100] {
        got.extend(frames(&mut line, &[], at + after * MS));
    }
    assert_eq!(got, vec![one, two]);
}
