//! Replies that must never reach a master on an RTU line, attacked end to end with a
//! device that is not ours (tests/py/raw_device.py, os and termios only) on a socat
//! pty pair: a frame of another function or shape than the request's, a stalled
//! device's backlog, a late reply after a learned timeout fired
//! (docs/reliability.md "RTU and ASCII", 5 and 6; "Learned timeouts").

use crate::common;
use common::*;
use mbgate::frame::Adu;
use std::net::TcpStream;
use std::path::Path;
use std::thread;
use std::time::Duration;

/// A gateway for one RTU line on `gw`, its relay settings and unit tables added.
fn gateway(dir: &Path, gw: &Path, serial: &str, relay: &str, units: &str) -> Gateway {
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, framing = \"rtu\", baud_rate = 19200, flow_control = \"none\"{serial} }}\n\
         relay = {{ unit_backoff = false{relay} }}\n{units}\n\
         [[listen]]\naddress = \"127.0.0.1:0\"\n[log]\nlevel = \"debug\"\n",
        gw.display().to_string()
    );
    Gateway::launch_text(&text, dir, Launch::default())
}

/// The exception 0x0B answer to `req` (an MBAP request).
fn target_failed(req: &[u8]) -> Vec<u8> {
    let tid = u16::from_be_bytes([req[0], req[1]]);
    Adu::build(tid, req[6], &[req[7] | 0x80, 0x0B])
        .as_bytes()
        .to_vec()
}

/// A request with this PDU to unit 1.
fn request(tid: u16, pdu: &[u8]) -> Vec<u8> {
    Adu::build(tid, 1, pdu).as_bytes().to_vec()
}

/// A device that answers every request with one FC 03 frame (`01 03 02 00 2A`), and
/// one that answers with an FC 06 exception (`01 86 02`): each request whose answer
/// that frame is not gets 0x0B, at once (long before the 5 s timeout), on a pty and on
/// a line declared a wire; the one it answers gets it; each refusal counted.
#[test]
fn a_reply_of_another_function_or_shape_is_refused() {
    for kind in ["", ", port_kind = \"wire\""] {
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let dev = socat.dev.to_str().unwrap();
        // 20 ms: after the request has left a wire at 19 200 baud (4.2 ms).
        let fixed = ["--port", dev, "--fast", "0.02", "fixed"];
        let device = Py::start("raw_device.py", &[&fixed[..], &["0302002A"]].concat());
        let mut gw = gateway(dir.path(), &socat.gw, kind, ", retries = 0", "");
        let mut m = gw.connect();
        m.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
        let others: [&[u8]; 6] = [
            &[0x06, 0, 1, 0, 7],          // FC 06 write
            &[0x10, 0, 1, 0, 1, 2, 0, 7], // FC 16 write
            &[0x04, 0, 0, 0, 1],          // FC 04 read
            &[0x05, 0, 1, 0xFF, 0],       // FC 05 write
            &[0x03, 0, 0, 0, 2],          // FC 03, two registers
            &[0x01, 0, 0, 0, 8],          // FC 01 coils
        ];
        for (i, pdu) in others.iter().enumerate() {
            let req = request(i as u16 + 1, pdu);
            let start = std::time::Instant::now();
            let got = transact(&mut m, &req);
            assert_eq!(
                hexs(&got),
                hexs(&target_failed(&req)),
                "{kind}: the answer to {}",
                hexs(pdu)
            );
            // Not the 5 s timeout: refused when the frame came (a generous bound).
            assert!(start.elapsed() < Duration::from_secs(4), "{kind}");
        }
        let req = request(9, &[0x03, 0, 0, 0, 1]);
        assert_eq!(
            hexs(&transact(&mut m, &req)),
            hexs(&read_reply(9, 1, &[0x2A])),
            "{kind}: the read it answers"
        );
        let counters = gw.stop();
        assert_eq!(counters["bad_frames"], others.len() as u64, "{counters:?}");
        drop(device);

        // An FC 06 exception is no answer to an FC 03.
        let dir = tempdir();
        let socat = Socat::start(dir.path());
        let dev = socat.dev.to_str().unwrap();
        let fixed = ["--port", dev, "--fast", "0.02", "fixed"];
        let _device = Py::start("raw_device.py", &[&fixed[..], &["8602"]].concat());
        let mut gw = gateway(dir.path(), &socat.gw, kind, ", retries = 0", "");
        let mut m = gw.connect();
        let req = request(1, &[0x03, 0, 0, 0, 1]);
        assert_eq!(
            hexs(&transact(&mut m, &req)),
            hexs(&target_failed(&req)),
            "{kind}"
        );
        let req = request(2, &[0x06, 0, 0, 0, 1]);
        assert_eq!(
            hexs(&transact(&mut m, &req)),
            hexs(Adu::build(2, 1, &[0x86, 0x02]).as_bytes()),
            "{kind}: its own exception is an answer"
        );
        gw.stop();
    }
}

