//! RTU and ASCII framing end to end: the real binary with `framing = "rtu"`
//! or `"ascii"`, socat pty pairs, pymodbus' `ModbusSerialServer` with the RTU and the
//! ASCII framer as the device, pymodbus TCP clients and raw bytes as the masters.
//! Everything on 127.0.0.1; every loop bounded in count and time.

use crate::common;
use common::sim::{serial_units, sim, RawLine};
use common::*;
use mbgate::frame::{ascii, rtu};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::thread;
use std::time::{Duration, Instant};

struct Bench {
    _dir: tempfile::TempDir,
    _socat: Socat,
    _device: Py,
    gw: Gateway,
}

/// socat, pymodbus' serial server with `framer` on one end, mbgate on the other.
fn pymodbus_bench(framer: &str, device_args: &[&str], extra: impl FnOnce(Cfg) -> Cfg) -> Bench {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let mut args = vec!["--port", socat.dev.to_str().unwrap(), "--framer", framer];
    args.extend_from_slice(device_args);
    let device = Py::start("stock_server.py", &args);
    // pymodbus answers as soon as a pty hands it the request, which on a real line
    // only a very fast one allows: a reply cannot start before the request has left.
    let cfg = Cfg::new(&socat.gw)
        .serial(&format!("framing = {framer:?}"))
        .serial("flow_control = \"none\"")
        .serial("baud_rate = 4000000")
        // pymodbus, in Python, answers in a few ms on a quiet machine and in hundreds
        // on a busy one: these tests are about bytes, not time.
        .relay("response_timeout_ms = 5000");
    let gw = Gateway::start(&extra(cfg), dir.path());
    Bench {
        _dir: dir,
        _socat: socat,
        _device: device,
        gw,
    }
}

fn run_tcp_client(gw: &Gateway) {
    let port = gw.addr.port().to_string();
    let (status, out) = Py::run("tcp_client.py", &["--host", "127.0.0.1", "--port", &port]);
    assert!(
        status.success() && out.contains("\"ok\": true"),
        "tcp_client.py failed: {out}\n{}",
        gw.log()
    );
}

/// pymodbus' RTU server as the device, pymodbus' TCP client as the master: FC 01, 02,
/// 03, 04, 05, 06, 0F, 10, 17 and an exception (83 02), each checked for its values
/// (tests/py/tcp_client.py), through `mbgate run` with `framing = "rtu"`.
#[test]
fn rtu_pymodbus_device_every_common_function_code() {
    every_common_function_code("rtu", rtu::encode);
}

/// The same with pymodbus' ASCII server and `framing = "ascii"`.
#[test]
fn ascii_pymodbus_device_every_common_function_code() {
    every_common_function_code("ascii", ascii::encode);
}

fn every_common_function_code(framer: &str, encode: fn(u8, &[u8]) -> Vec<u8>) {
    let b = pymodbus_bench(framer, &[], |c| c.log("traffic = true"));
    run_tcp_client(&b.gw);
    // The FC 03 read of registers 0..4 left in this framing, check and all.
    let want = Hex(&encode(1, &[0x03, 0, 0, 0, 5]));
    b.gw.wait_log(
        &format!("{want} dir=\"gw->serial\""),
        Duration::from_secs(2),
    );
}

struct Hex<'a>(&'a [u8]);

impl std::fmt::Display for Hex<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", mbgate::frame::hex::Hex(self.0))
    }
}

struct RawBench {
    _dir: tempfile::TempDir,
    _socat: Socat,
    device: RawRtuDevice,
    gw: Gateway,
}

fn raw_bench(handler: RtuHandler, extra: impl FnOnce(Cfg) -> Cfg) -> RawBench {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let device = RawRtuDevice::start(&socat.dev, handler);
    let cfg = Cfg::new(&socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"");
    let gw = Gateway::start(&extra(cfg), dir.path());
    RawBench {
        _dir: dir,
        _socat: socat,
        device,
        gw,
    }
}

/// Seed 001: TCP `0001 0000 0006 11 03 006B 0003` leaves mbgate as RTU
/// `11 03 00 6B 00 03 76 87`, and the RTU reply goes back with the master's id.
#[test]
fn the_rtu_read_of_protocol_md_section_2_byte_exact() {
    let b = raw_bench(rtu_register_device(&[0x11]), |c| c);
    let mut m = b.gw.connect();
    let reply = transact(&mut m, &hex("0001 0000 0006 11 03 006B 0003"));
    assert_eq!(b.device.requests(), [hex("11 03 00 6B 00 03 76 87")]);
    assert_eq!(reply, hex("0001 0000 0009 11 03 06 006B 006C 006D"));
}

