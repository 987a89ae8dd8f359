//! No listener and no dial answers an answer (docs/security.md "Threat model"): a frame
//! whose function code has the high bit set (an exception), or with a reply's shape and
//! not a request's (FC 03 with a byte count and 2N data bytes), is dropped and counted
//! (`not_requests`), never answered, and said once a minute per listener and kind; the
//! connection stays and the requests after it are answered. Over Modbus/TCP, RTU over
//! TCP, Modbus/TCP Security (Python's ssl, that is OpenSSL, as the master) and a dial to
//! a server that sends back every byte it gets. The device is pymodbus' RTU server on a
//! socat pty (unit 1, holding register i = 1000 + i). The UDP listener's own hostile
//! peers are tests/e2e/udp_hostile.rs.

use crate::common;
use common::pki::Pki;
use common::*;
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

fn mbap(tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    mbgate::frame::Adu::build(tid, unit, pdu)
        .as_bytes()
        .to_vec()
}

/// Answers as a device or a gateway sends them: exceptions, and replies of a shape no
/// request has (a read's, a long write's, a report server id's).
fn answers(tid: u16) -> Vec<Vec<u8>> {
    vec![
        mbap(tid, 1, &[0x83, 0x02]),
        mbap(tid, 1, &[0x80, 0x01]),
        mbap(tid, 1, &[3, 2, 0, 0xFF]),
        mbap(tid, 1, &[4, 4, 0, 1, 0, 2]),
        mbap(tid, 1, &[0x10, 0, 8, 0, 1]),
        mbap(tid, 1, &[0x11, 3, 0x2A, 0xFF, 1]),
    ]
}

const SAID: &str = "came where a request belongs";

/// The gateway in front of pymodbus' RTU device, with the listeners and dials of
/// `tables`.
struct Rig {
    dir: tempfile::TempDir,
    _socat: Socat,
    _device: Py,
    gw: Proc,
    addrs: Vec<std::net::SocketAddr>,
}

fn rig(tables: &str, listeners: usize) -> Rig {
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let args = ["--port", socat.dev.to_str().unwrap(), "--framer", "rtu"];
    let device = Py::start("stock_server.py", &args);
    let text = format!(
        "[[line]]\nserial = {{ path = {:?}, framing = \"rtu\", flow_control = \"none\", baud_rate = 4000000 }}\n\
         relay = {{ response_timeout_ms = 5000 }}\n{tables}\n[log]\nlevel = \"debug\"\n",
        socat.gw.to_str().unwrap()
    );
    let (gw, addrs) = gateway_from_file(dir.path(), &text, listeners);
    Rig {
        dir,
        _socat: socat,
        _device: device,
        gw,
        addrs,
    }
}

/// The counters the gateway logs as it stops.
fn stop(gw: &mut Proc) -> std::collections::HashMap<String, u64> {
    assert!(gw.terminate(Duration::from_secs(10)).success());
    let log = gw.log();
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains("stopped") && l.contains("not_requests="))
        .unwrap_or_else(|| panic!("no counters:\n{log}"));
    line.split_whitespace()
        .filter_map(|t| {
            let (k, v) = t.rsplit_once('=')?;
            Some((k.rsplit('=').next()?.to_string(), v.parse().ok()?))
        })
        .collect()
}

/// A Modbus/TCP master that sends 24 answers, then a read: the first frame it gets is
/// the read's reply, and nothing else comes; its connection stays. Two lines in the
/// log: one for exceptions, one for replies.
#[test]
fn a_tcp_master_sending_answers_gets_none_and_keeps_its_connection() {
    let mut r = rig("[[listen]]\naddress = \"127.0.0.1:0\"\n", 1);
    let mut m = TcpStream::connect(r.addrs[0]).unwrap();
    m.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    for round in 0..4 {
        for a in answers(round) {
            m.write_all(&a).unwrap();
        }
    }
    assert_eq!(
        transact(&mut m, &read_req(9, 1, 5, 1)),
        read_reply(9, 1, &[1005])
    );
    m.set_read_timeout(Some(Duration::from_millis(500)))
        .unwrap();
    assert!(try_read_frame(&mut m).is_none(), "nothing more");
    m.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    assert_eq!(
        transact(&mut m, &read_req(10, 1, 6, 1)),
        read_reply(10, 1, &[1006])
    );
    let log = r.gw.log();
    assert_eq!(log.matches(SAID).count(), 2, "{log}");
    let c = stop(&mut r.gw);
    let got = (c["not_requests"], c["requests"], c["bad_requests"]);
    assert_eq!(got, (24, 2, 0), "{c:?}");
    assert_eq!(c["protocol_violations"], 0, "{c:?}");
}

