//! The hostile peers of a Modbus/UDP listener, standing (docs/security.md "Threat
//! model", "A Modbus/UDP listener"): datagrams with forged sources (raw IPv4 packets,
//! tests/common/forge.rs; the tests skip, saying so, where raw sockets are refused),
//! the listener's own address among them; loops started between two gateways and
//! between mbgate and pymodbus' `ModbusUdpServer` (which answers even answers);
//! reflection and amplification counted in datagrams and bytes at the forged source;
//! the source table filled by forged and one-shot sources; a reload with requests
//! queued; the lines' notifications to UDP sources. Each gateway has its own device,
//! pymodbus' RTU server on a socat pty (unit 1; any other unit no line serves, answered
//! 0x0A at once with no device). Every count is asserted; every loop is bounded. A new
//! behaviour of the UDP listener is run through these before it ships.

use crate::common;
use common::forge::Forger;
use common::*;
use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, UdpSocket};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

fn mbap(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    mbgate::frame::Adu::build(tid, unit, pdu)
        .as_bytes()
        .to_vec()
}

/// FC 06, write `value` to holding register `addr`: its reply repeats it.
fn write06(tid: u16, unit: u8, addr: u16, value: u16) -> Vec<u8> {
    let [a, b] = addr.to_be_bytes();
    let [c, d] = value.to_be_bytes();
    mbap(tid, unit, &[6, a, b, c, d])
}

/// A gateway in front of its own device, with one UDP listener at `address` and
/// `extra` keys, and its metrics listener.
struct Site {
    _dir: tempfile::TempDir,
    _socat: Socat,
    _device: Py,
    gw: Gateway,
}

impl Site {
    fn udp(&self) -> SocketAddr {
        self.gw.addr
    }

    /// The sum of a metric's samples, now.
    fn metric(&self, name: &str) -> u64 {
        self.gw.metric(name) as u64
    }

    /// Waits until the metric `name` is `n` (fails past 10 s).
    fn wait_metric(&self, name: &str, n: u64) {
        let what = format!("{name} = {n}");
        wait_for(&what, Duration::from_secs(10), || self.metric(name) >= n);
        assert_eq!(self.metric(name), n, "{name}");
    }

    /// Holding register `addr` as an honest master reads it now.
    fn register(&self, addr: u16) -> u16 {
        let got = udp_transact(&self.udp().to_string(), &read_req(77, 1, addr, 1)).unwrap();
        assert_eq!(got.len(), 11, "{got:02X?}");
        u16::from_be_bytes([got[9], got[10]])
    }
}

fn site(address: &str, extra: &str) -> Site {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let args = ["--port", socat.dev.to_str().unwrap(), "--framer", "rtu"];
    let device = Py::start("stock_server.py", &args);
    let text = format!(
        "[[line]]\nunits = [1]\n\
         serial = {{ path = {:?}, framing = \"rtu\", flow_control = \"none\", baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000 }}\n\
         [[listen]]\naddress = {address:?}\ntransport = \"udp\"\n{extra}\n\
         [log]\nlevel = \"debug\"\n[metrics]\nlisten = \"127.0.0.1:0\"\n",
        socat.gw.to_str().unwrap()
    );
    let gw = Gateway::launch_text(&text, dir.path(), Launch::default());
    Site {
        _dir: dir,
        _socat: socat,
        _device: device,
        gw,
    }
}

/// What the gateways do, summed: requests on their lines, answers dropped, requests
/// answered for their limits, exceptions held back.
fn activity(sites: &[&Site]) -> u64 {
    let names = [
        "mbgate_line_requests",
        "mbgate_listener_not_requests",
        "mbgate_listener_bad_requests",
        "mbgate_listener_limited_exceptions",
    ];
    sites
        .iter()
        .map(|s| names.iter().map(|n| s.metric(n)).sum::<u64>())
        .sum()
}

/// Waits until the gateways have done nothing for a second; fails when they still do
/// after 10 s: a loop that does not end. (A loop goes round in milliseconds: a second
/// without a datagram is a loop ended, whatever the machine's load.)
fn settled(sites: &[&Site]) {
    let start = Instant::now();
    let mut before = activity(sites);
    loop {
        std::thread::sleep(Duration::from_secs(1));
        let now = activity(sites);
        if now == before {
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "still going after 10 s ({before} then {now}): a loop"
        );
        before = now;
    }
}

