//! A line whose device is the master (docs/design.md §4.2): serial masters (the
//! simulated CIE-M10 master, pymodbus' RTU client, a scripted raw master) on a socat
//! pty, mbgate in the middle, Modbus/TCP slaves (pymodbus' ModbusTcpServer, or a
//! recording slave written here) on real sockets.

use crate::common;

use common::sim::RawLine;
use common::{free_port, hexs, python, tempdir, wait_for, Proc, Py, Registers, Socat};
use mbgate::frame::mbap::decode_strict;
use mbgate::frame::{rtu, Adu};
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// The master line's configuration: the pty, its framing, and `[[line.route]]`
/// tables given as (`units = [...]` or "" for the default route, port, extra lines).
fn config(dir: &Path, gw: &Path, framing: &str, routes: &[(&str, u16, &str)]) -> String {
    let mut s = format!(
        "[[line]]\nrole = \"master\"\n\
         serial = {{ path = {:?}, framing = \"{framing}\", baud_rate = 4000000, \
         silence_floor_ms = 0, flow_control = \"none\" }}\n",
        gw.display().to_string()
    );
    for (units, port, extra) in routes {
        s += &format!("\n[[line.route]]\n{units}\naddress = \"127.0.0.1:{port}\"\n{extra}\n");
    }
    s += "\n[log]\nlevel = \"debug\"\ntraffic = true\n";
    let file = dir.join("mbgate.toml");
    std::fs::write(&file, &s).unwrap();
    file.to_str().unwrap().to_owned()
}

/// `mbgate run` on a master line, started once its line is up.
fn gateway(file: &str) -> Proc {
    Proc::start(&["run", "--config", file], "serial port open")
}

/// A master line in `framing` on a pty pair, its default route to one answering slave,
/// connected: the folder, the pty pair, the slave and the gateway.
fn one_slave(framing: &str) -> (tempfile::TempDir, Socat, Slave, Proc) {
    one_slave_doing(framing, Behaviour::Answer)
}

/// [`one_slave`] with a slave that does `behaviour`.
fn one_slave_doing(framing: &str, behaviour: Behaviour) -> (tempfile::TempDir, Socat, Slave, Proc) {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let slave = Slave::start(behaviour);
    let file = config(dir.path(), &socat.gw, framing, &[("", slave.port, "")]);
    let gw = gateway(&file);
    gw.wait_log("connected to the slave", Duration::from_secs(5));
    (dir, socat, slave, gw)
}

/// A pymodbus Modbus/TCP slave on `port`.
fn pymodbus_slave(port: u16, unit: u8, base: u16) -> Py {
    let _ = python();
    Py::start(
        "tcp_slave.py",
        &[
            "--port",
            &port.to_string(),
            "--unit",
            &unit.to_string(),
            "--base",
            &base.to_string(),
        ],
    )
}

/// One request to a Modbus/TCP server, directly (to look at or set a slave's
/// registers behind mbgate's back).
fn direct(port: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    s.write_all(Adu::build(0x4242, unit, pdu).as_bytes())
        .unwrap();
    common::read_frame(&mut s)[7..].to_vec()
}

/// What a recording slave does with each request.
#[derive(Clone, Copy, PartialEq)]
enum Behaviour {
    /// Answers as a register map (FC 03, 06, 16).
    Answer,
    /// The same, with this unit id in every reply (a server that ignores the unit).
    AnswerAs(u8),
    /// The same, this many milliseconds late.
    AnswerAfter(u64),
    /// Reads the request and closes the connection.
    Hang,
    /// Reads and never answers.
    Silent,
    /// Writes every request back as it came (a peer that mirrors what it gets).
    Mirror,
}

/// A Modbus/TCP slave written here: one connection at a time, every request recorded.
struct Slave {
    port: u16,
    seen: Arc<Mutex<Vec<Adu>>>,
    stop: Arc<AtomicBool>,
}

