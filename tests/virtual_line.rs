//! The virtual line (`mbgate wire`, docs/simulator.md "A virtual line") against real
//! peers: bytes take their time at the sender's baud rate, other baud rates garble
//! (pymodbus' client and server at different rates never make a transaction), loss is
//! the rate asked, echo returns the sender's bytes.

mod common;
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