fn count(log: &str, needle: &str) -> usize {
    log.lines().filter(|l| l.contains(needle)).count()
}

const ANSWER_SAID: &str = "came where a request belongs";
const REFLECTED_SAID: &str = "sent back the very reply";

/// A read, a read of a unit no line serves, a write and a malformed request, each
/// forged from the listener's own address: each is answered once, to the listener
/// itself, which drops the answer (a reply's shape, an exception, its own write's
/// reply come back at once, an exception); the write was done once. Each kind is
/// said once.
#[test]
fn a_datagram_forged_from_the_listeners_own_address_is_answered_once() {
    let Some(forger) = Forger::open() else {
        return;
    };
    let mut a = site("127.0.0.1:0", "");
    let own = a.udp();
    for (n, datagram) in [
        read_req(1, 1, 10, 1),
        read_req(2, 9, 10, 1),
        write06(3, 1, 60, 4321),
        mbap(4, 1, &[3, 0]),
    ]
    .iter()
    .enumerate()
    {
        forger.send(own, own, datagram);
        settled(&[&a]);
        a.wait_metric("mbgate_listener_not_requests", n as u64 + 1);
    }
    assert_eq!(a.register(60), 4321);
    let log = a.gw.log();
    assert_eq!(
        count(&log, ANSWER_SAID),
        2,
        "a reply's shape, an exception:\n{log}"
    );
    assert_eq!(count(&log, REFLECTED_SAID), 1, "{log}");
    let c = a.gw.stop();
    let got = (
        c["requests"],
        c["not_requests"],
        c["unavailable"],
        c["bad_requests"],
    );
    assert_eq!(got, (3, 4, 1, 1), "{c:?}");
}

/// Datagrams forged from gateway B's listener to gateway A's: A answers each once, to
/// B. B drops a read's reply and the exceptions; a write's reply it takes for the
/// write it repeats, writes its own device and answers A, which knows its own reply
/// come back and drops it. One datagram from each, then nothing: both devices written
/// once.
#[test]
fn loops_between_two_gateways_end_within_a_datagram_each() {
    let Some(forger) = Forger::open() else {
        return;
    };
    let (a, b) = (site("127.0.0.1:0", ""), site("127.0.0.1:0", ""));
    let not = "mbgate_listener_not_requests";
    forger.send(b.udp(), a.udp(), &read_req(1, 1, 10, 1));
    settled(&[&a, &b]);
    b.wait_metric(not, 1);
    forger.send(b.udp(), a.udp(), &write06(2, 1, 60, 1111));
    settled(&[&a, &b]);
    a.wait_metric(not, 1);
    forger.send(b.udp(), a.udp(), &read_req(3, 9, 10, 1));
    settled(&[&a, &b]);
    b.wait_metric(not, 2);
    forger.send(b.udp(), a.udp(), &mbap(4, 1, &[3, 0]));
    settled(&[&a, &b]);
    b.wait_metric(not, 3);
    assert_eq!((a.register(60), b.register(60)), (1111, 1111));
    let (mut a, mut b) = (a, b);
    let (ca, cb) = (a.gw.stop(), b.gw.stop());
    let at = |c: &std::collections::HashMap<String, u64>| {
        let keys = ["requests", "not_requests", "unavailable", "bad_requests"];
        keys.map(|k| c[k])
    };
    // A: the read, the write and the check; B: the write and the check.
    assert_eq!(at(&ca), [3, 1, 1, 1], "A: {ca:?}");
    assert_eq!(at(&cb), [2, 3, 0, 0], "B: {cb:?}");
}

/// tests/py/udp_server.py: pymodbus' ModbusUdpServer, its datagrams counted.
struct PyUdpServer {
    child: Child,
    stdin: ChildStdin,
    out: BufReader<ChildStdout>,
    addr: SocketAddr,
}

impl PyUdpServer {
    fn start() -> PyUdpServer {
        let port = free_udp_port();
        let mut child = Command::new(python())
            .arg(repo().join("tests/py/udp_server.py"))
            .args(["--port", &port.to_string()])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let stdin = child.stdin.take().unwrap();
        let mut out = BufReader::new(child.stdout.take().unwrap());
        let mut ready = String::new();
        out.read_line(&mut ready).unwrap();
        assert_eq!(ready.trim(), "READY");
        let addr = SocketAddr::from(([127, 0, 0, 1], port));
        PyUdpServer {
            child,
            stdin,
            out,
            addr,
        }
    }

