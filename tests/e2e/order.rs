//! Nothing reordered, nothing made up (docs/design.md §1 "Each master's order"): a
//! master's requests reach the device in the order it sent them however the queue
//! moves them (a shared read whose first master leaves, or whose first master's part
//! a full queue takes), and a read to unit 0 on a bus is answered with an exception,
//! never with bytes no device sent.
//!
//! Adversarial and exact: real masters on TCP sockets, a real device peer on a socat
//! pty (a scripted MBAP device holding its reply until the test lets it go, or
//! pymodbus' RTU server), each step taken only once the gateway's own metrics show
//! the previous one arrived, so the interleaving is the one written here whatever the
//! machine's load. The lines run at 4 Mbaud with a device that answers a millisecond
//! after the request, so the tests hold whether a pty is timed as a wire or not.

use crate::common;
use common::*;
use mbgate::frame::Adu;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

/// The register the device holds its answer to until the test opens the gate.
const GATED: u16 = 9;

/// A register device (register `a` reads as `a` until written) answering FC 03, 06 and
/// 16 a millisecond after each request, except a read of [`GATED`]: that one waits
/// for `gate` (the line stays busy meanwhile, as with a slow device).
fn gated_device(path: &std::path::Path, gate: Arc<AtomicBool>) -> RawDevice {
    let mut regs = Registers::default();
    RawDevice::scripted(
        path,
        Box::new(move |req: &Adu| {
            let pdu = req.pdu();
            if pdu[0] == 0x03 && u16::from_be_bytes([pdu[1], pdu[2]]) == GATED {
                while !gate.load(Ordering::Relaxed) {
                    thread::sleep(Duration::from_millis(2));
                }
            }
            let reply = regs.answer(req.unit(), pdu, true);
            let bytes = Adu::build(req.tid(), req.unit(), &reply)
                .as_bytes()
                .to_vec();
            vec![(Duration::from_millis(1), bytes)]
        }),
    )
}

struct Rig {
    gw: Gateway,
    dev: RawDevice,
    gate: Arc<AtomicBool>,
    metrics: SocketAddr,
    _socat: Socat,
    _dir: tempfile::TempDir,
}

/// An MBAP line on a pty to [`gated_device`], the metrics listener on, a response
/// timeout long enough for any machine, and `extra` relay keys.
fn rig(extra: &[&str]) -> Rig {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let gate = Arc::new(AtomicBool::new(false));
    let dev = gated_device(&socat.dev, gate.clone());
    let mut cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 20000")
        .metrics("listen = \"127.0.0.1:0\"");
    for line in extra {
        cfg = cfg.relay(line);
    }
    let gw = Gateway::start(&cfg, dir.path());
    gw.wait_log("serial port open", Duration::from_secs(5));
    let metrics = gw.proc.metrics_addr(Duration::from_secs(5));
    Rig {
        gw,
        dev,
        gate,
        metrics,
        _socat: socat,
        _dir: dir,
    }
}

impl Drop for Rig {
    /// The device's thread may be waiting at the gate (a test that failed early): let
    /// it go, so it can stop.
    fn drop(&mut self) {
        self.gate.store(true, Ordering::Relaxed);
    }
}

impl Rig {
    /// The line's gauge or counter `name` (one line: one sample).
    fn metric(&self, name: &str) -> u64 {
        let mut s = TcpStream::connect(self.metrics).expect("metrics listener");
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        write!(s, "GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n").unwrap();
        let mut all = String::new();
        s.read_to_string(&mut all).unwrap();
        let prefix = format!("{name}{{");
        let line = all
            .lines()
            .find(|l| l.starts_with(&prefix))
            .unwrap_or_else(|| panic!("no {name} in\n{all}"));
        let value = line.rsplit(' ').next().unwrap();
        value.parse::<f64>().unwrap() as u64
    }

    /// Waits until the relay has taken `n` requests in all.
    fn taken(&self, n: u64) {
        wait_for(
            &format!("{n} requests taken"),
            Duration::from_secs(10),
            || self.metric("mbgate_line_requests_total") >= n,
        );
    }

    /// Waits until `n` masters are attached to the line (a detach is done).
    fn masters(&self, n: u64) {
        wait_for(&format!("{n} masters"), Duration::from_secs(10), || {
            self.metric("mbgate_line_masters") == n
        });
    }