/// A reply with a bad CRC is resent for reads (`retries`), never for writes.
#[test]
fn bad_crc_is_retried_for_reads_only() {
    let mut good = rtu_register_device(&[1]);
    let mut answered = 0;
    let handler: RtuHandler = Box::new(move |frame: &[u8]| {
        let mut reply = good(frame);
        answered += 1;
        // The first answer to each request is damaged on the line.
        if answered % 2 == 1 {
            *reply.last_mut().unwrap() ^= 0x5A;
        }
        reply
    });
    let b = raw_bench(handler, |c| {
        // Far longer than a busy machine delays a reply: "at once" is told from
        // "after the timeout" by a wide margin.
        c.relay("retries = 1").relay("response_timeout_ms = 3000")
    });
    let mut m = b.gw.connect();
    let start = Instant::now();
    assert_eq!(
        transact(&mut m, &read_req(7, 1, 40, 2)),
        read_reply(7, 1, &[40, 41])
    );
    assert!(
        start.elapsed() < Duration::from_millis(2500),
        "a bad CRC is known at once, not after the timeout: {:?}",
        start.elapsed()
    );
    let sent = b.device.requests();
    assert_eq!(sent.len(), 2, "the read went twice");
    assert_eq!(sent[0], sent[1]);
    // A write whose answer is damaged: not resent; the master is told 0x0B.
    let write = request(1, &[0x06, 0, 9, 0x12, 0x34]);
    assert_eq!(transact(&mut m, &write), hex("0008 0000 0003 01 86 0B"));
    assert_eq!(b.device.requests().len(), 3, "the write went once");
}

/// A request with transaction id 8.
fn request(unit: u8, pdu: &[u8]) -> Vec<u8> {
    mbgate::frame::Adu::build(8, unit, pdu).as_bytes().to_vec()
}

/// Broadcast (unit 0) with pymodbus' RTU server: the write acts on the device, the
/// master gets nothing (`broadcast_reply = "none"`), and the line is left quiet for
/// `broadcast_delay_ms` before the next request.
#[test]
fn broadcast_acts_on_the_device_and_gets_no_reply() {
    let b = pymodbus_bench("rtu", &["--broadcast"], |c| {
        c.relay("broadcast_delay_ms = 150")
    });
    let port = b.gw.addr.port().to_string();
    let steps = r#"[["write_register", [30, 4321], {"device_id": 0, "no_response_expected": true}],
                    ["read_holding_registers", [30], {"count": 1, "device_id": 1}]]"#;
    let (status, out) = Py::run("master.py", &["--port", &port, steps]);
    assert!(status.success(), "{out}");
    assert_eq!(
        out.trim(),
        r#"[{"sent": true}, {"registers": [4321]}]"#,
        "{}",
        b.gw.log()
    );
    // From a raw master: nothing comes back for a broadcast, and the next request waits
    // for the turnaround delay.
    let mut m = b.gw.connect();
    m.write_all(&request(0, &[0x06, 0, 31, 0, 5])).unwrap();
    let sent = Instant::now();
    let reply = transact(&mut m, &read_req(9, 1, 31, 1));
    assert_eq!(reply, read_reply(9, 1, &[5]), "the broadcast got no reply");
    assert!(
        sent.elapsed() >= Duration::from_millis(150),
        "turnaround delay kept: {:?}",
        sent.elapsed()
    );
}

/// `broadcast_reply = "echo"`: the master gets the answer a device would have given.
#[test]
fn broadcast_echo_answers_the_master() {
    let b = raw_bench(rtu_register_device(&[1]), |c| {
        c.relay("broadcast_reply = \"echo\"")
    });
    let mut m = b.gw.connect();
    let write = mbgate::frame::Adu::build(0x77, 0, &[0x10, 0, 2, 0, 1, 2, 0, 9]);
    let reply = transact(&mut m, write.as_bytes());
    assert_eq!(reply, hex("0077 0000 0006 00 10 0002 0001"));
    wait_for("the broadcast on the line", Duration::from_secs(2), || {
        !b.device.requests().is_empty()
    });
    assert_eq!(
        b.device.requests(),
        [rtu::encode(0, &[0x10, 0, 2, 0, 1, 2, 0, 9])]
    );
}

/// The simulator as one RTU device, unit 1, paced at 19 200 baud.
fn rtu_unit_1(dev: &std::path::Path) -> Proc {
    sim(
        dev,
        &[
            "--framing",
            "rtu",
            "--profile",
            "generic",
            "--units",
            "1",
            "--baud",
            "19200",
            "--headless",
        ],
    )
}

