//! The relay in process: masters as outboxes on its channel, a device written in Rust on
//! the far end of an in-memory pipe (src/line/port/duplex.rs). No socat, no Python, no
//! sockets: every assertion is on bytes and on the relay's own counters (src/ops/stats.rs).
//! The socat/pymodbus tests stay as the outer ring (docs/architecture.md).

use mbgate::config::{Framing, Notifications, RelayConfig, SerialConfig};
use mbgate::frame::serial::Codec;
use mbgate::frame::Adu;
use mbgate::line::outbox::{Inbox, Outbox};
use mbgate::line::port::duplex::{self, DeviceEnd};
use mbgate::line::relay::{Command, ConnId, Relay, RelayHandle};
use mbgate::ops::stats::Stats;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};
use tokio::task::JoinHandle;
use tokio::time::{timeout, Instant};
use tokio_util::sync::CancellationToken;

const MS: Duration = Duration::from_millis(1);
/// 115200 bit/s, 8N1: one character on the wire.
const CHAR: Duration = Duration::from_nanos(86_806);

struct Gw {
    handle: RelayHandle,
    stats: Arc<Stats>,
    device: DeviceEnd,
    shutdown: CancellationToken,
    task: JoinHandle<()>,
    next_conn: ConnId,
}

fn serial(framing: Framing) -> SerialConfig {
    SerialConfig {
        path: "duplex".into(),
        baud_rate: 115_200,
        framing,
        silence_floor_ms: mbgate::config::Floor::Ms(5),
        ..SerialConfig::default()
    }
}

fn relay_cfg() -> RelayConfig {
    RelayConfig {
        response_timeout_ms: 300,
        frame_gap_ms: 20,
        ..RelayConfig::default()
    }
}

/// A relay over a pipe of `capacity` bytes each way.
fn start_with(cfg: RelayConfig, serial: SerialConfig, capacity: usize) -> Gw {
    let stats = Arc::new(Stats::default());
    let shutdown = CancellationToken::new();
    let (port, device) = duplex::pair(capacity, CHAR);
    let (relay, handle) = Relay::new(cfg, serial, false, stats.clone(), shutdown.clone());
    let task = tokio::spawn(relay.with_port(Box::new(port)).run());
    Gw {
        handle,
        stats,
        device,
        shutdown,
        task,
        next_conn: 1,
    }
}

fn start(cfg: RelayConfig) -> Gw {
    start_with(cfg, serial(Framing::Mbap), 4096)
}

/// One master: its tickets in request order, its replies in that order.
struct Master {
    conn: ConnId,
    outbox: Outbox,
    inbox: Inbox,
    handle: RelayHandle,
}

impl Gw {
    fn master(&mut self) -> Master {
        let conn = self.next_conn;
        self.next_conn += 1;
        let (outbox, inbox) = Outbox::new(16);
        self.handle
            .send(Command::Attach {
                conn,
                notifier: outbox.notifier(),
            })
            .unwrap();
        Master {
            conn,
            outbox,
            inbox,
            handle: self.handle.clone(),
        }
    }

    fn get(&self, counter: impl Fn(&Stats) -> &AtomicU64) -> u64 {
        self.stats.get(counter(&self.stats))
    }

    /// Waits until `counter` reaches `n` (the relay counts as it goes).
    async fn until(&self, what: &str, counter: impl Fn(&Stats) -> &AtomicU64, n: u64) {
        let t0 = Instant::now();
        while self.get(&counter) < n {
            assert!(
                t0.elapsed() < 3 * SEC,
                "{what} never reached {n}: {}",
                self.stats
            );
            tokio::time::sleep(MS).await;
        }
    }

    async fn stop(self) {
        self.shutdown.cancel();
        timeout(3 * SEC, self.task).await.expect("drained").unwrap();
    }
}

const SEC: Duration = Duration::from_secs(1);

impl Master {
    async fn send(&mut self, adu: Adu) {
        let ticket = self.outbox.ticket().await;
        self.handle
            .send(Command::Request {
                conn: self.conn,
                adu,
                ticket,
            })
            .unwrap();
    }

    async fn recv(&mut self) -> Adu {
        timeout(3 * SEC, self.inbox.next())
            .await
            .expect("an answer in time")
            .expect("open")
            .adu()
    }

    async fn nothing_for(&mut self, d: Duration) {
        if let Ok(got) = timeout(d, self.inbox.next()).await {
            panic!("expected nothing, got {:?}", got.map(|o| o.adu()));
        }
    }
}

/// FC 03 read of one register at `addr`.
fn read(tid: u16, unit: u8, addr: u16) -> Adu {
    let [hi, lo] = addr.to_be_bytes();
    Adu::build(tid, unit, &[0x03, hi, lo, 0x00, 0x01])
}

/// FC 06 write of `value` at `addr`.
fn write(tid: u16, unit: u8, addr: u16, value: u16) -> Adu {
    let [hi, lo] = addr.to_be_bytes();
    let [vh, vl] = value.to_be_bytes();
    Adu::build(tid, unit, &[0x06, hi, lo, vh, vl])
}

/// The register address a read or write names.
fn addr_of(adu: &Adu) -> u16 {
    u16::from_be_bytes([adu.pdu()[1], adu.pdu()[2]])
}

/// The device's answer to a read: the register holds its own address plus one.
fn answer(req: &Adu) -> Adu {
    match req.function() {
        0x03 => {
            let [hi, lo] = (addr_of(req) + 1).to_be_bytes();
            Adu::build(req.tid(), req.unit(), &[0x03, 0x02, hi, lo])
        }
        _ => Adu::build(req.tid(), req.unit(), req.pdu()),
    }
}

/// The value a read's reply carries.
fn value(reply: &Adu) -> u16 {
    assert_eq!(reply.function(), 0x03, "not a read reply: {reply:?}");
    u16::from_be_bytes([reply.pdu()[2], reply.pdu()[3]])
}

fn exception_of(reply: &Adu) -> Option<u8> {
    (reply.function() & 0x80 != 0).then(|| reply.pdu()[1])
}

/// Reads one MBAP frame from the device end.
async fn next_request(dev: &mut DuplexStream) -> Adu {
    let mut head = [0u8; 6];
    timeout(3 * SEC, dev.read_exact(&mut head))
        .await
        .expect("a request in time")
        .unwrap();
    let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
    let mut rest = vec![0u8; len];
    dev.read_exact(&mut rest).await.unwrap();
    let mut all = head.to_vec();
    all.extend(rest);
    Adu::from_frame(all.into())
}

async fn reply(dev: &mut DuplexStream, adu: &Adu) {
    dev.write_all(adu.as_bytes()).await.unwrap();
}

/// Nothing more arrives at the device for `d`.
async fn device_hears_nothing(dev: &mut DuplexStream, d: Duration) {
    let mut b = [0u8; 64];
    if let Ok(r) = timeout(d, dev.read(&mut b)).await {
        if matches!(r, Ok(0)) {
            return; // the relay closed the port: nothing more can come
        }
        panic!("device got {:?}", r.map(|n| b[..n].to_vec()));
    }
}