    /// A read of [`GATED`] from a master of its own: on the line until the gate opens.
    fn hold_the_line(&self) -> TcpStream {
        let mut c = self.gw.connect();
        c.write_all(&read_req(1, 1, GATED, 1)).unwrap();
        wait_for(
            "the gated read on the line",
            Duration::from_secs(10),
            || !self.dev.requests().is_empty(),
        );
        c
    }

    /// What the device received, as (function code, address) in order.
    fn on_the_line(&self) -> Vec<(u8, u16)> {
        let reqs = self.dev.requests();
        reqs.iter()
            .map(|r| (r.pdu()[0], u16::from_be_bytes([r.pdu()[1], r.pdu()[2]])))
            .collect()
    }
}

/// FC 16 of one register, answered with address and count.
fn write_reply(tid: u16, addr: u16) -> Vec<u8> {
    let [a0, a1] = addr.to_be_bytes();
    Adu::build(tid, 1, &[0x10, a0, a1, 0, 1])
        .as_bytes()
        .to_vec()
}

/// Masters A and B read register 5; B's read joins A's, still queued behind a read
/// that holds the line. B then writes register 5. A disconnects before the shared
/// read is sent (its connection reset). B sent its read before its write, so the read must reach the device
/// first and return the old value: the read keeps its place when A leaves, and is not
/// queued again behind B's write.
#[test]
fn a_shared_read_keeps_its_place_when_the_master_it_was_queued_for_leaves() {
    let r = rig(&[]);
    let mut holder = r.hold_the_line();
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    r.masters(3);
    a.write_all(&read_req(0x0A01, 1, 5, 1)).unwrap();
    r.taken(2);
    b.write_all(&read_req(0x0B01, 1, 5, 1)).unwrap();
    r.taken(3);
    b.write_all(&write_req(0x0B02, 1, 5, &[0x1234])).unwrap();
    r.taken(4);
    // Gone at once (a reset): a master that closes politely is detached only once
    // its replies are written.
    reset(a);
    r.masters(2);
    r.gate.store(true, Ordering::Relaxed);

    assert_eq!(read_frame(&mut holder), read_reply(1, 1, &[GATED]));
    assert_eq!(
        read_frame(&mut b),
        read_reply(0x0B01, 1, &[5]),
        "B's read, sent before its write, sees the value before the write:\n{}",
        r.gw.log()
    );
    assert_eq!(read_frame(&mut b), write_reply(0x0B02, 5));
    assert_eq!(
        transact(&mut b, &read_req(0x0B03, 1, 5, 1)),
        read_reply(0x0B03, 1, &[0x1234])
    );
    assert_eq!(
        r.on_the_line(),
        [(0x03, GATED), (0x03, 5), (0x10, 5), (0x03, 5)],
        "one shared read, then the write"
    );
}

/// The same through the full queue's 0x06: A queues three reads, the last one (of
/// register 5) joined by B's; B writes register 5; the queue is full, and D's request
/// takes the place of A's newest, its part of the shared read. The read stays where it
/// was, ahead of B's write; A gets 0x06 for it, and everything else its own answer.
#[test]
fn a_shared_read_keeps_its_place_when_a_full_queue_takes_its_first_masters_part() {
    let r = rig(&["queue_depth = 5", "max_pending_per_connection = 5"]);
    let mut holder = r.hold_the_line();
    let mut a = r.gw.connect();
    let mut b = r.gw.connect();
    let mut d = r.gw.connect();
    r.masters(4);
    for (i, addr) in [7u16, 8, 5].into_iter().enumerate() {
        a.write_all(&read_req(0x0A01 + i as u16, 1, addr, 1))
            .unwrap();
        r.taken(2 + i as u64);
    }
    b.write_all(&read_req(0x0B01, 1, 5, 1)).unwrap();
    r.taken(5);
    b.write_all(&write_req(0x0B02, 1, 5, &[0x1234])).unwrap();
    r.taken(6);
    d.write_all(&read_req(0x0D01, 1, 6, 1)).unwrap();
    r.taken(7);
    r.gate.store(true, Ordering::Relaxed);

    assert_eq!(read_frame(&mut holder), read_reply(1, 1, &[GATED]));
    assert_eq!(
        read_frame(&mut b),
        read_reply(0x0B01, 1, &[5]),
        "B's read, sent before its write, sees the value before the write:\n{}",
        r.gw.log()
    );
    assert_eq!(read_frame(&mut b), write_reply(0x0B02, 5));
    assert_eq!(read_frame(&mut a), read_reply(0x0A01, 1, &[7]));
    assert_eq!(read_frame(&mut a), read_reply(0x0A02, 1, &[8]));
    assert_eq!(
        read_frame(&mut a),
        Adu::exception(0x0A03, 1, 0x03, 0x06).as_bytes(),
        "A's newest made room"
    );
    assert_eq!(read_frame(&mut d), read_reply(0x0D01, 1, &[6]));
    let line = r.on_the_line();
    let read5 = line.iter().position(|&x| x == (0x03, 5)).unwrap();
    let write5 = line.iter().position(|&x| x == (0x10, 5)).unwrap();
    assert!(read5 < write5, "{line:?}");
    assert_eq!(line.len(), 6, "one shared read of register 5: {line:?}");
}

