//! The virtual line (`mbgate wire`, docs/simulator.md "A virtual line") against real
//! peers, and the gateway's timing rules proven on it with a third-party device behind
//! it: bytes take their time at the sender's baud rate, other baud rates garble
//! (pymodbus' client and server at different rates never make a transaction), loss is
//! the rate asked, echo returns the sender's bytes; with the gateway's port declared a
//! wire and a pymodbus RTU server on the far end, the echo, a frame just before or
//! crossing a request, the gap, late replies and a reply 3.5 characters after its
//! request each give every master its own answer or 0x0B, 0 wrong.

use crate::common;
use common::*;
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A running `mbgate wire` and its two ends.
struct Line {
    _proc: Proc,
    a: PathBuf,
    b: PathBuf,
    _dir: tempfile::TempDir,
}

impl Line {
    fn start(extra: &[&str]) -> Line {
        let dir = tempdir();
        let a = dir.path().join("a");
        let b = dir.path().join("b");
        let mut args = vec!["wire", a.to_str().unwrap(), b.to_str().unwrap()];
        args.extend_from_slice(extra);
        let proc = Proc::start(&args, "ready");
        Line {
            _proc: proc,
            a,
            b,
            _dir: dir,
        }
    }
}

/// Opens a pty end raw at `speed` (a termios B constant), non-blocking.
fn open_at(path: &Path, speed: libc::speed_t) -> std::fs::File {
    let f = open_pty(path);
    let fd = f.as_raw_fd();
    // SAFETY: termios is plain data, filled by tcgetattr before use; valid fd.
    unsafe {
        let mut t: libc::termios = std::mem::zeroed();
        assert_eq!(libc::tcgetattr(fd, &mut t), 0);
        libc::cfmakeraw(&mut t);
        libc::cfsetspeed(&mut t, speed);
        assert_eq!(libc::tcsetattr(fd, libc::TCSANOW, &t), 0);
    }
    f
}