#[tokio::test]
async fn round_robin_a_master_that_starts_waiting_goes_ahead_of_the_one_just_served() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let (mut a, mut b) = (gw.master(), gw.master());
    a.send(read(1, 1, 100)).await;
    let first = next_request(&mut dev).await;
    // A queues three more while its first is on the line; B then queues one.
    for i in 1..4 {
        a.send(read(1 + i, 1, 100 + i)).await;
    }
    tokio::time::sleep(5 * MS).await;
    b.send(read(9, 1, 200)).await;
    tokio::time::sleep(5 * MS).await;
    let mut order = vec![addr_of(&first)];
    reply(&mut dev, &answer(&first)).await;
    for _ in 0..4 {
        let req = next_request(&mut dev).await;
        order.push(addr_of(&req));
        reply(&mut dev, &answer(&req)).await;
    }
    assert_eq!(order, [100, 200, 101, 102, 103], "one request each in turn");
    for i in 0..4u16 {
        let r = a.recv().await;
        assert_eq!(
            (r.tid(), value(&r)),
            (1 + i, 101 + i),
            "A's replies, A's ids"
        );
    }
    let r = b.recv().await;
    assert_eq!((r.tid(), value(&r)), (9, 201));
    assert_eq!(gw.get(|s| &s.replies), 5);
    assert_eq!(gw.get(|s| &s.requests), 5);
    gw.stop().await;
}

