//! End to end with a scripted raw device on the pty: a device that never answers, a
//! cable that is pulled, notifications, hostile masters, full queues, late replies,
//! retries, limits and shutdown (docs/design.md §1, §3).

use crate::common;
use common::*;
use std::io::Write;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

struct Rig {
    dir: tempfile::TempDir,
    socat: Socat,
    gw: Gateway,
}

fn rig(cfg: impl FnOnce(Cfg) -> Cfg) -> Rig {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let gw = Gateway::start(&cfg(Cfg::new(&socat.gw)), dir.path());
    Rig { dir, socat, gw }
}

fn exception(tid: u16, unit: u8, function: u8, code: u8) -> Vec<u8> {
    mbgate::frame::Adu::exception(tid, unit, function, code)
        .as_bytes()
        .to_vec()
}

/// Item 4: a unit that never answers gets 0x0B after `response_timeout_ms`; another
/// master is served meanwhile and afterwards.
#[test]
fn silent_device_gives_0x0b_and_others_keep_being_served() {
    // Unit 1 answers at once, in far less than the timeout even on a loaded machine.
    let r = rig(|c| c.relay("response_timeout_ms = 2000"));
    let _dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    assert_eq!(
        transact(&mut b, &read_req(1, 1, 5, 1)),
        read_reply(1, 1, &[5])
    );

    let start = Instant::now();
    a.write_all(&read_req(7, 2, 0, 1)).unwrap();
    // While unit 2 is silent, b's request waits its turn (max_in_flight = 1), then is
    // answered.
    assert_eq!(
        transact(&mut b, &read_req(2, 1, 6, 1)),
        read_reply(2, 1, &[6])
    );
    assert_eq!(read_frame(&mut a), exception(7, 2, 0x03, 0x0B));
    let waited = start.elapsed();
    assert!(
        waited >= Duration::from_millis(2000),
        "0x0B too early: {waited:?}"
    );
    assert!(
        waited < Duration::from_secs(10),
        "0x0B too late: {waited:?}"
    );

    assert_eq!(
        transact(&mut b, &read_req(3, 1, 7, 1)),
        read_reply(3, 1, &[7])
    );
    assert_eq!(
        transact(&mut a, &read_req(8, 1, 9, 1)),
        read_reply(8, 1, &[9])
    );
}

/// Item 5: the serial end disappears and comes back. Requests meanwhile get 0x0A or
/// 0x0B promptly; service resumes without restarting mbgate; masters stay connected.
#[test]
fn serial_end_disappears_and_comes_back() {
    // Far beyond what load adds to the device's answer; "promptly" below is within it
    // and a margin.
    let mut r = rig(|c| c.relay("response_timeout_ms = 2000"));
    let dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut m = r.gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 1, 1)),
        read_reply(1, 1, &[1])
    );

    r.socat.stop();
    drop(dev);
    r.gw.wait_log("serial port lost", Duration::from_secs(5));
    for tid in 10..15u16 {
        let start = Instant::now();
        let got = transact(&mut m, &read_req(tid, 1, 1, 1));
        assert!(
            got == exception(tid, 1, 3, 0x0A) || got == exception(tid, 1, 3, 0x0B),
            "unexpected {got:02X?}"
        );
        assert!(start.elapsed() < Duration::from_secs(5), "not prompt");
    }

    r.socat.restart();
    let _dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let start = Instant::now();
    let mut tid = 100u16;
    loop {
        tid += 1;
        let got = transact(&mut m, &read_req(tid, 1, 42, 1));
        if got == read_reply(tid, 1, &[42]) {
            break;
        }
        assert!(
            got == exception(tid, 1, 3, 0x0A) || got == exception(tid, 1, 3, 0x0B),
            "unexpected {got:02X?}"
        );
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "service did not resume"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // Same TCP connection throughout.
    assert_eq!(
        transact(&mut m, &read_req(999, 1, 43, 1)),
        read_reply(999, 1, &[43])
    );
}