    /// Datagrams it received and sent so far.
    fn count(&mut self) -> (u64, u64) {
        writeln!(self.stdin, "count").unwrap();
        let mut line = String::new();
        self.out.read_line(&mut line).unwrap();
        let w: Vec<u64> = line
            .split_whitespace()
            .filter_map(|w| w.parse().ok())
            .collect();
        assert_eq!(w.len(), 4, "{line:?}");
        (w[0], w[2])
    }
}

impl Drop for PyUdpServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The same with pymodbus' ModbusUdpServer as the other end, which answers every
/// datagram it decodes, answers too (a reply with `80 01`, an exception with exception
/// 04), and writes its own register for a write's reply: mbgate drops each of its
/// answers, and what either sends the other ends there. Forged the other way (from
/// mbgate's listener to pymodbus), pymodbus' answers are dropped too; a datagram it
/// cannot decode it does not answer.
#[test]
fn loops_with_pymodbus_udp_server_end_within_a_datagram_each() {
    let Some(forger) = Forger::open() else {
        return;
    };
    let a = site("127.0.0.1:0", "");
    let mut p = PyUdpServer::start();
    let not = "mbgate_listener_not_requests";
    for (n, datagram) in [
        read_req(1, 1, 10, 1),
        write06(2, 1, 60, 2222),
        read_req(3, 9, 10, 1),
        mbap(4, 1, &[3, 0]),
    ]
    .iter()
    .enumerate()
    {
        forger.send(p.addr, a.udp(), datagram);
        settled(&[&a]);
        a.wait_metric(not, n as u64 + 1);
    }
    forger.send(a.udp(), p.addr, &read_req(5, 1, 10, 1));
    settled(&[&a]);
    a.wait_metric(not, 5);
    forger.send(a.udp(), p.addr, &mbap(6, 1, &[0x83, 0x02]));
    settled(&[&a]);
    a.wait_metric(not, 6);
    // pymodbus' device took the write, once.
    let got = udp_transact(&p.addr.to_string(), &read_req(8, 1, 60, 1)).unwrap();
    assert_eq!(got, read_reply(8, 1, &[2222]));
    // Bytes it cannot decode: no answer.
    forger.send(a.udp(), p.addr, b"hello");
    std::thread::sleep(Duration::from_millis(500));
    settled(&[&a]);
    // In: mbgate's 4 answers, 3 forged datagrams and the check; out: its 6 answers
    // (every one dropped by mbgate) and the check's.
    assert_eq!(p.count(), (4 + 3 + 1, 6 + 1));
    let mut a = a;
    let c = a.gw.stop();
    let got = (
        c["requests"],
        c["not_requests"],
        c["unavailable"],
        c["bad_requests"],
    );
    // The read and the write forged from pymodbus' address.
    assert_eq!(got, (2, 6, 1, 1), "{c:?}");
}