/// pymodbus' RTU server (unit 1, taking broadcasts) behind an RTU line, the broadcast
/// answer `echo`.
struct RtuBench {
    gw: Gateway,
    _device: Py,
    _socat: Socat,
    _dir: tempfile::TempDir,
}

fn rtu_bench(broadcast_reply: &str) -> RtuBench {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let device = Py::start(
        "stock_server.py",
        &[
            "--port",
            dev,
            "--framer",
            "rtu",
            "--broadcast",
            "--baud",
            "4000000",
        ],
    );
    let cfg = Cfg::new(&socat.gw)
        .serial("framing = \"rtu\"")
        .serial("flow_control = \"none\"")
        .serial("baud_rate = 4000000")
        .relay(&format!("broadcast_reply = {broadcast_reply:?}"))
        // pymodbus, a Python program on a machine that may be busy, gets the time a
        // slow device would to act on a broadcast before the next request (Modbus
        // over Serial Line V1.02 §2.4.1: the turnaround delay, typically 100 to 200 ms).
        .relay("broadcast_delay_ms = 200")
        .log("traffic = true");
    let gw = Gateway::start(&cfg, dir.path());
    gw.wait_log("serial port open", Duration::from_secs(5));
    RtuBench {
        gw,
        _device: device,
        _socat: socat,
        _dir: dir,
    }
}

/// The RTU frames the gateway wrote to the line, from its traffic log.
fn written(log: &str) -> Vec<String> {
    log.lines()
        .filter_map(|l| {
            l.split(" dir=\"gw->serial\"")
                .next()
                .filter(|_| l.contains("gw->serial"))
        })
        .filter_map(|l| l.split("mbgate::traffic: ").nth(1))
        .map(str::to_owned)
        .collect()
}

/// A read (FC 01) to unit 0 on an RTU line: a broadcast cannot carry a read (Modbus
/// over Serial Line V1.02 §2.1), so no device would answer it. With `broadcast_reply =
/// "echo"` the gateway used to answer it with its own request bytes, which pymodbus
/// took for 24 coils. Now: exception 0x01 from the gateway, nothing on the line, and
/// counted; a write to unit 0 is still a broadcast the device acts on.
#[test]
fn a_read_to_unit_0_on_an_rtu_line_is_refused_and_never_answered_with_made_up_data() {
    let b = rtu_bench("echo");
    let port = b.gw.addr.port().to_string();
    let steps = r#"[["read_coils", [0], {"count": 24, "device_id": 0}],
                    ["read_holding_registers", [0], {"count": 2, "device_id": 0}],
                    ["write_register", [30, 4321], {"device_id": 0}],
                    ["read_holding_registers", [30], {"count": 1, "device_id": 1}]]"#;
    let (status, out) = Py::run("master.py", &["--port", &port, steps]);
    assert!(status.success(), "{out}");
    assert_eq!(
        out.trim(),
        r#"[{"exception": 1}, {"exception": 1}, {"registers": [4321], "address": 30, "count": 0}, {"registers": [4321]}]"#,
        "{}",
        b.gw.log()
    );
    // A raw master: the exact exception, for FC 03 and FC 17 (which reads too).
    let mut m = b.gw.connect();
    let read = Adu::build(0x4401, 0, &[0x03, 0, 0, 0, 1]);
    assert_eq!(
        transact(&mut m, read.as_bytes()),
        hex("4401 0000 0003 00 83 01")
    );
    let rw = Adu::build(0x4402, 0, &[0x17, 0, 0, 0, 1, 0, 9, 0, 1, 2, 0, 7]);
    assert_eq!(
        transact(&mut m, rw.as_bytes()),
        hex("4402 0000 0003 00 97 01")
    );
    let mut gw = b.gw;
    let log = gw.log();
    let to_unit_0: Vec<String> = written(&log)
        .into_iter()
        .filter(|f| f.starts_with("00 "))
        .collect();
    assert_eq!(
        to_unit_0,
        ["00 06 00 1E 10 E1 25 95"],
        "only the write:\n{log}"
    );
    let counters = gw.stop();
    assert_eq!(counters["broadcasts"], 1, "{counters:?}");
    assert_eq!(counters["broadcasts_refused"], 4, "{counters:?}");
}