#[tokio::test]
async fn pipelining_puts_max_in_flight_on_the_line_and_answers_in_request_order() {
    let mut gw = start(RelayConfig {
        max_in_flight: 4,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    for i in 0..5u16 {
        // One transaction id for all, as many masters do.
        m.send(read(0, 1, 10 + i)).await;
    }
    let mut on_line = Vec::new();
    for _ in 0..4 {
        on_line.push(next_request(&mut dev).await);
    }
    device_hears_nothing(&mut dev, 30 * MS).await;
    let mut tids: Vec<u16> = on_line.iter().map(Adu::tid).collect();
    tids.sort_unstable();
    tids.dedup();
    assert_eq!(tids.len(), 4, "each on the line under its own id");
    // The device answers out of order.
    for req in on_line.iter().rev() {
        reply(&mut dev, &answer(req)).await;
    }
    let fifth = next_request(&mut dev).await;
    assert_eq!(addr_of(&fifth), 14, "the fifth once one was answered");
    reply(&mut dev, &answer(&fifth)).await;
    for i in 0..5u16 {
        let r = m.recv().await;
        assert_eq!((r.tid(), value(&r)), (0, 11 + i), "in request order");
    }
    assert_eq!(gw.get(|s| &s.replies), 5);
    gw.stop().await;
}

#[tokio::test]
async fn confirmation_a_reply_that_lost_a_byte_is_not_delivered_and_the_read_is_resent() {
    let mut gw = start(RelayConfig {
        max_in_flight: 2,
        retries: 1,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    m.send(read(1, 1, 10)).await;
    m.send(read(2, 1, 20)).await;
    let (r1, r2) = (next_request(&mut dev).await, next_request(&mut dev).await);
    // The first reply loses a byte of its value; the second follows back to back,
    // so the first borrows the second's first byte and looks whole.
    let mut bytes = answer(&r1).as_bytes().to_vec();
    bytes.remove(9);
    bytes.extend_from_slice(answer(&r2).as_bytes());
    dev.write_all(&bytes).await.unwrap();
    // Neither reply is usable (the second lost its first byte to the first): both
    // reads are resent, and answered whole this time.
    let mut resent = Vec::new();
    for _ in 0..2 {
        let again = next_request(&mut dev).await;
        resent.push(addr_of(&again));
        reply(&mut dev, &answer(&again)).await;
    }
    resent.sort_unstable();
    assert_eq!(resent, [10, 20], "both reads resent");
    let (a, b) = (m.recv().await, m.recv().await);
    assert_eq!((a.tid(), value(&a)), (1, 11), "never the shifted copy");
    assert_eq!((b.tid(), value(&b)), (2, 21));
    assert_eq!(gw.get(|s| &s.retries), 2);
    assert_eq!(gw.get(|s| &s.replies), 2);
    gw.stop().await;
}

#[tokio::test]
async fn retries_resend_reads_but_never_writes() {
    let mut gw = start(RelayConfig {
        retries: 2,
        response_timeout_ms: 100,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    m.send(read(7, 1, 10)).await;
    let first = next_request(&mut dev).await;
    // Ignored once: resent with the same bytes but a fresh id.
    let second = next_request(&mut dev).await;
    assert_eq!(second.pdu(), first.pdu());
    assert_ne!(second.tid(), first.tid());
    reply(&mut dev, &answer(&second)).await;
    let r = m.recv().await;
    assert_eq!((r.tid(), value(&r)), (7, 11));
    assert_eq!(gw.get(|s| &s.retries), 1);

    m.send(write(8, 1, 10, 0x1234)).await;
    let w = next_request(&mut dev).await;
    assert_eq!(w.function(), 0x06);
    let t0 = Instant::now();
    let r = m.recv().await;
    assert_eq!(
        exception_of(&r),
        Some(0x0B),
        "a write is answered, not resent"
    );
    assert!(
        t0.elapsed() >= 90 * MS,
        "after its timeout: {:?}",
        t0.elapsed()
    );
    device_hears_nothing(&mut dev, 50 * MS).await;
    assert_eq!(gw.get(|s| &s.retries), 1);
    assert_eq!(gw.get(|s| &s.timeouts), 1);
    gw.stop().await;
}

#[tokio::test]
async fn timeout_answers_0x0b_after_the_response_timeout_then_a_late_reply_is_dropped() {
    let mut gw = start(RelayConfig {
        response_timeout_ms: 150,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    let t0 = Instant::now();
    m.send(read(3, 1, 10)).await;
    let req = next_request(&mut dev).await;
    let r = m.recv().await;
    let waited = t0.elapsed();
    assert_eq!((r.tid(), exception_of(&r)), (3, Some(0x0B)));
    assert!(
        (140 * MS..600 * MS).contains(&waited),
        "0x0B after the timeout: {waited:?}"
    );
    assert_eq!(gw.get(|s| &s.timeouts), 1);
    // Its reply, late: recognised by its id, dropped, never delivered.
    reply(&mut dev, &answer(&req)).await;
    gw.until("late_replies", |s| &s.late_replies, 1).await;
    m.nothing_for(50 * MS).await;
    assert_eq!(
        gw.get(|s| &s.notifications_dropped),
        0,
        "not a notification"
    );
    gw.stop().await;
}

#[tokio::test]
async fn a_duplicate_reply_is_dropped_as_late() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    m.send(read(4, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer(&req)).await;
    let r = m.recv().await;
    assert_eq!(value(&r), 11);
    tokio::time::sleep(30 * MS).await;
    reply(&mut dev, &answer(&req)).await;
    gw.until("late_replies", |s| &s.late_replies, 1).await;
    m.nothing_for(50 * MS).await;
    assert_eq!(gw.get(|s| &s.replies), 1);
    gw.stop().await;
}

#[tokio::test]
async fn notifications_reach_every_master_or_are_dropped() {
    let notification = Adu::build(0, 1, &[0x03, 0x02, 0xAB, 0xCD]);
    for (mode, delivered) in [
        (Notifications::Broadcast, true),
        (Notifications::Drop, false),
    ] {
        let mut gw = start(RelayConfig {
            notifications: mode,
            ..relay_cfg()
        });
        let mut dev = gw.device.accept().await;
        let (mut a, mut b) = (gw.master(), gw.master());
        tokio::time::sleep(5 * MS).await;
        reply(&mut dev, &notification).await;
        if delivered {
            for m in [&mut a, &mut b] {
                assert_eq!(m.recv().await.as_bytes(), notification.as_bytes());
            }
            assert_eq!(gw.get(|s| &s.notifications_broadcast), 1);
        } else {
            gw.until("dropped", |s| &s.notifications_dropped, 1).await;
            a.nothing_for(30 * MS).await;
        }
        // The line carries on.
        a.send(read(1, 1, 10)).await;
        let req = next_request(&mut dev).await;
        reply(&mut dev, &answer(&req)).await;
        assert_eq!(value(&a.recv().await), 11);
        gw.stop().await;
    }
}

/// Reads one RTU request (FC 03/06: 8 bytes).
async fn next_rtu(dev: &mut DuplexStream) -> Vec<u8> {
    let mut b = [0u8; 8];
    timeout(3 * SEC, dev.read_exact(&mut b))
        .await
        .expect("a request in time")
        .unwrap();
    b.to_vec()
}

#[tokio::test]
async fn unit_backoff_answers_a_dead_unit_at_once_and_serves_the_others() {
    let mut gw = start_with(
        RelayConfig {
            response_timeout_ms: 60,
            unit_backoff_after: 2,
            unit_backoff_ms: 5_000,
            unit_backoff_max_ms: 5_000,
            ..relay_cfg()
        },
        serial(Framing::Rtu),
        4096,
    );
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    for i in 0..2 {
        m.send(read(i, 5, 10)).await;
        next_rtu(&mut dev).await;
        assert_eq!(exception_of(&m.recv().await), Some(0x0B));
    }
    assert_eq!(gw.get(|s| &s.timeouts), 2);
    // Backed off: answered without the line.
    let t0 = Instant::now();
    m.send(read(3, 5, 10)).await;
    assert_eq!(exception_of(&m.recv().await), Some(0x0B));
    assert!(t0.elapsed() < 50 * MS, "at once: {:?}", t0.elapsed());
    assert_eq!(gw.get(|s| &s.backed_off), 1);
    // Unit 1 is served as before.
    m.send(read(4, 1, 10)).await;
    let req = next_rtu(&mut dev).await;
    assert_eq!(req, Codec::Rtu.encode(1, &[0x03, 0x00, 0x0A, 0x00, 0x01]));
    // A reply cannot begin before the request has left the wire (8 characters).
    tokio::time::sleep(2 * MS).await;
    dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, 0x00, 0x0B]))
        .await
        .unwrap();
    assert_eq!(value(&m.recv().await), 11);
    gw.stop().await;
}

#[tokio::test]
async fn port_loss_answers_what_was_on_the_line_and_the_port_reopens() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    gw.until("opens", |s| &s.serial_opens, 1).await;
    m.send(read(1, 1, 10)).await;
    next_request(&mut dev).await;
    // Unplugged with the request on the line, and kept unplugged a while.
    gw.device.refuse_opens(true);
    drop(dev);
    let r = m.recv().await;
    assert_eq!(
        exception_of(&r),
        Some(0x0B),
        "it went out: it may have acted"
    );
    assert_eq!(gw.get(|s| &s.timeouts), 1);
    m.send(read(2, 1, 10)).await;
    assert_eq!(
        exception_of(&m.recv().await),
        Some(0x0A),
        "no path meanwhile"
    );
    assert_eq!(gw.get(|s| &s.unavailable), 1);
    // Plugged back: the relay reopens with backoff (100 ms first) and serves again.
    gw.device.refuse_opens(false);
    let mut dev = timeout(3 * SEC, gw.device.accept())
        .await
        .expect("reopened");
    gw.until("opens", |s| &s.serial_opens, 2).await;
    m.send(read(3, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer(&req)).await;
    assert_eq!(value(&m.recv().await), 11);
    gw.stop().await;
}

#[tokio::test]
async fn flow_control_withdraws_a_request_that_never_left() {
    // Room for one 12-byte request: the pipe stands in for CTS held low.
    let mut gw = start_with(
        RelayConfig {
            max_in_flight: 2,
            response_timeout_ms: 100,
            ..relay_cfg()
        },
        serial(Framing::Mbap),
        12,
    );
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    m.send(write(1, 1, 10, 1)).await;
    m.send(write(2, 1, 20, 2)).await;
    let (a, b) = (m.recv().await, m.recv().await);
    assert_eq!(
        (exception_of(&a), exception_of(&b)),
        (Some(0x0B), Some(0x0B))
    );
    // The device now reads: only the first ever reached it.
    let first = next_request(&mut dev).await;
    assert_eq!(addr_of(&first), 10);
    device_hears_nothing(&mut dev, 50 * MS).await;
    assert_eq!(gw.get(|s| &s.serial_bytes_out), 12);
    gw.stop().await;
}

#[tokio::test]
async fn shutdown_answers_the_queue_0x0a_and_waits_for_the_line() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let mut m = gw.master();
    m.send(read(1, 1, 10)).await;
    let req = next_request(&mut dev).await;
    m.send(read(2, 1, 20)).await;
    tokio::time::sleep(5 * MS).await;
    gw.shutdown.cancel();
    tokio::time::sleep(30 * MS).await;
    assert!(!gw.task.is_finished(), "waits for the request on the line");
    reply(&mut dev, &answer(&req)).await;
    let (a, b) = (m.recv().await, m.recv().await);
    assert_eq!(value(&a), 11, "the reply on the line is delivered");
    assert_eq!(exception_of(&b), Some(0x0A), "the queued one has no path");
    timeout(SEC, gw.task).await.expect("stopped").unwrap();
    device_hears_nothing(&mut dev, 20 * MS).await;
}

#[tokio::test]
/// A reply of the unit asked, its CRC or LRC good, but of another shape than the
/// request calls for (two registers for three asked: a device's own idea, or another
/// request's answer) is refused and counted, and the master gets 0x0B at once, as on
/// MBAP (docs/reliability.md "RTU and ASCII", 5).
async fn rtu_a_reply_of_another_shape_with_a_good_crc_is_refused_at_once() {
    for framing in [Framing::Rtu, Framing::Ascii] {
        let codec = if framing == Framing::Rtu {
            Codec::Rtu
        } else {
            Codec::Ascii
        };
        let mut gw = start_with(relay_cfg(), serial(framing), 4096);
        let mut dev = gw.device.accept().await;
        let mut m = gw.master();
        // Three registers asked, two answered (a device's own idea, or its error).
        m.send(Adu::build(5, 1, &[0x03, 0x00, 0x0A, 0x00, 0x03]))
            .await;
        let request = codec.encode(1, &[0x03, 0x00, 0x0A, 0x00, 0x03]);
        let mut got = vec![0u8; request.len()];
        timeout(3 * SEC, dev.read_exact(&mut got))
            .await
            .unwrap()
            .unwrap();
        assert_eq!(got, request);
        tokio::time::sleep(2 * MS).await;
        let t0 = Instant::now();
        let odd = [0x03, 0x04, 0x00, 0x0B, 0x00, 0x0C];
        dev.write_all(&codec.encode(1, &odd)).await.unwrap();
        let r = m.recv().await;
        assert_eq!(
            (r.tid(), r.unit(), r.pdu()),
            (5, 1, &[0x83, 0x0B][..]),
            "{framing:?}"
        );
        assert!(
            t0.elapsed() < 150 * MS,
            "not after the timeout: {:?}",
            t0.elapsed()
        );
        assert_eq!(gw.get(|s| &s.bad_frames), 1);
        assert_eq!(gw.get(|s| &s.replies), 0);
        gw.stop().await;
    }
}

/// MBAP has no checksum, but a whole frame with the request's id and unit, confirmed
/// by a pause like any reply, is the device's own answer: one whose shape does not fit
/// the request (two registers for one asked) is answered at once (docs/reliability.md),
/// 0x0B for a write or a read with no retry left, a resend under a fresh id for a read
/// that may be retried.
#[tokio::test]
async fn mbap_a_reply_of_another_shape_is_answered_at_once_not_after_the_timeout() {
    for retries in [0, 1] {
        let mut gw = start(RelayConfig {
            retries,
            response_timeout_ms: 1000,
            ..relay_cfg()
        });
        let mut dev = gw.device.accept().await;
        let mut m = gw.master();
        m.send(read(6, 1, 10)).await;
        let req = next_request(&mut dev).await;
        let t0 = Instant::now();
        let odd = Adu::build(req.tid(), 1, &[0x03, 0x04, 0x00, 0x0B, 0x00, 0x0C]);
        reply(&mut dev, &odd).await;
        if retries == 0 {
            let r = m.recv().await;
            assert_eq!((r.tid(), exception_of(&r)), (6, Some(0x0B)));
            assert_eq!(gw.get(|s| &s.retries), 0);
        } else {
            let again = next_request(&mut dev).await;
            assert_eq!(again.pdu(), req.pdu(), "the same read");
            assert_ne!(again.tid(), req.tid(), "under a fresh id");
            assert!(
                t0.elapsed() < 200 * MS,
                "resent at once: {:?}",
                t0.elapsed()
            );
            reply(&mut dev, &answer(&again)).await;
            let r = m.recv().await;
            assert_eq!((r.tid(), value(&r)), (6, 11));
            assert_eq!(gw.get(|s| &s.retries), 1);
            assert_eq!(gw.get(|s| &s.replies), 1);
        }
        assert!(
            t0.elapsed() < 200 * MS,
            "well before the 1 s timeout: {:?}",
            t0.elapsed()
        );
        assert_eq!(gw.get(|s| &s.bad_frames), 1);
        // The malformed reply's id is retired: sent again, it is a late reply.
        reply(&mut dev, &odd).await;
        gw.until("late_replies", |s| &s.late_replies, 1).await;
        m.nothing_for(30 * MS).await;
        // A write whose reply echoes another value: 0x0B at once, never resent.
        m.send(write(8, 1, 10, 0x1234)).await;
        let w = next_request(&mut dev).await;
        let t0 = Instant::now();
        reply(&mut dev, &write(w.tid(), 1, 10, 0x4321)).await;
        let r = m.recv().await;
        assert_eq!((r.tid(), exception_of(&r)), (8, Some(0x0B)));
        assert!(t0.elapsed() < 200 * MS, "at once: {:?}", t0.elapsed());
        device_hears_nothing(&mut dev, 30 * MS).await;
        assert_eq!(gw.get(|s| &s.bad_frames), 2);
        assert_eq!(gw.get(|s| &s.retries), retries.into());
        gw.stop().await;
    }
}

// ---------------------------------------------------------------------------------
// Many masters, one read: coalescing and the cache (docs/masters.md, "Many masters, one read")

/// A reply to `req` (FC 03 × 1) carrying `v`.
fn answer_with(req: &Adu, v: u16) -> Adu {
    let [hi, lo] = v.to_be_bytes();
    Adu::build(req.tid(), req.unit(), &[0x03, 0x02, hi, lo])
}

/// Answers a write with its echo, once the request has left the wire: a copy that
/// begins before is taken for the line's echo of the request (docs/cie-m10.md, "Confirmation and what it costs").
async fn reply_to_write(dev: &mut DuplexStream, req: &Adu) {
    tokio::time::sleep(3 * MS).await;
    reply(dev, &answer(req)).await;
}

/// Masters 2.. queue identical reads while master 1's read is on the line: they share
/// one transaction, each answered with its own id; master 1's read, already sent, is
/// joined by none of them; the line carries two transactions in all.
#[tokio::test]
async fn coalesce_identical_queued_reads_share_one_transaction_and_a_sent_one_is_not_joined() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let mut first = gw.master();
    let mut others: Vec<Master> = (0..3).map(|_| gw.master()).collect();
    first.send(read(0x100, 1, 10)).await;
    let on_line = next_request(&mut dev).await;
    for (i, m) in others.iter_mut().enumerate() {
        m.send(read(0x200 + i as u16, 1, 10)).await;
    }
    gw.until("coalesced", |s| &s.coalesced, 2).await;
    reply(&mut dev, &answer_with(&on_line, 1)).await;
    let r = first.recv().await;
    assert_eq!((r.tid(), value(&r)), (0x100, 1));
    let joint = next_request(&mut dev).await;
    assert_eq!(joint.pdu(), on_line.pdu(), "the same read, once");
    reply(&mut dev, &answer_with(&joint, 2)).await;
    for (i, m) in others.iter_mut().enumerate() {
        let r = m.recv().await;
        assert_eq!((r.tid(), value(&r)), (0x200 + i as u16, 2), "its own id");
    }
    device_hears_nothing(&mut dev, 30 * MS).await;
    assert_eq!(gw.get(|s| &s.coalesced), 2);
    assert_eq!(gw.get(|s| &s.requests), 4);
    assert_eq!(gw.get(|s| &s.replies), 4, "one for each master");
    assert_eq!(gw.get(|s| &s.serial_bytes_out), 2 * 12, "two transactions");

    // Off: the same reads are three transactions.
    let mut gw = start(RelayConfig {
        coalesce: false,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let mut ms: Vec<Master> = (0..3).map(|_| gw.master()).collect();
    for m in &mut ms {
        m.send(read(1, 1, 10)).await;
    }
    for _ in 0..3 {
        let req = next_request(&mut dev).await;
        reply(&mut dev, &answer(&req)).await;
    }
    for m in &mut ms {
        assert_eq!(value(&m.recv().await), 11);
    }
    assert_eq!(gw.get(|s| &s.coalesced), 0);
    gw.stop().await;
}

/// On an RTU line (one transaction at a time) too: the bytes the device sees are one
/// request for the masters that queued the same read.
#[tokio::test]
async fn coalesce_on_an_rtu_line_the_device_sees_one_request() {
    let mut gw = start_with(relay_cfg(), serial(Framing::Rtu), 4096);
    let mut dev = gw.device.accept().await;
    let mut a = gw.master();
    let (mut b, mut c) = (gw.master(), gw.master());
    a.send(read(1, 1, 20)).await;
    let req = Codec::Rtu.encode(1, &[0x03, 0x00, 0x14, 0x00, 0x01]);
    assert_eq!(next_rtu(&mut dev).await, req);
    b.send(read(7, 1, 10)).await;
    c.send(read(8, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 1).await;
    tokio::time::sleep(2 * MS).await;
    dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, 0x00, 0x15]))
        .await
        .unwrap();
    assert_eq!(value(&a.recv().await), 0x15);
    let joint = next_rtu(&mut dev).await;
    assert_eq!(joint, Codec::Rtu.encode(1, &[0x03, 0x00, 0x0A, 0x00, 0x01]));
    tokio::time::sleep(2 * MS).await;
    dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, 0x12, 0x34]))
        .await
        .unwrap();
    let (rb, rc) = (b.recv().await, c.recv().await);
    assert_eq!((rb.tid(), value(&rb)), (7, 0x1234));
    assert_eq!((rc.tid(), value(&rc)), (8, 0x1234));
    device_hears_nothing(&mut dev, 30 * MS).await;
    assert_eq!(
        gw.get(|s| &s.serial_bytes_out),
        16,
        "two requests of 8 bytes"
    );
    gw.stop().await;
}