impl Slave {
    fn start(behaviour: Behaviour) -> Slave {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        listener.set_nonblocking(true).unwrap();
        let port = listener.local_addr().unwrap().port();
        let seen = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        let (seen2, stop2) = (seen.clone(), stop.clone());
        thread::spawn(move || {
            let mut regs = Registers::default();
            while !stop2.load(Ordering::Relaxed) {
                let Ok((mut s, _)) = listener.accept() else {
                    thread::sleep(Duration::from_millis(2));
                    continue;
                };
                s.set_nonblocking(false).unwrap();
                s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
                let mut buf = bytes::BytesMut::new();
                let mut chunk = [0u8; 512];
                'conn: while !stop2.load(Ordering::Relaxed) {
                    match s.read(&mut chunk) {
                        Ok(0) => break,
                        Ok(n) => buf.extend_from_slice(&chunk[..n]),
                        Err(_) => continue,
                    }
                    while let Ok(Some(req)) = decode_strict(&mut buf) {
                        seen2.lock().unwrap().push(req.clone());
                        match behaviour {
                            Behaviour::Answer
                            | Behaviour::AnswerAs(_)
                            | Behaviour::AnswerAfter(_) => {
                                let pdu = regs.answer(req.unit(), req.pdu(), true);
                                let unit = match behaviour {
                                    Behaviour::AnswerAs(unit) => unit,
                                    _ => req.unit(),
                                };
                                if let Behaviour::AnswerAfter(ms) = behaviour {
                                    thread::sleep(Duration::from_millis(ms));
                                }
                                let reply = Adu::build(req.tid(), unit, &pdu);
                                if s.write_all(reply.as_bytes()).is_err() {
                                    break 'conn;
                                }
                            }
                            Behaviour::Hang => break 'conn,
                            Behaviour::Silent => {}
                            Behaviour::Mirror => {
                                if s.write_all(req.as_bytes()).is_err() {
                                    break 'conn;
                                }
                            }
                        }
                    }
                }
            }
        });
        Slave { port, seen, stop }
    }

    fn requests(&self) -> Vec<Adu> {
        self.seen.lock().unwrap().clone()
    }
}

impl Drop for Slave {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// The frames the simulated master's log shows it sent (`tx HEX (request)`) or
/// received (`rx HEX (reply)`), in order.
fn logged(log: &str, what: &str) -> Vec<String> {
    log.lines()
        .filter_map(|l| {
            let rest = l.split(&format!("{what} ")).nth(1)?;
            Some(rest.split(" (").next()?.to_owned())
        })
        .collect()
}

/// The simulated CIE-M10 master (docs/protocol.md §3) on a pty, through mbgate, to
/// pymodbus' ModbusTcpServer: the slave's output register follows the master's inputs,
/// the master's outputs follow the slave's input register, and the bytes on the serial
/// line are the manual's frames, ids counting from 0000.
#[test]
fn cie_m10_master_mirrors_a_pymodbus_slave() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let port = free_port();
    let _slave = pymodbus_slave(port, 1, 0);
    let file = config(dir.path(), &socat.gw, "mbap", &[("", port, "")]);
    let gw = gateway(&file);
    gw.wait_log("connected to the slave", Duration::from_secs(5));
    let dev = socat.dev.to_str().unwrap();
    let master = Proc::start(
        &[
            "sim",
            "--serial",
            dev,
            "--role",
            "master",
            "--poll-ms",
            "100",
            "--toggle-ms",
            "250",
            "--headless",
            "--flow-control",
            "none",
        ],
        "a CIE-M10 master on",
    );
    wait_for("the first two exchanges", Duration::from_secs(5), || {
        logged(&master.log(), "rx").len() >= 2
    });
    // Inputs 0 and outputs 0 at first: the manual's frames with ids 0000 and 0001.
    let sent = logged(&master.log(), "tx");
    let got = logged(&master.log(), "rx");
    assert_eq!(sent[0], "00 00 00 00 00 06 01 03 00 00 00 01");
    assert_eq!(got[0], "00 00 00 00 00 05 01 03 02 00 00");
    assert_eq!(sent[1], "00 01 00 00 00 09 01 10 00 08 00 01 02 00 00");
    assert_eq!(got[1], "00 01 00 00 00 06 01 10 00 08 00 01");
    // What mbgate read and wrote on its end of the line is the same.
    let log = gw.log();
    assert!(
        log.contains("serial rx 00 00 00 00 00 06 01 03 00 00 00 01"),
        "{log}"
    );
    assert!(
        log.contains("serial tx 00 00 00 00 00 05 01 03 02 00 00"),
        "{log}"
    );
    assert!(
        log.contains("serial tx 00 01 00 00 00 06 01 10 00 08 00 01"),
        "{log}"
    );

