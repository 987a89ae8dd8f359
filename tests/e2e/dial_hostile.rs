//! The dial as an attacker or an odd SCADA server uses it: a scripted server on a raw
//! socket (this file's [`Scada`]) that mbgate dials, writing exact bytes at exact
//! times: answers of its own to the identity and the heartbeat glued to requests or a
//! few ms before them, answers and requests cut at every byte, echoes of everything
//! mbgate sends, slow and silent servers. Behind the gateway a raw MBAP device on a
//! socat pty records every byte the line brought ([`RawDevice::bytes`]), so each test
//! asserts what reached the line byte for byte, and what the server got back.
//!
//! The rules under test (docs/dialing.md "What the SCADA server must do"): no byte of
//! an answer is ever part of a request on the line; a request never takes bytes from
//! before a pause while an answer is owed; heartbeats and their answers are not
//! requests (the idle clock runs from the last request or reply); a server that echoes
//! every byte does not start a loop.

use crate::common;
use common::*;
use mbgate::frame::Adu;
use std::io::{ErrorKind, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

const IDENTITY: &[u8] = b"site-17";
const HEARTBEAT: &[u8] = &[0xff, 0xfe, 0x00, 0x01];

/// The gateway, the raw device behind it and the server it dials.
struct Rig {
    gw: Gateway,
    dev: RawDevice,
    scada: Scada,
    _socat: Socat,
    _dir: tempfile::TempDir,
}

/// A gateway with one MBAP line on a pty (a raw register device behind it, unit 1: a
/// register reads as its address, FC 06 writes), an accepted listener beside, and a
/// `[[dial]]` to a [`Scada`] on a free port with the identity `site-17`, short backoff
/// bounds, and the dial's `extra` keys.
fn rig(extra: &str) -> Rig {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let scada = Scada::new();
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000 }}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\
         [log]\nlevel = \"debug\"\n[metrics]\nlisten = \"127.0.0.1:0\"\n\
         [[dial]]\naddress = \"127.0.0.1:{}\"\nidentity = \"site-17\"\n\
         backoff_min_ms = 100\nbackoff_max_ms = 400\n{extra}",
        socat.gw.to_str().unwrap(),
        scada.port
    );
    let gw = Gateway::launch_text(&text, dir.path(), Launch::default());
    let mut regs = Registers::default();
    let dev = RawDevice::start(
        &socat.dev,
        Box::new(move |req: &Adu| {
            let pdu = regs.answer(req.unit(), req.pdu(), true);
            Adu::build(req.tid(), req.unit(), &pdu).as_bytes().to_vec()
        }),
    );
    Rig {
        gw,
        dev,
        scada,
        _socat: socat,
        _dir: dir,
    }
}

impl Rig {
    /// What the line brought since `from` (a length of [`RawDevice::bytes`]), cut into
    /// its MBAP frames: each one's unit and PDU (the line's transaction ids are the
    /// gateway's own). Fails if any byte is not in a whole request.
    fn line_since(&self, from: usize) -> Vec<Vec<u8>> {
        let bytes = self.dev.bytes();
        let mut rest = &bytes[from..];
        let mut out = Vec::new();
        while !rest.is_empty() {
            assert!(
                rest.len() >= 7,
                "the line got bytes that are no request: {}",
                hexs(rest)
            );
            assert_eq!(&rest[2..4], [0, 0], "the line got {}", hexs(&bytes[from..]));
            let n = 6 + usize::from(u16::from_be_bytes([rest[4], rest[5]]));
            assert!(
                rest.len() >= n,
                "the line got a part of a request: {}",
                hexs(rest)
            );
            out.push(rest[6..n].to_vec());
            rest = &rest[n..];
        }
        out
    }
}

/// A request's unit and PDU, as the line carries them.
fn body(req: &[u8]) -> Vec<u8> {
    req[6..].to_vec()
}

/// FC 06: register `addr` = `value`.
fn write6(tid: u16, addr: u16, value: u16) -> Vec<u8> {
    let mut pdu = vec![6];
    pdu.extend(addr.to_be_bytes());
    pdu.extend(value.to_be_bytes());
    Adu::build(tid, 1, &pdu).as_bytes().to_vec()
}

// ---------------------------------------------------------------------------------
// The scripted server