/// The port disappears under requests (docs/masters.md, the exceptions mbgate answers itself):
/// the one whose bytes went out gets 0x0B, as for a timeout (it may have acted on the
/// device); one flow control held back and one still queued get 0x0A (no path, and
/// they cannot have acted). An ASCII line, whose frames XON/XOFF flow control (which a
/// pty honours) cannot cut: the device's end is played byte by byte.
#[test]
fn port_lost_answers_0x0b_for_a_request_sent_0x0a_for_the_rest() {
    let ascii = |c: Cfg| {
        c.serial("framing = \"ascii\"")
            .serial("flow_control = \"software\"")
            .relay("response_timeout_ms = 5000")
    };
    // Sent, with one queued behind it.
    let mut r = rig(ascii);
    let mut dev = common::sim::RawLine::open(&r.socat.dev);
    let (mut sent, mut queued) = (r.gw.connect(), r.gw.connect());
    sent.write_all(&read_req(1, 1, 0, 1)).unwrap();
    let asked = mbgate::frame::ascii::encode(1, &[3, 0, 0, 0, 1]);
    assert_eq!(dev.recv(asked.len(), Duration::from_secs(5)), asked);
    queued.write_all(&read_req(3, 1, 0, 1)).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    r.socat.stop();
    let start = Instant::now();
    assert_eq!(read_frame(&mut sent), exception(1, 1, 3, 0x0B));
    assert_eq!(read_frame(&mut queued), exception(3, 1, 3, 0x0A));
    assert!(start.elapsed() < Duration::from_secs(2), "not prompt");

    // Held back by XOFF, with one queued behind it: neither ever reaches the device.
    let mut r = rig(ascii);
    let mut dev = common::sim::RawLine::open(&r.socat.dev);
    dev.send(&[0x13]); // XOFF: nothing leaves
    std::thread::sleep(Duration::from_millis(100));
    let (mut held, mut queued) = (r.gw.connect(), r.gw.connect());
    held.write_all(&read_req(2, 1, 0, 1)).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    queued.write_all(&read_req(3, 1, 0, 1)).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    let got = dev.recv_until_quiet(Duration::from_millis(200), Duration::from_secs(1));
    r.socat.stop();
    let start = Instant::now();
    assert_eq!(read_frame(&mut held), exception(2, 1, 3, 0x0A));
    assert_eq!(read_frame(&mut queued), exception(3, 1, 3, 0x0A));
    assert!(start.elapsed() < Duration::from_secs(2), "not prompt");
    assert!(
        got.is_empty(),
        "the held request never left: {}",
        hexs(&got)
    );
}