/// Waits (poll(2), at most `within`) until `f` has bytes, then reads them.
fn read_some(f: &mut std::fs::File, within: Duration) -> Vec<u8> {
    let mut p = libc::pollfd {
        fd: f.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    // SAFETY: one valid pollfd.
    let n = unsafe { libc::poll(&mut p, 1, within.as_millis() as i32) };
    if n <= 0 {
        return Vec::new();
    }
    let mut buf = [0u8; 4096];
    match f.read(&mut buf) {
        Ok(n) => buf[..n].to_vec(),
        Err(_) => Vec::new(),
    }
}

/// Reads until `want` bytes came or nothing came for `quiet`.
fn read_until(f: &mut std::fs::File, want: usize, quiet: Duration) -> Vec<u8> {
    let mut got = Vec::new();
    while got.len() < want {
        let more = read_some(f, quiet);
        if more.is_empty() {
            break;
        }
        got.extend(more);
    }
    got
}

/// 10 bits at 9600 baud.
const CHAR_9600: Duration = Duration::from_nanos(1_041_667);

/// A byte written at 9600 8N1 is read at the other end no sooner than its 10 bits'
/// time, 1.0417 ms, and (generously, for a loaded machine) within 1 s. The tight
/// figure is docs/performance.md's.
#[test]
fn a_byte_at_9600_takes_its_ten_bits() {
    let line = Line::start(&[]);
    let mut a = open_at(&line.a, libc::B9600);
    let mut b = open_at(&line.b, libc::B9600);
    let mut took = Vec::new();
    for i in 0..20u8 {
        let t0 = Instant::now();
        a.write_all(&[i]).unwrap();
        let got = read_some(&mut b, Duration::from_secs(2));
        let dt = t0.elapsed();
        assert_eq!(got, vec![i]);
        assert!(
            dt >= CHAR_9600,
            "byte {i} after {dt:?}, under a character time"
        );
        assert!(dt < Duration::from_secs(1), "byte {i} after {dt:?}");
        took.push(dt);
        std::thread::sleep(Duration::from_millis(3));
    }
    took.sort();
    eprintln!(
        "9600 8N1, one byte: median {:?}, max {:?}",
        took[10], took[19]
    );
}

/// 1000 bytes written at once at 9600 8N1 arrive whole and in order, the last no
/// sooner than 1000 character times (1.0417 s) after the write.
#[test]
fn a_thousand_bytes_take_a_thousand_character_times() {
    let line = Line::start(&[]);
    let mut a = open_at(&line.a, libc::B9600);
    let mut b = open_at(&line.b, libc::B9600);
    let sent: Vec<u8> = (0..1000u32).map(|i| (i * 7 % 256) as u8).collect();
    let t0 = Instant::now();
    a.write_all(&sent).unwrap();
    let mut got = Vec::new();
    let mut first = None;
    while got.len() < sent.len() && t0.elapsed() < Duration::from_secs(10) {
        let more = read_some(&mut b, Duration::from_secs(1));
        if !more.is_empty() && first.is_none() {
            first = Some(t0.elapsed());
        }
        got.extend(more);
    }
    let dt = t0.elapsed();
    assert_eq!(got, sent);
    assert!(dt >= CHAR_9600 * 1000, "1000 bytes in {dt:?}");
    assert!(dt < Duration::from_secs(5), "1000 bytes in {dt:?}");
    assert!(first.unwrap() >= CHAR_9600);
    eprintln!("9600 8N1, 1000 bytes: {dt:?}");
}

/// pymodbus' serial client and its RTU server, each at its own baud rate behind the
/// line: at the same rate the read is answered, at different rates never (the server
/// hears garbage, or the client does). Both directions of mismatch.
#[test]
fn other_baud_rates_make_no_transaction() {
    for (client, server, answered) in [
        ("9600", "9600", true),
        ("19200", "9600", false),
        ("9600", "19200", false),
        ("115200", "9600", false),
    ] {
        let line = Line::start(&[]);
        let b = line.b.to_str().unwrap();
        let _device = Py::start(
            "serial_device.py",
            &[
                "--port", b, "--framer", "rtu", "--baud", server, "--units", "1",
            ],
        );
        let (status, out) = Py::run(
            "serial_read.py",
            &[
                "--port",
                line.a.to_str().unwrap(),
                "--baud",
                client,
                "--unit",
                "1",
                "--timeout",
                "1",
            ],
        );
        assert!(status.success(), "{out}");
        if answered {
            assert_eq!(out.trim(), "REPLY 255", "client {client}, server {server}");
        } else {
            assert!(
                out.starts_with("NO REPLY"),
                "client {client}, server {server}: {out}"
            );
        }
    }
}

/// Bytes that cross at the same rate but are read at another: what the receiver
/// gets is not what was sent (and, read as 8N1 at 19200, a 9600 byte becomes two).
#[test]
fn a_receiver_at_another_rate_reads_garbage() {
    let line = Line::start(&[]);
    let mut a = open_at(&line.a, libc::B9600);
    let mut b = open_at(&line.b, libc::B19200);
    let sent = [0x01, 0x03, 0x00, 0x00, 0x00, 0x01, 0x84, 0x0A];
    a.write_all(&sent).unwrap();
    let got = read_until(&mut b, 64, Duration::from_secs(1));
    assert!(!got.is_empty(), "nothing at all arrived");
    assert_ne!(got, sent);
}

/// `--loss 0.2` over 4000 bytes at 115200: 20 % lost, within five standard deviations
/// (800 ± 126), and the same seed loses the same count again.
#[test]
fn loss_is_the_rate_asked() {
    let mut counts = Vec::new();
    for _ in 0..2 {
        let line = Line::start(&["--loss", "0.2", "--seed", "11"]);
        let mut a = open_at(&line.a, libc::B115200);
        let mut b = open_at(&line.b, libc::B115200);
        let sent = vec![0x55u8; 4000];
        for chunk in sent.chunks(500) {
            a.write_all(chunk).unwrap();
        }
        let got = read_until(&mut b, 4000, Duration::from_secs(2));
        assert!(got.iter().all(|&x| x == 0x55), "a lost byte garbles none");
        counts.push(got.len());
    }
    let lost = 4000 - counts[0];
    assert!((674..=926).contains(&lost), "{lost} of 4000 lost");
    assert_eq!(counts[0], counts[1], "the same seed, the same losses");
}

/// `--echo`: the sender reads its own bytes back, and the other end gets them too.
#[test]
fn echo_returns_the_senders_bytes() {
    let line = Line::start(&["--echo"]);
    let mut a = open_at(&line.a, libc::B19200);
    let mut b = open_at(&line.b, libc::B19200);
    let sent = [0x11, 0x03, 0x00, 0x6B, 0x00, 0x03, 0x76, 0x87];
    a.write_all(&sent).unwrap();
    assert_eq!(read_until(&mut a, sent.len(), Duration::from_secs(2)), sent);
    assert_eq!(read_until(&mut b, sent.len(), Duration::from_secs(2)), sent);
    // Without --echo, nothing comes back.
    let quiet = Line::start(&[]);
    let mut a = open_at(&quiet.a, libc::B19200);
    let _b = open_at(&quiet.b, libc::B19200);
    a.write_all(&sent).unwrap();
    assert!(read_until(&mut a, 1, Duration::from_millis(100)).is_empty());
}

/// The parity of each end comes from the line's options: with `--a 8N1 --b 8E1`,
/// same baud, bytes reach the 8E1 end with parity or framing errors, which its
/// termios (INPCK, as set here) turns into 0x00.
#[test]
fn a_parity_mismatch_is_seen_as_errors() {
    let line = Line::start(&["--a", "8N1", "--b", "8E1"]);
    let mut a = open_at(&line.a, libc::B9600);
    let mut b = open_at(&line.b, libc::B9600);
    // SAFETY: as in open_at.
    unsafe {
        let mut t: libc::termios = std::mem::zeroed();
        libc::tcgetattr(b.as_raw_fd(), &mut t);
        t.c_iflag |= libc::INPCK;
        t.c_iflag &= !libc::IGNPAR;
        libc::tcsetattr(b.as_raw_fd(), libc::TCSANOW, &t);
    }
    // Back to back: each next start bit lands on the 8E1 receiver's stop bit.
    a.write_all(&[0x41, 0x42, 0x43]).unwrap();
    let got = read_until(&mut b, 3, Duration::from_secs(2));
    assert_eq!(got[..2], [0x00, 0x00], "{got:02X?}");
}

/// The gateway on end A, declared a wire (`port_kind = "wire"`), RTU at `baud`; a
/// pymodbus RTU server (unit 1, stock_server.py's registers: holding register 0 holds
/// 0x00FF, register i 1000 + i) on end B, started with `device` added to its
/// arguments (tests/py/serial_device.py); `tune` adds to the gateway's configuration
/// (its response timeout is 5 s unless `tune` sets one).
struct Behind {
    gw: Gateway,
    _device: Py,
    line: Line,
}

fn gateway_behind_the_line(
    baud: u32,
    line_args: &[&str],
    device: &[&str],
    tune: impl FnOnce(Cfg) -> Cfg,
) -> Behind {
    let line = Line::start(line_args);
    let baud_s = baud.to_string();
    let mut dev_args = vec![
        "--port",
        line.b.to_str().unwrap(),
        "--framer",
        "rtu",
        "--baud",
        &baud_s,
        "--units",
        "1",
    ];
    // No garbage reaches the device here: it starts afresh only after half a second
    // of silence, not after a pause a busy machine puts inside a long request.
    dev_args.extend_from_slice(&["--silence", "0.5"]);
    dev_args.extend_from_slice(device);
    let device = Py::start("serial_device.py", &dev_args);
    // pymodbus says READY before its port is set up: until then its end is at the
    // line's initial 50 baud, and a request would reach it garbled.
    let speed = match baud {
        1200 => libc::B1200,
        9600 => libc::B9600,
        19200 => libc::B19200,
        115200 => libc::B115200,
        _ => panic!("no termios speed for {baud} here"),
    };
    wait_for("the device's speed", Duration::from_secs(10), || {
        let f = open_pty(&line.b);
        // SAFETY: termios is plain data, filled by tcgetattr; valid fd.
        unsafe {
            let mut t: libc::termios = std::mem::zeroed();
            libc::tcgetattr(f.as_raw_fd(), &mut t) == 0 && libc::cfgetospeed(&t) == speed
        }
    });
    let cfg = Cfg::new(&line.a)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial("port_kind = \"wire\"")
        .serial(&format!("baud_rate = {baud}"))
        // The line is a program: on a loaded machine its wake-ups can pause a frame
        // by a few ms, as a USB adapter's latency timer does, and a user gives such a
        // port a floor of 50 ms (docs/simulator.md, "A virtual line"). At a load
        // average of 10 it paused inside 9 of 13 replies at 1200 baud for longer than that
        // (each a cut frame, 0x0B): these tests are of who gets which reply, not of
        // how short a pause ends one, and take 250 ms.
        .serial("silence_floor_ms = 250");
    let gw = Gateway::start(&tune(cfg), line._dir.path());
    Behind {
        gw,
        _device: device,
        line,
    }
}

/// The stock value of holding register `addr` (stock_server.py).
fn stock(addr: u16) -> u16 {
    if addr == 0 {
        0x00FF
    } else {
        1000 + addr
    }
}

/// What masters got, each answer judged against the exact reply its request should
/// have: its own (right), exception 0x0B (no reply in time: allowed, counted), or
/// anything else (wrong, kept to be shown), a frame of another function code included:
/// the gateway refuses a reply that does not answer its request
/// (src/line/relay/line/serial/mod.rs). Every test here asserts `wrong` empty.
#[derive(Debug, Default)]
struct Tally {
    right: u32,
    timed_out: u32,
    wrong: Vec<String>,
}

impl Tally {
    /// `got` for the request `req` (MBAP), which should have had `want`. Returns
    /// whether it was right.
    fn judge(&mut self, what: &str, req: &[u8], got: &[u8], want: &[u8]) -> bool {
        let timeout = mbgate::frame::Adu::build(
            u16::from_be_bytes([req[0], req[1]]),
            req[6],
            &[req[7] | 0x80, 0x0B],
        );
        if got == want {
            self.right += 1;
            true
        } else if got == timeout.as_bytes() {
            self.timed_out += 1;
            false
        } else {
            self.wrong
                .push(format!("{what}: got {}, want {}", hexs(got), hexs(want)));
            false
        }
    }

    /// Reads register `addr` of unit 1 and judges the answer against its stock value.
    fn read(&mut self, s: &mut std::net::TcpStream, tid: u16, addr: u16) -> bool {
        let req = read_req(tid, 1, addr, 1);
        let got = transact(s, &req);
        self.judge(
            &format!("read {tid} of register {addr}"),
            &req,
            &got,
            &read_reply(tid, 1, &[stock(addr)]),
        )
    }

    /// Panics, listing them, if any answer was wrong.
    fn assert_none_wrong(&self, what: &str, log: impl FnOnce() -> String) {
        assert!(
            self.wrong.is_empty(),
            "{what}: {} wrong ({} right, {} 0x0B): {:#?}\n{}",
            self.wrong.len(),
            self.right,
            self.timed_out,
            self.wrong,
            log()
        );
    }
}

/// Why a test counts the bytes dropped only when nothing timed out (the warm-up read
/// included). On a busy machine the line, or pymodbus, can pause inside a reply for
/// longer than the silence that ends a frame (`silence_floor_ms`): the gateway takes
/// the first part for a cut frame (a bad frame, 0x0B at once, counted as a timeout),
/// and the rest, coming while the next request leaves, is dropped as too early. Seen
/// once in about twenty runs beside two busy loops, on the warm-up read.
const NOT_COUNTED: &str = "a reply cut by a pause on a busy machine adds drops of its own";

/// The first read, not counted: the device's first answer may be lost while pymodbus
/// sets its port up.
fn warm_up(s: &mut std::net::TcpStream) {
    let _ = transact(s, &read_req(999, 1, 0, 1));
}

/// `n` reads of register `i % 5` through the gateway, after [`warm_up`]: none may get
/// another register's value or another request's reply; each is its own or 0x0B
/// (pymodbus in Python on a loaded machine can miss a request).
fn reads_never_wrong(gw: &Gateway, n: u16) -> Tally {
    let mut s = gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    warm_up(&mut s);
    let mut tally = Tally::default();
    for i in 0..n {
        tally.read(&mut s, i + 1, i % 5);
    }
    tally.assert_none_wrong("reads", || gw.log());
    tally
}

/// A third-party device whose replies take their time on the wire: on a line declared
/// a wire, at 1200 and at 9600 baud, no genuine reply is ever dropped as begun before
/// its request had left (`dropped_too_early` 0: none can, on this line), no read gets
/// a wrong answer, and most are answered.
#[test]
fn a_wire_timed_device_gets_every_reply_taken() {
    for (baud, n) in [(1200, 6), (9600, 20)] {
        let mut b = gateway_behind_the_line(baud, &[], &[], |c| c);
        let tally = reads_never_wrong(&b.gw, n);
        let right = tally.right as u16;
        eprintln!("{baud} baud: {tally:?}");
        assert!(right >= n / 2, "{baud}: {right} of {n} right");
        let counters = b.gw.stop();
        // A reply that came after its timeout can run into the next request, and is
        // rightly dropped as too early: the count holds when nothing timed out.
        if counters.get("timeouts") != Some(&0) {
            eprintln!("{baud}: timeouts, dropped_too_early not judged: {counters:?}");
            continue;
        }
        assert_eq!(
            counters.get("dropped_too_early"),
            Some(&0),
            "{baud}: {counters:?}"
        );
    }
}

/// An RS-232 loopback: the line echoes every byte to its sender. With `echo = true`
/// the gateway reads its echo back and discards it, and every write and read gets its
/// own answer. Without it, the gateway has only the wire's time to tell the echo from
/// the reply (docs/reliability.md: bytes read before the request could have left the
/// wire are dropped). The line starts sending when it has read the request, after the
/// gateway's write, so the echo's last bytes come after the instant the gateway
/// computes the request left: they run into the reply and spoil its CRC. On a quiet
/// machine nearly every read then gets 0x0B (a real UART's echo, read through a
/// driver, can be as late). That is a line set up wrong, and the gateway cannot
/// promise every answer there: an echo that comes whole after the request left is,
/// for FC 06, byte for byte the reply, so the gateway may answer a write the device
/// never heard, and run ahead of a device that lags. Beside two busy loops one read of
/// 20 runs got the previous read's value that way (that read had got 0x0B at once,
/// its echo spoiling the CRC, with no guard after it for its genuine reply, which
/// came after the next request had left: the guard now follows a reply that fails its
/// check as it follows a timeout, `rtu_binding`'s
/// `rtu_the_reply_after_a_damaged_one_never_answers_the_next_request`; a reply later
/// than the guard stays outside the guarantee). So with `echo = true` none may get
/// another answer than its own (0 wrong); without it, what is asserted is that the
/// gateway does not hide the trouble: echo bytes dropped as too early, or bad frames,
/// are counted, and any wrong answer is printed.
#[test]
fn an_echoing_line_never_gives_the_echo_as_the_reply() {
    for serial in [&["echo = true"][..], &[][..]] {
        let mut b = gateway_behind_the_line(19200, &["--echo"], &["--echo"], |mut c| {
            for line in serial {
                c = c.serial(line);
            }
            c
        });
        let mut s = b.gw.connect();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut tally = Tally::default();
        for i in 0..10u16 {
            // FC 06 to register 1 + i % 4 with a value the read then checks.
            let addr = 1 + i % 4;
            let value = 0x4000 + i;
            let mut pdu = vec![0x06];
            pdu.extend_from_slice(&addr.to_be_bytes());
            pdu.extend_from_slice(&value.to_be_bytes());
            let req = mbgate::frame::Adu::build(100 + i, 1, &pdu)
                .as_bytes()
                .to_vec();
            let wrote = transact(&mut s, &req);
            // A late read reply given to a write, or a late write reply given to the
            // read, is a frame of another function ([`Tally`]).
            let written = tally.judge(&format!("write {i}"), &req, &wrote, &req);
            let read = read_req(200 + i, 1, addr, 1);
            let got = transact(&mut s, &read);
            if written {
                tally.judge(
                    &format!("read back {i}"),
                    &read,
                    &got,
                    &read_reply(200 + i, 1, &[value]),
                );
            }
        }
        eprintln!("echo, {serial:?}: {tally:?}");
        if serial.is_empty() {
            let counters = b.gw.stop();
            assert!(
                counters["dropped_too_early"] + counters["bad_frames"] > 0,
                "no echo: {counters:?}"
            );
            continue;
        }
        tally.assert_none_wrong(&format!("echo, {serial:?}"), || b.gw.log());
        assert!(
            tally.right >= 10,
            "echo = true: {} of 20 writes and reads right",
            tally.right
        );
        b.gw.stop();
    }
}

/// `--noise 1`: every character has one bit flipped on the wire (a data bit, the
/// parity, start or stop bit), so what arrives is not what was sent: a flipped stop
/// bit still reads as the byte (a framing error a raw port passes on), a flipped data
/// bit as another byte, a flipped start bit shifts the receiver onto other bits.
#[test]
fn noise_flips_bits() {
    let line = Line::start(&["--noise", "1", "--seed", "3"]);
    let mut a = open_at(&line.a, libc::B19200);
    let mut b = open_at(&line.b, libc::B19200);
    let sent = [0x55u8; 64];
    a.write_all(&sent).unwrap();
    let got = read_until(&mut b, 64, Duration::from_secs(2));
    assert!(!got.is_empty());
    assert_ne!(got, sent);
    assert!(
        got.iter().filter(|&&x| x == 0x55).count() < got.len() / 2,
        "{got:02X?}"
    );
}

/// The gap before each request (Modbus over Serial Line V1.02 §2.5.1.1: 3.5 character
/// times of silence), seen by a device behind the line: a raw RTU device on end B that
/// answers each read the instant it has it. Its reply's last stop bit ends its wire
/// time after the write; the gateway's next request must not begin before 3.5
/// characters after that, so its first byte cannot be read at B before 4.5 character
/// times after it (the gap, then the byte's own time). Asserted for every request:
/// a lower bound, which no load can break; the silences are printed.
#[test]
fn the_gap_before_each_request_holds_behind_the_line() {
    let line = Line::start(&[]);
    let baud = 19200u32;
    let char_ns = 10 * 1_000_000_000u64 / u64::from(baud);
    let mut dev = open_at(&line.b, libc::B19200);
    let cfg = Cfg::new(&line.a)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial("port_kind = \"wire\"")
        .serial(&format!("baud_rate = {baud}"))
        .serial("silence_floor_ms = 50")
        .relay("response_timeout_ms = 5000");
    let gw = Gateway::start(&cfg, line._dir.path());
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stopping = stop.clone();
    let device = std::thread::spawn(move || {
        let mut silences = Vec::new();
        let mut reply_ends: Option<Instant> = None;
        let mut buf = Vec::new();
        while !stopping.load(std::sync::atomic::Ordering::Relaxed) {
            let more = read_some(&mut dev, Duration::from_millis(50));
            if more.is_empty() {
                continue;
            }
            let at = Instant::now();
            if buf.is_empty() {
                if let Some(end) = reply_ends.take() {
                    silences.push(at.saturating_duration_since(end));
                }
            }
            buf.extend(more);
            if buf.len() >= 8 {
                let addr = u16::from_be_bytes([buf[2], buf[3]]);
                let reply = mbgate::frame::rtu::encode(1, &[0x03, 0x02, 0x00, addr as u8]);
                buf.clear();
                let written = Instant::now();
                dev.write_all(&reply).unwrap();
                reply_ends = Some(written + Duration::from_nanos(char_ns * reply.len() as u64));
            }
        }
        silences
    });
    let mut s = gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut timed_out = 0;
    for i in 0..20u16 {
        let got = transact(&mut s, &read_req(i + 1, 1, i, 1));
        let timeout = mbgate::frame::Adu::build(i + 1, 1, &[0x83, 0x0B]);
        if hexs(&got) == hexs(timeout.as_bytes()) {
            timed_out += 1;
            continue;
        }
        assert_eq!(hexs(&got), hexs(&read_reply(i + 1, 1, &[i])), "read {i}");
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let mut silences = device.join().unwrap();
    assert!(timed_out <= 10, "{timed_out} of 20 timed out");
    if timed_out > 0 {
        // After a timeout the gateway rightly sends the next request whenever the
        // line is quiet, a late reply's end unknown to it: not a gap to judge.
        eprintln!("{timed_out} timed out on a loaded machine: the gaps are not judged");
        return;
    }
    assert_eq!(silences.len(), 19);
    let least = Duration::from_nanos(char_ns * 45 / 10);
    for (i, s) in silences.iter().enumerate() {
        assert!(
            *s >= least,
            "request {}: first byte {s:?} after the reply ended, under {least:?}",
            i + 1
        );
    }
    silences.sort();
    eprintln!("19200 8N1: from a reply's end to the next request's first byte: min {:?}, median {:?}, max {:?} (at least {least:?})", silences[0], silences[9], silences[18]);
}

/// A device that answers after the gateway has given up, behind the line: pymodbus
/// answers reads of even registers `late_by` after the response timeout
/// (serial_device.py `--late-even`), odd ones at once, and the master reads them in
/// turn, so each late reply comes just before the next request (Modbus over Serial
/// Line V1.02 has nothing to tie a reply to its request but time). Every answer is
/// its register's own value or 0x0B, never the late reply of the register before
/// (docs/reliability.md, "RTU and ASCII": the guard after a timeout); most late ones
/// are 0x0B (their own value only if the gateway's timer woke late), and every late
/// reply is discarded whole. The guard is far beyond how late a loaded machine makes
/// pymodbus (tests/e2e/rtu_binding.rs's `GUARD_MS` says why), `late_by` within it.
fn late_replies_behind_the_line(late_by: Duration) {
    const TIMEOUT: Duration = Duration::from_millis(400);
    const GUARD_MS: u64 = 1200;
    // A 7-byte RTU reply to a one-register read.
    const REPLY: u64 = 7;
    let late = format!("{:.3}", (TIMEOUT + late_by).as_secs_f64());
    let mut b = gateway_behind_the_line(19200, &[], &["--late-even", &late], |c| {
        c.relay(&format!("response_timeout_ms = {}", TIMEOUT.as_millis()))
            .relay(&format!("timeout_guard_ms = {GUARD_MS}"))
            // Every request goes on the line, however often the unit times out.
            .relay("unit_backoff = false")
    });
    let mut s = b.gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    // Register 1: odd, answered at once.
    let _ = transact(&mut s, &read_req(999, 1, 1, 1));
    let (mut even, mut odd) = (Tally::default(), Tally::default());
    for (i, addr) in (2..8u16).enumerate() {
        let tally = if addr % 2 == 0 { &mut even } else { &mut odd };
        tally.read(&mut s, i as u16 + 1, addr);
    }
    let counters = b.gw.stop();
    eprintln!("late by {late_by:?}: late {even:?}, at once {odd:?}\n{counters:?}");
    even.assert_none_wrong("the late ones", || b.gw.log());
    odd.assert_none_wrong("the ones after a late one", || b.gw.log());
    assert!(
        even.timed_out >= 2,
        "only {} of the 3 late replies timed out: {even:?}",
        even.timed_out
    );
    assert!(odd.right >= 1, "none answered at once was right: {odd:?}");
    let dropped = counters["dropped_bytes"];
    assert!(
        dropped >= u64::from(even.timed_out) * REPLY && dropped % REPLY == 0,
        "every late reply discarded whole: {dropped} bytes for {} late: {counters:?}",
        even.timed_out
    );
}

#[test]
fn late_replies_behind_the_line_never_reach_the_next_request_20_ms_late() {
    late_replies_behind_the_line(Duration::from_millis(20));
}

#[test]
fn late_replies_behind_the_line_never_reach_the_next_request_300_ms_late() {
    late_replies_behind_the_line(Duration::from_millis(300));
}

/// A frame on the line just before a request, behind the line: a second writer on the
/// device's end (as another station, or noise, would put it there) sends a reply-shaped
/// frame (unit 1, FC 03, one register, 0xBEEF, its CRC right), beside the pymodbus
/// device, at 1200 baud (a character takes 8.3 ms). Then a read is asked for: while
/// the frame is still arriving (once the gateway has some of it, not all: the request
/// then waits for the line to fall silent, Modbus over Serial Line V1.02 §2.5.1.1),
/// and 0, 5 and 50 ms after the gateway has read all of it. Every read gets its own
/// register's value or 0x0B, never 0xBEEF; and when nothing timed out
/// ([`NOT_COUNTED`]), each stray frame was discarded whole, as received before the
/// request (stale) or while it was leaving (too early), and no frame was bad.
#[test]
fn a_frame_just_before_a_request_is_never_its_reply_behind_the_line() {
    let mut b = gateway_behind_the_line(1200, &[], &[], |c| c.metrics("listen = \"127.0.0.1:0\""));
    let mut stray_writer = common::sim::RawLine::open(&b.line.b);
    let stray = mbgate::frame::rtu::encode(1, &[0x03, 0x02, 0xBE, 0xEF]);
    let mut s = b.gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    warm_up(&mut s);
    let mut tally = Tally::default();
    let mut tid = 0u16;
    let mut cases = Vec::new();
    for before in ["while it arrives", "0 ms", "5 ms", "50 ms"] {
        let received = b.gw.metric("mbgate_line_received_bytes");
        stray_writer.send(&stray);
        let start = Instant::now();
        let mut had = 0.0;
        // Bounded: the frame's 58 ms on the wire, and whatever a busy machine adds.
        while start.elapsed() < Duration::from_secs(20) {
            had = b.gw.metric("mbgate_line_received_bytes") - received;
            let enough = if before == "while it arrives" {
                had >= 1.0
            } else {
                had >= stray.len() as f64
            };
            if enough {
                break;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        if let Some(ms) = before.strip_suffix(" ms") {
            std::thread::sleep(Duration::from_millis(ms.parse().unwrap()));
        }
        // Until two were right (a busy machine can make pymodbus miss one), at most
        // six.
        let mut right = 0;
        for addr in 1..=6u16 {
            if right == 2 {
                break;
            }
            tid += 1;
            right += u32::from(tally.read(&mut s, tid, addr));
        }
        cases.push(format!(
            "{before}: the gateway had {had} of its bytes; {right} right"
        ));
    }
    let counters = b.gw.stop();
    eprintln!("{cases:#?}\n{tally:?}\n{counters:?}");
    tally.assert_none_wrong("after a stray frame", || b.gw.log());
    assert_eq!(
        tally.right, 8,
        "two right after each stray frame: {cases:#?}"
    );
    if counters["timeouts"] > 0 {
        eprintln!("timeouts: the drops are not counted ({NOT_COUNTED})");
        return;
    }
    let strays = 4 * stray.len() as u64;
    assert_eq!(counters["dropped_bytes"], strays, "{counters:?}");
    assert_eq!(
        counters["dropped_stale"] + counters["dropped_too_early"],
        strays,
        "{counters:?}"
    );
    assert_eq!(counters["bad_frames"], 0, "{counters:?}");
}

/// A frame begun while the request is still leaving the wire, behind the line: a
/// write of 60 registers (129 bytes, 1.07 s at 1200 baud) goes to the pymodbus device,
/// and as soon as the gateway has handed it to its port (its count of bytes sent), a
/// second writer on the device's end sends a reply-shaped frame for a write (unit 1,
/// FC 16, at 0xBEEF, its CRC right: 8 bytes, 67 ms), which arrives whole long before
/// the request has left (docs/reliability.md: bytes read before the request could
/// have left the wire are not its reply). Judged where the gateway had read the stray
/// frame before the request could have left (its count of bytes received, sampled
/// from the moment the request was sent until its time on the wire has passed; beside
/// two busy loops the line was once held up longer than that, and then the frame is,
/// to any gateway, a reply like another): every write gets its own reply (or 0x0B),
/// never the stray one, and the values it wrote read back (three such writes
/// answered, in at most eight tries); when nothing timed out ([`NOT_COUNTED`]) and
/// every stray came in time, each was dropped whole as too early and no frame was bad.
/// A full-duplex cable lets the two cross; on RS-485 they would collide, and the
/// gateway must still not take what it reads then.
#[test]
fn a_frame_begun_while_the_request_leaves_is_never_its_reply_behind_the_line() {
    const N: u16 = 60;
    let mut b = gateway_behind_the_line(1200, &[], &["--size", "100"], |c| {
        c.metrics("listen = \"127.0.0.1:0\"")
    });
    let mut stray_writer = common::sim::RawLine::open(&b.line.b);
    let stray = mbgate::frame::rtu::encode(1, &[0x10, 0xBE, 0xEF, 0x00, N as u8]);
    let mut s = b.gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    warm_up(&mut s);
    let mut tally = Tally::default();
    let mut waited = Vec::new();
    // Attempts whose stray frame the gateway had not read before the request could
    // have left: the line (a program) was held up longer than the request's 1.07 s on
    // the wire, and what it delivers then is, to any gateway, a reply like another.
    let mut late_strays = 0;
    // Until three writes whose stray frame came in time were answered (a busy machine
    // can make pymodbus miss one), at most eight tries.
    let mut written = 0;
    let mut i = 0u16;
    while written < 3 && i < 8 {
        let values: Vec<u16> = (0..N).map(|k| 0x5000 + 0x100 * i + k).collect();
        let req = write_req(10 + i, 1, 1, &values);
        // Its time on the wire: 129 bytes in RTU (the MBAP header gives way to the
        // CRC).
        let on_wire = Duration::from_micros((req.len() as u64 - 4) * 10_000_000 / 1200);
        let sent = b.gw.metric("mbgate_line_sent_bytes");
        let received = b.gw.metric("mbgate_line_received_bytes");
        s.write_all(&req).unwrap();
        let asked = Instant::now();
        // Bounded: on a quiet machine the gateway writes it within a millisecond.
        while b.gw.metric("mbgate_line_sent_bytes") < sent + 1.0
            && asked.elapsed() < Duration::from_secs(20)
        {
            std::thread::sleep(Duration::from_millis(1));
        }
        waited.push(asked.elapsed());
        stray_writer.send(&stray);
        // The gateway wrote the request after it was asked, so a stray frame it has
        // read before `asked` + `on_wire` came before the request could have left,
        // and must not be taken for its reply. Bounded by `on_wire`.
        let in_time = loop {
            if b.gw.metric("mbgate_line_received_bytes") - received >= stray.len() as f64 {
                break asked.elapsed() < on_wire;
            }
            if asked.elapsed() >= on_wire {
                break false;
            }
            std::thread::sleep(Duration::from_millis(1));
        };
        let got = read_frame(&mut s);
        i += 1;
        if !in_time {
            late_strays += 1;
            continue;
        }
        let want = mbgate::frame::Adu::build(9 + i, 1, &[0x10, 0x00, 0x01, 0x00, N as u8]);
        if tally.judge(&format!("write {}", i - 1), &req, &got, want.as_bytes()) {
            written += 1;
            let read = read_req(20 + i, 1, i, 1);
            let got = transact(&mut s, &read);
            tally.judge(
                &format!("read back {}", i - 1),
                &read,
                &got,
                &read_reply(20 + i, 1, &[values[usize::from(i - 1)]]),
            );
        }
    }
    let counters = b.gw.stop();
    eprintln!(
        "sent seen after {waited:?}\n{tally:?}, {late_strays} stray frames late, not judged\n{counters:?}"
    );
    tally.assert_none_wrong("a frame as the request leaves", || b.gw.log());
    assert_eq!(written, 3, "{tally:?}, {late_strays} stray frames late");
    if counters["timeouts"] > 0 || late_strays > 0 {
        eprintln!("timeouts or late strays: the drops are not counted ({NOT_COUNTED})");
        return;
    }
    let strays = u64::from(i) * stray.len() as u64;
    for (key, want) in [
        ("dropped_too_early", strays),
        ("dropped_bytes", strays),
        ("bad_frames", 0),
    ] {
        assert_eq!(counters[key], want, "{key}: {counters:?}\n{}", b.gw.log());
    }
}

/// The turnaround, behind the line: the device answers 3.5 character times after the
/// request has reached it (the least Modbus over Serial Line V1.02 §2.5.1.1 lets a
/// device keep; serial_device.py `--delay`), at 9600 and at 115 200 baud, on a port
/// declared a wire. The reply's first byte must not be lost, neither dropped as come
/// before the request had left (its time on the wire) nor cut off by a turnaround
/// still under way: every read is its own register's value (0x0B allowed, counted, as
/// pymodbus on a loaded machine can miss a request), and when nothing timed out
/// ([`NOT_COUNTED`]), no byte
/// was dropped and no frame was bad. (A pseudo-terminal has no RTS and the machine no
/// GPIO chip, so `serial.direction` cannot be set here, tests/e2e/rs485.rs: this is the
/// wire port's drain and timing path; the switch itself is tests/inprocess/relay_inprocess.rs's.)
#[test]
fn a_reply_three_and_a_half_characters_after_the_request_keeps_its_first_byte() {
    for baud in [9600u32, 115_200] {
        // 8N1: 10 bits a character.
        let t35 = Duration::from_secs_f64(35.0 / f64::from(baud));
        let delay = format!("{:.6}", t35.as_secs_f64());
        let mut b = gateway_behind_the_line(baud, &[], &["--delay", &delay], |c| c);
        let n = 20;
        let started = Instant::now();
        let tally = reads_never_wrong(&b.gw, n);
        let took = started.elapsed();
        let counters = b.gw.stop();
        eprintln!("{baud} baud, device after {t35:?}: {tally:?} in {took:?}\n{counters:?}");
        assert!(
            tally.right >= u32::from(n) / 2,
            "{baud}: {tally:?}\n{counters:?}"
        );
        if counters["timeouts"] > 0 {
            eprintln!("{baud}: timeouts, the drops are not counted ({NOT_COUNTED})");
            continue;
        }
        for key in ["dropped_bytes", "dropped_too_early", "bad_frames"] {
            assert_eq!(counters[key], 0, "{baud}: {key}: {counters:?}");
        }
    }
}