/// The SCADA server mbgate dials: a listening socket on 127.0.0.1, each connection
/// taken and scripted by the test.
struct Scada {
    listener: TcpListener,
    port: u16,
}

impl Scada {
    fn new() -> Scada {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        listener.set_nonblocking(true).unwrap();
        Scada { listener, port }
    }

    /// The next connection mbgate makes (within 20 s), its identity read and checked.
    fn take(&self) -> Conn {
        let until = Instant::now() + Duration::from_secs(20);
        let s = loop {
            match self.listener.accept() {
                Ok((s, _)) => break s,
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    assert!(Instant::now() < until, "mbgate did not dial in 20 s");
                    std::thread::sleep(Duration::from_millis(5));
                }
                Err(e) => panic!("accept: {e}"),
            }
        };
        s.set_nonblocking(false).unwrap();
        s.set_nodelay(true).unwrap();
        let mut c = Conn { s, got: Vec::new() };
        c.expect(IDENTITY);
        c
    }
}

/// One connection of mbgate's, as the server sees it.
struct Conn {
    s: TcpStream,
    /// What mbgate sent that was not taken yet.
    got: Vec<u8>,
}

impl Conn {
    fn write(&mut self, bytes: &[u8]) {
        self.s.write_all(bytes).expect("write to mbgate");
    }

    /// Reads more within `within`; false if nothing came (or the connection ended).
    fn more(&mut self, within: Duration) -> bool {
        let within = within.max(Duration::from_millis(1));
        self.s.set_read_timeout(Some(within)).unwrap();
        let mut chunk = [0u8; 4096];
        match self.s.read(&mut chunk) {
            Ok(0) | Err(_) => false,
            Ok(n) => {
                self.got.extend_from_slice(&chunk[..n]);
                true
            }
        }
    }

    /// `bytes` are what mbgate sends next (within 10 s).
    fn expect(&mut self, bytes: &[u8]) {
        let until = Instant::now() + Duration::from_secs(10);
        while self.got.len() < bytes.len() {
            let left = until.saturating_duration_since(Instant::now());
            assert!(
                !left.is_zero() && self.more(left),
                "expected {}, got {}",
                hexs(bytes),
                hexs(&self.got)
            );
        }
        assert_eq!(hexs(&self.got[..bytes.len()]), hexs(bytes));
        self.got.drain(..bytes.len());
    }

    /// The next heartbeat, the heartbeats before it skipped too.
    fn beat(&mut self) {
        self.expect(HEARTBEAT);
    }

    /// The frames mbgate sends (heartbeats passed over) until the reply with
    /// transaction id `tid` (within 10 s): every frame, that one last. `None` if the
    /// connection ended or nothing came in time.
    fn until_reply(&mut self, tid: u16) -> Option<Vec<Vec<u8>>> {
        let until = Instant::now() + Duration::from_secs(10);
        let mut frames = Vec::new();
        loop {
            while let Some(f) = self.frame() {
                let done = f[..2] == tid.to_be_bytes();
                frames.push(f);
                if done {
                    return Some(frames);
                }
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() || !self.more(left) {
                return None;
            }
        }
    }

    /// A whole frame at the front of what came, heartbeats taken off first.
    fn frame(&mut self) -> Option<Vec<u8>> {
        while self.got.starts_with(HEARTBEAT) {
            self.got.drain(..HEARTBEAT.len());
        }
        if self.got.len() < 6 {
            return None;
        }
        let n = 6 + usize::from(u16::from_be_bytes([self.got[4], self.got[5]]));
        (self.got.len() >= n).then(|| self.got.drain(..n).collect())
    }

    /// Has mbgate closed the connection (within `within`)?
    fn closed(&mut self, within: Duration) -> bool {
        let until = Instant::now() + within;
        while Instant::now() < until {
            self.s
                .set_read_timeout(Some(Duration::from_millis(100)))
                .unwrap();
            let mut chunk = [0u8; 512];
            match self.s.read(&mut chunk) {
                Ok(0) => return true,
                Ok(n) => self.got.extend_from_slice(&chunk[..n]),
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(_) => return true,
            }
        }
        false
    }
}

/// Runs `script` at real-time priority where the test may set it (root, as CI runs
/// it): its short pauses (a request 1 ms after an answer, the two halves of a write 2
/// ms apart) are premises of the tests, and a busy machine must not stretch them.
fn scripted<T: Send + 'static>(script: impl FnOnce() -> T + Send + 'static) -> T {
    std::thread::spawn(move || {
        let param = libc::sched_param { sched_priority: 1 };
        // SAFETY: `param` is valid for the call; 0 is this thread.
        unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
        script()
    })
    .join()
    .expect("the script")
}

