//! End to end for the master client: `mbgate read` and `mbgate write`, the real
//! binary, against pymodbus' stock serial server on a socat pty (directly, and through
//! `mbgate run` over TCP), against scripted raw peers, and against nobody.
//!
//! The stock server's data (tests/py/stock_server.py): unit 1, HR0 = 0x00FF, HR[i] =
//! 1000 + i, IR[i] = 2000 + i, coil i ON when i % 3 == 0, discrete input i ON when
//! i % 2 == 0.

use crate::common;
use common::sim::serial_units;
use common::*;
use mbgate::frame::mbap::decode_strict;
use mbgate::frame::{ascii, rtu, Adu};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener};
use std::path::Path;
use std::thread;
use std::time::Duration;

/// `target` + `args`.
fn with<'a>(target: &[&'a str], args: &[&'a str]) -> Vec<&'a str> {
    [args, target].concat()
}

/// A normal response printed with `-v`: the status line, both frames byte-exact, then
/// exactly `values`.
fn assert_reply(run: &Run, tx: &str, rx: &str, values: &[&str]) {
    assert_eq!(run.code, 0, "exit code; stderr: {}", run.stderr);
    let lines = run.lines();
    assert!(
        lines[0].starts_with("reply in ") && lines[0].ends_with(" ms"),
        "status line: {:?}",
        lines[0]
    );
    assert_eq!(lines[1], format!("tx {tx}"));
    assert_eq!(lines[2], format!("rx {rx}"));
    assert_eq!(&lines[3..], values);
}

/// A normal response printed without `-v`: the status line, then exactly `values`.
fn assert_values(run: &Run, values: &[&str]) {
    assert_eq!(run.code, 0, "exit code; stderr: {}", run.stderr);
    let lines = run.lines();
    assert!(
        lines[0].starts_with("reply in "),
        "status line: {:?}",
        lines[0]
    );
    assert_eq!(&lines[1..], values);
}

/// Every function code of the client against a fresh stock server, each frame
/// byte-exact, each write read back. Every run starts at transaction id 1.
fn every_function_code(target: &[&str]) {
    let m = |args: &[&str]| mbgate(&with(target, args));

    // FC 01: coils 0, 3, 6, 9 ON = 0x49 0x02.
    assert_reply(
        &m(&["read", "-v", "coils", "0", "10"]),
        "00 01 00 00 00 06 01 01 00 00 00 0A",
        "00 01 00 00 00 05 01 01 02 49 02",
        &[
            "0: 1", "1: 0", "2: 0", "3: 1", "4: 0", "5: 0", "6: 1", "7: 0", "8: 0", "9: 1",
        ],
    );
    // FC 02: inputs 0, 2, 4, 6, 8 ON = 0x55 0x01.
    assert_reply(
        &m(&["read", "-v", "discrete", "0", "10"]),
        "00 01 00 00 00 06 01 02 00 00 00 0A",
        "00 01 00 00 00 05 01 02 02 55 01",
        &[
            "0: 1", "1: 0", "2: 1", "3: 0", "4: 1", "5: 0", "6: 1", "7: 0", "8: 1", "9: 0",
        ],
    );
    // FC 03, with register 0 = the CIE-M10 inputs 0..7 ON (docs/protocol.md §3).
    assert_reply(
        &m(&["read", "-v", "holding", "0", "3"]),
        "00 01 00 00 00 06 01 03 00 00 00 03",
        "00 01 00 00 00 09 01 03 06 00 FF 03 E9 03 EA",
        &["0: 255 (0x00FF)", "1: 1001 (0x03E9)", "2: 1002 (0x03EA)"],
    );
    // FC 04, the address in hex.
    assert_reply(
        &m(&["read", "-v", "input", "0x10", "2"]),
        "00 01 00 00 00 06 01 04 00 10 00 02",
        "00 01 00 00 00 07 01 04 04 07 E0 07 E1",
        &["16: 2016 (0x07E0)", "17: 2017 (0x07E1)"],
    );

    // FC 05, then read back (coil 5 was OFF).
    assert_reply(
        &m(&["write", "-v", "coil", "5", "on"]),
        "00 01 00 00 00 06 01 05 00 05 FF 00",
        "00 01 00 00 00 06 01 05 00 05 FF 00",
        &["5: 1"],
    );
    assert_values(&m(&["read", "coils", "4", "3"]), &["4: 0", "5: 1", "6: 1"]);

    // FC 06, then read back.
    assert_reply(
        &m(&["write", "-v", "register", "8", "0x0011"]),
        "00 01 00 00 00 06 01 06 00 08 00 11",
        "00 01 00 00 00 06 01 06 00 08 00 11",
        &["8: 17 (0x0011)"],
    );
    assert_values(
        &m(&["read", "holding", "7", "2"]),
        &["7: 1007 (0x03EF)", "8: 17 (0x0011)"],
    );

    // FC 0F: coils 10..12 were 0 0 1.
    assert_reply(
        &m(&["write", "-v", "coils", "10", "1", "true", "off"]),
        "00 01 00 00 00 08 01 0F 00 0A 00 03 01 03",
        "00 01 00 00 00 06 01 0F 00 0A 00 03",
        &["wrote 3 coils at 10..=12"],
    );
    assert_values(
        &m(&["read", "coils", "9", "5"]),
        &["9: 1", "10: 1", "11: 1", "12: 0", "13: 0"],
    );

    // FC 10, a negative value as its two's complement.
    assert_reply(
        &m(&["write", "-v", "registers", "20", "7", "8", "-1"]),
        "00 01 00 00 00 0D 01 10 00 14 00 03 06 00 07 00 08 FF FF",
        "00 01 00 00 00 06 01 10 00 14 00 03",
        &["wrote 3 registers at 20..=22"],
    );
    assert_values(
        &m(&["read", "holding", "20", "4"]),
        &[
            "20: 7 (0x0007)",
            "21: 8 (0x0008)",
            "22: 65535 (0xFFFF)",
            "23: 1023 (0x03FF)",
        ],
    );
    // FC 10 for one value with --multiple.
    assert_reply(
        &m(&["write", "-v", "--multiple", "register", "30", "5"]),
        "00 01 00 00 00 09 01 10 00 1E 00 01 02 00 05",
        "00 01 00 00 00 06 01 10 00 1E 00 01",
        &["wrote 1 register at 30"],
    );
    assert_values(&m(&["read", "holding", "30"]), &["30: 5 (0x0005)"]);

    // FC 17: the write (40, 41) happens before the read (39..42).
    assert_reply(
        &m(&[
            "write",
            "-v",
            "registers",
            "40",
            "0x1234",
            "0x5678",
            "--read",
            "39",
            "4",
        ]),
        "00 01 00 00 00 0F 01 17 00 27 00 04 00 28 00 02 04 12 34 56 78",
        "00 01 00 00 00 0B 01 17 08 04 0F 12 34 56 78 04 12",
        &[
            "39: 1039 (0x040F)",
            "40: 4660 (0x1234)",
            "41: 22136 (0x5678)",
            "42: 1042 (0x0412)",
        ],
    );

    // Exceptions: exit 3 and the code by name.
    let r = m(&["read", "-v", "holding", "10000"]);
    assert_eq!(r.code, 3);
    let lines = r.lines();
    assert!(
        lines[0].starts_with("exception 0x02 illegal data address (fc 0x03) in "),
        "{lines:?}"
    );
    assert_eq!(lines[1], "tx 00 01 00 00 00 06 01 03 27 10 00 01");
    assert_eq!(lines[2], "rx 00 01 00 00 00 03 01 83 02");
    assert_eq!(lines.len(), 3);
    let r = m(&["write", "coil", "10000", "1"]);
    assert_eq!(r.code, 3);
    assert!(r
        .stdout
        .starts_with("exception 0x02 illegal data address (fc 0x05) in "));
}

/// socat, pymodbus' stock serial server on the `dev` end.
fn stock_device(dir: &Path) -> (Socat, Py) {
    let socat = Socat::start(dir);
    let device = Py::start("stock_server.py", &["--port", socat.dev.to_str().unwrap()]);
    (socat, device)
}

/// (a) Every function code straight to the stock server on the serial port, MBAP
/// framing (the CIE-M10 serial Modbus/TCP mode).
#[test]
fn serial_every_function_code_against_the_stock_server() {
    let dir = tempdir();
    let (socat, _device) = stock_device(dir.path());
    every_function_code(&["--serial", socat.gw.to_str().unwrap()]);
}

/// (b) The same through the gateway: `mbgate run` on the pty, the client over TCP.
#[test]
fn tcp_every_function_code_through_the_gateway() {
    let dir = tempdir();
    let (socat, _device) = stock_device(dir.path());
    let gw = Gateway::start(&Cfg::new(&socat.gw).pty_line(), dir.path());
    let addr = gw.addr.to_string();
    every_function_code(&["--tcp", &addr]);
}

/// (c) The gateway's own exception: a silent device gives 0x0B, exit 3.
#[test]
fn gateway_exception_for_a_silent_device() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let gw = Gateway::start(
        &Cfg::new(&socat.gw).relay("response_timeout_ms = 200"),
        dir.path(),
    );
    let r = mbgate(&["read", "--tcp", &gw.addr.to_string(), "holding", "0"]);
    assert_eq!(r.code, 3, "{}", r.stderr);
    assert!(
        r.stdout
            .starts_with("exception 0x0B gateway target device failed to respond (fc 0x03) in "),
        "{}",
        r.stdout
    );
}