/// A write to the unit queued between two identical reads (from a third master)
/// keeps them apart: the second read is sent after the write and sees it.
#[tokio::test]
async fn coalesce_a_write_between_two_identical_reads_prevents_the_merge() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let (mut a, mut b, mut w, mut d) = (gw.master(), gw.master(), gw.master(), gw.master());
    a.send(read(1, 1, 99)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(2, 1, 10)).await;
    w.send(write(3, 1, 10, 0x0777)).await;
    d.send(read(4, 1, 10)).await;
    tokio::time::sleep(10 * MS).await;
    reply(&mut dev, &answer(&blocking)).await;
    // The device holds register 10: 0 until written.
    let mut reg = 0u16;
    let mut seen = Vec::new();
    for _ in 0..3 {
        let req = next_request(&mut dev).await;
        seen.push(req.function());
        if req.function() == 0x06 {
            reg = u16::from_be_bytes([req.pdu()[3], req.pdu()[4]]);
            reply_to_write(&mut dev, &req).await;
        } else {
            reply(&mut dev, &answer_with(&req, reg)).await;
        }
    }
    assert_eq!(seen, [0x03, 0x06, 0x03], "read, write, read: not merged");
    device_hears_nothing(&mut dev, 30 * MS).await;
    assert_eq!(value(&b.recv().await), 0);
    assert_eq!(w.recv().await.function(), 0x06);
    let r = d.recv().await;
    assert_eq!(
        (r.tid(), value(&r)),
        (4, 0x0777),
        "sees the write before it"
    );
    assert_eq!(gw.get(|s| &s.coalesced), 0);
    a.recv().await;
    gw.stop().await;
}