/// With `broadcast_reply = "none"` the read to unit 0 was put on the line and the
/// master got nothing, until its own timeout: now the same exception at once.
#[test]
fn a_read_to_unit_0_gets_the_exception_with_broadcast_reply_none_too() {
    let b = rtu_bench("none");
    let mut m = b.gw.connect();
    m.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let read = Adu::build(0x4501, 0, &[0x04, 0, 0, 0, 2]);
    assert_eq!(
        transact(&mut m, read.as_bytes()),
        hex("4501 0000 0003 00 84 01")
    );
    let log = b.gw.log();
    assert!(
        !written(&log).iter().any(|f| f.starts_with("00 ")),
        "nothing to unit 0 on the line:\n{log}"
    );
}

/// An RTU-over-TCP master (a `[[listen]]` with `framing = "rtu"`): unit 0 is a
/// broadcast in its framing, so it awaits no answer and would take one for the answer
/// to its next request. Nothing comes back for unit 0, write or read (the read never
/// reaches the line), and its next request gets its own answer.
#[test]
fn an_rtu_over_tcp_master_gets_nothing_back_for_unit_0() {
    use mbgate::frame::rtu;
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let device = RawRtuDevice::start_at(&socat.dev, 4_000_000, rtu_register_device(&[1]));
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, framing = \"rtu\", baud_rate = 4000000, flow_control = \"none\" }}\n\
         relay = {{ broadcast_reply = \"echo\", broadcast_delay_ms = 5 }}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n[log]\nlevel = \"debug\"\n",
        socat.gw.display().to_string()
    );
    let mut gw = Gateway::launch_text(&text, dir.path(), Launch::default());
    gw.wait_log("serial port open", Duration::from_secs(5));
    let mut m = gw.connect();
    m.write_all(&rtu::encode(0, &[0x06, 0, 12, 0, 77])).unwrap();
    wait_for("the broadcast on the line", Duration::from_secs(5), || {
        !device.requests().is_empty()
    });
    m.write_all(&rtu::encode(0, &[0x03, 0, 12, 0, 1])).unwrap();
    m.write_all(&rtu::encode(1, &[0x03, 0, 12, 0, 1])).unwrap();
    // (This device takes no broadcast: register 12 still reads 12.)
    let want = rtu::encode(1, &[0x03, 2, 0, 12]);
    let mut got = vec![0u8; want.len()];
    m.read_exact(&mut got).unwrap();
    assert_eq!(hexs(&got), hexs(&want), "its own answer, nothing before it");
    assert_eq!(
        device.requests(),
        [
            rtu::encode(0, &[0x06, 0, 12, 0, 77]),
            rtu::encode(1, &[0x03, 0, 12, 0, 1])
        ],
        "the read to unit 0 never went on the line"
    );
    m.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let mut more = [0u8; 1];
    assert!(m.read(&mut more).is_err(), "nothing else: {more:?}");
    let counters = gw.stop();
    assert_eq!(counters["broadcasts_refused"], 1, "{counters:?}");
}