/// What masters got: right (their own answer), 0x0B, or wrong (kept to be shown).
#[derive(Debug, Default)]
struct Tally {
    right: u32,
    failed: u32,
    wrong: Vec<String>,
}

impl Tally {
    fn judge(&mut self, req: &[u8], got: &[u8], want: &[u8]) {
        if got == want {
            self.right += 1;
        } else if got == target_failed(req) {
            self.failed += 1;
        } else {
            self.wrong.push(format!(
                "{} got {}, want {}",
                hexs(req),
                hexs(got),
                hexs(want)
            ));
        }
    }

    /// Panics, listing them and the gateway's log, if any answer was wrong.
    fn assert_none_wrong(&self, gw: &Gateway) {
        assert!(
            self.wrong.is_empty(),
            "{} wrong: {:#?}\n{}",
            self.wrong.len(),
            self.wrong,
            gw.log()
        );
    }

    fn add(&mut self, other: Tally) {
        self.right += other.right;
        self.failed += other.failed;
        self.wrong.extend(other.wrong);
    }
}

/// `n` transactions by one master: reads of its own registers (raw_device.py gives
/// each its address plus 1000), and with `writes` an FC 16 write every third, each
/// answer judged against the one it should have.
fn master(gw: &Gateway, base: u16, n: u16, writes: bool) -> Tally {
    let mut s: TcpStream = gw.connect();
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut tally = Tally::default();
    for i in 0..n {
        let (tid, addr) = (i + 1, base + i % 7);
        if writes && i % 3 == 2 {
            let req = write_req(tid, 1, addr, &[i]);
            let want = Adu::build(tid, 1, &[0x10, (addr >> 8) as u8, addr as u8, 0, 1]);
            tally.judge(&req, &transact(&mut s, &req), want.as_bytes());
        } else {
            let req = read_req(tid, 1, addr, 1);
            let want = read_reply(tid, 1, &[addr + 1000]);
            tally.judge(&req, &transact(&mut s, &req), &want);
        }
    }
    tally
}

/// Two masters, one reading and one reading and writing, each in a thread.
fn two_masters(gw: &Gateway, n: u16) -> Tally {
    let mut tally = Tally::default();
    thread::scope(|s| {
        let a = s.spawn(|| master(gw, 0, n, false));
        let b = s.spawn(|| master(gw, 100, n, true));
        tally.add(a.join().unwrap());
        tally.add(b.join().unwrap());
    });
    tally
}

/// A device that stops reading for 3 s after its fifth answer (a hung firmware) while
/// two masters go on, then answers every request that waited for it, at once, in
/// order. `unit_backoff = false`, so every request meanwhile reaches the line and
/// times out (300 ms): the backlog is long. None of its answers is taken for a
/// request sent later: every answer is the request's own or 0x0B, and the backlog is
/// dropped (counted in dropped_bytes: late replies, stale bytes, a frame refused).
#[test]
fn a_stalled_devices_backlog_never_answers_new_requests() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--stall-after",
            "5",
            "--stall-for",
            "3",
        ],
    );
    let relay = ", response_timeout_ms = 300, retries = 0";
    let mut gw = gateway(dir.path(), &socat.gw, "", relay, "");
    let tally = two_masters(&gw, 30);
    let counters = gw.stop();
    eprintln!("{tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(tally.failed >= 3, "the stall timed requests out: {tally:?}");
    assert!(tally.right >= 20, "{tally:?}");
    assert!(
        counters["dropped_bytes"] > 0,
        "the backlog came and was dropped: {counters:?}"
    );
}