/// A gateway configuration for an RTU line without flow control.
fn rtu_line(gw: &std::path::Path) -> Cfg {
    Cfg::new(gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
}

/// A dead unit beside a healthy one on the same line: once the dead one is backed
/// off, its requests are answered 0x0B without using the line and the healthy unit's
/// median latency stays within one response timeout and its guard of what it is
/// alone. The timeout is far beyond what a busy machine adds to the simulator's
/// answer (the healthy unit must never time out); the worst case beside a dead unit,
/// a tight bound, is measured by `cargo bench --bench gateway -- rtu-backoff`.
#[test]
fn dead_unit_is_backed_off_and_does_not_slow_the_healthy_one() {
    const TIMEOUT_MS: u64 = 1000;
    const GUARD_MS: u64 = 50;
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _device = rtu_unit_1(&socat.dev);
    let cfg = rtu_line(&socat.gw)
        .relay(&format!("response_timeout_ms = {TIMEOUT_MS}"))
        .relay(&format!("timeout_guard_ms = {GUARD_MS}"))
        .relay("unit_backoff_after = 2")
        .relay("unit_backoff_ms = 1000")
        .relay("unit_backoff_max_ms = 4000");
    let mut gw = Gateway::start(&cfg, dir.path());
    let addr = gw.addr;

    let poll = |s: &mut TcpStream, n: usize| -> Vec<Duration> {
        (0..n)
            .map(|i| {
                let t = Instant::now();
                let reply = transact(s, &read_req(i as u16, 1, 0, 1));
                assert_eq!(reply, read_reply(i as u16, 1, &[0]));
                t.elapsed()
            })
            .collect()
    };
    let mut healthy = gw.connect();
    warm_up(&mut healthy);
    let solo = spread(poll(&mut healthy, 60));

    // The dead unit's master asks as fast as it is answered, for 6 s: two timeouts
    // back it off, then it is answered at once but for a probe now and then.
    let dead = thread::spawn(move || {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut fast = 0;
        let mut slow = 0;
        let stop = Instant::now() + Duration::from_secs(6);
        for i in 0..100_000u32 {
            if Instant::now() >= stop {
                break;
            }
            let t = Instant::now();
            let reply = transact(&mut s, &read_req(i as u16, 2, 0, 1));
            assert_eq!(reply, hex(&format!("{:04X} 0000 0003 02 83 0B", i as u16)));
            if t.elapsed() < Duration::from_millis(TIMEOUT_MS / 2) {
                fast += 1;
            } else {
                slow += 1;
            }
        }
        (fast, slow)
    });
    thread::sleep(Duration::from_millis(2 * (TIMEOUT_MS + GUARD_MS) + 100));
    let mut samples = Vec::new();
    let stop = Instant::now() + Duration::from_millis(2500);
    while Instant::now() < stop && samples.len() < 10_000 {
        samples.extend(poll(&mut healthy, 1));
    }
    let beside = spread(samples);
    let (fast, slow) = dead.join().unwrap();
    eprintln!(
        "healthy alone: p50 {:?} max {:?}; beside a dead unit: p50 {:?} max {:?} ({} polls); \
         dead unit: {fast} answered 0x0B at once, {slow} after a timeout",
        solo.p50, solo.max, beside.p50, beside.max, beside.n
    );
    let one = Duration::from_millis(TIMEOUT_MS + GUARD_MS);
    assert!(beside.p50 <= solo.p50 + one, "p50 {:?}", beside.p50);
    assert!(
        slow <= 6,
        "the dead unit timed out {slow} times: not backed off"
    );
    assert!(fast >= 20, "only {fast} fast 0x0B answers");
    gw.terminate(Duration::from_secs(5));
    assert!(gw.log().contains("unit backed off"), "{}", gw.log());
}

/// A master polls a backed-off unit in a tight loop: its 0x0B answers come no faster
/// than the line could have served the requests (19 200 baud: a read and an exception
/// reply, each after 3.5 character times, 10.3 ms), and the gateway's CPU stays low.
/// The healthy unit's throughput beside it is checked only for gross loss here (two
/// one-second windows on a shared machine are too noisy for more); `cargo bench
/// --bench gateway -- rtu-backoff` measures it.
#[test]
fn backed_off_unit_polled_in_a_tight_loop_is_answered_at_the_line_pace() {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Arc, Mutex};
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _device = rtu_unit_1(&socat.dev);
    let cfg = rtu_line(&socat.gw)
        // Far beyond what a busy machine adds to the simulator's answer: the healthy
        // unit never times out.
        .relay("response_timeout_ms = 2000")
        .relay("timeout_guard_ms = 50")
        .relay("unit_backoff_after = 2")
        // No probe while this runs.
        .relay("unit_backoff_ms = 60000")
        .relay("unit_backoff_max_ms = 60000");
    let mut gw = Gateway::start(&cfg, dir.path());
    let addr = gw.addr;
    let pid = gw.proc.pid();
    let healthy_for = |s: &mut TcpStream, window: Duration| -> usize {
        let stop = Instant::now() + window;
        let mut n = 0;
        while Instant::now() < stop {
            assert_eq!(transact(s, &read_req(n, 1, 0, 1)), read_reply(n, 1, &[0]));
            n = n.wrapping_add(1);
        }
        usize::from(n)
    };
    let mut healthy = gw.connect();
    warm_up(&mut healthy);
    let alone = healthy_for(&mut healthy, Duration::from_secs(1));

    let answered = Arc::new(Mutex::new(Vec::new()));
    let done = Arc::new(AtomicBool::new(false));
    let (answered2, done2) = (answered.clone(), done.clone());
    let dead = thread::spawn(move || {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut i = 0u16;
        while !done2.load(Ordering::Relaxed) && i < 60_000 {
            let reply = transact(&mut s, &read_req(i, 2, 0, 1));
            assert_eq!(reply, hex(&format!("{i:04X} 0000 0003 02 83 0B")));
            answered2.lock().unwrap().push(Instant::now());
            i += 1;
        }
    });
    // Two timeouts and their guards back it off (bounded wait, then a margin).
    wait_for("the unit backed off", Duration::from_secs(30), || {
        gw.log().contains("unit backed off")
    });
    thread::sleep(Duration::from_millis(200));
    let window = Duration::from_millis(1500);
    let (from, cpu0) = (Instant::now(), cpu_ns(pid));
    thread::sleep(window);
    let (to, cpu1) = (Instant::now(), cpu_ns(pid));
    let beside = healthy_for(&mut healthy, Duration::from_secs(1));
    done.store(true, Ordering::Relaxed);
    dead.join().unwrap();
    let counters = gw.stop();

    let paced = answered
        .lock()
        .unwrap()
        .iter()
        .filter(|t| (from..to).contains(*t))
        .count();
    let cpu = (cpu1 - cpu0) as f64 / (to - from).as_nanos() as f64;
    // 8 bytes out, 5 back at 10 bits a byte, and twice 1.75 ms.
    let line = Duration::from_micros(13 * 10 * 1_000_000 / 19_200 + 3500);
    let most = ((to - from).as_secs_f64() / line.as_secs_f64() * 1.1) as usize + 2;
    eprintln!(
        "backed-off unit: {paced} answers in {:?} (at most {most}), gateway CPU {:.2} % of a core; \
         healthy unit {alone}/s alone, {beside}/s beside it; {counters:?}",
        to - from,
        cpu * 100.0
    );
    assert!(
        paced >= 10,
        "the backed-off unit was answered {paced} times"
    );
    assert!(paced <= most, "{paced} answers: faster than the line");
    assert!(cpu < 0.10, "{:.2} % of a core", cpu * 100.0);
    // Without the back-off each healthy read waits behind a 2 s timeout: a fifth of
    // the rate alone still tells that apart on a machine whose load changes between
    // the two windows.
    assert!(
        beside * 5 >= alone,
        "healthy unit: {beside}/s beside a polled dead unit, {alone}/s alone"
    );
    assert_eq!(counters["timeouts"], 2, "only the two that backed it off");
}