/// A serial port that does not exist at start is not fatal: 0x0A at once, and service
/// starts when the port appears.
#[test]
fn missing_port_at_start_answers_0x0a_then_serves() {
    let dir = tempdir();
    let gw_path = dir.path().join("gw");
    let gw = Gateway::start(&Cfg::new(&gw_path), dir.path());
    let mut m = gw.connect();
    let start = Instant::now();
    assert_eq!(
        transact(&mut m, &read_req(5, 1, 0, 1)),
        exception(5, 1, 3, 0x0A)
    );
    assert!(
        start.elapsed() < Duration::from_secs(1),
        "0x0A is not immediate"
    );

    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let start = Instant::now();
    loop {
        let got = transact(&mut m, &read_req(6, 1, 3, 1));
        if got == read_reply(6, 1, &[3]) {
            break;
        }
        assert_eq!(got, exception(6, 1, 3, 0x0A));
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "port never opened"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// `n` masters, each served once, so the relay knows them all.
fn served_masters(gw: &Gateway, n: u16) -> Vec<std::net::TcpStream> {
    (1..=n)
        .map(|tid| {
            let mut m = gw.connect();
            assert_eq!(
                transact(&mut m, &read_req(tid, 1, 0, 1)),
                read_reply(tid, 1, &[0])
            );
            m
        })
        .collect()
}

/// Each master's next frame is the reply to its own read of `addr` (and so not a
/// notification or someone else's answer).
fn each_gets_its_own_reply(masters: &mut [std::net::TcpStream], first_tid: u16, addr: u16) {
    for (tid, m) in (first_tid..).zip(masters.iter_mut()) {
        assert_eq!(
            transact(m, &read_req(tid, 1, addr, 1)),
            read_reply(tid, 1, &[addr])
        );
    }
}

const NOTIFICATION: &str = "00 00 00 00 00 05 01 03 02 00 0F";

/// Item 6, broadcast: an unsolicited frame from the device reaches every master.
#[test]
fn notification_broadcast_reaches_every_master() {
    let r = rig(|c| c.relay("notifications = \"broadcast\""));
    let mut dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut masters = served_masters(&r.gw, 3);
    dev.inject(&hex(NOTIFICATION));
    for m in &mut masters {
        assert_eq!(read_frame(m), hex(NOTIFICATION));
    }
    // A malformed one (byte count disagrees with the length) goes to nobody.
    dev.inject(&hex("00 00 00 00 00 05 01 03 04 00 0F"));
    std::thread::sleep(Duration::from_millis(200));
    each_gets_its_own_reply(&mut masters, 50, 4);
}

/// Item 6, drop (the default): the same frame reaches no master.
#[test]
fn notification_dropped_by_default() {
    let r = rig(|c| c);
    let mut dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut masters = served_masters(&r.gw, 3);
    dev.inject(&hex(NOTIFICATION));
    r.gw.wait_log("unsolicited frame dropped", Duration::from_secs(2));
    each_gets_its_own_reply(&mut masters, 10, 2);
}

/// Item 7: bad TCP input closes only that connection; another master is unaffected.
#[test]
fn bad_tcp_input_closes_only_that_connection() {
    let r = rig(|c| c);
    let dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut good = r.gw.connect();
    assert_eq!(
        transact(&mut good, &read_req(1, 1, 0, 1)),
        read_reply(1, 1, &[0])
    );

    // Seeded pseudo-random bytes whose protocol id is not 0.
    let mut x: u32 = 0x2545_F491;
    let mut random: Vec<u8> = (0..64)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        })
        .collect();
    random[2] |= 0x01;
    let mut with_300 = hex("00 01 00 00 01 2C 01 03");
    with_300.extend(vec![0u8; 298]);
    let bad: [(&str, Vec<u8>); 4] = [
        ("protocol id 1", hex("00 01 00 01 00 06 01 03 00 00 00 01")),
        ("length 0", hex("00 01 00 00 00 00")),
        ("length 300", with_300),
        ("random bytes", random),
    ];
    for (i, (what, bytes)) in bad.iter().enumerate() {
        let mut m = r.gw.connect();
        m.write_all(bytes).unwrap();
        assert!(
            is_closed(&mut m, Duration::from_secs(3)),
            "{what}: not closed"
        );
        let tid = 100 + i as u16;
        assert_eq!(
            transact(&mut good, &read_req(tid, 1, 9, 1)),
            read_reply(tid, 1, &[9]),
            "{what}: the other master was affected"
        );
    }
    r.gw.wait_log("protocol violation", Duration::from_secs(2));
    // None of it reached the line.
    assert_eq!(dev.requests().len(), 5);
}

/// A request outside protocol limits is answered by the gateway (exception 03), and
/// never reaches the line.
#[test]
fn request_outside_protocol_limits_is_answered_locally() {
    let r = rig(|c| c);
    let dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut m = r.gw.connect();
    // FC 03 for 0 registers, and for 126.
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 0, 0)),
        exception(1, 1, 3, 0x03)
    );
    assert_eq!(
        transact(&mut m, &read_req(2, 1, 0, 126)),
        exception(2, 1, 3, 0x03)
    );
    assert_eq!(
        transact(&mut m, &read_req(3, 1, 0, 1)),
        read_reply(3, 1, &[0])
    );
    assert_eq!(dev.requests().len(), 1);
}

/// A full queue answers 0x06 at once; what was accepted is still answered. Each
/// master's replies come in the order of its requests, a 0x06 included.
#[test]
fn full_queue_answers_0x06() {
    let r = rig(|c| {
        c.relay("queue_depth = 2")
            .relay("max_pending_per_connection = 2")
            .relay("response_timeout_ms = 2000")
    });
    let dev = RawDevice::start(
        &r.socat.dev,
        register_device(&[1], Duration::from_millis(300)),
    );
    let (mut a, mut b, mut c) = (r.gw.connect(), r.gw.connect(), r.gw.connect());
    // a: one on the line, one queued; b: one queued (the queue is full), one refused.
    a.write_all(&[read_req(1, 1, 1, 1), read_req(2, 1, 2, 1)].concat())
        .unwrap();
    wait_for(
        "a's first request on the line",
        Duration::from_secs(2),
        || dev.requests().len() == 1,
    );
    b.write_all(&[read_req(3, 1, 3, 1), read_req(4, 1, 4, 1)].concat())
        .unwrap();
    std::thread::sleep(Duration::from_millis(50));
    // c holds nothing, but no master holds two more than it: turned away at once.
    let start = Instant::now();
    assert_eq!(
        transact(&mut c, &read_req(5, 1, 5, 1)),
        exception(5, 1, 3, 0x06)
    );
    assert!(
        start.elapsed() < Duration::from_millis(200),
        "{:?}",
        start.elapsed()
    );
    assert_eq!(read_frame(&mut a), read_reply(1, 1, &[1]));
    assert_eq!(read_frame(&mut a), read_reply(2, 1, &[2]));
    assert_eq!(read_frame(&mut b), read_reply(3, 1, &[3]));
    assert_eq!(read_frame(&mut b), exception(4, 1, 3, 0x06));
    assert_eq!(dev.requests().len(), 3);
}