/// A unit whose timeout is learned (ceiling 300 ms) answers in 20 ms, but every 30th
/// request in 360 ms: after the learned timeout fires, that reply comes after the
/// ceiling and within the guard (100 ms) after it, where a fixed timeout at the
/// ceiling would have dropped it. It is never taken for the next request's answer.
#[test]
fn a_late_reply_after_a_learned_timeout_answers_nothing() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--fast",
            "0.02",
            "--slow-every",
            "30",
            "--slow",
            "0.36",
        ],
    );
    let units = "[[line.unit]]\nunits = 1\nresponse_timeout_ms = \"auto\"\n\
                 response_timeout_max_ms = 300\nretries = 0\n";
    let relay = ", response_timeout_ms = 300, timeout_guard_ms = 100";
    let mut gw = gateway(dir.path(), &socat.gw, "", relay, units);
    let tally = master(&gw, 0, 95, false);
    let counters = gw.stop();
    eprintln!("{tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(tally.right >= 60, "{tally:?}");
}

/// A device that stalls 2.5 s after its fifth answer while two masters go on (each
/// request meanwhile times out after the default 1 s and waits in the device), then
/// answers that backlog one frame every `pace_ms`, and what came meanwhile after it.
/// Every answer is the request's own or 0x0B, whatever the pace: a unit owes an answer
/// for each request that timed out until it has paid it or been quiet for its whole
/// response timeout after its last frame (docs/reliability.md "RTU and ASCII", 6).
fn backlog_drained_every(pace_ms: u64) {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let pace = format!("{}", pace_ms as f64 / 1000.0);
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--stall-after",
            "5",
            "--stall-for",
            "2.5",
            "--drain",
            &pace,
        ],
    );
    let mut gw = gateway(dir.path(), &socat.gw, "", ", retries = 0", "");
    let tally = two_masters(&gw, 16);
    let counters = gw.stop();
    eprintln!("drained every {pace_ms} ms: {tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(tally.failed >= 2, "the stall timed requests out: {tally:?}");
    assert!(tally.right >= 20, "{tally:?}");
    assert!(
        counters["late_replies"] >= 2,
        "the backlog came and was dropped: {counters:?}"
    );
}

#[test]
fn a_backlog_drained_every_40_ms_never_answers_new_requests() {
    backlog_drained_every(40);
}

#[test]
fn a_backlog_drained_every_90_ms_never_answers_new_requests() {
    backlog_drained_every(90);
}

#[test]
fn a_backlog_drained_every_120_ms_never_answers_new_requests() {
    backlog_drained_every(120);
}

#[test]
fn a_backlog_drained_every_250_ms_never_answers_new_requests() {
    backlog_drained_every(250);
}

#[test]
fn a_backlog_drained_every_500_ms_never_answers_new_requests() {
    backlog_drained_every(500);
}

/// `n` reads by pymodbus' `ModbusTcpClient` (tests/py/master.py), one register each
/// at `base` + 0..7 in turn, each answer judged: the register's address plus 1000
/// (raw_device.py's), or 0x0B.
fn pymodbus_master(gw: &Gateway, base: u16, n: u16) -> Tally {
    let steps: Vec<serde_json::Value> = (0..n)
        .map(|i| {
            serde_json::json!(["read_holding_registers", [base + i % 7], {"count": 1, "device_id": 1}])
        })
        .collect();
    let steps = serde_json::Value::Array(steps).to_string();
    let port = gw.addr.port().to_string();
    let (status, out) = Py::run("master.py", &["--port", &port, "--timeout", "10", &steps]);
    assert!(status.success(), "{out}");
    let got: Vec<serde_json::Value> = serde_json::from_str(out.trim()).expect("master.py's JSON");
    assert_eq!(got.len(), usize::from(n), "{out}");
    let mut tally = Tally::default();
    for (i, answer) in (0..n).zip(got) {
        let addr = base + i % 7;
        if answer == serde_json::json!({"registers": [addr + 1000]}) {
            tally.right += 1;
        } else if answer == serde_json::json!({"exception": 11}) {
            tally.failed += 1;
        } else {
            tally.wrong.push(format!("read of {addr}: {answer}"));
        }
    }
    tally
}