/// What a source whose address is forged is sent back, per datagram: nothing for an
/// answer (a reply, an exception), at most one exception in its budget for a request
/// the gateway refuses at once, one reply a read (of 11 bytes for a 12-byte read of a
/// register; of 259 bytes for a read of 125: the read amplification Modbus/UDP has,
/// which only a network that drops spoofed sources can stop). Counted at the victim,
/// a socket bound at the forged address.
#[test]
fn a_forged_source_is_sent_nothing_for_answers_and_a_budget_of_exceptions() {
    let Some(forger) = Forger::open() else {
        return;
    };
    let a = site("127.0.0.1:0", "");
    let victim = UdpSocket::bind("127.0.0.7:0").unwrap();
    victim
        .set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let from = victim.local_addr().unwrap();
    // Whatever the victim got: datagrams and bytes, once nothing came for 1 s.
    let drain = || {
        let (mut n, mut bytes, mut quiet) = (0u64, 0u64, Instant::now());
        let mut buf = [0u8; 600];
        while quiet.elapsed() < Duration::from_secs(1) {
            if let Ok(k) = victim.recv(&mut buf) {
                n += 1;
                bytes += k as u64;
                quiet = Instant::now();
            }
        }
        (n, bytes)
    };
    let mut table = Vec::new();
    // 100 answers: replies and exceptions.
    let mut sent = 0;
    for i in 0..50u16 {
        for d in [mbap(i, 1, &[3, 2, 0, i as u8]), mbap(i, 1, &[0x83, 0x02])] {
            forger.send(from, a.udp(), &d);
            sent += d.len() as u64;
        }
    }
    let got = drain();
    table.push(("answers", 100, sent, got));
    assert_eq!(got, (0, 0), "answers are never answered");
    a.wait_metric("mbgate_listener_not_requests", 100);
    // 100 requests for a unit no line serves, at once: each refused 0x0A, but only
    // the source's budget of exceptions sent.
    let start = Instant::now();
    for i in 0..100u16 {
        forger.send(from, a.udp(), &read_req(i, 9, 0, 1));
    }
    let got = drain();
    let took = start.elapsed();
    table.push(("unit 9", 100, 1200, got));
    // 10 at once, one more each 100 ms since (and one for the rounding).
    let budget = 10 + took.as_millis() as u64 / 100 + 1;
    assert!(got.0 >= 10 && got.0 <= budget, "{got:?} in {took:?}");
    assert_eq!(got.1, got.0 * 9);
    // Reads, one at a time: one reply each.
    for (qty, reply) in [(1u16, 11u64), (125, 259)] {
        let mut got = (0, 0);
        for i in 0..20u16 {
            forger.send(from, a.udp(), &read_req(i, 1, 10, qty));
            let mut buf = [0u8; 600];
            let n = victim.recv(&mut buf).expect("a reply") as u64;
            assert_eq!(n, reply);
            got = (got.0 + 1, got.1 + n);
        }
        assert_eq!(drain(), (0, 0), "nothing more");
        table.push((if qty == 1 { "read 1" } else { "read 125" }, 20, 240, got));
    }
    for (what, n, bytes_in, (out, bytes_out)) in &table {
        eprintln!(
            "forged {what}: {n} datagrams, {bytes_in} bytes in; {out} datagrams, {bytes_out} bytes out ({:.2} a byte)",
            *bytes_out as f64 / *bytes_in as f64
        );
    }
    let mut a = a;
    let c = a.gw.stop();
    let unit9 = table[1].3 .0;
    assert_eq!(
        c["exceptions_limited"] + c["datagrams_dropped"] + unit9,
        100,
        "{c:?}"
    );
}

/// 2 000 forged sources, each one datagram (the table of 8 full 250 times over):
/// pymodbus' UDP client is then served as a new master, and a client that opens a
/// new socket for each of 100 requests is answered each time; no new source was ever
/// refused. With `idle_timeout_ms = 0` (sources never forgotten for being quiet) too.
#[test]
fn forged_and_one_shot_sources_never_keep_a_new_master_out() {
    let Some(forger) = Forger::open() else {
        return;
    };
    for idle in [60_000, 0] {
        let extra = format!("max_connections = 8\nidle_timeout_ms = {idle}\n");
        let mut a = site("127.0.0.1:0", &extra);
        // In bursts of 100, each taken before the next (a socket's receive buffer
        // holds a few hundred datagrams: more at once would be the kernel's drops).
        for i in 0..2000u16 {
            let from = SocketAddr::from(([127, 0, 1 + (i / 200) as u8, 1 + (i % 200) as u8], 4000));
            forger.send(from, a.udp(), &read_req(i, 9, 0, 1));
            if i % 100 == 99 {
                a.wait_metric("mbgate_listener_connections", u64::from(i) + 1);
            }
        }
        let port = a.udp().port().to_string();
        let (status, out) = Py::run("udp_master.py", &["--port", &port]);
        assert!(status.success(), "{out}\n{}", a.gw.log());
        assert!(out.contains("sync ok") && out.contains("async ok"), "{out}");
        for tid in 0..100u16 {
            let got = udp_transact(&a.udp().to_string(), &read_req(tid, 1, 5, 1));
            assert_eq!(got.unwrap(), read_reply(tid, 1, &[1005]), "request {tid}");
        }
        let c = a.gw.stop();
        assert_eq!(
            c["connections_refused"], 0,
            "idle_timeout_ms = {idle}: {c:?}"
        );
        assert!(c["connections"] >= 2100, "{c:?}");
    }
}