// ---------------------------------------------------------------------------------
// Answers and requests glued, split and paused

/// The case as found: the server answers the heartbeat with `00 00 00 00 00 06` in
/// one write, waits 50 ms and sends an FC 03 read of register 3. The line gets the
/// read and nothing else (before: `01 06 00 00 00 06`, a write of register 0 = 6), and
/// the server the read's reply and nothing else (before: a reply with id 0 to a
/// request it never sent, and none to its read).
#[test]
fn a_header_shaped_answer_never_becomes_a_write() {
    let mut r = rig("heartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 300\n");
    let mut c = r.scada.take();
    let from = r.dev.bytes().len();
    let read = read_req(1, 1, 3, 1);
    let frames = scripted(move || {
        c.beat();
        c.write(&[0, 0, 0, 0, 0, 6]);
        std::thread::sleep(Duration::from_millis(50));
        c.write(&read);
        let frames = c.until_reply(1);
        drop(c);
        frames
    });
    let line = r.line_since(from);
    for body in &line {
        assert_eq!(body, &[1, 3, 0, 3, 0, 1], "the line got {line:02x?}");
    }
    // 50 ms is five times the pause: the read came after one and is answered (on a
    // machine so busy that mbgate read the two together, it was lost with the answer:
    // still nothing else on the line, nothing else back).
    match frames {
        Some(f) => assert_eq!(f, vec![read_reply(1, 1, &[3])]),
        None => eprintln!("the read was lost with the answer (read together)"),
    }
    let counters = r.gw.stop();
    assert!(counters["dial_answers"] >= 1, "{counters:?}");
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
}

/// Answers of the server's own to the identity (`06`, "OK", "OK\r\n",
/// `00 00 00 00 00 06`), each followed by a read in the same write, or 1, 5, 50 or
/// 500 ms after it, then another read 500 ms later. Whatever the gap, the line gets
/// only whole reads the server sent (never an answer's byte), and the server only
/// replies to its own reads, right by value. A read in the answer's write is lost
/// with it; one 500 ms after it is answered (before: a 1- or 2-byte answer took it
/// with it whatever the pause); the read after a pause always is.
#[test]
fn answers_glued_to_requests_never_reach_the_line() {
    let r = rig("");
    let mut round = 0u16;
    for answer in [&b"\x06"[..], b"OK", b"OK\r\n", &[0, 0, 0, 0, 0, 6]] {
        for gap in [0u64, 1, 5, 50, 500] {
            round += 1;
            let (first, second) = (100 + 2 * round, 101 + 2 * round);
            let (r1, r2) = (read_req(1, 1, first, 1), read_req(2, 1, second, 1));
            let from = r.dev.bytes().len();
            let mut c = r.scada.take();
            let (ans, a, b) = (answer.to_vec(), r1.clone(), r2.clone());
            let frames = scripted(move || {
                if gap == 0 {
                    c.write(&[ans, a].concat());
                } else {
                    c.write(&ans);
                    std::thread::sleep(Duration::from_millis(gap));
                    c.write(&a);
                }
                std::thread::sleep(Duration::from_millis(500));
                c.write(&b);
                c.until_reply(2)
            });
            let said = format!("{answer:02x?} then {gap} ms");
            let frames = frames.unwrap_or_else(|| {
                panic!(
                    "{said}: no reply to the read after the pause\n{}",
                    r.gw.log()
                )
            });
            // The first read's reply, if it came, came first.
            let answered_first = frames.len() == 2;
            if answered_first {
                assert_eq!(frames[0], read_reply(1, 1, &[first]), "{said}");
            }
            assert_eq!(
                frames.last().unwrap(),
                &read_reply(2, 1, &[second]),
                "{said}"
            );
            assert!(frames.len() <= 2, "{said}: {frames:02x?}");
            let line = r.line_since(from);
            let want: Vec<Vec<u8>> = match answered_first {
                true => vec![body(&r1), body(&r2)],
                false => vec![body(&r2)],
            };
            assert_eq!(line, want, "{said}");
            match gap {
                0 => assert!(!answered_first, "{said}: the read in the answer's write"),
                500 => assert!(answered_first, "{said}: the read 500 ms after the answer"),
                _ => {}
            }
        }
    }
}