/// A reply that comes after its request timed out is dropped and counted, never given
/// to anyone, not even with broadcast on; the next request is answered correctly.
#[test]
fn late_reply_is_never_delivered() {
    let mut r = rig(|c| {
        c.relay("response_timeout_ms = 2000")
            .relay("notifications = \"broadcast\"")
    });
    let calls = Arc::new(AtomicUsize::new(0));
    let mut inner = register_device(&[1], Duration::ZERO);
    let c2 = calls.clone();
    let _dev = RawDevice::start(
        &r.socat.dev,
        Box::new(move |req| {
            if c2.fetch_add(1, Ordering::SeqCst) == 0 {
                // Late by far more than the timeout; the others on time by far.
                std::thread::sleep(Duration::from_millis(3000));
            }
            inner(req)
        }),
    );
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    assert_eq!(
        transact(&mut a, &read_req(1, 1, 11, 1)),
        exception(1, 1, 3, 0x0B)
    );
    r.gw.wait_log("late reply dropped", Duration::from_secs(20));
    assert_eq!(
        transact(&mut a, &read_req(2, 1, 12, 1)),
        read_reply(2, 1, &[12])
    );
    // b's first frame is its own reply: the late one was not broadcast.
    assert_eq!(
        transact(&mut b, &read_req(3, 1, 13, 1)),
        read_reply(3, 1, &[13])
    );
    assert_eq!(r.gw.terminate(Duration::from_secs(5)).code(), Some(0));
    let log = r.gw.log();
    assert!(
        log.contains("timeouts=1 unavailable=0 busy=0 bad_requests=0"),
        "{log}"
    );
    assert!(log.contains("late_replies=1"), "{log}");
    assert!(log.contains("notifications_broadcast=0"), "{log}");
}

/// `retries` resends reads after a timeout; writes are not resent without
/// `retry_writes`.
#[test]
fn retries_resend_reads_but_not_writes() {
    let r = rig(|c| c.relay("response_timeout_ms = 2000").relay("retries = 1"));
    let calls = Arc::new(AtomicUsize::new(0));
    let mut inner = register_device(&[1], Duration::ZERO);
    let c2 = calls.clone();
    let dev = RawDevice::start(
        &r.socat.dev,
        Box::new(move |req| {
            // Ignore the first read and the first write.
            match c2.fetch_add(1, Ordering::SeqCst) {
                0 | 2 => vec![],
                _ => inner(req),
            }
        }),
    );
    let mut m = r.gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 20, 1)),
        read_reply(1, 1, &[20])
    );
    assert_eq!(
        transact(&mut m, &write_req(2, 1, 20, &[5])),
        exception(2, 1, 0x10, 0x0B)
    );
    std::thread::sleep(Duration::from_millis(300));
    let seen = dev.requests();
    assert_eq!(seen.len(), 3, "read twice, write once: {seen:?}");
    assert_ne!(seen[0].tid(), seen[1].tid(), "a resend gets a fresh id");
    assert!(seen.iter().all(|s| s.tid() != 0), "serial ids are never 0");
}