/// With two sources at once, a third takes the place of the quieter, and the one that
/// keeps talking keeps its own (it is not made anew); the one forgotten is a new
/// source when it comes back, taking the place of the quietest then. Sources quiet for
/// `idle_timeout_ms` are forgotten, and not sooner.
#[test]
fn a_new_source_takes_the_quietest_place_and_a_quiet_one_is_forgotten_in_time() {
    let a = site(
        "127.0.0.1:0",
        "max_connections = 2\nidle_timeout_ms = 3000\n",
    );
    let socket = || {
        let s = UdpSocket::bind("127.0.0.1:0").unwrap();
        s.connect(a.udp()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        s
    };
    let ask = |s: &UdpSocket, tid: u16| {
        s.send(&read_req(tid, 1, 5, 1)).unwrap();
        let mut buf = [0u8; 300];
        let n = s.recv(&mut buf).expect("answered");
        assert_eq!(&buf[..n], read_reply(tid, 1, &[1005]));
    };
    let (talker, quiet, third) = (socket(), socket(), socket());
    ask(&talker, 1);
    ask(&quiet, 2);
    ask(&talker, 3);
    ask(&third, 4);
    assert_eq!(a.metric("mbgate_listener_connections"), 3);
    ask(&talker, 5);
    assert_eq!(
        a.metric("mbgate_listener_connections"),
        3,
        "the talker kept"
    );
    // No later than the quiet one is heard for the last time.
    let heard = Instant::now();
    ask(&quiet, 6);
    assert_eq!(a.metric("mbgate_listener_connections"), 4);
    wait_for("the two known", Duration::from_secs(10), || {
        a.metric("mbgate_listener_masters") == 2
    });
    std::thread::sleep(Duration::from_secs(1).saturating_sub(heard.elapsed()));
    if heard.elapsed() < Duration::from_millis(2500) {
        assert_eq!(a.metric("mbgate_listener_masters"), 2, "forgotten too soon");
    }
    wait_for("both forgotten", Duration::from_secs(10), || {
        a.metric("mbgate_listener_masters") == 0
    });
    assert!(heard.elapsed() >= Duration::from_secs(3));
    let mut a = a;
    let c = a.gw.stop();
    assert_eq!(
        (c["connections_refused"], c["datagrams_dropped"]),
        (0, 0),
        "{c:?}"
    );
}

/// A reload that changes a UDP listener, then one that removes it, each while a source
/// has four requests in the gateway (one on the line, three queued behind a device
/// that answers in 300 ms): every one is answered, by value, before the source is
/// forgotten.
#[test]
fn a_reload_that_changes_or_removes_a_udp_listener_answers_what_its_sources_queued() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = RawDevice::start(
        &socat.dev,
        register_device(&[1], Duration::from_millis(300)),
    );
    let at = format!("127.0.0.1:{}", free_udp_port());
    let base = format!(
        "[[line]]\nserial = {{ path = {:?}, baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000, max_in_flight = 1 }}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n[log]\nlevel = \"debug\"\n",
        socat.gw.to_str().unwrap()
    );
    let udp = |extra: &str| format!("[[listen]]\naddress = {at:?}\ntransport = \"udp\"\n{extra}");
    let file = dir.path().join("mbgate.toml");
    let mut gw = Gateway::launch_text(&format!("{base}{}", udp("")), dir.path(), Launch::default());
    let s = UdpSocket::bind("127.0.0.1:0").unwrap();
    s.connect(&at).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    for (round, then, said) in [
        (
            0u16,
            format!("{base}{}", udp("max_connections = 9\n")),
            "changed (started again)",
        ),
        (1, base.clone(), "(gone from the file)"),
    ] {
        let tids: Vec<u16> = (1 + 4 * round..5 + 4 * round).collect();
        let before = dev.requests().len();
        for &tid in &tids {
            s.send(&read_req(tid, 1, 10 + tid, 1)).unwrap();
        }
        wait_for("the first on the line", Duration::from_secs(10), || {
            dev.requests().len() > before
        });
        std::fs::write(&file, then).unwrap();
        gw.proc.signal("HUP");
        gw.wait_log(
            &format!("listen \"{at} (UDP)\" {said}"),
            Duration::from_secs(10),
        );
        let mut got = Vec::new();
        let mut buf = [0u8; 300];
        for _ in &tids {
            let n = s.recv(&mut buf).unwrap_or_else(|e| {
                panic!(
                    "round {round}: {} of 4 answered ({e}):\n{}",
                    got.len(),
                    gw.log()
                )
            });
            got.push(buf[..n].to_vec());
        }
        let want: Vec<Vec<u8>> = tids.iter().map(|&t| read_reply(t, 1, &[10 + t])).collect();
        assert_eq!(got, want, "round {round}");
    }
}