    // The slave's inputs change: the master's outputs follow.
    assert_eq!(direct(port, 1, &[6, 0, 0, 0, 0x5A]), [6, 0, 0, 0, 0x5A]);
    wait_for("the master's outputs", Duration::from_secs(5), || {
        master.stdout.lock().unwrap().contains("outputs 01011010")
    });
    // The master's inputs count up: the slave's output register follows them.
    let outputs = || direct(port, 1, &[3, 0, 8, 0, 1])[3];
    let mut values = std::collections::BTreeSet::new();
    wait_for(
        "the slave's outputs to change twice",
        Duration::from_secs(5),
        || {
            values.insert(outputs());
            values.len() >= 3
        },
    );
    // Each value the slave holds was sent by the master: its log line may come a
    // moment after the write it tells of, so the log is read until it says so.
    let all_sent = |sent: &[String]| {
        values
            .iter()
            .all(|v| sent.iter().any(|f| f.ends_with(&format!("02 00 {v:02X}"))))
    };
    wait_for(
        "the master's log of what it sent",
        Duration::from_secs(5),
        || all_sent(&logged(&master.log(), "tx")),
    );
    let sent = logged(&master.log(), "tx");
    for (i, f) in sent.iter().enumerate() {
        let tid = hexs(&(i as u16).to_be_bytes());
        assert!(
            f.starts_with(&tid),
            "ids count up from 0000: {f} is query {i}"
        );
    }
    let replies = logged(&master.log(), "rx");
    assert!(
        replies.iter().any(|f| f.ends_with("01 03 02 00 5A")),
        "the read replies carry the slave's inputs: {replies:?}"
    );
}

/// pymodbus' RTU client as the serial master, two pymodbus slaves by unit id: every
/// function code of docs/protocol.md §1 and an exception, and 0x0A for a unit with no
/// route.
#[test]
fn rtu_master_reaches_two_slaves_by_unit() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let (p1, p2) = (free_port(), free_port());
    let _s1 = pymodbus_slave(p1, 1, 0);
    let _s2 = pymodbus_slave(p2, 2, 1000);
    let file = config(
        dir.path(),
        &socat.gw,
        "rtu",
        &[("units = [1]", p1, ""), ("units = [2]", p2, "")],
    );
    let gw = gateway(&file);
    gw.wait_log(
        "connected to the slave at 127.0.0.1:",
        Duration::from_secs(5),
    );
    let steps = r#"[
        ["read_coils", [0], {"count": 5, "device_id": 1}],
        ["read_discrete_inputs", [0], {"count": 4, "device_id": 2}],
        ["read_holding_registers", [16], {"count": 2, "device_id": 1}],
        ["read_holding_registers", [16], {"count": 2, "device_id": 2}],
        ["read_input_registers", [1], {"count": 2, "device_id": 2}],
        ["write_coil", [1, true], {"device_id": 1}],
        ["write_register", [3, 77], {"device_id": 2}],
        ["write_coils", [8, [true, false, true]], {"device_id": 2}],
        ["write_registers", [20, [5, 6, 7]], {"device_id": 1}],
        ["readwrite_registers", [], {"read_address": 20, "read_count": 3, "write_address": 4, "values": [9], "device_id": 1}],
        ["read_holding_registers", [300], {"count": 1, "device_id": 1}],
        ["read_holding_registers", [0], {"count": 1, "device_id": 3}]
    ]"#;
    let gw_dev = socat.dev.to_str().unwrap();
    let (status, out) = Py::run(
        "rtu_master.py",
        &["--port", gw_dev, "--baud", "115200", steps],
    );
    assert!(status.success(), "{out}");
    let got: serde_json::Value = serde_json::from_str(&out).unwrap();
    let want = serde_json::json!([
        {"bits": [true, false, false, true, false, false, false, false]},
        {"bits": [true, false, true, false, false, false, false, false]},
        {"registers": [16, 17]},
        {"registers": [1016, 1017]},
        {"registers": [1501, 1502]},
        {"bits": [true], "address": 1},
        {"registers": [77], "address": 3},
        {"address": 8, "count": 3},
        {"address": 20, "count": 3},
        {"registers": [5, 6, 7]},
        {"exception": 2},
        {"exception": 10}
    ]);
    // pymodbus reports a single write with a count of its own; compare the rest.
    let (got, want) = (got.as_array().unwrap(), want.as_array().unwrap());
    assert_eq!(got.len(), want.len(), "{got:?}");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        for (k, v) in w.as_object().unwrap() {
            assert_eq!(g.get(k), Some(v), "step {i}: {g} vs {w}");
        }
    }
    // The writes reached the right slave, and only it.
    assert_eq!(direct(p1, 1, &[1, 0, 1, 0, 1]), [1, 1, 1]);
    assert_eq!(direct(p2, 2, &[3, 0, 3, 0, 2]), [3, 4, 0, 77, 0, 0]);
    assert_eq!(direct(p2, 2, &[1, 0, 8, 0, 3]), [1, 1, 0b101]);
    assert_eq!(direct(p1, 1, &[3, 0, 4, 0, 1]), [3, 2, 0, 9]);
    assert_eq!(
        direct(p1, 1, &[3, 0, 3, 0, 1]),
        [3, 2, 0, 0],
        "unit 2's write stayed there"
    );
}