/// (c) Nobody at a TCP port: exit 1 at once, naming the address.
#[test]
fn tcp_connection_refused_exits_1() {
    let port = {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let target = format!("127.0.0.1:{port}");
    let r = mbgate(&[
        "read",
        "--tcp",
        &target,
        "--timeout-ms",
        "5000",
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 1);
    assert!(r.stdout.is_empty(), "{}", r.stdout);
    assert!(
        r.stderr.contains(&format!("cannot connect to {target}")),
        "{}",
        r.stderr
    );
    assert!(r.elapsed < Duration::from_secs(3), "{:?}", r.elapsed);
}

/// (c) A TCP peer that accepts and never answers: exit 1 after the timeout, not before,
/// not much later.
#[test]
fn tcp_silent_peer_exits_1_after_the_timeout() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let target = listener.local_addr().unwrap().to_string();
    let holder = thread::spawn(move || {
        let (s, _) = listener.accept().unwrap();
        thread::sleep(Duration::from_secs(3));
        drop(s);
    });
    let r = mbgate(&[
        "read",
        "--tcp",
        &target,
        "--timeout-ms",
        "300",
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 1);
    assert_eq!(
        r.stderr.trim(),
        format!("mbgate: no reply from {target} within 300 ms")
    );
    assert!(r.elapsed >= Duration::from_millis(300), "{:?}", r.elapsed);
    assert!(r.elapsed < Duration::from_secs(2), "{:?}", r.elapsed);
    holder.join().unwrap();
}

/// (c) A serial port with nobody on the other end, and one that does not exist.
#[test]
fn serial_silent_or_missing_port_exits_1() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let gw = socat.gw.to_str().unwrap();
    let r = mbgate(&[
        "read",
        "-v",
        "--serial",
        gw,
        "--timeout-ms",
        "300",
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 1);
    assert_eq!(
        r.stderr.trim(),
        format!("mbgate: no reply from {gw} within 300 ms")
    );
    // With -v the request that went unanswered is still shown.
    assert_eq!(r.stdout, "tx 00 01 00 00 00 06 01 03 00 00 00 01\n");
    assert!(r.elapsed >= Duration::from_millis(300), "{:?}", r.elapsed);
    assert!(r.elapsed < Duration::from_secs(2), "{:?}", r.elapsed);

    let missing = dir.path().join("ttyUSB9");
    let r = mbgate(&[
        "read",
        "--serial",
        missing.to_str().unwrap(),
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 1);
    assert!(
        r.stderr
            .contains(&format!("cannot open {}", missing.display())),
        "{}",
        r.stderr
    );
}

/// (d) On a lossy serial line the client takes only its own reply: noise and a frame
/// with another transaction id (a CIE-M10 notification uses 0x0000) are skipped, and
/// `-v` shows both frames byte-exact and how many bytes were skipped.
#[test]
fn serial_skips_noise_and_frames_for_other_transactions() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let noise = hex("FF 13 00 7E");
    let other = hex("00 00 00 00 00 05 01 03 02 00 11");
    let (noise2, other2) = (noise.clone(), other.clone());
    let device = RawDevice::start(
        &socat.dev,
        Box::new(move |req: &Adu| {
            let reply = Adu::build(req.tid(), req.unit(), &[0x03, 0x02, 0x00, 0xFF]);
            [&noise2[..], &other2[..], reply.as_bytes()].concat()
        }),
    );
    let r = mbgate(&[
        "read",
        "-v",
        "--serial",
        socat.gw.to_str().unwrap(),
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let lines = r.lines();
    assert!(lines[0].starts_with("reply in "), "{lines:?}");
    assert_eq!(
        &lines[1..],
        [
            "tx 00 01 00 00 00 06 01 03 00 00 00 01".to_string(),
            format!(
                "rx skipped {} bytes that were not the reply",
                noise.len() + other.len()
            ),
            "rx 00 01 00 00 00 05 01 03 02 00 FF".to_string(),
            "0: 255 (0x00FF)".to_string(),
        ]
    );
    assert_eq!(
        device.requests()[0].as_bytes(),
        &hex("00 01 00 00 00 06 01 03 00 00 00 01")[..]
    );
}

/// A Modbus/TCP peer for one connection: each request gets whatever `reply` returns.
fn raw_tcp_peer(
    mut reply: impl FnMut(&Adu) -> Vec<u8> + Send + 'static,
) -> (SocketAddr, thread::JoinHandle<Vec<Adu>>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let handle = thread::spawn(move || {
        let (mut s, _) = listener.accept().unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut buf = bytes::BytesMut::new();
        let mut seen = Vec::new();
        let mut chunk = [0u8; 512];
        loop {
            match s.read(&mut chunk) {
                Ok(0) | Err(_) => return seen,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
            }
            while let Ok(Some(req)) = decode_strict(&mut buf) {
                let _ = s.write_all(&reply(&req));
                seen.push(req);
            }
        }
    });
    (addr, handle)
}

/// (d) Over TCP a frame with another transaction id (a late answer) is ignored and
/// shown with `-v`; a frame with ours that answers something else is an error (exit 1).
#[test]
fn tcp_ignores_other_transactions_and_rejects_a_wrong_answer() {
    let (addr, peer) = raw_tcp_peer(|req| {
        let late = Adu::build(0x7777, 1, &[0x03, 0x02, 0x12, 0x34]);
        let ours = Adu::build(req.tid(), req.unit(), &[0x03, 0x02, 0x00, 0x2A]);
        [late.as_bytes(), ours.as_bytes()].concat()
    });
    let r = mbgate(&["read", "-v", "--tcp", &addr.to_string(), "holding", "0x6B"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert_eq!(
        &r.lines()[1..],
        [
            "tx 00 01 00 00 00 06 01 03 00 6B 00 01",
            "rx 77 77 00 00 00 05 01 03 02 12 34 (transaction id 0x7777 is not ours: ignored)",
            "rx 00 01 00 00 00 05 01 03 02 00 2A",
            "107: 42 (0x002A)",
        ]
    );
    assert_eq!(peer.join().unwrap().len(), 1);

    // Two registers asked, one answered.
    let (addr, peer) = raw_tcp_peer(|req| {
        Adu::build(req.tid(), req.unit(), &[0x03, 0x02, 0x00, 0x2A])
            .as_bytes()
            .to_vec()
    });
    let r = mbgate(&["read", "--tcp", &addr.to_string(), "holding", "0", "2"]);
    assert_eq!(r.code, 1);
    assert!(r.stdout.is_empty());
    assert!(
        r.stderr
            .contains("reply PDU 03 02 00 2A does not answer request PDU 03 00 00 00 02"),
        "{}",
        r.stderr
    );
    peer.join().unwrap();
}

/// Timestamp at the start of a polled result: `2025-06-01T10:00:00.123Z `.
fn is_stamped(line: &str) -> bool {
    let b = line.as_bytes();
    line.len() > 25
        && b[4] == b'-'
        && b[10] == b'T'
        && b[19] == b'.'
        && b[23] == b'Z'
        && b[24] == b' '
}

/// (e) `--poll 50 --count 3`: three timestamped results, transaction ids 1, 2, 3, a
/// summary; exit 0.
#[test]
fn poll_three_times_with_increasing_transaction_ids() {
    let dir = tempdir();
    let (socat, _device) = stock_device(dir.path());
    let r = mbgate(&[
        "read",
        "--serial",
        socat.gw.to_str().unwrap(),
        "--poll",
        "50",
        "--count",
        "3",
        "-v",
        "holding",
        "0",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let lines = r.lines();
    assert_eq!(lines.len(), 13, "{lines:?}");
    for (i, block) in lines[..12].chunks(4).enumerate() {
        let tid = i + 1;
        assert!(is_stamped(block[0]), "{:?}", block[0]);
        assert!(block[0][25..].starts_with("reply in "), "{:?}", block[0]);
        assert_eq!(
            block[1],
            format!("tx 00 {tid:02X} 00 00 00 06 01 03 00 00 00 01")
        );
        assert_eq!(
            block[2],
            format!("rx 00 {tid:02X} 00 00 00 05 01 03 02 00 FF")
        );
        assert_eq!(block[3], "0: 255 (0x00FF)");
    }
    assert!(
        lines[12].starts_with("--- 3 requests: 3 replies, 0 exceptions, 0 unanswered; round trip"),
        "{}",
        lines[12]
    );
    // Requests start 50 ms apart: the third no earlier than 100 ms after the first.
    assert!(r.elapsed >= Duration::from_millis(100), "{:?}", r.elapsed);
}

/// (e) Polling keeps going after a timeout and an exception; the exit code is that of
/// the last poll.
#[test]
fn poll_keeps_going_after_a_timeout_and_an_exception() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let mut n = 0;
    let _device = RawDevice::start(
        &socat.dev,
        Box::new(move |req: &Adu| {
            n += 1;
            match n {
                1 => vec![],
                2 => Adu::exception(req.tid(), req.unit(), 0x03, 0x02)
                    .as_bytes()
                    .to_vec(),
                _ => Adu::build(req.tid(), req.unit(), &[0x03, 0x02, 0x00, 0x07])
                    .as_bytes()
                    .to_vec(),
            }
        }),
    );
    let gw = socat.gw.to_str().unwrap();
    let r = mbgate(&[
        "read",
        "--serial",
        gw,
        "--poll",
        "50",
        "--count",
        "3",
        "--timeout-ms",
        "200",
        "holding",
        "9",
    ]);
    assert_eq!(r.code, 0, "the last poll was answered; {}", r.stderr);
    let lines = r.lines();
    assert_eq!(lines.len(), 5, "{lines:?}");
    assert!(lines.iter().take(3).all(|l| is_stamped(l)), "{lines:?}");
    assert_eq!(&lines[0][25..], format!("no reply from {gw} within 200 ms"));
    assert!(
        lines[1][25..].starts_with("exception 0x02 illegal data address (fc 0x03) in "),
        "{}",
        lines[1]
    );
    assert!(lines[2][25..].starts_with("reply in "), "{}", lines[2]);
    assert_eq!(lines[3], "9: 7 (0x0007)");
    assert!(
        lines[4].starts_with("--- 3 requests: 1 replies, 1 exceptions, 1 unanswered"),
        "{}",
        lines[4]
    );

    // Nobody answers any poll: exit 1, every poll reported.
    drop(_device);
    let r = mbgate(&[
        "read",
        "--serial",
        gw,
        "--poll",
        "50",
        "--count",
        "2",
        "--timeout-ms",
        "100",
        "coils",
        "0",
    ]);
    assert_eq!(r.code, 1);
    let lines = r.lines();
    assert_eq!(lines.len(), 3, "{lines:?}");
    assert_eq!(
        lines[2],
        "--- 2 requests: 0 replies, 0 exceptions, 2 unanswered"
    );
}

/// Bad arguments exit 2 before anything is sent (nothing listens at the target).
#[test]
fn bad_arguments_exit_2() {
    for (args, message) in [
        (
            &["read", "holding", "0", "126"][..],
            "registers must be 1..=125, got 126",
        ),
        (
            &["read", "coils", "65535", "2"][..],
            "runs past address 65535",
        ),
        (&["write", "coil", "0", "maybe"][..], "coil value 'maybe'"),
        (
            &["write", "register", "0", "70000"][..],
            "register value '70000'",
        ),
        (
            &["write", "coils", "0", "1", "--read", "0", "1"][..],
            "registers only",
        ),
        (&["read", "registers", "0"][..], "invalid value 'registers'"),
        (&["read", "holding", "0", "--count", "3"][..], "--poll"),
        (&["write", "register", "0"][..], "required"),
    ] {
        let mut full = args.to_vec();
        full.extend(["--tcp", "127.0.0.1:1"]);
        let r = mbgate(&full);
        assert_eq!(r.code, 2, "{args:?}");
        assert!(r.stderr.contains(message), "{args:?}: {}", r.stderr);
        assert!(r.stdout.is_empty(), "{args:?}");
    }
}

/// `--framing rtu` and `--framing ascii` ask a serial-line device directly: `mbgate
/// sim` as units 1 and 2, each register holding its address. Both frames byte-exact in
/// the port's framing (CRC or LRC included), the values decoded, a write read back.
#[test]
fn serial_rtu_and_ascii_ask_a_device_directly() {
    for (framing, encode) in [
        ("rtu", rtu::encode as fn(u8, &[u8]) -> Vec<u8>),
        ("ascii", ascii::encode),
    ] {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let _sim = serial_units(&socat.dev, framing, "1,2");
        let port = socat.gw.to_str().unwrap();
        let target = ["--serial", port, "--framing", framing, "--baud", "19200"];
        let m = |args: &[&str]| mbgate(&with(&target, args));
        let spaced = |b: Vec<u8>| mbgate::frame::hex::Hex(&b).to_string();
        assert_reply(
            &m(&["read", "-v", "-u", "2", "holding", "7", "2"]),
            &spaced(encode(2, &[0x03, 0x00, 0x07, 0x00, 0x02])),
            &spaced(encode(2, &[0x03, 0x04, 0x00, 0x07, 0x00, 0x08])),
            &["7: 7 (0x0007)", "8: 8 (0x0008)"],
        );
        assert_values(
            &m(&["write", "register", "1", "0x0105"]),
            &["1: 261 (0x0105)"],
        );
        assert_values(
            &m(&["read", "holding", "0", "3"]),
            &["0: 0 (0x0000)", "1: 261 (0x0105)", "2: 2 (0x0002)"],
        );
    }
}