/// `notifications = "broadcast"` on the line: a TCP master gets every notification;
/// a UDP source of a listener without `notifications = true` gets none; one of a
/// listener with it gets those that come within 1 s of its last request, and no
/// other. A source forged once earns at most that second's worth.
#[test]
fn udp_sources_get_notifications_only_when_asked_and_only_after_a_request() {
    let Some(forger) = Forger::open() else {
        return;
    };
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let mut dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let (u1, u2) = (free_udp_port(), free_udp_port());
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000, notifications = \"broadcast\" }}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n\
         [[listen]]\naddress = \"127.0.0.1:{u1}\"\ntransport = \"udp\"\n\
         [[listen]]\naddress = \"127.0.0.1:{u2}\"\ntransport = \"udp\"\nnotifications = true\n\
         [log]\nlevel = \"debug\"\n",
        socat.gw.to_str().unwrap()
    );
    let (_gw, addrs) = gateway_from_file(dir.path(), &text, 3);
    let tcp = addrs
        .iter()
        .find(|a| ![u1, u2].contains(&a.port()))
        .unwrap();
    let mut m = std::net::TcpStream::connect(tcp).unwrap();
    m.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let source = |port: u16| {
        let s = UdpSocket::bind("127.0.0.1:0").unwrap();
        s.connect(("127.0.0.1", port)).unwrap();
        s
    };
    let (quiet, asking) = (source(u1), source(u2));
    // The next datagram within `within`, if any.
    let next = |s: &UdpSocket, within: Duration| -> Option<Vec<u8>> {
        s.set_read_timeout(Some(within)).unwrap();
        let mut buf = [0u8; 300];
        s.recv(&mut buf).ok().map(|n| buf[..n].to_vec())
    };
    let ask = |s: &UdpSocket, tid: u16| {
        s.send(&read_req(tid, 1, 5, 1)).unwrap();
        assert_eq!(
            next(s, Duration::from_secs(10)),
            Some(read_reply(tid, 1, &[5]))
        );
    };
    let note = |n: u8| hex(&format!("00 00 00 00 00 05 01 03 02 00 {n:02X}"));
    assert_eq!(
        transact(&mut m, &read_req(1, 1, 5, 1)),
        read_reply(1, 1, &[5])
    );
    ask(&quiet, 2);
    ask(&asking, 3);
    dev.inject(&note(1));
    assert_eq!(read_frame(&mut m), note(1));
    assert_eq!(next(&asking, Duration::from_secs(5)), Some(note(1)));
    assert_eq!(
        next(&quiet, Duration::from_millis(500)),
        None,
        "not asked for"
    );
    // Quiet for 1.5 s: the next one goes to the TCP master alone.
    std::thread::sleep(Duration::from_millis(1500));
    dev.inject(&note(2));
    assert_eq!(read_frame(&mut m), note(2));
    assert_eq!(
        next(&asking, Duration::from_millis(500)),
        None,
        "too long since it asked"
    );
    ask(&asking, 4);
    dev.inject(&note(3));
    assert_eq!(read_frame(&mut m), note(3));
    assert_eq!(next(&asking, Duration::from_secs(5)), Some(note(3)));
    assert_eq!(next(&quiet, Duration::from_millis(200)), None);
    // One forged read: its reply and the notifications of the next second, no more.
    let victim = UdpSocket::bind("127.0.0.9:0").unwrap();
    let to = SocketAddr::from(([127, 0, 0, 1], u2));
    forger.send(victim.local_addr().unwrap(), to, &read_req(5, 1, 5, 1));
    assert_eq!(
        next(&victim, Duration::from_secs(5)),
        Some(read_reply(5, 1, &[5]))
    );
    dev.inject(&note(4));
    assert_eq!(read_frame(&mut m), note(4));
    assert_eq!(next(&victim, Duration::from_secs(5)), Some(note(4)));
    std::thread::sleep(Duration::from_millis(1500));
    for n in 5..10 {
        dev.inject(&note(n));
        assert_eq!(read_frame(&mut m), note(n));
    }
    assert_eq!(next(&victim, Duration::from_millis(500)), None);
}