/// An RTU request from a raw master, and its reply (empty if none within `within`).
fn ask(
    line: &mut RawLine,
    unit: u8,
    pdu: &[u8],
    reply_pdu_len: usize,
    within: Duration,
) -> Vec<u8> {
    line.send(&rtu::encode(unit, pdu));
    line.recv(1 + reply_pdu_len + 2, within)
}

/// The slave stops: 0x0A; a request already sent when its connection goes: 0x0B; a
/// slave that never answers: 0x0B; the slave back: served again by the same mbgate.
#[test]
fn slave_lost_and_back() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let port = free_port();
    let hang = Slave::start(Behaviour::Hang);
    let silent = Slave::start(Behaviour::Silent);
    let timeout = "response_timeout_ms = 300";
    let file = config(
        dir.path(),
        &socat.gw,
        "rtu",
        &[
            ("units = [1]", port, timeout),
            ("units = [2]", hang.port, timeout),
            ("units = [3]", silent.port, timeout),
        ],
    );
    let slave = pymodbus_slave(port, 1, 0);
    let gw = gateway(&file);
    let pid = gw.pid();
    gw.wait_log(
        "connected to the slave at 127.0.0.1:",
        Duration::from_secs(5),
    );
    thread::sleep(Duration::from_millis(300));
    let mut line = RawLine::open(&socat.dev);
    let read = [3, 0, 16, 0, 1];
    let second = Duration::from_secs(1);
    assert_eq!(
        ask(&mut line, 1, &read, 4, second),
        rtu::encode(1, &[3, 2, 0, 16])
    );

    let started = Instant::now();
    assert_eq!(
        ask(&mut line, 2, &read, 2, second),
        rtu::encode(2, &[0x83, 0x0B])
    );
    assert!(
        started.elapsed() < Duration::from_millis(250),
        "at once when the connection goes"
    );
    assert_eq!(hang.requests().len(), 1);
    let started = Instant::now();
    assert_eq!(
        ask(&mut line, 3, &read, 2, second),
        rtu::encode(3, &[0x83, 0x0B])
    );
    assert!(started.elapsed() >= Duration::from_millis(290));

    drop(slave);
    gw.wait_log("slave connection lost", Duration::from_secs(5));
    assert_eq!(
        ask(&mut line, 1, &read, 2, second),
        rtu::encode(1, &[0x83, 0x0A])
    );

    let _slave = pymodbus_slave(port, 1, 0);
    let mut served = Vec::new();
    wait_for("served again", Duration::from_secs(10), || {
        served = ask(&mut line, 1, &read, 4, second);
        served == rtu::encode(1, &[3, 2, 0, 16])
            || (served == rtu::encode(1, &[0x83, 0x0A]) && {
                thread::sleep(Duration::from_millis(100));
                false
            })
    });
    assert_eq!(gw.pid(), pid);
}

