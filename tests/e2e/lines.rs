//! Several lines behind one address, a device on the network, RTU-over-TCP masters
//! (docs/design.md §4.1; docs/several-buses.md, network-devices.md, rtu-over-tcp.md,
//! whose commands tests/packaging/docs.rs runs), end to end: the mbgate binary, socat ptys with
//! raw devices, pymodbus' ModbusTcpServer as the device on TCP and pymodbus' RTU
//! framer on a TCP client as a master.

use crate::common;

use common::*;
use mbgate::frame::rtu;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// Two pty pairs, each in its own folder of `dir`: two serial lines.
fn two_ptys(dir: &Path) -> (Socat, Socat) {
    let (a, b) = (dir.join("a"), dir.join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    (Socat::start(&a), Socat::start(&b))
}

fn connect(addr: SocketAddr) -> TcpStream {
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    s.set_nodelay(true).unwrap();
    s
}

/// `[[line]]` serial tables for a pty at the fastest speed (see `Cfg::pty_line`).
fn pty_line(path: &Path, framing: &str) -> String {
    format!(
        "[line.serial]\npath = {:?}\nframing = {framing:?}\nbaud_rate = 4000000\n\
         silence_floor_ms = 0\n",
        path.display().to_string()
    )
}

/// Two pty lines (RTU and MBAP) and a Modbus/TCP device (pymodbus) behind one
/// listener: each request reaches the line serving its unit and no other, the master's
/// unit 11 is unit 1 on the TCP line and comes back as 11, and a unit no line serves
/// is answered 0x0A without reaching any line or waiting for a timeout.
#[test]
fn requests_are_routed_by_unit_to_two_ptys_and_a_device_on_tcp() {
    let dir = tempdir();
    let (sa, sb) = two_ptys(dir.path());
    let rtu_dev = RawRtuDevice::start_at(&sa.dev, 4_000_000, rtu_register_device(&[1, 2]));
    let mbap_dev = RawDevice::start(&sb.dev, register_device(&[5], Duration::ZERO));
    let port = free_port();
    let _tcp_dev = Py::start("tcp_device.py", &["--port", &port.to_string()]);
    let text = format!(
        "[[line]]\nunits = [1, 2]\n{}\n[[line]]\nunits = [5]\n{}\n\
         [[line]]\nunits = [\"20-22\"]\nremap = {{ 11 = 1 }}\n\
         [line.tcp]\naddress = \"127.0.0.1:{port}\"\nframing = \"mbap\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n[log]\nlevel = \"debug\"\n",
        pty_line(&sa.gw, "rtu"),
        pty_line(&sb.gw, "mbap"),
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    gw.wait_log("device socket open", Duration::from_secs(10));
    let mut m = connect(addrs[0]);

    assert_eq!(
        transact(&mut m, &read_req(1, 1, 3, 2)),
        read_reply(1, 1, &[3, 4])
    );
    assert_eq!(
        transact(&mut m, &read_req(2, 5, 7, 1)),
        read_reply(2, 5, &[7])
    );
    assert_eq!(
        transact(&mut m, &read_req(3, 11, 1, 3)),
        read_reply(3, 11, &[1001, 1002, 1003]),
        "unit 11 is the TCP device's unit 1, answered as 11"
    );
    // Unit 20 is on the TCP line as itself: the device has no unit 20 and says so
    // (exception 04 from pymodbus), which is not the gateway's 0x0A.
    assert_eq!(
        transact(&mut m, &read_req(4, 20, 1, 1)),
        hex("00 04 00 00 00 03 14 83 04")
    );
    let asked = Instant::now();
    assert_eq!(
        transact(&mut m, &read_req(5, 9, 1, 1)),
        hex("00 05 00 00 00 03 09 83 0A"),
        "a unit no line serves: 0x0A"
    );
    assert!(
        asked.elapsed() < Duration::from_millis(1000),
        "answered before any response timeout: {:?}",
        asked.elapsed()
    );
    let rtu_units: Vec<u8> = rtu_dev.requests().iter().map(|f| f[0]).collect();
    let mbap_units: Vec<u8> = mbap_dev.requests().iter().map(|r| r.unit()).collect();
    assert_eq!((rtu_units, mbap_units), (vec![1], vec![5]));
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// One line's device never answers; another line's replies keep coming meanwhile: the
/// dead line's masters get 0x0B after its response timeout, and while each of those
/// requests waits, the healthy line answers many. Prints the healthy line's p50 alone
/// and beside the dead one.
#[test]
fn a_dead_line_does_not_hold_up_another() {
    let dir = tempdir();
    let (sa, sb) = two_ptys(dir.path());
    // Line A: an RTU bus whose device is gone (nothing answers on the pty).
    let _dead = RawRtuDevice::start_at(&sa.dev, 4_000_000, rtu_register_device(&[]));
    let _alive = RawDevice::start(&sb.dev, register_device(&[5], Duration::ZERO));
    let text = format!(
        "[[line]]\nunits = [1]\n{}\n[line.relay]\nresponse_timeout_ms = 300\n\
         unit_backoff = false\n\n[[line]]\nunits = [5]\n{}\n\
         [line.relay]\nresponse_timeout_ms = 5000\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n",
        pty_line(&sa.gw, "rtu"),
        pty_line(&sb.gw, "mbap"),
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let addr = addrs[0];

    let healthy = |n: u16, m: &mut TcpStream, at: &mut Vec<Instant>| -> Vec<Duration> {
        (0..n)
            .map(|i| {
                let t = Instant::now();
                assert_eq!(transact(m, &read_req(i, 5, i, 1)), read_reply(i, 5, &[i]));
                at.push(Instant::now());
                t.elapsed()
            })
            .collect()
    };
    let p50 = |mut d: Vec<Duration>| {
        d.sort();
        d[d.len() / 2]
    };
    let mut m = connect(addr);
    let alone = p50(healthy(200, &mut m, &mut Vec::new()));

    // Three masters keep the dead line busy: each request waits its 300 ms.
    let stop = Arc::new(AtomicBool::new(false));
    let timed_out = Arc::new(Mutex::new(Vec::new()));
    let dead: Vec<_> = (0..3)
        .map(|_| {
            let (stop, timed_out) = (stop.clone(), timed_out.clone());
            thread::spawn(move || {
                let mut d = connect(addr);
                while !stop.load(Ordering::Relaxed) {
                    let sent = Instant::now();
                    let reply = transact(&mut d, &read_req(7, 1, 0, 1));
                    assert_eq!(reply, hex("00 07 00 00 00 03 01 83 0B"));
                    timed_out.lock().unwrap().push((sent, Instant::now()));
                }
            })
        })
        .collect();
    thread::sleep(Duration::from_millis(50));
    let mut at = Vec::new();
    let beside = healthy(400, &mut m, &mut at);
    // Keep the dead masters going until one of their requests has spanned a stretch
    // of healthy replies.
    wait_for(
        "a dead-line request to time out",
        Duration::from_secs(10),
        || !timed_out.lock().unwrap().is_empty(),
    );
    stop.store(true, Ordering::Relaxed);
    for t in dead {
        t.join().unwrap();
    }
    let timed_out = timed_out.lock().unwrap().clone();
    let most = timed_out
        .iter()
        .map(|(sent, answered)| at.iter().filter(|t| *t > sent && *t < answered).count())
        .max()
        .unwrap();
    let beside = p50(beside);
    eprintln!("healthy line p50: alone {alone:?}, beside a dead line {beside:?}; {} dead-line timeouts, up to {most} healthy replies during one", timed_out.len());
    assert!(
        most >= 10,
        "the healthy line answered only {most} requests while a dead-line request waited"
    );
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// What one master saw, in order: `Ok` for the device's registers, else the code.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Seen {
    Ok,
    Exception(u8),
}

/// pymodbus' ModbusTcpServer behind a TCP line, eight masters all on transaction id 0;
/// the device is stopped and started again mid-run: every master keeps its connection,
/// gets 0x0A while the device is down (0x0B for a request on the way when it went),
/// and is served again once it is back, without restarting mbgate.
#[test]
fn masters_stay_connected_while_the_device_on_tcp_restarts() {
    let dir = tempdir();
    let port = free_port();
    let arg = port.to_string();
    let device = Py::start("tcp_device.py", &["--port", &arg]);
    let text = format!(
        "[[line]]\n[line.tcp]\naddress = \"127.0.0.1:{port}\"\n\n[line.relay]\n\
         response_timeout_ms = 500\n\n[[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [log]\nlevel = \"debug\"\n"
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    gw.wait_log("device socket open", Duration::from_secs(10));
    let stop = Arc::new(AtomicBool::new(false));
    let seen: Vec<Arc<Mutex<Vec<Seen>>>> = (0..8).map(|_| Arc::default()).collect();
    let masters: Vec<_> = seen
        .iter()
        .map(|seen| {
            let (stop, seen, addr) = (stop.clone(), seen.clone(), addrs[0]);
            thread::spawn(move || {
                let mut m = connect(addr);
                while !stop.load(Ordering::Relaxed) {
                    let reply = transact(&mut m, &read_req(0, 1, 1, 2));
                    let got = if reply == read_reply(0, 1, &[1001, 1002]) {
                        Seen::Ok
                    } else {
                        assert_eq!(reply[..8], hex("00 00 00 00 00 03 01 83"), "{reply:02X?}");
                        Seen::Exception(reply[8])
                    };
                    seen.lock().unwrap().push(got);
                    thread::sleep(Duration::from_millis(5));
                }
            })
        })
        .collect();
    let all = |ok: &dyn Fn(&[Seen]) -> bool| seen.iter().all(|s| ok(&s.lock().unwrap()));
    let count = |s: &[Seen], what: Seen| s.iter().filter(|x| **x == what).count();
    wait_for("every master served", Duration::from_secs(10), || {
        all(&|s| count(s, Seen::Ok) >= 5)
    });
    drop(device);
    wait_for("0x0A for every master", Duration::from_secs(10), || {
        all(&|s| count(s, Seen::Exception(0x0A)) >= 3)
    });
    let down: Vec<usize> = seen.iter().map(|s| s.lock().unwrap().len()).collect();
    let _device = Py::start("tcp_device.py", &["--port", &arg]);
    wait_for("every master served again", Duration::from_secs(15), || {
        seen.iter()
            .zip(&down)
            .all(|(s, &from)| count(&s.lock().unwrap()[from..], Seen::Ok) >= 5)
    });
    stop.store(true, Ordering::Relaxed);
    for m in masters {
        m.join()
            .expect("a master lost its connection or got a wrong reply");
    }
    for s in &seen {
        let s = s.lock().unwrap();
        assert!(
            s.iter()
                .all(|x| matches!(x, Seen::Ok | Seen::Exception(0x0A | 0x0B))),
            "{s:?}"
        );
    }
    let stats = {
        let status = gw.terminate(Duration::from_secs(10));
        assert!(status.success());
        gw.log()
    };
    assert!(stats.contains("device socket lost"), "{stats}");
    // One connection to the device for all eight masters, once before the restart and
    // once after it.
    assert_eq!(stats.matches("device socket open").count(), 2, "{stats}");
}

/// `request_pause_ms` keeps the line quiet that long after each reply: a master that
/// sends its next request the moment it has the reply still finds the device's
/// requests that far apart (without it they come a few milliseconds apart).
#[test]
fn request_pause_ms_spaces_the_requests_on_the_line() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = RawRtuDevice::start_at(&socat.dev, 4_000_000, rtu_register_device(&[1]));
    let text = format!(
        "[[line]]\nunits = [1]\n{}\n[line.relay]\nrequest_pause_ms = 80\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n",
        pty_line(&socat.gw, "rtu")
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    let mut m = connect(addrs[0]);
    for tid in 1..=4 {
        assert_eq!(
            transact(&mut m, &read_req(tid, 1, tid, 1)),
            read_reply(tid, 1, &[tid])
        );
    }
    let at = dev.seen_at.lock().unwrap().clone();
    assert_eq!(at.len(), 4);
    for pair in at.windows(2) {
        let apart = pair[1] - pair[0];
        assert!(
            apart >= Duration::from_millis(80),
            "requests {apart:?} apart"
        );
    }
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// pymodbus as an RTU-over-TCP master (its RTU framer on a TCP client) through an
/// `rtu` listener, beside a Modbus/TCP one, to an RTU device on one pty and an MBAP
/// device on another; a master whose request has a bad CRC is closed, and only it.
#[test]
fn rtu_over_tcp_masters_reach_an_rtu_and_an_mbap_line() {
    let dir = tempdir();
    let (sa, sb) = two_ptys(dir.path());
    let rtu_dev = RawRtuDevice::start_at(&sa.dev, 4_000_000, rtu_register_device(&[1]));
    let mbap_dev = RawDevice::start(&sb.dev, register_device(&[5], Duration::ZERO));
    let text = format!(
        "[[line]]\nunits = [1]\n{}\n[[line]]\nunits = [5]\n{}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n",
        pty_line(&sa.gw, "rtu"),
        pty_line(&sb.gw, "mbap"),
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 2);
    let (mbap_at, rtu_at) = (addrs[0], addrs[1]);

    let steps = r#"[["read_holding_registers", [3], {"count": 2, "device_id": 1}],
                    ["write_register", [8, 4660], {"device_id": 1}],
                    ["read_holding_registers", [8], {"count": 1, "device_id": 1}],
                    ["read_holding_registers", [7], {"count": 2, "device_id": 5}],
                    ["read_holding_registers", [0], {"count": 1, "device_id": 9}]]"#;
    let port = rtu_at.port().to_string();
    let (status, out) = Py::run("master.py", &["--port", &port, "--framer", "rtu", steps]);
    assert!(status.success(), "master.py: {out}");
    let want = r#"[{"registers": [3, 4]}, {"registers": [4660], "address": 8, "count": 0}, {"registers": [4660]}, {"registers": [7, 8]}, {"exception": 10}]"#;
    assert_eq!(out.trim(), want);
    assert_eq!(rtu_dev.requests().len(), 3);
    assert_eq!(mbap_dev.requests().len(), 1);

    // Raw RTU masters: one stays, one sends a frame whose CRC is wrong and is closed.
    let mut good = connect(rtu_at);
    let mut bad = connect(rtu_at);
    let request = rtu::encode(1, &[3, 0, 3, 0, 1]);
    good.write_all(&request).unwrap();
    let mut reply = [0u8; 7];
    good.read_exact(&mut reply).unwrap();
    assert_eq!(reply[..], rtu::encode(1, &[3, 2, 0, 3])[..]);
    let mut broken = request.clone();
    broken[7] ^= 0xFF;
    bad.write_all(&broken).unwrap();
    assert!(
        is_closed(&mut bad, Duration::from_secs(5)),
        "a bad CRC closes"
    );
    good.write_all(&request).unwrap();
    good.read_exact(&mut reply).unwrap();
    assert_eq!(
        reply[..],
        rtu::encode(1, &[3, 2, 0, 3])[..],
        "the other stays"
    );
    // The Modbus/TCP listener shares the same lines.
    let mut m = connect(mbap_at);
    assert_eq!(
        transact(&mut m, &read_req(1, 5, 2, 1)),
        read_reply(1, 5, &[2])
    );
    assert_eq!(
        rtu_dev.requests().len(),
        5,
        "the bad frame never reached the line"
    );
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// `mbgate sim --listen` as a serial device server in raw TCP mode (RTU frames on a
/// socket, one connection at a time) behind a TCP line in RTU framing, and `mbgate
/// read --tcp --framing rtu` through an `rtu` listener: the client's RTU frame goes
/// to the simulator as RTU, and a second connection to the simulator, while the
/// gateway holds the first, is closed at once.
#[test]
fn the_client_and_the_simulator_speak_rtu_over_tcp_through_the_gateway() {
    let dir = tempdir();
    let port = free_port();
    let at = format!("127.0.0.1:{port}");
    let _sim = Proc::start(
        &[
            "sim",
            "--listen",
            &at,
            "--framing",
            "rtu",
            "--profile",
            "generic",
            "--units",
            "1,2",
            "--fill",
            "address",
            "--headless",
        ],
        "simulating ",
    );
    let text = format!(
        "[[line]]\n[line.tcp]\naddress = \"{at}\"\nframing = \"rtu\"\n\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n\n[log]\nlevel = \"debug\"\n"
    );
    let (mut gw, addrs) = gateway_from_file(dir.path(), &text, 1);
    gw.wait_log("device socket open", Duration::from_secs(10));
    let listener = addrs[0].to_string();
    let run = mbgate(&[
        "read",
        "--tcp",
        &listener,
        "--framing",
        "rtu",
        "--unit",
        "2",
        "holding-registers",
        "3",
        "2",
        "-v",
    ]);
    assert_eq!(run.code, 0, "{}", run.stderr);
    assert!(
        run.stdout.contains("tx 02 03 00 03 00 02"),
        "{}",
        run.stdout
    );
    assert!(
        run.stdout.contains("3: 3 (0x0003)\n4: 4 (0x0004)"),
        "{}",
        run.stdout
    );
    let mut second = TcpStream::connect(&at).unwrap();
    assert!(
        is_closed(&mut second, Duration::from_secs(5)),
        "one connection at a time"
    );
    let run = mbgate(&[
        "read",
        "--tcp",
        &listener,
        "--framing",
        "rtu",
        "--unit",
        "1",
        "holding-registers",
        "7",
        "1",
    ]);
    assert_eq!(run.code, 0, "{}", run.stderr);
    assert!(run.stdout.contains("7: 7 (0x0007)"), "{}", run.stdout);
    assert!(gw.terminate(Duration::from_secs(10)).success());
}

/// `mbgate sim --listen ADDR --connections 2` is a Modbus/TCP slave two masters reach
/// at once: both are answered, each with its own transaction id, while a third
/// connection is closed at once; `--connections` above 1 in RTU framing is refused.
#[test]
fn the_simulator_serves_as_many_connections_as_asked() {
    let port = free_port();
    let at = format!("127.0.0.1:{port}");
    let args = |framing: &str| -> Vec<String> {
        let argv = [
            "sim",
            "--listen",
            &at,
            "--connections",
            "2",
            "--framing",
            framing,
        ];
        let tail = ["--profile", "generic", "--fill", "address", "--headless"];
        argv.iter().chain(&tail).map(|s| s.to_string()).collect()
    };
    let refused = std::process::Command::new(env!("CARGO_BIN_EXE_mbgate"))
        .args(args("rtu"))
        .output()
        .unwrap();
    assert_eq!(refused.status.code(), Some(2), "{refused:?}");
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("--framing mbap"),
        "{refused:?}"
    );
    let argv = args("mbap");
    let argv: Vec<&str> = argv.iter().map(String::as_str).collect();
    let _sim = Proc::start(&argv, "serving Modbus/TCP on");
    let addr: SocketAddr = at.parse().unwrap();
    let (mut a, mut b) = (connect(addr), connect(addr));
    let mut third = connect(addr);
    third
        .set_read_timeout(Some(Duration::from_secs(3)))
        .unwrap();
    let mut buf = [0u8; 1];
    assert!(
        matches!(third.read(&mut buf), Ok(0)),
        "the third is closed at once"
    );
    assert_eq!(
        transact(&mut a, &read_req(7, 1, 3, 2)),
        read_reply(7, 1, &[3, 4])
    );
    assert_eq!(
        transact(&mut b, &read_req(9, 1, 5, 1)),
        read_reply(9, 1, &[5])
    );
    assert_eq!(
        transact(&mut a, &read_req(8, 1, 0, 1)),
        read_reply(8, 1, &[0])
    );
}