/// While an answer is owed (after each heartbeat), a request cut at every byte into
/// two writes 2 ms apart, and the answer "OK\r\n" itself cut in two: each request
/// reaches the line whole, each answer is dropped.
#[test]
fn writes_cut_at_every_byte_join() {
    let mut r = rig("heartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 100\n");
    let mut c = r.scada.take();
    let from = r.dev.bytes().len();
    let n = read_req(0, 1, 0, 1).len();
    let frames = scripted(move || {
        let mut replies = Vec::new();
        for cut in 1..n {
            let tid = cut as u16;
            let req = read_req(tid, 1, 200 + tid, 1);
            c.beat();
            if cut % 2 == 0 {
                c.write(b"O");
                std::thread::sleep(Duration::from_millis(2));
                c.write(b"K\r\n");
                std::thread::sleep(Duration::from_millis(300));
            }
            c.write(&req[..cut]);
            std::thread::sleep(Duration::from_millis(2));
            c.write(&req[cut..]);
            replies.push(c.until_reply(tid));
        }
        replies
    });
    for (i, f) in frames.iter().enumerate() {
        let tid = i as u16 + 1;
        assert_eq!(
            f.as_deref(),
            Some(&[read_reply(tid, 1, &[200 + tid])][..]),
            "cut at {tid}"
        );
    }
    let line = r.line_since(from);
    let want: Vec<Vec<u8>> = (1..n as u16)
        .map(|t| body(&read_req(t, 1, 200 + t, 1)))
        .collect();
    assert_eq!(line, want);
    let counters = r.gw.stop();
    assert_eq!(counters["protocol_violations"], 0, "{counters:?}");
    assert_eq!(counters["dial_answers"], (n as u64 - 1) / 2, "{counters:?}");
}

/// A request cut by a pause of 300 ms while the identity's answer is owed: its first
/// part is taken for the answer and its rest breaks the protocol (the connection is
/// closed and dialed again); nothing of it reaches the line (before: the two parts
/// were joined, whatever the pause).
#[test]
fn a_pause_never_joins_the_parts_of_a_request_while_an_answer_is_owed() {
    let mut r = rig("");
    let mut c = r.scada.take();
    let from = r.dev.bytes().len();
    let req = read_req(1, 1, 300, 1);
    let closed = scripted(move || {
        c.write(&req[..5]);
        std::thread::sleep(Duration::from_millis(300));
        c.write(&req[5..]);
        c.closed(Duration::from_secs(10))
    });
    assert!(closed, "{}", r.gw.log());
    assert_eq!(r.line_since(from), Vec::<Vec<u8>>::new());
    let counters = r.gw.stop();
    assert_eq!(counters["protocol_violations"], 1, "{counters:?}");
}

/// A slow server, once nothing is owed (the identity's answer lapses after
/// `connect_timeout_ms`): a read trickled a byte every 50 ms reaches the line whole
/// and is answered. A silent one is sent heartbeats and closed after
/// `idle_timeout_ms`.
#[test]
fn a_slow_server_is_served_and_a_silent_one_closed() {
    let r = rig("connect_timeout_ms = 500\nidle_timeout_ms = 3000\n\
         heartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 5000\n");
    let mut c = r.scada.take();
    let from = r.dev.bytes().len();
    let req = read_req(1, 1, 77, 1);
    let frames = scripted(move || {
        std::thread::sleep(Duration::from_millis(1000));
        for b in req {
            c.write(&[b]);
            std::thread::sleep(Duration::from_millis(50));
        }
        let frames = c.until_reply(1);
        // Silent from now on: closed idle_timeout_ms after the reply.
        let quiet = Instant::now();
        let closed = c.closed(Duration::from_secs(15));
        (frames, closed, quiet.elapsed())
    });
    assert_eq!(frames.0, Some(vec![read_reply(1, 1, &[77])]));
    assert_eq!(r.line_since(from), vec![body(&read_req(1, 1, 77, 1))]);
    assert!(frames.1, "a silent server is closed: {}", r.gw.log());
    // From the reply read, a little after it was written.
    assert!(
        frames.2 >= Duration::from_millis(2000),
        "closed after {:?}",
        frames.2
    );
}