/// The simulated master loses 1 % of the bytes it sends; the slave records every
/// request mbgate forwards: each is one the master sent, in the order it sent them
/// (docs/reliability.md). MBGATE_LONG=1: at least 2 000 requests.
#[test]
fn lossy_line_forwards_only_what_the_master_sent() {
    let long = std::env::var_os("MBGATE_LONG").is_some();
    let want = if long { 2_000 } else { 300 };
    let (_dir, socat, slave, _gw) = one_slave("mbap");
    let dev = socat.dev.to_str().unwrap();
    // A master timeout shorter than mbgate's frame gap (50 ms): a request that lost a
    // byte is still buffered when the next one comes, the hardest case.
    let mut master = Proc::start(
        &[
            "sim",
            "--serial",
            dev,
            "--role",
            "master",
            "--poll-ms",
            "1",
            "--timeout-ms",
            "20",
            "--toggle-ms",
            "3",
            "--drop",
            "0.01",
            "--faults",
            "from-device",
            "--seed",
            "14",
            "--headless",
            "--flow-control",
            "none",
        ],
        "a CIE-M10 master on",
    );
    wait_for(
        "the requests",
        Duration::from_secs(if long { 120 } else { 20 }),
        || logged(&master.log(), "tx").len() >= want,
    );
    master.terminate(Duration::from_secs(5));
    thread::sleep(Duration::from_millis(100));
    let sent: Vec<Vec<u8>> = logged(&master.log(), "tx")
        .iter()
        .map(|f| common::hex(f)[6..].to_vec())
        .collect();
    let forwarded: Vec<Vec<u8>> = slave
        .requests()
        .iter()
        .map(|f| f.as_bytes()[6..].to_vec())
        .collect();
    // Each forwarded request (unit and PDU) is the next one the master sent, or one of
    // the few after it (the master's inputs count up, so its writes differ: one that
    // is found only far ahead was made up).
    let mut at = 0;
    for (i, f) in forwarded.iter().enumerate() {
        let ahead = &sent[at..sent.len().min(at + 20)];
        let found = ahead.iter().position(|s| s == f);
        let Some(k) = found else {
            panic!(
                "forwarded request {i} {} was never sent (after sent {at})",
                hexs(f)
            );
        };
        at += k + 1;
    }
    let lost = sent.len() - forwarded.len();
    eprintln!(
        "{} sent, {} forwarded, {lost} not",
        sent.len(),
        forwarded.len()
    );
    assert!(sent.len() >= want);
    assert!(
        lost > 0,
        "the loss must cost some requests, or the test shows nothing"
    );
    assert!(
        forwarded.len() * 10 > sent.len() * 7,
        "most requests get through"
    );
}

/// A scripted master writes garbage, an RTU frame with a bad CRC, then a good one:
/// only the good one is forwarded and answered.
#[test]
fn rtu_garbage_and_bad_crc_are_not_forwarded() {
    let (_dir, socat, slave, _gw) = one_slave("rtu");
    let mut line = RawLine::open(&socat.dev);
    line.send(&[0xFF, 0x00, 0x13, 0x37]);
    thread::sleep(Duration::from_millis(20));
    let mut bad = rtu::encode(1, &[6, 0, 5, 0, 9]);
    bad[6] ^= 0x40;
    line.send(&bad);
    assert_eq!(
        line.recv(1, Duration::from_millis(300)),
        Vec::<u8>::new(),
        "no answer, as on a bus"
    );
    assert_eq!(
        ask(&mut line, 1, &[3, 0, 5, 0, 1], 4, Duration::from_secs(1)),
        rtu::encode(1, &[3, 2, 0, 5])
    );
    let seen: Vec<String> = slave.requests().iter().map(|f| hexs(f.pdu())).collect();
    assert_eq!(seen, ["03 00 05 00 01"]);
}

/// MBAP: garbage, a truncated frame followed at once by a good one, then another
/// good one after a pause. The truncated frame takes the good one's first byte, and
/// what follows refutes it: it is not forwarded, but the good one behind it is found
/// where it starts, inside it, and is (before, it was lost with it). Both good ones
/// are answered with the master's own transaction ids, in order.
#[test]
fn mbap_truncated_frame_then_a_good_one() {
    let (_dir, socat, slave, _gw) = one_slave("mbap");
    let mut line = RawLine::open(&socat.dev);
    let write = |tid: u16, v: u8| {
        Adu::build(tid, 1, &[0x10, 0, 8, 0, 1, 2, 0, v])
            .as_bytes()
            .to_vec()
    };
    let mut cut = write(0x0107, 0x11);
    cut.remove(13);
    let mut burst = vec![0x55, 0x00, 0x00];
    burst.extend_from_slice(&cut);
    burst.extend_from_slice(&write(0x0108, 0x22));
    line.send(&burst);
    let reply = line.recv(12, Duration::from_secs(1));
    assert_eq!(hexs(&reply), "01 08 00 00 00 06 01 10 00 08 00 01");
    line.send(&write(0x0109, 0x33));
    let reply = line.recv(12, Duration::from_secs(1));
    assert_eq!(hexs(&reply), "01 09 00 00 00 06 01 10 00 08 00 01");
    let seen: Vec<String> = slave.requests().iter().map(|f| hexs(f.pdu())).collect();
    assert_eq!(seen, ["10 00 08 00 01 02 00 22", "10 00 08 00 01 02 00 33"]);
}