/// A device on a pty that answers every read 20 ms after it came, and every third
/// answer with one frame too many, a reply of the same shape for the address before,
/// 2 ms `before` or `after` its real one. pymodbus reads 30 registers in turn: every
/// answer is the read's own or 0x0B, never either frame handed to the wrong request:
/// a reply is taken only once the line has been quiet after it for the confirmation
/// quiet (here `silence_floor_ms = 200`, so the 2 ms gap stays inside it on a busy
/// machine), and a second frame within it refutes both (docs/reliability.md "RTU and
/// ASCII", 7).
fn one_frame_too_many(mode: &str) {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--fast",
            "0.02",
            "--extra-every",
            "3",
            "--extra",
            mode,
            "--extra-gap",
            "0.002",
        ],
    );
    let serial = ", silence_floor_ms = 200";
    let mut gw = gateway(dir.path(), &socat.gw, serial, ", retries = 0", "");
    let tally = pymodbus_master(&gw, 0, 30);
    let counters = gw.stop();
    eprintln!("extra frame {mode}: {tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(
        tally.failed >= 5,
        "the extra frames refuted replies: {tally:?}"
    );
    assert!(tally.right >= 15, "{tally:?}");
    assert!(counters["refuted_frames"] >= 5, "{counters:?}");
}

#[test]
fn an_extra_frame_before_the_reply_is_never_taken() {
    one_frame_too_many("before");
}

#[test]
fn an_extra_frame_after_the_reply_is_never_taken() {
    one_frame_too_many("after");
}

/// The extra frame later, 150 ms after the real reply, with the defaults of a pty:
/// the reply is taken once the line has been quiet for 10 ms, the master's next read
/// goes on the line at once, and the extra frame comes in its window, long before
/// the device (answering in 600 ms) could have answered it. Once the unit's fastest
/// reply is known (its first 8 taken, no extra frame among them), such a frame is
/// dropped (sooner than half its fastest reply), and the read gets its own answer
/// (docs/reliability.md "RTU and ASCII", 7).
#[test]
fn an_extra_frame_sooner_than_the_device_answers_never_answers_the_next_read() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--fast",
            "0.6",
            "--extra-every",
            "3",
            "--extra",
            "after",
            "--extra-gap",
            "0.15",
            "--extra-from",
            "9",
        ],
    );
    let relay = ", retries = 0, response_timeout_ms = 2000";
    let mut gw = gateway(dir.path(), &socat.gw, "", relay, "");
    let tally = master(&gw, 0, 17, false);
    let counters = gw.stop();
    eprintln!("{tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(tally.right >= 14, "{tally:?}");
}

/// A device that answers every request in 5 ms, and every seventh in 450 ms: 150 ms
/// after its 300 ms timeout, in the window of the next request, which goes 1 ms after
/// the timeout (`timeout_guard_ms = 1`, the least an RTU line takes). The device reads
/// that request and answers it after the late one; the late reply pays the answer its
/// unit owes, and the request gets its own: with next to no guard, not one wrong
/// value (docs/reliability.md "RTU and ASCII", 3 and 6).
#[test]
fn with_next_to_no_guard_a_late_reply_never_answers_the_next_request() {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let dev = socat.dev.to_str().unwrap();
    let _device = Py::start(
        "raw_device.py",
        &[
            "--port",
            dev,
            "registers",
            "--fast",
            "0.005",
            "--slow-every",
            "7",
            "--slow",
            "0.45",
        ],
    );
    let relay = ", response_timeout_ms = 300, timeout_guard_ms = 1, retries = 0";
    let mut gw = gateway(dir.path(), &socat.gw, "", relay, "");
    let tally = master(&gw, 0, 70, false);
    let counters = gw.stop();
    eprintln!("{tally:?} {counters:?}");
    tally.assert_none_wrong(&gw);
    assert!(tally.failed >= 5, "the slow answers timed out: {tally:?}");
    assert!(tally.right >= 50, "{tally:?}");
    assert!(counters["late_replies"] >= 5, "{counters:?}");
}