/// A probe of a backed-off unit waits `probe_timeout_ms`, not the full response
/// timeout, so a dead unit holds the line from the healthy ones less long.
#[test]
fn probe_of_a_backed_off_unit_has_its_own_shorter_timeout() {
    let b = raw_bench(rtu_register_device(&[1]), |c| {
        c.relay("response_timeout_ms = 2000")
            .relay("probe_timeout_ms = 60")
            .relay("timeout_guard_ms = 20")
            .relay("unit_backoff_after = 1")
            .relay("unit_backoff_ms = 200")
    });
    let mut m = b.gw.connect();
    let timed = |m: &mut TcpStream, tid: u16| {
        let t = Instant::now();
        let reply = transact(m, &read_req(tid, 2, 0, 1));
        assert_eq!(reply, hex(&format!("{tid:04X} 0000 0003 02 83 0B")));
        t.elapsed()
    };
    let first = timed(&mut m, 1);
    assert!(first >= Duration::from_millis(1990), "{first:?}");
    thread::sleep(Duration::from_millis(250));
    let probe = timed(&mut m, 2);
    // The device's thread records what it read; on a busy machine it may read the
    // probe after the gateway has given up on it.
    wait_for("the probe on the line", Duration::from_secs(10), || {
        b.device.requests().len() == 2
    });
    // Shorter than the response timeout by far more than load adds.
    assert!(
        probe >= Duration::from_millis(60) && probe < Duration::from_millis(1000),
        "the probe took {probe:?}"
    );
    // Backed off again: answered without the line.
    timed(&mut m, 3);
    assert_eq!(b.device.requests().len(), 2);
    // The healthy unit is served throughout.
    assert_eq!(
        transact(&mut m, &read_req(4, 1, 3, 1)),
        read_reply(4, 1, &[3])
    );
}