/// A slave that connects to mbgate (the ezTCP's active setting facing mbgate's passive
/// route) and answers as a register map until `stop`.
fn connecting_slave(port: u16, stop: Arc<AtomicBool>) -> thread::JoinHandle<()> {
    thread::spawn(move || {
        let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
        s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
        let mut regs = Registers::default();
        let mut buf = bytes::BytesMut::new();
        let mut chunk = [0u8; 512];
        while !stop.load(Ordering::Relaxed) {
            match s.read(&mut chunk) {
                Ok(0) => return,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(_) => continue,
            }
            while let Ok(Some(req)) = decode_strict(&mut buf) {
                let pdu = regs.answer(req.unit(), req.pdu(), true);
                let reply = Adu::build(req.tid(), req.unit(), &pdu);
                s.write_all(reply.as_bytes()).unwrap();
            }
        }
    })
}

/// A passive route: 0x0A until the slave connects in, served once it has, and served
/// again when it connects anew.
#[test]
fn passive_route_serves_the_slave_that_connects_in() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let port = free_port();
    let mut text = std::fs::read_to_string(config(dir.path(), &socat.gw, "rtu", &[])).unwrap();
    text = text.replace(
        "\n[log]",
        &format!("\n[[line.route]]\nlisten = \"127.0.0.1:{port}\"\n\n[log]"),
    );
    let file = dir.path().join("passive.toml");
    std::fs::write(&file, text).unwrap();
    let gw = gateway(file.to_str().unwrap());
    gw.wait_log(
        "waiting for the slave to connect to",
        Duration::from_secs(5),
    );
    let mut line = RawLine::open(&socat.dev);
    let read = [3, 0, 7, 0, 1];
    let second = Duration::from_secs(1);
    assert_eq!(
        ask(&mut line, 5, &read, 2, second),
        rtu::encode(5, &[0x83, 0x0A])
    );

    let stop = Arc::new(AtomicBool::new(false));
    let first = connecting_slave(port, stop.clone());
    gw.wait_log("slave connected from", Duration::from_secs(5));
    assert_eq!(
        ask(&mut line, 5, &[6, 0, 7, 0, 99], 5, second),
        rtu::encode(5, &[6, 0, 7, 0, 99])
    );
    assert_eq!(
        ask(&mut line, 5, &read, 4, second),
        rtu::encode(5, &[3, 2, 0, 99])
    );

    // The slave restarts and connects again: the new connection is the route's.
    let stop2 = Arc::new(AtomicBool::new(false));
    let _second = connecting_slave(port, stop2.clone());
    gw.wait_log("slave connected again", Duration::from_secs(5));
    thread::sleep(Duration::from_millis(50));
    assert_eq!(
        ask(&mut line, 5, &read, 4, second),
        rtu::encode(5, &[3, 2, 0, 7]),
        "the new slave's registers"
    );
    stop.store(true, Ordering::Relaxed);
    stop2.store(true, Ordering::Relaxed);
    let _ = first.join();
}

/// `mbgate demo --master` on a terminal: an input set on the master shows in the
/// slave's outputs through the command the banner prints (run as printed), and one set
/// on the slave shows in the master's outputs on the console; Ctrl-C ends it cleanly.
#[test]
fn demo_master_mirrors_both_ways() {
    let (status, out) = Py::run("master_demo.py", &[env!("CARGO_BIN_EXE_mbgate")]);
    assert!(status.success(), "master_demo.py:\n{out}");
    let got: serde_json::Value = serde_json::from_str(&out).unwrap();
    let banner = got["banner"].as_str().unwrap();
    assert!(
        banner.contains("a simulated CIE-M10 master on /dev/pts/"),
        "{banner}"
    );
    assert!(got["command"]
        .as_str()
        .unwrap()
        .ends_with(" holding-registers 8"));
    assert_eq!(
        got["shown"].as_str().unwrap().lines().last(),
        Some("8: 1 (0x0001)"),
        "{got}"
    );
    assert_eq!(got["followed"], true);
    assert_eq!(got["exit"], 0);
}