// ---------------------------------------------------------------------------------
// Heartbeats are no requests

/// A dial with `idle_timeout_ms = 1500` and a heartbeat every 300 ms, to a server
/// that sends no request and echoes every heartbeat (then, on the next connection,
/// answers each "OK\r\n"): mbgate closes each connection about 1.5 s after it opened,
/// never sooner (before: never, 20 heartbeats and more).
#[test]
fn heartbeats_and_their_answers_do_not_keep_a_dial_alive() {
    let r = rig("idle_timeout_ms = 1500\nheartbeat = \"hex:ff fe 00 01\"\nheartbeat_ms = 300\n");
    for answer in [HEARTBEAT, b"OK\r\n"] {
        let mut c = r.scada.take();
        let opened = Instant::now();
        let (beats, closed) = scripted(move || {
            let mut beats = 0;
            let until = Instant::now() + Duration::from_secs(10);
            while Instant::now() < until {
                // A heartbeat, or the end of the connection.
                while !c.got.starts_with(HEARTBEAT) {
                    if !c.more(until.saturating_duration_since(Instant::now())) {
                        return (beats, Instant::now() < until);
                    }
                }
                c.got.drain(..HEARTBEAT.len());
                beats += 1;
                c.write(answer);
            }
            (beats, false)
        });
        let lived = opened.elapsed();
        assert!(
            closed,
            "{answer:02x?}: never closed, {beats} heartbeats answered"
        );
        // From the identity read, a little after the connection opened.
        assert!(
            lived >= Duration::from_millis(1000),
            "{answer:02x?}: closed after {lived:?}"
        );
        eprintln!("{answer:02x?}: closed after {lived:?}, {beats} heartbeats answered");
    }
    assert!(r.gw.log().contains("idle timeout"), "{}", r.gw.log());
}

// ---------------------------------------------------------------------------------
// An echo of everything

/// A server that echoes every byte it receives, and sends one request of each kind:
/// a read, an FC 06 write, and a request the gateway answers itself with an exception
/// (FC 03 of no register). The bytes going back and forth stay a handful of frames
/// (before: 1.8 MB in 3 s, a reply loop), the line gets the read and the write once
/// each, and the echoes are counted.
///
/// The loop ends by the masters' rule that a reply is never a request (a frame with
/// the exception bit, a reply's shape, or the very reply just sent, dropped and
/// counted): this test needs it in the shared reader.
#[test]
fn a_server_echoing_every_byte_starts_no_loop() {
    let r = rig("");
    let mut c = r.scada.take();
    let from = r.dev.bytes().len();
    // The identity echoed, then the requests, one every 500 ms, every byte echoed.
    let requests = [
        read_req(1, 1, 3, 1),
        write6(2, 120, 7),
        read_req(3, 1, 0, 0),
    ];
    let (sent, echoed) = scripted(move || {
        c.write(IDENTITY);
        let (mut sent, mut echoed) = (IDENTITY.len(), 0usize);
        let start = Instant::now();
        let mut next = 0;
        while start.elapsed() < Duration::from_secs(3) {
            if next < requests.len() && start.elapsed() >= Duration::from_millis(500 * next as u64)
            {
                c.write(&requests[next]);
                sent += requests[next].len();
                next += 1;
            }
            if c.more(Duration::from_millis(20)) {
                let got = std::mem::take(&mut c.got);
                echoed += got.len();
                c.write(&got);
                sent += got.len();
            }
        }
        (sent, echoed)
    });
    eprintln!("echo: {sent} bytes to mbgate, {echoed} from it in 3 s");
    assert!(sent + echoed < 1000, "{sent} bytes sent, {echoed} echoed");
    let line = r.line_since(from);
    assert_eq!(
        line,
        vec![body(&read_req(1, 1, 3, 1)), body(&write6(2, 120, 7))]
    );
}
