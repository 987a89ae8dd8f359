//! Replies that must never reach a master on an RTU line, attacked end to end with a
//! device that is not ours (tests/py/raw_device.py, os and termios only) on a socat
//! pty pair: a frame of another function or shape than the request's, a stalled
//! device's backlog, a late reply after a learned timeout fired
//! (docs/reliability.md "RTU and ASCII", 5 and 6; "Learned timeouts").

mod common;
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