/// An MBAP master pipelines three requests; the route allows two at once: the slave
/// (which never answers) gets two, the third only once the first two are given up,
/// and each of the three gets 0x0B with the master's own transaction id when its time
/// is up.
#[test]
fn pipelined_up_to_max_in_flight_each_answered_with_its_own_id() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let slave = Slave::start(Behaviour::Silent);
    let extra = "max_in_flight = 2\nresponse_timeout_ms = 300";
    let file = config(dir.path(), &socat.gw, "mbap", &[("", slave.port, extra)]);
    let gw = gateway(&file);
    gw.wait_log("connected to the slave", Duration::from_secs(5));
    let mut line = RawLine::open(&socat.dev);
    let mut burst = Vec::new();
    for tid in [0x0A01u16, 0x0A02, 0x0A03] {
        burst.extend_from_slice(Adu::build(tid, 7, &[3, 0, 1, 0, 1]).as_bytes());
    }
    let started = Instant::now();
    line.send(&burst);
    thread::sleep(Duration::from_millis(150));
    let seen: Vec<u16> = slave.requests().iter().map(Adu::tid).collect();
    assert_eq!(seen.len(), 2, "two at once: {seen:?}");
    assert_ne!(seen[0], seen[1], "mbgate's own ids, distinct");
    let replies = line.recv(27, Duration::from_secs(2));
    assert!(
        started.elapsed() >= Duration::from_millis(290),
        "{:?}",
        started.elapsed()
    );
    assert_eq!(
        hexs(&replies),
        "0A 01 00 00 00 03 07 83 0B 0A 02 00 00 00 03 07 83 0B 0A 03 00 00 00 03 07 83 0B"
    );
}

/// A Modbus/TCP slave that ignores the unit id and answers with 0 or 255 (many do;
/// TCP/IP Implementation Guide §4.4.2): its reply is matched by mbgate's transaction
/// id and the function code, and the serial master gets it with its own unit and
/// transaction id (before, it timed out: 0x0B).
#[test]
fn a_slave_answering_as_unit_0_or_255_is_matched() {
    for as_unit in [0u8, 0xFF] {
        let (_dir, socat, _slave, gw) = one_slave_doing("mbap", Behaviour::AnswerAs(as_unit));
        let mut line = RawLine::open(&socat.dev);
        line.send(Adu::build(0x0A0B, 1, &[3, 0, 4, 0, 2]).as_bytes());
        let reply = line.recv(13, Duration::from_secs(2));
        assert_eq!(
            hexs(&reply),
            "0A 0B 00 00 00 07 01 03 04 00 04 00 05",
            "answered as unit {as_unit}:\n{}",
            gw.log()
        );
    }
}

/// SIGTERM while a request is with a slow slave: the serial master still gets its
/// reply before mbgate exits (before, the line stopped at once and the master was
/// cut off), and mbgate exits 0.
#[test]
fn shutdown_answers_the_request_in_flight_first() {
    let (_dir, socat, _slave, mut gw) = one_slave_doing("rtu", Behaviour::AnswerAfter(300));
    let mut line = RawLine::open(&socat.dev);
    line.send(&rtu::encode(1, &[3, 0, 6, 0, 1]));
    gw.wait_log("slave tx", Duration::from_secs(2));
    gw.signal("TERM");
    let reply = line.recv(7, Duration::from_secs(3));
    assert_eq!(hexs(&reply), hexs(&rtu::encode(1, &[3, 2, 0, 6])));
    let status = gw.stop_with("TERM", Duration::from_secs(5));
    assert!(status.success(), "{status:?}:\n{}", gw.log());
    assert!(gw.log().contains("replies=1"), "{}", gw.log());
}

/// A slave that mirrors every request back: a read's mirror has the request's id and
/// unit but not a reply's shape, so the serial master never gets its own request as
/// the answer (before, it got `03 00 07 00 01` back as the reply); it gets 0x0B at the
/// route's timeout, and the frame is counted as bad.
#[test]
fn a_slave_mirroring_requests_never_answers_with_them() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let slave = Slave::start(Behaviour::Mirror);
    let extra = "response_timeout_ms = 300";
    let file = config(dir.path(), &socat.gw, "rtu", &[("", slave.port, extra)]);
    let mut gw = gateway(&file);
    gw.wait_log("connected to the slave", Duration::from_secs(5));
    let mut line = RawLine::open(&socat.dev);
    let read = [3, 0, 7, 0, 1];
    // Room for a mirrored request (8 bytes) as well as an exception (5).
    line.send(&rtu::encode(5, &read));
    let got = line.recv(8, Duration::from_secs(2));
    assert_eq!(
        hexs(&got),
        hexs(&rtu::encode(5, &[0x83, 0x0B])),
        "{}",
        gw.log()
    );
    assert_eq!(slave.requests().len(), 1);
    let status = gw.stop_with("TERM", Duration::from_secs(5));
    assert!(status.success(), "{status:?}");
    assert!(gw.log().contains("bad_replies=1"), "{}", gw.log());
}