/// `max_connections`: the next connection is closed at once and logged; the others
/// keep working.
#[test]
fn max_connections_enforced() {
    let r = rig(|c| c.tcp("max_connections = 2"));
    let _dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    assert_eq!(
        transact(&mut a, &read_req(1, 1, 1, 1)),
        read_reply(1, 1, &[1])
    );
    assert_eq!(
        transact(&mut b, &read_req(1, 1, 2, 1)),
        read_reply(1, 1, &[2])
    );
    let mut c = r.gw.connect();
    assert!(is_closed(&mut c, Duration::from_secs(3)));
    r.gw.wait_log("max_connections (2) reached", Duration::from_secs(2));
    assert_eq!(
        transact(&mut a, &read_req(2, 1, 3, 1)),
        read_reply(2, 1, &[3])
    );
    // A slot frees when a master leaves.
    drop(b);
    std::thread::sleep(Duration::from_millis(200));
    let mut d = r.gw.connect();
    assert_eq!(
        transact(&mut d, &read_req(3, 1, 4, 1)),
        read_reply(3, 1, &[4])
    );
}

/// `idle_timeout_ms`: a master that sends nothing is closed; a busy one is not.
#[test]
fn idle_masters_are_closed() {
    let r = rig(|c| c.tcp("idle_timeout_ms = 400"));
    let _dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut idle = r.gw.connect();
    let mut busy = r.gw.connect();
    assert_eq!(
        transact(&mut idle, &read_req(1, 1, 1, 1)),
        read_reply(1, 1, &[1])
    );
    let start = Instant::now();
    for t in 0..8u16 {
        assert_eq!(
            transact(&mut busy, &read_req(t, 1, t, 1)),
            read_reply(t, 1, &[t])
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(is_closed(&mut idle, Duration::from_secs(3)));
    assert!(start.elapsed() >= Duration::from_millis(300));
    assert_eq!(
        transact(&mut busy, &read_req(9, 1, 9, 1)),
        read_reply(9, 1, &[9])
    );
}

/// SIGTERM: stop accepting, answer what is queued 0x0A, finish what is on the line,
/// exit 0 within the response timeout.
#[test]
fn sigterm_drains_in_flight_and_exits_0() {
    let mut r = rig(|c| c.relay("response_timeout_ms = 2000"));
    let _dev = RawDevice::start(
        &r.socat.dev,
        register_device(&[1], Duration::from_millis(500)),
    );
    let mut m = r.gw.connect();
    let burst: Vec<u8> = [read_req(1, 1, 31, 1), read_req(2, 1, 32, 1)].concat();
    m.write_all(&burst).unwrap();
    std::thread::sleep(Duration::from_millis(150));
    let addr = r.gw.addr;
    let start = Instant::now();
    let status = r.gw.terminate(Duration::from_secs(5));
    assert_eq!(status.code(), Some(0));
    assert!(start.elapsed() < Duration::from_millis(2000 + 1000));
    let mut got = vec![read_frame(&mut m), read_frame(&mut m)];
    got.sort();
    assert_eq!(got, vec![read_reply(1, 1, &[31]), exception(2, 1, 3, 0x0A)]);
    assert!(
        std::net::TcpStream::connect(addr).is_err(),
        "still accepting"
    );
    let _ = &r.dir;
}

/// SIGHUP is a reload now (docs/configuration.md, "Reload"), no longer a stop: the request on the line
/// is answered, the gateway keeps running, and SIGTERM still drains and exits 0.
#[test]
fn sighup_reloads_and_the_request_on_the_line_is_answered() {
    let mut r = rig(|c| c.relay("response_timeout_ms = 2000"));
    let _dev = RawDevice::start(
        &r.socat.dev,
        register_device(&[1], Duration::from_millis(500)),
    );
    let mut m = r.gw.connect();
    m.write_all(&read_req(7, 1, 41, 1)).unwrap();
    std::thread::sleep(Duration::from_millis(150));
    r.gw.proc.signal("HUP");
    assert_eq!(read_frame(&mut m), read_reply(7, 1, &[41]));
    r.gw.wait_log("reloaded: nothing to change", Duration::from_secs(5));
    // Still serving, on the same connection.
    assert_eq!(
        transact(&mut m, &read_req(8, 1, 42, 1)),
        read_reply(8, 1, &[42])
    );
    let counters = r.gw.stop();
    assert_eq!((counters["requests"], counters["replies"]), (2, 2));
    let _ = &r.dir;
}

/// SIGTERM while the device is silent: the drain waits no longer than the response
/// timeout, the master gets 0x0B for the request on the line, and the exit is 0 (what
/// systemd's stop sees, within the unit's TimeoutStopSec).
#[test]
fn sigterm_with_a_silent_device_exits_0_within_the_response_timeout() {
    let mut r = rig(|c| c.relay("response_timeout_ms = 1000"));
    let dev = RawDevice::start(&r.socat.dev, Box::new(|_| vec![]));
    let mut m = r.gw.connect();
    m.write_all(&read_req(5, 1, 0, 1)).unwrap();
    while dev.requests().is_empty() {
        std::thread::sleep(Duration::from_millis(5));
    }
    let start = Instant::now();
    let status = r.gw.terminate(Duration::from_secs(5));
    let took = start.elapsed();
    assert_eq!(status.code(), Some(0));
    assert!(
        took < Duration::from_millis(1000 + 300),
        "exit took {took:?}: {}",
        r.gw.log()
    );
    assert_eq!(read_frame(&mut m), exception(5, 1, 3, 0x0B));
}

/// XON/XOFF on an ASCII line (the one framing whose frames can never hold 0x11 or
/// 0x13): XOFF from the device holds the gateway's next request back past its timeout
/// (a pty honours it; RTS/CTS behaves the same on real ports): the master gets 0x0B,
/// and the request is withdrawn, so it never reaches the device after the master was
/// told it failed. XON releases the line: the next request is the first bytes the
/// device reads after it.
#[test]
fn request_held_back_by_flow_control_is_withdrawn_on_timeout() {
    let r = rig(|c| {
        c.serial("framing = \"ascii\"")
            .serial("flow_control = \"software\"")
            .relay("response_timeout_ms = 300")
    });
    let mut dev = common::sim::RawLine::open(&r.socat.dev);
    let mut m = r.gw.connect();
    let ascii = mbgate::frame::ascii::encode;
    let answer = |dev: &mut common::sim::RawLine, pdu: &[u8], reply: &[u8]| {
        let asked = ascii(1, pdu);
        assert_eq!(dev.recv(asked.len(), Duration::from_secs(5)), asked);
        dev.send(&ascii(1, reply));
    };
    m.write_all(&read_req(1, 1, 1, 1)).unwrap();
    answer(&mut dev, &[3, 0, 1, 0, 1], &[3, 2, 0, 1]);
    assert_eq!(read_frame(&mut m), read_reply(1, 1, &[1]));

    dev.send(&[0x13]); // XOFF
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(
        transact(&mut m, &write_req(2, 1, 7, &[0xDEAD])),
        exception(2, 1, 0x10, 0x0B)
    );
    r.gw.wait_log("could not be written in time", Duration::from_secs(2));
    dev.send(&[0x11]); // XON
    m.write_all(&read_req(3, 1, 7, 1)).unwrap();
    // The withdrawn write never reached the device: the read is the next it hears.
    answer(&mut dev, &[3, 0, 7, 0, 1], &[3, 2, 0, 7]);
    assert_eq!(read_frame(&mut m), read_reply(3, 1, &[7]));
}

/// XON/XOFF flow control is refused on the binary framings, where any byte of a frame
/// may be 0x11 or 0x13, naming the key and why; allowed on ASCII.
#[test]
fn software_flow_control_is_refused_on_binary_framings() {
    let dir = tempdir();
    for framing in ["rtu", "mbap", "ascii"] {
        let path = dir.path().join(format!("{framing}.toml"));
        std::fs::write(
            &path,
            format!(
                "[serial]\npath = \"/dev/ttyUSB0\"\nframing = \"{framing}\"\nflow_control = \"software\"\n"
            ),
        )
        .unwrap();
        let run = mbgate(&["check-config", path.to_str().unwrap()]);
        if framing == "ascii" {
            assert_eq!(run.code, 0, "{}", run.stderr);
        } else {
            assert_eq!(run.code, 2, "{framing}: {}", run.stderr);
            assert!(
                run.stderr.contains(&format!(
                    "{framing}.toml:4:16: serial.flow_control: cannot go with serial.framing = \"{framing}\": software flow control takes the bytes 0x11 and 0x13"
                )),
                "{}",
                run.stderr
            );
        }
    }
}

/// Pipelining past `max_pending_per_connection` is held back by TCP, not refused: every
/// request is answered, in order.
#[test]
fn pipelining_past_the_per_connection_limit_is_backpressure_not_refusal() {
    let r = rig(|c| c.relay("max_pending_per_connection = 2"));
    let dev = RawDevice::start(&r.socat.dev, register_device(&[1], Duration::ZERO));
    let mut m = r.gw.connect();
    let burst: Vec<u8> = (1..=12u16).flat_map(|t| read_req(t, 1, t, 1)).collect();
    m.write_all(&burst).unwrap();
    for t in 1..=12u16 {
        assert_eq!(read_frame(&mut m), read_reply(t, 1, &[t]));
    }
    assert_eq!(dev.requests().len(), 12);
}

/// Round-robin: a master that pipelines 16 requests does not make another master wait
/// behind all of them.
#[test]
fn round_robin_across_connections() {
    let r = rig(|c| c);
    let dev = RawDevice::start(
        &r.socat.dev,
        register_device(&[1], Duration::from_millis(20)),
    );
    let mut busy = r.gw.connect();
    let mut other = r.gw.connect();
    let burst: Vec<u8> = (1..=16u16).flat_map(|t| read_req(t, 1, t, 1)).collect();
    busy.write_all(&burst).unwrap();
    // Send just after a request of the busy master reached the device: it is on the
    // line for 20 ms, and the other master's request must be the next one.
    std::thread::sleep(Duration::from_millis(30));
    let seen = dev.requests().len();
    while dev.requests().len() == seen {
        std::thread::sleep(Duration::from_millis(1));
    }
    let on_line = dev.requests().len();
    assert_eq!(
        transact(&mut other, &read_req(99, 1, 99, 1)),
        read_reply(99, 1, &[99])
    );
    for t in 1..=16u16 {
        assert_eq!(read_frame(&mut busy), read_reply(t, 1, &[t]));
    }
    // On the line, the other master's request went right after the one in flight: the
    // busy master had just had its turn, so a master that starts waiting goes first.
    let order: Vec<u16> = dev
        .requests()
        .iter()
        .map(|a| u16::from_be_bytes([a.pdu()[1], a.pdu()[2]]))
        .collect();
    let pos = order.iter().position(|&a| a == 99).unwrap();
    assert_eq!(pos, on_line, "served at position {pos}: {order:?}");
}

/// `max_in_flight = 4` with a device that takes four requests before answering, and
/// answers them in reverse order: each reply still reaches its master with its own id.
#[test]
fn max_in_flight_pipelines_and_matches_replies_out_of_order() {
    let r = rig(|c| c.relay("max_in_flight = 4"));
    let mut batch: Vec<Vec<u8>> = Vec::new();
    let mut inner = register_device(&[1], Duration::ZERO);
    let dev = RawDevice::start(
        &r.socat.dev,
        Box::new(move |req| {
            batch.push(inner(req));
            if batch.len() < 4 {
                return vec![];
            }
            batch.drain(..).rev().flatten().collect()
        }),
    );
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    let burst_a: Vec<u8> = (1..=4u16).flat_map(|t| read_req(t, 1, 10 + t, 1)).collect();
    let burst_b: Vec<u8> = (1..=4u16).flat_map(|t| read_req(t, 1, 20 + t, 1)).collect();
    a.write_all(&burst_a).unwrap();
    b.write_all(&burst_b).unwrap();
    let mut got_a: Vec<_> = (0..4).map(|_| read_frame(&mut a)).collect();
    let mut got_b: Vec<_> = (0..4).map(|_| read_frame(&mut b)).collect();
    got_a.sort();
    got_b.sort();
    let want =
        |base: u16| -> Vec<Vec<u8>> { (1..=4u16).map(|t| read_reply(t, 1, &[base + t])).collect() };
    assert_eq!(got_a, want(10));
    assert_eq!(got_b, want(20));
    // Eight requests on the line with eight distinct serial ids.
    let mut ids: Vec<u16> = dev.requests().iter().map(|r| r.tid()).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), 8);
}

/// A device that answers twice: the second answer is recognised as one to mbgate's own
/// request and dropped, not broadcast to the other masters as a notification.
#[test]
fn duplicate_reply_is_not_broadcast() {
    let r = rig(|c| c.relay("notifications = \"broadcast\""));
    let mut inner = register_device(&[1], Duration::ZERO);
    let _dev = RawDevice::start(&r.socat.dev, Box::new(move |req| inner(req).repeat(2)));
    let mut masters = served_masters(&r.gw, 2);
    r.gw.wait_log("late reply dropped", Duration::from_secs(2));
    // Each master's next frame is its own reply.
    each_gets_its_own_reply(&mut masters, 40, 8);
}