/// Reads unit 1 until it has answered 5 times in a row: on a busy machine the
/// simulator, just started, can miss the first response timeouts of 200 ms.
fn warm_up(s: &mut TcpStream) {
    let mut in_a_row = 0;
    for tid in 0..50 {
        if transact(s, &read_req(tid, 1, 0, 1)) == read_reply(tid, 1, &[0]) {
            in_a_row += 1;
            if in_a_row == 5 {
                return;
            }
        } else {
            in_a_row = 0;
        }
    }
    panic!("unit 1 never answered 5 times in a row");
}

struct Spread {
    p50: Duration,
    max: Duration,
    n: usize,
}

fn spread(mut v: Vec<Duration>) -> Spread {
    v.sort();
    Spread {
        p50: v[v.len() / 2],
        max: *v.last().unwrap(),
        n: v.len(),
    }
}

/// `rs485 = true` on a pty, which cannot do it: a warning, and the gateway serves.
#[test]
fn rs485_on_a_port_without_it_warns_and_serves() {
    let b = raw_bench(rtu_register_device(&[1]), |c| {
        c.serial("rs485 = true")
            .serial("rs485_delay_before_send_ms = 1")
    });
    let mut m = b.gw.connect();
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 3, 1)),
        read_reply(1, 1, &[3])
    );
    b.gw.wait_log("does not support RS-485 mode", Duration::from_secs(2));
}

/// `echo = true`: an adapter that echoes every byte sent, as it goes out; the echo is
/// read back and discarded, the reply after it is the master's.
#[test]
fn local_echo_is_suppressed() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let mut device = rtu_register_device(&[1]);
    let _device = RawRtuDevice::scripted(
        &socat.dev,
        Box::new(move |frame: &[u8]| {
            vec![
                (Duration::ZERO, frame.to_vec()),
                (wire_time(frame.len(), 19_200), device(frame)),
            ]
        }),
    );
    let cfg = Cfg::new(&socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial("echo = true");
    let gw = Gateway::start(&cfg, dir.path());
    let mut m = gw.connect();
    for i in 0..5u16 {
        assert_eq!(
            transact(&mut m, &read_req(i, 1, 10 + i, 2)),
            read_reply(i, 1, &[10 + i, 11 + i])
        );
    }
}

/// `mbgate sim --framing rtu` and `--framing ascii`: requests decoded by CRC or LRC,
/// answered in the same framing, byte for byte.
#[test]
fn simulator_speaks_rtu_and_ascii() {
    for (framing, encode) in [
        ("rtu", rtu::encode as fn(u8, &[u8]) -> Vec<u8>),
        ("ascii", ascii::encode),
    ] {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let _sim = serial_units(&socat.dev, framing, "1,2");
        let mut line = RawLine::open(&socat.gw);
        let want = encode(2, &[0x03, 4, 0, 7, 0, 8]);
        let got = line.transact(&encode(2, &[0x03, 0, 7, 0, 2]), want.len());
        assert_eq!(got, want, "{framing}");
        // A damaged request gets no answer; the next good one does.
        let mut bad = encode(1, &[0x06, 0, 1, 0, 5]);
        bad[3] ^= 0x01;
        line.send(&bad);
        let want = encode(1, &[0x06, 0, 1, 0, 5]);
        let got = line.transact(&want, want.len());
        assert_eq!(got, want, "{framing}: the write after a damaged one");
        // Through the gateway.
        drop(line);
        let cfg = Cfg::new(&socat.gw)
            .serial(&format!("framing = {framing:?}"))
            .serial("flow_control = \"none\"");
        let gw = Gateway::start(&cfg, dir.path());
        let mut m = gw.connect();
        assert_eq!(
            transact(&mut m, &read_req(3, 1, 1, 2)),
            read_reply(3, 1, &[5, 2]),
            "{framing}"
        );
        let mut buf = [0u8; 1];
        m.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
        assert!(m.read(&mut buf).is_err(), "one reply only");
    }
}