/// A slave connecting from `ip` to `port` (a passive route) that answers as a register
/// map whose every register holds `mark`, until `stop`.
fn slave_from(ip: &str, port: u16, mark: u16, stop: Arc<AtomicBool>) -> thread::JoinHandle<()> {
    use socket2::{Domain, Socket, Type};
    let sock = Socket::new(Domain::IPV4, Type::STREAM, None).unwrap();
    sock.bind(
        &format!("{ip}:0")
            .parse::<std::net::SocketAddr>()
            .unwrap()
            .into(),
    )
    .unwrap();
    sock.connect(
        &format!("127.0.0.1:{port}")
            .parse::<std::net::SocketAddr>()
            .unwrap()
            .into(),
    )
    .unwrap();
    let mut s: TcpStream = sock.into();
    thread::spawn(move || {
        s.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
        let mut buf = bytes::BytesMut::new();
        let mut chunk = [0u8; 512];
        while !stop.load(Ordering::Relaxed) {
            match s.read(&mut chunk) {
                Ok(0) => return,
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(_) => continue,
            }
            while let Ok(Some(req)) = decode_strict(&mut buf) {
                let [hi, lo] = mark.to_be_bytes();
                let reply = Adu::build(req.tid(), req.unit(), &[3, 2, hi, lo]);
                if s.write_all(reply.as_bytes()).is_err() {
                    return;
                }
            }
        }
    })
}

/// A passive route with `allow`: a peer from outside the list neither becomes the
/// route's slave (its connection is closed unread, the serial master keeps getting
/// 0x0A) nor replaces the slave that is allowed (before, any peer that connected took
/// the route and answered the serial master's requests).
#[test]
fn a_passive_route_takes_only_allowed_slaves() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let port = free_port();
    let mut text = std::fs::read_to_string(config(dir.path(), &socat.gw, "rtu", &[])).unwrap();
    text = text.replace(
        "\n[log]",
        &format!(
            "\n[[line.route]]\nlisten = \"127.0.0.1:{port}\"\nallow = [\"127.0.0.2\"]\n\n[log]"
        ),
    );
    let file = dir.path().join("passive.toml");
    std::fs::write(&file, text).unwrap();
    let gw = gateway(file.to_str().unwrap());
    gw.wait_log(
        "waiting for the slave to connect to",
        Duration::from_secs(5),
    );
    let mut line = RawLine::open(&socat.dev);
    let read = [3, 0, 7, 0, 1];
    let second = Duration::from_secs(1);

    let stop = Arc::new(AtomicBool::new(false));
    let _intruder = slave_from("127.0.0.1", port, 666, stop.clone());
    gw.wait_log(
        "slave connection refused: 127.0.0.1",
        Duration::from_secs(5),
    );
    assert_eq!(
        ask(&mut line, 5, &read, 2, second),
        rtu::encode(5, &[0x83, 0x0A])
    );

    let _allowed = slave_from("127.0.0.2", port, 7, stop.clone());
    gw.wait_log("slave connected from 127.0.0.2", Duration::from_secs(5));
    assert_eq!(
        ask(&mut line, 5, &read, 4, second),
        rtu::encode(5, &[3, 2, 0, 7])
    );

    // The intruder again, while the allowed slave is connected: it replaces nothing.
    let _again = slave_from("127.0.0.1", port, 666, stop.clone());
    thread::sleep(Duration::from_millis(300));
    for _ in 0..3 {
        assert_eq!(
            ask(&mut line, 5, &read, 4, second),
            rtu::encode(5, &[3, 2, 0, 7])
        );
    }
    assert!(!gw.log().contains("slave connected again"), "{}", gw.log());
    assert_eq!(
        gw.log().matches("slave connection refused").count(),
        1,
        "said once a minute per source:\n{}",
        gw.log()
    );
    stop.store(true, Ordering::Relaxed);
}