/// What the line answers a joined read goes to every master joined: the device's
/// exception, a timeout's 0x0B (each counted), the reply after a resend, and 0x0A
/// when the relay shuts down with the read still queued.
#[tokio::test]
async fn coalesce_exceptions_timeouts_resends_and_shutdown_are_shared() {
    let mut gw = start(RelayConfig {
        response_timeout_ms: 100,
        retries: 1,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let (mut a, mut b, mut c) = (gw.master(), gw.master(), gw.master());
    // Held on the line while B and C queue the same read.
    let hold = |tid| read(tid, 1, 99);
    a.send(hold(1)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(0xB1, 1, 10)).await;
    c.send(read(0xC1, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 1).await;
    reply(&mut dev, &answer(&blocking)).await;
    let joint = next_request(&mut dev).await;
    reply(&mut dev, &Adu::exception(joint.tid(), 1, 0x03, 0x02)).await;
    let (rb, rc) = (b.recv().await, c.recv().await);
    assert_eq!((rb.tid(), exception_of(&rb)), (0xB1, Some(0x02)));
    assert_eq!((rc.tid(), exception_of(&rc)), (0xC1, Some(0x02)));
    assert_eq!(gw.get(|s| &s.replies), 3);

    // No reply: resent once (both still joined), then a reply for both.
    a.send(hold(2)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(0xB2, 1, 10)).await;
    c.send(read(0xC2, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 2).await;
    reply(&mut dev, &answer(&blocking)).await;
    let first_try = next_request(&mut dev).await;
    let again = next_request(&mut dev).await;
    assert_eq!(again.pdu(), first_try.pdu());
    assert_eq!(gw.get(|s| &s.retries), 1, "one resend for both");
    reply(&mut dev, &answer_with(&again, 0x55)).await;
    assert_eq!(value(&b.recv().await), 0x55);
    assert_eq!(value(&c.recv().await), 0x55);

    // No reply at all: 0x0B to both, counted for both.
    a.send(hold(3)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(0xB3, 1, 10)).await;
    c.send(read(0xC3, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 3).await;
    reply(&mut dev, &answer(&blocking)).await;
    next_request(&mut dev).await;
    next_request(&mut dev).await;
    let (rb, rc) = (b.recv().await, c.recv().await);
    assert_eq!((rb.tid(), exception_of(&rb)), (0xB3, Some(0x0B)));
    assert_eq!((rc.tid(), exception_of(&rc)), (0xC3, Some(0x0B)));
    assert_eq!(gw.get(|s| &s.timeouts), 2);

    // Shut down with the joined read queued: 0x0A to both.
    a.send(hold(4)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(0xB4, 1, 10)).await;
    c.send(read(0xC4, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 4).await;
    gw.shutdown.cancel();
    tokio::time::sleep(10 * MS).await;
    reply(&mut dev, &answer(&blocking)).await;
    let (rb, rc) = (b.recv().await, c.recv().await);
    assert_eq!((rb.tid(), exception_of(&rb)), (0xB4, Some(0x0A)));
    assert_eq!((rc.tid(), exception_of(&rc)), (0xC4, Some(0x0A)));
    assert_eq!(gw.get(|s| &s.unavailable), 2);
    for _ in 0..4 {
        a.recv().await;
    }
    timeout(SEC, gw.task).await.expect("stopped").unwrap();
    device_hears_nothing(&mut dev, 20 * MS).await;
}

/// The master a joined read was queued for disconnects: the read stays queued for the
/// master that joined it, which gets its reply; a joined master that disconnects while
/// the read is on the line takes nothing from the others.
#[tokio::test]
async fn coalesce_a_joined_master_that_disconnects_does_not_affect_the_others() {
    let mut gw = start(relay_cfg());
    let mut dev = gw.device.accept().await;
    let (mut a, mut b, mut c) = (gw.master(), gw.master(), gw.master());
    a.send(read(1, 1, 99)).await;
    let blocking = next_request(&mut dev).await;
    b.send(read(0xB, 1, 10)).await;
    c.send(read(0xC, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 1).await;
    // B, whose read C joined, goes away before it is sent.
    gw.handle.send(Command::Detach { conn: b.conn }).unwrap();
    drop(b);
    tokio::time::sleep(5 * MS).await;
    reply(&mut dev, &answer(&blocking)).await;
    let joint = next_request(&mut dev).await;
    assert_eq!(addr_of(&joint), 10);
    reply(&mut dev, &answer_with(&joint, 0x66)).await;
    let r = c.recv().await;
    assert_eq!((r.tid(), value(&r)), (0xC, 0x66));

    // Now C, joined to A's read, goes away while it is on the line.
    let mut d = gw.master();
    a.send(read(2, 1, 99)).await;
    let blocking = next_request(&mut dev).await;
    a.send(read(3, 1, 10)).await;
    c.send(read(0xC2, 1, 10)).await;
    d.send(read(0xD, 1, 10)).await;
    gw.until("coalesced", |s| &s.coalesced, 3).await;
    reply(&mut dev, &answer(&blocking)).await;
    let joint = next_request(&mut dev).await;
    gw.handle.send(Command::Detach { conn: c.conn }).unwrap();
    drop(c);
    tokio::time::sleep(5 * MS).await;
    reply(&mut dev, &answer_with(&joint, 0x77)).await;
    assert_eq!(value(&a.recv().await), 100);
    assert_eq!(value(&a.recv().await), 100);
    let ra = a.recv().await;
    assert_eq!((ra.tid(), value(&ra)), (3, 0x77));
    let rd = d.recv().await;
    assert_eq!((rd.tid(), value(&rd)), (0xD, 0x77));
    device_hears_nothing(&mut dev, 30 * MS).await;
    assert_eq!(gw.get(|s| &s.serial_bytes_out), 4 * 12);
    gw.stop().await;
}

/// `cache_ms`: a read is answered from the identical read's reply while that reply
/// is younger than `cache_ms` (the device hears nothing), not after; a write to the
/// unit clears it; an exception reply is never kept.
#[tokio::test]
async fn cache_serves_within_cache_ms_not_after_and_a_write_clears_it() {
    const CACHE: Duration = Duration::from_millis(400);
    let mut gw = start(RelayConfig {
        cache_ms: 400,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let (mut a, mut b) = (gw.master(), gw.master());
    a.send(read(1, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer_with(&req, 0x11)).await;
    assert_eq!(value(&a.recv().await), 0x11);
    let kept = Instant::now();
    b.send(read(2, 1, 10)).await;
    let r = b.recv().await;
    assert!(kept.elapsed() < CACHE, "the check below needs it young");
    assert_eq!((r.tid(), value(&r)), (2, 0x11), "from the cache");
    device_hears_nothing(&mut dev, 20 * MS).await;
    assert_eq!(gw.get(|s| &s.served_from_cache), 1);
    // Another register, or the same after cache_ms: the device is asked.
    b.send(read(3, 1, 11)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer(&req)).await;
    assert_eq!(value(&b.recv().await), 12);
    tokio::time::sleep_until(kept + CACHE + 50 * MS).await;
    b.send(read(4, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer_with(&req, 0x22)).await;
    assert_eq!(value(&b.recv().await), 0x22);
    // A write to the unit clears it.
    a.send(write(5, 1, 50, 1)).await;
    let req = next_request(&mut dev).await;
    reply_to_write(&mut dev, &req).await;
    assert_eq!(a.recv().await.function(), 0x06);
    b.send(read(6, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer_with(&req, 0x33)).await;
    assert_eq!(value(&b.recv().await), 0x33);
    // An exception is not kept.
    a.send(read(7, 1, 12)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &Adu::exception(req.tid(), 1, 0x03, 0x02)).await;
    assert_eq!(exception_of(&a.recv().await), Some(0x02));
    b.send(read(8, 1, 12)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer(&req)).await;
    assert_eq!(value(&b.recv().await), 13);
    assert_eq!(gw.get(|s| &s.served_from_cache), 1);
    gw.stop().await;
}

/// Several masters read a block while another writes to it; the device counts the
/// writes it has acted on and every register of the block reads that count. A read
/// sent after a write was answered must see at least that write: coalescing (and the
/// cache) never answer a master with a value older than its request.
#[tokio::test]
async fn mixed_readers_never_see_a_value_older_than_their_request_while_one_writes() {
    use std::sync::atomic::{AtomicBool, AtomicU16, Ordering};
    for cache_ms in [0, 200] {
        let mut gw = start(RelayConfig {
            cache_ms,
            ..relay_cfg()
        });
        let mut dev = gw.device.accept().await;
        let device = tokio::spawn(async move {
            let mut writes = 0u16;
            loop {
                let mut head = [0u8; 6];
                if dev.read_exact(&mut head).await.is_err() {
                    return writes;
                }
                let len = usize::from(u16::from_be_bytes([head[4], head[5]]));
                let mut rest = vec![0u8; len];
                dev.read_exact(&mut rest).await.unwrap();
                let req = Adu::from_frame([&head[..], &rest].concat().into());
                if req.function() == 0x06 {
                    writes += 1;
                    reply_to_write(&mut dev, &req).await;
                } else {
                    let n = usize::from(req.pdu()[4]);
                    let mut pdu = vec![0x03, 2 * n as u8];
                    for _ in 0..n {
                        pdu.extend(writes.to_be_bytes());
                    }
                    tokio::time::sleep(MS).await;
                    reply(&mut dev, &Adu::build(req.tid(), req.unit(), &pdu)).await;
                }
            }
        });
        let acked = Arc::new(AtomicU16::new(0));
        let done = Arc::new(AtomicBool::new(false));
        let mut writer = gw.master();
        let readers: Vec<_> = (0..6u16)
            .map(|r| {
                let mut m = gw.master();
                let (acked, done) = (acked.clone(), done.clone());
                tokio::spawn(async move {
                    // Until the writer is done (and a little after), bounded.
                    for i in 0..100u16 {
                        if done.load(Ordering::SeqCst) && i >= 10 {
                            break;
                        }
                        let tid = r * 1000 + i;
                        let at_least = acked.load(Ordering::SeqCst);
                        m.send(Adu::build(tid, 1, &[0x03, 0x00, 0x00, 0x00, 0x0A]))
                            .await;
                        let reply = m.recv().await;
                        assert_eq!(reply.tid(), tid);
                        assert_eq!(reply.pdu().len(), 22, "{reply:?}");
                        let seen = value(&reply);
                        assert!(
                            seen >= at_least,
                            "reader {r} saw {seen} after write {at_least} was answered"
                        );
                        // Each at its own pace: some join, some come after a reply.
                        tokio::time::sleep(u32::from(r) * MS).await;
                    }
                })
            })
            .collect();
        for n in 1..=10u16 {
            writer.send(write(0x1000 + n, 1, 0, n)).await;
            assert_eq!(writer.recv().await.function(), 0x06);
            acked.store(n, Ordering::SeqCst);
            tokio::time::sleep(20 * MS).await;
        }
        done.store(true, Ordering::SeqCst);
        for r in readers {
            r.await.unwrap();
        }
        let answered = gw.get(|s| &s.replies) + gw.get(|s| &s.served_from_cache);
        assert_eq!(
            answered,
            gw.get(|s| &s.requests),
            "every one answered normally"
        );
        let shared = gw.get(|s| &s.coalesced) + gw.get(|s| &s.served_from_cache);
        assert!(shared > 0, "nothing was shared: {}", gw.stats);
        eprintln!("cache_ms {cache_ms}: {}", gw.stats);
        gw.stop().await;
        assert_eq!(device.await.unwrap(), 10);
    }
}

/// A read that came after a write but went on the line before it (its master's turn
/// came first) is answered as it would be without the cache, but its reply is not
/// kept past the write: a master that reads after the write was answered is never
/// answered from before it.
#[tokio::test]
async fn cache_a_reply_read_before_a_write_went_out_is_not_kept_past_it() {
    let mut gw = start(RelayConfig {
        cache_ms: 2000,
        ..relay_cfg()
    });
    let mut dev = gw.device.accept().await;
    let (mut a, mut w, mut d, mut e) = (gw.master(), gw.master(), gw.master(), gw.master());
    a.send(read(1, 1, 99)).await;
    let blocking = next_request(&mut dev).await;
    // W queues a read, then a write; D's read comes after the write, and its turn
    // comes before the write's.
    w.send(read(2, 1, 50)).await;
    w.send(write(3, 1, 10, 7)).await;
    d.send(read(4, 1, 10)).await;
    tokio::time::sleep(5 * MS).await;
    reply(&mut dev, &answer(&blocking)).await;
    let mut reg = 0u16;
    let mut order = Vec::new();
    for _ in 0..3 {
        let req = next_request(&mut dev).await;
        order.push((req.function(), addr_of(&req)));
        if req.function() == 0x06 {
            reg = 7;
            reply_to_write(&mut dev, &req).await;
        } else {
            reply(
                &mut dev,
                &answer_with(&req, if addr_of(&req) == 10 { reg } else { 0 }),
            )
            .await;
        }
    }
    assert_eq!(
        order,
        [(0x03, 50), (0x03, 10), (0x06, 10)],
        "D's read went first"
    );
    assert_eq!(value(&d.recv().await), 0, "as without the cache");
    w.recv().await;
    assert_eq!(w.recv().await.function(), 0x06);
    // After the write was answered: the device is asked again.
    e.send(read(5, 1, 10)).await;
    let req = next_request(&mut dev).await;
    reply(&mut dev, &answer_with(&req, reg)).await;
    assert_eq!(
        value(&e.recv().await),
        7,
        "never the reply from before the write"
    );
    assert_eq!(gw.get(|s| &s.served_from_cache), 0);
    a.recv().await;
    gw.stop().await;
}

/// A switch of the in-memory bus that keeps the transmitter's state and logs each
/// switching; fails to switch on while `broken` is set.
struct FakeSwitch {
    on: Arc<std::sync::atomic::AtomicBool>,
    log: Arc<std::sync::Mutex<Vec<(Instant, bool)>>>,
    broken: Arc<std::sync::atomic::AtomicBool>,
}

impl mbgate::line::port::serial::direction::Switch for FakeSwitch {
    fn set(&mut self, transmit: bool) -> std::io::Result<()> {
        use std::sync::atomic::Ordering::SeqCst;
        if transmit && self.broken.load(SeqCst) {
            return Err(std::io::Error::other("the adapter is gone"));
        }
        self.on.store(transmit, SeqCst);
        self.log.lock().unwrap().push((Instant::now(), transmit));
        Ok(())
    }
}

/// `serial.direction` on a half-duplex bus (the pipe loses what the relay writes while
/// its transmitter is off): every request reaches the device whole, so the switch was
/// on before its first byte and stayed on past its last; the device, which answers only
/// once the bus is free, is answered; the switch goes on once per request, only after
/// the previous reply came (never while a reply can come), and stays on at least the
/// two delays; a switch that fails loses the port (0x0A: nothing was written) and the
/// port reopens; at shutdown the transmitter is left off.
#[tokio::test]
async fn direction_on_for_each_request_off_before_its_reply() {
    use mbgate::config::{Direction, FlowControl};
    use mbgate::line::port::duplex::Bus;
    use std::sync::atomic::Ordering::SeqCst;
    let on = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let log = Arc::new(std::sync::Mutex::new(Vec::new()));
    let broken = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let lost = Arc::new(AtomicU64::new(0));
    let (on2, log2, broken2) = (on.clone(), log.clone(), broken.clone());
    let bus = Bus {
        make: Arc::new(move || {
            Box::new(FakeSwitch {
                on: on2.clone(),
                log: log2.clone(),
                broken: broken2.clone(),
            })
        }),
        on: on.clone(),
        lost: lost.clone(),
    };
    let serial = SerialConfig {
        direction: Direction::Rts,
        flow_control: FlowControl::None,
        direction_delay_before_us: 300,
        direction_delay_after_us: 200,
        ..serial(Framing::Rtu)
    };
    let stats = Arc::new(Stats::default());
    let shutdown = CancellationToken::new();
    let (port, mut device) = duplex::pair(4096, CHAR);
    let port = port.with_switch(bus);
    let (relay, handle) = Relay::new(relay_cfg(), serial, false, stats.clone(), shutdown.clone());
    let task = tokio::spawn(relay.with_port(Box::new(port)).run());
    let mut gw = Gw {
        handle,
        stats,
        device: mbgate::line::port::duplex::pair(1, CHAR).1,
        shutdown,
        task,
        next_conn: 1,
    };
    let mut dev = device.accept().await;
    let mut m = gw.master();
    let mut replied = Vec::new();
    for i in 0..20u16 {
        m.send(read(i, 1, i)).await;
        let req = next_rtu(&mut dev).await;
        assert_eq!(
            req,
            Codec::Rtu.encode(1, &[0x03, 0x00, i as u8, 0x00, 0x01])
        );
        // The device answers once the bus is free.
        let t0 = Instant::now();
        while on.load(SeqCst) {
            assert!(t0.elapsed() < 3 * SEC, "the transmitter stayed on");
            tokio::time::sleep(Duration::from_micros(100)).await;
        }
        let [hi, lo] = (i + 1).to_be_bytes();
        dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, hi, lo]))
            .await
            .unwrap();
        assert_eq!(value(&m.recv().await), i + 1);
        replied.push(Instant::now());
    }
    assert_eq!(lost.load(SeqCst), 0, "no byte written while off");
    {
        let log = log.lock().unwrap();
        // Off when taken at open, then on and off once per request.
        assert_eq!(log.len(), 1 + 2 * 20, "{log:?}");
        assert!(!log[0].1);
        for (i, pair) in log[1..].chunks(2).enumerate() {
            let ((t_on, on_), (t_off, off_)) = (pair[0], pair[1]);
            assert!(on_ && !off_, "on then off: {pair:?}");
            assert!(
                t_off - t_on >= Duration::from_micros(500),
                "the delays before and after: {:?}",
                t_off - t_on
            );
            if i > 0 {
                assert!(t_on >= replied[i - 1], "on before the last reply came");
            }
        }
    }

    // The switch fails: the port is lost, the request never left (0x0A), the port
    // reopens with a new switch and serves again.
    broken.store(true, SeqCst);
    m.send(read(50, 1, 50)).await;
    assert_eq!(exception_of(&m.recv().await), Some(0x0A));
    broken.store(false, SeqCst);
    let mut dev = timeout(3 * SEC, device.accept()).await.expect("reopened");
    m.send(read(51, 1, 51)).await;
    let req = next_rtu(&mut dev).await;
    assert_eq!(req, Codec::Rtu.encode(1, &[0x03, 0x00, 51, 0x00, 0x01]));
    while on.load(SeqCst) {
        tokio::time::sleep(Duration::from_micros(100)).await;
    }
    dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, 0x00, 52]))
        .await
        .unwrap();
    assert_eq!(value(&m.recv().await), 52);
    assert_eq!(lost.load(SeqCst), 0);

    // Shutdown with the transmitter on (a request written, its reply not yet come):
    // left off.
    m.send(read(60, 1, 60)).await;
    next_rtu(&mut dev).await;
    gw.shutdown.cancel();
    let _ = timeout(3 * SEC, &mut gw.task).await.expect("stopped");
    assert!(!on.load(SeqCst), "left off");
    assert_eq!(log.lock().unwrap().last().map(|e| e.1), Some(false));
}

/// `echo = true` with the gateway switching the transmitter (a receiver left on while
/// sending reads the request back), by either method: the copy of the request is
/// read back and dropped, the reply after it taken.
#[tokio::test]
async fn direction_with_echo_drops_the_request_read_back() {
    use mbgate::config::{Direction, FlowControl};
    use mbgate::line::port::duplex::Bus;
    use std::sync::atomic::Ordering::SeqCst;
    for direction in [Direction::Rts, Direction::Gpio] {
        let on = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let lost = Arc::new(AtomicU64::new(0));
        let on2 = on.clone();
        let bus = Bus {
            make: Arc::new(move || {
                Box::new(FakeSwitch {
                    on: on2.clone(),
                    log: Arc::default(),
                    broken: Arc::default(),
                })
            }),
            on: on.clone(),
            lost: lost.clone(),
        };
        let serial = SerialConfig {
            direction,
            flow_control: FlowControl::None,
            echo: true,
            direction_gpio_line: mbgate::config::GpioLine::Offset(4),
            ..serial(Framing::Rtu)
        };
        let stats = Arc::new(Stats::default());
        let (port, mut device) = duplex::pair(4096, CHAR);
        let (relay, handle) = Relay::new(
            relay_cfg(),
            serial,
            false,
            stats.clone(),
            CancellationToken::new(),
        );
        let _task = tokio::spawn(relay.with_port(Box::new(port.with_switch(bus))).run());
        let (outbox, inbox) = Outbox::new(16);
        handle
            .send(Command::Attach {
                conn: 1,
                notifier: outbox.notifier(),
            })
            .unwrap();
        let mut m = Master {
            conn: 1,
            outbox,
            inbox,
            handle,
        };
        let mut dev = device.accept().await;
        for i in 0..5u16 {
            m.send(read(i, 1, i)).await;
            let req = next_rtu(&mut dev).await;
            // The bus gives the request back to the gateway's receiver, then the
            // device answers once the transmitter is off.
            dev.write_all(&req).await.unwrap();
            while on.load(SeqCst) {
                tokio::time::sleep(Duration::from_micros(100)).await;
            }
            let [hi, lo] = (i + 7).to_be_bytes();
            dev.write_all(&Codec::Rtu.encode(1, &[0x03, 0x02, hi, lo]))
                .await
                .unwrap();
            assert_eq!(value(&m.recv().await), i + 7, "{direction:?}");
        }
        assert_eq!(lost.load(SeqCst), 0);
        // Each echo (8 bytes) was read with its reply (7), and none taken for one.
        assert_eq!(
            stats.get(&stats.serial_bytes_in),
            5 * 15,
            "{direction:?}: {stats}"
        );
        assert_eq!(stats.get(&stats.bad_frames), 0, "{direction:?}: {stats}");
    }
}

/// A request held back (the pipe full, as with CTS low) times out with the
/// transmitter on: the master gets 0x0B and the transmitter goes off at the timeout
/// (it goes on again only to finish the frame begun, which keeps the device's parser in
/// step); the loop waits meanwhile rather than spinning.
#[tokio::test]
async fn direction_a_request_that_times_out_stuck_leaves_the_transmitter_off() {
    use mbgate::config::{Direction, FlowControl};
    use mbgate::line::port::duplex::Bus;
    use std::sync::atomic::Ordering::SeqCst;
    let on = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let log = Arc::new(std::sync::Mutex::new(Vec::new()));
    let (on2, log2) = (on.clone(), log.clone());
    let bus = Bus {
        make: Arc::new(move || {
            Box::new(FakeSwitch {
                on: on2.clone(),
                log: log2.clone(),
                broken: Arc::default(),
            })
        }),
        on: on.clone(),
        lost: Arc::default(),
    };
    let serial = SerialConfig {
        direction: Direction::Gpio,
        flow_control: FlowControl::None,
        direction_gpio_line: mbgate::config::GpioLine::Offset(4),
        ..serial(Framing::Rtu)
    };
    let stats = Arc::new(Stats::default());
    // Room for 4 bytes of the 8-byte request; the device never reads.
    let (port, mut device) = duplex::pair(4, CHAR);
    let cfg = RelayConfig {
        response_timeout_ms: 100,
        ..relay_cfg()
    };
    let (relay, handle) = Relay::new(cfg, serial, false, stats, CancellationToken::new());
    let _task = tokio::spawn(relay.with_port(Box::new(port.with_switch(bus))).run());
    let (outbox, inbox) = Outbox::new(16);
    handle
        .send(Command::Attach {
            conn: 1,
            notifier: outbox.notifier(),
        })
        .unwrap();
    let mut m = Master {
        conn: 1,
        outbox,
        inbox,
        handle,
    };
    let _dev = device.accept().await;
    m.send(read(1, 1, 1)).await;
    let t0 = Instant::now();
    while !on.load(SeqCst) {
        assert!(t0.elapsed() < 3 * SEC, "never switched on");
        tokio::time::sleep(Duration::from_micros(100)).await;
    }
    let t_on = log.lock().unwrap()[1].0;
    assert_eq!(
        exception_of(&m.recv().await),
        Some(0x0B),
        "it began to go out"
    );
    let log = log.lock().unwrap().clone();
    assert!(log[1].1, "{log:?}");
    assert!(!log[2].1, "off at the timeout: {log:?}");
    assert!(
        log[2].0 >= t_on + 100 * MS,
        "not before the timeout: {log:?}"
    );
}