/// An RTU-over-TCP master that sends an exception frame (CRC good): no answer; the
/// read after it is answered.
#[test]
fn an_rtu_over_tcp_master_sending_an_exception_gets_no_answer() {
    use mbgate::frame::rtu::encode;
    let mut r = rig(
        "[[listen]]\naddress = \"127.0.0.1:0\"\nframing = \"rtu\"\n",
        1,
    );
    let mut m = TcpStream::connect(r.addrs[0]).unwrap();
    m.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    m.write_all(&encode(1, &[0x83, 0x02])).unwrap();
    // A function of no known shape ends at the master's pause (50 ms).
    std::thread::sleep(Duration::from_millis(300));
    m.write_all(&encode(1, &[3, 0, 5, 0, 1])).unwrap();
    let want = encode(1, &[3, 2, 0x03, 0xED]);
    let mut got = vec![0u8; want.len()];
    m.read_exact(&mut got).unwrap();
    assert_eq!(got, want);
    let c = stop(&mut r.gw);
    assert_eq!((c["not_requests"], c["requests"]), (1, 1), "{c:?}");
}

/// A Modbus/TCP Security master (Python's ssl) that sends answers, then a read: the
/// read's reply is all it gets.
#[test]
fn a_tls_master_sending_answers_gets_none() {
    if !peer("openssl", "openssl") {
        return;
    }
    let dir = tempdir();
    let pki = Pki::new(&dir.path().join("pki"));
    pki.master("operator-1", "ca", Some("operator"), 30);
    let tables = format!(
        "[[listen]]\naddress = \"127.0.0.1:0\"\n{}\n\n[[role]]\nname = \"operator\"\n",
        pki.listen_tls("")
    );
    let mut r = rig(&tables, 1);
    let mut frames: Vec<String> = answers(1)
        .iter()
        .map(|a| hexs(a).replace(' ', ""))
        .collect();
    frames.push(hexs(&read_req(2, 1, 5, 1)).replace(' ', ""));
    let port = r.addrs[0].port().to_string();
    let (ca, cert, key) = (pki.pem("ca"), pki.pem("operator-1"), pki.key("operator-1"));
    let mut args = vec!["--port", &port, "--ca", &ca, "--cert", &cert, "--key", &key];
    args.extend(frames.iter().map(String::as_str));
    let (status, out) = Py::run("tls_frames.py", &args);
    assert!(status.success(), "{out}");
    let got: String = out.lines().take_while(|l| *l != "end").collect();
    let want = hexs(&read_reply(2, 1, &[1005]))
        .replace(' ', "")
        .to_lowercase();
    assert_eq!(got, want, "{out}");
    let c = stop(&mut r.gw);
    assert_eq!((c["not_requests"], c["requests"]), (6, 1), "{c:?}");
    drop(r.dir);
}

/// A dialed server that sends one read, then sends back every byte it gets for two
/// seconds: the reply it sends back is a reply's shape, dropped; it gets that one reply
/// and nothing more (before, 1.8 MB went back and forth in 3 s).
#[test]
fn a_dialed_server_that_echoes_every_byte_gets_one_reply() {
    let server = TcpListener::bind("127.0.0.1:0").unwrap();
    let dial = format!(
        "[[listen]]\naddress = \"127.0.0.1:0\"\n\
         [[dial]]\naddress = \"{}\"\nbackoff_min_ms = 100\nbackoff_max_ms = 400\n",
        server.local_addr().unwrap()
    );
    let mut r = rig(&dial, 1);
    let (mut s, _) = server.accept().unwrap();
    s.write_all(&read_req(1, 1, 5, 1)).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(100)))
        .unwrap();
    let (mut got, mut buf) = (Vec::new(), [0u8; 4096]);
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(2) {
        match s.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => {
                got.extend_from_slice(&buf[..n]);
                s.write_all(&buf[..n]).unwrap();
            }
            Err(_) => {}
        }
    }
    assert_eq!(got, read_reply(1, 1, &[1005]), "one reply, nothing after");
    let c = stop(&mut r.gw);
    assert_eq!((c["not_requests"], c["requests"]), (1, 1), "{c:?}");
}
